"""Where trials run: a local process pool, or Ray (local or a cluster)."""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write
from neural_brdf.tooling.sweep.spec import MARKER
from neural_brdf.tooling.sweep.trial import _failed, _one_line, _read_marker, run_trial

# ------------------------------------------------------------------ executors
# Seconds an interrupted sweep waits for its workers (each saves its checkpoint on the
# same Ctrl-C) before it ends those still running
STOP_GRACE = 20.0


def _stop(pool: ProcessPoolExecutor, grace: float) -> None:
    """Stop a pool at once: cancel the trials not started, give the running ones
    ``grace`` seconds, then terminate the workers still alive.  Leaving the pool's
    ``with`` waits for every worker instead, for ever where one is blocked (an idle
    worker that missed the interrupt)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())  # shutdown drops it
    pool.shutdown(wait=False, cancel_futures=True)
    deadline = time.monotonic() + grace
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(5.0)


def _run_local(jobs: list[dict], workers: int, *, trial=run_trial, grace: float = STOP_GRACE):
    """Yield records as trials finish, on a spawn process pool.  If a worker process
    dies, the trials it may have been running are failed and the others go on in a
    fresh pool.  Ctrl-C (or closing the generator) stops the pool (:func:`_stop`).
    ``trial``: what a worker runs on a job (a module-level function)."""
    ctx = multiprocessing.get_context("spawn")
    pending = list(jobs)
    while pending:
        broken = []
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            try:
                futures = {pool.submit(trial, job): job for job in pending}
                for fut in as_completed(futures):
                    try:
                        yield fut.result()
                    except BrokenProcessPool:
                        broken.append(futures[fut])
            except (KeyboardInterrupt, GeneratorExit):
                _stop(pool, grace)
                raise
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
        raise InputError("--executor ray: Ray is not installed: pip install -e '.[ray]'") from None
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
