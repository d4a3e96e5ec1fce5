"""Throughput of the neural BRDF in torch, onnxruntime and Dr.Jit, as a fraction of the
matmul-peak bound, and against batch size.

    python benchmarks/neural_throughput.py                     # -> results/neural_throughput.json
    python benchmarks/neural_throughput.py --n 262144 --no-drjit

Model: the default architecture of ``neural_brdf.config`` (since issue 21 the compact
model, one hidden layer of 32 ReLU and a 32^2 grid; 64-64-64 SiLU before) with the
isotropic and the anisotropic encoding, exported exactly as training exports it.  Its
weights are random, since speed does not depend on them, but none is zero: Dr.Jit
would fold away a layer of zeros (as the freshly initialised output layer is) and time
a smaller network.  The albedo table is constant (its values do not change the cost).

Backends (:func:`backends`), each on the same random pairs:

* ``torch``: ``NormalizedBRDF`` forward in ``torch.inference_mode``;
* ``onnxruntime``: ``neural_brdf.load(path, threads=T).eval``, the public runtime;
* ``drjit``: the ``neural_brdf`` Mitsuba plugin's ``eval`` (see ``drjit_eval.py``),
  on Dr.Jit's own thread pool.

Bound: an evaluation needs 2 * sum(fan_in * fan_out) FLOPs in its Linear layers, so a
machine whose fp32 matmul runs at P FLOP/s (measured in the same run, at the backend's
thread count) allows at most P / FLOPs evaluations per second.  The fraction reported
is measured / bound: the encoding, activations, normalisation and call overhead are
what separates the two.  Rates are the best of ``repeats`` after a warm-up
(``common.evals_per_second``).  ``run_all.py`` calls :func:`measure` and
:func:`batch_curve` for the suite; this script alone writes
benchmarks/results/neural_throughput.json.  Nothing here asserts a speed.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(REPO))

import onnx  # noqa: E402
from common import evals_per_second, matmul_flops_per_s, write_json  # noqa: E402

import neural_brdf  # noqa: E402
from analytic import physics  # noqa: E402
from neural_brdf import config, export  # noqa: E402
from neural_brdf.train.model import NormalizedBRDF, RawBRDF  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "neural_throughput.json"
ENCODINGS = ("isotropic", "anisotropic")
# 1 to 4^10 = 1048576 pairs per call
BATCHES = tuple(4**k for k in range(11))


def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def backends() -> list[tuple[str, int]]:
    """(backend, threads): torch and onnxruntime on 1 thread and on every core;
    Dr.Jit on its own pool (one thread per core by default)."""
    n = cores()
    threads = sorted({1, n})
    return [("torch", t) for t in threads] + [("onnxruntime", t) for t in threads] + [("drjit", n)]


def linear_flops(proto: onnx.ModelProto) -> int:
    """2 * sum(fan_in * fan_out) over the Gemm/MatMul weights of an exported model."""
    weights = {t.name: tuple(t.dims) for t in proto.graph.initializer}
    total = 0
    for node in proto.graph.node:
        if node.op_type in ("Gemm", "MatMul"):
            dims = [weights[i] for i in node.input if i in weights and len(weights[i]) == 2]
            total += sum(2 * d[0] * d[1] for d in dims)
    return total


def build_model(encoding: str, folder: Path, *, seed: int = 0) -> tuple[NormalizedBRDF, Path]:
    """The default architecture with random nonzero weights, and its exported file."""
    cfg = config.from_dict({"model": {"encoding": encoding}})
    torch.manual_seed(seed)
    raw = RawBRDF.from_config(cfg.model).eval()
    with torch.no_grad():
        raw.mlp.head.weight.normal_(0.0, 0.1)  # initialised to zero: see the module doc
    n = cfg.normalization
    shape = (n.grid_size, n.grid_size, 3) if encoding != "isotropic" else (n.table_size, 3)
    model = NormalizedBRDF(raw, torch.full(shape, 1.5)).eval()
    proto = onnx.load_from_string(export.to_onnx_bytes(model, cfg.export.opset))
    onnx.helper.set_model_props(proto, {"encoding": encoding})
    path = folder / f"default_{encoding}.onnx"
    onnx.save(proto, path)
    return model, path


def random_pairs(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """float32 pairs above the horizon, 10% of them within a degree of grazing."""
    return (
        physics.random_directions(n, seed).astype(np.float32),
        physics.random_directions(n, seed + 1).astype(np.float32),
    )


def evaluator(
    backend: str, threads: int, model: NormalizedBRDF, path: Path, wi: np.ndarray, wo: np.ndarray
):
    """A no-argument callable evaluating the model on (wi, wo) with ``backend``."""
    if backend == "torch":
        torch.set_num_threads(threads)
        wi_t, wo_t = torch.from_numpy(wi), torch.from_numpy(wo)

        def call():
            with torch.inference_mode():
                model(wi_t, wo_t)

        return call
    if backend == "onnxruntime":
        brdf = neural_brdf.load(path, threads=threads)
        return lambda: brdf.eval(wi, wo)
    if backend == "drjit":
        import drjit_eval  # imports Mitsuba: only when Dr.Jit is benchmarked

        return drjit_eval.evaluator({"type": "neural_brdf", "filename": str(path)}, wi, wo)
    raise ValueError(f"unknown backend {backend!r}")


def measure_peaks(threads: list[int], repeats: int) -> dict[int, float]:
    """fp32 matmul FLOP/s at each thread count (torch.mm), torch's count restored."""
    saved = torch.get_num_threads()
    peaks = {}
    for t in threads:
        torch.set_num_threads(t)
        peaks[t] = matmul_flops_per_s(repeats)
    torch.set_num_threads(saved)
    return peaks


def measure(
    n: int, repeats: int, peaks: dict[int, float], folder: Path, *, drjit: bool = True
) -> dict:
    """Rates at batch ``n`` for every encoding and backend, against the bound."""
    wi, wo = random_pairs(n)
    saved = torch.get_num_threads()
    models, rows = {}, []
    for encoding in ENCODINGS:
        model, path = build_model(encoding, folder)
        flops = linear_flops(onnx.load(path))
        models[encoding] = {
            "linear_flops_per_eval": flops,
            "parameters": sum(p.numel() for p in model.parameters()),
        }
        for backend, threads in backends():
            if backend == "drjit" and not drjit:
                continue
            call = evaluator(backend, threads, model, path, wi, wo)
            row = {"encoding": encoding, "backend": backend, "threads": threads}
            if backend == "drjit":
                import drjit_eval

                row["first_call_s"] = drjit_eval.first_call_seconds(call)
            row["evals_per_s"] = evals_per_second(call, n, repeats)
            rows.append(row)
            print(
                f"  neural {encoding:11s} {backend:11s} {threads} thr  "
                f"{row['evals_per_s'] / 1e6:8.3f} M evals/s",
                flush=True,
            )
    torch.set_num_threads(saved)
    result = {"batch": n, "repeats": repeats, "models": models, "rows": rows}
    normalise(result, peaks)
    return result


def normalise(result: dict, peaks: dict[int, float]) -> None:
    """Set each row's bound, fraction of it and cost in matmul FLOPs (in place)."""
    for r in result["rows"]:
        peak = peaks[r["threads"]]
        bound = peak / result["models"][r["encoding"]]["linear_flops_per_eval"]
        r.update(
            {
                "bound_evals_per_s": bound,
                "fraction_of_bound": r["evals_per_s"] / bound,
                "matmul_flops_per_eval": peak / r["evals_per_s"],
            }
        )


def batch_curve(
    backend: str, threads: int, folder: Path, *, batches=BATCHES, repeats: int = 3
) -> list[dict]:
    """Rate against batch size for the isotropic default model."""
    model, path = build_model("isotropic", folder)
    saved = torch.get_num_threads()
    wi_all, wo_all = random_pairs(max(batches))
    out = []
    for n in batches:
        call = evaluator(backend, threads, model, path, wi_all[:n].copy(), wo_all[:n].copy())
        out.append({"batch": n, "evals_per_s": evals_per_second(call, n, repeats)})
    torch.set_num_threads(saved)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1 << 20, help="pairs per timed call")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-drjit", action="store_true", help="skip the Mitsuba plugin")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    peaks = measure_peaks(sorted({1, cores()}), args.repeats)
    with tempfile.TemporaryDirectory() as tmp:
        result = measure(args.n, args.repeats, peaks, Path(tmp), drjit=not args.no_drjit)
    result["matmul_gflops"] = {str(t): p / 1e9 for t, p in peaks.items()}
    write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
