"""Reciprocity-invariant input features of a (wi, wo) pair.

Everything is built from two vectors (convention of :mod:`analytic.frame`):

    s = wi + wo      swapping wi and wo leaves s unchanged, bit for bit (IEEE + commutes);
    d = wi - wo      swapping negates d exactly (a - b == -(b - a) in IEEE arithmetic).

A feature that is a function of ``s`` and of *products of two components of d* (or of
``wi_z * wo_z``, whose product commutes) is therefore bit-exactly symmetric, in torch
and in the exported ONNX graph alike.  No symmetrisation pass and no angle with a
branch cut (atan2) is needed.  With |wi| = |wo| = 1 (Rusinkiewicz 1998):

    cos theta_d = |s| / 2,  h = s / |s|,  cos theta_h = s_z / |s|,
    tan(theta_h / 2) = |s_xy| / (|s| + s_z),  tan(theta_d / 2) = |d| / (2 + |s|),
    cos_i + cos_o = s_z,  (cos_i - cos_o)^2 = d_z^2,  cos_i cos_o = wi_z wo_z.

Isotropic encoding (8 features).  For an isotropic BRDF with bilateral symmetry (every
analytic isotropic model here) the configuration up to the swap is fixed by
(theta_h, theta_d, cos_i cos_o); the remaining features are redundant views that make
the peaks and the grazing behaviour easy to fit:

    u_h = log(1 + t^2 / eps) / log(1 + 1 / eps),   t = tan(theta_h / 2)
                             stretches the specular peak (docs/model.md, "The encoding"),
                             and is smooth (even) in the offset from the mirror direction
    theta_d / (pi/2)
    cos theta_h, cos theta_d
    (cos_i + cos_o) / 2, cos_i cos_o, (cos_i - cos_o)^2   masking / grazing terms
    ((cos_i - cos_o) / (cos_i + cos_o))^2                 the same, scale-free: it
                             resolves pairs a hundredth of a degree above the horizon,
                             where Ward and Ashikhmin-Shirley grow like 1 / cos^2

Anisotropic encoding (14 features) adds the azimuth of h and the orientation of d.
With q = sqrt(u_h) and r = sin theta_h = |h_xy|:

    q h_x / r, q h_y / r     "stretched slope" coordinates of h: smooth at theta_h = 0
                             (q is proportional to tan(theta_h / 2) there)
    h_x, h_y
    (d_x^2 - d_y^2) / 4, d_x d_y / 2    the azimuth of d = wi - wo, sign-free (2 phi),
                                        weighted by |d_xy|^2

Since d is orthogonal to s, h and these fix d up to its sign, hence (wi, wo) up to the
swap, mirror images included.

Raw encoding (6 features, ablations only): (wi, wo) as they are.  It is NOT
reciprocal -- the network sees the order of the pair -- and it is there to measure
what the symmetric encodings buy (the ablation "symmetric encoding vs raw input").
It can represent anisotropic BRDFs, so everything that depends on the encoding (the
albedo table, the furnace grid) treats it as anisotropic: see :func:`is_anisotropic`.
"""

from __future__ import annotations

import math

import torch

ENCODINGS = ("isotropic", "anisotropic", "raw")

# |s| = 2 cos theta_d is >= 2 sin(min elevation) > 0 for two directions above the horizon;
# the clamp only protects masked-out pairs (below the horizon) from 0/0.
EPS_NORM = 1e-12

HALF_PI = 0.5 * math.pi

# The peak coordinate u_h = log(1 + t^2 / PEAK_EPS) / log(1 + 1 / PEAK_EPS), t = tan(theta_h/2).
# Why not sqrt(theta_h / (pi/2)), used before: its slope is infinite at theta_h = 0, so a
# network (piecewise linear in its inputs with ReLU) or a grid (linear within a cell) made
# a V-shaped cusp at the exact mirror direction, and pairs near u = 0 were so rare (their
# density in u vanishes like u^3) that the grid's first node was barely trained: compact
# gold read 0.13x its target at the mirror direction, 1.0x at 0.3 degrees off it.  u_h is
# a smooth function of t^2, which is itself smooth and even in the offset from the mirror
# direction, so every model built on it has a flat, not a notched, peak.  It is linear in
# t^2 up to t^2 ~ PEAK_EPS (theta_h ~ 1.1 degrees) and logarithmic beyond, where it spreads
# lobes from alpha ~ 0.02 to 1 evenly over [0, 1]; the density of lobe-sampled pairs
# near u_h = 0 stays finite.  u_h(0) = 0, u_h(90 degrees) = 1.
PEAK_EPS = 1e-4
PEAK_LOG_SCALE = 1.0 / math.log1p(1.0 / PEAK_EPS)


def peak_coordinate(tan_half: torch.Tensor) -> torch.Tensor:
    """u_h from t = tan(theta_h / 2) (see PEAK_EPS): smooth in t^2, in [0, 1]."""
    return torch.log(1.0 + (tan_half * tan_half) * (1.0 / PEAK_EPS)) * PEAK_LOG_SCALE


def half_angle(sin_part: torch.Tensor, one_plus_cos: torch.Tensor) -> torch.Tensor:
    """theta = 2 atan(sin / (1 + cos)) (both scaled alike), for theta in [0, pi).

    Unlike acos(cos), this is well conditioned near theta = 0, where acos turns a
    1-ulp difference of cos into a ~30% difference of theta (float32, theta ~ 1e-3);
    that broke torch/onnxruntime parity at 2e-5.  ONNX has Atan but no Atan2.
    """
    return 2.0 * torch.atan(sin_part / one_plus_cos.clamp_min(EPS_NORM))


def num_features(encoding: str) -> int:
    return {"isotropic": 8, "anisotropic": 14, "raw": 6}[encoding]


def is_anisotropic(encoding: str) -> bool:
    """Whether a model with this encoding can depend on the azimuth (2-D albedo table)."""
    return encoding != "isotropic"


def features(wi: torch.Tensor, wo: torch.Tensor, encoding: str, peak: str = "u_h") -> torch.Tensor:
    """(..., 3), (..., 3) -> (..., F), bit-exactly invariant under wi <-> wo
    (except for the ``raw`` ablation encoding, which is (wi, wo) itself)."""
    if encoding == "raw":
        return torch.cat([wi, wo], -1)
    s = wi + wo
    d = wi - wo
    norm_s = torch.sqrt((s * s).sum(-1)).clamp_min(EPS_NORM)
    norm_d = torch.sqrt((d * d).sum(-1))
    r_s = torch.sqrt(s[..., 0] * s[..., 0] + s[..., 1] * s[..., 1])
    cos_d = (0.5 * norm_s).clamp(0.0, 1.0)
    cos_h = (s[..., 2] / norm_s).clamp(-1.0, 1.0)
    tan_h = r_s / (norm_s + s[..., 2]).clamp_min(EPS_NORM)  # tan(theta_h / 2)
    theta_d = half_angle(norm_d, 2.0 + norm_s)
    if peak == "u_h":
        u_h = peak_coordinate(tan_h)
    else:  # "sqrt": the first version's sqrt(theta_h / (pi/2)); fits measured MERL data
        u_h = torch.sqrt(half_angle(r_s, norm_s + s[..., 2]) / HALF_PI)  # better (merl.yaml)
    dz = d[..., 2]
    sz = s[..., 2].clamp_min(EPS_NORM)
    feats = [
        u_h,
        theta_d / HALF_PI,
        cos_h,
        cos_d,
        0.5 * s[..., 2],
        wi[..., 2] * wo[..., 2],
        dz * dz,
        dz * dz / (sz * sz),
    ]
    if encoding == "anisotropic":
        hx, hy = s[..., 0] / norm_s, s[..., 1] / norm_s
        r = torch.sqrt(hx * hx + hy * hy).clamp_min(EPS_NORM)  # |hx| / r <= 1, 0 at r = 0
        dx, dy = d[..., 0], d[..., 1]
        q = torch.sqrt(u_h) if peak == "u_h" else u_h  # u_h: ~ tan(theta_h / 2) near 0
        feats += [q * hx / r, q * hy / r, hx, hy, 0.25 * (dx * dx - dy * dy), 0.5 * dx * dy]
    elif encoding != "isotropic":
        raise ValueError(f"encoding: must be one of {list(ENCODINGS)}, got {encoding!r}")
    return torch.stack(feats, -1)
