"""Fresh training pairs for a textured fit (``texture.fresh_every``, docs/mitsuba.md "The
pool and the field's resolution"): the pool is drawn from the teacher again every N
steps, each draw fixed by its seed and index, so that several starts and a resumed run
see the same pairs at the same step; without the key the run draws the one pool it
always drew."""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest
import torch

from cli_helpers import assert_one_line_error, cli
from neural_brdf.train import textured_loop
from textured_helpers import one_torch_thread, small_run_config  # noqa: F401  (autouse)


class _Teacher:
    """A cheap teacher: f depends on uv and both directions, the sampler mirrors wi."""

    def __init__(self):
        self.evals = 0

    def eval(self, wi, wo, uv):
        self.evals += 1
        v = (uv[:, :1] + 0.1) * (wi[:, 2:3] + wo[:, 2:3])
        return np.concatenate([v, 2 * v, 3 * v], 1)

    def sample(self, wi, uv, u):
        return wi * np.array([-1.0, -1.0, 1.0])


def _same(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_without_fresh_pairs_the_pool_is_the_one_pool_drawn_from_the_seed():
    teacher = _Teacher()
    pool = textured_loop.PairPool(teacher, 256, seed=5)
    first = pool.at(0)
    drawn = textured_loop.pairs(
        teacher, 256, np.random.default_rng(5), peak=textured_loop.PEAK_SHARE
    )
    assert _same(first, drawn)
    assert pool.at(10**6) is first and pool.draws == 1


def test_fresh_pairs_are_drawn_every_n_steps_and_fixed_by_seed_and_index():
    teacher = _Teacher()
    pool = textured_loop.PairPool(teacher, 256, seed=5, fresh_every=4)
    d0 = pool.at(0)
    assert pool.at(3) is d0 and pool.draws == 1
    d1 = pool.at(4)
    assert pool.draws == 2 and not torch.equal(d1[2], d0[2])  # new uv
    assert all(len(x) == 256 for x in d1)
    # back at an earlier step (the next start): the same pairs again
    assert _same(pool.at(1), d0)
    # a pool made at step 9 (a resumed run) sees what a run from step 0 saw there
    other = textured_loop.PairPool(_Teacher(), 256, seed=5, fresh_every=4)
    assert _same(other.at(9), textured_loop.PairPool(teacher, 256, 5, 4).at(8))
    assert not _same(other.at(9), textured_loop.PairPool(teacher, 256, 6, 4).at(8))
    with pytest.raises(ValueError, match="fresh_every"):
        textured_loop.PairPool(teacher, 256, seed=5, fresh_every=0)


def test_a_run_with_fresh_pairs_sees_more_of_the_teacher():
    """The batches of a run with fresh pairs come from every draw, not from one pool."""
    teacher = _Teacher()
    pool = textured_loop.PairPool(teacher, 64, seed=1, fresh_every=2)
    seen = set()
    for step in range(8):
        seen.update(map(float, pool.at(step)[2][:, 0]))
    assert len(seen) == 4 * 64 and pool.draws == 4


def _config(path, xml, fresh, steps: int) -> None:
    small_run_config(
        path,
        xml,
        texture=f"lobes: 2, resolution: 8, validation_uv: 8, fresh_every: {fresh}",
        train=f"steps: {steps}, checkpoint_every: 10, log_every: 10, eval_every: 0, "
        "progress: false",
        normalization="samples: 4096",
    )


@pytest.mark.mitsuba
def test_a_resumed_run_with_fresh_pairs_continues_the_run_it_resumes(tmp_path, capsys):
    """40 steps in one run, and 20 then a resume to 40, with a draw every 10 steps: the
    same file, and metrics.json says how many draws each made."""
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "roughplastic", size=16)
    whole, part = tmp_path / "whole.yaml", tmp_path / "part.yaml"
    _config(whole, xml, 10, 40)
    _config(part, xml, 10, 20)
    code, _, err = cli(capsys, "train", str(whole), "--out", str(tmp_path / "a"))
    assert code == 0, err
    code, _, err = cli(capsys, "train", str(part), "--out", str(tmp_path / "b"))
    assert code == 0, err
    code, _, err = cli(
        capsys, "train", str(part), "--out", str(tmp_path / "b"), "--resume",
        "--set", "train.steps=40",
    )  # fmt: skip
    assert code == 0, err
    a = json.loads((tmp_path / "a" / "metrics.json").read_text())["training"]
    b = json.loads((tmp_path / "b" / "metrics.json").read_text())["training"]
    assert a["fresh_every"] == b["fresh_every"] == 10
    assert a["pool_draws"] == 4  # steps 0, 10, 20, 30
    assert b["pool_draws"] == 3  # the resume: step 0's (the init), then 20 and 30
    rng = np.random.default_rng(3)
    wi = rng.normal(size=(512, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.05
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    feeds = {"wi": wi.astype(np.float32), "wo": wi[::-1].astype(np.float32).copy()}
    feeds["uv"] = rng.random((512, 2)).astype(np.float32)

    def f(run):
        sess = ort.InferenceSession(str(run / "model.onnx"), providers=["CPUExecutionProvider"])
        return sess.run(["f"], feeds)[0]

    np.testing.assert_allclose(f(tmp_path / "b"), f(tmp_path / "a"), rtol=1e-5, atol=1e-7)
    # and it is not the run without fresh pairs
    plain = tmp_path / "plain.yaml"
    _config(plain, xml, "null", 40)
    code, _, err = cli(capsys, "train", str(plain), "--out", str(tmp_path / "c"))
    assert code == 0, err
    assert json.loads((tmp_path / "c" / "metrics.json").read_text())["training"]["pool_draws"] == 1
    assert not np.allclose(f(tmp_path / "c"), f(tmp_path / "a"), rtol=1e-3)


def test_fresh_every_must_be_a_positive_step_count(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    _config(cfg, tmp_path / "none.xml", 0, 10)
    code, out, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, "texture.fresh_every")
