"""Evaluation rate of the generated C (``neural-brdf codegen --target c``) against
onnxruntime, at batch 1 and batch 4096, on one thread.

    python benchmarks/codegen_c.py [--rounds 5] [--out benchmarks/results/codegen_c.json]

The model is the default architecture of each encoding with random nonzero weights
(``neural_throughput.build_model``; the weights do not change the work).  The C header
is compiled with ``cc -std=c99 -O2`` into a timing program that calls
``neural_brdf_eval`` once per pair in a plain loop:

* batch 1: the same pair, ``CALLS_1`` calls per block;
* batch 4096: a loop over 4096 different pairs per block;

best block of ``--rounds``, per-eval time.  onnxruntime is ``neural_brdf.load(path,
threads=1).eval`` on the same pairs (common.evals_per_second, best of blocks).  The two
are run interleaved round by round, so that a change of machine load hits both; the
load average before and after is recorded, as is the maximum relative difference of the
C values against onnxruntime on the 4096 pairs.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
for p in (str(HERE), str(REPO)):
    if p not in sys.path:
        sys.path.insert(0, p)

from common import evals_per_second, write_json  # noqa: E402
from neural_throughput import build_model, random_pairs  # noqa: E402

import neural_brdf  # noqa: E402
from neural_brdf import backends  # noqa: E402
from neural_brdf.export import relative_difference  # noqa: E402

OUT = HERE / "results" / "codegen_c.json"
BATCH = 4096
CALLS_1 = 20000  # calls per block at batch 1
LOBE = {"alpha": 0.3, "weight": 0.5}  # sampling is not timed; any lobe will do
CFLAGS = ["-std=c99", "-O2"]

TIMER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "model.h"

static double now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* timer N CALLS1 IN OUT: writes f of the N pairs to OUT, prints the seconds per eval
   of one block at batch 1 (CALLS1 calls) and of one block over the N pairs */
int main(int argc, char **argv)
{
    long n = atol(argv[1]), calls = atol(argv[2]), i;
    float *rows = malloc(sizeof(float) * 6 * (size_t)n);
    float *out = malloc(sizeof(float) * 3 * (size_t)n);
    volatile float sink = 0.0f;
    double t0, one, batch;
    FILE *in = fopen(argv[3], "rb"), *res;
    if (!in || fread(rows, sizeof(float), 6 * (size_t)n, in) != 6 * (size_t)n) return 2;
    t0 = now();
    for (i = 0; i < calls; i++) {
        float f[3];
        neural_brdf_eval(rows, rows + 3, f);
        sink += f[0];
    }
    one = (now() - t0) / (double)calls;
    t0 = now();
    for (i = 0; i < n; i++)
        neural_brdf_eval(rows + 6 * i, rows + 6 * i + 3, out + 3 * i);
    batch = (now() - t0) / (double)n;
    res = fopen(argv[4], "wb");
    fwrite(out, sizeof(float), 3 * (size_t)n, res);
    fclose(res);
    printf("%.6e %.6e %g\n", one, batch, (double)sink);
    return 0;
}
"""


def compile_timer(model: Path, folder: Path) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        sys.exit("codegen_c: needs a C compiler (cc)")
    (folder / "model.h").write_text(backends.generate(model, "c", lobe=LOBE))
    (folder / "timer.c").write_text(TIMER)
    exe = folder / "timer"
    subprocess.run([cc, *CFLAGS, "-o", str(exe), str(folder / "timer.c"), "-lm"], check=True)
    return exe


def c_round(exe: Path, folder: Path, rows: np.ndarray) -> tuple[float, float, np.ndarray]:
    src, dst = folder / "pairs.bin", folder / "f.bin"
    rows.astype(np.float32).tofile(src)
    out = subprocess.run(
        [str(exe), str(len(rows)), str(CALLS_1), str(src), str(dst)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    return float(out[0]), float(out[1]), np.fromfile(dst, np.float32).reshape(-1, 3)


def loadavg() -> list[float]:
    return [float(v) for v in Path("/proc/loadavg").read_text().split()[:3]]


def compiler_version() -> str:
    cc = shutil.which("cc") or "cc"
    return subprocess.run([cc, "--version"], capture_output=True, text=True).stdout.split("\n")[0]


def bench_encoding(enc: str, folder: Path, rounds: int) -> dict:
    folder.mkdir()
    _, path = build_model(enc, folder)
    exe = compile_timer(path, folder)
    wi, wo = random_pairs(BATCH)
    rows = np.concatenate([wi, wo], 1)
    brdf = neural_brdf.load(path, threads=1)
    c1, cn, ort1, ortn = [], [], [], []
    f = None
    for _ in range(rounds):  # interleaved
        one, batch, f = c_round(exe, folder, rows)
        c1.append(one)
        cn.append(batch)
        ort1.append(1.0 / evals_per_second(lambda: brdf.eval(wi[:1], wo[:1]), 1, 3))
        ortn.append(1.0 / evals_per_second(lambda: brdf.eval(wi, wo), BATCH, 3))
    return {
        "c_evals_per_s": {"batch_1": 1.0 / min(c1), f"batch_{BATCH}": 1.0 / min(cn)},
        "onnxruntime_evals_per_s": {"batch_1": 1.0 / min(ort1), f"batch_{BATCH}": 1.0 / min(ortn)},
        "c_over_onnxruntime": {
            "batch_1": min(ort1) / min(c1),
            f"batch_{BATCH}": min(ortn) / min(cn),
        },
        "c_parity_rel_error": relative_difference(f, brdf.eval(wi, wo)),
        "header_lines": (folder / "model.h").read_text().count("\n"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    load_before = loadavg()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for enc in ("isotropic", "anisotropic"):
            results[enc] = bench_encoding(enc, Path(tmp) / enc, args.rounds)
            print(enc, results[enc], flush=True)
    write_json(
        args.out,
        {
            "benchmark": "codegen_c",
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": " ".join(["benchmarks/codegen_c.py"] + sys.argv[1:]),
            "machine": {
                "cpu": platform.processor() or platform.machine(),
                "cores": os.cpu_count(),
                "compiler": compiler_version(),
                "cflags": CFLAGS,
                "loadavg_before": load_before,
                "loadavg_after": loadavg(),
            },
            "rounds": args.rounds,
            "batch": BATCH,
            "calls_batch_1": CALLS_1,
            "models": "neural_throughput.build_model (default architecture, random weights)",
            "results": results,
        },
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
