"""``neural-brdf export RUN`` of a projected textured run: the run's kept model
(``RUN/textured.pt``, ``neural_brdf.train.textured_store``) against projecting and
refitting again from the checkpoint (issue 30).

    python benchmarks/textured_export.py            # about 6 minutes on 2 cores
    python benchmarks/textured_export.py --quick    # tiny budgets: the machinery only

The README tour's config (``python -m neural_brdf.measured.procedural DIR``: the
roughplastic teacher, a 32^2 field, 1500 steps, projected at 128^2) with
``texture.refit_steps`` 3000, the refit of ``textured.py``'s recipe, trained once by
``pipeline.run``.  Then ``export.export_run`` of the run, timed in interleaved rounds:
with ``textured.pt`` in place (kept) and with it moved aside (projected and refitted
again); each figure is the best of ``--rounds``.  Each exported file is compared with
the run's ``model.onnx`` byte for byte, and by f at 4096 rows (onnxruntime).  Nothing is
chosen here (no setting), so there is no development or test set; nothing asserts.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import machine, write_json  # noqa: E402

REFIT_STEPS = 3000  # textured.py's recipe (textured_refit_dev.json chose it)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny budgets: the machinery only")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    out_path = args.out or Path(__file__).resolve().parent / "results" / (
        "textured_export_quick.json" if args.quick else "textured_export.json"
    )
    import numpy as np
    import onnxruntime as ort
    import torch

    torch.set_num_threads(2)
    from textured_tour import tour_config

    from neural_brdf import config as cfgmod
    from neural_brdf import export, pipeline, runfolder, validate
    from neural_brdf.measured.procedural import write_teacher

    load_before = [round(x, 2) for x in os.getloadavg()]
    rounds = 1 if args.quick else args.rounds
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        # the tour's own teacher: write_teacher's default seed, as the README's command
        write_teacher(folder, "roughplastic", size=32 if args.quick else 512)
        (folder / "textured.yaml").write_text(tour_config(folder, 20 if args.quick else 1500))
        overrides = [f"texture.refit_steps={20 if args.quick else REFIT_STEPS}"]
        if args.quick:
            overrides.append("texture.project=16")
        cfg = cfgmod.load(folder / "textured.yaml", overrides)
        run_dir = folder / "run"
        t0 = time.perf_counter()
        pipeline.run(cfg, run_dir)
        train_s = time.perf_counter() - t0
        kept_file = run_dir / runfolder.TEXTURED
        aside = folder / "aside.pt"

        def export_to(name: str) -> tuple[float, Path, dict]:
            out = folder / name
            t = time.perf_counter()
            info = export.export_run(
                run_dir,
                out,
                measure=validate.physics,
                measure_textured=validate.physics_textured,
            )
            return time.perf_counter() - t, out, info

        times: dict[str, list[float]] = {"kept": [], "again": []}
        files: dict[str, Path] = {}
        flags: dict[str, bool] = {}
        for r in range(rounds):
            s, files["kept"], info = export_to(f"kept_{r}.onnx")
            times["kept"].append(s)
            flags["kept"] = bool(info["projection"]["kept_by_the_run"])
            shutil.move(kept_file, aside)
            s, files["again"], info = export_to(f"again_{r}.onnx")
            times["again"].append(s)
            flags["again"] = bool(info["projection"]["kept_by_the_run"])
            shutil.move(aside, kept_file)
        model = (run_dir / runfolder.MODEL).read_bytes()
        rng = np.random.default_rng(3)
        n = 4096
        wi = rng.normal(size=(n, 3))
        wo = rng.normal(size=(n, 3))
        for v in (wi, wo):
            v[:, 2] = np.abs(v[:, 2]) + 0.05
            v /= np.linalg.norm(v, axis=-1, keepdims=True)
        feeds = {
            "wi": wi.astype(np.float32),
            "wo": wo.astype(np.float32),
            "uv": rng.random((n, 2)).astype(np.float32),
        }

        def f_of(p: Path):
            s = ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
            return s.run(["f"], feeds)[0]

        ref = f_of(run_dir / runfolder.MODEL)
        same = {
            k: {
                "bytes": p.read_bytes() == model,
                "max_abs_f_difference": float(np.abs(f_of(p) - ref).max()),
            }
            for k, p in files.items()
        }
        kept_bytes = kept_file.stat().st_size
    import mitsuba as mi

    write_json(
        out_path,
        {
            "benchmark": "textured_export",
            "quick": args.quick,
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(load_before, mitsuba=mi.__version__, torch=torch.__version__),
            "run": "the README tour's config (roughplastic, write_teacher seed 0, 512^2; "
            f"project 128) with texture.refit_steps {REFIT_STEPS}",
            "overrides": overrides,
            "train_seconds": train_s,
            "rounds": rounds,
            "export_seconds": {k: min(v) for k, v in times.items()},
            "export_seconds_all": times,
            "kept_by_the_run": flags,
            "same_as_the_runs_file": same,
            "textured_pt_bytes": kept_bytes,
            "model_onnx_bytes": len(model),
        },
    )
    print(f"wrote {out_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
