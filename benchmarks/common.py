"""Shared by the benchmark scripts: timing, the matmul-peak reference, atomic JSON."""

from __future__ import annotations

import json
import math
import os
import platform
import time
from pathlib import Path

import torch

MATMUL_N = 2048


def best_time(fn, repeats: int) -> float:
    """Seconds of the fastest of ``repeats`` calls, after one warm-up call."""
    fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def evals_per_second(fn, n: int, repeats: int, *, min_block_s: float = 0.02) -> float:
    """Rate of ``fn``, which evaluates ``n`` pairs per call: n / seconds per call.

    Calls are timed in blocks of at least ``min_block_s`` (one call for large batches,
    many for small ones, which a single call would time below the clock's resolution
    and above its overhead); the best of ``repeats`` blocks, after one warm-up call.
    """
    fn()
    t0 = time.perf_counter()
    fn()
    once = time.perf_counter() - t0
    calls = max(1, math.ceil(min_block_s / max(once, 1e-9)))
    best = once if calls == 1 else math.inf
    for _ in range(repeats - (calls == 1)):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        best = min(best, (time.perf_counter() - t0) / calls)
    return n / best


def matmul_flops_per_s(repeats: int) -> float:
    """fp32 matmul rate (FLOP/s) of torch.mm on two 2048 x 2048 matrices, at the
    current torch thread count: the machine's reference peak for ratios."""
    a = torch.randn(MATMUL_N, MATMUL_N, dtype=torch.float32)
    b = torch.randn(MATMUL_N, MATMUL_N, dtype=torch.float32)
    return 2.0 * MATMUL_N**3 / best_time(lambda: torch.mm(a, b), repeats)


def loadavg() -> list[float]:
    """The 1-, 5- and 15-minute load averages, rounded."""
    return [round(x, 2) for x in os.getloadavg()]


def machine(load_before: list[float], **versions) -> dict:
    """The JSON's ``machine`` entry: platform, cores, the load average (1, 5, 15 min)
    before the run and now, then ``versions`` (mitsuba=..., torch=...)."""
    return {
        "platform": platform.platform(),
        "cores": os.cpu_count(),
        "loadavg_before": load_before,
        "loadavg_after": loadavg(),
        **versions,
    }


def dev_test_args(argv, doc: str, name: str):
    """The command line of a benchmark with a development and a test set: ``--quick``,
    ``--set dev|test`` (``args.which``), ``--out``.  Returns (args, the JSON's path:
    ``--out``, or ``results/<name>_quick.json`` / ``results/<name>_<set>.json``)."""
    import argparse

    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny budgets: the machinery only")
    ap.add_argument("--set", choices=("dev", "test"), default="dev", dest="which")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    results = Path(__file__).resolve().parent / "results"
    tail = "quick" if args.quick else args.which
    return args, args.out or results / f"{name}_{tail}.json"


def write_json(path: Path, data) -> None:
    """Write pretty JSON atomically (neural_brdf.fileio: temporary file, fsync, rename)."""
    from neural_brdf.fileio import atomic_write

    atomic_write(path, json.dumps(data, indent=2) + "\n", parents=True)


# the arithmetic instructions of a lowered graph (neural_brdf.graph); an fma counts 2
ARITH_OPS = {"add", "sub", "mul", "div", "fma", "neg", "abs", "min", "max"}


def arith_ops(counts: dict[str, int]) -> int:
    """Arithmetic operations per evaluation from ``graph.lower(proto).count()``."""
    return sum(counts.get(k, 0) * (2 if k == "fma" else 1) for k in ARITH_OPS)


def add_fit_arguments(p, *, work: str, data: Path, out: Path, resume: str, data_holds: str) -> None:
    """The options the benchmarks that train many fits share: --set, --work, --data,
    --out and --resume (``resume`` says what it keeps, ``data_holds`` what --data holds)."""
    import tempfile

    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        help="extra config override for every fit (recorded in the JSON)",
    )
    p.add_argument(
        "--work",
        type=Path,
        default=Path(tempfile.gettempdir()) / work,
        help="folder for the .binary files and run directories",
    )
    p.add_argument("--data", type=Path, default=data, help=f"holds {data_holds}")
    p.add_argument("--out", type=Path, default=out)
    p.add_argument("--resume", action="store_true", help=f"keep {resume} in --out")
