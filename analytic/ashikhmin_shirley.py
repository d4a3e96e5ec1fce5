"""Ashikhmin-Shirley anisotropic Phong with Fresnel and coupled diffuse.

Ashikhmin & Shirley 2000, as Shirley & Marschner 2009, eq. 24.5, give it.
"""

from __future__ import annotations

import math

import torch

from . import frame
from .base import BRDF, Lobe, rgb, scalar
from .blinn_phong import half_vector_lobe
from .phong import clamped_power


class AshikhminShirley(BRDF):
    """Ashikhmin & Shirley 2000, "An Anisotropic Phong BRDF Model" (Shirley & Marschner 2009, 24.5).

    With h = normalize(wi + wo), k.h = wi.h = wo.h = |wi + wo| / 2 and the anisotropic
    exponent e(h) = n_u cos^2 phi_h + n_v sin^2 phi_h = (n_u h_x^2 + n_v h_y^2) / (1 - h_z^2)::

        f_s = sqrt((n_u+1)(n_v+1)) / (8 pi) h_z^e(h) / ((k.h) max(cos_i, cos_o)) F(k.h)   (24.5)
        F(c) = rs + (1 - rs) (1 - c)^5                                                  (24.6)
        f_d = 28 rd / (23 pi) (1 - rs) (1 - (1 - cos_i / 2)^5) (1 - (1 - cos_o / 2)^5)   (24.7)
        f = f_s + f_d                                                                   (24.8)

    * Reciprocal: yes (k.h, h and max(cos_i, cos_o) are symmetric; k.h is computed as
      |wi + wo| / 2 so that the swap is bit-identical).
    * Energy conserving: yes, for rd, rs in [0, 1] (measured; no proof).  Bound for the
      specular term: with dwo = 4 (k.h) dwh its albedo is
      int p_h(h) F(k.h) cos_o / max(cos_i, cos_o) dh <= max F <= 1 (p_h of eq. 24.10
      integrates to 1).  The diffuse albedo is exactly rd (1 - rs) (1 - (1 - cos_i/2)^5)
      (the 28/23 makes int (1 - (1 - cos/2)^5) cos dw = 23 pi / 28).  The total,
      rs S_1 + (1 - rs)(S_5 + rd D), is bilinear in (rd, rs), so its maximum over
      [0, 1]^2 is at a corner.  Measured max over theta_i in [0, 89.9] deg, phi_i,
      and n_u, n_v in {0, 1, 10, 100, 1000, 10000} (and anisotropic pairs), rd, rs in {0, 1}:
      0.9996 (rs = 1, n_u = n_v = 1e4, theta_i = 0; the specular bound is nearly
      reached); rd = 1, rs = 0 gives at most 0.969 (31/32 diffuse + small specular).
    * Differs from the source (Shirley & Marschner 2009): the textbook's typeset
      eq. 24.9 places the denominator
      (h.k_i) max(cos_i, cos_o) inside the exponent of (n.h); that is a typesetting
      error -- eq. 24.5 (implemented) has it as a factor of the BRDF.  The exponent's
      1 - h_z^2 is computed as h_x^2 + h_y^2 (no cancellation; at h = n, where phi_h
      is undefined, h_z^e = 1 for any e).  All formulas are the textbook's otherwise.

    Sampling: half-vector sampling, eqs. 24.10-24.14 (the four-quadrant mapping of xi_1
    is one atan2: phi = atan(sqrt((n_u+1)/(n_v+1)) tan(2 pi xi_1)) kept in the quadrant
    of 2 pi xi_1, which is the textbook's mapping with the flips made continuous),
    pdf = p_h / (4 k.h) (24.12), weight ~ F(cos_i); cosine for the diffuse term,
    weight rd (1 - rs)(1 - (1 - cos_i/2)^5), its exact albedo.
    """

    name = "ashikhmin_shirley"
    reciprocal = True
    energy_conserving = True
    anisotropic = True  # per instance: nu != nv
    notes = (
        "Eq. 24.5 implemented (the textbook's typeset 24.9 misplaces the denominator "
        "inside the exponent). Measured max total albedo 0.9996 (rs = 1, "
        "n_u = n_v = 1e4, normal incidence); rd = 1, rs = 0 gives at most 0.969 "
        "(31/32 diffuse + small specular). Energy conserving for rd, rs in [0, 1]."
    )
    param_space = {
        "rd": ("rgb", 0.0, 1.0),
        "rs": ("rgb", 0.0, 1.0),
        "nu": ("logfloat", 1.0, 1000.0),
        "nv": ("logfloat", 1.0, 1000.0),
    }

    def __init__(self, *, rd=0.5, rs=0.05, nu=200.0, nv=20.0):
        """rd: RGB diffuse reflectance of the substrate in [0, 1] (default 0.5).
        rs: RGB specular reflectance at normal incidence in [0, 1] (default 0.05,
        a plastic; use e.g. 0.9 for a metal with rd = 0).
        nu, nv: Phong exponents >= 0 along the tangent x and along y (defaults 200
        and 20: a brushed look, highlight stretched along y)."""
        rd = rgb("rd", rd)
        rs = rgb("rs", rs)
        nu = scalar("nu", nu, lo=0.0)
        nv = scalar("nv", nv, lo=0.0)
        super().__init__(rd=rd, rs=rs, nu=nu, nv=nv)
        self.anisotropic = nu != nv  # per instance: equal exponents do not see the azimuth

    # ------------------------------------------------------------------ pieces
    def _hexp(self, h: torch.Tensor) -> torch.Tensor:
        """e(h) = (n_u h_x^2 + n_v h_y^2) / (h_x^2 + h_y^2), between n_u and n_v.

        Within 1e-6 of the normal (h_x^2 + h_y^2 <= 1e-12) phi_h is undefined and
        h_z^e = 1 - O(e 1e-12) for any e, so e = (n_u + n_v) / 2 is used there; the
        divisor is replaced by 1 in that branch so that no gradient is 0/0.
        """
        nu, nv = self.params["nu"], self.params["nv"]
        hx2, hy2 = h[..., 0] ** 2, h[..., 1] ** 2
        s = hx2 + hy2
        ok = s > 1e-12
        ratio = (nu * hx2 + nv * hy2) / torch.where(ok, s, torch.ones_like(s))
        return torch.where(ok, ratio, torch.full_like(s, 0.5 * (nu + nv)))

    def _pdf_h(self, h: torch.Tensor) -> torch.Tensor:
        # Shirley & Marschner 2009, eq. 24.10:
        #   sqrt((nu+1)(nv+1)) / (2 pi) (n.h)^(nu cos^2 phi + nv sin^2 phi)
        nu, nv = self.params["nu"], self.params["nv"]
        c = math.sqrt((nu + 1.0) * (nv + 1.0)) / (2.0 * math.pi)
        return c * clamped_power(h[..., 2], self._hexp(h))

    def _sample_h(self, u: torch.Tensor) -> torch.Tensor:
        nu, nv = self.params["nu"], self.params["nv"]
        t = 2.0 * math.pi * u[..., 1]
        # Shirley & Marschner 2009, eq. 24.13 with the four-quadrant mapping of xi_1
        phi = torch.atan2(math.sqrt(nu + 1.0) * torch.sin(t), math.sqrt(nv + 1.0) * torch.cos(t))
        cp, sp = torch.cos(phi), torch.sin(phi)
        e = nu * cp * cp + nv * sp * sp
        # Shirley & Marschner 2009, eq. 24.14: cos theta = (1 - xi_2)^(1 / (e + 1))
        cos_t = (1.0 - u[..., 0]).clamp_min(0.0) ** (1.0 / (e + 1.0))
        sin_t = torch.sqrt((1.0 - cos_t * cos_t).clamp_min(0.0))
        return torch.stack([sin_t * cp, sin_t * sp, cos_t], -1)

    @staticmethod
    def _schlick(rs: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        # Shirley & Marschner 2009, eq. 24.6: F = Rs + (1 - Rs)(1 - k.h)^5
        return rs + (1.0 - rs) * (1.0 - c[..., None]).clamp_min(0.0) ** 5

    @staticmethod
    def _diffuse_shape(c: torch.Tensor) -> torch.Tensor:
        return 1.0 - (1.0 - 0.5 * c) ** 5

    # ------------------------------------------------------------------ model
    def _f(self, wi, wo):
        rd = self.const(self.params["rd"], wi)
        rs = self.const(self.params["rs"], wi)
        nu, nv = self.params["nu"], self.params["nv"]
        s = wi + wo
        norm = torch.linalg.vector_norm(s, dim=-1)
        h = s / norm.clamp_min(1e-30)[..., None]
        kh = (0.5 * norm).clamp_min(frame.EPS_COS)  # k.h = |wi + wo| / 2
        ci, co = wi[..., 2], wo[..., 2]
        cmax = torch.maximum(ci, co).clamp_min(frame.EPS_COS)
        # Shirley & Marschner 2009, eq. 24.5
        spec = (
            math.sqrt((nu + 1.0) * (nv + 1.0))
            / (8.0 * math.pi)
            * clamped_power(h[..., 2], self._hexp(h))
            / (kh * cmax)
        )
        fs = spec[..., None] * self._schlick(rs, kh)
        # Shirley & Marschner 2009, eq. 24.7
        fd = (
            (28.0 / (23.0 * math.pi))
            * rd
            * (1.0 - rs)
            * (self._diffuse_shape(ci) * self._diffuse_shape(co))[..., None]
        )
        return fs + fd  # Shirley & Marschner 2009, eq. 24.8

    def _lobes(self, wi) -> list[Lobe]:
        rd = self.const(self.params["rd"], wi)
        rs = self.const(self.params["rs"], wi)
        ci = wi[..., 2].clamp(0.0, 1.0)
        # weights: exact diffuse albedo; Fresnel at cos_i for the specular lobe (its
        # albedo is about F for narrow lobes), floored so the lobe is always sampled.
        wd = (rd * (1.0 - rs)).mean(-1) * self._diffuse_shape(ci)
        ws = self._schlick(rs, ci).mean(-1).clamp_min(0.05)
        return [
            Lobe(wd, frame.square_to_cosine_hemisphere, frame.cosine_hemisphere_pdf),
            half_vector_lobe(wi, ws, self._sample_h, self._pdf_h),
        ]
