"""A start's fit, timed: each family's fit to three views, its steps traced anew every time
or recorded once per view and replayed (issue 29, item 4: the whole fit within 300 s).

    python benchmarks/start_fit.py                        # about five minutes on 2 cores
    python benchmarks/start_fit.py --rounds 2 --out /tmp/start_fit.json

``images.start: auto`` fits every family of :data:`neural_brdf.inverse.families.FAMILIES`
(Mitsuba's own BSDFs) to the training pixels, then the contenders and the chosen one's
refinement: most of an image fit's time before the network.  A step of such a fit
renders each view with ``mi.render`` (primal and gradient passes), takes the relative
MSE and calls ``dr.backward``; Dr.Jit traces the integrator and the BSDF again for every
call.  Since 2026-12-04 (``images.start_freeze``, the default) the step's render, loss
and gradient (:func:`neural_brdf.inverse.starts.render_loss_backward`) run under
:func:`drjit.freeze`: recorded at a view's first step and replayed after, without
tracing.  Routes, each :func:`neural_brdf.inverse.starts.fit_candidate` with the
default :class:`~neural_brdf.inverse.starts.Schedule` (80 steps, 4 spp in the gradient
pass, 16 in the primal, two held-out renders of 64 spp):

* ``frozen``: ``Schedule.freeze`` true, the recordings included (a fit makes its own);
* ``traced``: false, the route before.

The views: the example's three 96 x 96 views of the unit sphere under its sky
(:func:`neural_brdf.inverse.scene.write`, 64 spp targets), the issue's plastic
(``roughplastic``, GGX alpha 0.15, diffuse 0.5/0.2/0.1) as the truth: the case the
start's choice meets first.  Rounds interleave the routes and families, each fit from
the same seed; each figure is the best of ``--rounds``.  The two routes compute the same
fit up to float rounding (the recorded kernels are not the traced ones bit for bit):
the JSON records the largest relative difference of the fitted parameters and of the
held-out loss, and the benchmark fails when one exceeds 1e-3
(tests/inverse/test_starts.py checks the routes at 1e-4 on small views).  Nothing is
tuned here: no setting is chosen, so there is no development set and no test set.  The
JSON records the load average before and after.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import loadavg, machine, write_json  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
RESOLUTION = 96
TARGET_SPP = 64
TOLERANCE = 1e-3  # the routes' largest relative difference allowed (module doc)
ROUTES = {"frozen": True, "traced": False}


def write_views(folder: Path) -> Path:
    """The example's three views with the plastic as their material; returns fit.yaml."""
    from neural_brdf.fileio import atomic_write
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene

    truth = inverse.bsdf_element(
        "roughplastic", distribution="ggx", alpha=0.15, diffuse_reflectance=(0.5, 0.2, 0.1)
    )
    scene.write(folder, resolution=RESOLUTION, spp=TARGET_SPP)
    for k in (1, 2, 3):
        xml = folder / f"view{k}.xml"
        atomic_write(xml, inverse.scene_text(ET.parse(xml), truth))
        scene.write_exr(folder / f"view{k}.exr", scene.render_file(xml, TARGET_SPP, seed=k))
    return folder / "fit.yaml"


def flat(c, names) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(c.params[n], np.float64)) for n in names])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "start_fit.json")
    args = ap.parse_args(argv)

    import drjit as dr

    from neural_brdf import config
    from neural_brdf.inverse import fit as inverse

    mi = inverse.use_variant("llvm_ad_rgb")
    from neural_brdf.inverse import families, starts

    load_before = loadavg()
    sched = starts.Schedule()
    seconds = {f: {r: math.inf for r in ROUTES} for f in families.FAMILIES}
    worst = {f: {"params": 0.0, "val_loss": 0.0} for f in families.FAMILIES}
    with tempfile.TemporaryDirectory() as tmp:
        views = inverse.read_views(config.load(write_views(Path(tmp))))
        train, held = starts.split_pixels(views, 0.3, seed=0)
        for r in range(args.rounds):
            for name, fam in families.FAMILIES.items():
                fits = {}
                for route, freeze in ROUTES.items():
                    t0 = time.perf_counter()
                    c = starts.fit_candidate(
                        views,
                        name,
                        mask_train=train,
                        mask_val=held,
                        seed=r,
                        schedule=starts.Schedule(freeze=freeze),
                    )
                    dr.sync_thread()
                    seconds[name][route] = min(seconds[name][route], time.perf_counter() - t0)
                    fits[route] = c
                a, b = flat(fits["traced"], fam.params), flat(fits["frozen"], fam.params)
                w = worst[name]
                w["params"] = max(w["params"], float(np.max(np.abs(a - b) / np.abs(a))))
                va, vb = fits["traced"].val_loss, fits["frozen"].val_loss
                w["val_loss"] = max(w["val_loss"], abs(va - vb) / abs(va))
            each = (f"{f} {s['frozen']:.2f}/{s['traced']:.2f} s" for f, s in seconds.items())
            print(f"round {r + 1}: " + ", ".join(each), file=sys.stderr)
    bad = {f: w for f, w in worst.items() if max(w.values()) > TOLERANCE}
    if bad:
        print(f"start_fit: the routes differ beyond {TOLERANCE}: {bad}", file=sys.stderr)
        return 1
    total = {r: sum(s[r] for s in seconds.values()) for r in ROUTES}
    out = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(load_before, mitsuba=mi.__version__, drjit=dr.__version__),
        "views": len(views),
        "resolution": RESOLUTION,
        "target": "roughplastic, GGX alpha 0.15, diffuse 0.5/0.2/0.1 (the issue's plastic)",
        "schedule": {
            "steps": sched.steps,
            "spp": sched.spp,
            "primal_spp": sched.primal_spp,
            "val_spp": sched.val_spp,
        },
        "rounds": args.rounds,
        "seconds": seconds,
        "traced_over_frozen": {f: s["traced"] / s["frozen"] for f, s in seconds.items()},
        "total_s": total,
        "total_traced_over_frozen": total["traced"] / total["frozen"],
        "largest_relative_difference": worst,
        "tolerance": TOLERANCE,
    }
    write_json(args.out, out)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
