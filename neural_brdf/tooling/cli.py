"""``neural-brdf`` command line: argument parsing and error-to-exit-code mapping only.

    neural-brdf train CONFIG|PRESET [--out RUN_DIR] [--set KEY=VALUE ...] [--resume|--overwrite]
    neural-brdf train-many CONFIG|PRESET ... --out FOLDER [--set KEY=VALUE ...] [--overwrite]
    neural-brdf presets
    neural-brdf export RUN_DIR [-o model.onnx]
    neural-brdf report RUN_DIR [-o OUT_DIR]
    neural-brdf validate model.onnx [--reference CONFIG|MEASURED] [--json out.json]
    neural-brdf bake model.onnx|CONFIG -o MEASURED
    neural-brdf render model.onnx [--reference CONFIG] [--spp N] -o out.png|out.jpg
    neural-brdf sweep SWEEP.yaml [--executor local|ray] [--workers N] [--ray-address ADDR]
    neural-brdf codegen model.onnx --target c|glsl|wgsl [--prefix NAME] -o FILE
    neural-brdf view model.onnx [--compare OTHER.onnx|TEACHER.xml|CONFIG] [--uv U,V] -o viewer.html

A CONFIG (train, train-many, validate, bake, render, view) may be a preset's name instead
(``gold``, ``mitsuba/roughplastic``: ``neural-brdf presets``).  A MEASURED file's suffix
names its format (:mod:`neural_brdf.measured.formats`; ``neural-brdf bake --help`` lists
the registered ones).

Exit codes: 0 success; 1 a physics check failed (also: training diverged, or the ONNX
graph failed the parity check -- the model cannot be trusted); 2 bad input (a one-line
message on stderr, never a traceback: a bad key, file or option, a folder in use, a
full disk); 130 interrupted by Ctrl-C, 143 (128 + 15) by SIGTERM, as docker, systemd,
Slurm and Ray send it (a checkpoint was written; ``--resume`` continues).

Output files are replaced atomically (a temporary file, then a rename); a symbolic link
is followed, and a device or FIFO (``-o /dev/null``) is written in place.  ``-o -``
writes a text output (codegen, view, validate --json) to stdout; binary outputs refuse
it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
from pathlib import Path

# Idle OpenMP threads that spin made torch's elementwise ops 10-40x slower on a busy
# 2-core machine (measured: 0.7 ms -> 30 ms); sleeping ones cost nothing measurable.
# Only effective before torch is first imported, which this module does not do.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from neural_brdf.errors import InputError, not_a_file  # noqa: E402  (light: no torch, no pydantic)

EXIT_OK, EXIT_PHYSICS, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130  # SIGTERM: 128 + 15
STDOUT = "-"  # -o -: the output on stdout (text formats only)
# what ``codegen --target``'s help says of a target (backends.TARGETS lists them; one
# without a note here is listed by its name)
TARGET_NOTES = {"c": "a C99 header", "glsl": "GLSL ES 3.00 / 4.50", "wgsl": "WebGPU"}


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of usage + message
        raise _UsageError(f"{self.prog}: {message} (see --help)")


class _UsageError(Exception):
    pass


def _parser() -> argparse.ArgumentParser:
    from neural_brdf.version import __version__

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

    tm = sub.add_parser(
        "train-many",
        help="train several materials in one batch (same network and optimisation)",
    )
    tm.add_argument("configs", nargs="+", help="YAML config files or preset names")
    tm.add_argument("--out", required=True, help="folder: one run folder per config name")
    tm.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key in every config (repeatable)",
    )
    tm.add_argument("--overwrite", action="store_true", help="replace runs already there")
    tm.add_argument("--report", action="store_true", help="also write each run's report")

    sub.add_parser("presets", help="list the shipped configs (neural-brdf train NAME)")

    e = sub.add_parser("export", help="export a run's checkpoint to ONNX")
    e.add_argument("run_dir")
    e.add_argument("-o", "--out", help="output file (default: RUN_DIR/model.onnx)")

    rp = sub.add_parser("report", help="write a run's report.html and report.md")
    rp.add_argument("run_dir")
    rp.add_argument("-o", "--out", help="output folder (default: RUN_DIR)")

    # the measured formats by suffix, from their registry (numpy only, as backends)
    from neural_brdf.measured import formats

    measured = formats.known()  # ".binary (MERL), .bsdf (RGL)"

    v = sub.add_parser("validate", help="check physics (and accuracy) of an exported model")
    v.add_argument("model")
    v.add_argument(
        "--reference",
        help="ground truth: a config (its target) or a preset name, or a measured file "
        f"by its suffix: {measured}",
    )
    v.add_argument("--json", help="write the report as JSON to this file")

    b = sub.add_parser(
        "bake",
        help="tabulate a model (.onnx) or a config's analytic target as a measured file "
        f"(the output's suffix names the format: {measured})",
    )
    b.add_argument(
        "source", help="model.onnx, or a YAML config (or a preset name) whose target is baked"
    )
    b.add_argument("-o", "--out", required=True, help=f"output file, by its suffix: {measured}")

    r = sub.add_parser(
        "render",
        help="render a material preview in Mitsuba 3 (needs the mitsuba extra and libllvm19)",
    )
    r.add_argument("model", help="model.onnx")
    r.add_argument(
        "--reference",
        help="a config (or a preset name) whose analytic target or Mitsuba teacher is "
        "rendered beside it, with an error map and PSNR",
    )
    r.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    r.add_argument("--resolution", type=int, default=256, help="image height in pixels")
    r.add_argument("-o", "--out", required=True, help="output image: .png, or .jpg/.jpeg (JPEG)")

    from neural_brdf.backends import TARGETS

    g = sub.add_parser(
        "codegen",
        help=f"generate source code ({', '.join(TARGETS)}) that evaluates and "
        "samples the model (docs/codegen.md)",
    )
    g.add_argument("model", help="model.onnx")
    g.add_argument(
        "--target",
        required=True,
        choices=list(TARGETS),
        help=", ".join(f"{t} ({TARGET_NOTES[t]})" if t in TARGET_NOTES else t for t in TARGETS),
    )
    g.add_argument(
        "--prefix",
        default=None,
        help="prefix of every name the code defines (default neural_brdf: neural_brdf_eval, "
        "NEURAL_BRDF_H); give each model its own to use several in one program",
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
        help="a second model (.onnx), a Mitsuba teacher (.xml), or a config (or a preset "
        "name) whose analytic target or Mitsuba teacher is shown beside it with a "
        "difference view",
    )
    vw.add_argument(
        "--uv",
        action="append",
        metavar="U,V",
        help="a textured model's plots at this point uv (repeatable; default four points)",
    )
    vw.add_argument("-o", "--out", required=True, help="output .html")

    w = sub.add_parser("sweep", help="run (or resume) a sweep of trainings (docs/sweeps.md)")
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


def _warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def _output_file(out: str, what: str, flag: str = "-o") -> None:
    """Refuse ``-o -`` for a binary output, ``-o FOLDER`` and a file in a folder that
    does not exist (InputError, exit 2): a mistyped path is an error, not a new folder,
    as for codegen and view (:func:`neural_brdf.fileio.atomic_path`)."""
    if out == STDOUT:
        raise InputError(
            f"{flag} -: {what} is binary, not for stdout; give a file name "
            "(-o - is for text: codegen, view, validate --json)"
        )
    if Path(out).is_dir():
        raise InputError(f"{flag} {out}: is a folder; give a file name ({what})")
    _output_folder(out, flag)


def _output_folder(out: str, flag: str = "-o") -> None:
    """Refuse an output file spelled as a folder's (``-o out/``) or whose folder does not
    exist (or is a file): InputError (:func:`neural_brdf.fileio.check_output_folder`)."""
    from neural_brdf.fileio import check_output_folder

    check_output_folder(out, flag)


# A run folder's own files (neural_brdf.runfolder owns the list): no command's output may
# replace one of them, except the file that command exists to write into its own run.
def _not_an_input(
    out: str | None,
    inputs: dict[str, str | None],
    *,
    flag: str,
    may: str | os.PathLike | None = None,
) -> None:
    """Refuse an output (``flag out``) that is one of the command's ``inputs`` (name ->
    path) or one of a run folder's own files (other than the path ``may``, the file the
    command writes into the run it was given): writing it would destroy what the command
    was given, or leave another run's files describing two runs (InputError, exit 2;
    nothing is written)."""
    if out is None or out == STDOUT:
        return
    target = Path(os.path.realpath(out))
    for what, path in inputs.items():
        if path is None or path == STDOUT:
            continue
        same = target == Path(os.path.realpath(path))
        if not same:
            with contextlib.suppress(OSError):
                same = os.path.samefile(out, path)
        if same:
            raise InputError(
                f"{flag} {out}: is the {what} this command reads; give another output file"
            )
    from neural_brdf import runfolder

    allowed = may is not None and target == Path(os.path.realpath(may))
    if not allowed and runfolder.is_own_file(target):
        raise InputError(
            f"{flag} {out}: is a file of the run in {target.parent}; give a file outside "
            "the run folder (or another name)"
        )


def _same_path(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    return Path(os.path.realpath(a)) == Path(os.path.realpath(b))


@contextlib.contextmanager
def _holding(run_dir: str | os.PathLike):
    """Hold a run folder's lock (:func:`neural_brdf.runfolder.run_lock`) while a command
    writes a run's own file into it (``export RUN``, ``report RUN``): a run still
    training there (train, resume) is refused in one line, exit 2, instead of having
    its files replaced under it.  A folder that is not a run is left to the command."""
    from neural_brdf import runfolder

    path = Path(run_dir)
    if not (path.is_dir() and runfolder.is_run(path)):
        yield
        return
    with runfolder.run_lock(path, elsewhere="write elsewhere with -o"):
        yield


def _cannot_write(path, e: OSError) -> Exception:
    """The one-line error of a failed write of ``path``; a pipe whose reader left
    (``codegen -o /dev/stdout | head``) stays a BrokenPipeError, which ends quietly
    (:func:`main`), as ``-o -`` does."""
    if isinstance(e, BrokenPipeError):
        return e
    return InputError(f"{path}: cannot write ({e.strerror})")


def _write_files(payloads: dict[str, bytes]) -> None:
    """Each file of ``payloads`` (path -> bytes) atomically (see fileio), and all of them
    or none: every one is written to its temporary file before the first is renamed, and
    a failed write removes them all."""
    from neural_brdf.fileio import atomic_write_all

    try:
        atomic_write_all(payloads)
    except OSError as e:
        raise _cannot_write(e.filename or next(iter(payloads)), e) from None


def _write_text(out: str, text: str) -> None:
    """``text`` to the file ``out`` (atomic; see fileio) or, for ``-``, to stdout."""
    from neural_brdf.fileio import atomic_write

    if out != STDOUT:
        try:
            atomic_write(out, text)
        except OSError as e:
            raise _cannot_write(out, e) from None
        return
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except BrokenPipeError:
        raise
    except OSError as e:  # e.g. > /dev/full: no second try at exit
        _stdout_to_devnull()
        raise InputError(f"stdout: cannot write ({e.strerror})") from None


def _stdout_to_devnull() -> None:
    """Point fd 1 at /dev/null, so that the interpreter's last flush cannot fail."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _train(args) -> int:
    from neural_brdf import presets

    if args.out == STDOUT:
        raise InputError("--out -: a run is a folder, not stdout")
    path = presets.resolve(args.config)  # an unknown name fails before torch loads
    from neural_brdf import config

    # a bad config fails before torch loads
    _not_measured(path)
    cfg = config.load(path, args.overrides, warn=_warn)
    from neural_brdf import pipeline, validate
    from neural_brdf.train import loop

    run_dir = Path(args.out) if args.out else loop.default_run_dir(cfg)
    try:
        report = pipeline.run(cfg, run_dir, resume=args.resume, overwrite=args.overwrite)
    except config.ConfigError as e:  # a key checked after validation: target.params
        blamed = config.blamed(e, str(path), args.overrides)
        data = cfg.target.data
        gone = bool(data) and not os.path.lexists(str(data))
        if gone and not args.resume and str(e).startswith("target.data:"):
            # configs/merl.yaml names a placeholder: say how to give one's own file
            blamed = config.ConfigError(f"{blamed} (give yours with --set target.data=FILE)")
        raise blamed from None
    if report.get("already_finished") is not None:
        # an images run stopped early: a larger train.steps would stop it again at once
        advice = report.get("resume_advice") or "raise train.steps to train on"
        print(
            f"{run_dir}: already finished at step {report['already_finished']}; nothing "
            f"to do ({advice}, or --overwrite to start again)"
        )
        return EXIT_OK
    print(validate.format_table(report))
    for note in validate.accuracy_notes(report):  # what the exit code (physics) does not see
        print(f"note: {note}", file=sys.stderr)
    s = report["seconds"]
    # seconds.report is there only when the report was written (pipeline.finish)
    written = "report" in s and (run_dir / "report.html").is_file()
    stages = stage_times(s)
    print(
        f"run: {run_dir}  ({stages}, report {s['report']:.1f} s: report.html)"
        if written
        else f"run: {run_dir}  ({stages}; no report written)"
    )
    return EXIT_OK if report["passed"] else EXIT_PHYSICS


def stage_times(s: dict[str, float]) -> str:
    """The run's last line's times (metrics.json's ``seconds``): an images fit's whole
    fit, its start and its image stage (``train``), else the training; then the export
    and the validation."""
    fit = f"train {s['train']:.1f} s"
    if "start" in s:  # (a resumed images fit has no whole fit's time)
        fit = f"start {s['start']:.1f} s, image stage {s['train']:.1f} s"
        fit = f"fit {s['fit']:.1f} s: {fit}" if "fit" in s else fit
    return f"{fit}, export {s['export']:.1f} s, validate {s['validate']:.1f} s"


def _train_many(args) -> int:
    from neural_brdf import presets

    paths = [presets.resolve(c) for c in args.configs]  # unknown names fail before torch
    from neural_brdf import config

    cfgs = [config.load(path, args.overrides, warn=_warn) for path in paths]
    from neural_brdf import pipeline, validate

    reports = pipeline.run_many(
        cfgs,
        Path(args.out),
        overwrite=args.overwrite,
        report=args.report,
        sources=[str(p) for p in paths],
    )
    errors = {}
    for cfg, report in zip(cfgs, reports):
        acc = report.get("accuracy") or {}
        err = ""
        if "rel_rmse" in acc:
            errors[cfg.name] = acc["rel_rmse"]
            err = f"rel_rmse (f cos) {100 * acc['rel_rmse']:.2f} %"
        verdict = "ok" if report["passed"] else "FAILED"
        print(f"{cfg.name}: physics {verdict}  {err}  -> {Path(args.out) / cfg.name}")
    s = reports[0]["seconds"]
    worst = max(errors, key=errors.__getitem__) if errors else None
    accuracy = (
        f"; accuracy, which is reported and not judged: worst rel_rmse "
        f"{100 * errors[worst]:.2f} % ({worst})"
        if worst is not None
        else ""
    )
    print(
        f"{len(cfgs)} materials in one batch: train {s['train']:.1f} s for all of them; "
        f"{sum(r['passed'] for r in reports)} of {len(cfgs)} passed the physics checks"
        f"{accuracy}"
    )
    if any(not r["passed"] for r in reports):
        print(validate.format_table(next(r for r in reports if not r["passed"])))
    return EXIT_OK if all(r["passed"] for r in reports) else EXIT_PHYSICS


def _presets(args) -> int:
    from neural_brdf import presets

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


def _target_files_of(run_dir: str) -> dict[str, str]:
    """The files a run's target reads (its measured file, a teacher and its bitmaps, an
    images fit's scenes and images), named as inputs: export reads the target (for its
    accuracy) and must not write over them.  {} where the run's config cannot be read
    (export's own error says why)."""
    from neural_brdf import config
    from neural_brdf.train import target_files

    try:
        cfg = config.load(Path(run_dir) / "config.yaml", run=True)
    except (InputError, OSError):
        return {}
    return {f"run's {target_files.where(cfg, p)} ({p})": p for p in target_files.files(cfg)}


def _export(args) -> int:
    if args.out is not None:
        _output_file(args.out, "an ONNX model")
        _not_an_input(
            args.out,
            {"run folder": args.run_dir, **_target_files_of(args.run_dir)},
            flag="-o",
            may=Path(args.run_dir) / "model.onnx",
        )
    from neural_brdf import export, validate

    # export writes (and checks parity); validate measures the graph and gives the verdict
    into_run = args.out is None or _same_path(args.out, Path(args.run_dir) / "model.onnx")
    with _holding(args.run_dir) if into_run else contextlib.nullcontext():
        info = export.export_run(
            args.run_dir,
            args.out,
            measure=validate.physics,
            measure_textured=validate.physics_textured,
        )
    c = info["physics"]["checks"]
    t = info.get("target") or {}
    fitted = f" (an images fit of {t['views']} views)" if t.get("kind") == "images" else ""
    print(
        f"wrote {info['path']}{fitted}: parity {info['parity_rel_error']:.2g}, max albedo "
        f"{c['max_albedo']['value']:.6f}, reciprocity {c['reciprocity']['value']:.2g}"
    )
    if into_run:
        _metrics_of_another_model(Path(args.run_dir))
    return EXIT_OK if validate.physics_passed(info["physics"]) else EXIT_PHYSICS


def _metrics_of_another_model(run_dir: Path) -> None:
    """After ``export RUN`` into the run: a note when its metrics.json measured another
    model.onnx (a config.yaml edited, another machine's float sums), which ``report
    RUN`` then refuses (neural_brdf.viewer.report.run)."""
    from neural_brdf.train.session import measured_another_model, remeasure_advice

    try:
        metrics = json.loads((run_dir / "metrics.json").read_text())
        another = isinstance(metrics, dict) and measured_another_model(metrics, run_dir)
    except (OSError, ValueError):
        return  # no metrics.json to describe the old file (or none readable)
    if another:
        print(
            f"note: {run_dir / 'metrics.json'} measured the model.onnx that was there, not "
            f"this one (report RUN refuses it now); {remeasure_advice(run_dir)}",
            file=sys.stderr,
        )


def _report(args) -> int:
    if args.out == STDOUT:
        raise InputError("-o -: the report is a folder of files, not for stdout")
    from neural_brdf import runfolder
    from neural_brdf.viewer.report import write_report

    if args.out is not None and runfolder.is_run(Path(args.out)):
        if not _same_path(args.out, args.run_dir):
            raise InputError(
                f"-o {args.out}: is another run's folder (its report would describe "
                f"{args.run_dir}); give a folder outside it, or leave -o out"
            )
    into_run = args.out is None or _same_path(args.out, args.run_dir)
    with _holding(args.run_dir) if into_run else contextlib.nullcontext():
        paths = write_report(args.run_dir, args.out)
    others = sorted(p.name for k, p in paths.items() if k not in ("html", "md"))
    print(
        f"wrote {paths['html']} and {paths['md']}"
        + (f" with {', '.join(others)}" if others else "")
    )
    return EXIT_OK


def _validate(args) -> int:

    from neural_brdf import validate

    if args.json and args.json != STDOUT:  # before the validation's time is spent
        if Path(args.json).is_dir():
            raise InputError(f"--json {args.json}: is a folder; give a file name")
        _output_folder(args.json, "--json")
    given = _preset_or_path(args.reference)  # a preset name, as train takes one
    _not_an_input(args.json, {"model": args.model, "reference": given}, flag="--json")
    reference = validate.reference_from(given, warn=_warn) if given else None
    report = validate.report(args.model, target=reference)
    # "passed" is the physics' verdict (train's); this one is the exit code's, the peak too
    report["checks_passed"] = validate.passed(report)
    # with --json -, stdout carries the JSON alone and the table goes to stderr
    table_to = sys.stderr if args.json == STDOUT else sys.stdout
    print(validate.format_table(report), file=table_to)
    # a poor accuracy, which the exit code does not see (the peak's is in it)
    for note in validate.accuracy_notes(report, peak=False):
        print(f"note: {note}", file=sys.stderr)
    if args.json == STDOUT:
        # as validate.write_json writes it (NaN and infinities as strings)
        from neural_brdf.fileio import json_text

        _write_text(STDOUT, json_text(report))
    elif args.json:
        try:
            validate.write_json(report, args.json)
        except OSError as e:
            raise _cannot_write(args.json, e) from None
    return EXIT_OK if report["checks_passed"] else EXIT_PHYSICS  # the peak too


def _preset_or_path(text: str | None) -> str | None:
    """A preset name (``gold``, ``mitsuba/roughplastic``: ``neural-brdf presets``) as its
    config file, as ``train`` takes one; anything else as it is: a file that exists wins,
    and a missing one with a suffix (``x.onnx``, ``x.yaml``) is reported by whoever reads
    it.  A bare name that is neither: InputError listing the presets, as train's."""
    if not text or text == STDOUT or Path(text).is_file():  # a folder does not shadow one
        return text
    from neural_brdf import presets

    try:
        return str(presets.resolve(text))
    except InputError:
        if not Path(text).suffix:
            raise
        return text  # the command's own message names the missing file


def _not_measured(path: str | os.PathLike | None) -> None:
    """A measured file (MERL, RGL: :func:`neural_brdf.measured.formats.find`, by suffix
    or an RGL file's first bytes) where a config goes: one line saying so (read as
    YAML it was "more than a config may be" or "not UTF-8")."""
    if path is None or path == STDOUT:
        return
    from neural_brdf.measured import formats

    fmt = formats.find(path)
    if fmt is not None:
        raise InputError(
            f"{path}: measured data ({fmt.name} {fmt.suffix}), not a config file (a config "
            "names measured data as target.data)"
        )


def _analytic_target(config_path: str):
    """The analytic model of a config's target (measured-data targets are refused)."""
    from neural_brdf import config

    _not_measured(config_path)

    if Path(config_path).suffix.lower() == ".xml":  # else read as YAML: "expected a mapping"
        raise InputError(
            f"{config_path}: a Mitsuba file; give a config of an analytic target here (a "
            "Mitsuba teacher is compared with neural-brdf view MODEL --compare FILE.xml)"
        )
    from neural_brdf.train import data

    cfg = config.load(config_path, warn=_warn)  # an empty config: train's warning
    data.refuse_images(cfg.target, config_path)  # its target.model: the unused default
    return _analytic_of(cfg, config_path)


def _analytic_of(cfg, config_path: str):
    """(name, params, BRDF) of a loaded config's analytic target; a measured or Mitsuba
    one is refused, naming ``config_path``."""
    from neural_brdf.train import data

    for key in ("data", "mitsuba"):
        if getattr(cfg.target, key) is not None:
            raise InputError(f"{config_path}: target.{key}: only analytic targets here")
    # a bad model or parameter: train's message (target.model, target.params), after the file
    brdf = data.build_target(cfg.target, source=config_path)
    return cfg.target.model, dict(cfg.target.params), brdf


def _render_reference(path: str, model) -> tuple[dict | None, tuple | None]:
    """``render --reference``: ({"model", "params"} of a config's analytic target, None),
    or (None, (Mitsuba BSDF, words)) of its Mitsuba teacher (``target.mitsuba``),
    homogeneous or textured, rendered by Mitsuba as the report renders it
    (:func:`neural_brdf.viewer.report.sections.teacher_to_render`)."""
    from neural_brdf import config
    from neural_brdf.train import data

    if Path(path).suffix.lower() == ".xml":  # else read as YAML: "expected a mapping"
        raise InputError(
            f"{path}: a Mitsuba file; give a config whose target names it (target: "
            f"{{mitsuba: {Path(path).name}}}) or an analytic target here (neural-brdf view "
            "MODEL --compare FILE.xml takes the file itself)"
        )
    cfg = config.load(path, warn=_warn)  # an empty config: train's warning
    data.refuse_images(cfg.target, path)  # its target.model: the unused default
    if cfg.target.data is not None:
        raise InputError(
            f"{path}: target.data: render compares analytic targets and Mitsuba "
            "teachers only (a measured table is not a BSDF Mitsuba renders)"
        )
    if cfg.target.mitsuba is None:
        name, params, _ = _analytic_of(cfg, path)
        return {"model": name, "params": params}, None
    from neural_brdf.viewer.report.sections import teacher_to_render

    # (a teacher of target.variant cuda_ad_rgb: one line, the render runs in llvm_ad_rgb)
    teacher = teacher_to_render(model, data.build_target(cfg.target, source=path))
    assert teacher is not None  # a Mitsuba target always has its BSDF
    return None, teacher


def _bake(args) -> int:
    """The output format by its suffix: :mod:`neural_brdf.measured.formats`."""
    from neural_brdf.measured import formats

    suffixes = ", ".join(f.suffix for f in formats.all_formats())
    _output_file(args.out, f"a tabulated BRDF ({suffixes})")
    _not_an_input(args.out, {"source": args.source}, flag="-o")
    fmt = formats.format_of(args.out)  # an unknown suffix: InputError naming the known ones
    if Path(args.source).suffix.lower() == ".onnx":
        from neural_brdf.runtime import load
        from neural_brdf.train.encoding import is_anisotropic

        model = load(args.source)
        _project_model(model, args.source)
        _homogeneous(model, args.source, "bake", "an RGL or MERL table holds one BRDF")
        encoding = model.metadata.get("encoding")  # none (a file edited by hand): unknown
        if encoding is None or is_anisotropic(encoding):  # an unknown one counts as such
            raise InputError(
                f"{args.source}: encoding {encoding or '(none in its metadata)'}: the model "
                f"may depend on the azimuth; {_ISOTROPIC_TABLES}"
            )
        fn = model.eval
    else:  # a config, or a preset's name
        name, _, brdf = _analytic_target(_preset_or_path(args.source) or args.source)
        if brdf.anisotropic:
            raise InputError(f"{args.source}: target: an anisotropic {name}; {_ISOTROPIC_TABLES}")
        fn = brdf.eval
    try:
        fmt.bake(fn, args.out)
    except OSError as e:
        raise _cannot_write(args.out, e) from None
    print(f"wrote {args.out} ({fmt.name})")
    return EXIT_OK


# why bake refuses an anisotropic model or target (docs/rgl.md)
_ISOTROPIC_TABLES = (
    "bake writes isotropic tables only (MERL, and RGL with one phi_i: anisotropic .bsdf "
    "files are not written yet)"
)


def _homogeneous(model, path: str, command: str, why: str) -> None:
    """Refuse a textured file (inputs wi, wo, uv) where ``command`` draws one BRDF."""
    if getattr(model, "textured", False):
        raise InputError(
            f"{path}: a textured model (inputs wi, wo, uv): {command} takes a homogeneous "
            f"one ({why}); render it with neural-brdf render"
        )


def _project_model(model, path: str) -> None:
    """Refuse an ONNX file that was not written by neural-brdf (no format version in its
    metadata): its graph may take (wi, wo) and mean anything else (exit 2)."""
    if "format_version" not in model.metadata:
        raise InputError(
            f"{path}: an ONNX model without neural-brdf's metadata (no format_version): "
            "not a neural BRDF this command can trust; export one with neural-brdf"
        )


MAX_RESOLUTION = 16384  # render's --resolution at most


def _render(args) -> int:
    from neural_brdf.runtime import load

    if args.spp < 1 or args.resolution < 8:
        raise InputError("render: --spp must be >= 1 and --resolution >= 8")
    if args.resolution > MAX_RESOLUTION:
        raise InputError(f"render: --resolution {args.resolution}: at most {MAX_RESOLUTION}")
    samples = args.resolution**2 * args.spp  # the film is square; one pass renders them all
    if samples >= 2**32:
        raise InputError(
            f"render: --resolution {args.resolution} at --spp {args.spp}: {samples:.3g} "
            "samples, more than Mitsuba renders in one pass (2^32); lower either"
        )
    from neural_brdf import limits

    # the film's RGBA and weight, the image and its display copy: float32
    limits.check_bytes(f"render: --resolution {args.resolution}", 64.0 * args.resolution**2)
    _output_file(args.out, "a PNG or JPEG image")
    given = _preset_or_path(args.reference)  # a preset name, as train takes one
    _not_measured(given)
    _not_an_input(args.out, {"model": args.model, "reference": given}, flag="-o")
    model = load(args.model)
    _project_model(model, args.model)  # an empty, foreign or broken file: exit 2
    try:
        import mitsuba as mi
    except ImportError:
        raise InputError(
            "render: needs Mitsuba 3: pip install -e '.[mitsuba]' and apt-get install libllvm19"
        ) from None
    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb")
    from neural_brdf.renderers import render as nbr

    nbr.image_format(args.out)  # .png, .jpg or .jpeg: refused before the render
    reference, teacher = _render_reference(given, model) if given else (None, None)
    info = nbr.render_comparison(
        args.model,
        args.out,
        reference=reference,
        reference_bsdf=teacher[0] if teacher else None,
        spp=args.spp,
        resolution=args.resolution,
    )
    if info["psnr"] is None:
        print(f"wrote {args.out}")
    else:
        versus = f"the teacher: {teacher[1]}" if teacher else "reference"
        print(
            f"wrote {args.out}  (PSNR {info['psnr']:.2f} dB vs {versus}; panels: neural, "
            f"target, |difference| x {info['gain']:g})"
        )
    return EXIT_OK


def _view(args) -> int:
    from neural_brdf import fileio
    from neural_brdf.runtime import load
    from neural_brdf.viewer import page as viewer

    probes = viewer.parse_probes(args.uv)
    if args.out != STDOUT:
        _output_folder(args.out)
    args.compare = _preset_or_path(args.compare)  # a preset name, as train takes one
    _not_measured(args.compare)
    if args.uv and Path(args.model).is_file() and not load(args.model).textured:
        raise InputError(f"--uv: {args.model} is not a textured model (its plots have no uv)")
    _not_an_input(
        args.out,
        {"model": args.model, "compared model": args.compare},
        flag="-o",
        # the run's own viewer, of its own model.onnx only (not of another file put there)
        may=Path(args.model).parent / "viewer.html"
        if Path(args.model).name == "model.onnx"
        else None,
    )

    if args.out == STDOUT or fileio.written_in_place(args.out):  # /dev/stdout, a FIFO: any name
        models = viewer.models_for(args.model, args.compare, probes=probes, warn=_warn)
        title = f"neural-brdf viewer: {Path(args.model).name}"  # as write_viewer's
        _write_text(args.out, viewer.page(models, title=title, probes=probes))
        if args.out != STDOUT:  # not into the page, when the device is stdout
            print(f"wrote {args.out}", file=sys.stderr)
        return EXIT_OK
    # into a run folder (its own viewer.html): while holding its lock, as export RUN and
    # report RUN do, so that a run training there does not race the write
    with _holding(Path(os.path.realpath(args.out)).parent):
        written = viewer.write_viewer(
            args.model, args.out, compare=args.compare, probes=probes, warn=_warn
        )
    print(f"wrote {written}")
    return EXIT_OK


def _sweep(args) -> int:
    from neural_brdf import presets

    path = presets.resolve(args.sweep, folder="sweeps")
    from neural_brdf.tooling import sweep

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


def _has_uv(model: str) -> bool:
    """Whether ``model`` (checked readable by codegen already) is a textured file."""
    from neural_brdf.fileformat import SIGNATURES, reader

    return reader.signature(reader.load(model, external_data=False), source=model) == SIGNATURES[1]


def _codegen(args) -> int:
    from neural_brdf import backends
    from neural_brdf.fileio import written_in_place

    if not Path(args.model).is_file():
        raise InputError(not_a_file(args.model, "model"))
    if args.out != STDOUT and Path(args.out).is_dir():
        raise InputError(f"-o {args.out}: is a folder; give a file name")
    if args.out != STDOUT:
        _output_folder(args.out)
    _not_an_input(args.out, {"model": args.model}, flag="-o")
    # -o -, /dev/stdout, a FIFO: stdout may be the code itself, so status goes to stderr
    in_place = args.out == STDOUT or written_in_place(args.out)
    text = backends.generate(args.model, args.target, prefix=args.prefix)
    # a textured file's code reads its weight table from buffers the host binds: their
    # data go next to the code, OUT's stem + .texture<k>.f32 (docs/codegen.md)
    textures = backends.textures(args.model) if _has_uv(args.model) else []
    if textures and args.out == STDOUT:
        _warn(
            "the textures are not written with -o -: give -o FILE (FILE's stem + "
            ".texture<k>.f32) or use neural_brdf.backends.textures()"
        )
        textures = []
    elif textures and in_place:
        raise InputError(
            f"-o {args.out}: not a regular file; a textured model's textures are written "
            "beside its code (FILE's stem + .texture<k>.f32): give a file path (or -o - "
            "for the code alone)"
        )
    stem = Path(args.out).with_suffix("")
    files = {f"{stem}.texture{k}.f32": t for k, t in enumerate(textures)}
    for path in files:  # every check before the first write
        _not_an_input(path, {"model": args.model}, flag="-o")
    if files:  # the textures and the code: all of them or none
        payloads = {p: t.astype("<f4").tobytes() for p, t in files.items()}
        _write_files({**payloads, args.out: text.encode("utf-8")})
    else:
        _write_text(args.out, text)
    status = sys.stderr if in_place else sys.stdout
    for k, (path, t) in enumerate(files.items()):
        print(f"wrote {path} (texture {k}: {t.shape[0]} x {t.shape[1]} float32)", file=status)
    print(
        f"wrote {'stdout' if args.out == STDOUT else args.out} "
        f"({args.target}, {text.count(chr(10))} lines)",
        file=status,
    )
    return EXIT_OK


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, as Ctrl-C raises KeyboardInterrupt: the
    same clean-ups run (no temporary file is left) and the exit code is 143."""

    signum = signal.SIGTERM


def _on_sigterm(signum, frame):
    raise _Terminated("terminated (SIGTERM)")


@contextlib.contextmanager
def _sigterm_as_interrupt(command: str):
    """SIGTERM behaves as Ctrl-C while ``command`` runs (training checkpoints between
    steps: train.deferred_interrupt), except for ``sweep``: its workers stop on the
    terminal's Ctrl-C, which reaches the whole process group."""
    if command == "sweep" or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def _error(message: str) -> None:
    """One line on stderr, at most limits.MAX_MESSAGE characters."""
    from neural_brdf.limits import bounded

    print(bounded(message), file=sys.stderr)


# the arguments that name a file or folder, and how the user wrote them
_PATHS = {
    "config": "CONFIG",
    "configs": "CONFIG",
    "sweep": "SWEEP",
    "run_dir": "RUN_DIR",
    "model": "MODEL",
    "source": "SOURCE",
    "out": "--out",
    "json": "--json",
    "reference": "--reference",
    "compare": "--compare",
}


def _no_empty_paths(args) -> None:
    """Refuse an empty path (``--out ""``, an unset shell variable): it would be taken as
    'not given', and the run would go to runs/NAME, the JSON nowhere (InputError)."""
    for dest, flag in _PATHS.items():
        value = getattr(args, dest, None)
        values = value if isinstance(value, list) else [value]
        if any(isinstance(v, str) and not v.strip() for v in values):
            raise InputError(f"{flag}: an empty path; give a file or folder name")


def _exit_code(e: BaseException) -> int:
    """128 + the signal that interrupted the program: 130 (Ctrl-C), 143 (SIGTERM)."""
    return 128 + int(getattr(e, "signum", None) or signal.SIGINT)


def main(argv: list[str] | None = None) -> int:
    # errors, not config/export/train: --help, --version and presets stay free of torch
    from neural_brdf.errors import Diverged, InputError, Interrupted, ParityError

    try:
        args = _parser().parse_args(argv)
        _no_empty_paths(args)
        commands = {
            "train": _train,
            "train-many": _train_many,
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
        with _sigterm_as_interrupt(args.command):
            return commands[args.command](args)
    except (_UsageError, InputError) as e:
        _error(f"error: {e}")
        return EXIT_INPUT
    except Diverged as e:
        _error(f"error: training diverged: {e}")
        return EXIT_PHYSICS
    except ParityError as e:
        _error(f"error: export: {e}")
        return EXIT_PHYSICS
    except (Interrupted, KeyboardInterrupt) as e:
        signum = getattr(e, "signum", None)
        what = "terminated (SIGTERM)" if signum == signal.SIGTERM else "interrupted (Ctrl-C)"
        _error(f"neural-brdf: {str(e).strip() or what}")
        return _exit_code(e)
    except BrokenPipeError:  # `neural-brdf presets | head`: the reader left; no traceback
        _stdout_to_devnull()
        return 0
    except OSError as e:  # the file system: a full disk, a read-only folder, ...
        where = f"{e.filename}: " if e.filename else ""
        _error(f"error: {where}{e.strerror or e}")
        return EXIT_INPUT
    except MemoryError:  # a size no check foresaw: still one line, never a traceback
        _error(
            "error: out of memory; a size in the config or the file is too large "
            "(docs/cli.md, Limits)"
        )
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
