"""Normalised, reciprocal modified Phong (Lewis 1994).

Also home of two small helpers shared by the Phong-like models (``retroreflective``,
``bank``): :func:`clamped_power` and :func:`power_cosine_lobe`.
"""

from __future__ import annotations

import math

import torch

from . import frame
from .base import BRDF, Lobe, cosine_lobe, luminance, rgb_pair, scalar

# Smallest base fed to ``pow``: keeps x^n and its gradient finite at x = 0.
_TINY = 1e-30


def clamped_power(x: torch.Tensor, n) -> torch.Tensor:
    """``max(0, x)^n`` for ``n >= 0`` (float or tensor), with finite value and gradient.

    ``x == 0`` would give an infinite gradient for ``0 < n < 1``; the positive branch
    therefore sees ``x`` clamped to 1e-30, and the other branch is an exact 0.  For
    ``n == 0`` the result is the indicator ``x > 0`` (the limit n -> 0+), not torch's
    ``0 ** 0 == 1``, so a clipped lobe stays clipped.
    """
    return torch.where(x > 0, x.clamp_min(_TINY) ** n, torch.zeros_like(x))


def power_cosine_lobe(axis: torch.Tensor, exponent: float, weight) -> Lobe:
    """Sampling lobe with pdf (n+1)/(2 pi) max(0, cos a)^n about ``axis`` (unit, (..., 3)).

    Integrates to 1 over the whole sphere.  ``frame.power_cosine_pdf`` is masked to
    the hemisphere about the axis: for n = 0 it alone would return 1/(2 pi) on the far
    hemisphere too (torch's 0 ** 0 == 1), i.e. integrate to 2.
    """
    w = torch.as_tensor(weight, dtype=axis.dtype, device=axis.device).expand(axis.shape[:-1])

    def sample(u):
        return frame.to_world(frame.square_to_power_cosine(u, exponent), axis)

    def pdf(wo):
        c = frame.dot(wo, axis)
        return torch.where(c > 0, frame.power_cosine_pdf(c, exponent), torch.zeros_like(c))

    return Lobe(w, sample, pdf)


class Phong(BRDF):
    """Normalised modified Phong (Lewis 1994, "Making Shaders More Physically Plausible").

    Formula::

        f = kd / pi + ks (n + 2) / (2 pi) max(0, r . wo)^n,   r = (-wi_x, -wi_y, wi_z)

    (r is the mirror of wi about the normal).

    * Reciprocal: yes.  ``r . wo = -wi_x wo_x - wi_y wo_y + wi_z wo_z`` is symmetric in
      (wi, wo) and is computed so that the swap is bit-identical.
    * Energy conserving: yes, with ``kd + ks <= 1`` per channel (checked at creation).
      The specular albedo is ``(n+2)/(2 pi) int max(0, cos a)^n max(0, cos theta_o) dwo``
      with a measured from r; at normal incidence it is exactly 1, and tilting the lobe
      (r_z = cos theta_i < 1) lowers it (Lewis 1994).  Measured (n from 0 to 1000,
      theta_i up to 89.9 deg): max 1.000 at theta_i = 0, e.g. 0.50 at 60 deg for n >= 100.
    * Differs from the source: Boksanský 2021 ("Crash Course in BRDF Implementation"
      excerpt) writes the classic un-normalised ``ks (R.V)^s cos theta_i`` shading formula, which is
      neither a BRDF in 1/sr nor energy conserving; Shirley & Marschner 2009 (ch. 24, notes) cite
      Lewis 1994 for the plausible version implemented here.  The lobe is clipped to
      ``r . wo > 0`` also for n = 0 (indicator), where ``0 ** 0`` would make it 1.

    Sampling: cosine (weight mean(kd)) + power-cosine about r (weight mean(ks)); the
    lobe can send wo below the horizon, where eval is 0 (see :mod:`analytic.base`).
    """

    name = "phong"
    reciprocal = True
    energy_conserving = True
    anisotropic = False
    notes = (
        "Lewis 1994 normalisation (n+2)/(2 pi) added to the un-normalised seed "
        "Phong lobe (Boksanský 2021); kd + ks <= 1 enforced; lobe clipped to r.wo > 0 "
        "also at n = 0."
    )
    param_space = {
        "kd": ("rgb", 0.0, 0.5),
        "ks": ("rgb", 0.0, 0.5),
        "exponent": ("float", 0.0, 500.0),
    }

    def __init__(self, *, kd=0.5, ks=0.3, exponent=20.0):
        """kd: RGB diffuse albedo in [0, 1] (default 0.5).
        ks: RGB specular albedo at normal incidence in [0, 1] (default 0.3).
        exponent: Phong exponent n >= 0 (default 20); larger is sharper.
        Requires kd + ks <= 1 in every channel."""
        kd, ks = rgb_pair("kd", kd, "ks", ks)
        n = scalar("exponent", exponent, lo=0.0)
        super().__init__(kd=kd, ks=ks, exponent=n)

    def _f(self, wi, wo):
        kd = self.const(self.params["kd"], wi)
        ks = self.const(self.params["ks"], wi)
        n = self.params["exponent"]
        # Lewis 1994 normalised Phong lobe (cited by Shirley & Marschner 2009, ch. 24 notes)
        cos_a = frame.dot(frame.reflect_z(wi), wo)
        spec = (n + 2.0) / (2.0 * math.pi) * clamped_power(cos_a, n)
        return kd / math.pi + ks * spec[..., None]

    def _lobes(self, wi):
        wd = luminance(torch.tensor(self.params["kd"])).item()
        ws = luminance(torch.tensor(self.params["ks"])).item()
        if wd + ws <= 0.0:  # f == 0: any valid density will do
            wd = 1.0
        return [
            cosine_lobe(wi, wd),
            power_cosine_lobe(frame.reflect_z(wi), self.params["exponent"], ws),
        ]
