"""The run folder (neural_brdf.runfolder, issue 28): a run writes only into a new or empty
folder or its own run, never over a file it did not write; an interrupted --overwrite
leaves the folder the old run whole or consistently the new one; run folders of earlier
versions (no marker) are still resumed and overwritten.

The cases of issue 28 part 1 drive the command line only (in process, or a real process
sent SIGTERM), so that they fail on a version without these rules, not on an import."""

from __future__ import annotations

import os
import shutil
import signal
from pathlib import Path

import pytest
import torch
import yaml

from cli_helpers import ROOT, SETS, TINY, assert_one_line_error, cli, run

MARKER = ".neural-brdf-run"  # runfolder.MARKER, spelled here for the old-code runs


@pytest.fixture(autouse=True)
def no_render(monkeypatch):
    """The report without its Mitsuba render (seconds per run, not what is tested)."""
    from neural_brdf.viewer import plots

    monkeypatch.setattr(plots, "mitsuba_unavailable", lambda: "switched off by the test")


def snapshot(folder: Path) -> dict:
    """relative name -> (bytes, mtime_ns) of every file under ``folder``."""
    return {
        str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def config_steps(run_dir: Path) -> int:
    return yaml.safe_load((run_dir / "config.yaml").read_text())["train"]["steps"]


def ckpt_step(run_dir: Path) -> int:
    return int(torch.load(run_dir / "ckpt.pt", weights_only=True)["step"])


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished run with its report and viewer.html (10 steps)."""
    out = tmp_path_factory.mktemp("finished") / "run"
    from neural_brdf.viewer import plots

    saved = plots.mitsuba_unavailable
    plots.mitsuba_unavailable = lambda: "switched off by the test"
    try:
        from neural_brdf.tooling.cli import main

        assert main(["train", "lambert", "--out", str(out), *SETS]) == 0
    finally:
        plots.mitsuba_unavailable = saved
    assert (out / "viewer.html").is_file() and (out / "report.html").is_file()
    return out


# ------------------------------------------------- a folder that is not a run
@pytest.mark.parametrize(
    "mine", ["config.yaml", "log.csv", "report.html", "report.md", "notes.txt"]
)
@pytest.mark.parametrize(
    "flag", [[], ["--overwrite"], ["--resume"]], ids=["", "overwrite", "resume"]
)
def test_a_folder_of_the_users_files_is_refused_and_left_as_it_is(capsys, tmp_path, mine, flag):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / mine).write_text("the user's own file\n")
    (folder / "data.txt").write_text("more of the user's\n")
    before = snapshot(folder)
    code, _, err = cli(capsys, "train", "lambert", "--out", str(folder), *SETS, *flag)
    assert_one_line_error(code, err, str(folder), "not a run folder")
    if mine != "notes.txt":
        assert mine in err  # the file a run would have written over
    assert snapshot(folder) == before
    assert sorted(os.listdir(folder)) == sorted([mine, "data.txt"])  # no lock, no marker


def test_out_dot_in_a_project_folder_keeps_its_config(capsys, tmp_path, monkeypatch):
    project = tmp_path / "project"
    project.mkdir()
    (project / "config.yaml").write_text("my_project: {setting: 1}\n")
    (project / "README.md").write_text("# my project\n")
    before = snapshot(project)
    monkeypatch.chdir(project)
    code, _, err = cli(capsys, "train", "lambert", "--out", ".", *SETS)
    assert_one_line_error(code, err, "config.yaml", "not a run folder")
    assert snapshot(project) == before


def test_train_many_refuses_a_users_folder_before_writing_any(capsys, tmp_path):
    out = tmp_path / "out"
    (out / "beckmann_rough").mkdir(parents=True)
    (out / "beckmann_rough" / "log.csv").write_text("my,own\n1,2\n")
    before = snapshot(out)
    code, _, err = cli(capsys, "train-many", "gold", "beckmann_rough", "--out", str(out), *SETS)
    assert_one_line_error(code, err, str(out / "beckmann_rough"), "log.csv")
    assert snapshot(out) == before
    assert sorted(os.listdir(out)) == ["beckmann_rough"]  # gold/ was not left behind


def test_an_empty_folder_and_a_missing_one_take_a_run(capsys, tmp_path):
    (tmp_path / "empty").mkdir()
    for out in (tmp_path / "empty", tmp_path / "new" / "nested"):
        code, _, err = cli(capsys, "train", "lambert", "--out", str(out), *SETS)
        assert code == 0, err
        assert (out / MARKER).is_file() and (out / "model.onnx").is_file()


def test_a_run_folder_made_by_an_earlier_version_is_resumed_and_overwritten(
    capsys, finished, tmp_path
):
    """No marker: config.yaml and ckpt.pt together are a run, as before."""
    old = tmp_path / "old"
    shutil.copytree(finished, old)
    (old / MARKER).unlink()
    (old / "notes.txt").write_text("kept\n")
    before = snapshot(old)
    code, _, err = cli(capsys, "train", "lambert", "--out", str(old), *SETS)
    assert_one_line_error(code, err, str(old), "finished", "--overwrite")
    code, out, err = cli(capsys, "train", "lambert", "--out", str(old), *SETS, "--resume")
    assert code == 0 and "already finished at step 10" in out, err
    assert snapshot(old) == before  # nothing touched, not even a marker written
    code, _, err = cli(
        capsys,
        "train",
        "lambert",
        "--out",
        str(old),
        *SETS,
        "--set",
        "train.steps=6",
        "--overwrite",
    )
    assert code == 0, err
    assert (old / MARKER).is_file() and ckpt_step(old) == 6 and config_steps(old) == 6
    assert (old / "notes.txt").read_text() == "kept\n"


def test_an_unfinished_run_of_an_earlier_version_resumes(capsys, tmp_path):
    from neural_brdf import config
    from neural_brdf.train import loop

    half = tmp_path / "half"
    cfg = config.load(ROOT / "configs" / "lambert.yaml", [*TINY, "train.steps=4"])
    loop.train(cfg, half)
    (half / MARKER).unlink()  # as an earlier version left it
    code, _, err = cli(capsys, "train", "lambert", "--out", str(half), *SETS, "--resume")
    assert code == 0, err
    assert ckpt_step(half) == 10 and (half / MARKER).is_file()


# ------------------------------------------------- an interrupted replacement
SIGTERM_AT = """
import os, signal, sys
from neural_brdf.tooling import cli
from neural_brdf.viewer import plots
from neural_brdf.train import data
from neural_brdf import pipeline
plots.mitsuba_unavailable = lambda: "switched off by the test"
where, n = sys.argv[1], int(sys.argv[2])
calls = [0]
def hook(real):
    def wrapped(*args, **kwargs):
        calls[0] += 1
        if calls[0] == n:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*args, **kwargs)
    return wrapped
if where == "batch":
    data.Pool.batch = hook(data.Pool.batch)
else:
    pipeline.finish = hook(pipeline.finish)
sys.exit(cli.main(sys.argv[3:]))
"""


def sigterm_at(where: str, n: int, *args: str):
    """The CLI in a real process, sent SIGTERM at the ``n``-th call of data.Pool.batch
    (``batch``: in training) or of pipeline.finish (``finish``: after training)."""
    return run("-c", SIGTERM_AT, where, str(n), *args)


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """Two finished runs of one train-many --report (10 steps)."""
    out = tmp_path_factory.mktemp("batch") / "out"
    proc = sigterm_at(
        "batch", 0, "train-many", "gold", "beckmann_rough", "--report", "--out", str(out), *SETS
    )
    assert proc.returncode == 0, proc.stderr
    for name in ("gold", "beckmann_rough"):
        assert (out / name / "viewer.html").is_file() and (out / name / "model.onnx").is_file()
    return out


@pytest.mark.slow
def test_sigterm_while_train_many_overwrites_keeps_the_old_runs_whole(batch, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(batch, out)
    before = snapshot(out)
    proc = sigterm_at(
        "batch", 6, "train-many", "gold", "beckmann_rough", "--overwrite", "--out", str(out),
        *SETS, "--set", "train.steps=7",
    )  # fmt: skip
    assert proc.returncode == 143, proc.stderr
    assert "interrupted at step 3 (SIGTERM)" in proc.stderr
    assert snapshot(out) == before  # each old run whole: model, metrics, ckpt, viewer
    exported = run(
        "-m", "neural_brdf", "export", str(out / "beckmann_rough"), "-o", str(tmp_path / "c.onnx")
    )
    assert exported.returncode == 0, exported.stderr  # the old weights, with the old config


@pytest.mark.slow
def test_sigterm_after_train_many_trained_leaves_the_new_runs(batch, tmp_path):
    """Stopped as the first export starts: every folder is consistently the new run (its
    config, checkpoint and log), with nothing of the old one beside it."""
    out = tmp_path / "out"
    shutil.copytree(batch, out)
    proc = sigterm_at(
        "finish", 1, "train-many", "gold", "beckmann_rough", "--overwrite", "--out", str(out),
        *SETS, "--set", "train.steps=7",
    )  # fmt: skip
    assert proc.returncode == 143, proc.stderr
    for name in ("gold", "beckmann_rough"):
        run_dir = out / name
        assert config_steps(run_dir) == 7 and ckpt_step(run_dir) == 7
        left = sorted(os.listdir(run_dir))
        assert left == sorted([MARKER, "config.yaml", "ckpt.pt", "log.csv"]), left
    exported = run(
        "-m", "neural_brdf", "export", str(out / "beckmann_rough"), "-o", str(tmp_path / "c.onnx")
    )
    assert exported.returncode == 0, exported.stderr  # the new weights, with the new config


@pytest.mark.slow
def test_sigterm_while_train_overwrites_leaves_no_old_viewer(finished, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    proc = sigterm_at(
        "batch", 4, "train", "lambert", "--out", str(run_dir), "--overwrite",
        *SETS, "--set", "train.steps=8",
    )  # fmt: skip
    assert proc.returncode == 143, proc.stderr
    left = sorted(os.listdir(run_dir))
    assert left == sorted([MARKER, "config.yaml", "ckpt.pt", "log.csv"]), left
    assert config_steps(run_dir) == 8 and ckpt_step(run_dir) == 4  # the new run, resumable
    proc = run("-m", "neural_brdf", "train", "lambert", "--out", str(run_dir), *SETS,
               "--set", "train.steps=8", "--resume")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert ckpt_step(run_dir) == 8 and (run_dir / "viewer.html").is_file()


# ------------------------------------------------- the module
def test_own_files_lists_a_runs_files_and_nothing_else(finished, tmp_path):
    from neural_brdf import runfolder
    from neural_brdf.viewer import report

    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    (run_dir / "notes.txt").write_text("mine\n")
    (run_dir / "report-notes.png").write_bytes(b"mine")  # a user's, named like the report's
    names = {p.name for p in runfolder.own_files(run_dir)}
    assert "report-notes.png" not in names and not runfolder.is_own_file(
        run_dir / "report-notes.png"
    )
    assert {MARKER, "config.yaml", "ckpt.pt", "log.csv", "model.onnx", "metrics.json"} <= names
    assert {"report.html", "report.md", "viewer.html", "report-loss.png"} <= names
    assert "notes.txt" not in names and ".lock" not in names
    assert (
        runfolder.is_own_file(run_dir / "ckpt.pt")
        and runfolder.is_own_file(run_dir / "x.onnx") is False
    )
    assert runfolder.is_own_file(run_dir / "notes.txt") is False
    assert runfolder.own_files(tmp_path) == []  # not a run
    assert runfolder.MARKER == MARKER and runfolder.VIEWER == report.VIEWER_FILE
    assert set(report.RUN_FILES) <= set(runfolder.FILES)


def test_a_resumed_run_removes_what_a_killed_write_left(finished, tmp_path, capsys):
    """kill -9 while a checkpoint is written leaves its temporary file (as large as the
    checkpoint); --resume kept each one, so a job killed again and again filled the disk."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    stale = [".ckpt.pt.k7x2a9q1.tmp", ".metrics.json.3jd8_0ab.tmp", ".log.csv.q0q0q0q0.tmp"]
    for name in stale:
        (run_dir / name).write_bytes(b"half a write")
    # not a run file's temporary (another file's, or not mkstemp's name): the user's
    mine = [".notes.txt.abcdefgh.tmp", ".config.yaml.bak.tmp", "notes.txt"]
    for name in mine:
        (run_dir / name).write_text("mine")
    code, _, err = cli(
        capsys, "train", "lambert", "--out", str(run_dir), *SETS, "--set", "train.steps=12",
        "--resume",
    )  # fmt: skip
    assert code == 0, err
    left = {p.name for p in run_dir.iterdir()}
    assert not left & set(stale), left
    assert set(mine) <= left
    # a resume of the finished run, or a refused train, touches nothing (docs/cli.md)
    (run_dir / stale[0]).write_bytes(b"half a write")
    before = snapshot(run_dir)
    for extra in (["--resume"], []):
        cli(capsys, "train", "lambert", "--out", str(run_dir), *SETS, "--set", "train.steps=12",
            *extra)  # fmt: skip
        assert snapshot(run_dir) == before


def test_a_sweeps_trial_record_does_not_make_a_folder_foreign(tmp_path):
    from neural_brdf import runfolder
    from neural_brdf.tooling.sweep.spec import MARKER as TRIAL

    assert TRIAL in runfolder.COMPANIONS
    (tmp_path / TRIAL).write_text("{}")
    runfolder.check_fresh_run_dir(tmp_path, resume=False, overwrite=False)  # no error
    (tmp_path / "other.txt").write_text("")
    with pytest.raises(runfolder.NotARunFolder, match="other.txt"):
        runfolder.check_fresh_run_dir(tmp_path, resume=False, overwrite=True)


def test_overwrite_keeps_a_device_in_a_run_files_place(tmp_path):
    """A link to /dev/null in ckpt.pt's place stays (a run writes into it in place);
    the old run's regular files go."""
    from neural_brdf import runfolder

    (tmp_path / MARKER).write_text("")
    (tmp_path / "ckpt.pt").symlink_to(os.devnull)
    (tmp_path / "model.onnx").write_text("old")
    (tmp_path / "viewer.html").write_text("old")
    runfolder.remove_run(tmp_path)
    assert sorted(os.listdir(tmp_path)) == ["ckpt.pt"] and (tmp_path / "ckpt.pt").is_symlink()


def test_held_signals_delivers_a_signal_after_the_block():
    from neural_brdf import runfolder

    got = []
    previous = signal.signal(signal.SIGTERM, lambda s, f: got.append(("handler", s)))
    try:
        with runfolder.held_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            got.append("block done")
        assert got == ["block done", ("handler", signal.SIGTERM)]
    finally:
        signal.signal(signal.SIGTERM, previous)
