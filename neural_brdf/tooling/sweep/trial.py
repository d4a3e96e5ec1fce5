"""One trial: an ordinary :func:`neural_brdf.pipeline.run`, its marker file and
metrics; a finished trial is recognised and not run again."""

from __future__ import annotations

import copy
import json
import os
import socket
import time
import traceback
from pathlib import Path

from neural_brdf import config as cfgmod
from neural_brdf.fileio import atomic_write, json_text
from neural_brdf.tooling.sweep.spec import MARKER


# ------------------------------------------------------------------ one trial
def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def _write_json(path: Path, obj) -> None:
    atomic_write(path, json_text(obj))  # a NaN or an infinity as "nan", "inf"


def _metrics(report: dict, cfg: cfgmod.Config) -> dict:
    from neural_brdf.train.model import RawBRDF

    checks, acc = report["checks"], report.get("accuracy", {})
    params = RawBRDF.parameter_count(cfg.model)
    values = {
        "rel_rmse": acc.get("rel_rmse"),
        "nbrdf_log_error": acc.get("nbrdf_log_error"),
        "max_albedo": checks["max_albedo"]["value"],
        "reciprocity": checks["reciprocity"]["value"],
        "min_value": checks["min_value"]["value"],
        "passed": report["passed"],
        "params": params,
        "train_seconds": report["seconds"]["train"],
        "total_seconds": report["seconds"]["total"],
    }
    return values


def _materialise(m: dict) -> None:
    from neural_brdf.measured import merl

    path = Path(m["path"])
    if not path.is_file():  # racing trials write the same bytes
        path.parent.mkdir(parents=True, exist_ok=True)
        merl.bake(merl.nbrdf_fixture(m["npz"], m["name"], reciprocal=True), path)


def run_trial(job: dict) -> dict:
    """Train one trial in ``job["run_dir"]``; never raises: returns its record."""
    from neural_brdf import pipeline
    from neural_brdf.train import loop

    run_dir = Path(job["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    record = {
        "trial": job["name"],
        "run_dir": str(run_dir),
        "overrides": job["overrides"],
        "status": "running",
        "error": None,
        "metrics": {},
        "started": _now(),
        "host": socket.gethostname(),
        "pid": os.getpid(),
    }
    _write_json(run_dir / MARKER, record)
    try:
        if job["materialise"]:
            _materialise(job["materialise"])
        cfg = cfgmod.from_dict(job["config"], source=f"trial {job['name']}")
        record["metrics"] = _metrics(pipeline.run(cfg, run_dir, overwrite=True), cfg)
        record["status"] = "ok"
    except loop.Interrupted as e:  # Ctrl-C reached this worker: the sweep stops (run_sweep)
        record["status"] = "interrupted"
        record["error"] = _one_line(e)
    except Exception as e:  # noqa: BLE001 -- recorded, then the next trial
        record["status"] = "failed"
        record["error"] = _one_line(e)
    record["finished"] = _now()
    return record


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    where = "" if text else traceback.format_exception_only(type(e), e)[-1].strip()
    return f"{type(e).__name__}: {text[0] if text else where}"


def _failed(job: dict, error: str) -> dict:
    return {
        "trial": job["name"],
        "run_dir": job["run_dir"],
        "overrides": job["overrides"],
        "status": "failed",
        "error": error,
        "metrics": {},
        "started": _now(),
        "finished": _now(),
        "host": socket.gethostname(),
        "pid": os.getpid(),
    }


def _read_marker(run_dir: Path) -> dict | None:
    try:
        return json.loads((Path(run_dir) / MARKER).read_text())
    except (OSError, ValueError):
        return None


def _same_config(stored, config: dict) -> bool:
    """Whether a finished trial's config is this one.  The stored config is read with
    today's schema first, so that a setting added since (with its default) changes
    nothing, and its target paths are made absolute by today's rule (a trial written
    before paths were, which kept a base config's relative ``target.data``: the current
    folder's then, as :func:`neural_brdf.train.session.check_resumable` reads it)."""
    if not isinstance(stored, dict):
        return False
    stored = copy.deepcopy(stored)
    cfgmod.paths_relative_to(stored, Path.cwd())
    try:
        return cfgmod.from_dict(stored).model_dump() == config
    except cfgmod.ConfigError:
        return False


def _finished(job: dict) -> dict | None:
    """The record of a trial finished earlier with this very config, else None."""
    marker = _read_marker(job["run_dir"])
    if (
        marker is None
        or marker.get("status") != "ok"
        or not (Path(job["run_dir"]) / "metrics.json").is_file()
        or not _same_config(marker.get("config"), job["config"])
    ):
        return None
    marker.pop("config")
    return {**marker, "run_dir": job["run_dir"]}  # the sweep folder may have moved
