"""When the image stage stops: ``images.patience`` replayed on recorded development fits.

    python benchmarks/images_any.py --set dev --work W    # fits that ran train.steps
    python benchmarks/images_patience.py W [W2 ...]       # results/images_patience_dev.json

The held-out loss of an images fit is scored before the first step and every
``images.validation_every`` steps, and the fit keeps the best-scoring weights
(docs/inverse.md).  ``images.patience`` P stops the stage once P scorings in a row have
not beaten the best.  The rule needs only those scorings, so it is replayed here on the
recorded ones (each run's ``log.csv`` column ``heldout_loss`` and the start's loss in its
``metrics.json``) of fits that ran every step: for each P, where each run would have
stopped, whether it would have kept the same weights (the same best step) and how many
image-stage steps it saves.  A run's kept weights depend only on the scorings up to its
stop, so "the same best step" means the same exported network and the same figures.

Only development runs are read (a folder ``<work>/dev/<material>/run``): the patience is
chosen here, and the test set's figures come from ``images_any.py`` with the chosen value.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

from neural_brdf import config as cfgmod
from neural_brdf.inverse.fit import stalled_for

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "images_patience_dev.json"
PATIENCES = tuple(range(1, 9))


def scorings(run: Path) -> tuple[list[tuple[int, float]], dict]:
    """[(step, held-out loss)] with the start's at step 0, and metrics.json's training."""
    training = json.loads((run / "metrics.json").read_text())["training"]
    out = [(0, float(training["validation"]["start_loss"]))]
    with open(run / "log.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            if row.get("heldout_loss"):
                out.append((int(row["step"]), float(row["heldout_loss"])))
    return out, training


def replay(seq: list[tuple[int, float]], every: int, steps: int, patience: int | None):
    """(stop step, best step) of the fit's own rule (``inverse.fit.stalled_for``) on the
    scorings ``seq``, recorded as the fit records them."""
    images = cfgmod.Images(patience=patience, validation_every=every)
    val: dict = {"best_step": seq[0][0], "best_loss": seq[0][1]}
    for step, loss in seq[1:]:
        if loss < val["best_loss"]:
            val.update(best_step=step, best_loss=loss)
        val["last_step"] = step
        if stalled_for(val, images, steps) is not None:
            break
    return val.get("last_step", seq[0][0]), val["best_step"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", nargs="+", type=Path, help="images_any.py --set dev work folders")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    runs: dict[str, dict] = {}
    for work in args.work:
        for run in sorted((work / "dev").glob("*/run")):
            if not (run / "metrics.json").is_file():
                continue
            seq, training = scorings(run)
            every, steps = int(training["validation"]["every"]), int(training["steps"])
            if seq[-1][0] != steps:
                print(
                    f"{run}: stopped before train.steps ({seq[-1][0]} < {steps})", file=sys.stderr
                )
                return 2
            # the image stage's rate over train.lr tells two fits of one material apart
            name = f"{run.parent.name}, lr x{training.get('lr_factor', 1.0):g}"
            full = replay(seq, every, steps, None)
            runs[name] = {
                "folder": str(run),
                "lr_factor": training.get("lr_factor"),
                "scorings": seq,
                "every": every,
                "steps": steps,
                "full_run_best_step": full[1],
                "per_patience": {},
            }
            for p in PATIENCES:
                stop, best_step = replay(seq, every, steps, p)
                runs[name]["per_patience"][str(p)] = {
                    "stop": stop,
                    "best_step": best_step,
                    "same_weights": best_step == full[1],
                }
    if not runs:
        print(f"no development runs under {', '.join(map(str, args.work))}", file=sys.stderr)
        return 2
    summary = {}
    for p in PATIENCES:
        per = [r["per_patience"][str(p)] for r in runs.values()]
        summary[str(p)] = {
            "same_weights": sum(x["same_weights"] for x in per),
            "runs": len(per),
            "steps": sum(x["stop"] for x in per),
            "steps_full": sum(r["steps"] for r in runs.values()),
        }
    result = {
        "benchmark": "images_patience",
        "set": "dev",
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "definition": "images.patience P replayed on the recorded held-out scorings of "
        "development fits that ran every step: the stage stops at the first scoring P "
        "scorings (P x validation_every steps) after the best so far; same_weights: the "
        "kept best step equals the full run's",
        "chosen": 5,
        "why": "the smallest P keeping every run's weights is 3, and only just: gold's "
        "scorings at steps 10 and 20 were above its start, and step 30 beat the start by "
        "1e-6; P = 5 keeps two scorings of margin",
        "runs": runs,
        "summary": summary,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    for p, s in summary.items():
        print(
            f"patience {p}: {s['same_weights']}/{s['runs']} same weights, "
            f"{s['steps']}/{s['steps_full']} steps"
        )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
