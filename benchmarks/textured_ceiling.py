"""What the textured recipe's lobes reach at a single texel: the ceiling of its accuracy
(issue 30, development teachers, nothing chosen here).

    python benchmarks/textured_ceiling.py            # about 15 minutes on 2 cores
    python benchmarks/textured_ceiling.py --quick    # tiny budgets: the machinery only
    python benchmarks/textured_ceiling.py --grazing-power 2 --only r0.25_m0   # both
        # models' model.grazing_power 2 -> results/textured_ceiling_gp2_dev.json

``textured_floor.py`` asks what an R x R field costs by itself (the teacher's maps
block-averaged).  This asks the other half: with no field at all, how close does the
textured model's lobe family come to one texel of the principled teacher?  Each teacher
here is a homogeneous ``principled`` (a development base colour :data:`BASE`, specular
0.5, no sheen) at a (roughness, metallic) of :data:`TEACHERS`, spanning the textured
teachers' roughness range (``neural_brdf.measured.procedural.ROUGHNESS``) and metallic
range.  Two models are trained for each:

* ``lobes``: ``textured.SETTINGS`` (the test set's recipe: K shared lobes with per-channel
  weights and the latent, lr, steps, batch, pool, the lobes' bound; the JSON records
  them as ``lobes_settings``: the run in results/ had ``lobe_bound: scale``, the recipe
  then) with a field of one texel (R = 1) and one start, through
  ``textured.train_textured_file`` (trained, normalised, exported);
* ``compact``: the ordinary pipeline on ``target: {mitsuba: teacher.xml}`` (the compact
  recipe, ``textured.train_homogeneous_file``): the homogeneous file of the same teacher.

Both files are scored by onnxruntime on the pairs ``textured.py`` scores a file on
(``textured.validation_pairs``: wi uniform, wo half uniform, half from the teacher's
sampler; :data:`PAIRS` of them, seed :data:`SEED`): the relative RMSE of f cos, and its
share and value by bands of cos theta_i (where the squared error lies).

Reading: a textured file cannot be more accurate at a texel than its lobes are at that
texel's material, so the ``lobes`` column bounds the textured principled's figure from
below wherever the field is perfect.  Development teachers only: the test set's
homogeneous principled (``textured.HOMOGENEOUS``) is not among them.  Nothing asserts.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import machine, write_json  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
BASE = (0.7, 0.4, 0.2)  # a development base colour (the test's principled_plain: 0.6, 0.35, 0.2)
# name -> (roughness, metallic): the textured teachers' roughness range is 0.25 to 0.8
TEACHERS = {
    "r0.25_m0": (0.25, 0.0),
    "r0.25_m0.5": (0.25, 0.5),
    "r0.25_m1": (0.25, 1.0),
    "r0.4_m0.5": (0.4, 0.5),
    "r0.8_m0.5": (0.8, 0.5),
}
PAIRS = 200_000
SEED = 900  # the development pairs' seed (textured_sweep.py's first set)
BANDS = ((0.0, 0.2), (0.2, 0.5), (0.5, 1.01))  # cos theta_i


def teacher_xml(roughness: float, metallic: float) -> str:
    base = ", ".join(f"{c:g}" for c in BASE)
    return (
        '<bsdf version="3.0.0" type="twosided">\n'
        ' <bsdf type="principled">\n'
        f'  <rgb name="base_color" value="{base}"/>\n'
        f'  <float name="roughness" value="{roughness:g}"/>\n'
        f'  <float name="metallic" value="{metallic:g}"/>\n'
        '  <float name="specular" value="0.5"/>\n'
        '  <float name="sheen" value="0"/>\n'
        " </bsdf>\n"
        "</bsdf>\n"
    )


def score(f, pairs) -> dict:
    """Relative RMSE of f cos on ``pairs`` (wi, wo, uv, ref), overall and by cos theta_i."""
    import numpy as np
    from textured_sweep import error_share

    wi, wo, uv, ref = pairs
    got = f(wi, wo, uv)
    cos = wo[:, 2:3]
    d2 = (((got - ref) * cos) ** 2).sum(1)
    r2 = ((ref * cos) ** 2).sum(1)
    out = {"rel_rmse": float(np.sqrt(d2.sum() / r2.sum())), "cos_i": {}}
    for lo, hi in BANDS:
        m = (wi[:, 2] >= lo) & (wi[:, 2] < hi)
        out["cos_i"][f"{lo:g}-{min(hi, 1.0):g}"] = error_share(m, d2, r2)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", action="append", default=[], help="a name of TEACHERS (repeat)")
    ap.add_argument("--quick", action="store_true", help="tiny budgets: the machinery only")
    ap.add_argument(
        "--grazing-power",
        type=float,
        default=None,
        help="model.grazing_power of both models (default: each recipe's own, 1)",
    )
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    tag = "" if args.grazing_power is None else f"_gp{args.grazing_power:g}"
    out_path = args.out or RESULTS / (
        "textured_ceiling_quick.json" if args.quick else f"textured_ceiling{tag}_dev.json"
    )
    import torch

    torch.set_num_threads(2)
    import textured as bench

    from neural_brdf.measured.textured import TexturedMitsubaTarget

    names = args.only or list(TEACHERS)
    unknown = [n for n in names if n not in TEACHERS]
    if unknown:
        print(f"textured_ceiling: --only: {unknown[0]!r} is not one of {', '.join(TEACHERS)}")
        return 2
    settings = {**bench.SETTINGS, "resolution": 1, "starts": 1}
    overrides = []  # the compact file's config changes
    if args.grazing_power is not None:
        settings["grazing_power"] = args.grazing_power
        overrides.append(f"model.grazing_power={args.grazing_power:g}")
    if args.quick:
        settings.update(steps=20, pool=1 << 14, batch=1024)
    pairs_n = 4096 if args.quick else PAIRS
    load_before = [round(x, 2) for x in os.getloadavg()]
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            rough, metal = TEACHERS[name]
            folder = Path(tmp) / name
            folder.mkdir()
            xml = folder / "teacher.xml"
            xml.write_text(teacher_xml(rough, metal))
            teacher = TexturedMitsubaTarget(str(xml))
            pairs = bench.validation_pairs(teacher, pairs_n, SEED)
            t0 = time.perf_counter()
            (folder / "lobes").mkdir()
            lobes_path, lobes_fig = bench.train_textured_file(teacher, folder / "lobes", settings)
            t1 = time.perf_counter()
            (folder / "compact").mkdir()
            compact_path, compact_fig = bench.train_homogeneous_file(
                xml, folder / "compact", args.quick, overrides
            )
            t2 = time.perf_counter()
            rows[name] = {
                "roughness": rough,
                "metallic": metal,
                "lobes": {
                    **score(bench.OnnxFile(lobes_path), pairs),
                    "seconds": t1 - t0,
                    "raw_max_albedo": lobes_fig.get("lobe_raw_max_albedo"),
                },
                "compact": {
                    **score(bench.OnnxFile(compact_path), pairs),
                    "seconds": t2 - t1,
                    "steps": compact_fig["steps"],
                },
            }
            r = rows[name]
            print(
                f"{name}: lobes {r['lobes']['rel_rmse']:.2%}, compact "
                f"{r['compact']['rel_rmse']:.2%}",
                file=sys.stderr,
            )
    import mitsuba as mi

    write_json(
        out_path,
        {
            "benchmark": "textured_ceiling",
            "set": "dev",
            "quick": args.quick,
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(load_before, mitsuba=mi.__version__, torch=torch.__version__),
            "teacher": "twosided > principled, base_color "
            + ", ".join(f"{c:g}" for c in BASE)
            + ", specular 0.5, sheen 0; roughness and metallic per row (development)",
            "pairs": {"n": pairs_n, "seed": SEED, "draw": "textured.validation_pairs"},
            "lobes_settings": settings,
            "compact": "the pipeline's defaults (compact), target: {mitsuba: teacher.xml}",
            "compact_overrides": overrides,
            "rows": rows,
        },
    )
    print(f"wrote {out_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
