"""``texture.lobe_bound: scale`` and ``texel`` (textured_model.normalized_textured,
textured_loop.bound_scale and bound_envelope, docs/model.md "The lobes' bound"): with
scale each lobe is bounded by one constant per head and channel, 1 / max(1, its largest
A+), never a table in the graph, and training divides the lobes by its own estimate of
that constant; with texel the lobes stay raw and each texel's weights are divided so
that sum_k z_k A+_k <= 1 at every node of incidence and channel, in training (by the
loop's estimate) and in the file (by the export's tables).

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
from neural_brdf.train.textured_loop import _rebound, bound_envelope, bound_scale
from neural_brdf.train.textured_model import (
    ScaledBRDF,
    TexturedBRDF,
    WeightField,
    bilinear_wrap,
    exportable,
    normalized_textured,
    texel_bound,
)
from textured_helpers import (
    INPUTS,
    albedos,
    albedos_of,
    assert_file_matches,
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


def _texel_sums(table: np.ndarray, env: np.ndarray, channels: int, lobes: int) -> np.ndarray:
    """max over nodes j of sum_k z_k,c E[j, 3k + c], per row and channel (row, 3), by loops
    (an independent reading of texel_bound's contract)."""
    out = np.zeros((len(table), 3))
    for t in range(len(table)):
        for c in range(3):
            z = [table[t, (c if channels == 3 else 0) * lobes + k] for k in range(lobes)]
            out[t, c] = max(
                sum(z[k] * env[j, 3 * k + c] for k in range(lobes)) for j in range(len(env))
            )
    return out


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("latent", [0, 1])
def test_texel_bound_holds_at_every_texel_and_between_them(channels, latent):
    torch.manual_seed(5)
    lobes = 3
    field = WeightField(4, lobes, channels=channels, latent=latent)
    with torch.no_grad():
        field.logits[0, ..., :-1] = -20.0  # texel 0: "nothing" takes it all, weights near 0
        field.logits[0, ..., -1] = 0.0
        table = field.weights()
    env = torch.rand(7, 3 * lobes) * 3.0  # lobes up to albedo 3 at some nodes
    bounded = texel_bound(table, env, field)
    ck = channels * lobes
    before = _texel_sums(table.numpy(), env.numpy(), channels, lobes)
    after = _texel_sums(bounded.numpy(), env.numpy(), channels, lobes)
    assert before.max() > 1.5  # the bound has work to do
    assert after.max() <= 1.0 + 1e-6, after.max()
    # a texel within the bound is kept as it is, and the latent columns always are
    np.testing.assert_array_equal(bounded[0].numpy(), table[0].numpy())
    np.testing.assert_array_equal(bounded[:, ck:].numpy(), table[:, ck:].numpy())
    # a texel above it is scaled, not reshaped: one factor per channel (per texel for 1)
    ratio = (bounded[1:, :ck] / table[1:, :ck]).reshape(-1, channels, lobes).numpy()
    np.testing.assert_allclose(ratio, ratio[..., :1].repeat(lobes, -1), rtol=1e-5)
    if channels == 1:  # the largest of the three channels' sums is brought to 1
        np.testing.assert_allclose(after.max(1)[before.max(1) > 1.0], 1.0, rtol=1e-5)
    # between texel centres (bilinear blends): still within
    uv = torch.from_numpy(np.random.default_rng(2).uniform(-1.0, 2.0, (2000, 2))).float()
    blended = bilinear_wrap(bounded, uv, 4).numpy()
    assert _texel_sums(blended, env.numpy(), channels, lobes).max() <= 1.0 + 1e-5
    # an envelope of another width (a per-head table, not per channel) is refused
    with pytest.raises(ValueError, match="envelope"):
        texel_bound(table, env[:, :lobes], field)


def test_training_bounds_the_texels_by_the_estimated_envelope():
    """Constant lobes (albedo 1.5 and 0.6 in closed form), all the weight on the first:
    the loop's envelope estimates those albedos, and training divides the texels'
    weights by 1.5, so f is the plain f / 1.5; nothing of it is saved."""
    model = _constant(1.5, lobes=2)
    with torch.no_grad():
        model.lobes[1].mlp.head.bias.fill_(float(np.log(np.expm1(0.6 / np.pi))))
    env = bound_envelope(model, seed=3)
    assert env.shape[1] == 6
    # an estimate at 256 points per node (the export's bound has its own tables)
    np.testing.assert_allclose(env[:, :3].numpy(), 1.5, rtol=0.05)
    np.testing.assert_allclose(env[:, 3:].numpy(), 0.6, rtol=0.05)
    wi, wo, uv = (torch.from_numpy(x) for x in rows(512, 3))
    with torch.no_grad():
        plain = model(wi, wo, uv)
        _rebound(model, "texel", 0, seed=3)
        assert model.lobe_scale is None and model.texel_envelope is not None
        bounded = model(wi, wo, uv)
    np.testing.assert_allclose(bounded.numpy(), plain.numpy() / 1.5, rtol=0.05)
    assert float(plain.abs().max()) > 0.0
    assert "texel_envelope" not in model.state_dict()


@pytest.fixture(scope="module")
def bright() -> dict:
    """The helpers' bright conditioned lobes on a 4 x 4 field, with either bound."""
    raw, _ = bright_conditioned(4)
    norm = cfgmod.Normalization(table_size=T_NODES, grid_size=S_NODES, samples=4096)
    model, info = normalized_textured(raw, norm, seed=3, bound="scale")
    table, table_info = normalized_textured(raw, norm, seed=3, bound="table")
    texel, texel_info = normalized_textured(raw, norm, seed=3, bound="texel")
    return {
        "raw": raw,
        "model": model,
        "info": info,
        "table": table,
        "table_info": table_info,
        "texel": texel,
        "texel_info": texel_info,
    }


def test_texel_bound_keeps_raw_lobes_and_bounds_every_uv(bright):
    model, info = bright["texel"], bright["texel_info"]
    assert {i["form"] for i in info} == {"texel"} and not any(i["in_graph"] for i in info)
    assert isinstance(model.lobes[0], RawBRDF)  # the lobes as trained, nothing divided
    wi = incidences(0.0, 40.0, 70.0, 86.0, 89.5)
    # texel centres of the 4 x 4 field and points between them
    uvs = np.random.default_rng(13).uniform(0.0, 1.0, (40, 2)).astype(np.float32)
    rho, _ = albedos(model, uvs, wi)
    assert rho.max() <= 1.0 + 1e-3, rho.max()
    assert rho.max() > 0.3  # not crushed
    # the lobes' own albedo is far above 1: the field carries the whole bound
    raw_rho, _ = albedos(bright["raw"], uvs, wi)
    assert raw_rho.max() > 2.0


def test_texel_bound_file_has_no_table_is_reciprocal_and_matches_torch(bright):
    model = bright["texel"]
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=INPUTS)
    dims = {tuple(t.dims) for t in onnx.load_from_string(payload).graph.initializer}
    assert (S_NODES * T_NODES, 2) not in dims
    assert_file_matches(model, payload, 23)


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
    assert_file_matches(model, payload, 21)


@pytest.mark.mitsuba
@pytest.mark.parametrize("bound", ["scale", "texel"])
def test_a_scale_or_texel_bound_run_trains_exports_and_export_rebuilds_it(tmp_path, capsys, bound):
    """Many sigmas put the tables far above 1, so that the default would keep
    a table: with ``lobe_bound: scale`` or ``texel`` the file has none, and ``export``
    of the checkpoint (which must read the same key) gives the same f."""
    from cli_helpers import cli
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "principled", size=16)
    cfg = tmp_path / "c.yaml"
    small_run_config(
        cfg,
        xml,
        texture="lobes: 2, resolution: 8, validation_uv: 8, latent: 1, weights: rgb, "
        f"lobe_bound: {bound}",
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
    meta = {p.key: p.value for p in proto.metadata_props}
    assert ("lobe_bound: texel" in meta["normalization"]) == (bound == "texel")


def test_an_unknown_lobe_bound_is_one_line(tmp_path, capsys):
    from cli_helpers import assert_one_line_error, cli

    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: teacher.xml}\ntexture: {lobe_bound: clamp}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, "texture.lobe_bound")
    assert not (tmp_path / "r").exists()
