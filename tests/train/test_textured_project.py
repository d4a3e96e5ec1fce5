"""The projection of a textured field onto frozen lobes, texel by texel
(``neural_brdf.train.textured_project``, docs/mitsuba.md "A finer field by projection"):
the exact NNLS against SciPy's and its optimality conditions, a teacher the lobes can
represent recovered texel by texel (weights and latent), the texels bounded as
``texture.lobe_bound: texel`` bounds them, the ridge toward the trained field, and the
lobes refitted on a frozen field."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from scipy.optimize import nnls as scipy_nnls

from analytic import frame
from neural_brdf import config as cfgmod
from neural_brdf.train.loop import rel_rmse
from neural_brdf.train.model import RawBRDF
from neural_brdf.train.textured_model import FrozenWeightField, TexturedBRDF, bilinear_wrap
from neural_brdf.train.textured_project import (
    _nnls_all_sets,
    draw_pairs,
    nnls,
    project_field,
    refit_lobes,
    texel_centres,
)

K, R = 3, 4


@pytest.mark.parametrize("k", [1, 3, 5])
def test_nnls_equals_scipys_and_meets_the_optimality_conditions(k):
    rng = np.random.default_rng(k)
    a = rng.normal(size=(64, 40, k))
    y = rng.normal(size=(64, 40))  # random signs: many solutions on the boundary
    gram = torch.from_numpy(np.einsum("bmk,bml->bkl", a, a))
    rhs = torch.from_numpy(np.einsum("bmk,bm->bk", a, y))
    z, r = nnls(gram, rhs, torch.from_numpy((y * y).sum(-1)))
    z = z.numpy()
    for i in range(64):
        ref, norm = scipy_nnls(a[i], y[i])
        assert np.allclose(z[i], ref, atol=1e-7), (i, z[i], ref)
        assert r[i].item() == pytest.approx(norm**2, rel=1e-9)
    grad = np.einsum("bkl,bl->bk", gram.numpy(), z) - rhs.numpy()
    tol = 1e-6 * np.abs(rhs.numpy()).max()  # the solves' ridge is 1e-9 of G's diagonal
    assert (z >= 0).all()
    assert np.all(np.abs(grad[z > 0]) < tol) and np.all(grad[z == 0] > -tol)
    assert (z == 0).any() and (z > 0).any()  # both kinds of constraint were exercised


def test_nnls_stops_at_the_full_set_only_where_it_is_feasible():
    """The full-set shortcut gives the enumeration's answer on every problem, those whose
    unconstrained optimum is >= 0 (most of a projection's) and those whose is not."""
    rng = np.random.default_rng(7)
    a = rng.random(size=(3, 50, 30, 5)) ** 2
    z_true = rng.random(size=(3, 50, 5)) - np.where(rng.random((3, 50, 1)) < 0.3, 0.4, 0.0)
    y = np.einsum("cbmk,cbk->cbm", a, z_true) + 0.01 * rng.normal(size=(3, 50, 30))
    gram = torch.from_numpy(np.einsum("cbmk,cbml->cbkl", a, a))
    rhs = torch.from_numpy(np.einsum("cbmk,cbm->cbk", a, y))
    sq = torch.from_numpy((y * y).sum(-1))
    z, r = nnls(gram, rhs, sq)
    z_all, r_all = _nnls_all_sets(gram, rhs, sq)
    feasible = (torch.linalg.solve(gram, rhs) >= 0).all(-1)
    assert 0 < int(feasible.sum()) < feasible.numel()  # both paths were taken
    assert torch.allclose(z, z_all, rtol=1e-10, atol=1e-12)
    assert torch.allclose(r, r_all, rtol=1e-10, atol=1e-12)


class MixTeacher:
    """A teacher the lobes represent exactly at texel centres: at uv, the nearest
    centre's weights z* (3, K) and latent s* mix the lobes' own values; its sampler
    always fails (the pairs stay uniform)."""

    def __init__(self, lobe, z, s):
        self.lobe, self.z, self.s = lobe, z, s

    def _texel(self, uv):
        ij = np.floor(np.asarray(uv) * R).astype(int) % R
        return ij[:, 1] * R + ij[:, 0]

    def eval(self, wi, wo, uv):
        t = self._texel(uv)
        s = torch.from_numpy(self.s[t]).float()
        with torch.no_grad():
            g = self.lobe(torch.from_numpy(wi).float(), torch.from_numpy(wo).float(), s)
        g = g.double().numpy().reshape(len(t), K, 3)
        return np.einsum("nkc,nck->nc", g, self.z[t])

    def sample(self, wi, uv, u):
        return np.tile([0.0, 0.0, -1.0], (len(wi), 1))


@pytest.fixture(scope="module")
def lobe():
    torch.manual_seed(0)
    net = RawBRDF.from_config(cfgmod.Model(hidden=[8]), heads=K, latent=1).eval()
    with torch.no_grad():  # heads that differ (a new network's heads start alike)
        for p in net.parameters():
            p.add_(0.5 * torch.randn_like(p))
    return net


def _field(rng, channels=3):
    table = np.concatenate([rng.random((R * R, channels * K)), rng.random((R * R, 1))], -1)
    return FrozenWeightField(
        torch.tensor(table, dtype=torch.float32), R, channels=channels, latent=1
    )


def test_a_teacher_the_lobes_represent_is_recovered_texel_by_texel(lobe):
    rng = np.random.default_rng(1)
    z = rng.random((R * R, 3, K)) * 0.4
    z[rng.random(z.shape) < 0.3] = 0.0  # some weights on the constraint
    latents = 5
    s = rng.integers(0, latents, (R * R, 1)) / (latents - 1)  # on the search's grid
    start = _field(rng)  # another field: the search must not keep its latent
    env = torch.zeros(1, 3 * K)  # no bound
    out, fig = project_field(
        lobe, start, MixTeacher(lobe, z, s), env, resolution=R, pairs=64, latents=latents
    )
    table = out.weights().numpy()
    assert np.allclose(table[:, : 3 * K].reshape(-1, 3, K), z, atol=2e-4)
    assert np.allclose(table[:, 3 * K :], s)
    assert fig["residual"] < 1e-6 * fig["residual_trained_field"]
    assert fig["bounded_texel_share"] == 0.0
    # the order of the table is the field's: a look-up at each centre gives its texel
    uv = torch.from_numpy(texel_centres(R)).float()
    assert torch.allclose(bilinear_wrap(out.weights(), uv, R), out.weights(), atol=1e-6)


def test_projected_texels_keep_the_albedo_bound_of_every_node(lobe):
    rng = np.random.default_rng(2)
    z = rng.random((R * R, 3, K)) * 0.5
    s = np.full((R * R, 1), 0.5)
    env = torch.from_numpy(rng.random((6, 3 * K)) * 2.0).float()  # bounds that bind
    out, fig = project_field(
        lobe, _field(rng), MixTeacher(lobe, z, s), env, resolution=R, pairs=32, latents=3
    )
    w = out.weights()[:, : 3 * K].reshape(-1, 3, K)
    e = env.reshape(-1, K, 3).permute(0, 2, 1)  # (J, 3, K)
    assert (w >= 0).all()
    assert torch.einsum("tck,jck->tjc", w, e).max() <= 1.0 + 1e-5
    assert fig["bounded_texel_share"] > 0


def test_one_weight_per_lobe_fits_the_three_channels_together(lobe):
    rng = np.random.default_rng(3)
    z1 = rng.random((R * R, 1, K)) * 0.4
    s = np.zeros((R * R, 1))
    teacher = MixTeacher(lobe, np.repeat(z1, 3, 1), s)
    out, _ = project_field(
        lobe,
        _field(rng, channels=1),
        teacher,
        torch.zeros(1, 3 * K),
        resolution=R,
        pairs=48,
        latents=2,
    )
    assert out.channels == 1
    assert np.allclose(out.weights()[:, :K].numpy(), z1[:, 0], atol=2e-4)


def _data_error(lobe, out, teacher, pairs, seed):
    """The squared error of f cos of the projected field ``out`` on the pairs
    project_field drew (the same seed; one chunk: every texel's pairs in one draw)."""
    uv = np.repeat(texel_centres(R), pairs, 0)
    wi, wo, f = draw_pairs(teacher, uv, np.random.default_rng(seed))
    model = TexturedBRDF([lobe], out).eval()
    with torch.no_grad():
        got = model(*(torch.from_numpy(a).float() for a in (wi, wo, uv))).double().numpy()
    return float((((got - f) * wo[:, 2:3]) ** 2).sum())


def test_a_ridge_shrinks_each_texel_toward_the_trained_field(lobe):
    rng = np.random.default_rng(4)
    z = rng.random((R * R, 3, K)) * 0.4
    s = np.full((R * R, 1), 0.5)
    teacher = MixTeacher(lobe, z, s)
    start = _field(rng)  # the "trained" field: other weights, latent 0.5 at every texel
    start.table[:, 3 * K :] = 0.5
    env = torch.zeros(1, 3 * K)  # no bound
    kw = dict(resolution=R, pairs=32, latents=3, seed=9)
    free, f0 = project_field(lobe, start, teacher, env, **kw)
    mid, f1 = project_field(lobe, start, teacher, env, ridge=1.0, **kw)
    stiff, f2 = project_field(lobe, start, teacher, env, ridge=1e7, **kw)
    w = [m.weights()[:, : 3 * K].reshape(-1, 3, K).numpy() for m in (free, mid, stiff)]
    z0 = start.weights()[:, : 3 * K].reshape(-1, 3, K).numpy()
    assert np.allclose(w[0], z, atol=2e-4)  # no ridge: the teacher's own weights
    assert np.allclose(w[2], z0, atol=1e-4)  # a stiff ridge: the trained field's
    d_mid, d_start = np.abs(w[1] - z).sum(), np.abs(z0 - z).sum()
    assert 0.05 * d_start < d_mid < 0.95 * d_start  # in between
    # the figure is the error alone (the penalty left out), on the pairs it drew
    assert f1["residual"] == pytest.approx(_data_error(lobe, mid, teacher, 32, 9), rel=1e-4)
    assert (
        f0["residual"]
        < f1["residual"]
        < f2["residual"]
        <= f2["residual_trained_field"] * (1 + 1e-6)
    )


class ModelTeacher:
    """A teacher that is a textured model itself (any uv, between centres included);
    its sampler always fails (the pairs stay uniform)."""

    def __init__(self, model):
        self.model = model

    def eval(self, wi, wo, uv):
        with torch.no_grad():
            f = self.model(*(torch.from_numpy(np.asarray(x)).float() for x in (wi, wo, uv)))
        return f.double().numpy()

    def sample(self, wi, uv, u):
        return np.tile([0.0, 0.0, -1.0], (len(wi), 1))


def test_a_refit_trains_the_lobes_toward_the_teacher_and_keeps_the_field(lobe):
    """``texture.refit_steps``: lobes pushed off the teacher's come back toward them with
    the field frozen (the same table, bit for bit); the model passed is left as it was."""
    rng = np.random.default_rng(7)
    field = _field(rng)
    teacher = ModelTeacher(TexturedBRDF([lobe], field).eval())
    wrong = copy.deepcopy(lobe)
    torch.manual_seed(3)
    with torch.no_grad():
        for p in wrong.parameters():
            p.add_(0.3 * torch.randn_like(p))
    model = TexturedBRDF([wrong], copy.deepcopy(field)).eval()
    n = 8192
    wi, wo = (
        frame.square_to_uniform_hemisphere(torch.from_numpy(rng.random((n, 2)))).float()
        for _ in range(2)
    )
    uv = torch.from_numpy(rng.random((n, 2))).float()
    ref = torch.from_numpy(teacher.eval(wi.numpy(), wo.numpy(), uv.numpy())).float()

    def error(m):
        with torch.no_grad():
            return rel_rmse(m(wi, wo, uv), ref, wo[:, 2:3])

    before = error(model)
    out, fig = refit_lobes(model, teacher, steps=300, lr=0.01, batch=1024, seed=2, pool=1 << 14)
    assert error(out) < 0.5 * before, (error(out), before)
    assert torch.equal(out.field.table, field.table)
    assert error(model) == before  # a copy was trained
    assert not any(p.requires_grad for p in out.parameters())
    assert fig["steps"] == 300 and fig["pool"] == 1 << 14 and fig["kept_step"] > 0


def test_a_refit_never_ends_worse_than_its_start_on_its_check_pairs(lobe):
    """Lobes a hair off the teacher's, refitted at a learning rate that throws them off:
    the check pairs keep the start (step 0), the same f bit for bit.  (The teacher is not
    the start itself: there the loss and every gradient can be exactly 0, and Adam then
    leaves the lobes where they are, on a CPU whose matrix products round alike at every
    batch size.)"""
    rng = np.random.default_rng(8)
    field = _field(rng)
    model = TexturedBRDF([copy.deepcopy(lobe)], field).eval()
    taught = TexturedBRDF([copy.deepcopy(lobe)], field).eval()
    with torch.no_grad():
        g = torch.Generator().manual_seed(8)
        for p in taught.lobes.parameters():
            p.add_(1e-3 * torch.randn(p.shape, generator=g))
    teacher = ModelTeacher(taught)
    out, fig = refit_lobes(
        model, teacher, steps=60, lr=0.5, batch=256, seed=4, pool=1 << 12, check_pairs=4096,
        check_every=20,
    )  # fmt: skip
    assert [k for k, _ in fig["check_errors"]] == [0, 20, 40, 60]
    start = fig["check_errors"][0][1]
    assert fig["kept_step"] == 0 and 0 < start < 1e-2, fig["check_errors"]
    # the steps did throw them off
    assert all(e > 10 * start for _, e in fig["check_errors"][1:]), fig["check_errors"]
    wi = frame.square_to_uniform_hemisphere(torch.from_numpy(rng.random((512, 2)))).float()
    uv = torch.from_numpy(rng.random((512, 2))).float()
    with torch.no_grad():
        assert torch.equal(out(wi, wi.flip(0), uv), model(wi, wi.flip(0), uv))


def test_a_refit_measures_the_model_as_bounded(lobe):
    """``bounded``: the check measures the model as the caller will bound it (here one
    whose weights are all 0: every error is 1, so no step is kept)."""
    rng = np.random.default_rng(9)
    field = _field(rng)
    teacher = ModelTeacher(TexturedBRDF([lobe], field).eval())
    zero = FrozenWeightField(torch.zeros_like(field.table), R, channels=3, latent=1)
    model = TexturedBRDF([copy.deepcopy(lobe)], copy.deepcopy(field)).eval()
    _, fig = refit_lobes(
        model, teacher, steps=40, lr=0.01, batch=256, seed=5, pool=1 << 12, check_pairs=2048,
        check_every=20, bounded=lambda m: TexturedBRDF(list(m.lobes), zero).eval(),
    )  # fmt: skip
    assert [e for _, e in fig["check_errors"]] == [1.0, 1.0, 1.0]
    assert fig["kept_step"] == 0
