"""The ``anisotropic`` encoding, 14 features: the isotropic 8, the azimuth of h and the
orientation of d.

With q = sqrt(u_h) and r = sin theta_h = |h_xy|:

    q h_x / r, q h_y / r     "stretched slope" coordinates of h: smooth at theta_h = 0
                             (q is proportional to tan(theta_h / 2) there)
    h_x, h_y
    (d_x^2 - d_y^2) / 4, d_x d_y / 2    the azimuth of d = wi - wo, sign-free (2 phi),
                                        weighted by |d_xy|^2

Since d is orthogonal to s, h and these fix d up to its sign, hence (wi, wo) up to the
swap, mirror images included.  Columns 0 and 1 are the ``theta`` grid's axes, as in
:mod:`.isotropic`; columns 8 and 9, the half vector's polar map sqrt(u_h) (cos phi_h,
sin phi_h) in the unit disc, are the ``half_disc`` grid's.
"""

from __future__ import annotations

import torch

from .angles import EPS_NORM, columns
from .isotropic import half_difference


def features(wi: torch.Tensor, wo: torch.Tensor, peak: str = "u_h") -> torch.Tensor:
    """(..., 3), (..., 3) -> (..., 14), bit-exactly invariant under wi <-> wo."""
    feats, s, d, norm_s, u_h = half_difference(wi, wo, peak)
    hx, hy = s[..., 0] / norm_s, s[..., 1] / norm_s
    r = torch.sqrt(hx * hx + hy * hy).clamp_min(EPS_NORM)  # |hx| / r <= 1, 0 at r = 0
    dx, dy = d[..., 0], d[..., 1]
    q = torch.sqrt(u_h) if peak == "u_h" else u_h  # u_h: ~ tan(theta_h / 2) near 0
    feats += [q * hx / r, q * hy / r, hx, hy, 0.25 * (dx * dx - dy * dy), 0.5 * dx * dy]
    return columns(feats)
