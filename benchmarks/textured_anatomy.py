"""Where the textured principled's error is: its squared error of f cos grouped by the
teacher's roughness and metallic at each pair's uv, by cos theta_i, and by pair (issue 30:
the principled misses the 3 % goal; the development set, which chooses nothing here).

    python benchmarks/textured_anatomy.py            # about 4 minutes on 2 cores
    python benchmarks/textured_anatomy.py --quick    # tiny budgets: the machinery only

The recipe of ``textured.py`` (``textured.SETTINGS``: its projected field and refitted
lobes included) with one start, training seed 1, made by ``textured.train_textured_file``
(the function that makes ``textured.json``'s files) on the development principled
(``write_teacher(principled, 512, textured.SEEDS['dev'])``); its file without the normal
field is scored by onnxruntime on the development pairs of ``textured_project.py`` (two
draws of ``textured_project.PAIRS``).  Each pair's squared error of f cos is grouped by the
teacher's roughness and metallic maps at its uv (the texel it falls in), by cos theta_i,
by cos theta_d, by the uv distance to the nearest edge of the procedural tiles (where the
teacher's maps jump), and ranked: the share of the total carried by the worst 0.1 % and
1 % of the pairs.  With analytic heads, the field's alpha at its texel centres is set
against the teacher's roughness^2 there.  ``--setting KEY=VALUE`` changes one value of
the recipe (a development question); ``--keep DIR`` keeps the teacher, the files, the
recipe, the trained model and the pairs, ``--keep DIR --rescore`` scores that file
again (no training), and ``--keep DIR --reproject --setting project...=V`` projects,
refits and exports that trained model again (only the projection's and the refit's keys
may change: a comparison of projections on one training).  The held-out teacher is not
used.  Nothing asserts.  Its runs are development runs: textured.py's recipe chose its
projection from four of them (``SETTINGS``, textured_anatomy_dev_{base,both,512,
512_both}.json); the others chose nothing.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import write_json  # noqa: E402

ROUGHNESS_BANDS = ((0.25, 0.35), (0.35, 0.5), (0.5, 0.65), (0.65, 0.8))
METALLIC_BANDS = ((0.0, 0.25), (0.25, 0.75), (0.75, 1.0))
COS_BANDS = ((0.0, 0.05), (0.05, 0.2), (0.2, 0.5), (0.5, 1.0))
COS_D_BANDS = ((0.0, 0.2), (0.2, 0.5), (0.5, 0.8), (0.8, 1.0))  # cos theta_d = |wi + wo| / 2
# uv distance to the nearest edge of the procedural tiles (procedural.TILES per side):
# the teacher's maps jump there, over one of its texels (1/512) under bilinear filtering
EDGE_BANDS = (
    (0.0, 1 / 1024),
    (1 / 1024, 1 / 512),
    (1 / 512, 1 / 128),
    (1 / 128, 1 / 32),
    (1 / 32, 1.0),
)
WORST = (0.001, 0.01)  # the worst shares of the pairs, by squared error
# the recipe's keys that --reproject may change (what comes after the training)
REPROJECT_KEYS = ("project", "refit_")


def _map(path: Path):
    import mitsuba as mi
    import numpy as np

    a = np.array(mi.Bitmap(str(path)), dtype=np.float64)
    return a[..., 0] if a.ndim == 3 else a


def _field_alpha(path: Path):
    """The GGX heads' alpha at the field's texel centres (its last column) and the
    field's resolution, from the file's field table."""
    import numpy as np
    import onnx
    import torch
    from onnx import numpy_helper

    from neural_brdf.train.ggx_heads import alpha_of

    for init in onnx.load(str(path)).graph.initializer:
        if init.name.endswith("field.table"):
            table = numpy_helper.to_array(init)
            r = int(round(np.sqrt(table.shape[0])))
            return alpha_of(torch.from_numpy(table[:, -1].astype(np.float64))).numpy(), r
    raise ValueError(f"{path}: no field table")


def _band(x, lo: float, hi: float, last: bool):
    return (x >= lo) & ((x <= hi) if last else (x < hi))


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny budgets: the machinery only")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--setting",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change one scalar value of textured.SETTINGS (this script is development only)",
    )
    ap.add_argument(
        "--keep", type=Path, default=None, help="keep the teacher, the file and the pairs here"
    )
    ap.add_argument(
        "--rescore",
        action="store_true",
        help="score the file an earlier --keep DIR kept (its recipe.json) instead of training",
    )
    ap.add_argument(
        "--reproject",
        action="store_true",
        help="project, refit and export again the trained model an earlier --keep DIR kept "
        "(trained.pt), with --setting changing only the projection's and refit's keys",
    )
    args = ap.parse_args(argv)
    if args.rescore and (args.keep is None or args.setting or args.reproject):
        ap.error(
            "--rescore: with --keep DIR (a folder an earlier --keep filled), "
            "no --setting, no --reproject"
        )
    if args.reproject and args.keep is None:
        ap.error("--reproject: with --keep DIR (a folder an earlier --keep filled)")
    out_path = args.out or Path(__file__).resolve().parent / "results" / (
        "textured_anatomy_quick.json" if args.quick else "textured_anatomy_dev.json"
    )
    import numpy as np
    import torch

    torch.set_num_threads(2)
    import textured as bench
    import textured_project as tp

    from neural_brdf.measured.procedural import TILES
    from neural_brdf.train.textured_model import bilinear_wrap
    from neural_brdf.train.textured_project import texel_centres

    # textured.py's recipe (its projection and refit included) with one start, through
    # the function that makes textured.json's files
    settings = {**(bench.QUICK if args.quick else bench.SETTINGS), "starts": 1, "seed": 1}
    for item in args.setting:
        key, _, value = item.partition("=")
        if key not in settings or isinstance(settings[key], list):
            ap.error(f"--setting {item}: a scalar key of textured.SETTINGS")
        settings[key] = type(settings[key])(value)
    pairs_n = 4096 if args.quick else tp.PAIRS
    load_before = [round(x, 2) for x in os.getloadavg()]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = (args.keep or Path(tmp)) / "principled"
        teacher, pairs = tp.teacher_and_pairs(folder, "principled", "dev", pairs_n)
        made: dict = {}  # train_textured_file's figures (none when rescored)
        if args.rescore:  # the kept file, as its recipe made it
            settings = json.loads((folder / "recipe.json").read_text())
        else:
            if args.reproject:  # the kept trained model, projected and refitted again
                kept = json.loads((folder / "recipe.json").read_text())
                changed = sorted(
                    k
                    for k in set(kept) | set(settings)
                    if kept.get(k) != settings.get(k) and not k.startswith(REPROJECT_KEYS)
                )
                if changed:
                    ap.error(f"--reproject: --setting changes training keys {changed}")
                trained = torch.load(folder / "trained.pt", weights_only=False)
            else:
                trained = bench.trained_model(teacher, settings)
                if args.keep is not None:
                    torch.save(trained, folder / "trained.pt")
            _, made = bench.train_textured_file(teacher, folder, settings, trained=trained)
            (folder / "recipe.json").write_text(json.dumps(settings))
        f = bench.OnnxFile(folder / "bare.onnx")  # f alone, without the normal field
        got = tp.score(f, pairs)
        rough, metal = (
            _map(folder / "teacher" / "roughness.exr"),
            _map(folder / "teacher" / "metallic.exr"),
        )
        d2s, r2s, ros, mes, cis, cds, eds = [], [], [], [], [], [], []
        for wi, wo, uv, ref in pairs:
            cos = wo[:, 2:3]
            d2s.append((((f(wi, wo, uv) - ref) * cos) ** 2).sum(1))
            r2s.append(((ref * cos) ** 2).sum(1))
            h, w = rough.shape
            i = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
            j = np.clip((uv[:, 1] * h).astype(int), 0, h - 1)  # row j: v = (j + 0.5) / h
            ros.append(rough[j, i])
            mes.append(metal[j, i])
            cis.append(wi[:, 2])
            cds.append(np.linalg.norm(wi + wo, axis=1) / 2)
            eds.append(np.abs((uv + 0.5 / TILES) % (1.0 / TILES) - 0.5 / TILES).min(1))
        if args.keep is not None:
            np.savez(
                folder / "pairs.npz",
                **{f"{k}{n}": a for n, p in enumerate(pairs) for k, a in zip("iouf", p)},
            )
        file_bytes = (folder / "bare.onnx").stat().st_size
        teacher_bytes = sum(p.stat().st_size for p in (folder / "teacher").glob("*.exr"))
        alpha = None
        if settings.get("analytic_heads", "none") != "none":
            # the heads' alpha at the field's texel centres against the teacher's
            # roughness^2 there (Mitsuba's principled: alpha = roughness^2, anisotropic 0)
            a_model, r = _field_alpha(folder / "bare.onnx")
            rough_t = torch.from_numpy(np.ascontiguousarray(rough).reshape(-1, 1))
            at = bilinear_wrap(rough_t, torch.from_numpy(texel_centres(r)), rough.shape[0])
            log_ratio = np.log(a_model / at[:, 0].numpy() ** 2)  # Mitsuba's filter, as the file's
            err = np.abs(log_ratio)
            alpha = {
                "resolution": r,
                "log_ratio_median": float(np.median(log_ratio)),
                "abs_log_ratio_median": float(np.median(err)),
                "abs_log_ratio_p90": float(np.percentile(err, 90)),
            }
    d2, r2, ro, me, ci, cd, ed = (np.concatenate(x) for x in (d2s, r2s, ros, mes, cis, cds, eds))
    total, ref_total = float(d2.sum()), float(r2.sum())

    def group(mask) -> dict:
        return {
            "pairs_share": float(mask.mean()),
            "error_share": float(d2[mask].sum() / total),
            "reference_share": float(r2[mask].sum() / ref_total),
            "rel_rmse": float(np.sqrt(d2[mask].sum() / r2[mask].sum())) if mask.any() else None,
        }

    by_texel = []
    for k, (lo, hi) in enumerate(ROUGHNESS_BANDS):
        for m, (mlo, mhi) in enumerate(METALLIC_BANDS):
            mask = _band(ro, lo, hi, k == len(ROUGHNESS_BANDS) - 1) & _band(
                me, mlo, mhi, m == len(METALLIC_BANDS) - 1
            )
            by_texel.append({"roughness": [lo, hi], "metallic": [mlo, mhi], **group(mask)})
    by_cos = [
        {"cos_theta_i": [lo, hi], **group(_band(ci, lo, hi, k == len(COS_BANDS) - 1))}
        for k, (lo, hi) in enumerate(COS_BANDS)
    ]
    by_cos_d = [
        {"cos_theta_d": [lo, hi], **group(_band(cd, lo, hi, k == len(COS_D_BANDS) - 1))}
        for k, (lo, hi) in enumerate(COS_D_BANDS)
    ]
    by_edge = [
        {"tile_edge_distance": [lo, hi], **group(_band(ed, lo, hi, k == len(EDGE_BANDS) - 1))}
        for k, (lo, hi) in enumerate(EDGE_BANDS)
    ]
    order = np.sort(d2)[::-1]
    worst = [
        {"pairs_share": s, "error_share": float(order[: max(1, int(s * len(d2)))].sum() / total)}
        for s in WORST
    ]
    write_json(
        out_path,
        {
            **tp.header("textured_anatomy", "dev", args.quick, load_before),
            "teacher": f"write_teacher(principled, size 512, seed {bench.SEEDS['dev']}) "
            "(development)",
            "recipe": settings,
            "pairs": tp.pairs_entry("dev", pairs_n),
            "rel_rmse": got["rel_rmse"],
            "rel_rmse_sets": got["rel_rmse_sets"],
            "by_texel": by_texel,
            "by_cos_theta_i": by_cos,
            "by_cos_theta_d": by_cos_d,
            "by_tile_edge": by_edge,
            "alpha_vs_teacher": alpha,
            "worst_pairs": worst,
            "file_bytes": file_bytes,  # f alone, without the normal field
            "teacher_map_bytes": teacher_bytes,  # the teacher's EXR maps together
            "rescored": args.rescore,  # then seconds is the scoring's alone
            "reprojected": args.reproject,  # then seconds leaves the training out
            "projection": {k: v for k, v in (made.get("projection") or {}).items() if k != "refit"}
            or None,
            "seconds": time.perf_counter() - t0,
        },
    )
    print(f"wrote {out_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
