"""Sweeps: many ordinary training runs over materials, config keys and seeds.

    neural-brdf sweep configs/sweeps/ablation.yaml                   # local process pool
    neural-brdf sweep configs/sweeps/ablation.yaml --executor ray    # local Ray instance
    neural-brdf sweep SWEEP.yaml --executor ray --ray-address HOST:6379 --out sweeps/x

A sweep file (YAML; paths in it are relative to the file)::

    name: ablation                  # output: runs/sweeps/<name>/ (default: the file's stem)
    base: ../gold.yaml              # the config every trial starts from (default: defaults)
    set: {train.steps: 800}         # overrides for every trial
    grid:                           # axes, crossed (cartesian product)
      config: [../gold.yaml, ../clay.yaml]     # `config` swaps the base config
      model.encoding: [isotropic, raw]         # any dotted config key
      train.seed: [0, 1]
    list:                           # explicit trials, crossed with the grid: either
      - {train.loss: log_l2}        #   a list of override mappings, or
      - {train.loss: nbrdf, train.lr: 0.01}   # a mapping of equal-length lists (zipped)
    materials:                      # measured materials: adds the axis `material`
      nbrdf: path/to/merl_nbrdf_weights.npz
      names: [alum-bronze, gold-paint]         # or: all

Each trial is ``pipeline.run(cfg, run_dir, overwrite=True)`` (an unfinished trial is rerun
from scratch in place): its own run directory under
``<out>/trials/<trial>/`` with ``config.yaml``, ``model.onnx``, ``metrics.json`` and the
rest, plus ``trial.json``, written last, atomically, as the completion marker.
``results.csv`` and ``results.json`` gather every trial's overrides, status, error and
metrics; ``summary.png`` plots them.  Both tables are rewritten after every trial.

Trials run with ``train.threads: 1`` and ``train.progress: false`` unless the sweep
sets them.  One thread per trial is what makes the results independent of the executor
and of the worker count: training is deterministic per seed *and* thread count.

Materials.  Each NBRDF network in the ``.npz`` is baked (made reciprocal, then
tabulated with :func:`neural_brdf.measured.merl.bake`) to ``<out>/data/<name>.binary`` by the
first trial that needs it, on the node that runs it; the trial's target becomes
``{data: <that file>}``.

Resuming.  A trial is finished when its ``trial.json`` says ``ok`` for the same resolved
config; re-running the sweep skips it.  Failed, interrupted and changed trials are run
again from scratch.  A failing trial (a bad value, a diverged loss, even a crashed worker
process) is recorded with its one-line error and does not stop the others (a crash in the
local pool fails the trials then in flight, since the pool cannot tell which one died).
A bad sweep file stops before anything runs, with a one-line error naming the key.
Exit codes of ``neural-brdf sweep``: 0 every trial ran (a trial's physics verdict is in
the table), 1 some trial failed, 2 a bad sweep file, 130 Ctrl-C (re-run to resume).

Executors.  ``local`` (default): a ``spawn`` process pool with ``--workers`` processes
(default: the usable CPU cores).  ``ray``: one Ray task per trial (``num_cpus=1``) on
the cluster at ``--ray-address``, or on a local instance with ``--workers`` CPUs.  A Ray
task writes the run directory on its node and sends its files back, so the driver's
sweep folder ends up the same either way; the package (and any data file) must be
installed (reachable) on every node.
"""

from __future__ import annotations

import csv
import hashlib
import io
import itertools
import json
import math
import multiprocessing
import os
import re
import shutil
import socket
import time
import traceback
import zipfile
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from neural_brdf import config as cfgmod
from neural_brdf.fileio import atomic_write

TRIAL_DEFAULTS = {"train.threads": 1, "train.progress": False}
MARKER = "trial.json"
METRICS = (
    "rel_rmse",
    "nbrdf_log_error",
    "max_albedo",
    "reciprocity",
    "min_value",
    "passed",
    "params",
    "train_seconds",
    "total_seconds",
)
MAX_SLUG = 80


class SweepError(cfgmod.ConfigError):
    """The sweep file is invalid (one line, naming the key); nothing was run."""


# ------------------------------------------------------------------ the sweep file
class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, populate_by_name=True)


class Materials(_Section):
    nbrdf: str  # NBRDF weights (.npz), relative to the file
    names: list[str] | Literal["all"] = "all"  # networks in it to train on


class SweepFile(_Section):
    name: str | None = None  # default: the file's stem
    base: str | None = None  # base config, relative to the file
    set: dict[str, Any] = Field(default_factory=dict)  # overrides for every trial
    grid: dict[str, list[Any]] = Field(default_factory=dict)  # crossed axes
    entries: list[dict[str, Any]] | dict[str, list[Any]] = Field(default_factory=list, alias="list")
    materials: Materials | None = None


def _is_config_key(key: str) -> bool:
    """Whether ``key`` (dotted) names a setting of :class:`config.Config`; anything under
    a free-form dict (``target.params.alpha``) counts."""
    node: Any = cfgmod.Config
    for part in key.split("."):
        fields = getattr(node, "model_fields", None)
        if fields is None or part not in fields:
            return False
        node = fields[part].annotation
        if getattr(node, "__origin__", None) is dict:
            return True
    return not hasattr(node, "model_fields")


def _error(source: str, err: Any) -> str:
    loc = ".".join(str(p) for p in err["loc"])
    if err["type"] == "extra_forbidden":
        return f"{source}: {loc}: unknown key"
    return f"{source}: {loc}: {err['msg']}"


def load_sweep(path: str | Path) -> SweepFile:
    """Read and check a sweep file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise SweepError(f"{path}: cannot read sweep file ({e.strerror})") from None
    raw = cfgmod.parse_yaml(text, source=str(path))
    if not isinstance(raw, dict):
        raise SweepError(f"{path}: expected a mapping of keys at the top level")
    try:
        spec = SweepFile.model_validate(raw)
    except ValidationError as e:
        raise SweepError(_error(str(path), e.errors()[0])) from None
    _check(spec, path)
    return spec


def _entries(spec: SweepFile, source: Path) -> list[dict]:
    if isinstance(spec.entries, list):
        return spec.entries
    lengths = {k: len(v) for k, v in spec.entries.items()}
    if len(set(lengths.values())) > 1:
        raise SweepError(f"{source}: list: zipped axes need equal lengths, got {lengths}")
    return [dict(zip(spec.entries, values)) for values in zip(*spec.entries.values())]


def _check(spec: SweepFile, source: Path) -> None:
    here = source.parent
    axes = (
        [("grid", k) for k in spec.grid]
        + [("list", k) for e in _entries(spec, source) for k in e]
        + [("set", k) for k in spec.set]
    )
    for section, key in axes:
        if key == "config" and section != "set":
            continue
        if key == "material" or not _is_config_key(key):
            raise SweepError(f"{source}: {section}.{key}: unknown config key")
    both = set(spec.grid) & {k for e in _entries(spec, source) for k in e}
    if both:
        raise SweepError(f"{source}: {sorted(both)[0]}: in both grid and list")
    files = [("base", spec.base)] + [("config", c) for c in _axis_values(spec, source, "config")]
    for key, name in files:
        if name is not None and not (isinstance(name, str) and (here / name).is_file()):
            raise SweepError(f"{source}: {key}: no such config file {name!r}")
    if spec.materials is not None:
        _material_names(spec.materials, here, source)


def _axis_values(spec: SweepFile, source: Path, key: str) -> list:
    return spec.grid.get(key, []) + [e[key] for e in _entries(spec, source) if key in e]


def _material_names(m: Materials, here: Path, source: Path) -> list[str]:
    from neural_brdf.measured import merl

    npz = here / m.nbrdf
    if not npz.is_file():
        raise SweepError(f"{source}: materials.nbrdf: no such file {m.nbrdf!r}")
    try:
        available = merl.nbrdf_names(npz)
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise SweepError(f"{source}: materials.nbrdf: cannot read {m.nbrdf!r} ({e})") from None
    if m.names == "all":
        return available
    unknown = [n for n in m.names if n not in available]
    if unknown:
        raise SweepError(f"{source}: materials.names: {unknown[0]!r} is not in {m.nbrdf}")
    return list(m.names)


# ------------------------------------------------------------------ planning trials
def _fmt(value) -> str:
    if isinstance(value, list):
        return "x".join(_fmt(v) for v in value)
    if isinstance(value, dict):
        return "_".join(f"{k}-{_fmt(v)}" for k, v in value.items())
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def _slug(overrides: dict) -> str:
    parts = []
    for key, value in overrides.items():
        if key == "config":
            parts.append(Path(value).stem)
        elif key == "material":
            parts.append(value)
        else:
            parts.append(f"{key.split('.')[-1]}-{_fmt(value)}")
    return re.sub(r"[^A-Za-z0-9._+=-]+", "-", "_".join(parts)) or "trial"


def _digest(overrides: dict) -> str:
    return hashlib.sha1(json.dumps(overrides, sort_keys=True).encode()).hexdigest()[:6]


def _names(points: list[dict]) -> list[str]:
    """Readable, stable run-directory names; a short hash only where needed."""
    slugs = [_slug(p) for p in points]
    taken = {s: slugs.count(s) for s in slugs}
    return [
        s if len(s) <= MAX_SLUG and taken[s] == 1 else f"{s[:MAX_SLUG]}-{_digest(p)}"
        for s, p in zip(slugs, points)
    ]


def _points(spec: SweepFile, source: Path) -> list[dict]:
    grid = dict(spec.grid)
    if spec.materials is not None:
        grid = {"material": _material_names(spec.materials, source.parent, source), **grid}
    crossed = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
    points = [{**e, **g} for e in (_entries(spec, source) or [{}]) for g in crossed]
    first = ("config", "material")  # these lead the names
    return [
        {**{k: p[k] for k in first if k in p}, **{k: v for k, v in p.items() if k not in first}}
        for p in points
    ]


def _override(raw: dict, key: str, value) -> None:
    cfgmod.apply_override(raw, f"{key}={json.dumps(value)}")  # JSON is YAML


def plan(spec: SweepFile, source: Path, out_dir: Path) -> list[dict]:
    """One job per trial: name, run_dir, overrides, and its resolved config (or the
    ConfigError that its values raise)."""
    here = source.parent
    points = _points(spec, source)
    keys = [json.dumps(p, sort_keys=True) for p in points]
    for point, key in zip(points, keys):
        if keys.count(key) > 1:
            raise SweepError(
                f"{source}: the trial {_slug(point)!r} appears {keys.count(key)} times"
            )
    jobs = []
    for name, point in zip(_names(points), points):
        base = point.get("config", spec.base)
        raw = (cfgmod.parse_yaml((here / base).read_text(), source=base) if base else None) or {}
        if not isinstance(raw, dict):
            raise SweepError(f"{source}: {base}: expected a mapping of config keys")
        raw["name"] = name
        job = {
            "name": name,
            "run_dir": str((out_dir / "trials" / name).resolve()),
            "overrides": point,
            "config": None,
            "error": None,
            "materialise": None,
        }
        for key, value in {**TRIAL_DEFAULTS, **spec.set}.items():
            _override(raw, key, value)
        for key, value in point.items():
            if key == "material" and spec.materials is not None:  # a "materials" sweep
                data = (out_dir / "data" / f"{value}.binary").resolve()
                job["materialise"] = {
                    "npz": str((here / spec.materials.nbrdf).resolve()),
                    "name": value,
                    "path": str(data),
                }
                raw["target"] = {"data": str(data)}  # replaces an analytic target
            elif key != "config":
                _override(raw, key, value)
        try:
            job["config"] = cfgmod.from_dict(raw, source=f"trial {name}").model_dump()
        except cfgmod.ConfigError as e:
            job["error"] = f"ConfigError: {e}"
        jobs.append(job)
    return jobs


# ------------------------------------------------------------------ one trial
def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def _write_json(path: Path, obj) -> None:
    atomic_write(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def _finite(x):
    return x if not isinstance(x, float) or math.isfinite(x) else str(x)


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
    return {k: _finite(v) for k, v in values.items()}


def _materialise(m: dict) -> None:
    from neural_brdf.measured import merl

    path = Path(m["path"])
    if not path.is_file():  # racing trials write the same bytes
        path.parent.mkdir(parents=True, exist_ok=True)
        merl.bake(merl.nbrdf_fixture(m["npz"], m["name"], reciprocal=True), path)


def run_trial(job: dict) -> dict:
    """Train one trial in ``job["run_dir"]``; never raises: returns its record."""
    from neural_brdf import pipeline
    from neural_brdf.train import loop as train

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
    except train.Interrupted as e:  # Ctrl-C reached this worker: the sweep stops (run_sweep)
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
    nothing."""
    if not isinstance(stored, dict):
        return False
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


# ------------------------------------------------------------------ executors
def _run_local(jobs: list[dict], workers: int):
    """Yield records as trials finish, on a spawn process pool.  If a worker process
    dies, the trials it may have been running are failed and the others go on in a
    fresh pool."""
    ctx = multiprocessing.get_context("spawn")
    pending = list(jobs)
    while pending:
        broken = []
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            futures = {pool.submit(run_trial, job): job for job in pending}
            for fut in as_completed(futures):
                try:
                    yield fut.result()
                except BrokenProcessPool:
                    broken.append(futures[fut])
        # run_trial's first act is to write its marker: those without one never started
        started = [j for j in broken if _read_marker(j["run_dir"]) is not None] or broken
        for job in started:
            yield _failed(
                job,
                "BrokenProcessPool: a worker process died while this trial "
                "was running (it or another trial in flight crashed)",
            )
        pending = [j for j in broken if j not in started]


def _ray_trial(job: dict) -> tuple[dict, dict[str, bytes]]:
    """Ray task: the trial's record and its run directory's files."""
    record = run_trial(job)
    run_dir = Path(job["run_dir"])
    files = {
        str(p.relative_to(run_dir)): p.read_bytes()
        for p in sorted(run_dir.rglob("*"))
        if p.is_file() and p.name != MARKER
    }
    return record, files


def _receive(run_dir: Path, files: dict[str, bytes]) -> None:
    """Write a Ray task's files where they differ (another node); same node: no-op."""
    for rel, body in files.items():
        path = run_dir / rel
        if path.is_file() and path.read_bytes() == body:
            continue
        atomic_write(path, body, parents=True)


def _run_ray(jobs: list[dict], workers: int, address: str | None):
    try:
        import ray
    except ImportError:
        raise cfgmod.InputError(
            "--executor ray: Ray is not installed: pip install -e '.[ray]'"
        ) from None
    ours = not ray.is_initialized()
    if ours:
        if address is None:
            ray.init(num_cpus=workers, include_dashboard=False)
        else:
            ray.init(address=address)
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(_ray_trial)
        refs = {task.remote(job): job for job in jobs}
        waiting = list(refs)
        while waiting:
            (ref,), waiting = ray.wait(waiting, num_returns=1)
            job = refs[ref]
            try:
                record, files = ray.get(ref)
            except ray.exceptions.RayError as e:  # the worker died: this trial only
                yield _failed(job, _one_line(e))
                continue
            _receive(Path(job["run_dir"]), files)
            yield record
    finally:
        if ours:
            ray.shutdown()


def default_workers() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


# ------------------------------------------------------------------ the sweep
def run_sweep(
    path: str | Path,
    *,
    executor: str = "local",
    workers: int | None = None,
    ray_address: str | None = None,
    out: str | Path | None = None,
    progress: Callable[[dict, int, int], None] | None = None,
) -> dict:
    """Run (or resume) a sweep; returns the results (also written to ``out``)."""
    spec = load_sweep(path)
    if executor not in ("local", "ray"):
        raise cfgmod.InputError(f"--executor: expected local or ray, got {executor!r}")
    workers = workers or default_workers()
    if workers < 1:
        raise cfgmod.InputError(f"--workers: must be >= 1, got {workers}")
    name = spec.name or Path(path).stem
    out_dir = Path(out) if out is not None else Path("runs", "sweeps", name)
    jobs = plan(spec, Path(path), out_dir)
    records = {job["name"]: _finished(job) for job in jobs}
    todo = [job for job in jobs if records[job["name"]] is None]
    for job in todo:  # a fresh start for reruns
        shutil.rmtree(job["run_dir"], ignore_errors=True)
    configs = {job["name"]: job["config"] for job in jobs}
    done = len(jobs) - len(todo)

    def finish(record: dict) -> None:
        nonlocal done
        done += 1
        records[record["trial"]] = record
        run_dir = Path(record["run_dir"])
        run_dir.mkdir(parents=True, exist_ok=True)
        _write_json(run_dir / MARKER, {**record, "config": configs[record["trial"]]})
        write_results(out_dir, name, jobs, records)
        if progress:
            progress(record, done, len(jobs))

    write_results(out_dir, name, jobs, records)  # the table exists from the start
    for job in [j for j in todo if j["error"]]:
        finish(_failed(job, job["error"]))
    runnable = [j for j in todo if not j["error"]]
    if runnable:
        run = (
            _run_ray(runnable, workers, ray_address)
            if executor == "ray"
            else _run_local(runnable, workers)
        )
        try:
            for record in run:
                if record["status"] == "interrupted":
                    # The terminal's Ctrl-C reaches every process of the group, but the
                    # worker's may be handled first (its trainer saves a checkpoint and
                    # returns): that trial is not failed, the sweep is interrupted, and a
                    # rerun starts the trial afresh.
                    raise KeyboardInterrupt
                finish(record)
        except KeyboardInterrupt:
            run.close()  # stops the pool / shuts Ray down
            write_results(out_dir, name, jobs, records)  # Ctrl-C may land mid-finish()
            from neural_brdf.train.loop import Interrupted

            raise Interrupted(
                f"sweep interrupted after {done} of {len(jobs)} trials; "
                "run the same command again to resume"
            ) from None
    return write_results(out_dir, name, jobs, records, figure=True)


def print_progress(record: dict, done: int, total: int) -> None:
    rel = record["metrics"].get("rel_rmse")
    what = (
        record["error"]
        if record["status"] != "ok"
        else (f"rel_rmse {100 * rel:.2f} %" if isinstance(rel, float) else "")
    )
    print(f"[{done}/{total}] {record['status']:6s} {record['trial']}  {what}", flush=True)


def summary_line(results: dict) -> str:
    failed = sum(r["status"] != "ok" for r in results["trials"])
    return (
        f"{len(results['trials']) - failed} trials ok, {failed} failed: "
        f"{results['folder']}/results.csv"
    )


# ------------------------------------------------------------------ results
def _cell(value) -> str:
    if value is None:
        return ""
    return value if isinstance(value, str) else json.dumps(value)


def write_results(
    out_dir: Path, name: str, jobs: list[dict], records: dict, *, figure: bool = False
) -> dict:
    """results.json, results.csv (and summary.png) from the records, in plan order."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for job in jobs:
        r = records.get(job["name"]) or {
            "trial": job["name"],
            "run_dir": job["run_dir"],
            "overrides": job["overrides"],
            "status": "pending",
            "error": None,
            "metrics": {},
        }
        rows.append({**r, "run_dir": os.path.relpath(r["run_dir"], out_dir)})
    results = {"sweep": name, "folder": str(out_dir), "trials": rows}
    _write_json(out_dir / "results.json", results)
    keys = list(dict.fromkeys(k for r in rows for k in r["overrides"]))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["trial", "status", *keys, *METRICS, "error", "run_dir"])
    for r in rows:
        w.writerow(
            [
                r["trial"],
                r["status"],
                *(_cell(r["overrides"].get(k)) for k in keys),
                *(_cell(r["metrics"].get(m)) for m in METRICS),
                r["error"] or "",
                r["run_dir"],
            ]
        )
    _write_text(out_dir / "results.csv", buf.getvalue())
    if figure:
        summary_figure(rows, out_dir / "summary.png")
    return results


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, text)


def summary_figure(rows: list[dict], path: Path) -> None:
    """Per trial: accuracy, max albedo (furnace line at 1) and reciprocity error."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = [r["trial"] for r in rows]
    fig = Figure(figsize=(13, 1.2 + 0.28 * len(rows)), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3, sharey=True)
    panels = [
        ("rel_rmse", "rel. RMSE of f cos (%)", 100.0, "linear"),
        ("max_albedo", "max directional albedo", 1.0, "linear"),
        ("reciprocity", "reciprocity error", 1.0, "symlog"),
    ]
    y = range(len(rows))
    for ax, (key, label, scale, xscale) in zip(axes, panels):
        values = [r["metrics"].get(key) for r in rows]
        ok = [isinstance(v, (int, float)) for v in values]
        ax.barh(
            [i for i, k in zip(y, ok) if k],
            [scale * v for v, k in zip(values, ok) if k],
            color="tab:blue",
        )
        for i, (r, k) in enumerate(zip(rows, ok)):
            if not k:
                ax.text(
                    0.01,
                    i,
                    r["status"],
                    va="center",
                    color="tab:red",
                    transform=ax.get_yaxis_transform(),
                )
        if key == "max_albedo":
            ax.axvline(1.0, color="k", lw=0.8, ls="--")
        if key == "reciprocity":  # mostly exact zeros: write the values
            for i, (v, k) in enumerate(zip(values, ok)):
                if k:
                    ax.text(
                        0.02,
                        i,
                        f"{v:.2g}",
                        va="center",
                        fontsize=7,
                        transform=ax.get_yaxis_transform(),
                    )
            top = max([v for v, k in zip(values, ok) if k] + [0.0])
            ax.set_xlim(0.0, max(1e-6, 10 * top))
        ax.set_xscale(xscale, **({"linthresh": 1e-7} if xscale == "symlog" else {}))
        ax.set_xlabel(label)
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(list(y), names, fontsize=7)
    axes[0].invert_yaxis()
    fig.savefig(path, dpi=110)
