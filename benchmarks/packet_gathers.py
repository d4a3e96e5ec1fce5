"""The Dr.Jit back end's packet gathers, on and off, in the BSDF-bound scene.

    python benchmarks/packet_gathers.py compact=runs/quickstart/model.onnx \
        textured=runs/textured/model.onnx [--variant cuda_ad_rgb] [--repeats 6]

The plugin's back end reads the gathered columns of a tensor as 4-wide packets from a
cache-line-aligned copy (neural_brdf/backends/drjit.py, "Gathers");
``neural_brdf.backends.drjit.PACKET_GATHERS = False`` before a model is loaded gives the
one-gather-per-column evaluation.  Each model is loaded both ways, beside Mitsuba's
built-in ``roughconductor`` (GGX alpha 0.3, Au: bsdf_bound.py's yardstick), and every
scene is rendered in interleaved rounds of rotating order after one compiling render
each, in one process; the figures are best-of wall times and their ratios.  The images
of the two evaluations are compared too (they must be equal: the same floats).

Nothing is chosen here (the packing has no setting to tune); the recorded files are the
README's quickstart model and the test-set files of benchmarks/textured.py.

Writes results/packet_gathers.json (merged by label, with the machine's load).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import bsdf_bound  # noqa: E402  (sets the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi
import numpy as np
from common import write_json

from neural_brdf.backends import drjit as backend

OUT = Path(__file__).resolve().parent / "results" / "packet_gathers.json"
REFERENCE = {"type": "roughconductor", "distribution": "ggx", "material": "Au", "alpha": 0.3}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+", help="LABEL=PATH of an exported model")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--variant", default=bsdf_bound.VARIANTS[0], choices=bsdf_bound.VARIANTS)
    args = ap.parse_args(argv)
    models = {}
    for item in args.models:
        label, sep, path = item.partition("=")
        if not sep or not Path(path).is_file():
            print(f"packet_gathers: {item!r}: expected LABEL=PATH of a model file", file=sys.stderr)
            return 2
        models[label] = path
    before = bsdf_bound.machine()
    # the switch is read when a model is loaded: each neural BSDF is loaded here, both ways
    bsdfs: dict[str, object] = {"roughconductor": REFERENCE}
    for label, path in models.items():
        for mode in ("packets", "columns"):
            backend.PACKET_GATHERS = mode == "packets"
            bsdfs[f"{label} {mode}"] = mi.load_dict({"type": "neural_brdf", "filename": path})
    backend.PACKET_GATHERS = True
    images: dict[str, np.ndarray] = {}
    cost = bsdf_bound.render_cost(bsdfs, args.resolution, args.spp, args.repeats, images)
    runs, best = cost["render_wall_s"], cost["best_s"]
    ref = best["roughconductor"]
    result = json.loads(args.out.read_text()) if args.out.is_file() else {}
    result.update(
        {
            "benchmark": "packet_gathers",
            "variant": mi.variant(),
            "mitsuba": mi.__version__,
            "drjit": dr.__version__,
            "scene": f"bsdf_bound.scene, {args.resolution}^2, {args.spp} spp",
            "reference": REFERENCE,
            "repeats": args.repeats,
        }
    )
    entries = result.setdefault("models", {})
    for label, path in models.items():
        p, c = best[f"{label} packets"], best[f"{label} columns"]
        same = bool(np.array_equal(images[f"{label} packets"], images[f"{label} columns"]))
        entries[label] = {
            "model": str(path),
            "render_wall_s": {k: runs[f"{label} {k}"] for k in ("packets", "columns")},
            "reference_wall_s": runs["roughconductor"],
            "best_s": {"packets": p, "columns": c, "roughconductor": ref},
            "packets_over_columns": p / c,
            "vs_roughconductor": {"packets": p / ref, "columns": c / ref},
            "images_equal": same,
            "machine_start": before,
            "machine_end": bsdf_bound.machine(),
            "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        print(
            f"{label}: packets {p:.3f} s, columns {c:.3f} s ({p / c:.3f}x); "
            f"vs roughconductor {p / ref:.2f}x and {c / ref:.2f}x; images equal: {same}"
        )
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
