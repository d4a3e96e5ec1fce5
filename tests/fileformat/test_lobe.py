"""The sampling lobe's density as the file format defines it (neural_brdf.fileformat.lobe):
against an independent reference built from analytic's visible-normal pdfs
(tests/lobe_reference.py), its integral over the hemisphere, and hostile rows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import chi2
import lobe_reference as ref
from analytic import frame
from analytic.microfacet import Distribution
from neural_brdf.fileformat import lobe

LOBES = {
    "ggx": {"alpha": 0.3, "weight": 0.7},
    "beckmann": {"alpha": 0.25, "weight": 0.6, "distribution": "beckmann"},
    "anisotropic retro": ref.ANISO_RETRO,
    "per incidence": ref.PER_INCIDENCE,
    "beckmann anisotropic": {
        "alpha": 0.2,
        "alpha_x": 0.1,
        "alpha_y": 0.4,
        "weight": 0.5,
        "distribution": "beckmann",
    },
}


def _sphere(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("name", sorted(LOBES))
def test_the_pdf_is_the_reference_mixture(name):
    stored = lobe.complete(LOBES[name])
    rng = np.random.default_rng(1)
    wi, wo = _sphere(rng, 3000), _sphere(rng, 3000)
    wi[:, 2] = np.abs(wi[:, 2])  # mostly above the horizon; wo on the whole sphere
    wi[:50, 2] *= -1.0
    got, want = lobe.pdf(stored, wi, wo), ref.mixture_pdf(wi, wo, stored)
    assert np.all(got[wo[:, 2] <= 0] == 0) and np.all(got[wi[:, 2] <= 0] == 0)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", sorted(LOBES))
@pytest.mark.parametrize("theta_deg", [10.0, 60.0])
def test_the_pdf_integrates_to_the_share_sampled_above_the_horizon(name, theta_deg):
    # The cosine share 1 - w lies above the horizon; of the lobe's share w, the visible
    # normals that reflect wi below it are refused.  The pdf's integral over the
    # hemisphere (uniform Monte Carlo) must be the share that analytic's own sampler
    # puts above the horizon (torch, independent of the code under test).
    stored = lobe.complete(LOBES[name])
    t = math.radians(theta_deg)
    n = 400_000
    rng = np.random.default_rng(2)
    wo = _sphere(rng, n)
    wo[:, 2] = np.abs(wo[:, 2])
    wi1 = np.array([math.sin(t) * 0.6, math.sin(t) * 0.8, math.cos(t)])
    total = 2.0 * math.pi * lobe.pdf(stored, np.broadcast_to(wi1, wo.shape), wo).mean()
    ax, ay, w = (float(v) for v in lobe.at(stored, math.cos(t)))
    d = Distribution(stored["distribution"], ax, ay)
    wi_t = torch.from_numpy(wi1).expand(n, 3)
    m = d.sample_visible(wi_t, torch.from_numpy(rng.random((n, 2))))
    above = float((frame.reflect(wi_t, m)[:, 2] > 0).double().mean())
    assert total == pytest.approx((1.0 - w) + w * above, rel=0.02), (total, above)


def test_hostile_rows_give_zero_never_nan():
    stored = lobe.complete(LOBES["anisotropic retro"])
    wi = np.array([[0, 0, 1], [1, 0, 0], [0, 0, 1], [0, 0, -1], [0.6, 0, 0.8]], float)
    wo = np.array([[0, 0, -1], [1, 0, 0], [1, 0, 0], [0, 0, 1], [-0.6, 0, 0.8]], float)
    got = lobe.pdf(stored, wi, wo)
    assert np.all(np.isfinite(got)) and np.all(got >= 0)
    assert list(got[:4]) == [0.0, 0.0, 0.0, 0.0]


@pytest.mark.parametrize("name", sorted(LOBES))
@pytest.mark.parametrize("theta_deg", [30.0, 75.0])
def test_the_reference_sampler_follows_the_pdf(name, theta_deg):
    # chi-square on the whole sphere (tests/chi2.py): the sampler's directions against the
    # pdf it claims, below-horizon lobe samples included (sphere=True)
    stored = lobe.complete(LOBES[name])
    t = math.radians(theta_deg)
    wi1 = np.array([math.sin(t) * 0.8, -math.sin(t) * 0.6, math.cos(t)])
    beckmann = stored["distribution"] == "beckmann"
    n = 100_000 if beckmann else 400_000  # math.erf per element: the Beckmann path is slow

    def sample_fn(u):
        u1 = np.random.default_rng(7).random(len(u))
        wo, p = lobe.sample(stored, np.broadcast_to(wi1, (len(u), 3)), u1, u)
        below = wo[:, 2] <= 0
        assert np.all(p[below] == 0) and np.all(p[~below] > 0)  # the pdf it returns
        return wo

    def pdf_fn(wo):
        return lobe.pdf(stored, np.broadcast_to(wi1, wo.shape), wo, sphere=True)

    result = chi2.chi2_test(
        sample_fn,
        pdf_fn,
        name=f"lobe-{name}-{theta_deg}",
        n_samples=n,
        test_count=2 * len(LOBES),
    )
    assert result.passed, result.summary()


def test_the_sampler_test_sees_a_wrong_roughness():
    # the same test fails for a sampler of another roughness than the pdf's
    stored = lobe.complete(LOBES["ggx"])
    other = lobe.complete({**LOBES["ggx"], "alpha": 0.4})
    wi1 = np.array([0.3, 0.0, math.sqrt(1 - 0.09)])

    def sample_fn(u):
        u1 = np.random.default_rng(7).random(len(u))
        return lobe.sample(other, np.broadcast_to(wi1, (len(u), 3)), u1, u)[0]

    def pdf_fn(wo):
        return lobe.pdf(stored, np.broadcast_to(wi1, wo.shape), wo, sphere=True)

    assert not chi2.chi2_test(sample_fn, pdf_fn, name="lobe-wrong", n_samples=200_000).passed


def test_same_density_reads_what_the_sampler_reads_and_nothing_else():
    # two fits of one lobe differ in their scored second moments, which no sampler
    # reads; every key the density reads tells two lobes apart
    a = lobe.complete({"alpha": 0.2, "weight": 0.9, "second_moment": 1.3})
    assert lobe.same_density(a, {**a, "second_moment": 2.7, "second_moment_cosine": 4.0})
    assert lobe.same_density({"alpha": 0.2, "weight": 0.9}, a)  # partial: completed first
    table = {"cos_theta": [0.2, 0.9], "alpha_x": [0.2, 0.3], "alpha_y": [0.2, 0.3]}
    table["weight"] = [0.9, 0.9]
    for other in (
        {"alpha_x": 0.3},
        {"alpha_y": 0.3},
        {"weight": 0.8},
        {"retro": True},
        {"distribution": "beckmann"},
        {"table": table},
    ):
        b = {**a, **other}
        assert not lobe.same_density(a, b), other
        # and the sampler does tell them apart: their densities differ somewhere
        wi = np.array([[0.6, 0.0, 0.8]] * 64)
        rng = np.random.default_rng(0)
        wo, _ = lobe.sample(a, wi, rng.random(64), rng.random((64, 2)))
        assert not np.allclose(lobe.pdf(a, wi, wo), lobe.pdf(lobe.complete(b), wi, wo)), other


@pytest.mark.parametrize(
    "key, given",
    [
        ("alpha", {"alpha": 1e30}),
        ("alpha_x", {"alpha": 0.5, "alpha_x": 1.5}),
        ("alpha_y", {"alpha": 0.5, "alpha_y": 1e30}),
        ("table alpha_x", {"alpha": 0.3, "table": {"alpha_x": [0.2, 3.0]}}),
        ("table alpha_y", {"alpha": 0.3, "table": {"alpha_y": [1e30, 0.3]}}),
    ],
)
def test_an_alpha_above_the_maximum_is_refused_naming_the_key(key, given):
    """The fitter's grid ends at MAX_ALPHA (1.0); a larger alpha (1e30 gave a NaN pdf at
    normal incidence in the generated code) is a one-line error naming the key, in the
    metadata (parse) and in a lobe given whole or in part (complete)."""
    from neural_brdf.errors import InputError

    assert lobe.MAX_ALPHA == 1.0
    table = {"cos_theta": [0.2, 0.9], "alpha_x": [0.2, 0.3], "alpha_y": [0.2, 0.3]}
    table["weight"] = [0.5, 0.5]
    if "table" in given:
        given = {**given, "table": {**table, **given["table"]}}
    text = lobe.to_json({"kind": lobe.KIND, "weight": 0.5, **given})
    for read in (lambda: lobe.parse(text), lambda: lobe.complete({"weight": 0.5, **given})):
        with pytest.raises(InputError, match=rf"{lobe.KEY!r}: {key} must be at most 1 ") as e:
            read()
        assert "\n" not in str(e.value)
    # the fitter's roughest lobe is taken, in a table too
    assert lobe.complete({"alpha": 1.0, "weight": 0.5})["alpha_x"] == 1.0
    assert lobe.complete({"alpha": 0.3, "weight": 0.5, "table": {**table, "alpha_x": [1.0, 1.0]}})
