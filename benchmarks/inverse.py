"""Issue 20's figures: a neural BRDF fitted to images by inverse rendering, held out.

    python benchmarks/inverse.py                  # the full measurement (about an hour on 2 cores)
    python benchmarks/inverse.py --steps 40 --out /tmp/inverse.json   # a quick look

The material is not a preset: Mitsuba's ``roughconductor``, GGX alpha 0.2, copper
(``neural_brdf.inverse.scene.TRUTH``), on a unit sphere under a procedural environment
the project does not otherwise use (a sky gradient and four bright coloured blobs,
written as EXR by :func:`neural_brdf.inverse.scene.sky`).  Three views are rendered at
96 x 96 and 256 spp as the targets; a fourth direction is held out.

Fits, all from the same three images, the same loss (relative MSE) and the same
optimiser (``mi.ad.Adam``, warm-up and cosine decay), ``--steps`` steps, each rendering
every view with ``--primal-spp`` samples per pixel in the primal pass and ``--spp`` in the
gradient pass:

* ``neural``: the compact recipe (32 x 32 x 4 grid + 1 x 32 ReLU MLP) from its constant
  start (``images.start=constant``), through neural_brdf.pipeline.run on the generated
  ``fit.yaml`` (what ``neural-brdf train`` runs), which exports and validates model.onnx;
* ``neural_ggx_init``: the same with the default ``ggx`` start: a roughconductor fit
  (as many steps), the network trained on BRDF samples of that GGX (its BRDF error is
  recorded as ``start_brdf_rel_rmse``), then the image fit at ``images.start_lr_scale``
  times the learning rate, the grids at ``images.start_grid_lr_scale`` times that.

Every setting of the neural fits is a config key (``images.*``, docs/config.md), given
here as overrides of ``fit.yaml``; ``--set KEY=VALUE`` adds more (a validation split:
``--set images.validation_pixels=0.1``; its figures are in each fit's ``validation``).
* ``roughconductor``: Mitsuba's roughconductor parameters (alpha, RGB eta and k).

Measured for each: the held-out view rendered at 1024 spp (the neural fits from their
exported model.onnx, through the ``neural_brdf`` plugin) against the true material at
1024 spp, as linear PSNR over the sphere's pixels (peak: the reference's largest value
there) and relative RMSE; the noise floor is the true material against itself with
another seed.  The BRDF error is the relative RMSE of f cos(theta_o) over pairs with both
cosines above 0.5 (``neural_brdf.inverse.fit.brdf_pairs``: wi uniform on that cap, wo half
uniform on it, half from the true BRDF's sampler), against Mitsuba's own evaluation of
the true roughconductor.  Times are wall-clock seconds with the machine's load average.
Nothing here asserts anything; the JSON goes to benchmarks/results/inverse.json.
``--resume`` keeps what ``--work`` already holds (targets, the roughconductor fit, finished
runs) and resumes an interrupted neural fit from its checkpoint (its recorded fit time
is the checkpointed time plus the rest).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):  # run from a checkout without `pip install -e .`
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import numpy as np  # noqa: E402
from common import loadavg, write_json  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "inverse.json"
RESOLUTION, TARGET_SPP, HELDOUT_SPP = 96, 256, 1024
PAIRS = 1 << 17
PSNR_GOAL_DB, BRDF_GOAL = 35.0, 0.05


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300, help="optimiser steps of every fit")
    ap.add_argument("--spp", type=int, default=8, help="gradient-pass spp per view and step")
    ap.add_argument("--primal-spp", type=int, default=32, help="primal-pass spp per view and step")
    ap.add_argument("--init-train-steps", type=int, default=1500, help="GGX pre-training steps")
    ap.add_argument("--skip-init", action="store_true", help="no neural_ggx_init fit")
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override of the neural fits, e.g. images.validation_pixels=0.1",
    )
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "nbrdf-inverse")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep --work's targets, roughconductor fit and finished runs; resume the others",
    )
    args = ap.parse_args(argv)

    from neural_brdf import config, pipeline, runtime
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as inverse_example

    machine_before = {"loadavg": loadavg(), "cpus": os.cpu_count()}
    mi = inverse.use_variant("llvm_ad_rgb")
    scenes = args.work / "scenes"
    if not (args.resume and (scenes / "fit.yaml").is_file()):
        inverse_example.write(
            scenes, resolution=RESOLUTION, spp=TARGET_SPP, heldout=True, steps=args.steps
        )
    cfg = config.load(scenes / "fit.yaml", ["train.progress=false"])
    tree4, _ = inverse.read_scene(scenes / "view4.xml", "heldout")
    heldout = inverse.View(scenes / "view4.xml", scenes / "view4.exr", tree4, None, "path")
    truth_el = inverse.fit_element(tree4)
    mask = inverse.sphere_mask(heldout)
    ref = inverse.render_view(heldout, truth_el, spp=HELDOUT_SPP, seed=101)
    floor = inverse.render_view(heldout, truth_el, spp=HELDOUT_SPP, seed=202)
    truth = inverse.mitsuba_bsdf(truth_el)
    wi, wo = inverse.brdf_pairs(truth, PAIRS, seed=7)
    fc_true = inverse.mitsuba_f_cos(truth, wi, wo)

    def heldout_figures(bsdf_el) -> dict:
        img = inverse.render_view(heldout, bsdf_el, spp=HELDOUT_SPP, seed=303)
        return {
            "psnr_db": inverse.psnr_linear(ref, img, mask),
            "image_rel_rmse": inverse.image_rel_rmse(ref, img, mask),
        }

    result = {
        "benchmark": "inverse",
        "material": dict(inverse_example.TRUTH, bsdf="roughconductor"),
        "environment": "procedural sky gradient + 4 coloured blobs (inverse_example.sky), EXR",
        "views": {"fitted": 3, "held_out": 1, "resolution": RESOLUTION},
        "target_spp": TARGET_SPP,
        "heldout_spp": HELDOUT_SPP,
        "fit_spp_per_step": args.spp,
        "fit_primal_spp_per_step": args.primal_spp,
        "steps": args.steps,
        "overrides": args.overrides,
        "sphere_pixels": int(mask.sum()),
        "psnr_definition": "10 log10(peak^2 / MSE) of linear RGB over the sphere's pixels "
        "(centre ray on the sphere, 2-pixel erosion); peak = the reference's max there",
        "brdf_error_definition": "relative RMSE of f cos(theta_o), all RGB, over pairs with "
        "cos(theta_i) > 0.5 and cos(theta_o) > 0.5: wi uniform on that cap; wo half uniform "
        "on it, half from the true BRDF's sampler (kept when in the cap)",
        "brdf_pairs": int(len(wi)),
        "goals": {"heldout_psnr_db": PSNR_GOAL_DB, "brdf_rel_rmse": BRDF_GOAL},
        "noise_floor": {
            "psnr_db": inverse.psnr_linear(ref, floor, mask),
            "image_rel_rmse": inverse.image_rel_rmse(ref, floor, mask),
        },
        "fits": {},
    }

    # -- Mitsuba's roughconductor, same images, loss, optimiser and schedule
    views = inverse.read_views(cfg)
    rough_json = args.work / "roughconductor.json"
    if args.resume and rough_json.is_file():
        rough = json.loads(rough_json.read_text())
    else:
        rough = inverse.fit_roughconductor(
            views, cfg.train, spp=args.spp, primal_spp=args.primal_spp, steps=args.steps
        )
        write_json(rough_json, rough)
    rough_el = inverse.roughconductor_element(rough)
    fc_rough = inverse.mitsuba_f_cos(inverse.mitsuba_bsdf(rough_el), wi, wo)
    result["fits"]["roughconductor"] = {
        "parameters": {k: rough[k] for k in ("alpha", "eta", "k")},
        "true_parameters": {
            k: [float(x) for x in np.asarray(v.numpy()).reshape(-1)]
            for k, v in mi.traverse(truth).items()
        },
        "fit_seconds": rough["seconds"],
        "final_image_loss": rough["final_image_loss"],
        "brdf_rel_rmse": inverse.brdf_rel_rmse(fc_rough, fc_true),
        **heldout_figures(rough_el),
    }
    print(json.dumps(result["fits"]["roughconductor"], indent=1), flush=True)

    # -- the neural fits: the config's images section, set by overrides
    common = [
        "train.progress=false",
        f"images.spp={args.spp}",
        f"images.primal_spp={args.primal_spp}",
        *args.overrides,
    ]
    runs = [("neural", config.load(scenes / "fit.yaml", [*common, "images.start=constant"]))]
    if not args.skip_init:
        ggx = [*common, "images.start=ggx", f"images.start_train_steps={args.init_train_steps}"]
        runs.append(("neural_ggx_init", config.load(scenes / "fit.yaml", ggx)))

    def start_error(ckpt: Path) -> float | None:
        """The BRDF error of the network the GGX start hands to the image fit."""
        if not ckpt.is_file():
            return None
        import torch

        from neural_brdf.train.model import RawBRDF

        state = torch.load(ckpt, weights_only=True)
        raw = RawBRDF.from_config(config.from_dict(state["config"]).model)
        raw.load_state_dict(state["model"])
        with torch.no_grad():
            f = raw.eval()(torch.from_numpy(wi).float(), torch.from_numpy(wo).float())
        return inverse.brdf_rel_rmse(f.double().numpy() * wo[:, 2:3], fc_true)

    for label, run_cfg in runs:
        run_dir = args.work / label
        if args.resume and (run_dir / "metrics.json").is_file():
            metrics = json.loads((run_dir / "metrics.json").read_text())
        else:
            resume = args.resume and (run_dir / "ckpt.pt").is_file()
            metrics = pipeline.run(run_cfg, run_dir, resume=resume, overwrite=not resume)
        onnx = run_dir / "model.onnx"
        model = runtime.load(onnx)
        fc = np.asarray(model.eval(wi, wo), np.float64) * wo[:, 2:3]
        checks = metrics["checks"]
        tr = metrics["training"]
        result["fits"][label] = {
            "recipe": "compact: 32x32x4 grid + 1x32 ReLU",
            "fit_seconds": tr["train_seconds"],
            "init": tr.get("init"),
            "validation": tr.get("validation"),
            "coverage": tr.get("coverage", {}).get("figure"),
            "lr_factor": tr["lr_factor"],
            "grid_lr_scales": tr["grid_lr_scales"],
            "start_brdf_rel_rmse": start_error(run_dir / "init" / "ckpt.pt"),
            "export_validate_seconds": metrics["seconds"]["export"]
            + metrics["seconds"]["validate"],
            "final_image_loss": tr["final_image_loss"],
            "brdf_rel_rmse": inverse.brdf_rel_rmse(fc, fc_true),
            **heldout_figures(inverse.bsdf_element("neural_brdf", filename=str(onnx))),
            "reciprocity": checks["reciprocity"]["value"],
            "max_albedo": checks["max_albedo"]["value"],
            "min_value": checks["min_value"]["value"],
            "physics_passed": metrics["passed"],
            "raw_max_albedo": metrics["export"]["normalization"].get("raw_max_albedo"),
            "normalization_in_graph": metrics["export"]["normalization"].get("in_graph"),
            "fit_max_albedo_estimate": tr["final_max_albedo_estimate"],
        }
        print(label, json.dumps(result["fits"][label], indent=1), flush=True)

    result["machine"] = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "mitsuba": mi.__version__,
        "variant": mi.variant(),
        "cpus": os.cpu_count(),
        "loadavg_before": machine_before["loadavg"],
        "loadavg_after": loadavg(),
    }
    result["date"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
