"""The training session (neural_brdf.train.session, issue 28): the frame that train/loop.py,
train/many.py and inverse/fit.py share.  What the next issues add to it (an images fit's
log columns, another kind of checkpoint) are additions; a direct call of the loop writes
into no folder of the user's."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest

from neural_brdf import config
from neural_brdf.errors import InputError
from neural_brdf.train import loop
from neural_brdf.train.session import LOG_COLUMNS, RunFiles, Session

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
TINY = ["train.steps=6", "train.log_every=2", "train.checkpoint_every=3", "train.progress=false"]


def cfg(*extra: str) -> config.Config:
    return config.load(CONFIGS / "lambert.yaml", TINY + list(extra))


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def fake_loop(sess: Session, *, stop: int | None = None) -> None:
    """A loop in the session's frame: no model, a 'loss' and an extra 'image' column."""
    steps = sess.train.steps if stop is None else stop
    with sess.run(lambda: {"model": {}, "loss": 0.5}) as s:
        while s.step < steps:
            s.stop_if_interrupted()
            s.advance()
            if s.due(s.train.log_every):
                s.log(loss=1.0 / s.step, lr=0.01, image=2.0 * s.step)
            if s.due(s.train.checkpoint_every):
                s.checkpoint()


def test_extra_log_columns_are_written_and_kept_on_resume(tmp_path):
    columns = (*LOG_COLUMNS, "image")
    c = cfg()
    first = Session.one(c, tmp_path / "r", columns=columns)
    first.begin()
    fake_loop(first, stop=3)  # stopped after step 3 (its checkpoint); logged at step 2
    assert [r["step"] for r in rows(tmp_path / "r" / "log.csv")] == ["2"]
    again = Session.one(c, tmp_path / "r", resume=True, columns=columns)
    ckpt = again.resumed()
    assert ckpt is not None and ckpt["step"] == 3 and ckpt["loss"] == 0.5
    again.begin()
    again.restore(ckpt)
    fake_loop(again)
    got = rows(tmp_path / "r" / "log.csv")
    assert list(got[0]) == list(columns)
    assert [(r["step"], r["image"]) for r in got] == [("2", "4"), ("4", "8"), ("6", "12")]
    assert got[0]["val_rel_rmse"] == "" and got[0]["loss"] == "0.5"


def test_a_resume_that_cannot_write_its_log_leaves_the_old_one_whole(tmp_path, monkeypatch):
    """A resume rewrites log.csv with the rows up to its checkpoint: whole through
    fileio, so a resume stopped there (here: writing the rows fails) leaves the old log
    as it was, never a truncated one."""
    c = cfg()
    first = Session.one(c, tmp_path / "r")
    first.begin()
    fake_loop(first)
    log = tmp_path / "r" / "log.csv"
    before = log.read_bytes()
    assert [r["step"] for r in rows(log)] == ["2", "4", "6"]

    def fail(self, rowdicts):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(csv.DictWriter, "writerows", fail)
    again = Session.one(
        c.model_copy(update={"train": c.train.model_copy(update={"steps": 8})}),
        tmp_path / "r",
        resume=True,
    )
    ckpt = again.resumed()
    assert ckpt is not None and ckpt["step"] == 6
    with pytest.raises(Exception, match="log.csv"):
        again.begin()
        again.restore(ckpt)
        fake_loop(again)
    assert log.read_bytes() == before


def _resume_with_log(tmp_path, text: bytes | None, steps: int = 8, log_every: int = 2):
    """A run of 6 steps (rows 2, 4, 6; checkpoint at 6) resumed to ``steps`` (logging
    every ``log_every``) after its log.csv was replaced by ``text`` (None: kept)."""
    c = cfg()
    first = Session.one(c, tmp_path / "r")
    first.begin()
    fake_loop(first)
    log = tmp_path / "r" / "log.csv"
    if text is not None:
        log.write_bytes(text)
    _resume(tmp_path, c, steps=steps, log_every=log_every)
    return log


def _resume(tmp_path, c: config.Config, **train) -> None:
    """The run in ``tmp_path / "r"`` (checkpoint at step 6) resumed with ``train``'s
    settings changed, to the end."""
    c = c.model_copy(update={"train": c.train.model_copy(update=train)})
    again = Session.one(c, tmp_path / "r", resume=True)
    ckpt = again.resumed()
    assert ckpt is not None and ckpt["step"] == 6
    again.begin()
    again.restore(ckpt)
    fake_loop(again)


HEAD = b"step,loss,lr,seconds,val_rel_rmse\n"


@pytest.mark.parametrize(
    ("text", "says"),
    [
        (b"hello world\nfoo,bar\n", "no step column"),
        (b"\xff\xfe\x00garbage", "cannot read it"),
        (HEAD + b"2,0.5,0.01,0.1,\nfour,0.25,0.01,0.2,\n6,0.1,0.01,0.3,\n", "line 3"),
        (HEAD + b"4,0.5,0.01,0.1,\n2,0.25,0.01,0.2,\n6,0.1,0.01,0.3,\n", "line 3"),
    ],
)
def test_a_damaged_log_is_refused_on_resume_and_left_as_it_is(tmp_path, text, says):
    """A log.csv that is not the run's (another file, binary, a line that is no row,
    steps out of order) was read as far as it went, or raised a KeyError or a
    UnicodeDecodeError: the resume refuses it in one line naming it and leaves it."""
    with pytest.raises(InputError, match=f"log.csv: .*{says}.*move it away"):
        _resume_with_log(tmp_path, text)
    assert (tmp_path / "r" / "log.csv").read_bytes() == text


def test_a_log_whose_last_line_a_kill_cut_short_resumes(tmp_path, capsys):
    """The log is appended to row by row: a kill can leave its last line partial, which
    the resume drops (it was kept, its missing values empty, and a line cut inside its
    step read as a smaller step, out of order)."""
    log = _resume_with_log(tmp_path, HEAD + b"2,0.5,0.01,0.1,\n4,0.25,0.01,0.2,\n6,0.1")
    assert [r["step"] for r in rows(log)] == ["2", "4", "8"]  # (6: lost with its line)
    assert "missing" not in capsys.readouterr().err


def test_a_last_line_cut_inside_its_last_value_is_dropped(tmp_path):
    """A row is written with its newline: a last line without one was cut short, even
    when it has every column (here a held-out error of 0.0125 cut to 0.01)."""
    text = HEAD + b"2,0.5,0.01,0.1,\n4,0.25,0.01,0.2,\n6,0.1,0.01,0.3,0.01"
    log = _resume_with_log(tmp_path, text)
    assert [r["step"] for r in rows(log)] == ["2", "4", "8"]


def test_a_refused_log_leaves_config_yaml_as_it_was(tmp_path):
    """The log is read before the resume's first write: a refused one left config.yaml
    holding the refused command's settings beside the old checkpoint."""
    c = cfg()
    first = Session.one(c, tmp_path / "r")
    first.begin()
    fake_loop(first)
    before = (tmp_path / "r" / "config.yaml").read_bytes()
    (tmp_path / "r" / "log.csv").write_bytes(b"hello\n1,2\n")
    c = c.model_copy(update={"train": c.train.model_copy(update={"steps": 8, "lr": 0.02})})
    again = Session.one(c, tmp_path / "r", resume=True)
    assert again.resumed() is not None
    with pytest.raises(InputError, match="log.csv"):
        again.begin()
    assert (tmp_path / "r" / "config.yaml").read_bytes() == before


def test_a_lower_log_every_on_resume_says_nothing_is_missing(tmp_path, capsys):
    """Rows are missing only if the checkpoint's own log_every says so: rows every 4
    steps, a checkpoint at 6 (the last row at 4), resumed logging every step, lost
    nothing (it said rows were missing, by the new log_every)."""
    c = cfg("train.steps=10", "train.log_every=4")
    first = Session.one(c, tmp_path / "r")
    first.begin()
    fake_loop(first, stop=7)  # checkpoints at 3 and 6; rows at 4
    _resume(tmp_path, c, log_every=1)
    assert [r["step"] for r in rows(tmp_path / "r" / "log.csv")] == ["4", "7", "8", "9", "10"]
    assert "missing" not in capsys.readouterr().err


def test_rows_lost_before_the_checkpoint_are_said(tmp_path, capsys):
    """A log cut short well before the checkpoint's step loses rows: said on stderr."""
    log = _resume_with_log(tmp_path, HEAD + b"2,0.5,0.01,0.1,\n")
    assert [r["step"] for r in rows(log)] == ["2", "8"]
    err = capsys.readouterr().err
    assert "rows end at step 2, the checkpoint's is 6" in err


def test_a_checkpoint_of_another_kind_is_not_resumed(tmp_path):
    c = cfg()
    files = RunFiles(c, Session.one(c, tmp_path / "r").files.folder, kind="images")
    files.begin()
    files.save(files.state(2, 0.0, {"model": {}}))
    with pytest.raises(config.ConfigError, match="an images fit.*training from BRDF samples"):
        Session.one(c, tmp_path / "r", resume=True).resumed()
    again = Session.one(c, tmp_path / "r", resume=True, kind="images").resumed()
    assert again is not None and again["kind"] == "images" and again["step"] == 2


def test_the_loop_called_directly_refuses_a_folder_of_the_users(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "config.yaml").write_text("mine: true\n")
    with pytest.raises(loop.NotARunFolder, match="config.yaml"):
        loop.train(cfg(), mine)
    assert os.listdir(mine) == ["config.yaml"]
    assert (mine / "config.yaml").read_text() == "mine: true\n"


def test_the_loop_called_directly_replaces_its_own_run(tmp_path):
    run_dir = tmp_path / "r"
    loop.train(cfg(), run_dir)
    (run_dir / "model.onnx").write_bytes(b"an old export")
    (run_dir / "viewer.html").write_text("an old viewer")
    loop.train(cfg("train.steps=4"), run_dir)
    assert not (run_dir / "model.onnx").exists() and not (run_dir / "viewer.html").exists()
    assert [r["step"] for r in rows(run_dir / "log.csv")] == ["2", "4"]


def test_a_checkpoint_saved_before_a_key_existed_still_resumes():
    """A config saved by an older version lacks keys added since (texture.lobe_color):
    they take their defaults, as loading that config would, so the run resumes; a key
    that really differs is still refused."""
    from neural_brdf.train.session import check_resumable

    cfg = config.Config()
    saved = cfg.model_dump()
    del saved["texture"]["lobe_color"]  # as a checkpoint written before it existed
    check_resumable(saved, cfg, ("texture", "model"))
    changed = cfg.model_dump()
    changed["texture"]["lobes"] = cfg.texture.lobes + 1
    with pytest.raises(config.ConfigError, match=r"^texture\.lobes: differs"):
        check_resumable(changed, cfg, ("texture", "model"))
    grey = cfg.model_copy(
        update={"texture": cfg.texture.model_copy(update={"weights": "rgb", "lobe_color": "grey"})}
    )
    with pytest.raises(config.ConfigError, match=r"^texture\.(weights|lobe_color): differs"):
        check_resumable(saved, grey, ("texture",))  # the default rgb there, grey here


def test_a_resume_records_the_settings_it_changed(tmp_path, capsys):
    """A resume may change what the checkpoint need not share (train.lr here), and
    config.yaml then holds the new value: the step and the change are said on stderr and
    kept in every later checkpoint and in the run's record (metrics.json's
    training.resumes), a second resume's after the first's."""
    first = Session.one(cfg("train.lr=0.01"), tmp_path / "r")
    first.begin()
    fake_loop(first, stop=3)
    assert first.record() == {}  # a fresh run records no resume
    again = Session.one(cfg("train.lr=0.005", "train.steps=9"), tmp_path / "r", resume=True)
    ckpt = again.resumed()
    assert ckpt is not None
    again.begin()
    again.restore(ckpt)
    err = capsys.readouterr().err
    assert "at step 3" in err and "train.lr 0.01 -> 0.005" in err and "train.steps 6 -> 9" in err
    fake_loop(again, stop=6)
    assert again.record() == {
        "resumes": [{"step": 3, "changed": {"train.lr": [0.01, 0.005], "train.steps": [6, 9]}}]
    }
    third = Session.one(cfg("train.lr=0.005", "train.steps=9"), tmp_path / "r", resume=True)
    ckpt = third.resumed()
    assert ckpt is not None and ckpt["step"] == 6
    assert ckpt["resumes"] == again.record()["resumes"]  # kept by the checkpoint
    third.begin()
    third.restore(ckpt)
    assert "changed since" not in capsys.readouterr().err  # nothing changed this time
    assert [r["step"] for r in third.record()["resumes"]] == [3, 6]
    assert third.record()["resumes"][1]["changed"] == {}


def test_a_resume_refused_names_the_setting_that_differs_not_its_section():
    """A checkpoint's section that differs is named down to its first differing value
    (a moved capture folder said "target: differs ... ({'model': 'lambertian', ...", the
    whole section, cut off in a terminal)."""
    from neural_brdf.train.session import check_resumable

    saved = cfg("target.params.albedo=[0.5,0.5,0.5]", "model.hidden=[16,16]").model_dump()
    with pytest.raises(config.ConfigError) as e:
        check_resumable(saved, cfg("target.params.albedo=[0.5,0.25,0.5]", "model.hidden=[16,16]"))
    assert str(e.value).startswith("target.params.albedo[1]: differs from the checkpoint")
    assert "(0.5 there, 0.25 here)" in str(e.value)
    with pytest.raises(config.ConfigError) as e:
        check_resumable(saved, cfg("target.params.albedo=[0.5,0.5,0.5]", "model.hidden=[16]"))
    # a leaf one side lacks: the deepest part both have, with its values
    assert str(e.value).startswith("model.hidden: differs"), str(e.value)
    assert "([16, 16] there, [16] here)" in str(e.value)
    with pytest.raises(config.ConfigError) as e:
        check_resumable(saved, cfg("target.params.albedo=0.5", "model.hidden=[16,16]"))
    assert str(e.value).startswith("target.params.albedo: differs"), str(e.value)
    assert "([0.5, 0.5, 0.5] there, 0.5 here)" in str(e.value)
