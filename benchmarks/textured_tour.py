"""The README tour's textured config, with and without the projected field (issue 30,
``texture.project``; the development teachers chose, the tour's own teacher reports).

    python benchmarks/textured_tour.py              # development: about 8 minutes on 2 cores
    python benchmarks/textured_tour.py --set test   # the choice, on held-out teachers
    python benchmarks/textured_tour.py --quick      # tiny budgets: the machinery only

``python -m neural_brdf.measured.procedural DIR`` writes a procedural teacher and the
config the README's tour trains (:data:`neural_brdf.measured.procedural.CONFIG`: a 32^2
field, 1500 steps).  This runs that config as a user does (``pipeline.run``: train,
export, validate) on each teacher of :data:`KINDS`, once per value of ``texture.project``
in :data:`PROJECT` (development) or with the value the config now holds (test), and
scores each ``model.onnx`` by onnxruntime on the pairs ``textured.py`` scores a file on
(two draws of :data:`PAIRS`, uv uniform: between texel centres); reciprocity and the
largest albedo are the run's own checks (``metrics.json``), the time the whole run's.

The teachers: the development set is ``write_teacher``'s seed 1 (``textured.SEEDS``); the
test set is its seed 0, **the teacher the tour itself writes**, so nothing is chosen on
it.  Nothing asserts.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import dev_test_args, write_json  # noqa: E402
from textured_project import PAIRS, SEEDS, header, pairs_entry, score  # noqa: E402

KINDS = ("roughplastic", "principled")  # the tour's default kind first
PROJECT = (None, 128, 256)  # texture.project on the development teachers
# the pairs: textured_project.py's (PAIRS per draw, its SEEDS of each set)


def tour_config(folder: Path, steps: int) -> str:
    """The config ``python -m neural_brdf.measured.procedural`` writes into ``folder``."""
    from neural_brdf.measured.procedural import CONFIG

    return CONFIG.format(config=folder / "textured.yaml", name="tour", steps=steps)


def main(argv: list[str] | None = None) -> int:
    args, out_path = dev_test_args(argv, __doc__, "textured_tour")
    import torch

    torch.set_num_threads(2)
    import textured as bench
    import yaml

    from neural_brdf import config as cfgmod
    from neural_brdf import pipeline
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    steps, size, pairs_n = 1500, 512, PAIRS
    if args.quick:
        steps, size, pairs_n = 20, 32, 4096
    # the test set: the config as the tour writes it, whatever texture.project it holds
    values: tuple = PROJECT if args.which == "dev" else ("tour",)
    load_before = [round(x, 2) for x in os.getloadavg()]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind in KINDS[:1] if args.quick else KINDS:
            folder = Path(tmp) / kind
            xml = write_teacher(folder, kind, size=size, seed=bench.SEEDS[args.which])
            (folder / "textured.yaml").write_text(tour_config(folder, steps))
            tour = yaml.safe_load((folder / "textured.yaml").read_text())
            teacher = TexturedMitsubaTarget(str(xml))
            pairs = [bench.validation_pairs(teacher, pairs_n, k) for k in SEEDS[args.which]]
            for value in values[:2] if args.quick else values:
                over = [] if value == "tour" else [f"texture.project={json.dumps(value)}"]
                cfg = cfgmod.load(folder / "textured.yaml", over)
                run = folder / f"run_{value}"
                t0 = time.perf_counter()
                metrics = pipeline.run(cfg, run, overwrite=True)
                seconds = time.perf_counter() - t0
                checks = metrics["checks"]
                row = {
                    "teacher": kind,
                    "project": cfg.texture.project,
                    "project_pairs": cfg.texture.project_pairs,
                    "project_ridge": cfg.texture.project_ridge,
                    "run_seconds": seconds,
                    "projection_seconds": (metrics["training"].get("projection") or {}).get(
                        "seconds"
                    ),
                    "file_bytes": (run / "model.onnx").stat().st_size,
                    "reciprocity": checks["reciprocity"]["value"],
                    "max_albedo": checks["max_albedo"]["value"],
                    "max_albedo_passed": checks["max_albedo"]["passed"],
                    **score(bench.OnnxFile(run / "model.onnx"), pairs),
                }
                rows.append(row)
                print(
                    f"{kind} project {cfg.texture.project}: {row['rel_rmse']:.2%} "
                    f"in {seconds:.0f} s",
                    file=sys.stderr,
                )
    write_json(
        out_path,
        {
            **header("textured_tour", args.which, args.quick, load_before),
            "teachers": f"write_teacher(kind, size {size}, seed {bench.SEEDS[args.which]}) "
            + (
                "(development)"
                if args.which == "dev"
                else "(test: held out; the teacher the tour itself writes)"
            ),
            "config": tour,
            "pairs": pairs_entry(args.which, pairs_n),
            "rows": rows,
        },
    )
    print(f"wrote {out_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
