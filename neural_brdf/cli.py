"""``neural-brdf`` command line: argument parsing and error-to-exit-code mapping only.

    neural-brdf train CONFIG|PRESET [--out RUN_DIR] [--set KEY=VALUE ...] [--resume|--overwrite]
    neural-brdf presets
    neural-brdf export RUN_DIR [-o model.onnx]
    neural-brdf report RUN_DIR [-o OUT_DIR]
    neural-brdf validate model.onnx [--reference CONFIG|material.binary|.bsdf] [--json out.json]
    neural-brdf bake model.onnx|CONFIG -o out.binary|out.bsdf
    neural-brdf sweep SWEEP.yaml [--executor local|ray] [--workers N] [--ray-address ADDR]
    neural-brdf codegen model.onnx --target c|glsl|wgsl -o FILE
    neural-brdf view model.onnx [--compare OTHER.onnx|CONFIG] -o viewer.html

Exit codes: 0 success; 1 a physics check failed (also: training diverged, or the ONNX
graph failed the parity check -- the model cannot be trusted); 2 bad input (a one-line
message on stderr, never a traceback); 130 interrupted by Ctrl-C (a checkpoint was
written; ``--resume`` continues).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# Idle OpenMP threads that spin made torch's elementwise ops 10-40x slower on a busy
# 2-core machine (measured: 0.7 ms -> 30 ms); sleeping ones cost nothing measurable.
# Only effective before torch is first imported, which this module does not do.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

EXIT_OK, EXIT_PHYSICS, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of usage + message
        raise _UsageError(f"{self.prog}: {message} (see --help)")


class _UsageError(Exception):
    pass


def _parser() -> argparse.ArgumentParser:
    from .version import __version__

    p = _Parser(prog="neural-brdf", description="Physically plausible neural BRDFs.")
    p.add_argument("--version", action="version", version=f"neural-brdf {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    t = sub.add_parser("train", help="train, export and validate a model from a YAML config")
    t.add_argument("config", help="YAML config file, or a preset name (neural-brdf presets)")
    t.add_argument("--out", help="run directory (default: runs/<name>/)")
    t.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key, e.g. --set train.steps=500 (repeatable)",
    )
    again = t.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true", help="continue from RUN_DIR/ckpt.pt")
    again.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a run already in RUN_DIR (its results are deleted)",
    )

    sub.add_parser("presets", help="list the shipped configs (neural-brdf train NAME)")

    e = sub.add_parser("export", help="export a run's checkpoint to ONNX")
    e.add_argument("run_dir")
    e.add_argument("-o", "--out", help="output file (default: RUN_DIR/model.onnx)")

    rp = sub.add_parser("report", help="write a run's report.html and report.md")
    rp.add_argument("run_dir")
    rp.add_argument("-o", "--out", help="output folder (default: RUN_DIR)")

    v = sub.add_parser("validate", help="check physics (and accuracy) of an exported model")
    v.add_argument("model")
    v.add_argument(
        "--reference",
        help="ground truth: a config (its target), a MERL "
        ".binary or an RGL .bsdf file (measured data)",
    )
    v.add_argument("--json", help="write the report as JSON to this file")

    b = sub.add_parser(
        "bake",
        help="tabulate a model (.onnx) or a config's analytic target: "
        "MERL .binary or RGL .bsdf (by the output extension)",
    )
    b.add_argument("source", help="model.onnx, or a YAML config whose target is baked")
    b.add_argument("-o", "--out", required=True, help="output file: .binary (MERL) or .bsdf (RGL)")

    r = sub.add_parser(
        "render",
        help="render a material preview in Mitsuba 3 (needs the mitsuba extra and libllvm19)",
    )
    r.add_argument("model", help="model.onnx")
    r.add_argument(
        "--reference",
        help="config whose analytic target is rendered beside it, with an error map and PSNR",
    )
    r.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    r.add_argument("--resolution", type=int, default=256, help="image height in pixels")
    r.add_argument("-o", "--out", required=True, help="output .png")

    g = sub.add_parser(
        "codegen",
        help="generate C / GLSL / WGSL source that evaluates and "
        "samples the model (docs/codegen.md)",
    )
    g.add_argument("model", help="model.onnx")
    from .backends import TARGETS

    g.add_argument(
        "--target",
        required=True,
        choices=list(TARGETS),
        help="c (a C99 header), glsl (GLSL ES 3.00 / 4.50) or wgsl (WebGPU)",
    )
    g.add_argument("-o", "--out", required=True, help="output file")
    vw = sub.add_parser(
        "view",
        help="write an interactive WebGL2 viewer (one HTML file) "
        "drawn with the model's generated GLSL",
    )
    vw.add_argument("model", help="model.onnx")
    vw.add_argument(
        "--compare",
        help="a second model (.onnx), or a config whose analytic "
        "target is shown beside it with a difference view",
    )
    vw.add_argument("-o", "--out", required=True, help="output .html")

    w = sub.add_parser("sweep", help="run (or resume) a sweep of trainings (neural_brdf/sweep.py)")
    w.add_argument("sweep", help="sweep file, or a preset sweep name (neural-brdf presets)")
    w.add_argument(
        "--executor",
        choices=["local", "ray"],
        default="local",
        help="local process pool (default) or Ray tasks",
    )
    w.add_argument("--workers", type=int, help="parallel trials (default: the CPU cores)")
    w.add_argument("--ray-address", help="Ray cluster to join (default: a local instance)")
    w.add_argument("--out", help="sweep folder (default: runs/sweeps/<name>/)")
    return p


def _train(args) -> int:
    from . import presets

    path = presets.resolve(args.config)  # an unknown name fails before torch loads
    from . import config

    cfg = config.load(path, args.overrides)  # a bad config fails before torch loads
    from . import train, validate

    run_dir = Path(args.out) if args.out else train.default_run_dir(cfg)
    report = train.run(cfg, run_dir, resume=args.resume, overwrite=args.overwrite)
    print(validate.format_table(report))
    s = report["seconds"]
    print(
        f"run: {run_dir}  (train {s['train']:.1f} s, export {s['export']:.1f} s, "
        f"validate {s['validate']:.1f} s, report {s['report']:.1f} s: report.html)"
    )
    return EXIT_OK if report["passed"] else EXIT_PHYSICS


def _presets(args) -> int:
    from . import presets

    rows = presets.listing()
    width = max(len(name) for name, _ in rows)
    for name, text in rows:
        print(f"{name:<{width}}  {text}")
    print(
        f"\n{len(rows)} presets in {presets.directory()}; train one with: "
        "neural-brdf train NAME [--out RUN_DIR] [--set KEY=VALUE]"
    )
    sweeps = presets.listing(folder="sweeps")
    print("\nsweeps (neural-brdf sweep NAME [--executor ray]):")
    for name, text in sweeps:
        print(f"  {name:<{width - 2}}  {text}")
    return EXIT_OK


def _export(args) -> int:
    from . import export

    info = export.export_run(args.run_dir, args.out)
    c = info["physics"]["checks"]
    print(
        f"wrote {info['path']}: parity {info['parity_rel_error']:.2g}, max albedo "
        f"{c['max_albedo']['value']:.6f}, reciprocity {c['reciprocity']['value']:.2g}"
    )
    return EXIT_OK if all(x["passed"] for x in c.values()) else EXIT_PHYSICS


def _report(args) -> int:
    from .report import write_report

    paths = write_report(args.run_dir, args.out)
    print(f"wrote {paths['html']} and {paths['md']}")
    return EXIT_OK


def _validate(args) -> int:
    from . import config, validate

    reference = validate.reference_from(args.reference) if args.reference else None
    report = validate.report(args.model, reference=reference)
    print(validate.format_table(report))
    if args.json:
        try:
            validate.write_json(report, args.json)
        except OSError as e:
            raise config.InputError(f"{args.json}: cannot write ({e.strerror})") from None
    return EXIT_OK if report["passed"] else EXIT_PHYSICS


def _analytic_target(config_path: str):
    """The analytic model of a config's target (measured-data targets are refused)."""
    import analytic

    from . import config

    cfg = config.load(config_path)
    if cfg.target.data is not None:
        raise config.InputError(f"{config_path}: target.data: only analytic targets here")
    return (
        cfg.target.model,
        dict(cfg.target.params),
        analytic.create(cfg.target.model, **cfg.target.params),
    )


# Output formats of ``bake``: suffix -> (name, module with ``bake(fn, path)``).  A third
# format is one entry here.
BAKE_FORMATS = {".binary": ("MERL", "merl"), ".bsdf": ("RGL", "rgl")}


def _bake(args) -> int:
    import importlib

    from . import config

    suffix = Path(args.out).suffix.lower()
    if suffix not in BAKE_FORMATS:
        known = ", ".join(f"{s} ({n})" for s, (n, _) in BAKE_FORMATS.items())
        raise config.InputError(
            f"{args.out}: unknown output extension {suffix or '(none)'!r}; known: {known}"
        )
    writer = importlib.import_module(f".{BAKE_FORMATS[suffix][1]}", __package__)
    if str(args.source).endswith(".onnx"):
        from .runtime import load

        fn = load(args.source).eval
    else:
        fn = _analytic_target(args.source)[2].eval
    try:
        writer.bake(fn, args.out)
    except OSError as e:
        raise config.InputError(f"{args.out}: cannot write ({e.strerror})") from None
    print(f"wrote {args.out} ({BAKE_FORMATS[suffix][0]})")
    return EXIT_OK


def _render(args) -> int:
    from .config import InputError

    try:
        import mitsuba as mi
    except ImportError:
        raise InputError(
            "render: needs Mitsuba 3: pip install -e '.[mitsuba]' and apt-get install libllvm19"
        ) from None
    if args.spp < 1 or args.resolution < 8:
        raise InputError("render: --spp must be >= 1 and --resolution >= 8")
    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb")
    from . import render as nbr

    reference = None
    if args.reference:
        name, params, _ = _analytic_target(args.reference)
        reference = {"model": name, "params": params}
    psnr = nbr.render_preview(
        args.model, args.out, reference=reference, spp=args.spp, resolution=args.resolution
    )
    print(f"wrote {args.out}" + ("" if psnr is None else f"  (PSNR {psnr:.2f} dB vs reference)"))
    return EXIT_OK


def _view(args) -> int:
    from .viewer import write_viewer

    print(f"wrote {write_viewer(args.model, args.out, compare=args.compare)}")
    return EXIT_OK


def _sweep(args) -> int:
    from . import presets

    path = presets.resolve(args.sweep, folder="sweeps")
    from . import sweep

    results = sweep.run_sweep(
        path,
        executor=args.executor,
        workers=args.workers,
        ray_address=args.ray_address,
        out=args.out,
        progress=sweep.print_progress,
    )
    print(sweep.summary_line(results))
    return EXIT_OK if all(r["status"] == "ok" for r in results["trials"]) else EXIT_PHYSICS


def _codegen(args) -> int:
    from . import backends
    from .config import InputError
    from .fileio import atomic_write

    if not Path(args.model).is_file():
        raise InputError(f"{args.model}: no such model file")
    text = backends.generate(args.model, args.target)
    try:
        atomic_write(args.out, text)
    except OSError as e:
        raise InputError(f"{args.out}: cannot write ({e.strerror})") from None
    print(f"wrote {args.out} ({args.target}, {text.count(chr(10))} lines)")
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    # errors, not config/export/train: --help, --version and presets stay free of torch
    from .errors import Diverged, InputError, Interrupted, ParityError

    try:
        args = _parser().parse_args(argv)
        commands = {
            "train": _train,
            "presets": _presets,
            "export": _export,
            "validate": _validate,
            "bake": _bake,
            "render": _render,
            "report": _report,
            "sweep": _sweep,
            "codegen": _codegen,
            "view": _view,
        }
        return commands[args.command](args)
    except (_UsageError, InputError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except Diverged as e:
        print(f"error: training diverged: {e}", file=sys.stderr)
        return EXIT_PHYSICS
    except ParityError as e:
        print(f"error: export: {e}", file=sys.stderr)
        return EXIT_PHYSICS
    except (Interrupted, KeyboardInterrupt) as e:
        print(f"neural-brdf: {e or 'interrupted'}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # `neural-brdf presets | head`: the reader left; no traceback
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
