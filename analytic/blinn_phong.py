"""Normalised Blinn-Phong, and the half-vector sampling lobe shared with ``ward`` and
``ashikhmin_shirley`` (:func:`half_vector_lobe`).
"""

from __future__ import annotations

import math

import torch

from . import frame
from .base import BRDF, Lobe, cosine_lobe, luminance, rgb_pair, scalar
from .phong import clamped_power


def half_vector_lobe(wi: torch.Tensor, weight, sample_h, pdf_h) -> Lobe:
    """Sample a half vector h in the upper hemisphere and reflect wi about it.

    ``sample_h(u) -> h`` (unit, z >= 0) has density ``pdf_h(h)`` over the upper
    hemisphere (solid angle).  Then wo = 2 (wi.h) h - wi.  The map h -> wo is two to one
    over the sphere (h and -h give the same wo), and exactly one preimage of a given wo
    lies in the upper hemisphere: +-normalize(wi + wo).  That preimage can have
    wi.h < 0 (then wo points below the horizon and eval is 0), so the density over the
    whole sphere is

        p(wo) = pdf_h(h+) / (4 |wi.h+|) = pdf_h(h+) / (2 |wi + wo|),

    with h+ the preimage flipped into z >= 0 (|wi.h| = |wi + wo| / 2 for unit vectors).
    It integrates to exactly 1 over the sphere (Shirley & Marschner 2009, eq. 24.12 is the case h+ =
    normalize(wi + wo)).
    """
    w = torch.as_tensor(weight, dtype=wi.dtype, device=wi.device).expand(wi.shape[:-1])

    def sample(u):
        return frame.reflect(wi, sample_h(u))

    def pdf(wo):
        s = wi + wo
        norm = torch.linalg.vector_norm(s, dim=-1)
        h = s / norm.clamp_min(1e-30)[..., None]
        h = torch.where(h[..., 2:3] < 0, -h, h)
        return pdf_h(h) / (2.0 * norm).clamp_min(frame.EPS_COS)

    return Lobe(w, sample, pdf)


def normalization_closed_form(n: float) -> float:
    """I(n) = 2 pi int_0^{pi/2} cos^n(theta/2) cos(theta) sin(theta) d theta.

    With c = cos(theta/2): cos(theta) = 2c^2 - 1, sin(theta) d theta = -4c dc, and
    theta in [0, pi/2] <-> c in [1/sqrt2, 1], so
    I(n) = 8 pi int_{1/sqrt2}^1 (2 c^{n+3} - c^{n+1}) dc
         = 8 pi [ 2 (1 - 2^{-(n+4)/2}) / (n+4) - (1 - 2^{-(n+2)/2}) / (n+2) ].
    I(0) = pi (a Lambertian lobe); I(n) ~ 8 pi / n for large n.
    """
    return (
        8.0
        * math.pi
        * (
            2.0 * (1.0 - 2.0 ** (-(n + 4.0) / 2.0)) / (n + 4.0)
            - (1.0 - 2.0 ** (-(n + 2.0) / 2.0)) / (n + 2.0)
        )
    )


class BlinnPhong(BRDF):
    """Blinn-Phong normalised to unit specular albedo at normal incidence.

    Formula::

        f = kd / pi + ks (n . h)^n / I(n),   h = normalize(wi + wo),
        I(n) = 8 pi [2 (1 - 2^{-(n+4)/2}) / (n+4) - (1 - 2^{-(n+2)/2}) / (n+2)]

    I(n) is the directional albedo of the raw lobe (n.h)^n at wi = z, where n.h =
    cos(theta_o / 2) (derivation in :func:`normalization_closed_form`).

    * Reciprocal: yes (h is symmetric bit for bit).
    * Energy conserving: yes, with kd + ks <= 1.  Checked numerically (analytic.albedo,
      16384 points, 46 values of theta_i in [0, 89.9] deg, n in {0, 0.1, 0.5, 1, 2,
      5, 10, 20, 50, 100, 300, 1000}): the lobe's directional albedo is largest at
      normal incidence for every n > 0 (equal to 1 to 1e-4 there; for n = 0 the lobe
      is Lambertian and the albedo is 1 everywhere), and it falls off roughly like
      cos^2(theta_i) for large n (0.52 at 45 deg, 0.001 at 89.9 deg for n = 1000).
      So I(n) itself, not a separately computed maximum, is the normalisation.
    * Differs from the sources: they name Blinn-Phong only; the lobe is
      the classic (n.h)^n with the exact normal-incidence normalisation derived here
      (the common factor (n+8)/(8 pi) only approximates 1/I(n), which tends to
      (n+2)(n+4)/(8 pi n) for large n).

    Sampling: cosine (weight mean(kd)) + h from (n+1)/(2 pi) cos^n(theta_h) about z,
    reflected: pdf = p_h / (4 wi.h) (weight mean(ks)), see :func:`half_vector_lobe`.
    """

    name = "blinn_phong"
    reciprocal = True
    energy_conserving = True
    anisotropic = False
    notes = (
        "Normalised so the specular lobe's albedo is exactly 1 at normal incidence, "
        "closed-form I(n); measured to be the maximum over wi for n in [0, 1000]."
    )
    param_space = {
        "kd": ("rgb", 0.0, 0.5),
        "ks": ("rgb", 0.0, 0.5),
        "exponent": ("float", 0.0, 500.0),
    }

    def __init__(self, *, kd=0.5, ks=0.3, exponent=50.0):
        """kd: RGB diffuse albedo in [0, 1] (default 0.5).
        ks: RGB specular albedo at normal incidence in [0, 1] (default 0.3).
        exponent: Blinn-Phong exponent n >= 0 (default 50; about Phong 12).
        Requires kd + ks <= 1 in every channel."""
        kd, ks = rgb_pair("kd", kd, "ks", ks)
        n = scalar("exponent", exponent, lo=0.0)
        super().__init__(kd=kd, ks=ks, exponent=n)
        self._norm = normalization_closed_form(n)

    def _f(self, wi, wo):
        kd = self.const(self.params["kd"], wi)
        ks = self.const(self.params["ks"], wi)
        n = self.params["exponent"]
        h = frame.half_vector(wi, wo)
        spec = clamped_power(h[..., 2], n) / self._norm
        return kd / math.pi + ks * spec[..., None]

    def _lobes(self, wi):
        n = self.params["exponent"]
        wd = luminance(torch.tensor(self.params["kd"])).item()
        ws = luminance(torch.tensor(self.params["ks"])).item()
        if wd + ws <= 0.0:
            wd = 1.0

        def pdf_h(h):
            c = h[..., 2]
            return torch.where(c > 0, frame.power_cosine_pdf(c, n), torch.zeros_like(c))

        return [
            cosine_lobe(wi, wd),
            half_vector_lobe(wi, ws, lambda u: frame.square_to_power_cosine(u, n), pdf_h),
        ]
