"""One step of an image fit, timed: the neural plugin's two evaluators against Mitsuba's
``roughconductor``, interleaved in one process (issue 29, item 4: speed).

    python benchmarks/image_step.py                        # about a minute on 2 cores
    python benchmarks/image_step.py --rounds 3 --out /tmp/step.json
    python benchmarks/image_step.py --variant cuda_ad_rgb --out results/cuda/image_step.json
    python benchmarks/image_step.py --capture lights --out results/image_step_lights.json

A step is what the image stage does per step, less its bookkeeping: for each of three
96 x 96 views of the unit sphere (``neural_brdf.inverse.scene``, its sky environment,
or with ``--capture lights`` the multi-light capture of ``benchmarks/images_any.py``: a
point or area light per view and no environment)
``mi.render`` with ``--primal-spp`` samples per pixel in the primal pass and ``--spp``
in the gradient pass, the fit's relative MSE against a target, ``dr.backward``; then one
``mi.ad.Adam`` step.  The target is Mitsuba's ``roughplastic`` (GGX alpha 0.15, the
issue's plastic), rendered once at 64 spp; its value does not matter here, only the
work.  Timed, each in its own scenes:

* ``roughconductor``: Mitsuba's own BSDF, its alpha and RGB eta and k trained, in Dr.Jit's
  symbolic mode (as ``neural_brdf.inverse.fit.fit_roughconductor`` runs it: the yardstick
  of the issue's 2x goal);
* ``neural_torch``: the ``neural_brdf_ad`` plugin (the compact recipe) with
  ``evaluator: torch``: torch evaluates the network, through ``dr.wrap``, in both passes;
* ``neural_graph``: the same with ``evaluator: graph``: the primal pass evaluates the
  RawBRDF's lowered ONNX graph in Dr.Jit with the live weights bound, the gradient pass
  torch, as before.

Where torch runs, it runs since 2026-12-05 the RawBRDF's network alone (the grids and
the MLP: ``RawBRDF.network``), and Dr.Jit its weight-free parts (``RawBRDF.encode``,
``RawBRDF.finish``) from their own lowered graphs (the JSON's ``torch_runs``:
"network"; before, torch ran the whole RawBRDF).

The plugin's default, ``evaluator: auto``, is whichever of the two the variant's entry
of ``neural_brdf.inverse.bsdf.AUTO`` names (chosen from this benchmark's primal passes;
the JSON records it).

Both neural variants run in ``evaluated_mode`` (the gradient pass needs it), and each
also times its primal pass alone (``mi.render`` without parameters, 3 views).  Rounds
interleave the variants, each built afresh in its round (one variant's scenes alive at a
time: a symbolic virtual call traces every BSDF instance alive) and warmed up by one
untimed step; each figure is the best of ``--rounds``.  Nothing here is tuned: there is
no setting to choose, so no development set and no test set; the plastic is the issue's
hard case.  The run of 2026-11-28 (evening) measured the grids' look-up in torch
through ``grid_sample`` (before it, the plugin handing torch its valid lanes only), and
the run of 2026-12-04 the encodings' column-major features: each a change of work, not of
any setting, checked by tests (tests/train/test_grid_lookup.py,
tests/inverse/test_inverse.py, tests/train/test_encodings.py); none changed a choice
(:data:`AUTO`'s primal passes still name the graph).  The JSON records the load average
before and after.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import loadavg, machine, write_json  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
RESOLUTION = 96
TARGET_SPP = 64


def sync(dr) -> None:
    """Wait for Dr.Jit's queue and, on a GPU, torch's (the gradient pass runs torch)."""
    import torch

    dr.sync_thread()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


class Case:
    """One variant's scenes, parameters and optimiser."""

    def __init__(self, mi, trees, targets, bsdf: ET.Element, keys, evaluated: bool):
        from neural_brdf.inverse import bsdf as ib
        from neural_brdf.inverse import fit as inverse

        self.scenes = [inverse.load_scene(Path("."), inverse.scene_text(t, bsdf)) for t in trees]
        self.params = [mi.traverse(inverse.fit_bsdf(s)) for s in self.scenes]
        self.keys = [k for k in self.params[0].keys() if keys(k)]
        self.opt = mi.ad.Adam(lr=1e-3)
        for k in self.keys:
            self.opt[k] = self.params[0][k]
        self.targets = targets
        self.mode = ib.evaluated_mode if evaluated else contextlib.nullcontext

    def step(self, mi, dr, seed: int, spp: int, primal_spp: int) -> float:
        from neural_brdf.inverse import fit as inverse

        t0 = time.perf_counter()
        with self.mode():
            for i, (scene, params) in enumerate(zip(self.scenes, self.params, strict=True)):
                for k in self.keys:
                    params[k] = self.opt[k]
                params.update()
                img = mi.render(scene, params, spp=primal_spp, spp_grad=spp, seed=seed + i)
                weight = dr.ones(mi.TensorXf, self.targets[i].shape)
                dr.backward(inverse.relative_mse(img, self.targets[i], weight))
            self.opt.step()
        sync(dr)
        return time.perf_counter() - t0

    def primal(self, mi, dr, seed: int, spp: int) -> float:
        t0 = time.perf_counter()
        with self.mode():
            for i, scene in enumerate(self.scenes):
                dr.eval(mi.render(scene, spp=spp, seed=seed + i))
        sync(dr)
        return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--spp", type=int, default=8, help="gradient pass (images.spp)")
    ap.add_argument("--primal-spp", type=int, default=16, help="primal pass (images.primal_spp)")
    ap.add_argument("--out", type=Path, default=RESULTS / "image_step.json")
    ap.add_argument(
        "--variant",
        default="llvm_ad_rgb",
        choices=("llvm_ad_rgb", "cuda_ad_rgb"),
        help="Mitsuba's variant (cuda_ad_rgb: torch runs the gradient pass on the GPU)",
    )
    ap.add_argument(
        "--capture",
        default="environment",
        choices=("environment", "lights"),
        help="the views' light: the sky, or a light per view (neural_brdf.inverse.scene)",
    )
    args = ap.parse_args(argv)

    import drjit as dr
    import torch

    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene

    mi = inverse.use_variant(args.variant)
    from neural_brdf.inverse import bsdf as ib

    torch.set_num_threads(inverse.TORCH_THREADS)  # as the fit runs it
    load_before = loadavg()
    with tempfile.TemporaryDirectory() as tmp:
        env = Path(tmp) / "sky.exr"
        scene.write_exr(env, scene.sky(64))
        trees = [
            ET.ElementTree(
                ET.fromstring(
                    scene.scene_xml(
                        az,
                        el,
                        resolution=RESOLUTION,
                        envmap=str(env),
                        emitters=scene.capture_emitters(args.capture, k),
                    )
                )
            )
            for k, (az, el) in enumerate(scene.VIEWS[:3])
        ]
        truth = inverse.bsdf_element("roughplastic", distribution="ggx", alpha=0.15)
        targets = [
            mi.TensorXf(
                mi.render(
                    inverse.load_scene(Path("."), inverse.scene_text(t, truth)),
                    spp=TARGET_SPP,
                    seed=k,
                )
            )
            for k, t in enumerate(trees)
        ]
        rough = inverse.bsdf_element("roughconductor", distribution="ggx", alpha=0.2)
        specs = {
            "roughconductor": (rough, inverse.ROUGH_BOUNDS.__contains__, False),
            **{
                f"neural_{ev}": (
                    inverse.bsdf_element(ib.PLUGIN, model=ib.COMPACT, evaluator=ev),
                    lambda k: k.startswith("raw."),
                    True,
                )
                for ev in ("torch", "graph")
            },
        }
        best = {name: {"step_s": math.inf, "primal_s": math.inf, "keys": []} for name in specs}
        for r in range(args.rounds):
            for name, (el, keys, evaluated) in specs.items():
                # one variant's scenes alive at a time: a symbolic virtual call traces
                # every BSDF instance alive, so the neural plugins would enter
                # roughconductor's kernels
                c = Case(mi, trees, targets, el, keys, evaluated)
                c.step(mi, dr, 0, args.spp, args.primal_spp)  # warm-up: kernel compilation
                c.primal(mi, dr, 0, args.primal_spp)
                seed = 1000 * (r + 1)
                b = best[name]
                b["step_s"] = min(b["step_s"], c.step(mi, dr, seed, args.spp, args.primal_spp))
                b["primal_s"] = min(b["primal_s"], c.primal(mi, dr, seed, args.primal_spp))
                b["keys"] = c.keys
                del c
                gc.collect()
            print(
                f"round {r + 1}: " + ", ".join(f"{n} {b['step_s']:.3f} s" for n, b in best.items()),
                file=sys.stderr,
            )
    base = best["roughconductor"]["step_s"]
    out = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(
            load_before,
            mitsuba=mi.__version__,
            drjit=dr.__version__,
            torch=torch.__version__,
            torch_threads=torch.get_num_threads(),
            **({"gpu": torch.cuda.get_device_name(0)} if args.variant.startswith("cuda") else {}),
        ),
        "variant": args.variant,
        "views": len(trees),
        "capture": args.capture,
        "resolution": RESOLUTION,
        "spp": args.spp,
        "primal_spp": args.primal_spp,
        "rounds": args.rounds,
        "target": "roughplastic, GGX alpha 0.15 (Mitsuba's defaults otherwise)",
        "trained": {n: b["keys"] for n, b in best.items()},
        "step_s": {n: b["step_s"] for n, b in best.items()},
        "primal_s": {n: b["primal_s"] for n, b in best.items()},
        "step_vs_roughconductor": {n: b["step_s"] / base for n, b in best.items()},
        "auto": ib.AUTO[args.variant],
        # since 2026-12-05 torch runs the RawBRDF's network alone where wi and wo track no
        # gradient (its weight-free parts in Dr.Jit, from their own lowered graphs)
        "torch_runs": "network",
        "graph_over_torch": {
            "step": best["neural_graph"]["step_s"] / best["neural_torch"]["step_s"],
            "primal": best["neural_graph"]["primal_s"] / best["neural_torch"]["primal_s"],
        },
    }
    write_json(args.out, out)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
