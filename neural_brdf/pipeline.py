"""The pipeline of a run: train -> export -> validate -> report, in one place.

    from neural_brdf import config, pipeline
    metrics = pipeline.run(config.load("configs/gold.yaml"), "runs/gold")

    target (analytic, measured data, a Mitsuba BSDF)  --train.loop.train-->  RawBRDF
        + log.csv + ckpt.pt (or images  --inverse.fit-->  RawBRDF)
    RawBRDF  --export.normalized_model, export.build-->  the graph (parity checked)
    the graph  --validate.physics-->  its figures  --export.write-->  model.onnx
    model.onnx  --validate.report-->  metrics.json
    run folder  --report.write_report-->  report.html, report.md

``neural-brdf train`` calls :func:`run`.  Each stage module knows only the stages before
it (train knows data and model; export knows the model; validate reads model.onnx), and
this module is the only one that knows them all.  A run holds its folder
(:func:`neural_brdf.runfolder.hold`: the lock, and the rules of which folders a run may
write into) from start to end.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any

from neural_brdf import config as cfgmod
from neural_brdf import export as exp
from neural_brdf import runfolder, validate
from neural_brdf.errors import InputError
from neural_brdf.target import Target, spatially_varying
from neural_brdf.train import data, loop, target_files
from neural_brdf.train.encoding import is_anisotropic
from neural_brdf.train.session import MUST_MATCH, REPORT_PENDING, TEXTURED_MUST_MATCH


def run(
    cfg: cfgmod.Config,
    run_dir: str | Path | None = None,
    *,
    resume: bool = False,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train, export ``model.onnx``, validate it, write the report; returns (and writes)
    ``metrics.json``.

    A folder that is neither new, empty nor a run raises
    :class:`neural_brdf.runfolder.NotARunFolder`; a fresh run (no ``resume``) into a
    folder that already holds a run raises :class:`neural_brdf.runfolder.RunExists`
    unless ``overwrite`` (:func:`neural_brdf.runfolder.check_fresh_run_dir`).  Resuming
    a run that has finished at ``train.steps`` writes nothing and returns its
    metrics.json with ``"already_finished"`` set to the step.  A config with
    ``target.images`` is fitted by inverse rendering (:mod:`neural_brdf.inverse.fit`,
    docs/inverse.md; its settings are the config's ``images`` section), then exported
    and validated without a reference.
    """
    run_dir = Path(run_dir) if run_dir is not None else runfolder.default_run_dir(cfg)
    with runfolder.hold(run_dir, resume=resume, overwrite=overwrite) as folder:
        if cfg.target.kind == "images":
            from neural_brdf.inverse import fit as inverse  # Mitsuba: only for an images fit

            done = inverse.finished_report(cfg, run_dir, folder) if resume else None
            if done is not None:  # nothing is written (docs/cli.md, resume)
                return {**done, "already_finished": done["training"]["steps"]}
            raw, training, t0, cfg = inverse.fit(  # cfg: its grid as the start chose it
                cfg, run_dir, resume=resume, overwrite=overwrite, folder=folder
            )
            return finish(cfg, run_dir, raw, training, t0=t0, report=True)
        return _run(cfg, folder, resume=resume)


def run_many(
    cfgs: list[cfgmod.Config],
    out: str | Path,
    *,
    overwrite: bool = False,
    report: bool = False,
    sources: list[str] | None = None,
) -> list[dict[str, Any]]:
    """Train every config in one batch (:func:`neural_brdf.train.many.train_many`) into
    ``out/NAME``, then export and validate each (and write its report with ``report``);
    returns the metrics.json of each, in order.  ``sources`` (the config files, one per
    config) name the file in an error about one config.  Every folder is checked before any is
    written; an old run in one (``overwrite``) is replaced only when the batch has
    trained."""
    from contextlib import ExitStack

    from neural_brdf.train import many

    label = sources if sources is not None else [f"config {c.name}" for c in cfgs]
    many.check_batchable(cfgs, label)
    names = [c.name for c in cfgs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        both = [src for src, n in zip(label, names) if n == twice[0]]
        raise cfgmod.ConfigError(
            f"name: {twice[0]!r} is given to two materials of the batch ({both[0]} and "
            f"{both[1]}; give each its own name, in its config file)"
        )
    t0 = time.perf_counter()
    targets = []  # built before any folder is made: a bad target changes nothing
    for src, c in zip(label, cfgs):
        try:
            targets.append(data.build_target(c.target))
        except InputError as e:  # say which file of the batch holds the bad target
            raise cfgmod.ConfigError(f"{src}: {e}") from None
    for src, target in zip(label, targets):
        if spatially_varying(target):
            raise cfgmod.ConfigError(
                f"{src}: target.mitsuba: {target.describe()}: a textured teacher trains "
                "alone (neural-brdf train), not in a batch"
            )
    for c, target in zip(cfgs, targets):  # as a run alone prints them (:func:`_run`)
        for line in teacher_warnings(c, target, textured=False):
            print(f"{c.name}: warning: {line}", file=sys.stderr)
    run_dirs = [Path(out) / n for n in names]
    for run_dir in run_dirs:  # a folder of the user's: refused before any lock file
        runfolder.check_writable(run_dir)
    with ExitStack() as stack:
        folders = [
            stack.enter_context(runfolder.hold(d, resume=False, overwrite=overwrite))
            for d in run_dirs
        ]
        trained = many.train_many(cfgs, run_dirs, targets=targets, folders=folders)
        return [
            finish(cfg, run_dir, raw, training, t0=t0, target=target, report=report)
            for cfg, run_dir, target, (raw, training) in zip(cfgs, run_dirs, targets, trained)
        ]


def _run(cfg: cfgmod.Config, folder: runfolder.Folder, *, resume: bool) -> dict[str, Any]:
    run_dir = folder.path
    t0 = time.perf_counter()
    # a Mitsuba teacher is loaded first: whether it varies over the surface decides the
    # loop (and the kind of checkpoint a resumed run must have)
    target = data.build_target(cfg.target) if cfg.target.mitsuba is not None else None
    textured = spatially_varying(target)
    started = os.path.lexists(run_dir / runfolder.MARKER)  # this run's first write
    if resume and started and not folder.ckpt.exists() and not (run_dir / runfolder.MODEL).exists():
        # stopped before its first checkpoint (kill -9 within train.checkpoint_every
        # steps, SIGTERM while starting): a scheduler's restart with --resume trains it
        # from step 0, where it refused every time before (a run that wrote its model
        # and lost its checkpoint is not replaced: load_resumable says so)
        print(
            f"{cfg.name}: {folder.ckpt} does not exist yet (the run was stopped before its "
            "first checkpoint): it trains from step 0",
            file=sys.stderr,
        )
        resume = False
    ckpt = (
        loop.load_resumable(
            cfg,
            folder.ckpt,
            kind="textured" if textured else None,
            must_match=TEXTURED_MUST_MATCH if textured else MUST_MATCH,
        )
        if resume
        else None
    )
    if ckpt is not None and int(ckpt["step"]) == cfg.train.steps:
        done = loop.finished_report(run_dir, cfg.train.steps)
        if done is not None:
            return {**done, "already_finished": cfg.train.steps}
    if target is None:
        target = data.build_target(cfg.target)
    for line in teacher_warnings(cfg, target, textured=textured):
        print(f"{cfg.name}: warning: {line}", file=sys.stderr)
    if textured:
        from neural_brdf.train import textured_loop

        if cfg.train.device == "cuda":
            print(f"{cfg.name}: a textured model trains on the CPU", file=sys.stderr)
        model, training = textured_loop.train(
            cfg, run_dir, target=target, resume=resume, checkpoint=ckpt, folder=folder
        )
        return finish_textured(cfg, run_dir, model, training, t0=t0, target=target)
    raw, training = loop.train(
        cfg, run_dir, resume=resume, target=target, checkpoint=ckpt, folder=folder
    )
    return finish(cfg, run_dir, raw, training, t0=t0, target=target)


# a uniform teacher whose albedo passes 1 by more than this is said so when its run starts
# (bounded by less, a perfect conductor's quadrature noise near grazing, 1.0014 for GGX
# alpha 0.2, changes f by less than the network's own error)
EXCESS_WARNING = 0.01


def teacher_warnings(cfg: cfgmod.Config, target: Any, *, textured: bool) -> list[str]:
    """What the run will do that the config did not say: a legitimate input whose file
    differs from what the user may assume (one line each; the run goes on)."""
    out = list(getattr(target, "warnings", ()))
    if getattr(target, "anisotropic", False) and not is_anisotropic(cfg.model.encoding):
        out.append(
            f"model.encoding: {cfg.model.encoding} cannot depend on the azimuth, but the "
            "teacher changes when turned about the normal (anisotropic): the file learns "
            "its average over the azimuth; set model.encoding: anisotropic"
        )
    if textured and cfg.target.mitsuba is not None:  # the file's field, projected or not
        from neural_brdf.train.textured_model import detail_warning

        line = detail_warning(target, cfg.texture.project or cfg.texture.resolution)
        if line is not None:
            out.append(line)
    excess = getattr(target, "excess", None)  # a textured teacher's: at the end (finish_textured)
    if (
        cfg.target.mitsuba is not None
        and not textured
        and excess is not None
        and excess["max_albedo"] > 1.0 + EXCESS_WARNING
    ):
        out.append(
            f"{cfg.target.mitsuba}: the teacher's albedo exceeds 1 (max "
            f"{excess['max_albedo']:.4f} in {excess['channel']} at theta_i "
            f"{excess['at_theta_deg']:g} deg): the model learns its energy-bounded version, "
            "f / max(1, A(wi), A(wo)), and its accuracy is measured against that"
        )
    if cfg.target.mitsuba is not None and not textured and cfg.texture != cfgmod.Texture():
        out.append(
            f"texture: ignored: {cfg.target.mitsuba} does not vary over the surface, so "
            "the file is a homogeneous BRDF"
        )
    return out


def finish_textured(
    cfg: cfgmod.Config,
    run_dir: Path,
    model: Any,
    training: dict[str, Any],
    *,
    t0: float,
    target: Any,
    report: bool = True,
) -> dict[str, Any]:
    """:func:`finish` for a textured model (``train.textured_loop.train``'s): each lobe
    normalised and, with ``texture.project``, the field projected
    (``export.textured_for_export``), the graph of (wi, wo, uv) built and checked
    (``export.build_textured``), its physics measured at random uv
    (``validate.physics_textured``), ``model.onnx`` written with the ``texture`` entry,
    the accuracy against the teacher at random uv, ``metrics.json`` and the report."""
    t1 = time.perf_counter()
    excess = target.measure_excess(seed=cfg.validation.seed + 5, tol=cfg.validation.albedo_tol)
    if excess is not None:
        print(
            f"{cfg.name}: the teacher's albedo reaches {excess['max_albedo']:.4f} (at uv "
            f"{excess['at_uv']}); the model learns its energy-bounded version",
            file=sys.stderr,
        )
    normalized, tables, projection = exp.textured_for_export(model, cfg, target)
    if projection is not None:  # texture.project: the field fitted texel by texel
        training = {**training, "projection": projection}
        # kept for export RUN, which would otherwise project and refit again
        from neural_brdf.train import textured_store

        textured_store.save(
            run_dir / runfolder.TEXTURED, normalized, tables, projection, cfg, model.state_dict()
        )
    built = exp.build_textured(exp.with_normal_field(normalized, target), cfg)
    phys = validate.physics_textured(
        built.eval,
        anisotropic=built.anisotropic,
        settings=cfg.validation,
        uv_count=cfg.texture.validation_uv,
    )
    exp.write(
        built,
        cfg,
        run_dir / "model.onnx",
        physics=phys,
        target=target,
        target_desc=target.describe(),
        texture_info=tables,
    )
    metrics = _record(
        run_dir,
        built,
        tables,
        phys,
        training,
        target=target,
        t0=t0,
        t1=t1,
        report=report,
        extra={"teacher_excess": excess},
    )
    warn = getattr(target, "normal_field_warning", None)  # a Mitsuba teacher's
    line = warn(metrics.get("normal_field")) if warn is not None else None
    if line is not None:  # a bump map's relief the file's normal field does not hold
        print(f"{cfg.name}: warning: {line}", file=sys.stderr)
    return metrics


def finish(
    cfg: cfgmod.Config,
    run_dir: Path,
    raw: Any,
    training: dict[str, Any],
    *,
    t0: float,
    target: Target | None = None,
    report: bool = True,
) -> dict[str, Any]:
    """The stages after training: export ``raw`` (normalised) to ``model.onnx`` with the
    physics validate measured on its graph, validate it (against ``target`` when there is
    one: an images fit has none), write ``metrics.json`` and, with ``report``,
    report.html / report.md (an images fit's describes the views and the coverage).
    ``seconds.report`` is in the metrics only when the report was written.  ``t0``: when
    the run started (``time.perf_counter()``), for the total."""
    t1 = time.perf_counter()
    model, table = exp.normalized_model(raw, cfg, target)
    desc = target.describe() if target is not None else training["target"]
    built = exp.build(model, cfg)  # the graph, checked against torch
    phys = validate.physics(
        built.eval, anisotropic=built.anisotropic, settings=cfg.validation, target=target
    )
    exp.write(built, cfg, run_dir / "model.onnx", physics=phys, target=target, target_desc=desc)
    return _record(
        run_dir, built, table, phys, training, target=target, t0=t0, t1=t1, report=report
    )


def _record(
    run_dir: Path,
    built: exp.Built,
    table: Any,
    phys: dict[str, Any],
    training: dict[str, Any],
    *,
    target: Any,
    t0: float,
    t1: float,
    report: bool,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """After ``model.onnx`` is written (export began at ``t1``, the run at ``t0``): its
    validation (``phys``, measured on the graph before writing, is reused), the training
    figures, ``extra`` entries, the export's and the stages' times, ``metrics.json`` and,
    with ``report``, report.html / report.md (``seconds.report`` only then)."""
    t2 = time.perf_counter()
    metrics = validate.report(run_dir / "model.onnx", target=target, physics_report=phys)
    metrics[runfolder.MODEL_DIGEST] = target_files.sha256(run_dir / "model.onnx")
    t3 = time.perf_counter()
    metrics["training"] = training
    metrics.update(extra or {})
    metrics["export"] = {
        "parity_rel_error": built.parity_rel_error,
        "float32_rel_precision": built.float32_rel_precision,
        "normalization": table,
        "seconds": t2 - t1,
    }
    metrics["seconds"] = {
        # an images fit: its start's choice and distillation, and the whole fit (the
        # start, the image stage, the checks around them; not for a resumed run, whose
        # process timed its own part alone); train is its image stage
        **({"start": training["start_seconds"]} if "start_seconds" in training else {}),
        **(
            {"fit": training["fit_seconds"]}
            if "fit_seconds" in training and not training.get("resumed")
            else {}
        ),
        "train": training["train_seconds"],
        "export": t2 - t1,
        "validate": t3 - t2,
        "total": t3 - t0,
    }
    if report:  # until the report is written: a run stopped in it is not finished
        metrics[REPORT_PENDING] = True
    validate.write_json(metrics, run_dir / "metrics.json")
    if not report:
        return metrics
    from neural_brdf.viewer.report import write_report  # matplotlib: only when a run has finished

    write_report(run_dir)  # report.html / report.md from the files above
    del metrics[REPORT_PENDING]
    metrics["seconds"]["report"] = time.perf_counter() - t3
    metrics["seconds"]["total"] = time.perf_counter() - t0
    validate.write_json(metrics, run_dir / "metrics.json")
    return metrics
