"""The sampling lobe's fit, timed: what an image fit pays every ``images.lobe_every`` steps
(issue 29, item 4: speed), and what an export pays once.

    python benchmarks/lobe_refit.py                       # about two minutes on 2 cores
    python benchmarks/lobe_refit.py --rounds 3 --out /tmp/refit.json

:func:`neural_brdf.physics.lobe_fit.fit` scores about a hundred candidate lobes (GGX and
Beckmann, mirror and retro, 25 roughnesses, each at 14 shares) on one pooled set of
samples per incident direction.  Since 2026-12-04 a pool computes a candidate's density
from the half vectors' parts computed once per lobe shape and the Smith term once (every
sample of a pool shares its incident direction), and sums its 14 shares in place with
the cosine lobe's part of each computed once: route ``pool``.  Route ``general`` is the
fit before that change: the file format's densities,
:func:`neural_brdf.fileformat.lobe.ggx_pdf` and ``beckmann_pdf``, on every sample, and
each share's mixture formed anew (the pools themselves are built alike, with the
isotropic GGX densities from their half vectors' parts, so ``general`` is a little
faster than the fit was).  The two routes give the same lobe to the last bit
(the JSON records the check; tests/physics/test_sampling_lobe.py checks the densities).

Cases, each the function an image fit or an export fits its lobe to:

* ``compact_network``: the compact recipe's RawBRDF (``neural_brdf.inverse.bsdf.COMPACT``,
  isotropic encoding, as the image stage runs it after an isotropic start), its weights
  at their seeded initialisation: the image stage's refit, evaluated by torch on one
  thread as :meth:`neural_brdf.inverse.bsdf.NeuralBSDFAD.refit_lobe` does;
* ``beckmann``: analytic's Beckmann microfacet, alpha 0.3 (a Beckmann lobe is chosen);
* ``ward``: analytic's Ward model, anisotropic (the anisotropic search runs).

Rounds interleave the routes and cases; each figure is the best of ``--rounds``.  The
image stage's share: the compact network's refit over ``images.lobe_every`` (the config's
default), beside one step of the stage from ``results/image_step.json`` (its
``neural_graph`` and ``roughconductor`` steps, recorded on the same machine kind: the
stage's step plus its share of a refit, over ``roughconductor``'s step, which refits
nothing).  Nothing is tuned here: no setting is chosen, so there is no development set
and no test set.  The JSON records the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import loadavg, machine, write_json  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def general_density(pool, ax: float, ay: float, retro: bool, dist: str):
    """A candidate's density through the file format's functions on every sample: the
    route before 2026-12-04."""
    from neural_brdf.fileformat import lobe as lobe_format
    from neural_brdf.physics import lobe_fit

    wo = lobe_format.turn(pool.wo) if retro else pool.wo
    if dist == "ggx":
        return lobe_format.ggx_pdf(pool.wi, wo, ax, ay)
    return lobe_format.beckmann_pdf(pool.wi, wo, ax, ay, erf=lobe_fit._torch_erf)


def general_second_moments(pool, ia: int, ib: int, retro: bool, dist: str = "ggx"):
    """A candidate's second moments at every share, each share's mixture formed anew:
    the route before 2026-12-04."""
    import numpy as np

    from neural_brdf.physics import lobe_fit

    if pool.black:
        return np.zeros(len(lobe_fit.WEIGHTS))
    if ia == ib and dist == "ggx":
        p = pool.p_iso[retro][ia]
    else:
        ax, ay = float(lobe_fit.ALPHAS[ia]), float(lobe_fit.ALPHAS[ib])
        p = general_density(pool, ax, ay, retro, dist).astype(np.float32)
    m2 = np.empty(len(lobe_fit.WEIGHTS))
    with np.errstate(divide="ignore"):
        for j, w in enumerate(lobe_fit.WEIGHTS.astype(np.float32)):
            m2[j] = np.sum(pool.c / ((1 - w) * pool.p_cos + w * p), dtype=np.float64)
    return m2 / pool.norm


def cases() -> dict:
    import torch
    import yaml

    import analytic
    from neural_brdf import config as cfgmod
    from neural_brdf.inverse import bsdf as ib  # the compact recipe (a JIT AD variant set)
    from neural_brdf.train.model import RawBRDF

    section = dict(yaml.safe_load(ib.COMPACT), encoding="isotropic")
    torch.manual_seed(0)
    raw = RawBRDF.from_config(cfgmod.Model(**section)).eval()

    def network(wi, wo):
        with torch.no_grad():
            return raw(torch.as_tensor(wi).float(), torch.as_tensor(wo).float()).numpy()

    return {
        "compact_network": (network, raw.anisotropic),
        "beckmann": (analytic.create("microfacet", distribution="beckmann", alpha=0.3).eval, True),
        "ward": (analytic.create("ward").eval, True),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULTS / "lobe_refit.json")
    args = ap.parse_args(argv)

    import mitsuba as mi
    import torch

    mi.set_variant("llvm_ad_rgb")  # neural_brdf.inverse.bsdf (COMPACT) needs a JIT AD variant
    from neural_brdf import config as cfgmod
    from neural_brdf.physics import lobe_fit

    torch.set_num_threads(1)  # as the image stage runs torch (inverse.fit.TORCH_THREADS)
    load_before = loadavg()
    pool_route = lobe_fit._Pool.second_moments
    routes = {"pool": pool_route, "general": general_second_moments}
    todo = cases()
    best = {c: dict.fromkeys(routes, math.inf) for c in todo}
    lobes: dict[str, dict[str, dict]] = {c: {} for c in todo}
    try:
        for r in range(args.rounds):
            for c, (fn, aniso) in todo.items():
                for route, moments in routes.items():
                    lobe_fit._Pool.second_moments = moments  # type: ignore[method-assign]
                    t0 = time.perf_counter()
                    lobes[c][route] = lobe_fit.fit(fn, seed=r, anisotropic=aniso)
                    best[c][route] = min(best[c][route], time.perf_counter() - t0)
                same = lobes[c]["pool"] == lobes[c]["general"]
                if not same:
                    print(f"{c}: the routes' lobes differ at seed {r}", file=sys.stderr)
                    return 1
            print(
                f"round {r + 1}: "
                + ", ".join(f"{c} {b['pool']:.2f} / {b['general']:.2f} s" for c, b in best.items()),
                file=sys.stderr,
            )
    finally:
        lobe_fit._Pool.second_moments = pool_route  # type: ignore[method-assign]
    every = cfgmod.Images().lobe_every
    out: dict = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(
            load_before, torch=torch.__version__, torch_threads=torch.get_num_threads()
        ),
        "rounds": args.rounds,
        "seconds": best,
        "general_over_pool": {c: b["general"] / b["pool"] for c, b in best.items()},
        "same_lobes": True,  # checked above at every round's seed, or the run fails
        "lobes": {c: lobes[c]["pool"] for c in todo},
        "lobe_every": every,
    }
    step_file = RESULTS / "image_step.json"
    if step_file.is_file():
        s = json.loads(step_file.read_text())
        step, rough = s["step_s"]["neural_graph"], s["step_s"]["roughconductor"]
        refit = {route: best["compact_network"][route] / every for route in routes}
        out["image_stage"] = {
            "step_file": "benchmarks/results/image_step.json",
            "step_date": s["date"],
            "neural_graph_step_s": step,
            "roughconductor_step_s": rough,
            "refit_per_step_s": refit,
            "step_with_refit_vs_roughconductor": {
                route: (step + refit[route]) / rough for route in routes
            },
        }
    write_json(args.out, out)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
