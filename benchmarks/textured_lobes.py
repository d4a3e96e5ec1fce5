"""Development-set comparison of the textured model's lobe networks (issue 30):
``texture.lobe_network`` separate (K networks) against shared (one network, K heads).

    python benchmarks/textured_lobes.py          # -> benchmarks/results/textured_lobes_dev.json

**Development set only.**  The teachers are ``write_teacher(kind, size=256, seed=1)``
(principled, roughplastic), the development teachers of benchmarks/textured.py at a
smaller size, as the per-channel weights were compared (docs/mitsuba.md); the test
set (seed 0) is never touched here.  The figures decide the recipe of
benchmarks/textured.py, which reports on the test set.

For each teacher and variant (:data:`VARIANTS`: separate with hidden [32]; shared with
hidden [32] and [64], and with K = 12 and 16), ``train_textured`` with K = 6 (unless the
variant says), a 64 x 64 field and 800 steps (:data:`RECIPE`, 2 torch threads), then:

* the held-out relative RMSE of f cos against Mitsuba's eval (``train_textured``'s
  ``val_rel_rmse``, raw lobes) and the training seconds;
* each lobe normalised (``normalized_textured``), the (wi, wo, uv) file exported;
* the render cost in benchmarks/bsdf_bound.py's BSDF-bound scene (256^2, 64 spp) of
  every file and of Mitsuba's own textured principled (the whole teacher), interleaved
  in rotating order after one compiling render each, best of ``--repeats``; the load
  average before and after (2 shared cores).

Nothing here asserts anything.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import bsdf_bound  # noqa: E402  (sets the Mitsuba variant, registers the plugins)
import mitsuba as mi  # noqa: E402
import torch  # noqa: E402
from common import write_json  # noqa: E402
from textured import loadavg  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
RECIPE = {"lobes": 6, "resolution": 64, "steps": 800, "size": 256, "seed": 1}
VARIANTS = {  # name: (texture.lobe_network, hidden widths, K)
    "separate_32": ("separate", [32], 6),
    "shared_32": ("shared", [32], 6),
    "shared_64": ("shared", [64], 6),
    "shared_32_k12": ("shared", [32], 12),
    "shared_32_k16": ("shared", [32], 16),
}


def main(argv: list[str] | None = None) -> int:
    from neural_brdf import export
    from neural_brdf.fileformat import SIGNATURES
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget
    from neural_brdf.train.textured_loop import train_textured
    from neural_brdf.train.textured_model import exportable, normalized_textured

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "textured_lobes_dev.json")
    ap.add_argument("--quick", action="store_true", help="a smoke test")
    args = ap.parse_args(argv)
    recipe = dict(RECIPE)
    if args.quick:
        recipe.update(lobes=2, resolution=8, steps=20, size=16)
    torch.set_num_threads(2)
    tmp = tempfile.TemporaryDirectory(prefix="nbrdf-lobes-")
    work = Path(tmp.name)
    t_start = time.perf_counter()
    result: dict = {
        "set": "dev: write_teacher(principled | roughplastic, size 256, seed 1); the test "
        "set (seed 0) is not used here",
        "recipe": recipe,
        "variants": {
            k: {"lobe_network": v[0], "hidden": v[1], "lobes": v[2]} for k, v in VARIANTS.items()
        },
        "machine_start": bsdf_bound.machine(),
        "teachers": {},
    }
    files: dict[str, Path] = {}
    xmls = {}
    for kind in ("principled", "roughplastic"):
        xml = write_teacher(work / kind, kind, size=recipe["size"], seed=recipe["seed"])
        xmls[kind] = xml
        teacher = TexturedMitsubaTarget(xml)
        rows = {}
        for name, (network, hidden, lobes) in VARIANTS.items():
            start = loadavg()
            model, fig = train_textured(
                teacher,
                lobes=lobes if not args.quick else recipe["lobes"],
                resolution=recipe["resolution"],
                hidden=hidden,
                steps=recipe["steps"],
                seed=0,
                lobe_network=network,
            )
            model, _ = normalized_textured(model)
            path = work / kind / f"{name}.onnx"
            path.write_bytes(export.to_onnx_bytes(exportable(model), 17, inputs=SIGNATURES[1]))
            files[f"{kind} {name}"] = path
            rows[name] = {
                "val_rel_rmse": fig["val_rel_rmse"],
                "init_val_rel_rmse": fig["init_val_rel_rmse"],
                "train_seconds": fig["train_seconds"],
                "lobes": fig["lobes"],
                "parameters": sum(p.numel() for p in model.parameters()),
                "file_bytes": path.stat().st_size,
                "loadavg": {"start": start, "end": loadavg()},
            }
            print(
                f"{kind} {name}: {100 * fig['val_rel_rmse']:.2f} % in {fig['train_seconds']:.0f} s",
                flush=True,
            )
        result["teachers"][kind] = rows
        write_json(args.out, result)
    bsdfs: dict[str, object] = {
        n: {"type": "neural_brdf", "filename": str(p)} for n, p in files.items()
    }
    bsdfs["mitsuba principled (whole teacher)"] = mi.load_file(str(xmls["principled"]))
    c = bsdf_bound.render_cost(bsdfs, 256, 64, args.repeats)
    best = c["best_s"]
    c["ratio_to_separate"] = {n: best[n] / best[f"{n.split()[0]} separate_32"] for n in files}
    result["render_cost"] = c
    result["machine_end"] = bsdf_bound.machine()
    result["wall_seconds"] = time.perf_counter() - t_start
    write_json(args.out, result)
    print({n: round(v, 3) for n, v in c["ratio_to_separate"].items()})
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
