"""A run's visual report: ``report.html`` (self-contained) and ``report.md`` (+ PNGs).

    neural-brdf report runs/quickstart                        # into the run directory
    neural-brdf report runs/quickstart -o docs/sample_report  # elsewhere

Training writes it at the end of every run (:func:`neural_brdf.pipeline.run`).  It reads
the run directory (``config.yaml``, ``metrics.json``, ``log.csv``, ``model.onnx``) and
holds: a summary, the physics checks with their verdicts and the furnace (albedo)
curve, the accuracy against the target with the BRDF Explorer style figures of
:mod:`neural_brdf.viewer.plots`, Mitsuba renders when Mitsuba is installed, the training
curve and times, and the resolved config.

The reference is the config's target (``data.build_target``).  When a measured-data
target cannot be built here, the report says so and plots the model alone.  An images
fit (``target.images``) has no reference: its report holds the "Images fit" section of
:mod:`neural_brdf.viewer.report.images` (the views, the fit's losses, the coverage and
``coverage.png``) in place of the accuracy, and plots the model alone.

``report.html`` embeds every image as a base64 PNG data URI and needs no script, so
the one file can be mailed or archived; ``report.md`` links the same PNGs, written
beside it as ``report-*.png``.  Both come from one list of blocks, so they always hold
the same content.  When the GLSL code generator translates the model, the interactive
viewer (:mod:`neural_brdf.viewer.page`, a page with script) is written beside them as
``viewer.html`` and carried inside report.html as a download link (a data URI), so the
report itself stays script-free.  Every file is written atomically (temp file + rename).
"""

from __future__ import annotations

from neural_brdf.viewer.report.blocks import (
    CSS,
    Attachment,
    Block,
    Code,
    Heading,
    Image,
    Table,
    Text,
    Verdict,
    image_name,
    to_html,
    to_markdown,
)
from neural_brdf.viewer.report.run import (
    RENDER_RESOLUTION,
    RENDER_SPP,
    RUN_FILES,
    VIEWER_FILE,
    Run,
    load_run,
    reference_of,
)
from neural_brdf.viewer.report.write import write_report

__all__ = [
    "Attachment",
    "Block",
    "CSS",
    "Code",
    "Heading",
    "Image",
    "Table",
    "Text",
    "Verdict",
    "image_name",
    "to_html",
    "to_markdown",
    "RENDER_RESOLUTION",
    "RENDER_SPP",
    "RUN_FILES",
    "Run",
    "VIEWER_FILE",
    "load_run",
    "reference_of",
    "write_report",
]
