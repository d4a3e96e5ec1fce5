"""Wall time of one small sweep on the three executor set-ups (issue 7's closing note).

    python experiments/sweep_timing.py [--repeats 2] [--trials 6] [--steps 300]

The sweep: ``--trials`` seeds of configs/quickstart.yaml at ``--steps`` steps, each an
ordinary trial (train, export, validate, report) on 1 thread.  It runs from scratch
with the local executor on 1 worker, on 2 workers, and with Ray on a local instance of
2 CPUs (its start-up included: that is what a user waits for), ``--repeats`` times in
turn; the best time of each is kept, since the machine may be shared.  Every set-up
must produce the same metrics (checked).  Writes docs/results/sweep_timing.json with
the times and the ratios to local-1-worker.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import yaml  # noqa: E402

from neural_brdf.fileio import atomic_write  # noqa: E402
from neural_brdf.tooling import sweep  # noqa: E402

SETUPS = {
    "local, 1 worker": ("local", 1),
    "local, 2 workers": ("local", 2),
    "ray, local instance (2 CPUs)": ("ray", 2),
}


def metrics(results: dict) -> list:
    return [
        (
            r["trial"],
            r["status"],
            {k: v for k, v in r["metrics"].items() if not k.endswith("seconds")},
        )
        for r in results["trials"]
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--steps", type=int, default=300)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="sweep-timing-"))
    spec = {
        "name": "timing",
        "base": str(REPO / "configs" / "quickstart.yaml"),
        "set": {"train.steps": args.steps},
        "grid": {"train.seed": list(range(args.trials))},
    }
    path = work / "timing.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    times = {name: [] for name in SETUPS}
    reference = None
    for _ in range(args.repeats):
        for name, (executor, workers) in SETUPS.items():
            out = work / "out"
            shutil.rmtree(out, ignore_errors=True)
            load = os.getloadavg()[0]
            t0 = time.perf_counter()
            results = sweep.run_sweep(path, executor=executor, workers=workers, out=out)
            wall = time.perf_counter() - t0
            trials = [
                {k: r[k] for k in ("trial", "started", "finished", "pid")}
                | {k: r["metrics"][k] for k in ("train_seconds", "total_seconds")}
                for r in results["trials"]
            ]
            times[name].append({"seconds": wall, "load_before": load, "trials": trials})
            print(f"{name:32s} {wall:7.1f} s  (load average before: {load:.1f})", flush=True)
            if reference is None:
                reference = metrics(results)
            assert metrics(results) == reference, f"{name}: different metrics"
            assert all(r["status"] == "ok" for r in results["trials"])
    best = {name: min(t["seconds"] for t in ts) for name, ts in times.items()}
    base = best["local, 1 worker"]
    report = {
        "sweep": {**spec, "base": "configs/quickstart.yaml"},
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "repeats": times,
        "best_seconds": best,
        "ratio_to_local_1_worker": {k: v / base for k, v in best.items()},
        "same_metrics_on_every_setup": True,
    }
    dest = REPO / "docs" / "results" / "sweep_timing.json"
    atomic_write(dest, json.dumps(report, indent=2) + "\n", parents=True)
    for name, ratio in report["ratio_to_local_1_worker"].items():
        print(f"{name:32s} best {best[name]:7.1f} s   ratio {ratio:.2f}")
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
