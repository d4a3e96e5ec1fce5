"""The ``isotropic`` encoding, 8 features of (theta_h, theta_d) and the two cosines.

For an isotropic BRDF with bilateral symmetry (every analytic isotropic model here) the
configuration up to the swap is fixed by (theta_h, theta_d, cos_i cos_o); the remaining
features are redundant views that make the peaks and the grazing behaviour easy to fit
(:mod:`.angles` has the notation and why each is bit-exactly symmetric):

    u_h = log(1 + t^2 / eps) / log(1 + 1 / eps),   t = tan(theta_h / 2)
                             stretches the specular peak (docs/model.md, "The encoding"),
                             and is smooth (even) in the offset from the mirror direction
    theta_d / (pi/2)
    cos theta_h, cos theta_d
    (cos_i + cos_o) / 2, cos_i cos_o, (cos_i - cos_o)^2   masking / grazing terms
    ((cos_i - cos_o) / (cos_i + cos_o))^2                 the same, scale-free: it
                             resolves pairs a hundredth of a degree above the horizon,
                             where Ward and Ashikhmin-Shirley grow like 1 / cos^2

Columns 0 and 1, (u_h, theta_d / (pi/2)) in [0, 1]^2, are the ``theta`` grid's axes.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .angles import EPS_NORM, HALF_PI, columns, half_angle, peak_coordinate


class HalfDifference(NamedTuple):
    """The isotropic features, and what :mod:`.anisotropic` builds on."""

    features: list[torch.Tensor]  # the 8 columns, in order
    s: torch.Tensor  # wi + wo
    d: torch.Tensor  # wi - wo
    norm_s: torch.Tensor  # |s|, clamped away from 0
    u_h: torch.Tensor  # the peak coordinate (or sqrt(theta_h / (pi/2)) with peak="sqrt")


def half_difference(wi: torch.Tensor, wo: torch.Tensor, peak: str = "u_h") -> HalfDifference:
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
    return HalfDifference(feats, s, d, norm_s, u_h)


def features(wi: torch.Tensor, wo: torch.Tensor, peak: str = "u_h") -> torch.Tensor:
    """(..., 3), (..., 3) -> (..., 8), bit-exactly invariant under wi <-> wo."""
    return columns(half_difference(wi, wo, peak).features)
