"""Analytic GGX heads beside the shared lobes (``texture.analytic_heads: ggx``;
neural_brdf/train/ggx_heads.py, docs/model.md "Analytic GGX heads").

* the heads are the analytic library's GGX (its D and Smith G1, written there from
  Walter et al. 2007) and its Schlick factor, in another form;
* reciprocal bit for bit in float32, 0 below the horizon, finite at grazing;
* each head's albedo is at most 1 for every alpha, by importance sampling of the visible
  normals (the library's sampler), down to alpha 0.01 and 89.5 degrees;
* alpha's start from the teacher's eval finds a homogeneous principled's alpha;
* a textured model with the heads, its texels bounded, keeps albedo <= 1 between texel
  centres with weights as bright as the bound allows, and its file is reciprocal bit for
  bit and equal to torch's model;
* the projection keeps each texel's alpha;
* a run with the heads trains, exports, says so, and a bad combination is one line.
"""

from __future__ import annotations

import json
import math

import numpy as np
import onnx
import pytest
import torch

from analytic import frame
from analytic.fresnel import schlick
from analytic.microfacet import Distribution
from neural_brdf import config as cfgmod
from neural_brdf import export
from neural_brdf.train.ggx_heads import (
    ALPHA_MIN,
    GGXLobes,
    alpha_from_teacher,
    alpha_of,
    ggx_heads,
    head_envelope,
)
from neural_brdf.train.model import RawBRDF
from neural_brdf.train.textured_model import (
    TexturedBRDF,
    WeightField,
    exportable,
    normalized_textured,
)
from textured_helpers import (
    albedos,
    assert_file_matches,
    incidences,
    one_torch_thread,  # noqa: F401  (autouse: one torch thread)
    small_run_config,
)

ALPHAS = (0.01, 0.03, 0.1, 0.3, 0.6, 1.0)


def _hemisphere(n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return frame.square_to_uniform_hemisphere(torch.rand(n, 2, generator=g, dtype=dtype))


@pytest.mark.parametrize("alpha", ALPHAS)
def test_the_heads_are_the_analytic_librarys_ggx_and_schlick(alpha):
    wi, wo = _hemisphere(20000, 1), _hemisphere(20000, 2)
    got = ggx_heads(wi, wo, torch.full((len(wi), 1), alpha, dtype=torch.float64))
    d = Distribution("ggx", alpha, alpha)
    h = frame.normalize(wi + wo)
    g_a = d.D(h) * d.G1(wi) * d.G1(wo) / (4.0 * wi[:, 2] * wo[:, 2])
    g_b = g_a * schlick(0.0, frame.dot(wi, h))[:, 0]
    np.testing.assert_allclose(got[:, 0].numpy(), g_a.numpy(), rtol=1e-9)
    np.testing.assert_allclose(got[:, 1].numpy(), g_b.numpy(), rtol=1e-9, atol=1e-300)


def test_reciprocal_bit_for_bit_zero_below_the_horizon_and_finite():
    rng = np.random.default_rng(3)
    n = 50000
    v = rng.normal(size=(2, n, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    v[:, : n // 10, 2] = np.abs(v[:, : n // 10, 2]) * 1e-4  # within 0.006 degrees of it
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    wi, wo = (torch.from_numpy(x).float() for x in v)
    alpha = torch.from_numpy(rng.uniform(ALPHA_MIN, 1.0, (n, 1))).float()
    a, b = ggx_heads(wi, wo, alpha), ggx_heads(wo, wi, alpha)
    assert torch.equal(a, b)
    assert bool(torch.isfinite(a).all()) and float(a.min()) >= 0.0
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    assert bool((a[below] == 0).all()) and bool((a[~below, 0] > 0).all())


@pytest.mark.parametrize("alpha", ALPHAS)
def test_each_heads_albedo_is_at_most_one(alpha):
    """int g cos dwo by sampling the visible normals (Heitz 2018, the library's sampler):
    wo = reflect(wi, h), pdf(wo) = G1(wi) (wi . h) D(h) / (4 cos_i (wi . h)).  g_a's
    albedo is at most 1, g_b's at most its measured envelope (head_envelope) at every
    node whose cell holds the incidence, for a table of 17 and of 65 nodes; random
    samples here, a stratified quadrature there."""
    d = Distribution("ggx", alpha, alpha)
    n = 200_000
    g = torch.Generator().manual_seed(7)
    envelopes = {size: head_envelope(size)[:, 3].double() for size in (17, 65)}
    for deg in (0.0, 30.0, 60.0, 80.0, 84.0, 87.0, 88.3, 89.5):
        wi = torch.from_numpy(incidences(deg)).expand(n, 3).contiguous()
        h = d.sample_visible(wi, torch.rand(n, 2, generator=g, dtype=torch.float64))
        cd = frame.dot(wi, h)[:, None]
        wo = 2.0 * cd * h - wi
        pdf = d.pdf_visible(wi, h)[:, None] / (4.0 * cd)
        ok = (wo[:, 2:3] > 0) & (pdf > 0)
        f = ggx_heads(wi, torch.where(ok, wo, wi), torch.full((n, 1), alpha, dtype=torch.float64))
        est = torch.where(ok, f * wo[:, 2:3] / torch.where(ok, pdf, 1.0), 0.0)
        mean, err = est.mean(0), est.std(0) / math.sqrt(n)
        assert bool((mean <= 1.0 + 4.0 * err + 1e-9).all()), (alpha, deg, mean, err)
        for size, env in envelopes.items():
            step = 90.0 / (size - 1)
            for j in range(size):  # node j's cell: its neighbours' span
                if (j - 1) * step <= deg <= (j + 1) * step:
                    assert float(mean[1]) <= float(env[j]) + 4.0 * float(err[1]), (size, j, deg)
        if deg == 0.0:  # a real lobe: most of the energy at normal incidence
            assert float(mean[0]) > (0.85 if alpha <= 0.3 else 0.25)


def _principled(tmp_path, roughness: float, base: str = "0.7, 0.4, 0.2"):
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    xml = tmp_path / f"p{roughness}.xml"
    xml.write_text(
        '<bsdf version="3.0.0" type="principled">\n'
        f' <rgb name="base_color" value="{base}"/>\n'
        f' <float name="roughness" value="{roughness}"/>\n'
        ' <float name="metallic" value="1.0"/>\n'
        "</bsdf>\n"
    )
    return TexturedMitsubaTarget(xml)


@pytest.mark.parametrize("roughness", [0.25, 0.4, 0.8])
def test_alpha_starts_at_a_homogeneous_principleds_own(tmp_path, roughness):
    logits = alpha_from_teacher(_principled(tmp_path, roughness), 2)
    alpha = alpha_of(torch.sigmoid(logits))
    assert alpha.shape == (4, 1)
    assert bool(((alpha - roughness**2).abs() <= 0.2 * roughness**2).all()), alpha.ravel()


@pytest.mark.parametrize("roughness", [0.3, 0.6])
def test_head_a_is_mitsubas_principled_where_its_fresnel_is_one(tmp_path, roughness):
    """Mitsuba's principled of base colour 1 and metallic 1 (Schlick's factor with F0 = 1:
    F = 1) is g_a at alpha = roughness^2 (D, the separable Smith masking and
    1 / (4 cos cos) the same), on uniform and on grazing pairs: the head is the teacher's
    own specular lobe, not an approximation of it."""
    teacher = _principled(tmp_path, roughness, base="1, 1, 1")
    wi, wo = _hemisphere(4096, 11), _hemisphere(4096, 12)
    wi[:1024, 2] *= 0.02  # grazing rows: both directions near the horizon
    wo[:1024, 2] *= 0.02
    wi, wo = (x / x.norm(dim=1, keepdim=True) for x in (wi, wo))
    f = np.asarray(teacher.eval(wi.numpy(), wo.numpy(), np.full((4096, 2), 0.5)), np.float64)
    g = ggx_heads(wi, wo, torch.full((4096, 1), roughness**2, dtype=torch.float64))
    np.testing.assert_allclose(f, np.repeat(g[:, :1].numpy(), 3, 1), rtol=2e-4, atol=1e-6)


def _bright_model(resolution: int = 4) -> TexturedBRDF:
    """Two grey shared heads and the GGX heads, the field's weights almost all on the
    GGX heads (the 'nothing' slot far below) and alpha spanning [0.01, 1]."""
    torch.manual_seed(4)
    net = RawBRDF("isotropic", [16], "relu", heads=2, latent=1, colors=1)
    with torch.no_grad():
        net.mlp.head.bias.fill_(1.0)
        net.mlp.head.weight.normal_(0.0, 0.5)
        net.mlp.body[0].weight[:, -1].normal_(0.0, 6.0)  # the lobes change a lot with s
    field = WeightField(resolution, 4, channels=3, init_std=1.0, latent=2)
    with torch.no_grad():
        field.logits[..., -1] = -12.0
        field.logits[..., 2:4] += 3.0
        field.latent_logits.normal_(0.0, 4.0)
    return TexturedBRDF([GGXLobes(net.eval())], field).eval()


@pytest.fixture(scope="module")
def bounded():
    norm = cfgmod.Normalization(table_size=17, samples=1024)
    model, info = normalized_textured(_bright_model(), norm, seed=2, bound="texel")
    return model, info


def test_the_heads_join_the_texel_bound_with_their_envelopes(bounded):
    """g_a's columns are 1; g_b's are its measured envelope at the table's nodes, far
    below 1 at normal incidence (what frees the texels' weights) and rising to grazing."""
    model, info = bounded
    assert [i["form"] for i in info] == ["texel", "texel", "analytic", "analytic"]
    env = model.bound_envelope
    assert env.shape[1] == 12 and bool((env[:, 6:9] == 1.0).all())
    want = head_envelope(env.shape[0])[:, 3:]
    torch.testing.assert_close(env[:, 9:], want, rtol=0, atol=0)
    b = env[:, 9]
    assert float(b[0]) < 0.05 and float(b[-1]) > 0.5 and bool((b[1:] >= b[:-1]).all())
    assert float(env[:, :6].max()) > 0.0


def test_albedo_at_most_one_between_texel_centres(bounded):
    model, _ = bounded
    rng = np.random.default_rng(8)
    uvs = rng.uniform(-1.0, 2.0, (6, 2))
    rho, err = albedos(model, uvs, incidences(0.0, 45.0, 75.0, 85.0, 89.0))
    assert float((rho - 3.0 * err).max()) <= 1.0 + 1e-3, float(rho.max())
    assert float(rho.max()) > 0.3  # bright: the heads carry the weights


def test_the_file_is_reciprocal_and_equals_torch(bounded):
    model, _ = bounded
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=("wi", "wo", "uv"))
    assert_file_matches(model, payload, seed=12)


def _teacher_class(model: TexturedBRDF, table: torch.Tensor) -> type:
    """A teacher: ``model``'s lobes under the field ``table`` (3 channels, latent s and
    t), sampled uniformly (any finite teacher will do for the projection)."""
    from neural_brdf.train.textured_model import FrozenWeightField

    other = TexturedBRDF(
        list(model.lobes), FrozenWeightField(table, model.field.resolution, channels=3, latent=2)
    ).eval()

    class Teacher:
        def eval(self, wi, wo, uv):
            with torch.no_grad():
                t = [torch.as_tensor(x).float() for x in (wi, wo, uv)]
                return other(*t).double().numpy()

        def sample(self, wi, uv, u):
            return frame.square_to_uniform_hemisphere(torch.as_tensor(u)).numpy()

    return Teacher


def test_the_projections_cached_parts_are_the_lobes_own_values(bounded):
    """The projection evaluates the network's part once per latent and the heads' once
    per alpha (textured_project._Parts): its blocks hold the lobes' forward values bit
    for bit, and its normal equations, assembled from the blocks, are those of the
    lobes' whole matrix."""
    from neural_brdf.train.textured_project import _Parts

    model, _ = bounded
    lobe = model.lobes[0]
    t, m = 6, 4  # 6 texels of 4 pairs each
    wi, wo = _hemisphere(t * m, 1, torch.float32), _hemisphere(t * m, 2, torch.float32)
    cos = wo[:, 2:3].double()
    y = torch.rand(t, 3, m, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    parts = _Parts(lobe, (wi, wo), m, cos, y)
    base = torch.rand(t, 2, generator=torch.Generator().manual_seed(3)) * 4.0 - 2.0
    other_alpha, other_s = base.clone(), base.clone()
    other_alpha[:, 1] += 1.0
    other_s[:, 0] = 0.25
    for s in (base, other_alpha, other_s, base.clone()):
        with torch.no_grad():
            want = lobe(wi, wo, s.repeat_interleave(m, 0))
        a = (want.double() * cos).reshape(t, m, -1, 3).permute(0, 3, 1, 2)  # (t, 3, M, K)
        blocks, gram, rhs = parts(s)
        joined = torch.cat([b.expand(t, 3, m, -1) for b in blocks], -1)
        torch.testing.assert_close(joined, a, rtol=0, atol=0)  # the forward's values
        torch.testing.assert_close(gram, a.transpose(-1, -2) @ a, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(rhs, (a.transpose(-1, -2) @ y[..., None])[..., 0])
    assert len(parts.cache) == 4  # 2 latents x 1 alpha, 1 latent x 2 alphas: 2 + 2 parts


def test_the_projection_keeps_each_texels_alpha(bounded):
    from neural_brdf.train.textured_project import project_field, texel_centres

    model, _ = bounded
    table = model.field.weights().clone()
    table[:, -2] = 1.0  # the teacher: the model with s = 1 everywhere (a grid value)
    Teacher = _teacher_class(model, table)

    field, _ = project_field(
        model.lobes[0], model.field, Teacher(), model.bound_envelope, resolution=8, pairs=32
    )
    centres = torch.from_numpy(texel_centres(8)).float()
    _, before = model.field.lookup(centres)
    _, after = field.lookup(centres)
    assert before is not None and after is not None
    np.testing.assert_array_equal(after[:, 1].numpy(), before[:, 1].numpy())
    assert float((after[:, 0] == 1.0).float().mean()) > 0.9  # s is searched: the teacher's


def test_a_run_with_ggx_heads_trains_exports_and_says_so(tmp_path, capsys):
    from cli_helpers import cli
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "principled", size=16)
    cfg = tmp_path / "c.yaml"
    small_run_config(
        cfg,
        xml,
        texture="lobes: 2, resolution: 8, validation_uv: 8, latent: 1, weights: rgb, "
        "lobe_color: grey, lobe_bound: texel, analytic_heads: ggx",
        train="steps: 150, checkpoint_every: 50, log_every: 10, progress: false",
        normalization="samples: 2048",
    )
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert code == 0, err
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert m["training"]["raw_val_rel_rmse"] < 0.8 * m["training"]["init_val_rel_rmse"]
    assert m["checks"]["reciprocity"]["value"] == 0.0 and m["checks"]["max_albedo"]["passed"]
    proto = onnx.load(str(tmp_path / "r" / "model.onnx"))
    texture = json.loads({p.key: p.value for p in proto.metadata_props}["texture"])
    assert texture["lobes"] == 4 and texture["analytic_heads"]["lobes"] == [2, 3]
    report = (tmp_path / "r" / "report.md").read_text()
    assert "the last 2 analytic ggx heads with a roughness α(uv)" in report
    state = torch.load(tmp_path / "r" / "ckpt.pt", weights_only=False)["model"]
    assert state["field.latent_logits"].shape[1] == 2  # s, then alpha's column
    code, _, err = cli(capsys, "export", str(tmp_path / "r"), "-o", str(tmp_path / "e.onnx"))
    assert code == 0, err
    a = onnx.load(str(tmp_path / "r" / "model.onnx")).graph
    b = onnx.load(str(tmp_path / "e.onnx")).graph
    assert a.SerializeToString() == b.SerializeToString()


@pytest.mark.parametrize(
    "texture, field, says",
    [
        ("analytic_heads: ggx, lobe_bound: scale", "texture.analytic_heads", "lobe_bound: texel"),
        (  # a projected alpha from the teacher needs the heads (and a projection)
            "lobe_network: shared, lobe_bound: texel, project: 8, project_alpha: teacher",
            "texture.project_alpha",
            "analytic_heads: ggx",
        ),
    ],
)
def test_ggx_heads_without_what_they_need_are_one_line(tmp_path, capsys, texture, field, says):
    from cli_helpers import assert_one_line_error, cli
    from neural_brdf.measured.procedural import write_teacher

    xml = write_teacher(tmp_path / "teacher", "principled", size=8)
    cfg = tmp_path / "c.yaml"
    small_run_config(
        cfg,
        xml,
        texture=f"lobes: 2, resolution: 4, {texture}",
        train="steps: 10, progress: false",
        normalization="samples: 1024",
    )
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, field, says)


def test_the_projection_can_search_alpha_around_each_texels_own(bounded):
    """texture.project_alphas 3: half, one and twice the trained alpha; a teacher whose
    alpha is twice the model's everywhere (where that stays <= 1) is found."""
    from neural_brdf.train.ggx_heads import ALPHA_MIN, alpha_of
    from neural_brdf.train.textured_project import project_field, texel_centres

    model, _ = bounded
    table = model.field.weights().clone()
    doubled = alpha_of(table[:, -1]) * 2.0
    table[:, -1] = (doubled.clamp(max=1.0) - ALPHA_MIN) / (1.0 - ALPHA_MIN)
    Teacher = _teacher_class(model, table)

    r = model.field.resolution  # the same texels: each centre's alpha is a texel's own
    centres = torch.from_numpy(texel_centres(r)).float()
    _, before = model.field.lookup(centres)
    for alphas in (1, 3):
        field, info = project_field(
            model.lobes[0], model.field, Teacher(), model.bound_envelope,
            resolution=r, pairs=64, alphas=alphas,
        )  # fmt: skip
        assert info["alphas"] == alphas
        _, after = field.lookup(centres)
        got, was = alpha_of(after[:, 1]), alpha_of(before[:, 1])
        if alphas == 1:
            np.testing.assert_array_equal(got.numpy(), was.numpy())
        else:
            free = was * 2.0 <= 1.0  # texels whose doubled alpha was not clipped
            assert int(free.sum()) >= 4
            close = (got[free] - 2.0 * was[free]).abs() <= 1e-5 * was[free] + 1e-6
            assert float(close.float().mean()) >= 0.75, (got[free], was[free])


@pytest.mark.parametrize("source", ["trained", "teacher", "both"])
def test_the_projection_can_take_each_texels_alpha_from_the_teacher(bounded, source):
    """texture.project_alpha: a teacher made of a diffuse term and one GGX head whose
    alpha varies over the surface (0.05 to 0.6) and differs from the model's field.
    'teacher' gives every projected texel the teacher's alpha at its centre (within the
    fit grid's step) and a smaller residual than 'trained', which keeps the field's;
    'both' keeps, texel by texel, the better, so it is never worse than either."""
    from neural_brdf.train.ggx_heads import ALPHA_GRID
    from neural_brdf.train.textured_project import project_field, texel_centres

    def alpha_at(uv: np.ndarray) -> np.ndarray:
        return 0.05 + 0.55 * ((uv[:, 0] + 2.0 * uv[:, 1]) % 1.0)

    class Teacher:
        def eval(self, wi, wo, uv):
            a = torch.from_numpy(alpha_at(np.asarray(uv)))[:, None]
            g = ggx_heads(torch.as_tensor(wi).double(), torch.as_tensor(wo).double(), a)
            f = 0.1 / math.pi + 0.6 * g[:, 0]
            up = (np.asarray(wi)[:, 2] > 0) & (np.asarray(wo)[:, 2] > 0)
            return np.repeat((f.numpy() * up)[:, None], 3, 1)

        def sample(self, wi, uv, u):
            return frame.square_to_uniform_hemisphere(torch.as_tensor(u)).numpy()

    model, _ = bounded
    r = model.field.resolution
    centres = texel_centres(r)
    truth = alpha_at(centres)
    _, before = model.field.lookup(torch.from_numpy(centres).float())
    trained = alpha_of(before[:, 1]).double().numpy()
    assert np.abs(np.log(trained / truth)).max() > 0.5  # the field's alpha is elsewhere

    def run(which: str):
        field, info = project_field(
            model.lobes[0], model.field, Teacher(), model.bound_envelope,
            resolution=r, pairs=256, alpha_source=which, seed=3,
        )  # fmt: skip
        _, after = field.lookup(torch.from_numpy(centres).float())
        return alpha_of(after[:, 1]).double().numpy(), info

    got, info = run(source)
    assert info["alpha_source"] == source
    step = float(ALPHA_GRID[1] / ALPHA_GRID[0])  # the fit's grid: one step apart at most
    if source == "trained":
        np.testing.assert_allclose(got, trained, rtol=1e-6)
    elif source == "teacher":
        assert np.all(np.abs(np.log(got / truth)) <= math.log(step) + 1e-6), (got, truth)
        _, kept = run("trained")
        assert info["residual"] < 0.5 * kept["residual"], (info["residual"], kept["residual"])
    else:
        _, kept = run("trained")
        _, fitted = run("teacher")
        assert info["residual"] <= min(kept["residual"], fitted["residual"]) * (1 + 1e-9)
        took = np.isclose(got, trained, rtol=1e-6) | (np.abs(np.log(got / truth)) <= 0.08)
        assert took.all()
