"""The sweep: plan, run (skipping finished trials), collect, write the results."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from neural_brdf import runfolder
from neural_brdf.errors import InputError
from neural_brdf.tooling.sweep.executors import _run_local, _run_ray, default_workers
from neural_brdf.tooling.sweep.plan import plan
from neural_brdf.tooling.sweep.results import write_results
from neural_brdf.tooling.sweep.spec import MARKER, load_sweep
from neural_brdf.tooling.sweep.trial import _failed, _finished, _write_json


# ------------------------------------------------------------------ the sweep
def _check_sweep_folder(out_dir: Path) -> None:
    """Refuse (InputError, one line) a ``--out`` that is a file, or a folder that holds
    files and no sweep's results.json (a sweep writes its table and trials there; the
    user's own files in a sweep's folder stay as they are)."""
    if os.path.lexists(out_dir) and not out_dir.is_dir():
        raise InputError(f"--out {out_dir}: is a file; a sweep's output is a folder")
    entries = sorted(os.listdir(out_dir)) if out_dir.is_dir() else []
    entries = [e for e in entries if e != runfolder.LOCK]  # (another sweep's: refused below)
    if not entries:
        return
    try:
        ours = isinstance(json.loads((out_dir / "results.json").read_text()).get("trials"), list)
    except (OSError, ValueError, AttributeError):
        ours = False
    if not ours:
        raise InputError(
            f"--out {out_dir}: not a sweep's folder (it holds {entries[0]} and no "
            "results.json of a sweep); choose a new or empty folder, or the sweep's own"
        )


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
        raise InputError(f"--executor: expected local or ray, got {executor!r}")
    if workers is None:
        workers = default_workers()
    if workers < 1:
        raise InputError(f"--workers: must be >= 1, got {workers}")
    name = spec.name or Path(path).stem
    out_dir = Path(out) if out is not None else Path("runs", "sweeps", name)
    _check_sweep_folder(out_dir)
    # one sweep at a time in a folder: a second one would count the trials the first
    # holds as failed, and the last to write would decide the table
    with runfolder.run_lock(out_dir, elsewhere="choose another --out", holder="sweep"):
        return _run_sweep(spec, Path(path), name, out_dir, executor, workers, ray_address, progress)


def _run_sweep(
    spec,
    path: Path,
    name: str,
    out_dir: Path,
    executor: str,
    workers: int,
    ray_address: str | None,
    progress: Callable[[dict, int, int], None] | None,
) -> dict:
    jobs = plan(spec, path, out_dir)
    records = {job["name"]: _finished(job) for job in jobs}
    todo = [job for job in jobs if records[job["name"]] is None]
    for job in todo:  # a rerun replaces the trial's run files alone (overwrite), never
        runfolder.check_writable(Path(job["run_dir"]))  # a folder of the user's
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
