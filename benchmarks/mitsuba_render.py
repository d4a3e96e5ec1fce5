"""Render time of the neural BSDF against Mitsuba's built-in roughconductor (llvm_ad_rgb).

    python benchmarks/mitsuba_render.py
    python benchmarks/mitsuba_render.py --model runs/quickstart/model.onnx --repeats 9

The scene is the material preview of ``neural_brdf.renderers.render.preview_scene`` (two spheres
with the BSDF on a diffuse checkerboard floor, a procedural sky and a directional key
light; path tracer, max_depth 8).  Three BSDFs render it at the same resolution and spp:

* ``neural_brdf`` with ``--model`` (default: configs/quickstart.yaml trained into a
  temporary directory with train.threads=1: GGX alpha = 0.3 gold, a 64-64-64 MLP);
* Mitsuba's ``roughconductor``, GGX alpha = 0.3, material Au (the quickstart target,
  with Mitsuba's separable Smith G instead of the height-correlated one);
* ``analytic_brdf`` with the model's target (the same ONNX interpreter as the neural
  plugin, running the analytic model's exported graph).

Each scene is loaded once (``load_s``; the neural plugin reads the sampling lobe from
the file's metadata), then rendered once to trace and compile (``first_s``; the Dr.Jit
kernel cache under ~/.drjit can shorten it on a later run of this script).  Then
``--repeats`` rounds render every BSDF once each, in an order that rotates from round to
round, so that load from other processes on a shared machine hits all of them alike.
Every render records its wall time (tracing the megakernel in Python included), its
process CPU time, and the execution time of its JIT kernels (``dr.kernel_history``).

The headline is ``ratio``: the best wall time of the neural BSDF over the best of
roughconductor (the issue's target: <= 3).  The per-round ratios (min, median, max)
show the spread; the same ratios of CPU and kernel time are given too.

``--modes symbolic wavefront`` also times Dr.Jit's wavefront mode (JitFlag
SymbolicLoops and SymbolicCalls off: each path vertex runs as separate kernels).  The
neural and analytic_brdf renders share a seed, so their PSNR (sRGB display values) is
reported too.  Results go to benchmarks/results/mitsuba_render.json (atomically).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import statistics
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

mi.set_variant("llvm_ad_rgb")

from common import write_json  # noqa: E402

import neural_brdf  # noqa: E402
from neural_brdf import config, pipeline  # noqa: E402
from neural_brdf.fileformat import lobe as lobe_format  # noqa: E402
from neural_brdf.renderers import render as nbr  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "mitsuba_render.json"
QUICKSTART = REPO / "configs" / "quickstart.yaml"
MODES = ("symbolic", "wavefront")
NEURAL, BUILTIN, ANALYTIC = "neural_brdf", "roughconductor", "analytic_brdf"


@contextlib.contextmanager
def execution_mode(mode: str):
    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    saved = [dr.flag(f) for f in flags]
    for f in flags:
        dr.set_flag(f, mode == "symbolic")
    try:
        yield
    finally:
        for f, v in zip(flags, saved):
            dr.set_flag(f, v)


def quickstart_model(tmp: Path) -> Path:
    cfg = config.load(QUICKSTART, ["train.progress=false", "train.threads=1"])
    pipeline.run(cfg, tmp / "quickstart")
    return tmp / "quickstart" / "model.onnx"


def bsdfs_for(model: Path) -> dict:
    target = neural_brdf.load(model).config.get("target") or {}
    out = {
        NEURAL: {"type": "neural_brdf", "filename": str(model)},
        BUILTIN: {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3, "material": "Au"},
    }
    if target.get("model") and not target.get("data"):
        out[ANALYTIC] = {
            "type": "analytic_brdf",
            "model": target["model"],
            "params": json.dumps(target.get("params") or {}),
        }
    return out


def timed(scene, spp: int) -> tuple[dict, object]:
    """One render: wall, process CPU and JIT kernel seconds, and the image."""
    dr.kernel_history()  # clear
    w, c = time.perf_counter(), time.process_time()
    img = mi.render(scene, spp=spp, seed=0)
    dr.eval(img)
    dr.sync_thread()
    w, c = time.perf_counter() - w, time.process_time() - c
    kernels = (
        sum(
            k.get("execution_time", 0.0)
            for k in dr.kernel_history()
            if k["type"] == dr.KernelType.JIT
        )
        / 1000.0
    )  # ms -> s
    return {"wall_s": w, "cpu_s": c, "kernel_s": kernels}, img


def bench_mode(scenes: dict, spp: int, repeats: int) -> tuple[dict, dict]:
    names = list(scenes)
    runs = {n: [] for n in names}
    first, images = {}, {}
    for n in names:
        t, _ = timed(scenes[n], spp)
        first[n] = t["wall_s"]
        print(f"  {n:15s} first render {first[n]:7.2f} s", flush=True)
    for r in range(repeats):
        order = names[r % len(names) :] + names[: r % len(names)]
        for n in order:
            t, images[n] = timed(scenes[n], spp)
            runs[n].append(t)
        print(
            f"  round {r + 1}/{repeats}: "
            + "  ".join(f"{n} {runs[n][-1]['wall_s']:.2f} s" for n in names),
            flush=True,
        )
    return {"first_render_s": first, "renders": runs, "ratio": ratios(runs)}, images


def ratios(runs: dict) -> dict:
    """neural / roughconductor: of the best times, and per round (min, median, max)."""
    out = {}
    for key in ("wall_s", "cpu_s", "kernel_s"):
        a = [t[key] for t in runs[NEURAL]]
        b = [t[key] for t in runs[BUILTIN]]
        per_round = [x / y for x, y in zip(a, b)]
        out[key.removesuffix("_s")] = {
            "best_over_best": min(a) / min(b),
            "per_round_min": min(per_round),
            "per_round_median": statistics.median(per_round),
            "per_round_max": max(per_round),
            "best_s": {NEURAL: min(a), BUILTIN: min(b)},
            "median_s": {NEURAL: statistics.median(a), BUILTIN: statistics.median(b)},
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, help="an exported model (default: train quickstart)")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--modes", nargs="+", choices=MODES, default=["symbolic"])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    with tempfile.TemporaryDirectory() as tmp:
        model = args.model or quickstart_model(Path(tmp))
        stored = lobe_format.from_metadata(neural_brdf.load(model).metadata)
        bsdfs = bsdfs_for(model)
        scenes, load_s = {}, {}
        for n, b in bsdfs.items():
            t0 = time.perf_counter()
            scenes[n] = mi.load_dict(nbr.preview_scene(b, resolution=args.resolution, spp=args.spp))
            load_s[n] = time.perf_counter() - t0
        results, psnr = {}, None
        for mode in args.modes:
            print(f"{mode}:", flush=True)
            with execution_mode(mode):
                results[mode], images = bench_mode(scenes, args.spp, args.repeats)
            if psnr is None and ANALYTIC in images:
                psnr = nbr.psnr(nbr.to_display(images[NEURAL]), nbr.to_display(images[ANALYTIC]))

    headline = results[args.modes[0]]["ratio"]["wall"]
    result = {
        "benchmark": "mitsuba_render",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "variant": mi.variant(),
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "machine": {
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "load_average_1min_at_end": os.getloadavg()[0],
        },
        "scene": "neural_brdf.renderers.render.preview_scene (path, max_depth 8)",
        "resolution": args.resolution,
        "spp": args.spp,
        "repeats": args.repeats,
        "model": str(
            args.model or "configs/quickstart.yaml (train.threads=1), trained by this script"
        ),
        "bsdfs": bsdfs,
        "sampling_lobe": stored,
        "load_s": load_s,
        "modes": results,
        "ratio": headline["best_over_best"],
        "ratio_mode": args.modes[0],
        "ratio_per_round": {k: headline[f"per_round_{k}"] for k in ("min", "median", "max")},
        "target_ratio": 3.0,
        "psnr_neural_vs_analytic_db": psnr,
        "statistic": "ratio = best wall time of neural_brdf over best of roughconductor, "
        "renders interleaved in rotating order, after one compiling render each",
    }
    write_json(args.out, result)
    for mode in args.modes:
        r = results[mode]["ratio"]
        print(
            f"{mode}: neural / roughconductor = {r['wall']['best_over_best']:.2f}x wall "
            f"(per round {r['wall']['per_round_min']:.2f}-{r['wall']['per_round_max']:.2f}), "
            f"{r['cpu']['best_over_best']:.2f}x CPU, {r['kernel']['best_over_best']:.2f}x "
            f"kernel time"
        )
    print(f"PSNR neural vs analytic: {'n/a' if psnr is None else f'{psnr:.2f} dB'}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
