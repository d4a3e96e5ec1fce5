"""The command line: exit codes 0 / 1 / 2, one-line errors, the train.py shim."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from cli_helpers import ROOT, SETS, TINY, assert_one_line_error, cli, run  # noqa: F401
from neural_brdf import config, export, runfolder, validate
from neural_brdf.train import loop
from test_fileio import devices  # noqa: F401  (a fixture)


def test_train_py_config_error_is_one_line_and_exit_2(tmp_path):
    proc = run(
        "train.py",
        str(ROOT / "configs" / "lambert.yaml"),
        "--out",
        str(tmp_path / "r"),
        "--set",
        "train.stepz=3",
    )
    assert_one_line_error(proc.returncode, proc.stderr, "train.stepz")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "args, key",
    [
        (["--set", "train.steps=many"], "train.steps"),
        (["--set", "model.encoding=spherical"], "model.encoding"),
        (["--set", "target.model=velvet"], "target.model"),
        (["--set", "target.params.albedo=7"], "albedo"),
        (["--set", "oops"], "oops"),
        (["--set", "train.progress=maybe"], "train.progress: expected true, false or auto"),
        (["--set", "train.progress=1"], "train.progress: expected true, false or auto"),
    ],
)
def test_config_errors_exit_2_naming_the_key(capsys, tmp_path, args, key):
    code, _, err = cli(
        capsys, "train", str(ROOT / "configs" / "lambert.yaml"), "--out", str(tmp_path / "r"), *args
    )
    assert_one_line_error(code, err, key)
    assert not (tmp_path / "r" / "ckpt.pt").exists()


def test_bad_arguments_and_files_exit_2(capsys, tmp_path):
    assert_one_line_error(*cli(capsys, "train")[::2], "config")
    assert_one_line_error(*cli(capsys, "frobnicate")[::2], "frobnicate")
    assert_one_line_error(*cli(capsys, "train", str(tmp_path / "none.yaml"))[::2], "none.yaml")
    assert_one_line_error(*cli(capsys, "validate", str(tmp_path / "none.onnx"))[::2], "none.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    assert_one_line_error(*cli(capsys, "validate", str(junk))[::2], "junk.onnx")
    assert_one_line_error(*cli(capsys, "export", str(tmp_path))[::2], str(tmp_path))
    assert_one_line_error(
        *cli(
            capsys,
            "train",
            str(ROOT / "configs" / "lambert.yaml"),
            "--out",
            str(tmp_path / "fresh"),
            "--resume",
        )[::2],
        "ckpt.pt",
    )


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "lambert"
    proc = run("train.py", str(ROOT / "configs" / "lambert.yaml"), "--out", str(out), *SETS)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "physics PASSED" in proc.stdout
    return out


def test_train_shim_writes_the_run(run_dir):
    for name in ["config.yaml", "model.onnx", "metrics.json", "ckpt.pt", "log.csv"]:
        assert (run_dir / name).is_file()
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["passed"] is True
    assert metrics["training"]["steps"] == 10
    assert "rel_rmse" in metrics["accuracy"]


@pytest.mark.parametrize("progress, bar", [(None, False), ("true", True), ("false", False)])
def test_a_redirected_run_gets_a_bar_only_when_asked(tmp_path, progress, bar):
    """train.progress auto (the default): stderr redirected to a file or a pipe gets no
    tqdm frames (a log full of carriage returns); true forces them, false never."""
    sets = [a for kv in TINY if not kv.startswith("train.progress") for a in ("--set", kv)]
    if progress is not None:
        sets += ["--set", f"train.progress={progress}"]
    out = tmp_path / "r"
    proc = run("-m", "neural_brdf", "train", "lambert", "--out", str(out), *sets)
    assert proc.returncode == 0, proc.stderr
    assert ("it/s" in proc.stderr) is bar, proc.stderr
    assert "physics PASSED" in proc.stdout


def test_validate_exit_0_with_json_and_reference(capsys, run_dir, tmp_path):
    out = tmp_path / "report.json"
    code, stdout, err = cli(
        capsys,
        "validate",
        str(run_dir / "model.onnx"),
        "--reference",
        str(ROOT / "configs" / "lambert.yaml"),
        "--json",
        str(out),
    )
    report = json.loads(out.read_text())
    assert code == (0 if report["peak"]["passed"] else 1), err  # 1: any check failed
    assert report["passed"] is True
    # the file says what the exit code says (its "passed" is the physics' alone)
    assert report["checks_passed"] is (code == 0) is report["peak"]["passed"]
    assert report["checks"]["reciprocity"]["value"] <= 1e-6
    assert report["accuracy"]["rel_rmse"] >= 0.0
    assert "max_albedo" in stdout


def test_validate_says_when_the_model_is_not_its_reference(capsys, run_dir):
    """A model far from its reference (here the run's Lambertian model against gold) is
    physical, and no exit code sees a poor relative RMSE (a measured reference has no
    peak check: 99 % off printed physics PASSED, exit 0, and nothing else): a note on
    stderr says it, as train's does; the peak's failure is the exit code's, not a note."""
    code, stdout, err = cli(capsys, "validate", str(run_dir / "model.onnx"), "--reference", "gold")
    rel = float(stdout.split("rel_rmse (f cos)")[1].split("%")[0])
    assert rel > 100 * validate.POOR_ACCURACY
    assert f"note: relative RMSE of f cos {rel:.1f} %" in err
    assert "peak is" not in err and code == 1  # (gold's peak check fails: the exit code)


def test_validate_exit_1_on_a_physics_failure(tmp_path):
    raw = loop.RawBRDF("isotropic", [8], "silu", init_value=50.0).eval()  # albedo ~150
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(export.to_onnx_bytes(raw, 17))
    proc = run("-m", "neural_brdf", "validate", str(bad), "--json", str(tmp_path / "bad.json"))
    assert proc.returncode == 1, proc.stderr
    assert "FAIL" in proc.stdout and "Traceback" not in proc.stderr
    assert json.loads((tmp_path / "bad.json").read_text())["passed"] is False


def test_train_says_when_the_peak_fails_though_the_physics_pass(capsys, tmp_path):
    """A sharp lobe at 10 steps misses its peak: train still exits 0 (its verdict is the
    physics'), and says on stderr what validate would exit 1 on."""
    args = ["train", "gold", "--out", str(tmp_path / "run"), *SETS]
    code, out, err = cli(capsys, *args, "--set", "target.params.alpha=0.05")
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert code == 0 and metrics["passed"] and not metrics["peak"]["passed"], metrics["peak"]
    assert "note: the highlight's peak is" in err and "validate" in err, err


def test_export_subcommand(capsys, run_dir, tmp_path):
    out = tmp_path / "exported.onnx"
    code, _, err = cli(capsys, "export", str(run_dir), "-o", str(out))
    assert code == 0, err
    assert out.is_file()


def test_neural_brdf_and_train_py_agree(capsys, run_dir, tmp_path):
    """`neural-brdf train` and `python train.py` are the same command."""
    out = tmp_path / "again"
    code, _, err = cli(
        capsys, "train", str(ROOT / "configs" / "lambert.yaml"), "--out", str(out), *SETS
    )
    assert code == 0, err
    a = torch.load(run_dir / "ckpt.pt", weights_only=True)["model"]
    b = torch.load(out / "ckpt.pt", weights_only=True)["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize(
    "content, needle",
    [
        (bytes(range(256)) * 4, "not a YAML text file"),  # binary garbage
        (b"\xff\xfetarget: {}\n", "not UTF-8"),  # UTF-16 BOM, not UTF-8
        (b"- a\n- b\n", "mapping"),  # a list
        (b"just a string\n", "mapping"),  # a scalar
        (b"target: [\n", "invalid YAML"),
        (b"train:\x00 {}\n", "invalid YAML"),  # a NUL in UTF-8 text
    ],
)
def test_unreadable_or_non_mapping_config_exits_2_naming_the_file(tmp_path, content, needle):
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(content)
    proc = run("-m", "neural_brdf", "train", str(bad), "--out", str(tmp_path / "r"))
    assert_one_line_error(proc.returncode, proc.stderr, str(bad), needle)
    assert not (tmp_path / "r").exists()


def test_a_finished_run_is_not_replaced_without_overwrite(capsys, run_dir, tmp_path):
    done = tmp_path / "done"
    shutil.copytree(run_dir, done)
    before = (done / "metrics.json").read_bytes()
    code, _, err = cli(capsys, "train", "lambert", "--out", str(done), *SETS)
    assert_one_line_error(code, err, str(done), "finished", "--resume", "--overwrite")
    assert (done / "metrics.json").read_bytes() == before
    code, _, err = cli(capsys, "train", "lambert", "--out", str(done), "--resume", "--overwrite")
    assert_one_line_error(code, err, "--overwrite")
    # --overwrite replaces it: a 5-step run's metrics, and no stale report or model left over
    code, _, err = cli(
        capsys,
        "train",
        "lambert",
        "--out",
        str(done),
        *SETS,
        "--set",
        "train.steps=5",
        "--overwrite",
    )
    assert code == 0, err
    assert json.loads((done / "metrics.json").read_text())["training"]["steps"] == 5


def test_an_unfinished_run_needs_resume_or_overwrite(capsys, tmp_path):
    half = tmp_path / "half"
    cfg = config.load(ROOT / "configs" / "lambert.yaml", TINY + ["train.steps=4"])
    loop.train(cfg, half)  # ckpt.pt, no model.onnx: unfinished
    (half / "keep.txt").write_text("mine")
    code, _, err = cli(capsys, "train", "lambert", "--out", str(half), *SETS)
    assert_one_line_error(code, err, str(half), "unfinished", "--resume", "--overwrite")
    assert torch.load(half / "ckpt.pt", weights_only=True)["step"] == 4
    code, _, err = cli(capsys, "train", "lambert", "--out", str(half), *SETS, "--resume")
    assert code == 0, err
    assert json.loads((half / "metrics.json").read_text())["training"]["steps"] == 10
    assert (half / "keep.txt").read_text() == "mine"


def test_a_run_stopped_before_its_first_checkpoint_resumes_from_step_0(capsys, run_dir, tmp_path):
    # kill -9 within train.checkpoint_every steps leaves the marker and config.yaml alone:
    # --resume (a scheduler's restart) refused it every time, "no checkpoint"
    early = tmp_path / "early"
    shutil.copytree(run_dir, early)
    for p in early.iterdir():
        if p.name not in (runfolder.MARKER, runfolder.CONFIG):
            p.unlink()
    code, _, err = cli(capsys, "train", "lambert", "--out", str(early), *SETS, "--resume")
    assert code == 0, err
    assert "stopped before its first checkpoint" in err and "from step 0" in err, err
    assert json.loads((early / "metrics.json").read_text())["training"]["steps"] == 10
    # a run that wrote its model and then lost its checkpoint is not trained over
    (early / runfolder.CKPT).unlink()
    model = (early / runfolder.MODEL).read_bytes()
    code, _, err = cli(capsys, "train", "lambert", "--out", str(early), *SETS, "--resume")
    assert code == 2 and "no checkpoint" in err, err
    assert (early / runfolder.MODEL).read_bytes() == model
    # nor is a folder that holds no run
    code, _, err = cli(
        capsys, "train", "lambert", "--out", str(tmp_path / "new"), *SETS, "--resume"
    )
    assert code == 2, err


@pytest.mark.parametrize("damage", ["empty", "truncated"])
def test_a_damaged_model_is_exported_again_on_resume(capsys, run_dir, tmp_path, damage):
    # --resume said "already finished" over an empty model.onnx, which validate refused
    done = tmp_path / "done"
    shutil.copytree(run_dir, done)
    model = done / runfolder.MODEL
    model.write_bytes(b"" if damage == "empty" else model.read_bytes()[:100])
    code, out, err = cli(capsys, "train", "lambert", "--out", str(done), *SETS, "--resume")
    assert code == 0, err
    assert "already finished" not in out
    code, _, err = cli(capsys, "validate", str(model))
    assert code == 0, err


def test_a_run_stopped_in_its_report_writes_it_on_resume(capsys, tmp_path, monkeypatch):
    # metrics.json came before the report: a run stopped there was "already finished" and
    # never got its report
    from neural_brdf.viewer import report as report_module

    real = report_module.write_report

    def stopped(run_dir):
        raise KeyboardInterrupt

    monkeypatch.setattr(report_module, "write_report", stopped)
    run = tmp_path / "run"
    code, _, err = cli(capsys, "train", "lambert", "--out", str(run), *SETS)
    assert code == 130, err
    assert (run / "metrics.json").is_file() and not (run / "report.html").exists()
    monkeypatch.setattr(report_module, "write_report", real)
    code, out, err = cli(capsys, "train", "lambert", "--out", str(run), *SETS, "--resume")
    assert code == 0, err
    assert "already finished" not in out and (run / "report.html").is_file()
    metrics = json.loads((run / "metrics.json").read_text())
    assert "report" in metrics["seconds"] and "report_pending" not in metrics
    code, out, _ = cli(capsys, "train", "lambert", "--out", str(run), *SETS, "--resume")
    assert code == 0 and "already finished" in out  # now it has


# ------------------------------------------------- issue 19: safe wherever it writes
def snapshot(folder: Path) -> dict:
    """name -> (bytes, mtime_ns) of every file in ``folder``."""
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.iterdir())}


def test_a_run_leaves_no_lock_file(run_dir):
    assert not (run_dir / loop.LOCK_FILE).exists()


def test_resume_of_a_finished_run_touches_nothing(capsys, run_dir, tmp_path):
    done = tmp_path / "done"
    shutil.copytree(run_dir, done)
    before = snapshot(done)
    code, out, err = cli(capsys, "train", "lambert", "--out", str(done), *SETS, "--resume")
    assert code == 0, err
    assert f"{done}: already finished at step 10" in out
    assert snapshot(done) == before  # metrics.json (final_loss) and config.yaml included


def test_resume_refuses_fewer_steps_than_the_checkpoint(capsys, run_dir, tmp_path):
    done = tmp_path / "done"
    shutil.copytree(run_dir, done)
    before = snapshot(done)
    code, _, err = cli(
        capsys, "train", "lambert", "--out", str(done), *SETS, "--set", "train.steps=5", "--resume"
    )
    assert_one_line_error(code, err, "train.steps", "10")
    assert snapshot(done) == before


def test_a_bad_override_names_the_set_not_the_file(capsys, tmp_path):
    code, _, err = cli(
        capsys, "train", str(ROOT / "configs" / "lambert.yaml"), "--set", "train.stepz=5"
    )
    assert_one_line_error(code, err, "--set train.stepz=5:", "train.stepz", "unknown key")
    assert "lambert.yaml" not in err
    bad = tmp_path / "bad.yaml"
    bad.write_text("train: {stepz: 5}\n")
    code, _, err = cli(capsys, "train", str(bad), "--set", "train.steps=5")
    assert_one_line_error(code, err, str(bad), "train.stepz")
    assert "--set" not in err


@pytest.mark.parametrize("text", ["train: {steps: 0}\n", ""], ids=["file", "set"])
def test_zero_steps_are_refused(capsys, tmp_path, text):
    cfg = tmp_path / "zero.yaml"
    cfg.write_text("target: {model: lambertian}\n" + text)
    sets = [] if text else ["--set", "train.steps=0"]
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"), *sets)
    assert_one_line_error(code, err, "train.steps", "--set" if sets else str(cfg))
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("text, what", [("", "empty config"), ("train: {lr: 0.01}\n", "target")])
def test_a_config_without_target_warns(capsys, tmp_path, text, what):
    """One warning line (it trains the default target); here the run then stops at once
    on a second mistake, an --out that is a file."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(a_file))
    warning, error = err.strip().splitlines()
    assert warning.startswith(f"warning: {cfg}: ") and what in warning
    assert "lambertian" in warning
    assert_one_line_error(code, error, str(a_file), "not a run folder")
    assert a_file.read_text() == "mine"


def test_an_out_that_cannot_be_a_folder_is_one_line(capsys, tmp_path):
    code, _, err = cli(capsys, "train", "lambert", "--out", "/proc/neural-brdf-test", *SETS)
    assert_one_line_error(code, err, "/proc/neural-brdf-test")


@pytest.mark.usefixtures("devices")
@pytest.mark.parametrize(
    "name, extra",
    [("config.yaml", []), ("ckpt.pt", ["--overwrite"]), ("log.csv", [])],
)
def test_a_full_disk_during_training_is_one_line(capsys, tmp_path, name, extra):
    """A file of the run on a full device: /dev/full behind a link in the run folder."""
    out = tmp_path / "r"
    out.mkdir()
    (out / ".neural-brdf-run").write_text("")  # a run's folder (a user's is refused)
    (out / name).symlink_to("/dev/full")
    code, _, err = cli(capsys, "train", "lambert", "--out", str(out), *SETS, *extra)
    assert_one_line_error(code, err, str(out / name), "No space left on device")
    assert stat.S_ISCHR(os.lstat("/dev/full").st_mode)
    assert (out / name).is_symlink()


def test_a_locked_run_folder_is_refused_naming_the_holder(capsys, tmp_path):
    out = tmp_path / "busy"
    with loop.run_lock(out):
        assert (out / loop.LOCK_FILE).read_text().strip() == str(os.getpid())
        code, _, err = cli(capsys, "train", "lambert", "--out", str(out), *SETS)
        assert_one_line_error(code, err, str(out), f"pid {os.getpid()}")
        assert sorted(p.name for p in out.iterdir()) == [loop.LOCK_FILE]  # nothing written
    assert not out.exists()  # the folder the lock created, empty again, is removed


def test_export_and_report_of_a_busy_run_name_their_own_flag(capsys, run_dir, tmp_path):
    busy = tmp_path / "busy"
    shutil.copytree(run_dir, busy)
    with runfolder.run_lock(busy):
        for command in ("export", "report"):
            code, _, err = cli(capsys, command, str(busy))
            assert_one_line_error(code, err, f"pid {os.getpid()}", "write elsewhere with -o")
            assert "--out" not in err  # train's flag, not theirs
        # the run's own viewer too (it wrote there without the lock, racing a resumed run)
        viewer = busy / "viewer.html"
        before = viewer.read_bytes() if viewer.exists() else None
        code, _, err = cli(capsys, "view", str(busy / "model.onnx"), "-o", str(viewer))
        assert_one_line_error(code, err, f"pid {os.getpid()}", "write elsewhere with -o")
        assert (viewer.read_bytes() if viewer.exists() else None) == before


def read_only(monkeypatch, folder: Path) -> None:
    """Files can no longer be created in ``folder`` (as on a read-only mount, which a
    test run as root cannot make with chmod): os.open with O_CREAT there fails."""
    real = os.open

    def fake(path, flags, *args, **kwargs):
        inside = Path(os.path.realpath(os.fspath(path))).is_relative_to(os.path.realpath(folder))
        if inside and flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(path))
        return real(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", fake)


def test_a_read_only_run_folder(capsys, monkeypatch, run_dir, tmp_path):
    """docs/cli.md: --resume of a finished run touches nothing and exits 0, also where
    nothing can be written (it stopped at the lock file); the writers name their file
    (report named a temporary folder of its render)."""
    done = tmp_path / "done"
    shutil.copytree(run_dir, done)
    before = snapshot(done)
    read_only(monkeypatch, done)
    code, out, err = cli(capsys, "train", "lambert", "--out", str(done), *SETS, "--resume")
    assert code == 0, err
    assert f"{done}: already finished at step 10" in out
    for command, name in (("report", "report.html"), ("export", "model.onnx")):
        code, _, err = cli(capsys, command, str(done))
        assert_one_line_error(code, err, str(done / name), "Read-only file system")
    assert snapshot(done) == before
    assert not (done / loop.LOCK_FILE).exists()


SIGTERM_AT_STEP_4 = """
import os, signal, sys
from neural_brdf.tooling import cli
from neural_brdf.train import data
real, calls = data.Pool.batch, [0]
def batch(self):
    calls[0] += 1
    if calls[0] == 4:  # SIGTERM arrives in the middle of step 4
        os.kill(os.getpid(), signal.SIGTERM)
    return real(self)
data.Pool.batch = batch
sys.exit(cli.main(sys.argv[1:]))
"""


def test_sigterm_checkpoints_the_current_step_and_exits_143(capsys, tmp_path):
    out = tmp_path / "t"
    proc = run("-c", SIGTERM_AT_STEP_4, "train", "lambert", "--out", str(out), *SETS)
    assert proc.returncode == 143, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "interrupted at step 4 (SIGTERM)" in lines[0] and "--resume" in lines[0]
    assert torch.load(out / "ckpt.pt", weights_only=True)["step"] == 4
    assert not (out / "model.onnx").exists() and not (out / loop.LOCK_FILE).exists()
    cfg = config.load(ROOT / "configs" / "lambert.yaml", TINY)
    loop.train(cfg, out, resume=True)
    assert f"resuming {out / 'ckpt.pt'} at step 4 of 10" in capsys.readouterr().err
    assert torch.load(out / "ckpt.pt", weights_only=True)["step"] == 10


def test_a_second_train_into_a_running_folder_and_sigterm(tmp_path):
    """Two real processes: the second stops naming the first's pid; the first, sent
    SIGTERM as docker or systemd would, checkpoints and exits with 143."""
    out = tmp_path / "long"
    endless = ["--set", "train.steps=1000000", "--set", "train.log_every=1"]
    first = subprocess.Popen(
        [sys.executable, "-m", "neural_brdf", "train", "lambert", "--out", str(out)]
        + SETS
        + endless,
        cwd=ROOT,
        env=dict(os.environ, PYTHONPATH=str(ROOT)),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 300
        while first.poll() is None and time.monotonic() < deadline:
            log = out / "log.csv"
            if log.is_file() and len(log.read_text().splitlines()) > 3:
                break
            time.sleep(0.05)
        assert first.poll() is None, first.communicate()
        second = run("-m", "neural_brdf", "train", "lambert", "--out", str(out), *SETS)
        assert_one_line_error(second.returncode, second.stderr, str(out), f"pid {first.pid}")
        first.send_signal(signal.SIGTERM)
        _, err = first.communicate(timeout=300)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 143, err
    step = torch.load(out / "ckpt.pt", weights_only=True)["step"]
    assert step >= 3
    assert err.strip() == (
        f"neural-brdf: interrupted at step {step} (SIGTERM); checkpoint saved to "
        f"{out / 'ckpt.pt'}; continue with --resume"
    )
    assert not (out / loop.LOCK_FILE).exists()


@pytest.mark.parametrize(
    "command",
    [["validate"], ["codegen", "--target", "c", "-o", "out.c"], ["render", "-o", "out.png"]],
    ids=["validate", "codegen", "render"],
)
def test_a_folder_given_as_the_model_is_named_a_folder(capsys, tmp_path, command):
    # (it was "no such model file", though the folder is there: a run's folder, often)
    folder = tmp_path / "a_run"
    folder.mkdir()
    code, _, err = cli(capsys, command[0], str(folder), *command[1:])
    assert_one_line_error(code, err, str(folder), "is a folder, not a file")
    code, _, err = cli(capsys, command[0], str(tmp_path / "absent.onnx"), *command[1:])
    assert_one_line_error(code, err, "absent.onnx", "no such model file")
    # a device or a pipe is there, but no file (it was "no such model file" too)
    os.mkfifo(tmp_path / "pipe.onnx")
    for there in ("/dev/null", str(tmp_path / "pipe.onnx")):
        code, _, err = cli(capsys, command[0], there, *command[1:])
        assert_one_line_error(code, err, there, "not a regular file")


def test_a_report_of_a_model_its_metrics_did_not_measure_is_refused(capsys, run_dir, tmp_path):
    """``export RUN`` after an edit of config.yaml, or another file put in as model.onnx,
    left metrics.json measuring the old one: the report showed the old figures and
    verdicts (a graph whose minimum is -2 as 'physics checks ok') beside the new file's
    plots.  metrics.json keeps the sha256 of the file it measured; the report refuses
    another, the export says so, and a metrics.json without the digest reads as before."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    metrics = json.loads((run / "metrics.json").read_text())
    assert len(metrics[runfolder.MODEL_DIGEST]) == 64
    assert cli(capsys, "report", str(run), "-o", str(tmp_path / "ok"))[0] == 0
    cfg = run / "config.yaml"
    text = cfg.read_text()
    assert "  sigmas: 3.0\n" in text  # normalization.sigmas: another albedo bound
    cfg.write_text(text.replace("  sigmas: 3.0\n", "  sigmas: 1.0\n"))
    code, _, err = cli(capsys, "export", str(run))
    assert code == 0 and "note:" in err and "metrics.json measured the model.onnx" in err
    code, _, err = cli(capsys, "report", str(run), "-o", str(tmp_path / "stale"))
    assert_one_line_error(code, err, "metrics.json", "measured another model.onnx", "--resume")
    assert not (tmp_path / "stale").exists()
    # the way back that both lines name: --resume exports, measures and reports again
    code, out, err = cli(capsys, "train", str(cfg), "--out", str(run), "--resume")
    assert code == 0 and "already finished" not in out, out + err
    assert cli(capsys, "report", str(run), "-o", str(tmp_path / "again"))[0] == 0
    del metrics[runfolder.MODEL_DIGEST]  # written before the digest was kept
    (run / "metrics.json").write_text(json.dumps(metrics))
    assert cli(capsys, "report", str(run), "-o", str(tmp_path / "old"))[0] == 0
