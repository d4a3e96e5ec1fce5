"""Writing the report beside a run: report.html, report.md, the PNGs and viewer.html."""

from __future__ import annotations

import tempfile
from pathlib import Path

from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write
from neural_brdf.viewer.report.blocks import Attachment, Image, image_name, to_html, to_markdown
from neural_brdf.viewer.report.run import load_run
from neural_brdf.viewer.report.sections import _blocks

# ------------------------------------------------------------------ writing


def write_report(run_dir, out_dir=None, *, render: bool = True) -> dict[str, Path]:
    """Write report.html, report.md and its PNGs for ``run_dir`` into ``out_dir`` (default:
    the run directory).  Returns {"html": path, "md": path, <figure key>: png path}.
    ``render=False`` skips the Mitsuba render (the report says so)."""
    run = load_run(run_dir)
    out_dir = Path(out_dir) if out_dir is not None else run.dir
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{out_dir}: cannot create the output directory ({e.strerror})") from None
    try:  # before the render's minute: a folder this process cannot write (read-only)
        with tempfile.NamedTemporaryFile(dir=out_dir):  # as atomic_write creates its files
            pass
    except OSError as e:
        raise InputError(f"{out_dir / 'report.html'}: cannot write ({e.strerror})") from None
    blocks = _blocks(run, render)
    paths = {}
    for b in blocks:
        if isinstance(b, Image):
            paths[b.key] = out_dir / image_name(b.key)
            atomic_write(paths[b.key], b.png)
        elif isinstance(b, Attachment):
            paths[b.name] = out_dir / b.name
            atomic_write(paths[b.name], b.data)
    paths["md"] = out_dir / "report.md"
    atomic_write(paths["md"], to_markdown(blocks).encode("utf-8"))
    paths["html"] = out_dir / "report.html"
    atomic_write(paths["html"], to_html(blocks).encode("utf-8"))
    return paths
