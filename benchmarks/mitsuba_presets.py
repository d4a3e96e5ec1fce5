"""PSNR of neural against analytic renders in Mitsuba 3, for every preset in configs/.

    python benchmarks/mitsuba_presets.py                        # train every preset
    python benchmarks/mitsuba_presets.py --runs runs/bench      # reuse runs/bench/NAME/
    python benchmarks/mitsuba_presets.py gold clay --steps 500 --images /tmp/previews

Each preset with an analytic target (configs/NAME.yaml; ``defaults`` and measured-data
targets are skipped) gets a model: ``RUNS/NAME/model.onnx`` when ``--runs`` has one,
else its config is trained into a temporary directory with train.threads=1 (the
machine is shared) and, with ``--steps N``, train.steps=N (recorded in the JSON: fewer
steps than the preset's own mean a less accurate network, so a lower PSNR).

Three renders of ``neural_brdf.renderers.render.preview_scene`` (llvm_ad_rgb, ``--spp``,
``--resolution``) per preset: the neural model and the analytic target
(``analytic_brdf``) with seed 0, and the analytic target again with seed 1.  The JSON
gives, in dB on sRGB display values:

* ``psnr_db``: neural against analytic, both seed 0: what ``neural-brdf render
  --reference`` reports.  Both draw the same random numbers, so where their sampling
  lobes agree their paths coincide and the Monte Carlo noise largely cancels; where
  the lobes differ, it does not;
* ``psnr_noise_floor_db``: analytic seed 0 against analytic seed 1: independent noise
  alone at this spp.  A ``psnr_db`` above it means that neural and analytic differ by
  less than two independent renders of the same material.

``--images DIR`` keeps each side-by-side preview (neural | analytic | error x10) as
DIR/NAME.png.  Results go to benchmarks/results/mitsuba_presets.json (atomically).
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

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):  # run from a checkout without `pip install -e .`
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")

from common import write_json  # noqa: E402

import neural_brdf  # noqa: E402
from neural_brdf import config, pipeline  # noqa: E402
from neural_brdf.fileformat import lobe as lobe_format  # noqa: E402
from neural_brdf.physics import lobe_fit  # noqa: E402
from neural_brdf.renderers import render as nbr  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "mitsuba_presets.json"
SKIP = {"defaults"}


def presets(names: list[str]) -> dict:
    """name -> config of every preset with an analytic target (or of ``names``)."""
    paths = (
        [REPO / "configs" / f"{n}.yaml" for n in names]
        if names
        else sorted(p for p in (REPO / "configs").glob("*.yaml") if p.stem not in SKIP)
    )
    out = {}
    for path in paths:
        cfg = config.load(path)
        if cfg.target.data is None:
            out[path.stem] = path
    return out


def model_for(
    name: str, cfg_path: Path, runs: Path | None, steps: int | None, tmp: Path
) -> tuple[Path, dict]:
    """An exported model of the preset, and how it was obtained."""
    if runs is not None and (runs / name / "model.onnx").is_file():
        model = runs / name / "model.onnx"
        cfg = neural_brdf.load(model).config
        return model, {"source": f"reused {model}", "steps": cfg["train"]["steps"]}
    sets = ["train.progress=false", "train.threads=1"]
    if steps is not None:
        sets.append(f"train.steps={steps}")
    cfg = config.load(cfg_path, sets)
    report = pipeline.run(cfg, tmp / name)
    return tmp / name / "model.onnx", {
        "source": "trained",
        "steps": cfg.train.steps,
        "train_s": report["seconds"]["train"],
        "rel_rmse": report["accuracy"]["rel_rmse"],
    }


def sampling_lobe(model: Path, metadata: dict) -> dict:
    """The lobe the plugin samples: stored by the exporter, or fitted at load (files
    exported before the exporter stored it) as the plugin does."""
    stored = lobe_format.from_metadata(metadata)
    return {
        "sampling_lobe": stored or lobe_fit.fit_onnx(model),
        "lobe_source": "metadata" if stored else "fitted at load",
    }


def renders(model: Path, target: dict, spp: int, resolution: int) -> dict:
    """The three display images: neural, analytic (seed 0), analytic (seed 1)."""
    ref = nbr.analytic_bsdf(target)
    bsdfs = {
        "neural": {"type": "neural_brdf", "filename": str(model)},
        "analytic": ref,
        "analytic_seed1": ref,
    }
    return {
        k: nbr.to_display(
            nbr.render_scene(b, resolution=resolution, spp=spp, seed=int(k.endswith("seed1")))
        )
        for k, b in bsdfs.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("presets", nargs="*", help="names in configs/ (default: all)")
    ap.add_argument("--runs", type=Path, help="reuse RUNS/NAME/model.onnx where present")
    ap.add_argument("--steps", type=int, help="train.steps for presets trained here")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--images", type=Path, help="write DIR/NAME.png side-by-side previews")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, cfg_path in presets(args.presets).items():
            model, how = model_for(name, cfg_path, args.runs, args.steps, Path(tmp))
            brdf = neural_brdf.load(model)
            target = brdf.config["target"]
            t0 = time.perf_counter()
            img = renders(model, target, args.spp, args.resolution)
            render_s = time.perf_counter() - t0
            if args.images:
                nbr.write_png(
                    args.images / f"{name}.png", nbr.side_by_side(img["neural"], img["analytic"])
                )
            rows.append(
                {
                    "preset": name,
                    "target": target,
                    **how,
                    "psnr_db": nbr.psnr(img["neural"], img["analytic"]),
                    "psnr_noise_floor_db": nbr.psnr(img["analytic"], img["analytic_seed1"]),
                    **sampling_lobe(model, brdf.metadata),
                    "render_s": render_s,
                }
            )
            r = rows[-1]
            print(
                f"{name:16s} PSNR {r['psnr_db']:6.2f} dB  (noise floor "
                f"{r['psnr_noise_floor_db']:6.2f} dB)  steps {r['steps']}  "
                f"renders {render_s:5.1f} s",
                flush=True,
            )
    write_json(
        args.out,
        {
            "benchmark": "mitsuba_presets",
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "variant": mi.variant(),
            "mitsuba": mi.__version__,
            "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count()},
            "scene": "neural_brdf.renderers.render.preview_scene (path, max_depth 8)",
            "spp": args.spp,
            "resolution": args.resolution,
            "steps_override": args.steps,
            "runs": None if args.runs is None else str(args.runs),
            "psnr": "dB on sRGB display values in [0, 1]",
            "presets": rows,
        },
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
