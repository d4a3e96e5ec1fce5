"""Directional albedo of any BRDF-like callable, by multiple importance sampling.

    rho(wi) = int f(wi, wo) cos(theta_o) dwo

``analytic.albedo`` needs the model's own sampler and ``analytic.physics.albedo_of``
samples the cosine only, which is noisy on a specular peak.  A trained network has no
sampler, so this integrator mixes fixed proposals that cover the lobes a BRDF can
have, and combines them with the balance heuristic (Veach 1997, ch. 9):

* the cosine-weighted hemisphere (diffuse lobes);
* the uniform hemisphere (a defensive share: it bounds the weight f cos / p by
  2 pi max(f cos) everywhere, e.g. for a lobe spread along the horizon at grazing wi);
* GGX-distributed half vectors around the normal, at several widths, reflected about
  wi: mirror-like lobes of any sharpness down to alpha ~ 0.005 (MERL's chrome: the
  narrowest proposal cut the standard error of its albedo ninefold);
* GGX-distributed half vectors around wi: retro-reflective lobes (wo near wi);
* optionally the target's own sampler (``target=``, a :class:`neural_brdf.target.Sampled`:
  an analytic model), e.g. the training target.

The half-vector proposals have density p(wo) = D_a(h) (h . axis) / (4 wo . h) with
h = (wi + wo) / |wi + wo| (Walter et al. 2007, eq. 14).  Points are scrambled Sobol,
deterministic per seed; the standard error comes from ``REPLICAS`` independent
scramblings (as in :mod:`analytic.physics`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from analytic import frame, physics
from neural_brdf.target import Described, sampler

REPLICAS = physics.REPLICAS  # independently scrambled replicas for the standard error

# (kind, alpha, share): kind "normal" = half vectors around +z, "retro" = around wi.
PROPOSALS = (
    ("cosine", 0.0, 0.25),
    ("uniform", 0.0, 0.125),
    ("normal", 0.005, 0.0625),
    ("normal", 0.02, 0.0625),
    ("normal", 0.08, 0.1875),
    ("normal", 0.3, 0.1875),
    ("retro", 0.15, 0.125),
)
TARGET_SHARE = 0.25  # share given to the target's own sampler, when it has one


def _ggx_sample(u: torch.Tensor, alpha: float) -> torch.Tensor:
    """GGX normal around +z with density D(h) cos(theta_h) (Walter et al. 2007, eq. 35-36)."""
    u0 = u[..., 0].clamp(0.0, 1.0 - 1e-12)
    tan2 = alpha * alpha * u0 / (1.0 - u0)
    cos_t = 1.0 / torch.sqrt(1.0 + tan2)
    sin_t = torch.sqrt((1.0 - cos_t * cos_t).clamp_min(0.0))
    phi = 2.0 * math.pi * u[..., 1]
    return torch.stack([sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t], -1)


def _ggx_pdf(cos_t: torch.Tensor, alpha: float) -> torch.Tensor:
    """D(h) cos(theta_h) for the isotropic GGX D of width alpha; 0 for cos_t <= 0."""
    c = cos_t.clamp_min(1e-12)
    a2 = alpha * alpha
    t = c * c * (a2 - 1.0) + 1.0
    p = a2 * c / (math.pi * t * t)
    return torch.where(cos_t > 0, p, torch.zeros_like(p))


def _draw(kind: str, alpha: float, wi: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    if kind == "cosine":
        return frame.square_to_cosine_hemisphere(u).expand(wi.shape[:-1] + (3,))
    if kind == "uniform":
        return frame.square_to_uniform_hemisphere(u).expand(wi.shape[:-1] + (3,))
    h = _ggx_sample(u, alpha)
    if kind == "retro":
        h = frame.to_world(h, wi)
    else:
        h = h.expand(wi.shape[:-1] + (3,))
    return frame.reflect(wi, h)


def _pdf(kind: str, alpha: float, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    if kind == "cosine":
        return frame.cosine_hemisphere_pdf(wo)
    if kind == "uniform":
        return frame.uniform_hemisphere_pdf(wo)
    h = frame.half_vector(wi, wo)
    axis_cos = h[..., 2] if kind == "normal" else frame.dot(h, wi)
    return _ggx_pdf(axis_cos, alpha) / (4.0 * frame.dot(wo, h).clamp_min(1e-12))


def from_numpy(fn: Callable) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """A numpy BRDF callable (an ONNX model's ``eval``, say) as the torch callable
    :func:`albedo` takes, float64 out."""

    def tfn(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(np.asarray(fn(a.numpy(), b.numpy()), dtype=np.float64))

    return tfn


def mis_directions(
    wi: torch.Tensor, n: int, seed: int, *, target: Described | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` outgoing directions per row of ``wi`` (M, 3), drawn from :data:`PROPOSALS`
    (and ``target``'s own sampler), and their weights cos(theta_o) / p(wo) under the
    balance heuristic (0 below the horizon): -> (wo (M, n', 3), weight (M, n')), n' > n
    only when ``n`` is too few to give every proposal its point (a handful).
    ``mean(f(wi, wo) * weight)`` over the second axis estimates rho(wi) without bias;
    the directions and weights do not depend on ``f``, so the estimate is
    differentiable in ``f``'s parameters.  The j-th proposal's points are scrambled
    Sobol of seed ``seed + j``."""
    wi = torch.as_tensor(wi).reshape(-1, 3)
    own = sampler(target)
    props = list(PROPOSALS)
    if own is not None:
        props = [(k, a, s * (1.0 - TARGET_SHARE)) for k, a, s in props] + [
            ("target", 0.0, TARGET_SHARE)
        ]
    counts = [max(1, int(round(s * n))) for _, _, s in props]
    # the cosine share absorbs the rounding, keeping a point: with fewer points than the
    # proposals need (a handful) the total grows instead; the shares are the true ones
    counts[0] = max(1, counts[0] + n - sum(counts))
    per = sum(counts)
    shares = [c / per for c in counts]
    w = wi.double()[:, None, :]  # (m, 1, 3)
    wos = []
    for j, ((kind, alpha, _), c) in enumerate(zip(props, counts)):
        u = physics.sobol_points(c, seed + j)
        wb = w.expand(-1, c, 3)
        if own is not None and kind == "target":
            wos.append(own.sample_dir_t(wb, u.expand(len(w), -1, 2)))
        else:
            wos.append(_draw(kind, alpha, wb, u))
    wo = torch.cat(wos, 1)  # (m, n', 3)
    wb = w.expand_as(wo)
    p: torch.Tensor = sum(  # type: ignore[assignment]  # of tensors: a tensor
        s * (own.pdf_t(wb, wo) if own is not None and k == "target" else _pdf(k, a, wb, wo))
        for (k, a, _), s in zip(props, shares)
    )
    ok = (wo[..., 2] > 0) & (p > 0)
    weight = torch.where(ok, wo[..., 2] / p.clamp_min(1e-300), torch.zeros_like(p))
    return wo, weight


def albedo(
    fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    wi: torch.Tensor,
    n: int = 8192,
    *,
    seed: int = 0,
    target: Described | None = None,
    chunk: int = 1 << 19,
):
    """rho(wi) for each row of ``wi`` (M, 3) -> (rho (M, C), stderr (M, C)), float64.

    ``fn(wi, wo)`` takes float32 tensors (K, 3) and returns (K, C).  ``target``: the
    target, whose own sampler (``sample_dir_t`` / ``pdf_t``: an :mod:`analytic` BRDF)
    becomes one more proposal; a target without a sampler (measured data) adds none.
    Each of :data:`REPLICAS` independent scramblings is a :func:`mis_directions` set.
    """
    wi = torch.as_tensor(wi, dtype=torch.float64).reshape(-1, 3)
    per = max(n // REPLICAS, 1)  # per replica (mis_directions: at least one per proposal)
    rows_per_chunk = max(1, chunk // per)
    replicas = []
    for r in range(REPLICAS):
        out = []
        for start in range(0, len(wi), rows_per_chunk):
            w = wi[start : start + rows_per_chunk]
            wo, weight = mis_directions(w, per, seed * 7919 + r * 101, target=target)
            wb = w[:, None, :].expand_as(wo)
            f = fn(wb.reshape(-1, 3).float(), wo.reshape(-1, 3).float()).double()
            f = f.reshape(wo.shape[:-1] + (-1,))
            val = torch.where(weight[..., None] > 0, f * weight[..., None], 0.0)
            out.append(val.mean(1))
        replicas.append(torch.cat(out, 0))
    m = torch.stack(replicas, 0)
    return m.mean(0), m.std(0, unbiased=True) / math.sqrt(REPLICAS)


def albedo_at(
    fn: Callable,
    theta_deg,
    n: int = 8192,
    *,
    seed: int = 0,
    target: Described | None = None,
    azimuths: int = 0,
) -> np.ndarray:
    """rho(theta_i) (M, C) of a numpy ``fn(wi, wo)`` at incidences ``theta_deg`` (M,) in
    the xz plane, by :func:`albedo` (``target`` as there): the albedo curve of
    the report and the viewer.  With ``azimuths`` > 0, averaged over that many equally
    spaced azimuths of wi instead: what the validator's furnace measures for an
    anisotropic model."""
    t = np.radians(np.asarray(theta_deg, dtype=np.float64))
    if azimuths <= 0:
        wi = torch.from_numpy(np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], -1))
        rho, _ = albedo(from_numpy(fn), wi, n, seed=seed, target=target)
        return rho.numpy()
    phi = (torch.arange(azimuths, dtype=torch.float64) + 0.5) * (2.0 * math.pi / azimuths)
    theta = torch.from_numpy(t)[:, None].expand(len(t), azimuths)
    wi = frame.spherical(theta, phi[None].expand_as(theta)).reshape(-1, 3)
    rho, _ = albedo(from_numpy(fn), wi, n, seed=seed, target=target)
    return rho.numpy().reshape(len(t), azimuths, -1).mean(1)
