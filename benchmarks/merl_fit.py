"""Fit measured materials (MERL format) and compare with the ABC analytic fits (issue 4).

    python benchmarks/merl_fit.py                          # 8 materials, both sizes
    python benchmarks/merl_fit.py --materials chrome,brass --sizes default
    python benchmarks/merl_fit.py --table                  # print the README table

The MERL measurements themselves are not shipped here.  ``--data DIR`` (default
``data/`` in the checkout, git-ignored) must hold ``nbrdf/merl_nbrdf_weights.npz``, the
NBRDF networks (Sztrajman et al. 2021) fitted to all 100 of them (the authors' Keras
weights as numpy arrays, layout in docs/merl.md), and ``merl_abc_low2012_params.csv``, the
ABC fits (Low et al. 2012).  Each material is
that network evaluated at every MERL bin centre (reciprocal average, as
``neural_brdf.measured.merl.nbrdf_fixture(..., reciprocal=True)``) and written as a ``.binary``
file, which is then fitted with ``configs/merl.yaml`` exactly as a user would:
``neural-brdf train configs/merl.yaml --set target.data=material.binary``.

Per material and network size, on every measured bin centre (``validate.accuracy``):

* ``nbrdf_log_error``: mean |log(1 + f^ cos) - log(1 + f cos)|, the NBRDF loss;
* ``rel_rmse``: relative RMSE of f cos(theta_o), all channels;
* the same two figures for the ABC fit (Low et al. 2012, ``merl.abc_fixture``) of the same
  material.  Caveat: ABC was fitted to the real measurements and is scored here against
  the NBRDF network, so its error includes NBRDF's own error of fit;
* physics of the exported model: reciprocity error, max directional albedo, verdict;
* training time (the optimisation only) and the parameter count.

Sizes: ``default`` is configs/merl.yaml's network; ``nbrdf`` has two hidden layers of 20,
663 parameters, the closest to NBRDF's 675 (6-21-21-3) with our 8 input features.
Results: benchmarks/results/merl_fit.json (written atomically after every fit, so a long
run can be stopped and its finished fits kept; ``--resume`` skips them).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.common import add_fit_arguments, write_json  # noqa: E402

DATA = REPO / "data"  # default of --data
RESULTS = REPO / "benchmarks" / "results" / "merl_fit.json"
# Diffuse to near-mirror: a diffuse, a fabric, two plastics, a metallic paint, three metals.
MATERIALS = [
    "white-diffuse-bball",
    "blue-fabric",
    "red-plastic",
    "specular-black-phenolic",
    "gold-metallic-paint",
    "brass",
    "aluminium",
    "chrome",
]
SIZES = {"default": [], "nbrdf": ["model.hidden=[20,20]"]}


def material_file(name: str, folder: Path, data: Path) -> Path:
    from neural_brdf.measured import merl

    path = folder / f"{name}.binary"
    if not path.is_file():
        npz = data / "nbrdf" / "merl_nbrdf_weights.npz"
        merl.bake(merl.nbrdf_fixture(npz, name, reciprocal=True), path)
    return path


def fit(path: Path, size: str, run_dir: Path, threads: int, overrides: list[str]) -> dict:
    from neural_brdf import config, pipeline
    from neural_brdf.train.model import RawBRDF

    cfg = config.load(
        REPO / "configs" / "merl.yaml",
        [
            f"target.data={path}",
            "train.progress=false",
            f"train.threads={threads}",
            f"name={path.stem}-{size}",
        ]
        + SIZES[size]
        + overrides,
    )
    report = pipeline.run(cfg, run_dir, overwrite=True)  # a rerun replaces the last
    c, acc = report["checks"], report["accuracy"]
    return {
        "rel_rmse": acc["rel_rmse"],
        "nbrdf_log_error": acc["nbrdf_log_error"],
        "bins": acc["pairs"],
        "reciprocity": c["reciprocity"]["value"],
        "max_albedo": c["max_albedo"]["value"],
        "passed": report["passed"],
        "train_seconds": report["training"]["train_seconds"],
        "steps": report["training"]["steps"],
        "hidden": cfg.model.hidden,
        "parameters": RawBRDF.parameter_count(cfg.model),
    }


def abc_errors(name: str, path: Path, folder: Path) -> dict:
    from neural_brdf import validate
    from neural_brdf.measured import merl
    from neural_brdf.train import data

    fn = merl.abc_fixture(folder / "merl_abc_low2012_params.csv", name)
    acc = validate.accuracy(fn, data.MeasuredTarget.from_file(path), n=0, seed=0)
    return {"rel_rmse": acc["rel_rmse"], "nbrdf_log_error": acc["nbrdf_log_error"]}


def table(results: dict) -> str:
    sizes = [s for s in SIZES if any(s in m["neural"] for m in results["materials"].values())]
    head = ["material"]
    for s in sizes:
        head += [f"log err ({s})", f"rel RMSE ({s})"]
    head += ["log err (ABC)", "rel RMSE (ABC)"] + [f"train s ({s})" for s in sizes]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, m in results["materials"].items():
        row = [name]
        for s in sizes:
            n = m["neural"].get(s)
            row += (
                [f"{n['nbrdf_log_error']:.4f}", f"{100 * n['rel_rmse']:.2f}%"] if n else ["-", "-"]
            )
        row += [f"{m['abc']['nbrdf_log_error']:.4f}", f"{100 * m['abc']['rel_rmse']:.1f}%"]
        row += [
            f"{m['neural'][s]['train_seconds']:.0f}" if s in m["neural"] else "-" for s in sizes
        ]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--materials", default=",".join(MATERIALS))
    p.add_argument("--sizes", default=",".join(SIZES))
    p.add_argument("--threads", type=int, default=2, help="train.threads of each fit")
    add_fit_arguments(
        p,
        work="nbrdf-merl",
        data=DATA,
        out=RESULTS,
        resume="finished fits",
        data_holds="nbrdf/merl_nbrdf_weights.npz and merl_abc_low2012_params.csv",
    )
    p.add_argument("--table", action="store_true", help="print the table of --out and exit")
    args = p.parse_args(argv)
    if args.table:
        print(table(json.loads(args.out.read_text())))
        return 0
    materials = [m for m in args.materials.split(",") if m]
    sizes = [s for s in args.sizes.split(",") if s]
    unknown = [s for s in sizes if s not in SIZES]
    if unknown:
        p.error(f"--sizes: unknown {unknown}; known: {list(SIZES)}")
    args.work.mkdir(parents=True, exist_ok=True)
    results = {"materials": {}}
    if args.resume and args.out.is_file():
        results = json.loads(args.out.read_text())
    results.update(
        {
            "reference": "NBRDF network of each MERL measurement, baked at the bin "
            "centres (reciprocal average)",
            "config": "configs/merl.yaml",
            "overrides": args.overrides,
            "threads": args.threads,
            "cores": os.cpu_count(),
            "metric_pairs": "every measured bin centre",
        }
    )
    for name in materials:
        path = material_file(name, args.work, args.data)
        entry = results["materials"].setdefault(name, {"neural": {}})
        entry["abc"] = abc_errors(name, path, args.data)
        for size in sizes:
            if size in entry["neural"]:
                continue
            entry["neural"][size] = fit(
                path, size, args.work / "runs" / f"{name}-{size}", args.threads, args.overrides
            )
            n = entry["neural"][size]
            print(
                f"{name:24s} {size:8s} log {n['nbrdf_log_error']:.4f} (ABC "
                f"{entry['abc']['nbrdf_log_error']:.4f})  rel {100 * n['rel_rmse']:.2f}% "
                f"(ABC {100 * entry['abc']['rel_rmse']:.1f}%)  {n['train_seconds']:.0f} s",
                flush=True,
            )
            write_json(args.out, results)
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
