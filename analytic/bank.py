"""The Bank anisotropic BRDF (Banks 1994), normalised by its maximum albedo."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from .base import BRDF, Lobe, cosine_lobe, luminance, rgb_pair, scalar
from .phong import clamped_power

# Relative safety margin on the normalisation N(n): the quadrature below is accurate
# to about 1e-10 relative, the refinement of the maximum to better than 1e-9, so
# 1e-4 keeps the lobe's albedo <= 1 with room for float32 evaluation.
SAFETY = 1.0 + 1e-4

_GL_X, _GL_W = np.polynomial.legendre.leggauss(512)


def lobe_albedo(a_angle: np.ndarray, n: float) -> np.ndarray:
    """Directional albedo of the raw lobe max(0, -cos(A + B))^n, as a function of A.

    A is the angle between wi and the tangent T = x, B that between wo and T.  In
    coordinates about T, wo = (cos B, sin B cos psi, sin B sin psi), cos theta_o =
    sin B sin psi and dwo = sin B dB dpsi; integrating psi over (0, pi) gives
    rho(A) = 2 int_0^pi max(0, -cos(A + B))^n sin^2 B dB.  It depends on wi only
    through A (so this 1-D integral replaces a grid over (theta_i, phi_i)).  With
    t = A + B - pi the support is t in [max(-pi/2, A - pi), min(pi/2, A)] and
    rho(A) = 2 int cos^n(t) sin^2(t - A) dt: Gauss-Legendre, 512 nodes.
    """
    a = np.asarray(a_angle, dtype=np.float64)[..., None]
    lo = np.maximum(-0.5 * np.pi, a - np.pi)
    hi = np.minimum(0.5 * np.pi, a)
    t = lo + (hi - lo) * 0.5 * (_GL_X + 1.0)
    vals = np.clip(np.cos(t), 0.0, None) ** n * np.sin(t - a) ** 2
    return (hi - lo)[..., 0] * (vals @ _GL_W)


@functools.lru_cache(maxsize=256)
def normalization(n: float) -> float:
    """N(n) = SAFETY * max over wi of the raw lobe's directional albedo (cached per n).

    A grid of 721 angles A in [0, pi] (wi can take any A in (0, pi) above the
    horizon), then golden-section refinement about the best node.  The maximum is at
    A = pi/2 (wi perpendicular to T), where rho = 2 int_0^pi sin^{n+2} B dB =
    2 sqrt(pi) Gamma((n+3)/2) / Gamma((n+4)/2); e.g. N(0) = pi, N(20) = 1.0568,
    N(1000) = 0.15834 (times SAFETY).
    """
    grid = np.linspace(0.0, np.pi, 721)
    vals = lobe_albedo(grid, n)
    k = int(np.argmax(vals))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):  # golden section on [lo, hi]
        c, d = hi - g * (hi - lo), lo + g * (hi - lo)
        if lobe_albedo(c, n) >= lobe_albedo(d, n):
            hi = d
        else:
            lo = c
    best = max(float(vals[k]), float(lobe_albedo(0.5 * (lo + hi), n)))
    return SAFETY * best


class Bank(BRDF):
    """Bank's anisotropic lobe (Banks 1994) plus a Lambertian term.

    Formula, with T = +x the tangent, a = wi.T, b = wo.T::

        f = kd / pi + ks max(0, sqrt(1 - a^2) sqrt(1 - b^2) - a b)^n / N(n)

    The bracket is -cos(A + B) with A, B the angles of wi, wo to T: the lobe is a cone
    about T, peaked at B = pi - A (the "mirror" cone of a thin fibre along T).

    * Reciprocal: yes (symmetric in a, b; computed bit-symmetrically).
    * Energy conserving: yes, with kd + ks <= 1.  Banks' lobe is not normalised
      (at n = 0 its albedo is pi).  N(n) is the maximum over wi of the raw lobe's
      directional albedo, computed once per exponent by quadrature (see
      :func:`normalization`), times a 1e-4 safety margin, so the specular albedo is
      <= 1 for every wi (1/(1 + 1e-4) for wi perpendicular to T).
    * Differs from the source: Banks 1994 gives only ``ks (...)^n_s`` for shading (no
      normalisation, no 1/sr units, T from a cross product with the view vector); here
      T is the fixed tangent x, the lobe is divided by N(n), and kd / pi is added.
      For n = 0 the lobe is the indicator of a positive bracket (the limit n -> 0+).

    Sampling: cosine (weight mean(kd)) + the cone about T (weight mean(ks)), with an
    exact pdf.  B is drawn from a Cauchy density centred on B0 = pi - A with scale
    gamma = 1.2 / sqrt(n + 1), truncated to [0, pi] (inverse CDF through tan/atan),
    and psi from sin(psi)/2 on (0, pi), which matches the cos theta_o = sin B sin psi
    factor and keeps wo above the horizon.  Then
    pdf(wo) = q_B(B) (sin psi / 2) / sin B = q_B(B) wo_z / (2 sin^2 B).
    """

    name = "bank"
    reciprocal = True
    energy_conserving = True
    anisotropic = True
    notes = (
        "Seed lobe divided by N(n) = (1 + 1e-4) x max_wi of its albedo (1-D "
        "quadrature, cached); kd / pi added; kd + ks <= 1 enforced; T = +x."
    )
    param_space = {
        "kd": ("rgb", 0.0, 0.5),
        "ks": ("rgb", 0.0, 0.5),
        "exponent": ("float", 0.0, 500.0),
    }

    def __init__(self, *, kd=0.3, ks=0.5, exponent=20.0):
        """kd: RGB diffuse albedo in [0, 1] (default 0.3).
        ks: RGB albedo of the anisotropic lobe (its maximum over wi), in [0, 1]
        (default 0.5).
        exponent: lobe exponent n >= 0 (default 20); larger gives a thinner cone.
        Requires kd + ks <= 1 in every channel."""
        kd, ks = rgb_pair("kd", kd, "ks", ks)
        n = scalar("exponent", exponent, lo=0.0)
        super().__init__(kd=kd, ks=ks, exponent=n)
        self._norm = normalization(n)
        self._gamma = 1.2 / math.sqrt(n + 1.0)

    def _f(self, wi, wo):
        kd = self.const(self.params["kd"], wi)
        ks = self.const(self.params["ks"], wi)
        n = self.params["exponent"]
        a, b = wi[..., 0], wo[..., 0]
        # sqrt(1 - a^2) written as |wi_yz| (no cancellation near a = +-1)
        # (clamped so that the gradient of sqrt stays finite when z^2 underflows)
        sa = torch.sqrt((wi[..., 1] ** 2 + wi[..., 2] ** 2).clamp_min(1e-30))
        sb = torch.sqrt((wo[..., 1] ** 2 + wo[..., 2] ** 2).clamp_min(1e-30))
        # Banks 1994: ks (sqrt(1-(L.T)^2) sqrt(1-(V.T)^2) - (L.T)(V.T))^n_s
        lobe = clamped_power(sa * sb - a * b, n) / self._norm
        return kd / math.pi + ks * lobe[..., None]

    # ---------------------------------------------------------------- cone sampling
    def _cone_lobe(self, wi: torch.Tensor, weight: float) -> Lobe:
        g = self._gamma
        b0 = torch.acos((-wi[..., 0]).clamp(-1.0, 1.0))  # B0 = pi - A
        lo = torch.atan(-b0 / g)
        hi = torch.atan((math.pi - b0) / g)
        w = torch.as_tensor(weight, dtype=wi.dtype, device=wi.device).expand(wi.shape[:-1])

        def sample(u):
            bb = (b0 + g * torch.tan(lo + u[..., 0] * (hi - lo))).clamp(0.0, math.pi)
            psi = torch.acos((1.0 - 2.0 * u[..., 1]).clamp(-1.0, 1.0))
            sb = torch.sin(bb)
            return torch.stack([torch.cos(bb), sb * torch.cos(psi), sb * torch.sin(psi)], -1)

        def pdf(wo):
            bb = torch.acos(wo[..., 0].clamp(-1.0, 1.0))
            q = 1.0 / (g * (hi - lo) * (1.0 + ((bb - b0) / g) ** 2))
            s2 = (wo[..., 1] ** 2 + wo[..., 2] ** 2).clamp_min(1e-30)
            p = q * wo[..., 2] / (2.0 * s2)
            return torch.where(wo[..., 2] > 0, p, torch.zeros_like(p))

        return Lobe(w, sample, pdf)

    def _lobes(self, wi):
        wd = luminance(torch.tensor(self.params["kd"])).item()
        ws = luminance(torch.tensor(self.params["ks"])).item()
        if wd + ws <= 0.0:
            wd = 1.0
        return [cosine_lobe(wi, wd), self._cone_lobe(wi, ws)]
