"""Train presets from configs/, tabulate their physics and accuracy, and time how long
each takes to reach the 2% accuracy target.

    python benchmarks/neural_presets.py                       # all analytic presets, runs/bench/
    python benchmarks/neural_presets.py gold lambert --root /tmp/bench

Each preset is trained, exported and validated as ``python train.py configs/NAME.yaml``
does (progress bar off), with one change: the held-out error is logged every
``EVAL_EVERY`` steps instead of every 500.  That error (log.csv's ``val_rel_rmse``) is
the relative RMSE of f cos(theta_o) of the raw network on 16384 held-out
importance-sampled pairs (``neural_brdf.train.loop``); it costs one forward pass and changes
nothing in the optimisation.  Per preset:

* ``steps_to_target``, ``seconds_to_target``: the first logged step with
  val_rel_rmse <= TARGET (2%) and the training time up to it (log.csv's ``seconds``,
  the held-out evaluations included); null when the target is never reached;
* the final figures of the validator on the exported model: relative RMSE of f cos on
  its own importance-sampled pairs, reciprocity error, max directional albedo (white
  furnace), min value; plus the training, wall and CPU time of the whole run.

Targets (issue 3): error <= 2%, reciprocity <= 1e-6, max albedo <= 1 + 1e-3, min >= 0.

Nothing here chooses a setting: every preset trains with its own config as shipped (the
compact recipe, chosen in issue 21 on its own development runs), so there is no
development set and no test set; the table reports those configs, not a tuning.
``run_all.py`` calls :func:`run_preset` for the suite; this script alone writes
benchmarks/results/neural_presets.json.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(REPO))

import yaml  # noqa: E402
from common import loadavg, machine, write_json  # noqa: E402

from neural_brdf import config, pipeline  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "neural_presets.json"
SKIP = {"defaults"}
TARGET = 0.02
LOG_EVERY = 25
EVAL_EVERY = 50


def preset_names() -> list[str]:
    """Every config in configs/ with an analytic target (a measured-data config, such as
    merl.yaml, names a file the user supplies)."""
    names = []
    for p in sorted((REPO / "configs").glob("*.yaml")):
        target = (yaml.safe_load(p.read_text()) or {}).get("target") or {}
        if p.stem not in SKIP and not target.get("data"):
            names.append(p.stem)
    return names


def first_below(log_csv: Path, target: float) -> tuple[int | None, float | None, list]:
    """(step, seconds) of the first logged held-out error <= target, and the curve."""
    with open(log_csv, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["val_rel_rmse"]]
    curve = [(int(r["step"]), float(r["seconds"]), float(r["val_rel_rmse"])) for r in rows]
    for step, seconds, err in curve:
        if err <= target:
            return step, seconds, curve
    return None, None, curve


def run_preset(name: str, root: Path, overrides: list[str] = ()) -> dict:
    """Train, export and validate one preset; the figures of the module doc."""
    cfg = config.load(
        REPO / "configs" / f"{name}.yaml",
        ["train.progress=false", f"train.log_every={LOG_EVERY}", f"train.eval_every={EVAL_EVERY}"]
        + list(overrides),
    )
    wall, cpu = time.perf_counter(), time.process_time()
    report = pipeline.run(cfg, root / name, overwrite=True)  # a rerun replaces the last
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    step, seconds, curve = first_below(root / name / "log.csv", TARGET)
    c = report["checks"]
    return {
        "preset": name,
        "target": report["target"],
        "steps": cfg.train.steps,
        "threads": cfg.train.threads,
        "target_rel_rmse": TARGET,
        "steps_to_target": step,
        "seconds_to_target": seconds,
        "final_val_rel_rmse": curve[-1][2] if curve else None,
        "rel_rmse": report["accuracy"]["rel_rmse"],
        "nbrdf_log_error": report["accuracy"]["nbrdf_log_error"],
        "reciprocity": c["reciprocity"]["value"],
        "max_albedo": c["max_albedo"]["value"],
        "min_value": c["min_value"]["value"],
        "passed": report["passed"],
        "train_s": report["seconds"]["train"],
        "wall_s": wall,
        "cpu_s": cpu,
        "val_curve": [{"step": s, "seconds": t, "val_rel_rmse": e} for s, t, e in curve],
        "run_dir": str(root / name),
    }


def summary_line(r: dict) -> str:
    reach = (
        "not reached"
        if r["steps_to_target"] is None
        else f"2% at step {r['steps_to_target']:5d} ({r['seconds_to_target']:5.1f} s)"
    )
    return (
        f"{r['preset']:16s} {reach}  final {100 * r['rel_rmse']:5.2f}%  "
        f"recip {r['reciprocity']:.1g}  max albedo {r['max_albedo']:.4f}  "
        f"train {r['train_s']:5.1f} s  wall {r['wall_s']:5.1f} s"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("presets", nargs="*", help="names in configs/ (default: all)")
    ap.add_argument("--root", type=Path, default=REPO / "runs" / "bench")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    rows = []
    before = loadavg()
    for name in args.presets or preset_names():
        rows.append(run_preset(name, args.root))
        print(summary_line(rows[-1]), flush=True)
    # the rows with when and where (a file before 2026-12-07 is the bare list of rows)
    stamp = {"date": datetime.datetime.now().isoformat(timespec="seconds")}
    write_json(args.out, {**stamp, "machine": machine(before), "rows": rows})


if __name__ == "__main__":
    main()
