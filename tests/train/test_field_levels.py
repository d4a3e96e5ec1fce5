"""A fine weight field learned as a sum of levels (``texture.field_levels``,
docs/mitsuba.md "The pool and the field's resolution"): the same R x R field in the file,
its logits the sum of tables R, R/2, R/4, ... looked up at the fine texel centres, so a
coarse logit learns from many texels' pairs; the bound holds as before, the checkpoint
and export keep the levels."""

from __future__ import annotations

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from cli_helpers import assert_one_line_error, cli
from neural_brdf.train.textured_model import WeightField, bilinear_wrap
from textured_helpers import one_torch_thread, small_run_config  # noqa: F401  (autouse)


def test_the_levels_sum_to_the_fine_logits_at_the_texel_centres():
    torch.manual_seed(1)
    f = WeightField(8, 3, channels=3, latent=1, levels=3, init_std=2.0)
    with torch.no_grad():
        for p in (*f.coarse, *f.coarse_latent, f.logits, f.latent_logits):
            p.normal_(0.0, 1.5)
    # the same field from one level: its logits are the sum, computed here by hand
    c = (torch.arange(8, dtype=torch.float32) + 0.5) / 8
    centres = torch.stack(torch.meshgrid(c, c, indexing="xy"), -1).reshape(-1, 2)

    def up(table, r):
        return bilinear_wrap(table.reshape(r * r, -1), centres, r).reshape(64, *table.shape[1:])

    one = WeightField(8, 3, channels=3, latent=1, levels=1)
    with torch.no_grad():
        one.logits.copy_(f.logits + up(f.coarse[0], 4) + up(f.coarse[1], 2))
        one.latent_logits.copy_(
            f.latent_logits + up(f.coarse_latent[0], 4) + up(f.coarse_latent[1], 2)
        )
    torch.testing.assert_close(f.weights(), one.weights(), rtol=1e-6, atol=1e-7)
    # at any uv: the table blended bilinearly, in [0, 1] and summing to at most 1
    uv = torch.rand(4096, 2) * 3 - 1
    z, s = f.lookup(uv)
    assert bool((z >= 0).all()) and bool((z.sum(-1) <= 1 + 1e-6).all())
    assert bool(((s >= 0) & (s <= 1)).all())
    frozen = f.frozen()
    torch.testing.assert_close(frozen.lookup(uv)[0], z, rtol=0, atol=0)


def test_a_coarse_level_learns_from_pairs_far_from_its_fine_texels():
    """One pair moves the four fine texels around it, and a coarse logit moves the
    weights of every texel within its reach: the point of the levels."""
    torch.manual_seed(0)
    f = WeightField(16, 2, levels=3)
    uv = torch.tensor([[0.53, 0.47]])
    f(uv)[0, 0].backward()
    fine = (f.logits.grad.abs().sum(-1) > 0).sum().item()
    assert fine == 4
    assert (f.coarse[0].grad.abs().sum(-1) > 0).sum().item() >= 4
    assert f.coarse[1].grad.abs().sum().item() > 0
    # the fine levels start at 0: the start is the coarsest table, upsampled
    assert float(f.logits.detach().abs().max()) == 0.0
    assert float(f.coarse[0].detach().abs().max()) == 0.0
    with pytest.raises(ValueError, match="divisible"):
        WeightField(10, 2, levels=3)


def _config(path, xml, r: int, levels: int) -> None:
    small_run_config(
        path,
        xml,
        texture=f"lobes: 2, resolution: {r}, field_levels: {levels}, validation_uv: 8",
        train="steps: 30, checkpoint_every: 10, log_every: 10, eval_every: 0, progress: false",
        normalization="samples: 4096",
    )


@pytest.mark.mitsuba
def test_a_run_with_levels_trains_records_and_exports_the_same_file(tmp_path, capsys):
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "roughplastic", size=16)
    cfg = tmp_path / "lv.yaml"
    _config(cfg, xml, 8, 3)
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"))
    assert code == 0, err
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["training"]["field_levels"] == 3
    ck = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=False)
    assert {"field.coarse.0", "field.coarse.1"} <= set(ck["model"])
    # export rebuilds the levels from the checkpoint: the same f as the run's own file
    code, _, err = cli(capsys, "export", str(tmp_path / "run"), "-o", str(tmp_path / "e.onnx"))
    assert code == 0, err
    rng = np.random.default_rng(2)
    wi = rng.normal(size=(256, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.05
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    feeds = {"wi": wi.astype(np.float32), "wo": wi[::-1].astype(np.float32).copy()}
    feeds["uv"] = rng.random((256, 2)).astype(np.float32)

    def f(path):
        return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
            ["f"], feeds
        )[0]

    np.testing.assert_allclose(f(tmp_path / "e.onnx"), f(tmp_path / "run" / "model.onnx"))
    # the file holds one 8 x 8 field, as without levels
    props = {p.key: p.value for p in onnx.load(str(tmp_path / "e.onnx")).metadata_props}
    assert json.loads(props["texture"])["resolution"] == [8, 8]


def test_levels_need_a_resolution_they_divide(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    _config(cfg, tmp_path / "none.xml", 10, 3)
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, "texture.field_levels", "divisible by 4")
