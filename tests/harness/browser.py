"""Look at a report the way a person does: in headless Chromium (Debian's ``chromium``).

    python -m harness.browser runs/quickstart/report.html screenshot.png

:func:`inspect` loads the page and reports what the browser made of it: every
``<img>`` with its decoded size (``naturalWidth`` is 0 for a broken image), and the
page height.  It works on a copy of the page with a small probe script added, which
writes its findings into the DOM once the page has loaded; ``--dump-dom`` prints that
DOM.  The report itself holds no script.  :func:`screenshot` captures the whole page,
with the window as tall as the page.

The flags keep Chromium quiet and offline: no sandbox (it runs as root in CI), no GPU,
no first-run, background networking, component updates or sync, and a throw-away
profile.  ``$CHROMIUM`` overrides the binary.
"""

from __future__ import annotations

import html
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from neural_brdf.fileio import atomic_path

CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--force-device-scale-factor=1",
)
WIDTH = 1200  # window width in CSS pixels
MAX_HEIGHT = 16384  # screenshots stop here (Chromium's texture size limit)
TIMEOUT = 120  # seconds per Chromium run
PROBE_ID = "neural-brdf-probe"
PROBE = f"""<script>
window.addEventListener("load", () => {{
  const images = [...document.images].map(i => ({{alt: i.alt, complete: i.complete,
    width: i.naturalWidth, height: i.naturalHeight}}));
  const out = document.createElement("pre");
  out.id = "{PROBE_ID}";
  out.textContent = JSON.stringify({{images: images,
    height: document.documentElement.scrollHeight, text: document.body.innerText.length}});
  document.body.appendChild(out);
}});
</script>"""


class BrowserError(RuntimeError):
    """Chromium is missing, failed, or the page could not be probed."""


def _chromium(args: list[str]) -> str:
    if not Path(CHROMIUM).is_file():
        raise BrowserError(f"{CHROMIUM}: not found; apt-get install chromium (or set $CHROMIUM)")
    with tempfile.TemporaryDirectory(prefix="nbrdf-chromium-") as profile:
        proc = subprocess.run(
            [CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args],
            capture_output=True,
            text=True,
            timeout=TIMEOUT,
        )
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or ["no output"]
        raise BrowserError(f"chromium exited with {proc.returncode}: {tail[0]}")
    return proc.stdout


def inspect(html_path) -> dict:
    """{"images": [{alt, complete, width, height}], "height": page px, "text": chars}
    as Chromium sees ``html_path`` after the load event."""
    page = Path(html_path).read_text(encoding="utf-8")
    if "</body>" not in page:
        raise BrowserError(f"{html_path}: no </body> to attach the probe to")
    probed = page.replace("</body>", PROBE + "</body>", 1)
    with tempfile.TemporaryDirectory(prefix="nbrdf-probe-") as tmp:
        copy = Path(tmp) / "page.html"
        copy.write_text(probed, encoding="utf-8")
        dom = _chromium(["--dump-dom", copy.as_uri()])
    found = re.search(rf'<pre id="{PROBE_ID}">(.*?)</pre>', dom, re.S)
    if found is None:
        raise BrowserError(f"{html_path}: the probe did not run (page never loaded?)")
    return json.loads(html.unescape(found.group(1)))


def screenshot(html_path, png_path, *, width: int = WIDTH) -> dict:
    """Capture the whole page into ``png_path``; returns :func:`inspect`'s findings."""
    seen = inspect(html_path)
    height = max(200, min(int(seen["height"]), MAX_HEIGHT))
    png_path = Path(png_path).resolve()
    with atomic_path(png_path, suffix=".png", parents=True) as tmp:  # chromium writes a temp file
        _chromium(
            [
                f"--screenshot={tmp}",
                f"--window-size={width},{height}",
                Path(html_path).resolve().as_uri(),
            ]
        )
        if os.path.getsize(tmp) == 0:
            raise BrowserError(f"{png_path}: chromium wrote no screenshot")
    return seen


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m harness.browser REPORT.html SCREENSHOT.png")
    info = screenshot(sys.argv[1], sys.argv[2])
    broken = [i["alt"] for i in info["images"] if not i["width"]]
    print(
        f"wrote {sys.argv[2]}: page {info['height']} px, {len(info['images'])} images"
        + (f", BROKEN: {broken}" if broken else "")
    )
    sys.exit(1 if broken else 0)
