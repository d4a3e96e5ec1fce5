"""Several starts of a textured fit (``texture.starts``, docs/mitsuba.md "Several starts"):
the start with the lowest error on the choice's own pairs continues, start 0 is the run a
single start makes, and the CLI runs, records and checkpoints the choice."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from neural_brdf.train import textured_loop
from neural_brdf.train.loop import rel_rmse
from textured_helpers import one_torch_thread, small_run_config  # noqa: F401  (autouse)


class _Scaled(torch.nn.Module):
    """f = scale x the reference: its relative RMSE is |scale - 1|."""

    def __init__(self, scale: float):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(scale))

    def forward(self, wi, wo, uv):
        return self.scale * _REF.expand(len(wi), 3)


_REF = torch.tensor([[0.2, 0.3, 0.4]])


@pytest.mark.parametrize("scales", [(1.5, 1.1, 1.3), (1.05, 1.4, 0.8), (0.5, 0.6, 0.97)])
def test_pick_start_keeps_the_lowest_error_with_its_optimizer_and_seed(scales):
    """Each start's error is set by its seed; the one returned is the lowest, with its
    own optimiser and generator, and every start ran its span from its own seed."""
    n = 64
    choose = (torch.zeros(n, 3), torch.zeros(n, 3) + 0.5, torch.zeros(n, 2), _REF.expand(n, 3))
    seen = []

    def make():
        seed = torch.initial_seed()
        model = _Scaled(scales[seed - 40])
        return model, torch.optim.Adam(model.parameters(), lr=0.1)

    def span(model, opt, gen, seed):
        seen.append((seed, gen.initial_seed(), float(model.scale.detach())))

    model, opt, gen, info = textured_loop.pick_start(make, 3, 7, 40, span, choose)
    errors = [abs(s - 1.0) for s in scales]
    best = min(range(3), key=errors.__getitem__)
    assert info["chosen_start"] == best and info["chosen_seed"] == 40 + best
    assert float(model.scale.detach()) == pytest.approx(scales[best])
    assert opt.param_groups[0]["params"][0] is model.scale
    assert gen.initial_seed() == 40 + best
    assert info["start_errors"] == pytest.approx(errors, abs=1e-6)
    assert seen == [(40 + i, 40 + i, pytest.approx(scales[i])) for i in range(3)]
    assert info["start_steps"] == 7
    with torch.no_grad():
        got = rel_rmse(model(*choose[:3]), choose[3], choose[1][:, 2:3])
    assert got == pytest.approx(min(errors), abs=1e-6)


@pytest.mark.mitsuba
def test_start_zero_is_the_single_run_and_the_best_start_is_kept(tmp_path):
    """Three whole starts: start 0's error on the choice's pairs is the single-start
    run's, the model returned is the best start's, and a continuation after a shorter
    prefix still trains (its held-out error falls)."""
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    teacher = TexturedMitsubaTarget(write_teacher(tmp_path, "principled", size=16))
    kw = dict(lobes=2, resolution=8, hidden=[16], steps=60, batch=512, pool=8192,
              val_pairs=2048, lobe_network="shared", latent=1, weights="rgb", lr=0.01)  # fmt: skip
    single, f1 = textured_loop.train_textured(teacher, seed=3, **kw)
    many, f3 = textured_loop.train_textured(teacher, seed=3, starts=3, **kw)
    choose = textured_loop.pairs(
        teacher, 2048, np.random.default_rng(3 + textured_loop.CHOOSE_SEED)
    )
    with torch.no_grad():
        e_single = rel_rmse(single(*choose[:3]), choose[3], choose[1][:, 2:3])
        e_many = rel_rmse(many(*choose[:3]), choose[3], choose[1][:, 2:3])
    assert f3["start_errors"][0] == pytest.approx(e_single, rel=1e-5)
    assert e_many == pytest.approx(min(f3["start_errors"]), rel=1e-5)
    assert f3["chosen_start"] == f3["start_errors"].index(min(f3["start_errors"]))
    assert len(set(f3["start_errors"])) == 3  # the starts differ
    # a prefix of 20 steps, then the chosen start continues to 60
    part, fp = textured_loop.train_textured(teacher, seed=3, starts=2, start_steps=20, **kw)
    assert fp["start_steps"] == 20 and fp["val_rel_rmse"] < fp["init_val_rel_rmse"]
    assert np.isfinite(fp["final_loss"])  # the continuation ran: its loss was read


@pytest.mark.mitsuba
def test_the_cli_runs_records_and_checkpoints_the_starts(tmp_path, capsys):
    from cli_helpers import cli
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "roughplastic", size=16)
    cfg = tmp_path / "c.yaml"
    small_run_config(
        cfg,
        xml,
        texture="lobes: 2, resolution: 8, validation_uv: 8, starts: 2, start_steps: 40",
        train="steps: 80, checkpoint_every: 20, log_every: 10, progress: false",
        normalization="samples: 256, table_size: 17",
    )
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert code == 0, err
    assert "2 starts of 40 steps" in err
    tr = json.loads((tmp_path / "r" / "metrics.json").read_text())["training"]
    assert tr["starts"] == 2 and tr["start_steps"] == 40 and len(tr["start_errors"]) == 2
    assert tr["chosen_start"] == tr["start_errors"].index(min(tr["start_errors"]))
    assert tr["steps"] == 80
    rows = (tmp_path / "r" / "log.csv").read_text().splitlines()[1:]
    steps = [int(r.split(",")[0]) for r in rows]
    assert steps[0] == 40 and steps[-1] == 80  # the chosen start's row, then the loop's
    assert np.isfinite(tr["final_loss"])
    ckpt = torch.load(tmp_path / "r" / "ckpt.pt", weights_only=False)
    assert ckpt["starts"]["chosen_start"] == tr["chosen_start"]
    # a resumed run trains on from its checkpoint: no starts again, the choice kept
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(tmp_path / "r"), "--resume",
        "--set", "train.steps=100",
    )  # fmt: skip
    assert code == 0, err
    assert "at step 80" in err and "starts of" not in err
    again = json.loads((tmp_path / "r" / "metrics.json").read_text())["training"]
    assert again["steps"] == 100 and again["start_errors"] == tr["start_errors"]


def test_start_steps_above_the_steps_is_one_line(tmp_path, capsys):
    from cli_helpers import assert_one_line_error, cli

    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "target: {mitsuba: teacher.xml}\ntexture: {starts: 2, start_steps: 500}\n"
        "train: {steps: 100}\n"
    )
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, "texture.start_steps")
    assert not (tmp_path / "r").exists()
