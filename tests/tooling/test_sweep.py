"""Sweeps: local and Ray executors, the results table, resuming, failing trials, bad files.

The trials are tiny (60 steps, a [8, 8] network, small quadratures): these tests check
the mechanics, not accuracy.  One local sweep (module fixture) is the reference that the
Ray run, the resume test and the table checks compare against.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import ray
import torch
import yaml

import neural_brdf
from neural_brdf import config
from neural_brdf.tooling import cli, sweep
from neural_brdf.tooling.sweep import run as sweep_run
from neural_brdf.train import loop

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"
NPZ = REPO / "tests" / "data" / "nbrdf" / "merl_nbrdf_weights.npz"

TINY = {
    "train.steps": 60,
    "train.warmup": 5,
    "train.eval_every": 0,
    "model.hidden": [8, 8],
    "data.batch_size": 256,
    "data.pool_size": 2048,
    "normalization.table_size": 17,
    "normalization.samples": 2048,
    "validation.furnace_dirs": 6,
    "validation.furnace_samples": 4096,
    "validation.pairs": 2000,
    "validation.accuracy_samples": 2048,
    "export.parity_pairs": 512,
}
TRIALS = [
    {"train.seed": 0},
    {"train.seed": 1},
    {"model.encoding": "raw", "normalization.enabled": False},
]
NAMES = ["seed-0", "seed-1", "encoding-raw_enabled-false"]
# what may differ between two runs of the same trial: clocks and where it ran
VOLATILE = {"train_seconds", "total_seconds"}


def write_sweep(folder: Path, **spec) -> Path:
    spec = {"base": str(CONFIGS / "lambert.yaml"), "set": TINY, **spec}
    path = folder / "sweep.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def stable(results: dict) -> list[dict]:
    """The trials of a results table without clocks, hosts and process ids."""
    return [
        {
            "trial": r["trial"],
            "status": r["status"],
            "error": r["error"],
            "overrides": r["overrides"],
            "run_dir": r["run_dir"],
            "metrics": {k: v for k, v in r["metrics"].items() if k not in VOLATILE},
        }
        for r in results["trials"]
    ]


def read(path: Path) -> dict:
    return json.loads(path.read_text())


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    folder = tmp_path_factory.mktemp("local")
    path = write_sweep(folder, list=TRIALS)
    out = folder / "out"
    assert cli.main(["sweep", str(path), "--workers", "2", "--out", str(out)]) == 0
    return path, out


def test_local_sweep_table_matches_each_trials_own_metrics(local):
    _, out = local
    results = read(out / "results.json")
    assert [r["trial"] for r in results["trials"]] == NAMES
    with open(out / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["trial"] for r in rows] == NAMES
    for r, row, overrides in zip(results["trials"], rows, TRIALS):
        assert r["status"] == row["status"] == "ok" and r["error"] is None
        assert r["overrides"] == overrides
        run_dir = out / r["run_dir"]
        own = read(run_dir / "metrics.json")
        m = r["metrics"]
        assert m["rel_rmse"] == own["accuracy"]["rel_rmse"]
        assert m["nbrdf_log_error"] == own["accuracy"]["nbrdf_log_error"]
        assert m["max_albedo"] == own["checks"]["max_albedo"]["value"]
        assert m["reciprocity"] == own["checks"]["reciprocity"]["value"]
        assert m["passed"] == own["passed"]
        assert m["train_seconds"] == own["seconds"]["train"]
        for key in ("rel_rmse", "max_albedo", "reciprocity"):  # the CSV holds the same
            assert float(row[key]) == m[key]
        # parameter count, counted independently from the checkpoint's weights
        weights = torch.load(run_dir / "ckpt.pt", weights_only=True)["model"]
        assert m["params"] == sum(w.numel() for w in weights.values())
        # the trial is an ordinary run: its config holds the sweep's settings
        cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
        assert cfg["train"]["threads"] == 1 and cfg["train"]["steps"] == 60
        assert cfg["model"]["hidden"] == [8, 8]
        for key, value in overrides.items():
            section, name = key.split(".")
            assert cfg[section][name] == value
        assert read(run_dir / "trial.json")["status"] == "ok"
        model = neural_brdf.load(run_dir / "model.onnx")
        assert model.encoding == cfg["model"]["encoding"]
    assert (out / "summary.png").stat().st_size > 10_000
    # the raw-input ablation is not reciprocal and fails physics; the symmetric ones pass
    by_name = {r["trial"]: r["metrics"] for r in results["trials"]}
    assert by_name["seed-0"]["reciprocity"] == 0 and by_name["seed-0"]["passed"]
    assert by_name["encoding-raw_enabled-false"]["reciprocity"] > 1e-3
    assert not by_name["encoding-raw_enabled-false"]["passed"]
    assert by_name["seed-0"]["rel_rmse"] != by_name["seed-1"]["rel_rmse"]


@pytest.mark.slow
def test_ray_executor_gives_the_same_table(local, tmp_path):
    path, out_local = local
    out = tmp_path / "ray"
    try:
        assert (
            cli.main(["sweep", str(path), "--executor", "ray", "--workers", "2", "--out", str(out)])
            == 0
        )
        assert not ray.is_initialized()  # the sweep shut down the instance it started
    finally:
        ray.shutdown()
    a, b = read(out_local / "results.json"), read(out / "results.json")
    # same trials, same metrics: training is deterministic per seed and thread count
    assert stable(a) == stable(b)
    for r in b["trials"]:
        run_local, run_ray = out_local / r["run_dir"], out / r["run_dir"]
        assert sorted(p.name for p in run_local.iterdir()) == sorted(
            p.name for p in run_ray.iterdir()
        )
        ma, mb = read(run_local / "metrics.json"), read(run_ray / "metrics.json")
        assert ma["checks"] == mb["checks"] and ma["accuracy"] == mb["accuracy"]
        assert read(run_ray / "trial.json")["status"] == "ok"


def test_resume_runs_only_unfinished_trials(local, tmp_path):
    path, out_local = local
    out = tmp_path / "resume"
    shutil.copytree(out_local, out)
    runs = {n: out / "trials" / n for n in NAMES}

    def edit_marker(name, **changes):
        marker = read(runs[name] / "trial.json")
        (runs[name] / "trial.json").write_text(json.dumps({**marker, **changes}))
        return marker

    # seed-0 finished, but with another config (the sweep file was edited since)
    stored = edit_marker("seed-0")["config"]
    edit_marker("seed-0", config={**stored, "train": {**stored["train"], "steps": 59}})
    # seed-1 was killed mid-run
    edit_marker("seed-1", status="running")
    (runs["seed-1"] / "metrics.json").unlink()
    # the third finished under an older schema that lacked a setting (now at its default)
    kept = runs["encoding-raw_enabled-false"]
    stored = read(kept / "trial.json")["config"]
    assert stored["train"]["lr_min"] == config.Train().lr_min
    stored["train"].pop("lr_min")
    edit_marker("encoding-raw_enabled-false", config=stored)
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in kept.iterdir()}
    seen = []
    t0 = time.time()
    results = sweep.run_sweep(
        path, workers=2, out=out, progress=lambda r, done, total: seen.append(r["trial"])
    )
    assert sorted(seen) == ["seed-0", "seed-1"]  # only those two ran again
    assert {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in kept.iterdir()} == before
    for name in ("seed-0", "seed-1"):
        assert (runs[name] / "metrics.json").stat().st_mtime >= t0
        assert read(runs[name] / "trial.json")["config"]["train"]["steps"] == 60
    assert stable(results) == stable(read(out_local / "results.json"))


def test_a_trial_that_stored_its_data_path_relative_is_still_finished(tmp_path, monkeypatch):
    """A trial written before target paths were made absolute stored a base config's
    relative target.data (the current folder's, by the rule of its time); the sweep now
    plans it absolute, and the trial is the same one, not run again."""
    from neural_brdf.tooling.sweep import trial

    monkeypatch.chdir(tmp_path)
    for name in ("a.pbsdf", "b.pbsdf"):
        shutil.copy(REPO / "tests" / "data" / "spectralon_lowres.pbsdf", tmp_path / name)
    planned = config.from_dict({"target": {"data": str(tmp_path / "a.pbsdf")}}).model_dump()
    for stored, same in (("a.pbsdf", True), ("b.pbsdf", False)):
        old = config.from_dict({"target": {"data": stored}}).model_dump()
        assert old["target"]["data"] == stored  # (as such a trial.json holds it)
        assert trial._same_config(old, planned) is same, stored


@pytest.mark.slow
def test_ctrl_c_stops_the_sweep_and_a_rerun_resumes_it(tmp_path):
    path = write_sweep(tmp_path, list=TRIALS[:2])
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "neural_brdf",
        "sweep",
        str(path),
        "--workers",
        "1",
        "--out",
        str(out),
    ]
    proc = subprocess.Popen(
        cmd,
        cwd=REPO,
        start_new_session=True,
        # as a shell starts a foreground job: SIGINT at its default even where this test
        # runs as a background job (`cmd &` in a script), which inherits SIGINT ignored
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    first = out / "trials" / "seed-0" / "trial.json"
    deadline = time.time() + 300
    while not (first.is_file() and read(first)["status"] == "ok"):
        assert proc.poll() is None and time.time() < deadline, proc.communicate()
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole group
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130 and "run the same command again" in err
    rows = {r["trial"]: r["status"] for r in read(out / "results.json")["trials"]}
    assert rows["seed-0"] == "ok" and rows["seed-1"] != "ok"
    kept = {p.name: p.stat().st_mtime_ns for p in first.parent.iterdir()}
    seen = []
    sweep.run_sweep(path, workers=1, out=out, progress=lambda r, d, t: seen.append(r["trial"]))
    assert seen == ["seed-1"]
    assert {p.name: p.stat().st_mtime_ns for p in first.parent.iterdir()} == kept


def stuck_trial(job: dict) -> dict:
    """A worker that misses Ctrl-C and never ends on its own (an idle worker blocked as
    the walkthrough found one): it says it started, then sleeps."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    Path(job["run_dir"]).mkdir(parents=True, exist_ok=True)
    (Path(job["run_dir"]) / "started").write_text(str(os.getpid()))
    time.sleep(90)
    return {}


def test_an_interrupted_local_sweep_ends_a_worker_that_does_not(tmp_path):
    import threading

    from neural_brdf.tooling.sweep import executors

    started = tmp_path / "a" / "started"
    interrupted = []

    def interrupt_once_started():
        deadline = time.monotonic() + 120
        while not started.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        interrupted.append(time.monotonic())
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the sweep's own process

    records = executors._run_local(
        [{"name": "a", "run_dir": str(tmp_path / "a")}], 1, trial=stuck_trial, grace=1.0
    )
    threading.Thread(target=interrupt_once_started, daemon=True).start()
    # as in a terminal: a job started in the background (CI's) inherits SIGINT ignored
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            next(records)
    finally:
        signal.signal(signal.SIGINT, old)
    took = time.monotonic() - interrupted[0]
    pid = int(started.read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # the worker is gone
    assert took < 30  # it would have slept on for 90 s, and the sweep waited for it


def test_a_rerun_keeps_the_users_files_and_refuses_a_folder_not_its_own(tmp_path, capsys):
    path = write_sweep(tmp_path, list=TRIALS[:1])
    out = tmp_path / "out"
    sweep.run_sweep(path, workers=1, out=out)
    trial = out / "trials" / "seed-0"
    (trial / "notes.md").write_text("why seed 0 is odd")
    # a changed base reruns the trial: its run files are replaced, the user's stay
    path.write_text(path.read_text().replace("train.steps: 60", "train.steps: 61"))
    sweep.run_sweep(path, workers=1, out=out)
    assert read(trial / "trial.json")["config"]["train"]["steps"] == 61
    assert (trial / "notes.md").read_text() == "why seed 0 is odd"
    # a trial folder of the user's own (no run in it) is refused, nothing removed
    mine = tmp_path / "mine"
    (mine / "trials" / "seed-0").mkdir(parents=True)
    (mine / "trials" / "seed-0" / "thesis.tex").write_text("thesis")
    (mine / "results.json").write_text(json.dumps({"trials": []}))
    code = cli.main(["sweep", str(path), "--workers", "1", "--out", str(mine)])
    err = capsys.readouterr().err
    assert code == 2 and "thesis.tex" in err and len(err.strip().splitlines()) == 1
    assert (mine / "trials" / "seed-0" / "thesis.tex").read_text() == "thesis"
    # a folder that is no sweep's, and a file, are refused as --out
    (mine / "results.json").write_text("my own results")
    code = cli.main(["sweep", str(path), "--workers", "1", "--out", str(mine)])
    err = capsys.readouterr().err
    assert code == 2 and "not a sweep's folder" in err
    assert (mine / "results.json").read_text() == "my own results"
    code = cli.main(["sweep", str(path), "--out", str(mine / "results.json")])
    assert code == 2 and "is a file" in capsys.readouterr().err
    code = cli.main(["sweep", str(path), "--workers", "0", "--out", str(tmp_path / "w")])
    assert code == 2 and "--workers: must be >= 1, got 0" in capsys.readouterr().err


def test_failing_trials_are_recorded_and_the_others_finish(tmp_path):
    trials = [
        {"train.seed": 0},
        {"target.params.albedo": -0.5},  # invalid: raised in the worker
        {"train.lr": -1.0},
    ]  # invalid: caught when planning
    path = write_sweep(tmp_path, list=trials)
    out = tmp_path / "out"
    assert cli.main(["sweep", str(path), "--workers", "2", "--out", str(out)]) == 1
    rows = {r["trial"]: r for r in read(out / "results.json")["trials"]}
    assert rows["seed-0"]["status"] == "ok" and rows["seed-0"]["metrics"]["passed"]
    bad = rows["albedo--0.5"]
    assert bad["status"] == "failed" and bad["metrics"] == {}
    assert "target.params" in bad["error"] and "albedo" in bad["error"]
    assert "\n" not in bad["error"]
    lr = rows["lr--1.0"]
    assert lr["status"] == "failed" and "train.lr" in lr["error"] and "\n" not in lr["error"]
    for r in rows.values():  # every trial has its marker
        assert read(out / r["run_dir"] / "trial.json")["status"] == r["status"]


def test_a_diverging_trial_is_recorded_as_failed(tmp_path, monkeypatch):
    def nan_loss(*args, **kwargs):
        return torch.tensor(math.nan, requires_grad=True)

    monkeypatch.setattr(loop, "loss_fn", nan_loss)
    spec = sweep.load_sweep(write_sweep(tmp_path, list=[{"train.seed": 0}]))
    (job,) = sweep.plan(spec, tmp_path / "sweep.yaml", tmp_path / "out")
    record = sweep.run_trial(job)
    assert record["status"] == "failed"
    assert record["error"].startswith("Diverged: loss is nan")


def test_materials_become_data_targets(tmp_path):
    path = write_sweep(
        tmp_path,
        materials={"nbrdf": str(NPZ), "names": ["alum-bronze", "brass"]},
        grid={"train.seed": [0, 1]},
    )
    spec = sweep.load_sweep(path)
    jobs = sweep.plan(spec, path, tmp_path / "out")
    assert [j["name"] for j in jobs] == [
        "alum-bronze_seed-0",
        "alum-bronze_seed-1",
        "brass_seed-0",
        "brass_seed-1",
    ]
    for job in jobs:
        name = job["overrides"]["material"]
        data = (tmp_path / "out" / "data" / f"{name}.binary").resolve()
        assert job["config"]["target"]["data"] == str(data)
        assert job["materialise"] == {"npz": str(NPZ.resolve()), "name": name, "path": str(data)}
    everything = write_sweep(tmp_path, materials={"nbrdf": str(NPZ)})
    spec = sweep.load_sweep(everything)
    names = {j["overrides"]["material"] for j in sweep.plan(spec, everything, tmp_path / "o")}
    with np.load(NPZ) as z:
        assert names == {k.split("/")[0] for k in z.files} and len(names) == 100


def test_paths_are_relative_to_the_file_that_gives_them(tmp_path, monkeypatch):
    # a base config's paths are its own folder's (as `train` reads it); a path the sweep
    # sets is the sweep file's folder's; wherever the sweep is started from
    (tmp_path / "configs").mkdir()
    (tmp_path / "sweeps").mkdir()
    (tmp_path / "elsewhere").mkdir()
    base = tmp_path / "configs" / "teacher.yaml"
    base.write_text("target:\n  mitsuba: teacher.xml\n")
    path = tmp_path / "sweeps" / "sweep.yaml"
    grid = {"config": ["../configs/teacher.yaml", str(CONFIGS / "merl.yaml")]}
    path.write_text(yaml.safe_dump({"grid": grid, "set": {"target.data": "m.binary"}}))
    monkeypatch.chdir(tmp_path / "elsewhere")
    jobs = sweep.plan(sweep.load_sweep(path), path, tmp_path / "out")
    assert "target.mitsuba alone" in jobs[0]["error"] and jobs[1]["error"] is None
    assert jobs[1]["config"]["target"]["data"] == str(tmp_path / "sweeps" / "m.binary")
    path.write_text(yaml.safe_dump({"base": "../configs/teacher.yaml"}))
    (job,) = sweep.plan(sweep.load_sweep(path), path, tmp_path / "out")
    assert job["config"]["target"]["mitsuba"] == str(tmp_path / "configs" / "teacher.xml")


def test_grid_crosses_and_list_zips(tmp_path):
    path = write_sweep(
        tmp_path,
        grid={"train.seed": [0, 1, 2]},
        list={"model.hidden": [[4], [8, 8]], "train.lr": [0.01, 0.02]},
    )
    spec = sweep.load_sweep(path)
    points = [j["overrides"] for j in sweep.plan(spec, path, tmp_path / "out")]
    assert len(points) == 6
    assert {(tuple(p["model.hidden"]), p["train.lr"]) for p in points} == {
        ((4,), 0.01),
        ((8, 8), 0.02),
    }
    assert sorted(p["train.seed"] for p in points) == [0, 0, 1, 1, 2, 2]


@pytest.mark.parametrize(
    "spec, key",
    [
        ({"grids": {"train.seed": [0]}}, "grids"),
        ({"grid": {"train.stepz": [1]}}, "train.stepz"),
        ({"grid": {"train.seed": 3}}, "train.seed"),
        ({"list": {"train.seed": [0, 1], "train.lr": [0.1]}}, "list"),
        ({"base": "missing.yaml"}, "base"),
        ({"grid": {"config": ["nowhere.yaml"]}}, "config"),
        ({"materials": {"nbrdf": str(NPZ), "names": ["unobtainium"]}}, "materials.names"),
        ({"materials": {"nbrdf": __file__}}, "materials.nbrdf"),
        ({"list": [{"train.seed": 1}, {"train.seed": 1}]}, "'seed-1' appears 2 times"),
        # an empty axis crossed with others: no trial at all, and it said "0 trials ok"
        ({"grid": {"train.steps": [], "train.seed": [0, 1]}}, "grid.train.steps: an empty list"),
        ({"list": {"train.seed": [], "train.lr": []}}, "list.train.seed: an empty list"),
    ],
)
def test_bad_sweep_file_is_one_line_exit_2(tmp_path, capsys, spec, key):
    path = write_sweep(tmp_path, **spec)
    assert cli.main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and key in err
    assert str(path) in err
    assert not (tmp_path / "out").exists()  # nothing ran


def test_a_second_sweep_in_a_folder_in_use_is_refused(tmp_path, capsys):
    """Two sweeps in one folder each counted the trials the other held as failed, and
    the last to write decided the table: the folder is locked while a sweep runs."""
    from neural_brdf import runfolder

    path = write_sweep(tmp_path, list=TRIALS[:1])
    out = tmp_path / "out"
    with runfolder.run_lock(out, holder="sweep"):  # a sweep running there
        assert cli.main(["sweep", str(path), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "in use by another sweep" in err, err
        assert not (out / "results.json").exists()
    assert cli.main(["sweep", str(path), "--out", str(out), "--workers", "1"]) == 0
    assert read(out / "results.json")["trials"][0]["status"] == "ok"
    assert not (out / runfolder.LOCK).exists()


@pytest.mark.parametrize("name", ["../../escaped", "a/b", ".hidden", "-x", ""])
def test_a_sweep_name_that_is_not_one_plain_folder_is_refused(tmp_path, capsys, monkeypatch, name):
    """The sweep goes to runs/sweeps/<name>/: ``../../escaped`` wrote outside it."""
    here = tmp_path / "a" / "b"
    here.mkdir(parents=True)
    path = write_sweep(here, name=name)
    monkeypatch.chdir(here)
    assert cli.main(["sweep", str(path), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {path}: name: ") and "\n" not in err, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b", path.name]  # nothing ran


@pytest.mark.parametrize("path", sorted((CONFIGS / "sweeps").glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_sweep_files_plan_cleanly(path, tmp_path):
    raw = yaml.safe_load(path.read_text())
    if "materials" in raw:  # the user supplies the measured data (docs/merl.md): ours here
        raw["base"] = str((path.parent / raw["base"]).resolve())
        raw["materials"]["nbrdf"] = str(NPZ)
        path = tmp_path / path.name
        path.write_text(yaml.safe_dump(raw))
    jobs = sweep.plan(sweep.load_sweep(path), path, tmp_path)
    assert jobs and all(j["error"] is None for j in jobs)
    assert len({j["name"] for j in jobs}) == len(jobs)
    for job in jobs:  # every trial is an ordinary 1-thread run
        assert job["config"]["train"]["threads"] == 1


def test_a_trial_interrupted_in_its_worker_interrupts_the_sweep(tmp_path, monkeypatch):
    """Ctrl-C reaches every process of the terminal's group; when a worker's trainer
    handles it first and returns, the sweep stops as interrupted (not with a failed
    trial), and the trial is left for the rerun."""
    path = write_sweep(tmp_path, list=TRIALS[:2])
    out = tmp_path / "out"

    def worker_saw_ctrl_c(jobs, workers):
        for job in jobs:
            record = sweep.run_trial(job)  # a real trial
            if job["name"] == "seed-1":
                record = {**record, "status": "interrupted", "error": "Interrupted: step 5"}
            yield record

    monkeypatch.setattr(sweep_run, "_run_local", worker_saw_ctrl_c)  # where run_sweep finds it
    with pytest.raises(loop.Interrupted, match="run the same command again"):
        sweep.run_sweep(path, workers=1, out=out)
    rows = {r["trial"]: r["status"] for r in read(out / "results.json")["trials"]}
    assert rows["seed-0"] == "ok" and rows["seed-1"] not in ("ok", "failed")
