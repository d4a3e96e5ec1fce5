"""How well the targets' noise is estimated from the images alone (issue 29).

    python benchmarks/target_noise.py            # both sets, both captures (about 5 min)

``images.poor_start_loss`` calls a start poor when its held-out loss exceeds the
targets' own noise by more than the limit, and the noise is estimated from each target
image alone (:func:`neural_brdf.inverse.fit.target_noise`: a pixel against the mean of
its four neighbours, trimmed, scaled by ``NOISE_SCALE``).  Here each material of
``benchmarks/images_any.py``'s sets, under each capture (its set's fitting environment,
and the multi-light capture), has its three fitted views written as that benchmark
writes them (96 x 96, 256 spp), and the estimate is set against the noise measured by a
second render of every view with another seed: the mean over the object's pixels of the
relative MSE's weight times (y1 - y2)^2 / 2.  ``NOISE_SCALE`` was chosen on the
development rows; the test rows are reported.  Nothing here asserts anything; the JSON
goes to benchmarks/results/target_noise.json and ``tools/results_tables.py`` makes the
table of docs/results.md.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import images_any
from common import write_json

SEED = 1000  # the second render's seeds: SEED + the view's number


def measure(name: str, spec: dict, folder: Path, envs: dict[str, Path], capture: str) -> dict:
    from neural_brdf import config
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene, starts

    images_any.write_views(folder, spec["bsdf"], envs["fit"], envs["relit"], 150, capture)
    views = inverse.read_views(config.load(folder / "fit.yaml"))
    sums, pixels = 0.0, 0
    for k, v in enumerate(views, start=1):
        v.object = starts.object_mask(v)
        again = scene.render_file(v.scene_path, images_any.TARGET_SPP, seed=SEED + k)
        d = inverse.rel_weight(v.target) * (v.target - again) ** 2 / 2
        sums += float(d[v.object].sum())
        pixels += int(v.object.sum()) * 3
    second = sums / pixels
    est = inverse.target_noise(views)
    return {
        "estimate": est,
        "second_render": second,
        "ratio": None if est is None or second <= 0 else est / second,
        "object_pixels": pixels // 3,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", dest="which", action="append", choices=tuple(images_any.SETS))
    ap.add_argument("--capture", action="append", choices=images_any.CAPTURES)
    ap.add_argument("--only", action="append", default=[], help="a material (repeat)")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "nbrdf-noise")
    ap.add_argument("--out", type=Path, default=images_any.RESULTS / "target_noise.json")
    args = ap.parse_args(argv)
    sets = args.which or list(images_any.SETS)
    captures = args.capture or list(images_any.CAPTURES)

    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene

    mi = inverse.use_variant("llvm_ad_rgb")
    import neural_brdf.renderers.mitsuba  # noqa: F401  (registers analytic_brdf)

    result: dict = {
        "benchmark": "target_noise",
        "estimator": {
            "function": "neural_brdf.inverse.fit.target_noise",
            "keep": inverse.NOISE_KEEP,
            "scale": inverse.NOISE_SCALE,
            "chosen_on": "dev",
        },
        "views": {
            "fitted": 3,
            "resolution": images_any.RESOLUTION,
            "target_spp": images_any.TARGET_SPP,
        },
        "second_render": "each fitted view rendered again at the same spp, seed "
        f"{SEED} + its number; the mean over the object's pixels and RGB of "
        "rel_weight(y1) (y1 - y2)^2 / 2",
        "rows": [],
        "machine": images_any.machine(mi),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    for which in sets:
        for capture in captures:
            work = args.work / f"{which}_{capture}"
            work.mkdir(parents=True, exist_ok=True)
            envs = {}
            for role, env in images_any.SETS[which].items():
                envs[role] = work / f"{env}.exr"
                scene.write_exr(envs[role], images_any.environment(env))
            for name, spec in images_any.materials().items():
                if spec["set"] != which or (args.only and name not in args.only):
                    continue
                row = {"set": which, "capture": capture, "material": name}
                row.update(measure(name, spec, work / name, envs, capture))
                result["rows"].append(row)
                write_json(args.out, result)
                print(
                    f"{which} {capture} {name}: estimate {row['estimate']:.3g}, second "
                    f"render {row['second_render']:.3g}, ratio {row['ratio']:.2f}",
                    flush=True,
                )
    result["machine"] = images_any.machine(mi)
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
