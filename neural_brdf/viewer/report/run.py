"""Reading a finished run folder: config, metrics, log and model, with one-line
errors that name the file and key; the reference the report compares against."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neural_brdf import config as cfgmod
from neural_brdf import runfolder
from neural_brdf.errors import InputError
from neural_brdf.runtime import NeuralBRDF, load
from neural_brdf.train import data
from neural_brdf.train.session import LOG_COLUMNS, measured_another_model, remeasure_advice

# the run's files a report reads (their names: runfolder)
RUN_FILES = (runfolder.CONFIG, runfolder.METRICS, runfolder.LOG, runfolder.MODEL)
RENDER_SPP = 16  # Mitsuba preview: enough to judge the material, seconds to render
RENDER_RESOLUTION = 128
VIEWER_FILE = runfolder.VIEWER  # the interactive viewer, beside the report


# ------------------------------------------------------------------ reading a run
@dataclass
class Run:
    dir: Path
    config: cfgmod.Config
    config_text: str
    metrics: dict
    log: dict  # step, loss, val_step, val_rel_rmse: numpy arrays; columns: {name: array}
    model: NeuralBRDF

    @property
    def images(self) -> bool:
        """A fit to images by inverse rendering (``target.images``): no reference BRDF."""
        return self.config.target.kind == "images"


def _number(d: dict, dotted: str, path: Path, *, optional: bool = False):
    """The number at ``a.b.c`` (``a.0`` indexes a list) of a metrics dict; InputError
    naming the file and the key."""
    x = d
    for part in dotted.split("."):
        if isinstance(x, list) and part.isdigit() and int(part) < len(x):
            x = x[int(part)]
        elif isinstance(x, dict) and part in x:
            x = x[part]
        elif optional:
            return None
        else:
            raise InputError(f"{path}: {dotted}: missing")
    return _as_number(x, dotted, path)


def _as_number(x, key: str, path: Path) -> float:
    try:
        if isinstance(x, bool):
            raise TypeError
        return float(x)  # write_json stores inf / nan as strings
    except (TypeError, ValueError):
        raise InputError(f"{path}: {key}: not a number ({x!r})") from None


def _read_metrics(path: Path) -> dict:
    try:
        metrics = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON (line {e.lineno}: {e.msg})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    if not isinstance(metrics, dict):
        raise InputError(f"{path}: not a JSON object (not a metrics.json of a run?)")
    checks = metrics.get("checks")
    if checks is None:
        raise InputError(f"{path}: checks: missing (not a metrics.json of a run?)")
    if not isinstance(checks, dict) or not checks:
        kind = "an empty object" if isinstance(checks, dict) else type(checks).__name__
        raise InputError(f"{path}: checks: expected an object of the checks, got {kind}")
    for name, c in checks.items():
        if not isinstance(c, dict) or not isinstance(c.get("passed"), bool):
            raise InputError(f"{path}: checks.{name}.passed: missing or not true/false")
        _number(metrics, f"checks.{name}.value", path)
        _number(metrics, f"checks.{name}.limit", path)
    return metrics


def _float_or_nan(text: str | None) -> float:
    try:
        return float(text) if text else math.nan
    except ValueError:
        return math.nan


def _read_log(path: Path) -> dict:
    """log.csv's step, loss and held-out error, and ``columns``: every further column a
    loop wrote (an images fit's losses, ...), name -> values per row (NaN where empty)."""
    step, loss, val_step, val = [], [], [], []
    extra: dict[str, list[float]] = {}
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            if not reader.fieldnames or not {"step", "loss"} <= set(reader.fieldnames):
                raise InputError(f"{path}: expected a CSV with columns step, loss, ...")
            names = [n for n in reader.fieldnames if n not in LOG_COLUMNS]
            extra = {n: [] for n in names}
            for line, row in enumerate(reader, start=2):
                try:
                    step.append(float(row["step"]))
                    loss.append(float(row["loss"]))
                    if row.get("val_rel_rmse"):
                        val.append(float(row["val_rel_rmse"]))
                        val_step.append(step[-1])
                    for n in names:  # a loop's own column: a number, or NaN
                        extra[n].append(_float_or_nan(row.get(n)))
                except (TypeError, ValueError):
                    raise InputError(f"{path}: line {line}: not a number") from None
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    out: dict = {
        k: np.asarray(v, dtype=np.float64)
        for k, v in (("step", step), ("loss", loss), ("val_step", val_step), ("val_rel_rmse", val))
    }
    out["columns"] = {n: np.asarray(v, dtype=np.float64) for n, v in extra.items()}
    return out


def _describes_the_model(metrics: dict, run_dir: Path) -> None:
    """InputError unless ``metrics`` (its sha256 of the model it measured, written since
    session 96) is of the run's model.onnx: a file re-exported (``export RUN`` after an
    edit of config.yaml) or put there since was reported with the old file's figures
    and verdicts beside its own plots.  A metrics.json without the digest is read as
    before."""
    model = run_dir / "model.onnx"
    try:
        another = measured_another_model(metrics, run_dir)
    except OSError as e:
        raise InputError(f"{model}: cannot read ({e.strerror or e})") from None
    if another:
        raise InputError(
            f"{run_dir / 'metrics.json'}: measured another model.onnx than the one in the "
            "run (re-exported or replaced since), so its figures would not describe it; "
            f"{remeasure_advice(run_dir)}"
        )


def load_run(run_dir) -> Run:
    """Read a run directory; a missing or garbled file raises InputError naming it."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run directory")
    for name in RUN_FILES:
        if not (run_dir / name).is_file():
            raise InputError(
                f"{run_dir / name}: missing (a run directory holds {', '.join(RUN_FILES)})"
            )
    cfg = cfgmod.load(run_dir / "config.yaml", run=True)
    metrics = _read_metrics(run_dir / "metrics.json")
    log = _read_log(run_dir / "log.csv")
    model = load(run_dir / "model.onnx")  # (a file that is no model: said as such first)
    _describes_the_model(metrics, run_dir)
    return Run(
        dir=run_dir,
        config=cfg,
        config_text=(run_dir / "config.yaml").read_text(),
        metrics=metrics,
        log=log,
        model=model,
    )


def reference_of(cfg: cfgmod.Config):
    """(the target model, None), or (None, why not): a data target not buildable here, or
    an images fit (``target.images``), which has no reference BRDF at all."""
    if cfg.target.images is not None:  # not the default target.model (a Lambertian)
        n = len(cfg.target.images)
        return (
            None,
            f"No reference: an images fit ({n} view{'s' if n != 1 else ''}, fitted by "
            "inverse rendering) has no target BRDF to compare with; the figures show the "
            "neural model alone.",
        )
    try:
        return data.build_target(cfg.target), None
    except InputError as e:
        if cfg.target.data is None:
            raise
        return (
            None,
            f"No reference: the measured target {cfg.target.data} could not be "
            f"loaded here ({e}); the figures show the neural model alone.",
        )
