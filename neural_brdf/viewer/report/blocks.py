"""The report as a list of blocks (headings, text, tables, images, code, attachments)
and its two renderings, one self-contained HTML page and Markdown with PNGs."""

from __future__ import annotations

import base64
import html
import re
import struct
from dataclasses import dataclass

from neural_brdf import runfolder


# ------------------------------------------------------------------ document blocks
@dataclass
class Verdict:
    passed: bool


@dataclass
class Heading:
    text: str
    level: int = 2


@dataclass
class Text:
    text: str
    note: bool = False  # highlighted (a missing reference, no Mitsuba, ...)


@dataclass
class Table:
    header: list[str]
    rows: list[list]  # cells: str or Verdict


@dataclass
class Image:
    key: str  # file name report-<key>.png
    title: str
    caption: str
    png: bytes
    zoom: int = 1  # shown this many times its size in HTML (small renders)

    @property
    def width(self) -> int:
        return struct.unpack(">I", self.png[16:20])[0]  # PNG IHDR width


@dataclass
class Code:
    text: str
    lang: str = ""


@dataclass
class Attachment:
    """A file carried by the report: written beside it, and inside report.html as a
    download link (a data URI, so the page stays one file without script)."""

    name: str
    text: str  # the link text
    data: bytes
    mime: str = "text/html"


Block = Verdict | Heading | Text | Table | Image | Code | Attachment  # a report's parts


# ------------------------------------------------------------------ HTML and Markdown
CSS = """
body { font: 15px/1.45 system-ui, sans-serif; color: #222; background: #fff; margin: 0; }
main { max-width: 1100px; margin: 0 auto; padding: 24px; }
h1 { font-size: 26px; margin: 0 0 16px; } h2 { margin-top: 36px; border-bottom: 1px solid #ddd; }
.table { overflow-x: auto; max-width: 100%; }
table { border-collapse: collapse; margin: 12px 0; }
td, th { border: 1px solid #ddd; padding: 4px 10px; text-align: left; }
.ok, .fail, td.nw { white-space: nowrap; }
th { background: #f3f3f3; }
.ok { color: #fff; background: #2e7d32; padding: 1px 8px; border-radius: 3px; }
.fail { color: #fff; background: #c62828; padding: 1px 8px; border-radius: 3px; }
.note { background: #fff6d6; border-left: 4px solid #e0b000; padding: 8px 12px; }
figure { margin: 20px 0; } figcaption { color: #555; font-size: 14px; }
img { max-width: 100%; height: auto; display: block; }
pre { background: #f6f6f6; padding: 12px; overflow-x: auto; font-size: 13px; }
@media (max-width: 600px) { main { padding: 12px; } }
"""
VIEWPORT = '<meta name="viewport" content="width=device-width, initial-scale=1">'
# a cell that is a number and its unit ("0.18 %", "4.5 s", "31.2 dB") or a limit
# ("<= 1e-06") does not wrap (class nw): a narrow column would break it apart
_UNIT = re.compile(r"(<=|>=) [-+]?[\d.]+(e[-+]?\d+)?|[-+]?[\d.]+(e[-+]?\d+)? (%|s|dB|ms)")


def _cell_html(c) -> str:
    if isinstance(c, Verdict):
        return '<span class="ok">ok</span>' if c.passed else '<span class="fail">FAIL</span>'
    return html.escape(str(c))


def _td(c) -> str:
    keep = not isinstance(c, Verdict) and _UNIT.fullmatch(str(c))
    return ('<td class="nw">' if keep else "<td>") + _cell_html(c) + "</td>"


def to_html(blocks: list) -> str:
    title = next((b.text for b in blocks if isinstance(b, Heading)), "neural-brdf report")
    out = [
        "<!doctype html>",
        f'<html lang="en"><head><meta charset="utf-8">{VIEWPORT}',
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body><main>",
    ]
    for b in blocks:
        if isinstance(b, Heading):
            out.append(f"<h{b.level}>{html.escape(b.text)}</h{b.level}>")
        elif isinstance(b, Text):
            cls = ' class="note"' if b.note else ""
            out.append(f"<p{cls}>{html.escape(b.text)}</p>")
        elif isinstance(b, Table):
            head = "".join(f"<th>{html.escape(h)}</th>" for h in b.header)
            # in a box that scrolls sideways: a wide table does not widen a phone's page
            out.append(
                f'<div class="table"><table><tr>{head}</tr>'
                if any(b.header)
                else '<div class="table"><table>'
            )
            out += ["<tr>" + "".join(_td(c) for c in r) + "</tr>" for r in b.rows]
            out.append("</table></div>")
        elif isinstance(b, Image):
            data_uri = "data:image/png;base64," + base64.b64encode(b.png).decode("ascii")
            out.append(
                f'<figure><img src="{data_uri}" alt="{html.escape(b.title)}" '
                f'width="{b.zoom * b.width}">'
                f"<figcaption><b>{html.escape(b.title)}.</b> "
                f"{html.escape(b.caption)}</figcaption></figure>"
            )
        elif isinstance(b, Code):
            out.append(f"<pre><code>{html.escape(b.text)}</code></pre>")
        elif isinstance(b, Attachment):
            uri = f"data:{b.mime};base64," + base64.b64encode(b.data).decode("ascii")
            out.append(
                f'<p><a download="{html.escape(b.name)}" href="{uri}">{html.escape(b.text)}</a></p>'
            )
    out.append("</main></body></html>")
    return "\n".join(out) + "\n"


def _cell_md(c) -> str:
    if isinstance(c, Verdict):
        return "**ok**" if c.passed else "**FAIL**"
    return str(c).replace("|", "\\|")


def image_name(key: str) -> str:
    """report-<key>.png, for a key registered in :data:`runfolder.REPORT_IMAGES` (what
    ``--overwrite`` removes as the run's own)."""
    if key not in runfolder.REPORT_IMAGES:
        raise ValueError(f"report image {key!r}: add it to runfolder.REPORT_IMAGES")
    return f"report-{key}.png"


def to_markdown(blocks: list) -> str:
    out = []
    for b in blocks:
        if isinstance(b, Heading):
            out.append("#" * b.level + " " + b.text)
        elif isinstance(b, Text):
            out.append(f"> **Note:** {b.text}" if b.note else b.text)
        elif isinstance(b, Table):
            width = len(b.header)
            out.append("| " + " | ".join(b.header) + " |")
            out.append("|" + "---|" * width)
            out += ["| " + " | ".join(_cell_md(c) for c in r) + " |" for r in b.rows]
        elif isinstance(b, Image):
            out.append(f"![{b.title}]({image_name(b.key)})\n\n*{b.title}.* {b.caption}")
        elif isinstance(b, Code):
            out.append(f"```{b.lang}\n{b.text.rstrip()}\n```")
        elif isinstance(b, Attachment):
            out.append(f"[{b.text}]({b.name})")
        out.append("")
    return "\n".join(out)
