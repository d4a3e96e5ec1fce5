"""Throughput of the analytic models: BRDF evaluations per second, numpy and torch.

    python benchmarks/analytic_throughput.py
    python benchmarks/analytic_throughput.py --batch 65536 --repeats 3 --out /tmp/t.json

Every model in ``analytic.available()`` is evaluated at its defaults on a fixed batch
of random (wi, wo) pairs in the upper hemisphere, in float32: through ``brdf.eval`` on
numpy arrays and through ``brdf.f`` on torch tensors (CPU, the default thread count).
One warm-up call, then the best of ``--repeats`` timed calls.  The same run measures the
machine's fp32 matmul peak (torch.mm of two 2048 x 2048 matrices, at torch's thread
count: the numpy path converts and runs the same torch code), and each rate is also
given as its cost in matmul FLOPs: peak / rate, the FLOPs the machine's matmul
would have done in the time of one evaluation (the models have no matmul of their own,
so this is their machine-independent figure).  Results go to
benchmarks/results/analytic_throughput.json (written atomically) and a table is printed.
``run_all.py`` calls :func:`measure` for the suite.  Nothing here asserts a speed.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(REPO))

from common import MATMUL_N, evals_per_second, matmul_flops_per_s, write_json  # noqa: E402

import analytic  # noqa: E402

DEFAULT_OUT = REPO / "benchmarks" / "results" / "analytic_throughput.json"


def random_pairs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """float32 (wi, wo), each uniform over the upper hemisphere."""
    rng = np.random.default_rng(seed)

    def hemi():
        z = rng.uniform(0.0, 1.0, n)
        phi = rng.uniform(0.0, 2.0 * math.pi, n)
        r = np.sqrt(1.0 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1).astype(np.float32)

    return hemi(), hemi()


def bench_model(name: str, wi: np.ndarray, wo: np.ndarray, repeats: int) -> dict:
    brdf = analytic.create(name)
    wi_t, wo_t = torch.from_numpy(wi), torch.from_numpy(wo)
    n = len(wi)
    numpy_rate = evals_per_second(lambda: brdf.eval(wi, wo), n, repeats)
    with torch.inference_mode():
        torch_rate = evals_per_second(lambda: brdf.f(wi_t, wo_t), n, repeats)
    return {"model": repr(brdf), "numpy_evals_per_s": numpy_rate, "torch_evals_per_s": torch_rate}


def measure(batch: int, repeats: int, peak_flops: float) -> dict:
    """Every model's rates, plus their cost in matmul FLOPs at ``peak_flops`` (FLOP/s
    of the matmul at torch's current thread count)."""
    wi, wo = random_pairs(batch)
    models = {name: bench_model(name, wi, wo, repeats) for name in analytic.available()}
    result = {
        "batch": batch,
        "repeats": repeats,
        "dtype": "float32",
        "torch_threads": torch.get_num_threads(),
        "models": models,
    }
    normalise(result, peak_flops)
    return result


def normalise(result: dict, peak_flops: float) -> None:
    """Set each rate's cost in matmul FLOPs, peak / rate (in place)."""
    for m in result["models"].values():
        for api in ("numpy", "torch"):
            m[f"{api}_matmul_flops_per_eval"] = peak_flops / m[f"{api}_evals_per_s"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=1 << 18, help="(wi, wo) pairs per call")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls; the best is kept")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output path")
    args = ap.parse_args(argv)
    if args.batch < 1 or args.repeats < 1:
        ap.error("--batch and --repeats must be >= 1")

    load_at_start = os.getloadavg()[0]  # other work on the machine skews every figure
    peak = matmul_flops_per_s(args.repeats)
    result = measure(args.batch, args.repeats, peak)
    result = {
        "benchmark": "analytic_throughput",
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "statistic": "best of repeats, after one warm-up call",
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "numpy": np.__version__,
            "load_average_1min_at_start": load_at_start,
            "fp32_matmul_gflops": peak / 1e9,
            "matmul": f"torch.mm {MATMUL_N}x{MATMUL_N} float32",
        },
        **result,
    }
    write_json(args.out, result)

    print(
        f"analytic throughput: batch {args.batch}, float32, best of {args.repeats}; "
        f"{torch.get_num_threads()} torch threads"
    )
    print(
        f"fp32 matmul peak (torch.mm {MATMUL_N}^2): {peak / 1e9:.1f} GFLOP/s; "
        f"1-min load average at start {load_at_start:.2f}"
    )
    print(f"{'model':<20}{'numpy M evals/s':>18}{'torch M evals/s':>18}")
    for name, m in result["models"].items():
        print(
            f"{name:<20}{m['numpy_evals_per_s'] / 1e6:>18.2f}{m['torch_evals_per_s'] / 1e6:>18.2f}"
        )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
