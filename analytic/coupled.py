"""The coupled smooth-layered model (Shirley et al. 1997; Shirley & Marschner 2009, 24.4)."""

from __future__ import annotations

import math

import torch

from . import frame
from .base import BRDF, _common, _out, cosine_lobe, rgb, scalar


class Coupled(BRDF):
    """Coupled matte/specular model: a smooth dielectric coat over a matte substrate.

    Formula (with x_i = 1 - cos theta_i, x_o = 1 - cos theta_o)::

        f      = 21 / (20 pi) (1 - R0) Rm [1 - x_i^5] [1 - x_o^5]            (diffuse, eval)
        R_f(i) = R0 + (1 - R0) x_i^5                         (Dirac mirror lobe, not in eval)

    ``eval``/``pdf``/``sample`` cover only the diffuse part.  The ideal specular lobe
    is exposed separately: :meth:`delta_reflectance` gives R_f(theta_i) (RGB) and
    :meth:`delta_direction` the mirror direction.

    * Reciprocal: yes (separable, symmetric).  The Dirac lobe R_f(theta_i)
      delta(wo - mirror(wi)) / cos is reciprocal too, since theta_o = theta_i on it.
    * Energy conserving: yes.  int (1 - (1 - mu)^5) mu dmu = 1/2 - 1/42 = 10/21, so the
      diffuse albedo is exactly (1 - R0) Rm (1 - x_i^5) and the total is
      R_f + diffuse = R0 + (1 - R0) [x_i^5 + Rm (1 - x_i^5)] <= 1, with equality for Rm = 1.
    * Differs from the source: Shirley & Marschner 2009, eq. 24.3 as printed multiplies
      k = 21 / (20 pi (1 - R0)) (eq. 24.2) by [1 - x_i^5][1 - x_o^5] alone, dropping the
      (1 - R0)^2 of f(theta) f(theta') = [1 - R_f(theta)][1 - R_f(theta')] from the line
      above it, from which k was derived.  As printed, the normal-incidence total is
      R0 + Rm / (1 - R0) > 1 for Rm = 1 (1.1026 for R0 = 0.05).  Restoring the factor
      gives the prefactor 21 / (20 pi) (1 - R0) used here.
    """

    name = "coupled"
    reciprocal = True
    energy_conserving = True
    anisotropic = False
    notes = (
        "Diffuse prefactor 21/(20 pi) (1 - R0): Shirley & Marschner 2009 eq. 24.3 drops "
        "the (1 - R0)^2 "
        "of f(theta) f(theta') and, as printed, is not energy conserving "
        "(R0 + Rm/(1 - R0) at normal incidence). The Dirac specular lobe is not part "
        "of eval: see delta_reflectance / delta_direction."
    )
    param_space = {
        "rm": ("rgb", 0.0, 1.0),
        "r0": ("float", 0.0, 0.95),
    }

    def __init__(self, *, rm=0.5, r0=0.05):
        """rm: RGB matte (substrate) reflectance Rm in [0, 1] (default 0.5).
        r0: normal-incidence Fresnel reflectance of the coat, in [0, 1) (default 0.05;
        ((n - 1) / (n + 1))^2 is 0.02 for water, 0.04-0.06 for polish and glass)."""
        rm = rgb("rm", rm)
        r0 = scalar("r0", r0, lo=0.0, hi=1.0, hi_open=True)
        super().__init__(rm=rm, r0=r0)

    @staticmethod
    def _x5(c: torch.Tensor) -> torch.Tensor:
        return (1.0 - c.clamp(0.0, 1.0)) ** 5

    def _f(self, wi, wo):
        rm = self.const(self.params["rm"], wi)
        r0 = self.params["r0"]
        # Shirley & Marschner 2009, eq. 24.3, with the (1 - R0)^2 factor of f(theta) f(theta')
        # restored
        k = 21.0 / (20.0 * math.pi) * (1.0 - r0)
        shape = (1.0 - self._x5(wi[..., 2])) * (1.0 - self._x5(wo[..., 2]))
        return k * rm * shape[..., None]

    def _lobes(self, wi):
        return [cosine_lobe(wi, 1.0)]  # Shirley & Marschner 2009, fig. 24.5: cos(theta) / pi

    # ------------------------------------------------------------------ Dirac lobe
    def _delta_reflectance_t(self, wi: torch.Tensor) -> torch.Tensor:
        r0 = self.params["r0"]
        # Shirley & Marschner 2009, eq. 24.3 (Schlick, section 24.3): R_f = R0 + (1 - R0)(1 - cos)^5
        rf = r0 + (1.0 - r0) * self._x5(wi[..., 2])
        rf = torch.where(wi[..., 2] > 0, rf, torch.zeros_like(rf))
        return rf[..., None].expand(wi.shape[:-1] + (3,)).clone()

    def delta_reflectance(self, wi):
        """R_f(theta_i) of the Dirac mirror lobe, RGB (..., 3); 0 below the horizon."""
        is_np, (wi_t,) = _common(wi, names=("wi",), widths=(3,))
        return _out(self._delta_reflectance_t(wi_t), is_np)

    def delta_direction(self, wi):
        """The mirror direction of wi about the normal (where the Dirac lobe sends light)."""
        is_np, (wi_t,) = _common(wi, names=("wi",), widths=(3,))
        return _out(frame.reflect_z(wi_t), is_np)
