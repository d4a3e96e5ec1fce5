"""``texture.lobe_bound: scale`` (textured_model.normalized_textured, textured_loop.
bound_scale, docs/model.md "The lobes' bound"): each lobe is bounded by one constant per
head and channel, 1 / max(1, its largest A+), never a table in the graph, and training
divides the lobes by its own estimate of that constant.

References are independent of the code under test: albedos by analytic's cosine
quadrature (not the MIS quadrature that builds the tables), a constant lobe's albedo in
closed form (rho / pi integrates to rho), the graph by onnxruntime.
"""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch

from neural_brdf import config as cfgmod
from neural_brdf import export
from neural_brdf.train.model import RawBRDF
from neural_brdf.train.textured_loop import bound_scale
from neural_brdf.train.textured_model import (
    ScaledBRDF,
    TexturedBRDF,
    WeightField,
    exportable,
    normalized_textured,
)
from textured_helpers import (
    INPUTS,
    albedos,
    albedos_of,
    bright_conditioned,
    incidences,
    one_torch_thread,  # noqa: F401  (autouse: one torch thread)
    rows,
    run,
    session,
    small_run_config,
)

S_NODES = 9
T_NODES = 33


def _constant(albedo: float, lobes: int = 1) -> TexturedBRDF:
    """K = ``lobes`` constant lobes f = albedo / pi, all the weight on the first."""
    torch.manual_seed(0)
    nets = [
        RawBRDF("isotropic", [8], "relu", grazing_power=0.0, init_value=albedo / np.pi).eval()
        for _ in range(lobes)
    ]
    field = WeightField(2, lobes, init_std=0.0)
    with torch.no_grad():
        field.logits[:, -1] = -30.0
        field.logits[:, 1:lobes] = -30.0
    return TexturedBRDF(nets, field).eval()


@pytest.mark.parametrize("albedo", [1.5, 0.6])
def test_bound_scale_is_one_over_the_raw_albedo_above_one(albedo):
    scale = bound_scale(_constant(albedo, lobes=2), seed=3)
    assert scale.shape == (6,)
    want = 1.0 / max(1.0, albedo)
    np.testing.assert_allclose(scale.numpy(), want, rtol=0.02)


def test_training_divides_each_lobe_by_its_scale_and_never_saves_it():
    model = _constant(1.5, lobes=2)
    wi, wo, uv = (torch.from_numpy(x) for x in rows(512, 3))
    with torch.no_grad():
        plain = model(wi, wo, uv)
        model.lobe_scale = torch.tensor([0.5, 0.25, 0.125, 1.0, 1.0, 1.0])
        scaled = model(wi, wo, uv)
    # all the weight is on lobe 0: its three channels scaled by its three constants
    np.testing.assert_allclose(scaled.numpy(), plain.numpy() * [0.5, 0.25, 0.125], rtol=1e-6)
    assert float(plain.abs().max()) > 0.0
    assert "lobe_scale" not in model.state_dict()


@pytest.fixture(scope="module")
def bright() -> dict:
    """The helpers' bright conditioned lobes on a 4 x 4 field, with either bound."""
    raw, _ = bright_conditioned(4)
    norm = cfgmod.Normalization(table_size=T_NODES, grid_size=S_NODES, samples=4096)
    model, info = normalized_textured(raw, norm, seed=3, bound="scale")
    table, table_info = normalized_textured(raw, norm, seed=3, bound="table")
    return {"raw": raw, "model": model, "info": info, "table": table, "table_info": table_info}


def test_scale_bound_folds_bright_heads_and_bounds_them_everywhere(bright):
    info, model = bright["info"], bright["model"]
    assert len(info) == 2 and min(i["raw_max_albedo"] for i in info) > 5.0
    assert isinstance(model.lobes[0], ScaledBRDF)
    assert {i["form"] for i in info} == {"scale"}
    assert {i["form"] for i in bright["table_info"]} == {"table"}  # the default keeps it
    wi = incidences(0.0, 40.0, 70.0, 86.0, 89.5)
    uvs = np.random.default_rng(13).uniform(0.0, 1.0, (40, 2)).astype(np.float32)
    rho, _ = albedos(model, uvs, wi)
    assert rho.max() <= 1.0 + 1e-3, rho.max()
    # every latent value, for each head on its own (the constant holds for all s)
    g = model.lobes[0]
    fns = [
        (lambda x, y, s=s: g(x, y, torch.full((len(x), 1), float(s))))
        for s in np.linspace(0.0, 1.0, 2 * S_NODES - 1)
    ]
    rho_s, _ = albedos_of(fns, wi)
    assert rho_s.max() <= 1.0 + 1e-3, rho_s.max()
    assert rho_s.max() > 0.5  # the brightest (s, theta) is near 1: not crushed


def test_scale_bound_file_has_no_table_is_reciprocal_and_matches_torch(bright):
    model = bright["model"]
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=INPUTS)
    dims = {tuple(t.dims) for t in onnx.load_from_string(payload).graph.initializer}
    assert (S_NODES * T_NODES, 2) not in dims  # no (s, theta) table: a constant instead
    with_table = export.to_onnx_bytes(exportable(bright["table"]), 17, inputs=INPUTS)
    dims_t = {tuple(t.dims) for t in onnx.load_from_string(with_table).graph.initializer}
    assert (S_NODES * T_NODES, 2) in dims_t  # what the default carries
    sess = session(payload)
    wi, wo, uv = rows(8192, 21)
    a = run(sess, wi, wo, uv)
    np.testing.assert_array_equal(a, run(sess, wo, wi, uv))
    assert np.isfinite(a).all() and a.min() >= 0.0
    with torch.no_grad():
        ref = model(torch.from_numpy(wi), torch.from_numpy(wo), torch.from_numpy(uv)).numpy()
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    np.testing.assert_allclose(a[up], ref[up], rtol=1e-4, atol=1e-6)


@pytest.mark.mitsuba
def test_a_scale_bound_run_trains_exports_and_export_rebuilds_it(tmp_path, capsys):
    """Many sigmas put the tables far above 1, so that the default would keep
    a table: with ``lobe_bound: scale`` the file has none, and ``export`` of the
    checkpoint (which must read the same key) gives the same f."""
    from cli_helpers import cli
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "principled", size=16)
    cfg = tmp_path / "c.yaml"
    small_run_config(
        cfg,
        xml,
        texture="lobes: 2, resolution: 8, validation_uv: 8, latent: 1, weights: rgb, "
        "lobe_bound: scale",
        train="steps: 150, checkpoint_every: 50, log_every: 10, progress: false",
        normalization="samples: 256, grid_size: 5, table_size: 17, sigmas: 200.0",
    )
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert code == 0, err
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert m["training"]["raw_val_rel_rmse"] < 0.8 * m["training"]["init_val_rel_rmse"]
    assert m["checks"]["reciprocity"]["value"] == 0.0 and m["checks"]["max_albedo"]["passed"]
    proto = onnx.load(str(tmp_path / "r" / "model.onnx"))
    assert not [t for t in proto.graph.initializer if tuple(t.dims) == (5 * 17, 2)]
    code, _, err = cli(capsys, "export", str(tmp_path / "r"), "-o", str(tmp_path / "e.onnx"))
    assert code == 0, err
    wi, wo, uv = rows(1024, 19)
    a = run(session(str(tmp_path / "r" / "model.onnx")), wi, wo, uv)
    b = run(session(str(tmp_path / "e.onnx")), wi, wo, uv)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    assert float(np.abs(a).max()) > 0.0


def test_an_unknown_lobe_bound_is_one_line(tmp_path, capsys):
    from cli_helpers import assert_one_line_error, cli

    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: teacher.xml}\ntexture: {lobe_bound: clamp}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, "texture.lobe_bound")
    assert not (tmp_path / "r").exists()
