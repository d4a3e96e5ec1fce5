"""Issue 30's development sweep: textured recipes compared on fixed development pairs.

    python benchmarks/textured_sweep.py --jobs 8 --threads 2        # every variant, 2 seeds
    python benchmarks/textured_sweep.py --only base --only r128 --seeds 0

A choice of :data:`textured.SETTINGS` is made here, on the DEVELOPMENT textured teacher
(``write_teacher(kind, 512, seed 1)``, ``--kind``; principled by default), never on the
test set.  Each variant of :data:`VARIANTS` (changes to SETTINGS, plus ``grid_size``: the
lobes' feature grid over (theta_h, theta_d)) is trained with ``train_textured`` for each
training seed, normalised and exported as benchmarks/textured.py does
(``textured.train_textured_file``), and scored from its ONNX file on the same two fixed
sets of :data:`PAIRS` development pairs (seeds :data:`EVAL_SEEDS`; validation's draw, as
``textured.accuracy``): every model sees the same pairs, so the figures are paired.

Beside the figure, where the squared error lies (the principled's is heavy-tailed):
its share and relative RMSE on pairs whose uv lies within half a field texel of a
tile edge of the procedural maps (:data:`neural_brdf.measured.procedural.TILES`: every map
jumps there, and a bilinear field of R texels blurs the jump over one texel), by the
teacher's roughness at uv (terciles of the map's range), and by cos theta_i.

Runs go in parallel (``--jobs``, each ``--threads`` torch threads); the teacher is
evaluated in ``--variant`` (cuda_ad_rgb on a GPU machine: the many-core CPU trains, the
GPU serves the teacher).  Train seconds are each job's own and shared the machine with
the other jobs: they compare variants, not machines.  The JSON goes to
benchmarks/results/textured_sweep_dev.json; nothing asserts anything.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import write_json  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
PAIRS = 200_000
EVAL_SEEDS = (900, 901)  # the fixed development sets (as DEV_SWEEP's lr rows)
# name -> changes to textured.SETTINGS (grid_size: the lobes' (theta_h, theta_d) grid)
POOL_BEFORE = 1 << 21  # SETTINGS' pool when the first variants ran (now pool8m's 8M)
VARIANTS = {
    "base": {"pool": POOL_BEFORE},
    "r128": {"resolution": 128, "pool": POOL_BEFORE},
    "r128_8k": {"resolution": 128, "steps": 8000, "pool": POOL_BEFORE},
    "r256_8k": {"resolution": 256, "steps": 8000, "pool": POOL_BEFORE},
    "steps8k": {"steps": 8000, "pool": POOL_BEFORE},
    "r128_b16k": {"resolution": 128, "batch": 16384, "pool": POOL_BEFORE},
    "grid64": {"grid_size": 64, "pool": POOL_BEFORE},
    "h64": {"hidden": [64], "pool": POOL_BEFORE},
    # the loss's weight on large f cos (train.peak_weight 10, peak_cap 100 by default):
    # the figure is dominated by the largest values (grazing, sharp texels)
    "cap1k": {"peak_cap": 1000.0, "pool": POOL_BEFORE},
    "cap10k": {"peak_cap": 10000.0, "pool": POOL_BEFORE},
    "cap1k_w30": {"peak_cap": 1000.0, "peak_weight": 30.0, "pool": POOL_BEFORE},
    "r128_cap1k": {"resolution": 128, "peak_cap": 1000.0, "pool": POOL_BEFORE},
    # the pool: a bilinear field of R^2 texels needs pairs at every texel (2M pairs are
    # 512 per texel at 64^2, 32 at 256^2), and the teacher's calls are cheap next to steps
    "pool8m": {"pool": 1 << 23},
    "r128_pool8m": {"resolution": 128, "pool": 1 << 23},
    "r256_pool16m": {"resolution": 256, "pool": 1 << 24},
    # fresh pairs (texture.fresh_every): a pool of 2M drawn again every 256 steps, so
    # every pair of the 4000 steps' 33M is new
    "fresh": {"fresh_every": 256, "pool": POOL_BEFORE},
    "r256_fresh": {"resolution": 256, "fresh_every": 256, "pool": POOL_BEFORE},
    # the fine field learned as a sum of levels (texture.field_levels): 256, 128, 64
    "r128_l2_pool8m": {"resolution": 128, "field_levels": 2, "pool": 1 << 23},
    # the lobes' bound (texture.lobe_bound): one constant per lobe (the recipe's scale)
    # against the texels' bound (texel), one start each (results/textured_bound_dev.json)
    "scale_1start": {"lobe_bound": "scale", "starts": 1},
    "texel_1start": {"lobe_bound": "texel", "starts": 1},
    # the lobes' grazing factor (model.grazing_power, 1 in the compact recipe): a sharp GGX
    # texel grows like 1 / (cos_i cos_o) near the grazing mirror direction, where Smith's
    # masking is still about 1 (results/textured_grazing_dev.json)
    "gp1.5_1start": {"grazing_power": 1.5, "starts": 1},
    # grey lobes (texture.lobe_color: grey): one output per lobe, coloured by the rgb
    # weights; the network's last layer and softplus a third as wide (the render cost)
    "grey_1start": {"lobe_color": "grey", "starts": 1},
    # grey lobes leave room for more lobes at the same render cost: K = 6
    "grey_k6_1start": {"lobe_color": "grey", "lobes": 6, "starts": 1},
    "r256_l3_fresh": {
        "resolution": 256,
        "field_levels": 3,
        "fresh_every": 256,
        "pool": POOL_BEFORE,
    },
}


def _job(name: str, changes: dict, seed: int, args: dict) -> dict:
    import torch

    torch.set_num_threads(args["threads"])
    sys.argv = [sys.argv[0], "--variant", args["variant"]]  # bsdf_bound reads its variant
    import textured as bench

    from neural_brdf.measured.textured import TexturedMitsubaTarget

    teacher = TexturedMitsubaTarget(args["xml"], variant=args["variant"])
    settings = {**bench.SETTINGS, **changes, "seed": seed}
    if args["smoke"]:  # a dry run of the machinery: tiny budgets, figures meaningless
        # the projection and refit too: at the recipe's 512^2 x 256 teacher pairs and
        # 3000 refit steps they took 10 of a smoke run's 10.5 minutes
        settings.update(
            steps=20, pool=1 << 14, batch=1024, project=32, project_pairs=16, refit_steps=20
        )
    folder = Path(args["work"]) / f"{name}_s{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    path, fig = bench.train_textured_file(teacher, folder, settings)
    f = bench.OnnxFile(path, threads=args["threads"])
    rough = _roughness(Path(args["xml"]).parent)  # None for a teacher without the map
    sets = [where_error(f, teacher, args["pairs"], s, rough) for s in EVAL_SEEDS]
    return {
        "variant": name,
        "changes": changes,
        "seed": seed,
        "rel_rmse_fixed_sets": [s["rel_rmse"] for s in sets],
        "breakdown": sets,
        "val_rel_rmse": fig.get("val_rel_rmse"),
        "train_seconds": fig.get("train_seconds"),
        "pool_seconds": fig.get("pool_seconds"),
        "job_seconds": time.perf_counter() - t0,
        "file_bytes": path.stat().st_size,
    }


def _roughness(folder: Path):
    """The principled's roughness map (H, W) or None (another kind)."""
    import mitsuba as mi
    import numpy as np

    p = folder / "roughness.exr"
    if not p.is_file():
        return None
    a = np.asarray(mi.Bitmap(str(p)), np.float64)
    return a[..., 0] if a.ndim == 3 else a  # (H, W) float64


def error_share(mask, d2, r2) -> dict:
    """The pairs in ``mask``: their share of the pairs and of the squared error ``d2``,
    and their relative RMSE (``r2``: the reference's squares)."""
    import numpy as np

    return {
        "share_pairs": float(mask.mean()),
        "share_sq_error": float(d2[mask].sum() / d2.sum()),
        "rel_rmse": float(np.sqrt(d2[mask].sum() / max(r2[mask].sum(), 1e-300))),
    }


def where_error(f, teacher, n: int, seed: int, rough) -> dict:
    """The relative RMSE of f cos on validation-style pairs (``textured.accuracy``'s
    draw) and where its squared error lies (module doc)."""
    import numpy as np
    import textured as bench

    from neural_brdf.measured.procedural import TILES

    wi, wo, uv, ref = bench.validation_pairs(teacher, n, seed)
    half = n // 2
    got = f(wi, wo, uv)
    cos = wo[:, 2:3]
    d2 = (((got - ref) * cos) ** 2).sum(1)
    r2 = ((ref * cos) ** 2).sum(1)
    total = d2.sum()

    def part(mask) -> dict:
        return error_share(mask, d2, r2)

    # distance to the nearest tile edge, in units of the texture (every map jumps there)
    t = (uv * TILES) % 1.0
    edge = np.minimum(t, 1.0 - t).min(1) / TILES
    out = {"rel_rmse": float(np.sqrt(total / r2.sum())), "pairs": n}
    for r in (64, 128):
        out[f"near_edge_r{r}"] = part(edge < 0.5 / r)
    cos_i = wi[:, 2]
    out["cos_i"] = {
        f"{lo}-{hi}": part((cos_i >= lo) & (cos_i < hi))
        for lo, hi in ((0.0, 0.2), (0.2, 0.5), (0.5, 1.01))
    }
    out["sampled_wo"] = part(np.arange(n) >= half)
    if rough is not None:
        h, w = rough.shape
        r = rough[
            np.minimum((uv[:, 1] * h).astype(int), h - 1),
            np.minimum((uv[:, 0] * w).astype(int), w - 1),
        ]
        lo, hi = float(rough.min()), float(rough.max())
        cuts = lo + (hi - lo) * np.array([0.0, 1 / 3, 2 / 3, 1.0 + 1e-9])
        out["roughness"] = {
            f"{cuts[i]:.2f}-{min(cuts[i + 1], hi):.2f}": part((r >= cuts[i]) & (r < cuts[i + 1]))
            for i in range(3)
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", default="principled", choices=("principled", "roughplastic"))
    ap.add_argument("--only", action="append", default=[], help="a name of VARIANTS (repeat)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--job", action="append", default=[], help="NAME:SEED, one more run")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variant", default="llvm_ad_rgb", choices=("llvm_ad_rgb", "cuda_ad_rgb"))
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=RESULTS / "textured_sweep_dev.json")
    ap.add_argument("--smoke", action="store_true", help="tiny budgets: the machinery only")
    ap.add_argument(
        "--cost",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="after training: each file's render cost in textured.py's BSDF-bound scene, "
        "best of ROUNDS interleaved rounds (0: none)",
    )
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import mitsuba as mi

    from neural_brdf.measured.procedural import write_teacher

    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="nbrdf-sweep-")
        args.work = Path(tmp.name)
    xml = write_teacher(args.work / f"{args.kind}_dev", args.kind, size=512, seed=1)
    names = args.only or list(VARIANTS)
    jobs = [(n, s) for n in names for s in args.seeds] if args.only or not args.job else []
    for item in args.job:  # NAME:SEED, one more job
        n, _, s = item.partition(":")
        if n not in VARIANTS:
            ap.error(f"--job {item}: NAME is one of {', '.join(VARIANTS)}")
        jobs.append((n, int(s)))
    # the longest first, so that the last wave is short
    import textured as bench

    def work(name: str) -> int:
        s = {**bench.SETTINGS, **VARIANTS[name]}
        return s["steps"] * s["batch"] * (2 if s["hidden"][0] > 32 else 1)

    jobs.sort(key=lambda j: -work(j[0]))
    shared = {
        "xml": str(xml),
        "work": str(args.work),
        "threads": args.threads,
        "variant": args.variant,
        "smoke": args.smoke,
        "pairs": 2000 if args.smoke else PAIRS,
    }
    result = {
        "benchmark": "textured_sweep",
        "set": "dev",
        "teacher": f"write_teacher({args.kind}, size 512, seed 1)",
        "pairs": shared["pairs"],
        "smoke": args.smoke,
        "eval_seeds": list(EVAL_SEEDS),
        "variant": args.variant,
        "mitsuba": mi.__version__,
        "jobs": args.jobs,
        "threads_per_job": args.threads,
        "cpus": os.cpu_count(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "runs": [],
    }
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        futs = {pool.submit(_job, n, VARIANTS[n], s, shared): (n, s) for n, s in jobs}
        for fut in as_completed(futs):
            n, s = futs[fut]
            try:
                run = fut.result()
            except Exception as e:  # one failed variant must not lose the others
                run = {"variant": n, "seed": s, "error": f"{type(e).__name__}: {e}"}
            result["runs"].append(run)
            result["wall_seconds"] = time.perf_counter() - t0
            result["loadavg"] = list(os.getloadavg())  # the machine's, jobs included
            write_json(args.out, result)
            figs = run.get("rel_rmse_fixed_sets")
            print(
                f"{n} seed {s}: {figs or run.get('error')} ({run.get('train_seconds') or 0:.0f} s)",
                flush=True,
            )
    if args.cost > 0:  # the files' render cost, measured alone after the jobs
        result["render_cost"] = render_cost(result["runs"], args.work, args.cost, args.smoke)
        write_json(args.out, result)
        print("render cost (best, s):", result["render_cost"]["best_s"], flush=True)
    if tmp is not None:
        tmp.cleanup()
    return 0


def render_cost(runs: list[dict], work: Path, rounds: int, smoke: bool) -> dict:
    """Every scored run's file in benchmarks/textured.py's render-cost scene (its COST;
    bsdf_bound.render_cost: interleaved rounds, best of), keyed ``VARIANT_sSEED``, with
    the machine's load before and after."""
    import textured as bench

    cost = dict(bench.COST, resolution=64, spp=4) if smoke else dict(bench.COST)
    bsdfs: dict[str, object] = {}
    for r in sorted(runs, key=lambda r: (r["variant"], r["seed"])):
        if "rel_rmse_fixed_sets" in r:
            path = work / f"{r['variant']}_s{r['seed']}" / "model.onnx"
            bsdfs[f"{r['variant']}_s{r['seed']}"] = {"type": "neural_brdf", "filename": str(path)}
    return bench.bsdf_bound.render_cost(bsdfs, cost["resolution"], cost["spp"], rounds)


if __name__ == "__main__":
    sys.exit(main())
