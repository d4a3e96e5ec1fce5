"""Issue 19's peak figures: every analytic preset and its compact twin, trained as
shipped, then probed at and around the mirror direction (neural_brdf.validate.peak).

    python benchmarks/peak.py                         # every preset, both recipes (~1 h)
    python benchmarks/peak.py gold beckmann_smooth    # some presets
    python benchmarks/peak.py gold --legacy           # the old sqrt(theta_h) coordinate
    python benchmarks/peak.py --reuse                 # keep finished runs, re-probe

For each preset NAME with an analytic target, ``configs/mlp/NAME.yaml`` (the 3 x 64
SiLU network) and ``configs/NAME.yaml`` (the compact grid recipe) are trained
for their full step counts, exported and validated, without the HTML report.  The
validator's ``peak`` entry (model / target at the mirror direction and 0.01, 0.1, 0.3 and
1 degree off it, for theta_i 0, 10, 45 and 70 degrees, towards the normal, the horizon and
across the plane of incidence; anisotropic models in both tangent planes) is stored with
the overall relative RMSE of f cos.

``--legacy`` trains with the peak coordinate the encoding had before issue 19,
sqrt(theta_h / (pi/2)) (and sqrt of it in the anisotropic slope features), to show what
the peak check catches: labels get a ``legacy/`` prefix.  Results are merged by label
into benchmarks/results/peak.json after each model.  Nothing here asserts anything.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):  # run from a checkout without `pip install -e .`
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import torch  # noqa: E402
from common import write_json  # noqa: E402

from neural_brdf import config, validate  # noqa: E402
from neural_brdf import export as exp  # noqa: E402
from neural_brdf.train import data, loop  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "peak.json"
# the presets the training pairs' peak share was chosen on (2026-12-07, drawn uniform in
# (u_h, theta_d) over drawn half each way; the quickstart is the gold's target); the rest
# are held out
DEVELOPMENT = ("gold", "clay", "brushed_ggx", "beckmann_smooth")
CONFIGS = REPO / "configs"


def run_one(cfg: config.Config, run_dir: Path) -> dict:
    """Train, export and validate (the pipeline of ``neural-brdf train`` less the report)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    target = data.build_target(cfg.target)
    raw, training = loop.train(cfg, run_dir, resume=False, target=target)
    model, _ = exp.normalized_model(raw, cfg, target)
    info = exp.export(model, cfg, run_dir / "model.onnx", measure=validate.physics, target=target)
    report = validate.report(run_dir / "model.onnx", target=target, physics_report=info["physics"])
    report["training"] = training
    report["seconds"] = {"total": time.perf_counter() - t0}
    validate.write_json(report, run_dir / "metrics.json")
    return report


def summary(m: dict) -> dict:
    peak = m["peak"]
    by_offset: dict[str, float] = {}
    for row in peak["pairs"]:
        key = f"{row['offset_deg']:g}"
        by_offset[key] = max(by_offset.get(key, 0.0), row["error"])
    # the table: theta_i 45, in the plane towards the normal, first tangent plane
    row45 = {
        f"{r['offset_deg']:g}": r["ratio"]
        for r in peak["pairs"]
        if r["theta_deg"] == 45.0 and r["way"] == "normal" and r["phi_deg"] == 0.0
    }
    return {
        "peak_max_error": peak["value"],
        "peak_passed": peak["passed"],
        "peak_at": peak["at"],
        "peak_max_error_by_offset_deg": by_offset,
        "ratio_theta45_towards_normal": row45,
        "rel_rmse_f_cos": m["accuracy"]["rel_rmse"],
        "physics_passed": m["passed"],
        "reciprocity": m["checks"]["reciprocity"]["value"],
        "max_albedo": m["checks"]["max_albedo"]["value"],
        "steps": m["training"]["steps"],
        "seconds": m["seconds"]["total"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("presets", nargs="*", help="preset names (default: every analytic one)")
    ap.add_argument("--root", type=Path, default=REPO / "runs" / "peak-bench")
    ap.add_argument("--reuse", action="store_true", help="keep runs that have metrics.json")
    ap.add_argument("--recipes", default="compact,default", help="compact, default or both")
    ap.add_argument("--legacy", action="store_true", help="the old sqrt(theta_h) coordinate")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    known = sorted(
        p.stem for p in (CONFIGS / "mlp").glob("*.yaml") if not config.load(p).target.data
    )
    names = args.presets or known
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise SystemExit(f"peak: no analytic preset {unknown[0]!r}; known: {known}")
    torch.set_num_threads(2)
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    result.update(
        {
            "benchmark": "peak",
            "limit": config.Validation().peak_tol,
            "thetas_deg": list(validate.PEAK_THETAS),
            "offsets_deg": list(validate.PEAK_OFFSETS),
            "directions": list(validate.PEAK_DIRECTIONS),
            "statistic": "max over probed pairs and RGB of |f_model / f_target - 1|",
            "machine": f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f} at the start",
            "sets": {
                "development": list(DEVELOPMENT),
                "test": [n for n in known if n not in DEVELOPMENT],
            },
        }
    )
    models = result.setdefault("models", {})
    recipes = [r for r in ("compact", "default") if r in args.recipes.split(",")]
    for recipe in recipes:
        for name in names:
            # the compact recipe: the top-level presets; "default": the 3 x 64 networks
            # (configs/mlp/, the default recipe until issue 21)
            folder = CONFIGS if recipe == "compact" else CONFIGS / "mlp"
            cfg_path = folder / f"{name}.yaml"
            label = ("legacy/" if args.legacy else "") + f"{recipe}/{name}"
            run_dir = args.root / label
            metrics = run_dir / "metrics.json"
            if args.reuse and metrics.is_file():
                m = json.loads(metrics.read_text())
            else:
                print(f"{label}:", flush=True)
                # legacy: the pre-issue-19 peak coordinate sqrt(theta_h / (pi/2))
                sets = ["train.progress=false"] + ["model.peak_coordinate=sqrt"] * args.legacy
                m = run_one(config.load(cfg_path, sets), run_dir)
            models[label] = {
                "preset": name,
                "recipe": recipe,
                "encoding": "legacy sqrt(theta_h)" if args.legacy else "u_h",
                "config": cfg_path.relative_to(REPO).as_posix(),
                **summary(m),
            }
            s = models[label]
            print(
                f"  {label}: peak {100 * s['peak_max_error']:.2f} % "
                f"({'ok' if s['peak_passed'] else 'FAIL'}), rel_rmse "
                f"{100 * s['rel_rmse_f_cos']:.2f} %, {s['seconds']:.0f} s",
                flush=True,
            )
            write_json(args.out, result)
    bad = [k for k, v in models.items() if not v["peak_passed"]]
    print(f"peak: {len(models) - len(bad)} of {len(models)} within the limit")


if __name__ == "__main__":
    main()
