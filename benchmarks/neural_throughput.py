"""ONNX throughput of the default neural BRDF, and its fraction of the matmul-peak bound.

    python benchmarks/neural_throughput.py
    python benchmarks/neural_throughput.py --model runs/quickstart/model.onnx --n 1000000

The model is the default architecture of ``neural_brdf.config`` (random weights; speed
does not depend on them) exported exactly as training exports it, or ``--model``.  It is
evaluated through ``neural_brdf.load`` (onnxruntime, CPU) on ``--n`` random pairs with
1 and 2 intra-op threads; best of ``--repeats`` after a warm-up.  The same run measures
the fp32 matmul peak with torch.mm (2048 x 2048) at the same thread counts.

Bound: an evaluation needs 2 * sum(fan_in * fan_out) flops in its Linear layers, so the
peak allows at most peak / flops evaluations per second.  The fraction reported is
measured / bound (the encoding, activations and normalisation are the overhead).
Results go to benchmarks/results/neural_throughput.json.  Nothing here asserts a speed.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:            # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(REPO))

import onnx  # noqa: E402

import neural_brdf  # noqa: E402
from analytic import physics  # noqa: E402
from neural_brdf import config, export  # noqa: E402
from neural_brdf.model import NormalizedBRDF, RawBRDF  # noqa: E402
from common import best_time, matmul_flops_per_s, write_json  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "neural_throughput.json"





def linear_flops(path: Path) -> int:
    """2 * sum(fan_in * fan_out) over the Gemm/MatMul weights of an exported model."""
    proto = onnx.load(path)
    weights = {t.name: tuple(t.dims) for t in proto.graph.initializer}
    total = 0
    for node in proto.graph.node:
        if node.op_type in ("Gemm", "MatMul"):
            dims = [weights[i] for i in node.input if i in weights and len(weights[i]) == 2]
            total += sum(2 * d[0] * d[1] for d in dims)
    return total


def default_model(tmp: Path) -> Path:
    cfg = config.Config()
    torch.manual_seed(0)
    raw = RawBRDF.from_config(cfg.model).eval()
    table = torch.full((cfg.normalization.table_size, 3), 1.5)
    path = tmp / "default.onnx"
    path.write_bytes(export.to_onnx_bytes(NormalizedBRDF(raw, table).eval(), cfg.export.opset))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, help="an exported model (default: default architecture)")
    ap.add_argument("--n", type=int, default=1 << 20, help="pairs per timed call")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        path = args.model or default_model(Path(tmp))
        flops = linear_flops(path)
        wi = physics.random_directions(args.n, 1).astype(np.float32)
        wo = physics.random_directions(args.n, 2).astype(np.float32)
        rows = []
        for threads in (1, 2):
            model = neural_brdf.load(path, threads=threads)
            evals = args.n / best_time(lambda: model.eval(wi, wo), args.repeats)
            torch.set_num_threads(threads)
            peak = matmul_flops_per_s(args.repeats)
            bound = peak / flops
            rows.append({"threads": threads, "evals_per_s": evals, "matmul_gflops": peak / 1e9,
                         "bound_evals_per_s": bound, "fraction_of_bound": evals / bound})
    result = {"model": str(args.model or "default architecture (random weights)"),
              "linear_flops_per_eval": flops, "n": args.n, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, result)
    print(f"linear flops per evaluation: {flops}")
    print("threads  M evals/s  matmul GFLOP/s  bound M evals/s  fraction")
    for r in rows:
        print(f"{r['threads']:7d}  {r['evals_per_s'] / 1e6:9.2f}  {r['matmul_gflops']:14.1f}  "
              f"{r['bound_evals_per_s'] / 1e6:15.2f}  {r['fraction_of_bound']:8.2f}")


if __name__ == "__main__":
    main()
