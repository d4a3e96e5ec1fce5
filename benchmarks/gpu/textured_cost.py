"""Issue 30's render cost on another machine: the textured files in a CUDA variant.

    python benchmarks/gpu/textured_cost.py --train runs/gpu_models        # on a CPU, llvm
    python benchmarks/gpu/textured_cost.py --variant cuda_ad_rgb --models runs/gpu_models \
        --out /tmp/textured_cost.json                                     # on the GPU

``--train`` writes the test set's three files of benchmarks/textured.py with its recipe
(``SETTINGS`` for the textured principled and roughplastic, the pipeline's compact recipe for
the homogeneous principled) into a folder: training reads the teacher through Mitsuba's
llvm variant on a CPU, which a GPU machine without libLLVM lacks.  The second form renders
benchmarks/textured.py's render-cost comparison (bsdf_bound's ``render_cost``: its
BSDF-bound scene, interleaved rounds in rotating order after one compiling render each,
best of ``--repeats``) with those files and Mitsuba's own textured principled (the whole
teacher, and its nested BSDF), the teachers' maps written again by the same deterministic
recipe.  It renders at each ``--size`` (default 256x64 and 1024x128: resolution x spp).

Nothing here asserts a speed; the JSON (ratios per size, the device, the load) is copied to
benchmarks/results/cuda/textured_cost.json and tools/results_tables.py makes its table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import bsdf_bound  # noqa: E402  (sets --variant's Mitsuba variant, registers the plugins)
import textured  # noqa: E402
from common import write_json  # noqa: E402

FILES = ("principled_textured", "roughplastic_textured", "principled_plain")


def train(folder: Path) -> None:
    """The test set's three files, as benchmarks/textured.py trains them."""
    import torch

    from neural_brdf.measured.textured import TexturedMitsubaTarget

    torch.set_num_threads(2)
    folder.mkdir(parents=True, exist_ok=True)
    seconds = {}
    with tempfile.TemporaryDirectory(prefix="nbrdf-textured-cost-") as tmp:
        specs = textured.write_teachers(Path(tmp), "test", textured.SIZE)
        for name in FILES:
            spec, work = specs[name], Path(tmp) / name
            work.mkdir(parents=True, exist_ok=True)
            if spec["textured"]:
                teacher = TexturedMitsubaTarget(str(spec["xml"]))
                path, fig = textured.train_textured_file(teacher, work, textured.SETTINGS)
            else:
                path, fig = textured.train_homogeneous_file(Path(spec["xml"]), work, False)
            shutil.copyfile(path, folder / f"{name}.onnx")
            seconds[name] = fig["total_seconds"]
            print(f"{name}: {fig['total_seconds']:.0f} s", flush=True)
    (folder / "trained.json").write_text(
        json.dumps({"settings": textured.SETTINGS, "seconds": seconds}, indent=1)
    )


def device_name() -> str:
    import mitsuba as mi

    if mi.variant().startswith("cuda"):
        import torch

        if torch.cuda.is_available():
            return torch.cuda.get_device_name(0)
        return "a CUDA GPU"
    return "CPU (llvm)"


def measure(models: Path, sizes: list[tuple[int, int]], repeats: int) -> dict:
    import mitsuba as mi

    missing = [n for n in FILES if not (models / f"{n}.onnx").is_file()]
    if missing:
        raise SystemExit(f"--models {models}: no {missing[0]}.onnx (make them with --train)")
    result: dict = {
        "benchmark": "textured_cost",
        "variant": mi.variant(),
        "device": device_name(),
        "mitsuba": mi.__version__,
        "settings": textured.SETTINGS,
        "files": {n: (models / f"{n}.onnx").stat().st_size for n in FILES},
        "sizes": {},
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    trained = models / "trained.json"
    if trained.is_file():
        result["trained"] = json.loads(trained.read_text())
    with tempfile.TemporaryDirectory(prefix="nbrdf-textured-cost-") as tmp:
        specs = textured.write_teachers(Path(tmp), "test", textured.SIZE)
        prin = specs["principled_textured"]["xml"]
        bsdfs: dict[str, object] = {
            f"neural {n}": {"type": "neural_brdf", "filename": str(models / f"{n}.onnx")}
            for n in FILES
        }
        bsdfs["mitsuba principled_textured"] = mi.load_file(str(prin))
        bsdfs["mitsuba principled_textured nested"] = mi.load_file(str(textured.nested_xml(prin)))
        for res, spp in sizes:
            print(f"{res}^2 x {spp} spp:", ", ".join(bsdfs), flush=True)
            c = bsdf_bound.render_cost(bsdfs, res, spp, repeats)
            c["ratios"] = textured.cost_ratios(c["best_s"])
            print(json.dumps(c["ratios"], indent=1), flush=True)
            result["sizes"][f"{res}x{spp}"] = c
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", default="llvm_ad_rgb")  # read by bsdf_bound at import
    ap.add_argument("--train", type=Path, default=None, help="write the three files here")
    ap.add_argument("--models", type=Path, default=None, help="the folder --train wrote")
    ap.add_argument("--size", action="append", default=[], metavar="RESxSPP")
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.train is not None:
        train(args.train)
        return 0
    if args.models is None or args.out is None:
        ap.error("--models and --out (or --train)")
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.size] or [(256, 64), (1024, 128)]
    result = measure(args.models, sizes, args.repeats)  # type: ignore[arg-type]
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
