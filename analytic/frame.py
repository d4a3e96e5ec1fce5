"""The local shading frame and the small helpers that carry its convention.

Convention (shared by every model, test and file format of the project):

* directions are unit 3-vectors ``(..., 3)`` in the local frame: z is the normal,
  x the tangent (the anisotropy axis), y = z cross x;
* ``wi`` and ``wo`` both point *away* from the surface;
* a direction with ``z <= 0`` is below the horizon; a BRDF is 0 there.

Everything here is written once, in torch.  Numpy arrays are converted at the edge
(:mod:`analytic.base`), so models never re-derive these helpers.
"""

from __future__ import annotations

import math

import torch

# Cosines below this are treated as grazing when they appear in a denominator.
# 1e-7 keeps 1/cos and tan^2 finite in float32 (whose epsilon is 1.2e-7) without
# moving any value that a direction with z > 1e-7 produces.
EPS_COS = 1e-7

INV_PI = 1.0 / math.pi


def cos_theta(w: torch.Tensor) -> torch.Tensor:
    return w[..., 2]


def above(w: torch.Tensor) -> torch.Tensor:
    """Boolean mask: the direction is strictly above the horizon."""
    return w[..., 2] > 0


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def normalize(v: torch.Tensor) -> torch.Tensor:
    # Clamped so that a zero vector gives zeros, not NaN (callers mask those cases).
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-30)


def reflect(w: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Mirror ``w`` about ``n``; both point out, so the result points out too."""
    return 2.0 * dot(w, n)[..., None] * n - w


def reflect_z(w: torch.Tensor) -> torch.Tensor:
    """Mirror direction about the normal (0, 0, 1)."""
    return torch.stack([-w[..., 0], -w[..., 1], w[..., 2]], dim=-1)


def half_vector(wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """Unit half vector.  It is symmetric in (wi, wo) bit for bit, since IEEE
    addition is commutative."""
    return normalize(wi + wo)


def spherical(theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    st = torch.sin(theta)
    return torch.stack([st * torch.cos(phi), st * torch.sin(phi), torch.cos(theta)], dim=-1)


def onb(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors (t, b) with (t, b, n) orthonormal and right-handed.

    Branch-free construction of Duff et al., "Building an Orthonormal Basis,
    Revisited" (JCGT 2017); written out here from the paper's equations.
    """
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    bb = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t, bb


def to_world(local: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """Rotate ``local`` (z = pole) into the frame whose pole is ``axis``."""
    t, b = onb(axis)
    return local[..., 0:1] * t + local[..., 1:2] * b + local[..., 2:3] * axis


# --------------------------------------------------------------------------- sampling
def square_to_cosine_hemisphere(u: torch.Tensor) -> torch.Tensor:
    """Cosine-weighted hemisphere, pdf = cos(theta) / pi (Malley's method)."""
    r = torch.sqrt(u[..., 0])
    phi = 2.0 * math.pi * u[..., 1]
    z = torch.sqrt((1.0 - u[..., 0]).clamp_min(0.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def cosine_hemisphere_pdf(w: torch.Tensor) -> torch.Tensor:
    return w[..., 2].clamp_min(0.0) * INV_PI


def square_to_uniform_hemisphere(u: torch.Tensor) -> torch.Tensor:
    z = u[..., 0]
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = 2.0 * math.pi * u[..., 1]
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def uniform_hemisphere_pdf(w: torch.Tensor) -> torch.Tensor:
    return torch.where(w[..., 2] > 0, 1.0 / (2.0 * math.pi), 0.0).to(w.dtype)


def square_to_power_cosine(u: torch.Tensor, exponent) -> torch.Tensor:
    """Direction around the +z pole with pdf (n + 1) / (2 pi) cos^n(alpha)."""
    cos_a = (1.0 - u[..., 0]).clamp_min(0.0) ** (1.0 / (exponent + 1.0))
    sin_a = torch.sqrt((1.0 - cos_a * cos_a).clamp_min(0.0))
    phi = 2.0 * math.pi * u[..., 1]
    return torch.stack([sin_a * torch.cos(phi), sin_a * torch.sin(phi), cos_a], dim=-1)


def power_cosine_pdf(cos_a: torch.Tensor, exponent) -> torch.Tensor:
    # masked rather than clamped: torch evaluates 0 ** 0 as 1, which would give the
    # far hemisphere mass when the exponent is 0
    p = (exponent + 1.0) / (2.0 * math.pi) * cos_a.clamp_min(0.0) ** exponent
    return torch.where(cos_a > 0, p, torch.zeros_like(p))


# ----------------------------------------------------------------- Rusinkiewicz angles
def rusinkiewicz(wi: torch.Tensor, wo: torch.Tensor):
    """Half/difference angles (Rusinkiewicz 1998): (theta_h, phi_h, theta_d, phi_d).

    ``d`` is ``wi`` expressed in the frame of the half vector, obtained by rotating
    by -phi_h about z and then by -theta_h about y.  Swapping wi and wo keeps
    theta_h, phi_h, theta_d and sends phi_d to phi_d + pi.
    """
    h = half_vector(wi, wo)
    theta_h = torch.acos(h[..., 2].clamp(-1.0, 1.0))
    phi_h = torch.atan2(h[..., 1], h[..., 0])
    cp, sp = torch.cos(phi_h), torch.sin(phi_h)
    ct, st = torch.cos(theta_h), torch.sin(theta_h)
    # rotate wi by -phi_h about z
    x1 = cp * wi[..., 0] + sp * wi[..., 1]
    y1 = -sp * wi[..., 0] + cp * wi[..., 1]
    z1 = wi[..., 2]
    # then by -theta_h about y
    x2 = ct * x1 - st * z1
    z2 = st * x1 + ct * z1
    theta_d = torch.acos(z2.clamp(-1.0, 1.0))
    phi_d = torch.atan2(y1, x2)
    return theta_h, phi_h, theta_d, phi_d


def from_rusinkiewicz(theta_h, phi_h, theta_d, phi_d):
    """Inverse of :func:`rusinkiewicz`: returns (wi, wo)."""
    d = spherical(theta_d, phi_d)
    ct, st = torch.cos(theta_h), torch.sin(theta_h)
    cp, sp = torch.cos(phi_h), torch.sin(phi_h)

    def rotate(v):
        # by +theta_h about y, then by +phi_h about z
        x = ct * v[..., 0] + st * v[..., 2]
        z = -st * v[..., 0] + ct * v[..., 2]
        y = v[..., 1]
        return torch.stack([cp * x - sp * y, sp * x + cp * y, z], dim=-1)

    wi = rotate(d)
    h = spherical(theta_h, phi_h)
    wo = reflect(wi, h)
    return wi, wo
