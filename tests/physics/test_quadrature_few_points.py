"""The MIS quadrature with a handful of points: every proposal keeps a point, the
estimate stays unbiased (the mixture's shares are the counts it drew), and ``albedo``
with a target's own sampler works at any ``n`` (it raised at 8 points before)."""

from __future__ import annotations

import math

import pytest
import torch

import analytic
from neural_brdf.physics import quadrature

WI = torch.tensor([[0.3, 0.0, 0.954], [0.9, 0.1, 0.42]], dtype=torch.float64)
WI = WI / WI.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("with_target", [False, True])
@pytest.mark.parametrize("n", [1, 2, 7, 8, 11, 13])
def test_a_handful_of_points_estimates_a_lambertian_albedo_without_bias(n, with_target):
    ggx = analytic.create("microfacet", alpha=0.05)
    target = ggx if with_target else None
    estimates = []
    for seed in range(300):
        wo, weight = quadrature.mis_directions(WI, n, seed, target=target)
        assert wo.shape[1] >= n and weight.shape == wo.shape[:2]
        assert torch.isfinite(weight).all() and (weight >= 0).all()
        estimates.append(weight.mean(1) / math.pi)  # f = 1/pi: rho = 1
    e = torch.stack(estimates)  # (seeds, M)
    stderr = e.std(0) / math.sqrt(len(e))
    assert ((e.mean(0) - 1.0).abs() < 4 * stderr + 1e-3).all(), (e.mean(0), stderr)


@pytest.mark.parametrize("n", [8, 11, 32])
def test_albedo_with_the_targets_sampler_works_at_a_few_points(n):
    ggx = analytic.create("microfacet", alpha=0.3)
    rho, err = quadrature.albedo(ggx.f, WI, n, seed=1, target=ggx)
    assert rho.shape == (2, 3) and torch.isfinite(rho).all() and torch.isfinite(err).all()
    ref = torch.as_tensor(analytic.albedo(ggx, WI.numpy(), n=1 << 14))
    assert (rho - ref).abs().max() < 6 * err.max() + 0.05
