"""Train every preset in configs/ with its default config and tabulate the targets.

    python benchmarks/neural_presets.py                       # all presets, runs/bench/
    python benchmarks/neural_presets.py gold lambert --root /tmp/bench

Each preset is trained, exported and validated exactly as ``python train.py
configs/NAME.yaml`` does (progress bar off).  The table gives, per preset: the relative
RMSE of f cos(theta_o) on importance-sampled pairs, the reciprocity error, the max
directional albedo (white furnace), the min value, the training time and the total wall
and CPU time of the run.  Targets (issue 3): error <= 2%, reciprocity <= 1e-6, max
albedo <= 1 + 1e-3, min >= 0.  Results go to benchmarks/results/neural_presets.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")   # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:            # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(REPO))

from neural_brdf import config, train  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "neural_presets.json"
SKIP = {"defaults"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("presets", nargs="*", help="names in configs/ (default: all)")
    ap.add_argument("--root", type=Path, default=REPO / "runs" / "bench")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    names = args.presets or sorted(p.stem for p in (REPO / "configs").glob("*.yaml")
                                   if p.stem not in SKIP)
    rows = []
    for name in names:
        cfg = config.load(REPO / "configs" / f"{name}.yaml", ["train.progress=false"])
        wall, cpu = time.perf_counter(), time.process_time()
        report = train.run(cfg, args.root / name)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        c = report["checks"]
        rows.append({"preset": name, "target": report["target"],
                     "rel_rmse": report["accuracy"]["rel_rmse"],
                     "nbrdf_log_error": report["accuracy"]["nbrdf_log_error"],
                     "reciprocity": c["reciprocity"]["value"],
                     "max_albedo": c["max_albedo"]["value"], "min_value": c["min_value"]["value"],
                     "passed": report["passed"], "train_s": report["seconds"]["train"],
                     "wall_s": wall, "cpu_s": cpu})
        r = rows[-1]
        print(f"{name:16s} err {100 * r['rel_rmse']:6.2f}%  recip {r['reciprocity']:.1g}  "
              f"max albedo {r['max_albedo']:.4f}  min {r['min_value']:.2g}  "
              f"train {r['train_s']:5.1f} s  wall {wall:5.1f} s  cpu {cpu:5.1f} s", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
