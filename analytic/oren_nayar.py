"""Oren-Nayar rough diffuse reflection (the qualitative A/B model)."""

from __future__ import annotations

import math

import numpy as np
import torch

from . import frame
from .base import BRDF, cosine_lobe, rgb, scalar


def coefficients(sigma: float) -> tuple[float, float]:
    """(A, B) of the qualitative model for roughness sigma (radians)."""
    s2 = sigma * sigma
    return 1.0 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)


def directional_albedo(sigma: float, theta_i):
    """Closed-form directional albedo of the qualitative model for albedo = 1.

    The azimuthal integral of max(0, cos dphi) is 2, and the angular factor is
    sin(theta_i) sin(theta_o) / max(cos_i, cos_o), so
    rho(theta_i) = A + (2B/pi) sin(theta_i) [ (theta_i/2 - sin(2 theta_i)/4)
                                              + (1 - sin^3 theta_i) / (3 cos theta_i) ],
    which tends to A + B/2 as theta_i -> pi/2.  (Used to document and test the
    energy behaviour; numpy in, numpy out.)
    """
    a, b = coefficients(sigma)
    t = np.asarray(theta_i, dtype=np.float64)
    c = np.maximum(np.cos(t), 1e-300)
    inner = (t / 2.0 - np.sin(2.0 * t) / 4.0) + (1.0 - np.sin(t) ** 3) / (3.0 * c)
    return a + 2.0 * b / math.pi * np.sin(t) * inner


class OrenNayar(BRDF):
    """Oren & Nayar 1994, "Generalization of Lambert's Reflectance Model", the
    qualitative model (no interreflection term).

    Formula, sigma the standard deviation of the facet slope angle (radians)::

        f = albedo / pi (A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta))
        A = 1 - 0.5 sigma^2 / (sigma^2 + 0.33),   B = 0.45 sigma^2 / (sigma^2 + 0.09)
        alpha = max(theta_i, theta_o),            beta = min(theta_i, theta_o)

    Since sin(alpha) sin(beta) = sin(theta_i) sin(theta_o), the angular factor is
    ``max(0, wi_x wo_x + wi_y wo_y) / max(cos_i, cos_o)``: no trigonometry, and finite
    at normal incidence (it grows like 1/cos near grazing, finite for cos >= 1e-7).

    * Reciprocal: yes (symmetric in wi, wo, bit for bit).
    * Energy conserving: NO (slightly).  The directional albedo has the closed form
      of :func:`directional_albedo`; it increases with theta_i, from A at normal
      incidence to A + B/2 at grazing.  For albedo = 1 the limit A + B/2 exceeds 1
      for 0 < sigma < 0.3261 rad, by at most 1.52% (1.01518 at sigma = 0.1985 rad);
      at the default sigma = 0.3 it is 1.0018.  analytic.albedo agrees with the closed
      form (1.0067 at 80 deg, sigma = 0.1985).
    * Differs from the sources: Shirley & Marschner 2009 only cite Oren & Nayar 1994; this is the
      paper's qualitative model unchanged (kept as is, so it is not energy
      conserving; scale albedo down by the measured maximum if that matters).

    Sampling: cosine-weighted hemisphere.
    """

    name = "oren_nayar"
    reciprocal = True
    energy_conserving = False
    anisotropic = False
    notes = (
        "Qualitative model unchanged. Not energy conserving: for albedo = 1 the "
        "directional albedo tends to A + B/2 at grazing, > 1 for sigma < 0.326 rad, "
        "max 1.0152 (+1.5%) at sigma = 0.199 rad; 1.0018 at the default 0.3."
    )
    param_space = {
        "albedo": ("rgb", 0.0, 1.0),
        "sigma": ("float", 0.0, 0.5 * math.pi),
    }

    def __init__(self, *, albedo=0.8, sigma=0.3):
        """albedo: RGB reflectance in [0, 1] (default 0.8).
        sigma: roughness, the standard deviation of the facet slope angle in radians,
        in [0, pi/2] (default 0.3, about 17 degrees; 0 gives Lambertian)."""
        albedo = rgb("albedo", albedo)
        sigma = scalar("sigma", sigma, lo=0.0, hi=0.5 * math.pi)
        super().__init__(albedo=albedo, sigma=sigma)
        self._a, self._b = coefficients(sigma)

    def _f(self, wi, wo):
        rho = self.const(self.params["albedo"], wi)
        # Oren & Nayar 1994 qualitative model, cos(dphi) sin(alpha) tan(beta) rewritten
        proj = (wi[..., 0] * wo[..., 0] + wi[..., 1] * wo[..., 1]).clamp_min(0.0)
        cmax = torch.maximum(wi[..., 2], wo[..., 2]).clamp_min(frame.EPS_COS)
        shape = self._a + self._b * proj / cmax
        return rho / math.pi * shape[..., None]

    def _lobes(self, wi):
        return [cosine_lobe(wi, 1.0)]
