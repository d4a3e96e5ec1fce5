"""A neural BRDF rendered by our ``neural_brdf`` plugin and, baked to an RGL ``.bsdf``
file, by Mitsuba's built-in ``measured`` plugin (llvm_ad_rgb): PSNR and time.

    python benchmarks/rgl_render.py
    python benchmarks/rgl_render.py --model runs/quickstart/model.onnx --spp 64 --ref-spp 1024

The model (``--model``, default: configs/quickstart.yaml, GGX alpha 0.3 gold, trained
for ``--steps`` steps into a temporary folder) is baked with ``neural_brdf.measured.rgl.bake``
(default resolutions; bake time and file size recorded) and read back to measure the
eval fidelity of the file against onnxruntime on uniform random pairs (relative RMSE of
f cos).  The scene is the material preview of the render helpers (two spheres on a
checkerboard floor under a sky and a key light, path tracer, max_depth 8).  Renders:

* ``neural`` and ``measured`` at ``--spp`` (same seed), wall time of each (after one
  render to compile the kernels);
* a reference: ``neural`` at ``--ref-spp``; and ``measured`` at ``--ref-spp``.

PSNR (sRGB display values): each ``--spp`` render against the neural reference (noise +
bias; the measured plugin's sampling follows the data's luminance), and the two
``--ref-spp`` renders against each other (the bake's bias, little noise).
Results: benchmarks/results/rgl_render.json (atomically).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):  # run from a checkout without `pip install -e .`
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import write_json  # noqa: E402

QUICKSTART = REPO / "configs" / "quickstart.yaml"
OUT = REPO / "benchmarks" / "results" / "rgl_render.json"
FIDELITY_PAIRS = 50000


def render_helpers():
    """The module with ``render_scene``, ``to_display`` and ``psnr``.  THE one place that
    knows where the render helpers live (neural_brdf.renderers.render).
    Importing neural_brdf.renderers.mitsuba also registers the ``neural_brdf`` plugin."""
    import neural_brdf.renderers.mitsuba as plugins

    try:
        from neural_brdf.renderers import render
    except ImportError:
        return plugins
    return render if hasattr(render, "render_scene") else plugins


def quickstart_model(tmp: Path, steps: int) -> Path:
    from neural_brdf import config, pipeline

    cfg = config.load(
        QUICKSTART,
        [f"train.steps={steps}", "train.progress=false", "train.threads=1", "train.eval_every=0"],
    )
    pipeline.run(cfg, tmp / "quickstart")
    return tmp / "quickstart" / "model.onnx"


def fidelity(model, baked) -> dict:
    rng = np.random.default_rng(0)

    def hemisphere(n):
        u = rng.random((n, 2))
        th, ph = np.arccos(1.0 - u[:, 0]), 2 * np.pi * u[:, 1]
        return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)

    wi, wo = hemisphere(FIDELITY_PAIRS), hemisphere(FIDELITY_PAIRS)
    cos = wo[:, 2:3]
    a, b = baked.eval(wi, wo) * cos, np.asarray(model.eval(wi, wo), np.float64) * cos
    rel = float(np.sqrt(np.sum((a - b) ** 2) / np.sum(b**2)))
    node_wi, node_wo = baked.node_pairs()
    c = node_wo[:, 2:3]
    na = baked.eval(node_wi, node_wo) * c
    nb = np.asarray(model.eval(node_wi, node_wo), np.float64) * c
    return {
        "rel_rmse_f_cos_uniform_pairs": rel,
        "pairs": FIDELITY_PAIRS,
        "rel_rmse_f_cos_at_nodes": float(np.sqrt(np.sum((na - nb) ** 2) / np.sum(nb**2))),
        "nodes": len(node_wi),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", help="model.onnx (default: a short quickstart training)")
    ap.add_argument("--steps", type=int, default=1000, help="quickstart training steps")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)

    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    import neural_brdf
    from neural_brdf.measured import rgl

    r = render_helpers()

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        model_path = Path(args.model) if args.model else quickstart_model(tmp, args.steps)
        model = neural_brdf.load(model_path)
        bsdf_path = tmp / "model.bsdf"
        t0 = time.perf_counter()
        baked = rgl.bake(model.eval, bsdf_path, description=f"neural-brdf {model_path.name}")
        bake_s = time.perf_counter() - t0
        size = os.path.getsize(bsdf_path)
        fid = fidelity(model, baked)
        bsdfs = {
            "neural": {"type": "neural_brdf", "filename": str(model_path)},
            "measured": {"type": "measured", "filename": str(bsdf_path)},
        }

        def render(name, spp, seed=0):
            t = time.perf_counter()
            img = r.render_scene(bsdfs[name], resolution=args.resolution, spp=spp, seed=seed)
            return img, time.perf_counter() - t

        timing, imgs = {}, {}
        for name in bsdfs:
            render(name, args.spp)  # compile
            imgs[name], timing[name] = render(name, args.spp)
        ref = {name: render(name, args.ref_spp, seed=1) for name in bsdfs}
        disp = {k: r.to_display(v) for k, v in imgs.items()}
        ref_disp = {k: r.to_display(v[0]) for k, v in ref.items()}

    result = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "loadavg": list(os.getloadavg()),
        "model": str(model_path) if args.model else f"quickstart, {args.steps} steps",
        "resolution": args.resolution,
        "spp": args.spp,
        "ref_spp": args.ref_spp,
        "bake": {"seconds": bake_s, "bytes": size, "resolutions": dict(rgl.DEFAULTS), **fid},
        "render_seconds": {k: v for k, v in timing.items()},
        "render_seconds_ref": {k: v[1] for k, v in ref.items()},
        "psnr_db": {
            "neural_vs_neural_ref": r.psnr(disp["neural"], ref_disp["neural"]),
            "measured_vs_neural_ref": r.psnr(disp["measured"], ref_disp["neural"]),
            "measured_ref_vs_neural_ref": r.psnr(ref_disp["measured"], ref_disp["neural"]),
            "neural_vs_measured_same_spp": r.psnr(disp["measured"], disp["neural"]),
        },
    }
    write_json(Path(args.out), result)
    p = result["psnr_db"]
    print(
        f"bake {bake_s:.1f} s, {size / 2**20:.2f} MiB, eval rel RMSE "
        f"{100 * fid['rel_rmse_f_cos_uniform_pairs']:.2f} %"
    )
    print(
        f"render {args.spp} spp: neural {timing['neural']:.2f} s, measured "
        f"{timing['measured']:.2f} s"
    )
    print(
        f"PSNR vs neural {args.ref_spp} spp: neural {p['neural_vs_neural_ref']:.2f} dB, "
        f"measured {p['measured_vs_neural_ref']:.2f} dB; measured {args.ref_spp} spp vs "
        f"neural {args.ref_spp} spp: {p['measured_ref_vs_neural_ref']:.2f} dB"
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
