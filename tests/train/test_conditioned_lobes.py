"""Conditioned lobes (``texture.latent: 1``; neural_brdf/train/conditioned.py, docs/model.md
"Conditioned lobes"): every lobe takes a latent s(uv) in [0, 1] from the field, and is
normalised by a table over (s, theta).

References are independent of the code under test: albedos by analytic's cosine
quadrature (not the MIS quadrature that builds the tables), the graph by onnxruntime.

* the latent is a column of the field's table, stays in [0, 1] at any uv, and changes
  the lobes (a lobe that ignored it would pass every other test);
* deliberately bright conditioned heads (raw albedo far above 1) have albedo <= 1 + 1e-3
  once normalised, at uv between texel centres and at s halfway between the table's s
  nodes (the worst place for an interpolated bound);
* reciprocity bit for bit through onnxruntime, and onnxruntime agrees with torch;
* a config with ``texture.latent: 1`` trains, learns, says so in the file, and
  ``export`` rebuilds the same f from the checkpoint.
"""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
import torch

from neural_brdf import config as cfgmod
from neural_brdf import export
from neural_brdf.train.conditioned import ConditionedNormalizedBRDF
from neural_brdf.train.model import RawBRDF
from neural_brdf.train.textured_model import (
    TexturedBRDF,
    WeightField,
    exportable,
    normalized_textured,
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

R = 4
S_NODES = 9


@pytest.fixture(scope="module")
def bright() -> dict:
    """The helpers' bright conditioned lobes on a 4 x 4 field; raw and normalised."""
    raw, field = bright_conditioned(R)
    norm = cfgmod.Normalization(table_size=33, grid_size=S_NODES, samples=4096)
    model, info = normalized_textured(raw, norm, seed=3)
    return {"raw": raw, "model": model, "info": info, "field": field}


def test_the_latent_is_a_column_of_the_field_in_0_1_and_changes_the_lobes(bright):
    field = bright["field"]
    table = field.weights()
    assert table.shape == (R * R, 2 + 1)
    uv = torch.from_numpy(rows(5000, 3)[2])  # uv in [-3, 3)^2: wrapping too
    with torch.no_grad():
        z, s = field.lookup(uv)
    assert z.shape == (5000, 2) and s is not None and s.shape == (5000, 1)
    assert float(s.min()) >= 0.0 and float(s.max()) <= 1.0
    assert float(s.max() - s.min()) > 0.5  # the fixture's latent spans most of [0, 1]
    # the same look-up as the frozen field of the exported graph, bit for bit
    frozen = field.frozen()
    z2, s2 = frozen.lookup(uv)
    assert torch.equal(z, z2) and torch.equal(s, s2)
    g = bright["model"].lobes[0]
    assert isinstance(g, ConditionedNormalizedBRDF) and not g.identity
    wi, wo, _ = rows(2000, 4)
    x, y = torch.from_numpy(wi), torch.from_numpy(wo)
    with torch.no_grad():
        lo = g(x, y, torch.full((2000, 1), 0.1))
        hi = g(x, y, torch.full((2000, 1), 0.9))
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    assert float((lo - hi).abs()[up].max()) > 0.05 * float(lo[up].abs().max())


def test_bright_conditioned_heads_are_bounded_between_texels_and_latent_nodes(bright):
    info = bright["info"]
    assert len(info) == 2 and min(i["raw_max_albedo"] for i in info) > 5.0
    wi = incidences(0.0, 40.0, 70.0, 86.0, 89.5)
    rng = np.random.default_rng(13)
    uvs = rng.uniform(0.0, 1.0, (40, 2)).astype(np.float32)
    rho, _ = albedos(bright["model"], uvs, wi)
    assert rho.max() <= 1.0 + 1e-3, rho.max()
    assert rho.max() > 0.5  # not crushed
    # at s halfway between the table's nodes, for each head on its own
    g = bright["model"].lobes[0]
    mids = (np.arange(S_NODES - 1) + 0.5) / (S_NODES - 1)
    fns = [
        (lambda x, y, s=s: g(x, y, torch.full((len(x), 1), float(s))))
        for s in np.concatenate([mids, [0.0, 1.0]])
    ]
    rho_s, _ = albedos_of(fns, wi)
    assert rho_s.max() <= 1.0 + 1e-3, rho_s.max()
    raw_rho, _ = albedos(bright["raw"], uvs[:5], wi[:2])
    assert raw_rho.max() > 5.0  # the same lobes and weights, un-normalised


def test_reciprocity_bit_exact_and_onnxruntime_agrees(bright):
    model = bright["model"]
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=INPUTS)
    assert_file_matches(model, payload, 21)
    # the field's table in the file has the latent's column: K + 1 = 3 columns
    tables = [t for t in onnx.load_from_string(payload).graph.initializer if t.dims == [R * R, 3]]
    assert tables


@pytest.mark.mitsuba
def test_a_latent_run_trains_exports_and_says_so(tmp_path, capsys):
    from cli_helpers import cli
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "principled", size=16)
    cfg = tmp_path / "c.yaml"
    small_run_config(
        cfg,
        xml,
        texture="lobes: 2, resolution: 8, validation_uv: 8, latent: 1, weights: rgb",
        train="steps: 150, checkpoint_every: 50, log_every: 10, progress: false",
        normalization="samples: 2048, grid_size: 5",
    )
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert code == 0, err
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert m["training"]["raw_val_rel_rmse"] < 0.8 * m["training"]["init_val_rel_rmse"]
    assert m["checks"]["reciprocity"]["value"] == 0.0 and m["checks"]["max_albedo"]["passed"]
    proto = onnx.load(str(tmp_path / "r" / "model.onnx"))
    texture = json.loads({p.key: p.value for p in proto.metadata_props}["texture"])
    assert texture["latent"] == 1
    code, _, err = cli(capsys, "export", str(tmp_path / "r"), "-o", str(tmp_path / "e.onnx"))
    assert code == 0, err
    wi, wo, uv = rows(1024, 19)
    a = run(session(str(tmp_path / "r" / "model.onnx")), wi, wo, uv)
    b = run(session(str(tmp_path / "e.onnx")), wi, wo, uv)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    assert float(np.abs(a).max()) > 0.0


def test_conditioned_lobes_with_an_anisotropic_encoding_are_one_line(tmp_path, capsys):
    from cli_helpers import assert_one_line_error, cli

    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        "target: {mitsuba: teacher.xml}\n"
        "model: {encoding: anisotropic, grid: {coords: half_disc}}\n"
        "texture: {latent: 1}\n"
    )
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, "texture.latent", "isotropic")
    assert not (tmp_path / "r").exists()


class _SharpnessTeacher:
    """f(wi, wo, uv) = a Phong-like lobe about the normal whose exponent grows with u:
    sharper to the right.  Only ``eval`` (all latent_from_teacher asks)."""

    def eval(self, wi, wo, uv):
        e = 1.0 + 200.0 * np.asarray(uv)[:, 0]
        cos = np.clip(np.asarray(wo)[:, 2], 0.0, 1.0)
        return np.repeat(((e + 2.0) / (2.0 * np.pi) * cos**e)[:, None], 3, -1)


def test_the_latent_starts_ordered_by_the_teachers_lobe_sharpness():
    from neural_brdf.train.textured_loop import latent_from_teacher

    r = 6
    logits = latent_from_teacher(_SharpnessTeacher(), r)
    assert logits.shape == (r * r, 1)
    s = torch.sigmoid(logits)[:, 0].numpy().reshape(r, r)  # [v, u]
    # sharper to the right (u): s grows along every row, the same in every row
    assert (np.diff(s, axis=1) > 0).all()
    assert 0.0 < s.min() < 0.1 and 0.9 < s.max() < 1.0


@pytest.mark.parametrize("albedo, folded", [(1.004, True), (1.06, False)])
def test_a_lobe_barely_above_one_is_folded_into_a_constant(albedo, folded):
    """textured_model.FOLD_LIMIT: a constant lobe of albedo 1.004 gets a constant scale
    (ScaledBRDF, no table in the graph), one of 1.06 keeps its table; both are <= 1
    by independent quadrature afterwards, and reciprocal bit for bit."""
    from neural_brdf.train.textured_model import FOLD_LIMIT, ScaledBRDF

    torch.manual_seed(0)
    lobe = RawBRDF("isotropic", [8], "relu", grazing_power=0.0, init_value=albedo / np.pi)
    field = WeightField(2, 1, init_std=0.0)
    with torch.no_grad():
        field.logits[:, -1] = -30.0  # all the weight on the lobe
    raw = TexturedBRDF([lobe.eval()], field).eval()
    norm = cfgmod.Normalization(table_size=17, samples=4096)
    model, info = normalized_textured(raw, norm, seed=1)
    assert isinstance(model.lobes[0], ScaledBRDF) == folded
    assert info[0]["form"] == ("scale" if folded else "table")
    assert abs(info[0]["raw_max_albedo"] - albedo) < 5e-3
    wi = incidences(0.0, 50.0, 85.0)
    uvs = np.array([[0.3, 0.6], [0.9, 0.1]], np.float32)
    rho, _ = albedos(model, uvs, wi)
    assert rho.max() <= 1.0 + 1e-3, rho.max()
    assert rho.min() > 1.0 - 2.0 * (FOLD_LIMIT - 1.0) - 0.06  # dimmed a little, not crushed
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=INPUTS)
    wi_r, wo_r, uv_r = rows(2048, 7)
    sess = session(payload)
    np.testing.assert_array_equal(run(sess, wi_r, wo_r, uv_r), run(sess, wo_r, wi_r, uv_r))
    sizes = {tuple(t.dims) for t in onnx.load_from_string(payload).graph.initializer}
    assert ((17, 3) in sizes) != folded  # the albedo table is in the graph only unfolded
