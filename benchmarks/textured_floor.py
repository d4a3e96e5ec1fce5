"""How close can a field of R x R texels come?  The teacher at R x R, against itself.

    python benchmarks/textured_floor.py            # both sets, R = 32 ... 512 (about 2 min)

For each procedural textured teacher of benchmarks/textured.py (development set: seed 1,
test set: seed 0, 512 x 512 maps), every map (base colour, roughness, metallic, the normal
map; the roughplastic's diffuse reflectance) is averaged over blocks of (512 / R)^2 texels
and written as an R x R map, and Mitsuba evaluates that teacher (its bitmaps read
bilinearly and wrapping, as the textured file's field is) at the pairs on which
benchmarks/textured.py scores a file (``rel_rmse``: 200,000 pairs of
``textured.validation_pairs``, its seed 7: uv uniform, wi uniform on the hemisphere, wo
half uniform and half from the teacher's sampler) and at 1,000,000 more pairs drawn the
same way (``rel_rmse_1m``, seed 900: the figure is heavy-tailed, a few sampled pairs at
the sharpest texels carry much of it).  The figure is the relative RMSE of f cos(theta_o)
of the R x R teacher against the 512 x 512 one: how much of the textured model's error an
R x R field costs by itself.

It is an indicator, not a bound: the model's field holds lobe weights and a latent, not
the teacher's parameters, and training may place them better than a block average (on
the test principled the R = 64 file scores 10.6 % where its block-averaged teacher scores
11.6 %).  But it shows which error a resolution allows: where the block-averaged teacher
is at 12 %, a model at that R will not reach 3 %.  Nothing is tuned here; the JSON goes
to benchmarks/results/textured_floor.json.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import write_json  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
SIZE = 512
RESOLUTIONS = (32, 64, 128, 256)
PAIRS = {"rel_rmse": (200_000, 7), "rel_rmse_1m": (1_000_000, 900)}  # (pairs, seed)


def block_average(image: np.ndarray, r: int) -> np.ndarray:
    """(S, S, C) -> (r, r, C): the mean of each (S / r)^2 block."""
    s = image.shape[0]
    k = s // r
    return image.reshape(r, k, r, k, -1).mean((1, 3))


def floor_of(xml: Path, resolutions, pairs: dict, work: Path) -> dict:
    import mitsuba as mi
    import textured as bench

    from neural_brdf.measured.textured import TexturedMitsubaTarget

    teacher = TexturedMitsubaTarget(xml)
    draws = {k: bench.validation_pairs(teacher, n, seed) for k, (n, seed) in pairs.items()}
    maps = sorted(p.name for p in xml.parent.glob("*.exr"))
    out: dict = {"maps": maps, "teacher": teacher.describe(), **{k: {} for k in pairs}}
    images = {}  # each map read once, averaged at every R
    for name in maps:
        image = np.array(mi.Bitmap(str(xml.parent / name)), dtype=np.float64)
        images[name] = image.reshape(image.shape[0], image.shape[1], -1)
    for r in resolutions:
        folder = work / f"{xml.parent.name}_{r}"
        folder.mkdir(parents=True, exist_ok=True)
        for name, image in images.items():
            mi.Bitmap(block_average(image, r).astype(np.float32)).write(str(folder / name))
        (folder / xml.name).write_text(xml.read_text())
        coarse = TexturedMitsubaTarget(folder / xml.name)
        for key, (wi, wo, uv, ref) in draws.items():
            got = np.nan_to_num(np.asarray(coarse.eval(wi, wo, uv)))
            d = (got - ref) * wo[:, 2:3]
            out[key][str(r)] = float(np.linalg.norm(d) / np.linalg.norm(ref * wo[:, 2:3]))
        shown = ", ".join(f"{k} {100 * out[k][str(r)]:.2f} %" for k in pairs)
        print(f"  {xml.parent.name} R = {r}: {shown}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=None, help="one draw of this many (smoke)")
    ap.add_argument("--size", type=int, default=SIZE, help="the teachers' maps (a smoke test: 32)")
    ap.add_argument("--out", type=Path, default=RESULTS / "textured_floor.json")
    args = ap.parse_args(argv)
    import textured as bench

    from neural_brdf.measured.procedural import write_teacher

    resolutions = [r for r in RESOLUTIONS if r < args.size and args.size % r == 0]
    pairs = PAIRS if args.pairs is None else {"rel_rmse": (args.pairs, 7)}
    result = {
        "benchmark": "textured_floor",
        "what": "relative RMSE of f cos of the teacher with every map block-averaged to R x R "
        "(read bilinearly) against the full teacher, on benchmarks/textured.py's pairs",
        "pairs": {k: {"pairs": n, "seed": sd} for k, (n, sd) in pairs.items()},
        "size": args.size,
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "sets": {},
    }
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="nbrdf-floor-") as tmp:
        work = Path(tmp)
        for which, seed in bench.SEEDS.items():
            result["sets"][which] = {}
            for kind in bench.KINDS:
                xml = write_teacher(work / which / kind, kind, size=args.size, seed=seed)
                result["sets"][which][kind] = floor_of(xml, resolutions, pairs, work / which)
                write_json(args.out, result)
    result["wall_seconds"] = time.perf_counter() - t0
    write_json(args.out, result)
    print(f"wrote {args.out} ({result['wall_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
