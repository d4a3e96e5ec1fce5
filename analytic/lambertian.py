"""Lambertian diffuse reflection: f = albedo / pi.

Reciprocal (constant) and energy conserving (rho = albedo <= 1).  Sampled with the
cosine-weighted hemisphere, which is exact: f cos / pdf = albedo.
"""

from __future__ import annotations

import math

from .base import BRDF, rgb


class Lambertian(BRDF):
    name = "lambertian"
    reciprocal = True
    energy_conserving = True
    param_space = {"albedo": ("rgb", 0.0, 1.0)}

    def __init__(self, *, albedo=0.8):
        """albedo: RGB diffuse reflectance in [0, 1] (default 0.8 grey)."""
        super().__init__(albedo=rgb("albedo", albedo))

    def _f(self, wi, wo):
        a = self.const(self.params["albedo"], wi)
        # Lambert's law: f_r = rho / pi (Pharr et al. 2016, Yan 2020)
        return (a / math.pi).expand(wi.shape[:-1] + (3,))
