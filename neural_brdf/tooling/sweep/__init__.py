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

from neural_brdf.tooling.sweep.executors import default_workers
from neural_brdf.tooling.sweep.plan import plan
from neural_brdf.tooling.sweep.results import summary_figure, write_results
from neural_brdf.tooling.sweep.run import print_progress, run_sweep, summary_line
from neural_brdf.tooling.sweep.spec import (
    MARKER,
    MAX_SLUG,
    METRICS,
    TRIAL_DEFAULTS,
    Materials,
    SweepError,
    SweepFile,
    load_sweep,
)
from neural_brdf.tooling.sweep.trial import run_trial

__all__ = [
    "MARKER",
    "MAX_SLUG",
    "METRICS",
    "Materials",
    "SweepError",
    "SweepFile",
    "TRIAL_DEFAULTS",
    "load_sweep",
    "plan",
    "run_trial",
    "default_workers",
    "summary_figure",
    "write_results",
    "print_progress",
    "run_sweep",
    "summary_line",
]
