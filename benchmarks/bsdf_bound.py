"""BSDF-bound render time of neural BRDFs against Mitsuba's built-in BSDF (llvm_ad_rgb).

    python benchmarks/bsdf_bound.py --variant cuda_ad_rgb gold=runs/gold/model.onnx

    python benchmarks/bsdf_bound.py runs/gold/model.onnx runs/gold2x16/model.onnx
    python benchmarks/bsdf_bound.py --label gold=runs/gold/model.onnx --repeats 4

The scene (:func:`scene`) makes the BSDF the cost: one unit sphere filling a square
orthographic frame (every pixel hits it), a ``constant`` emitter (no light sampling
geometry), the ``path`` integrator with ``max_depth: -1`` (paths end when they leave the
convex sphere, after one scattering; Russian roulette never triggers), 256 x 256 pixels
at 64 spp by default.

Per model, two BSDFs render it:

* ``neural_brdf`` with the model;
* the reference, always Mitsuba's built-in ``roughconductor`` (issue 12's yardstick):
  with the target's distribution, alpha(s) and conductor when the target is a microfacet
  conductor (``reference_matched``; Mitsuba uses the separable Smith G where the target
  may use the height-correlated one: same cost), else gold's GGX alpha 0.3 Au for an
  isotropic model and brushed_ggx's GGX 0.15 x 0.45 Al for an anisotropic one;
* the headline ``ratio`` is the best wall time of the neural BSDF over the best of the
  reference, over ``--repeats`` interleaved rounds (rotating order, after one compiling
  render each, in one process that shares Dr.Jit's kernel cache).

Separately, the first render including tracing and kernel compilation is timed in a fresh
subprocess per BSDF with ``DRJIT_CACHE_DIR`` set to a new empty directory (Dr.Jit's
on-disk kernel cache, by default ~/.drjit, would otherwise return a kernel compiled in an
earlier run): ``first_render_s`` (load excluded), its second render ``second_render_s``
and ``compile_s`` = first - second.

Also per model: onnxruntime evaluations/s of the file (one thread, batch 2^16), Dr.Jit
evaluations/s of the plugin's ``eval`` on 2^18 random pairs
(``drjit_eval.evaluator``), the MLP's parameters and Linear FLOPs (2 * fan_in * fan_out
summed over Gemm/MatMul weights: the issue's "FLOPs per eval"), and the lowered op list's
instruction counts (``graph.lower``: every op of the total graph after constant folding,
``fma`` = one instruction).  The machine state (/proc/loadavg before and after, date,
cores) is stored with every model, since other processes may share the machine.
The relative RMSE of f cos and the training steps come from the run folder's
metrics.json and config when the model has them.  Results are merged into
benchmarks/results/bsdf_bound.json by label (atomically).
Nothing here asserts a speed.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):  # run from a checkout without `pip install -e .`
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")


def _variant_option() -> str:
    """``--variant`` of the command line, read here: the plugins below register for the
    variant set before they are imported."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--variant", default=VARIANTS[0], choices=VARIANTS)
    return pre.parse_known_args()[0].variant


mi.set_variant(_variant_option())

import numpy as np  # noqa: E402
import onnx  # noqa: E402
from common import arith_ops, evals_per_second, write_json  # noqa: E402

import neural_brdf  # noqa: E402
import neural_brdf.renderers.mitsuba  # noqa: E402,F401  (registers neural_brdf and analytic_brdf)
from neural_brdf import graph  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "bsdf_bound.json"
NEURAL = "neural_brdf"
EVAL_PAIRS = 1 << 18


def scene(bsdf: dict, *, resolution: int = 256, spp: int = 64) -> dict:
    """The BSDF-bound scene (a dict for ``mi.load_dict``)."""
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": -1},
        "sensor": {
            # Mitsuba's orthographic camera sees [-1, 1]^2 of its local frame: the unit
            # sphere touches the four edges of the frame.
            "type": "orthographic",
            "to_world": T().look_at(
                origin=[0.0, 0.0, 5.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0]
            ),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {
                "type": "hdrfilm",
                "width": resolution,
                "height": resolution,
                "rfilter": {"type": "box"},
            },
        },
        "light": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "sphere": {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0, "bsdf": bsdf},
    }


# The yardsticks of issue 12: Mitsuba's built-in roughconductor, matched to the target
# where the target is a microfacet conductor, else gold's (GGX alpha 0.3, Au) for an
# isotropic target and brushed_ggx's (GGX alpha 0.15 x 0.45, Al) for an anisotropic one.
GOLD_REFERENCE = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3, "material": "Au"}
ANISO_REFERENCE = {
    "type": "roughconductor",
    "distribution": "ggx",
    "alpha_u": 0.15,
    "alpha_v": 0.45,
    "material": "Al",
}
MITSUBA_CONDUCTORS = {"Au", "Ag", "Al", "Cu"}  # named the same in Mitsuba's IOR list


def reference_bsdf(target: dict, anisotropic: bool = False) -> tuple[dict, bool]:
    """(Mitsuba's roughconductor dict, whether it is matched to the target)."""
    p = target.get("params") or {}
    if (
        target.get("model") == "microfacet"
        and p.get("fresnel") == "conductor"
        and p.get("material") in MITSUBA_CONDUCTORS
        and p.get("distribution", "ggx") in ("ggx", "beckmann")
        and not target.get("data")
    ):
        ref = {
            "type": "roughconductor",
            "distribution": p.get("distribution", "ggx"),
            "material": p["material"],
        }
        if "alpha_x" in p or "alpha_y" in p:
            ref["alpha_u"] = float(p.get("alpha_x", p.get("alpha", 0.3)))
            ref["alpha_v"] = float(p.get("alpha_y", p.get("alpha", 0.3)))
        else:
            ref["alpha"] = float(p.get("alpha", 0.3))
        return ref, True
    return dict(ANISO_REFERENCE if anisotropic else GOLD_REFERENCE), False


def loadavg() -> list[float]:
    with open("/proc/loadavg") as fh:
        return [float(x) for x in fh.read().split()[:3]]


def machine() -> dict:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "loadavg": loadavg(),
        "cores": cores,
        "drjit_threads": dr.thread_count(),
        "platform": platform.platform(),
    }


def render_once(sc, spp: int) -> float:
    t0 = time.perf_counter()
    img = mi.render(sc, spp=spp, seed=0)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0


def render_cost(
    bsdfs: dict[str, object],
    resolution: int,
    spp: int,
    repeats: int,
    images: dict[str, np.ndarray] | None = None,
) -> dict:
    """:func:`scene` for each BSDF (a dict or a loaded object); interleaved rounds,
    rotating order, best of, after one compiling render each (its image kept in
    ``images`` when given)."""
    before = loadavg()
    scenes = {n: mi.load_dict(scene(b, resolution=resolution, spp=spp)) for n, b in bsdfs.items()}
    names = list(scenes)
    for n in names:  # trace + compile
        img = mi.render(scenes[n], spp=spp, seed=0)
        if images is not None:
            images[n] = np.asarray(img)
    runs: dict[str, list[float]] = {n: [] for n in names}
    for r in range(repeats):
        for n in names[r % len(names) :] + names[: r % len(names)]:
            runs[n].append(render_once(scenes[n], spp))
        print("  cost round", r + 1, {n: round(v[-1], 3) for n, v in runs.items()}, flush=True)
    return {
        "resolution": resolution,
        "spp": spp,
        "repeats": repeats,
        "render_wall_s": runs,
        "best_s": {n: min(v) for n, v in runs.items()},
        "loadavg_before": before,
        "loadavg_after": loadavg(),
    }


def model_size(path: Path) -> dict:
    """MLP parameters and Linear FLOPs per evaluation from the ONNX initializers, and the
    lowered op list's instruction counts."""
    proto = onnx.load(str(path))
    init = {t.name: tuple(t.dims) for t in proto.graph.initializer}
    params = flops = 0
    for node in proto.graph.node:
        if node.op_type in ("Gemm", "MatMul"):
            for i in node.input[1:]:
                d = init.get(i)
                if d is None:
                    continue
                params += int(np.prod(d))
                if len(d) == 2:
                    flops += 2 * d[0] * d[1]
    prog = graph.lower(proto)
    counts = prog.count()
    return {
        "mlp_params": params,
        "linear_flops_per_eval": flops,
        "lowered_instructions": len(prog.instrs),
        "lowered_arith_flops": arith_ops(counts),
        "lowered_op_counts": dict(sorted(counts.items())),
        "table_entries": int(sum(t.size for t in prog.tables)),
    }


def first_render_child(bsdf_json: str, resolution: int, spp: int) -> None:
    """In a fresh process (the parent gives it an empty DRJIT_CACHE_DIR): print JSON."""
    sc = mi.load_dict(scene(json.loads(bsdf_json), resolution=resolution, spp=spp))
    first = render_once(sc, spp)
    second = render_once(sc, spp)
    print(
        json.dumps(
            {"first_render_s": first, "second_render_s": second, "compile_s": first - second}
        )
    )


def first_render(bsdf: dict, resolution: int, spp: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="drjit-cache-") as cache:
        env = dict(
            os.environ,
            DRJIT_CACHE_DIR=cache,
            PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
        )
        out = subprocess.run(
            [
                sys.executable,
                __file__,
                "--child",
                json.dumps(bsdf),
                "--resolution",
                str(resolution),
                "--spp",
                str(spp),
                "--variant",
                str(mi.variant()),
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
            check=False,
        )
    if out.returncode != 0:
        raise SystemExit(f"bsdf_bound: first-render subprocess failed:\n{out.stderr[-2000:]}")
    r = json.loads(out.stdout.strip().splitlines()[-1])
    r["loadavg_after"] = loadavg()
    return r


def eval_rate(bsdf: dict, seed: int = 0) -> float:
    from drjit_eval import evaluator

    rng = np.random.default_rng(seed)

    def hemi(n):
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2]) + 1e-3
        return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)

    return evals_per_second(evaluator(bsdf, hemi(EVAL_PAIRS), hemi(EVAL_PAIRS)), EVAL_PAIRS, 3)


def ort_rate(path: Path, batch: int = 1 << 16, repeats: int = 5, seed: int = 0) -> float:
    """onnxruntime evaluations/s of the file (one intra-op thread, best of ``repeats``)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    wi, wo = (rng.normal(size=(batch, 3)).astype(np.float32) for _ in range(2))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    feed = {"wi": wi, "wo": wo}
    sess.run(None, feed)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        sess.run(None, feed)
        best = min(best, time.perf_counter() - t0)
    return batch / best


def bench_model(label: str, path: Path, *, resolution: int, spp: int, repeats: int) -> dict:
    rt = neural_brdf.load(path)
    cfg = rt.config or {}
    aniso = (cfg.get("model") or {}).get("encoding") == "anisotropic"
    ref_name = "roughconductor"
    ref, matched = reference_bsdf(cfg.get("target") or {}, aniso)
    bsdfs = {NEURAL: {"type": "neural_brdf", "filename": str(path)}, ref_name: ref}
    before = machine()
    print(f"{label}: {path} vs {ref_name}", flush=True)
    first = {n: first_render(b, resolution, spp) for n, b in bsdfs.items()}
    for n, r in first.items():
        print(
            f"  {n:15s} fresh-cache first render {r['first_render_s']:.2f} s "
            f"(compile ~{r['compile_s']:.2f} s)",
            flush=True,
        )
    scenes = {n: mi.load_dict(scene(b, resolution=resolution, spp=spp)) for n, b in bsdfs.items()}
    names = list(scenes)
    for n in names:
        render_once(scenes[n], spp)  # trace + compile / cache hit
    runs = {n: [] for n in names}
    for r in range(repeats):
        order = names[r % len(names) :] + names[: r % len(names)]
        for n in order:
            runs[n].append(render_once(scenes[n], spp))
        print(
            f"  round {r + 1}/{repeats}: " + "  ".join(f"{n} {runs[n][-1]:.2f} s" for n in names),
            flush=True,
        )
    per_round = [a / b for a, b in zip(runs[NEURAL], runs[ref_name], strict=True)]
    rates = {n: eval_rate(b) for n, b in bsdfs.items()}
    ort_evals = ort_rate(path)
    m = cfg.get("model") or {}
    metrics_file = path.parent / "metrics.json"  # a training run's folder has one
    metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
    acc = metrics.get("accuracy") or {}
    return {
        "model": str(path),
        "reference": ref_name,
        "reference_matched": matched,
        "target": cfg.get("target"),
        "bsdfs": bsdfs,
        "rel_rmse_f_cos": acc.get("rel_rmse"),
        "train_steps": (cfg.get("train") or {}).get("steps"),
        "architecture": {
            "hidden": m.get("hidden"),
            "activation": m.get("activation"),
            "encoding": m.get("encoding"),
            "grid": m.get("grid"),
            "cosine_grid": m.get("cosine_grid"),
        },
        "size": model_size(path),
        "render_wall_s": runs,
        "best_s": {n: min(v) for n, v in runs.items()},
        "ratio": min(runs[NEURAL]) / min(runs[ref_name]),
        "ratio_per_round": {"min": min(per_round), "max": max(per_round)},
        "first_render_fresh_cache": first,
        "drjit_evals_per_s": rates,
        "onnxruntime_evals_per_s": ort_evals,
        "albedo_table_in_graph": (metrics.get("export") or {})
        .get("normalization", {})
        .get("in_graph"),
        "machine_before": before,
        "machine_after": machine(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="*", help="LABEL=PATH or PATH (label: its folder name)")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--variant", default=VARIANTS[0], choices=VARIANTS, help="Mitsuba variant")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        first_render_child(args.child, args.resolution, args.spp)
        return
    if not args.models:
        ap.error("give at least one model")
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    result.update(
        {
            "benchmark": "bsdf_bound",
            "variant": mi.variant(),
            "mitsuba": mi.__version__,
            "drjit": dr.__version__,
            "scene": "unit sphere filling an orthographic frame, constant emitter, path "
            "max_depth -1",
            "resolution": args.resolution,
            "spp": args.spp,
            "repeats": args.repeats,
            "statistic": "ratio = best wall time of neural_brdf over best of the reference, "
            "interleaved rounds after one compiling render each; first renders "
            "in fresh processes with an empty DRJIT_CACHE_DIR",
            "target_ratio": 3.0,
        }
    )
    models = result.setdefault("models", {})
    for spec in args.models:
        label, _, path = spec.rpartition("=")
        path = Path(path)
        label = label or path.parent.name
        models[label] = bench_model(
            label, path, resolution=args.resolution, spp=args.spp, repeats=args.repeats
        )
        write_json(args.out, result)
        r = models[label]
        print(
            f"{label}: {r['ratio']:.2f}x {r['reference']} (best over best), "
            f"{r['size']['mlp_params']} params, {r['size']['linear_flops_per_eval']} "
            f"FLOP/eval, load {r['machine_after']['loadavg'][0]:.2f}",
            flush=True,
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
