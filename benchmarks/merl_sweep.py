"""All 100 MERL materials, compact recipe and default network, in BRDF and render space.

    python benchmarks/merl_sweep.py                      # 100 materials, 2 worker processes
    python benchmarks/merl_sweep.py --materials chrome,brass --workers 1
    python benchmarks/merl_sweep.py --resume             # keep the finished materials
    python benchmarks/merl_sweep.py --figure             # only redraw the figure

Each material is the NBRDF network (Sztrajman et al. 2021) of its MERL measurement, made
reciprocal and baked at every MERL bin centre as in ``benchmarks/merl_fit.py`` (``--data
DIR`` holds ``nbrdf/merl_nbrdf_weights.npz``; layout in docs/merl.md).  It is fitted as a
user would, ``neural-brdf train compact/merl`` and ``neural-brdf train merl`` with
``target.data`` set, with the configs' own settings (``--set`` adds overrides, recorded).

Per material and recipe:

* BRDF space, on every measured bin centre (``validate.accuracy``): the relative RMSE of
  f cos(theta_o) and the NBRDF log error; the physics verdict of the export;
* render space (``neural_brdf.renderers.spheres``): a sphere under a lat-long sky with a sun,
  rendered by quadrature (no noise) with the exported model through onnxruntime and with
  the reference network; PSNR of the display values and mean HDR-FLIP;
* parameters, arithmetic operations per evaluation of the lowered graph, training seconds.

Results: benchmarks/results/merl_sweep.json (written atomically after every material, so
a stopped run keeps its finished materials); the figure docs/figures/merl_spheres.png (the
reference, compact and default spheres of a few materials); its table in docs/results.md
is generated from the JSON by tools/results_tables.py.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.common import add_fit_arguments, arith_ops, write_json  # noqa: E402

DATA = REPO / "data"  # default of --data
RESULTS = REPO / "benchmarks" / "results" / "merl_sweep.json"
FIGURE = REPO / "docs" / "figures" / "merl_spheres.png"
RECIPES = {"compact": "merl.yaml", "default": "mlp/merl.yaml"}  # configs/ files
# The figure's rows: diffuse to near-mirror.
FIGURE_MATERIALS = [
    "white-diffuse-bball",
    "blue-fabric",
    "red-plastic",
    "gold-metallic-paint",
    "specular-black-phenolic",
    "brass",
    "aluminium",
    "chrome",
]


def _npz(data: Path) -> Path:
    return data / "nbrdf" / "merl_nbrdf_weights.npz"


def fit(path: Path, recipe: str, run_dir: Path, overrides: list[str]) -> dict:
    from neural_brdf import config, pipeline
    from neural_brdf.train.model import RawBRDF

    cfg = config.load(
        REPO / "configs" / RECIPES[recipe],
        [f"target.data={path}", "train.progress=false", "train.threads=1"] + overrides,
    )
    report = pipeline.run(cfg, run_dir, overwrite=True)
    c, acc = report["checks"], report["accuracy"]
    return {
        "rel_rmse": acc["rel_rmse"],
        "nbrdf_log_error": acc["nbrdf_log_error"],
        "reciprocity": c["reciprocity"]["value"],
        "max_albedo": c["max_albedo"]["value"],
        "passed": report["passed"],
        "train_seconds": report["training"]["train_seconds"],
        "steps": report["training"]["steps"],
        "parameters": RawBRDF.parameter_count(cfg.model),
        "flops": _flops(run_dir / "model.onnx"),
    }


def _flops(path: Path) -> int:
    """Arithmetic operations per evaluation of the lowered graph, as bsdf_bound.py."""
    import onnx

    from neural_brdf import graph

    return arith_ops(graph.lower(onnx.load(str(path))).count())


def material(name: str, work: Path, data: Path, overrides: list[str]) -> dict:
    """Bake, fit both recipes, render; runs in a worker process (one thread each)."""
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from neural_brdf import runtime
    from neural_brdf.measured import merl
    from neural_brdf.renderers import spheres

    reference = merl.nbrdf_fixture(_npz(data), name, reciprocal=True)
    path = work / f"{name}.binary"
    if not path.is_file():
        merl.bake(reference, path)
    t0 = time.perf_counter()
    ref_img = spheres.render(reference)
    entry = {"render_seconds_reference": time.perf_counter() - t0}
    renders = {"reference": ref_img}
    for recipe in RECIPES:
        run_dir = work / "runs" / f"{name}-{recipe}"
        r = fit(path, recipe, run_dir, overrides)
        img = spheres.render(runtime.load(run_dir / "model.onnx").eval)
        r.update(spheres.metrics(ref_img, img))
        entry[recipe] = r
        renders[recipe] = img
    np.savez_compressed(work / f"{name}.spheres.npz", **renders)
    path.unlink()  # 35 MB each; the fits are done
    return entry


def figure(results: dict, work: Path, out: Path) -> None:
    """Rows of reference | compact | default spheres for FIGURE_MATERIALS (those rendered),
    each exposed by its reference, with the PSNR and FLIP of each fit under it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from neural_brdf.fileio import atomic_path
    from neural_brdf.renderers import spheres

    rows = [
        m
        for m in FIGURE_MATERIALS
        if m in results["materials"] and (work / f"{m}.spheres.npz").is_file()
    ]
    if not rows:
        return
    cols = ["reference"] + list(RECIPES)
    fig, axes = plt.subplots(
        len(rows), len(cols), figsize=(1.9 * len(cols), 1.9 * len(rows)), squeeze=False
    )
    for i, name in enumerate(rows):
        with np.load(work / f"{name}.spheres.npz") as z:
            imgs = {k: z[k] for k in cols}
        scale = spheres.exposure(imgs["reference"])
        for j, col in enumerate(cols):
            ax = axes[i, j]
            ax.imshow(spheres.display(imgs[col], scale), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if col == "reference":
                ax.set_ylabel(name, fontsize=7)
                label = "NBRDF (reference)"
            else:
                m = results["materials"][name][col]
                label = f"{col}: {m['psnr_db']:.1f} dB, FLIP {m['flip']:.3f}"
            ax.set_title(label, fontsize=6.5)
    fig.tight_layout()
    with atomic_path(out, suffix=".png", parents=True) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--materials", default="all", help="comma-separated names, or all")
    p.add_argument("--workers", type=int, default=2, help="processes (one thread each)")
    add_fit_arguments(
        p,
        work="nbrdf-merl-sweep",
        data=DATA,
        out=RESULTS,
        resume="the finished materials",
        data_holds="nbrdf/merl_nbrdf_weights.npz",
    )
    p.add_argument("--figure-out", type=Path, default=FIGURE)
    p.add_argument("--figure", action="store_true", help="only redraw the figure from --out")
    args = p.parse_args(argv)
    if args.figure:
        figure(json.loads(args.out.read_text()), args.work, args.figure_out)
        return 0
    from neural_brdf.measured import merl

    if not _npz(args.data).is_file():
        p.error(f"--data: {_npz(args.data)} does not exist (see docs/merl.md)")
    names = merl.nbrdf_names(_npz(args.data))
    if args.materials != "all":
        wanted = [m for m in args.materials.split(",") if m]
        unknown = [m for m in wanted if m not in names]
        if unknown:
            p.error(f"--materials: unknown {unknown}")
        names = wanted
    args.work.mkdir(parents=True, exist_ok=True)
    results = {"materials": {}}
    if args.resume and args.out.is_file():
        results = json.loads(args.out.read_text())
    load = os.getloadavg()
    results.update(
        {
            "date": time.strftime("%Y-%m-%d"),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "load_at_start": f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}",
            "reference": "NBRDF network of each MERL measurement (reciprocal average), "
            "baked at the bin centres for training and BRDF-space errors, evaluated directly "
            "for the reference render",
            "recipes": {k: f"configs/{v}" for k, v in RECIPES.items()},
            "overrides": args.overrides,
            "workers": args.workers,
            "render": "neural_brdf.renderers.spheres: 48 x 48 sphere, 32 x 64 lat-long sky "
            "with a sun, quadrature; PSNR of sRGB display values, mean HDR-FLIP",
        }
    )
    todo = [n for n in names if n not in results["materials"]]
    print(f"{len(todo)} materials to fit ({len(names) - len(todo)} done)", flush=True)
    with ProcessPoolExecutor(args.workers) as pool:
        futures = {n: pool.submit(material, n, args.work, args.data, args.overrides) for n in todo}
        for n, fut in futures.items():
            entry = fut.result()
            results["materials"][n] = entry
            c, d = entry["compact"], entry["default"]
            print(
                f"{n:28s} compact {100 * c['rel_rmse']:6.2f}% {c['psnr_db']:5.1f} dB "
                f"FLIP {c['flip']:.3f} | default {100 * d['rel_rmse']:6.2f}% "
                f"{d['psnr_db']:5.1f} dB FLIP {d['flip']:.3f}",
                flush=True,
            )
            write_json(args.out, results)
    load = os.getloadavg()
    results["load_at_end"] = f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    write_json(args.out, results)
    figure(results, args.work, args.figure_out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
