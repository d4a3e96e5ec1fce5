"""The blend start's weight against its conductor's F0: how flat the views leave it.

    python benchmarks/images_valley.py      # about 2 minutes on 2 cores
    python benchmarks/images_valley.py --material satin_blend   # the test set's blend

A ``blend`` start (a diffuse and a GGX conductor, ``neural_brdf.inverse.starts``) draws
its specular highlight as weight x F(theta_d), and F rises from F0 to 1 only near grazing:
away from the rim, a smaller weight with a brighter F0 draws the same image.  This runs
the images fit of ``benchmarks/images_any.py`` on the development set's
``glazed_blend`` (0.5 diffuse + 0.5 aluminium GGX 0.15; Mitsuba's own BSDF, the truth),
then walks along that valley from the fitted start: for each weight w, F0 = F0_fit w_fit
/ w and the diffuse reflectance = r_fit (1 - w_fit) / (1 - w) (both products kept, the
roughness and the edge tint as fitted), and scores each material by the fit's loss on
the views (the relative MSE over the object's pixels, :mod:`neural_brdf.inverse.views`)
without the render's noise: the mean over pixels of w_p (x1 - y)(x2 - y), two renders of
:data:`SPP` samples with independent seeds (the estimate the split uses).  The truth is
scored the same way.  Each material is scored under :data:`SEEDS` sets of seeds, the
same sets for all, and the figure of a point is its loss minus the fitted start's under
the same seeds, with the standard error of that paired difference over the sets; the
fitted start's own loss under each set is recorded too (the estimate's spread, which the
pairing removes).  What it shows: whether the views pin the weight, and so the
specular at grazing, which the BRDF error over the observed domain holds
(docs/inverse-design.md, "Images of any material": "How flat the valley is").  It
chooses nothing, so it may run on the test set's ``satin_blend`` (0.65 diffuse + 0.35
silver GGX 0.1, fitted under the test set's environment) as well.  Writes
benchmarks/results/images_valley_<set>.json.
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

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):  # run from a checkout without `pip install -e .`
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import numpy as np  # noqa: E402
from common import write_json  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
# the blends of benchmarks/images_any.py's two sets, and the set each belongs to
MATERIALS = {"glazed_blend": "dev", "satin_blend": "test"}
WEIGHTS = (0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75)  # and the fitted one
SPP = 256  # each of the two renders per view and material
SEEDS = 4  # seed sets, the same for every material (paired differences)


def scored_loss(views, element, seed: int) -> float:
    """The noise-free relative MSE of ``element`` over the views' object pixels: the
    estimate the split uses (:func:`neural_brdf.inverse.starts.noise_free_loss`)."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    inverse.prepare_views(views, element)
    return starts.noise_free_loss(views, [v.object for v in views], spp=SPP, seed=seed)


def along(params: dict, w: float) -> dict:
    """The blend's parameters moved along the valley to weight ``w`` (module doc)."""
    w0 = float(params["weight"])
    out = dict(params, weight=w)
    out["f0"] = [float(x) * w0 / w for x in params["f0"]]
    out["reflectance"] = [float(x) * (1.0 - w0) / (1.0 - w) for x in params["reflectance"]]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", choices=sorted(MATERIALS), default="glazed_blend")
    ap.add_argument("--out", type=Path, default=None, help="images_valley_<set>.json")
    ap.add_argument("--work", type=Path, default=None, help="keep the fit here")
    args = ap.parse_args(argv)

    import images_any

    from neural_brdf import config, pipeline
    from neural_brdf.inverse import families, starts
    from neural_brdf.inverse import fit as inverse

    mi = inverse.use_variant("llvm_ad_rgb")
    import neural_brdf.renderers.mitsuba  # noqa: F401  (registers analytic_brdf)

    material, which = args.material, MATERIALS[args.material]
    out_path = args.out or RESULTS / f"images_valley_{which}.json"
    spec = images_any.materials()[material]
    load_before = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        envs = images_any.write_environments(work, which)
        folder = work / material
        images_any.write_views(folder, spec["bsdf"], envs["fit"], envs["relit"], 150)
        cfg = config.load(folder / "fit.yaml", ["train.progress=false"])
        t0 = time.perf_counter()
        metrics = pipeline.run(cfg, folder / "run", overwrite=True)
        fit_seconds = time.perf_counter() - t0
        start = metrics["training"]["init"]["start"]
        if start["family"] != "blend":
            print(f"{material}: the start is {start['family']}, not blend", file=sys.stderr)
            return 1
        fam = families.family("blend")
        views = inverse.read_views(cfg)
        for v in views:
            v.object = starts.object_mask(v)
        fitted = start["params"]
        w_fit = float(fitted["weight"])
        mats = [(w, along(fitted, w)) for w in sorted({*WEIGHTS, w_fit})]
        # past F0 = 1 or a reflectance of 1 there is no such material
        mats = [(w, p) for w, p in mats if max(p["f0"]) <= 1.0 and max(p["reflectance"]) <= 1.0]
        elements = [fam.element(p) for _, p in mats] + [spec["bsdf"]]
        # losses[s, m]: seed set s, material m (the points, then the truth)
        losses = np.array(
            [[scored_loss(views, el, seed=s) for el in elements] for s in range(SEEDS)]
        )
    k_fit = [w for w, _ in mats].index(w_fit)

    def paired(m: int) -> tuple[float, float]:
        """Material m's loss minus the fitted start's, over the seed sets: mean, its
        standard error (the same seeds for both: a paired difference)."""
        d = losses[:, m] - losses[:, k_fit]
        return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d)))

    points = []
    for m, (w, p) in enumerate(mats):
        diff, se = paired(m)
        points.append(
            {
                "weight": w,
                "f0": p["f0"],
                "reflectance": p["reflectance"],
                "fitted": m == k_fit,
                "loss": float(losses[:, m].mean()),
                "minus_fitted": diff,
                "minus_fitted_se": se,
            }
        )
    t_diff, t_se = paired(len(mats))
    out = {
        "benchmark": "images_valley",
        "set": which,
        "material": material,
        "what": spec["what"],
        "truth_weight": float(spec["bsdf"].find("float[@name='weight']").get("value")),
        "spp": SPP,
        "fitted": {k: fitted[k] for k in ("weight", "f0", "edge_tint", "alpha", "reflectance")},
        "points": points,
        "seed_sets": SEEDS,
        "truth": {
            "loss": float(losses[:, -1].mean()),
            "minus_fitted": t_diff,
            "minus_fitted_se": t_se,
        },
        # the estimate's own spread: the fitted start's loss under each seed set
        "fitted_loss_by_seeds": [float(x) for x in losses[:, k_fit]],
        "target_noise": start.get("target_noise"),
        "fit_seconds": fit_seconds,
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "cores": os.cpu_count(),
            "mitsuba": mi.__version__,
            "loadavg_before": load_before,
            "loadavg_after": [round(x, 2) for x in os.getloadavg()],
        },
    }
    write_json(out_path, out)
    for q in points:
        mark = "  (fitted)" if q["fitted"] else ""
        print(
            f"w {q['weight']:.3f}  F0 {np.round(q['f0'], 3)}  loss {q['loss']:.7f}  minus the "
            f"fitted {q['minus_fitted']:+.2e} +- {q['minus_fitted_se']:.1e}{mark}"
        )
    print(f"truth: minus the fitted {t_diff:+.2e} +- {t_se:.1e}")
    print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
