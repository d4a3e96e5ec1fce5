"""Issue 12's per-preset figures: every compact recipe, its default counterpart and the
held-out targets, trained, validated and timed in the BSDF-bound scene.

    python benchmarks/compact_presets.py                      # everything (about 40 min)
    python benchmarks/compact_presets.py gold plastic          # some presets
    python benchmarks/compact_presets.py --reuse               # keep finished runs, re-time
    python benchmarks/compact_presets.py --root /tmp/cb --no-default
    python benchmarks/compact_presets.py gold --held-out-only

Per preset NAME (each ``configs/compact/NAME.yaml``):

* ``compact``: ``configs/compact/NAME.yaml`` trained, exported and validated as
  ``neural-brdf train compact/NAME`` does (progress bar off);
* ``default``: ``configs/NAME.yaml``, the default 3 x 64 SiLU network, trained for
  ``--default-steps`` (300) steps only: its render cost does not depend on how well it
  is trained (the graph is the same), and its full-length accuracy is in
  ``neural_presets.json``;
* ``held_out``: the compact recipe of a preset on targets it was not tuned on
  (:data:`HELD_OUT`: other alphas, other conductors), to show the recipe is not fitted
  to one material.

Every model then goes through :func:`bsdf_bound.bench_model`: the sphere-under-a-
constant-emitter scene, the render-time ratio against Mitsuba's built-in
``roughconductor`` (matched to the target when it is a microfacet conductor),
interleaved, best of ``--repeats``; the first render with an empty kernel cache; Dr.Jit
and onnxruntime evaluations/s; parameters, FLOPs and lowered instructions.  The
validator's figures (relative RMSE of f cos, reciprocity, max albedo, physics verdict)
come from each run's metrics.json.  Results are merged by label into
benchmarks/results/compact_presets.json (atomically) after each model; the
``targets`` entry states issue 12's bars (1% and 3x).  Nothing here asserts anything.
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

import bsdf_bound  # noqa: E402  (sets the llvm_ad_rgb variant)
from common import write_json  # noqa: E402

from neural_brdf import config, pipeline  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "compact_presets.json"
COMPACT = REPO / "configs"  # the compact presets: the top-level ones since issue 21
MLP = REPO / "configs" / "mlp"  # the 3 x 64 networks ("default" in the results)
TARGET_ERROR, TARGET_RATIO = 0.01, 3.0

# (label, compact preset, overrides): targets the recipes were not tuned on
HELD_OUT = [
    (
        "held_out/ggx_cu_0.15",
        "gold",
        ["target.params.alpha=0.15", "target.params.material=Cu"],
    ),
    ("held_out/ggx_al_0.5", "gold", ["target.params.alpha=0.5", "target.params.material=Al"]),
    (
        "held_out/beckmann_au_0.3",
        "beckmann_rough",
        ["target.params.alpha=0.3", "target.params.material=Au"],
    ),
    (
        "held_out/as_blue_50",
        "plastic",
        [
            "target.params.rd=[0.05,0.1,0.5]",
            "target.params.rs=0.08",
            "target.params.nu=50",
            "target.params.nv=50",
        ],
    ),
    (
        "held_out/as_brushed_200x20",
        "brushed_as",
        [
            "target.params.rd=0.3",
            "target.params.rs=0.3",
            "target.params.nu=20",
            "target.params.nv=200",
        ],
    ),
    (
        "held_out/brushed_ggx_cu_0.3x0.1",
        "brushed_ggx",
        [
            "target.params.alpha_x=0.3",
            "target.params.alpha_y=0.1",
            "target.params.material=Cu",
        ],
    ),
]


def train_run(cfg_path: Path, overrides: list[str], run_dir: Path, reuse: bool) -> dict:
    """Train, export and validate into ``run_dir``; returns its metrics.json."""
    metrics = run_dir / "metrics.json"
    if not (reuse and metrics.is_file()):
        cfg = config.load(cfg_path, ["train.progress=false", *overrides])
        t0 = time.perf_counter()
        pipeline.run(cfg, run_dir, overwrite=True)
        print(f"  trained {cfg_path.name} in {time.perf_counter() - t0:.0f} s", flush=True)
    return json.loads(metrics.read_text())


def validation(m: dict) -> dict:
    checks = m.get("checks") or {}
    return {
        "rel_rmse_f_cos": (m.get("accuracy") or {}).get("rel_rmse"),
        "passed": m.get("passed"),
        "checks": checks,
        "train_seconds": (m.get("seconds") or {}).get("train"),
        "steps": (m.get("training") or {}).get("steps"),
        "albedo_table_in_graph": ((m.get("export") or {}).get("normalization") or {}).get(
            "in_graph"
        ),
    }


def jobs(names: list[str], default: bool, held_out: bool, default_steps: int, only_held_out=False):
    for name in [] if only_held_out else names:
        yield f"compact/{name}", name, "compact", COMPACT / f"{name}.yaml", []
        if default:
            yield (
                f"default/{name}",
                name,
                "default",
                MLP / f"{name}.yaml",
                [f"train.steps={default_steps}"],
            )
    if held_out:
        for label, preset, overrides in HELD_OUT:
            if preset in names:
                yield label, preset, "held_out", COMPACT / f"{preset}.yaml", overrides


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("presets", nargs="*", help="compact preset names (default: all)")
    ap.add_argument("--root", type=Path, default=REPO / "runs" / "compact-bench")
    ap.add_argument("--reuse", action="store_true", help="keep runs that have metrics.json")
    ap.add_argument("--no-default", action="store_true", help="skip the default networks")
    ap.add_argument("--no-held-out", action="store_true", help="skip the held-out targets")
    ap.add_argument(
        "--held-out-only", action="store_true", help="only the held-out targets of the presets"
    )
    ap.add_argument("--default-steps", type=int, default=300)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    # the analytic presets (compact/merl.yaml fits measured data: benchmarks/merl_sweep.py)
    known = sorted(p.stem for p in MLP.glob("*.yaml") if not config.load(p).target.data)
    names = args.presets or known
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise SystemExit(f"compact_presets: no configs/{unknown[0]}.yaml")
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    result.update(
        {
            "benchmark": "compact_presets",
            "targets": {"rel_rmse_f_cos": TARGET_ERROR, "render_ratio": TARGET_RATIO},
            "scene": "bsdf_bound.scene: unit sphere filling an orthographic frame, constant "
            "emitter, path max_depth -1",
            "resolution": args.resolution,
            "spp": args.spp,
            "repeats": args.repeats,
            "default_steps": args.default_steps,
            "statistic": "ratio = best wall time of neural_brdf over best of Mitsuba's "
            "roughconductor, interleaved rounds after one compiling render each",
        }
    )
    models = result.setdefault("models", {})
    for label, preset, kind, cfg_path, overrides in jobs(
        names, not args.no_default, not args.no_held_out, args.default_steps, args.held_out_only
    ):
        print(f"{label}:", flush=True)
        run_dir = args.root / label
        m = train_run(cfg_path, overrides, run_dir, args.reuse)
        render = bsdf_bound.bench_model(
            label,
            run_dir / "model.onnx",
            resolution=args.resolution,
            spp=args.spp,
            repeats=args.repeats,
        )
        models[label] = {
            "preset": preset,
            "kind": kind,
            "config": cfg_path.relative_to(REPO).as_posix(),
            "overrides": overrides,
            "validation": validation(m),
            "render": render,
        }
        write_json(args.out, result)
        v = models[label]["validation"]
        print(
            f"  {100 * v['rel_rmse_f_cos']:.2f} % rel RMSE, {render['ratio']:.2f}x "
            f"roughconductor, load {render['machine_after']['loadavg'][0]:.2f}",
            flush=True,
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
