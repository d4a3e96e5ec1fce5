"""An independent reference for the sampling lobe (neural_brdf.physics.lobe_fit), shared by
the tests of the generated code (test_codegen.py) and of the Mitsuba plugin
(test_mitsuba_plugin.py): the mixture's density from analytic's GGX and Beckmann
visible-normal pdfs and np.interp, not from the code under test, and the lobes those
tests write into files."""

from __future__ import annotations

import numpy as np
import torch

from analytic import frame
from analytic.microfacet import Distribution


def lobe_params(stored: dict, cos_i: np.ndarray):
    """Per-row (alpha_x, alpha_y, weight) of a stored lobe: its per-incidence table
    interpolated linearly in cos theta_i with np.interp (clamped), or its constants."""
    n = len(cos_i)
    t = stored.get("table")
    if t:
        return tuple(
            np.interp(cos_i, t["cos_theta"], t[k]) for k in ("alpha_x", "alpha_y", "weight")
        )
    ax = stored.get("alpha_x", stored["alpha"])
    ay = stored.get("alpha_y", stored["alpha"])
    return np.full(n, ax), np.full(n, ay), np.full(n, stored["weight"])


def mixture_pdf(wi: np.ndarray, wo: np.ndarray, lobe: dict) -> np.ndarray:
    """The lobe's density over the sphere (float64); a retro lobe is the mirror lobe
    turned by pi about the normal, so its density at wo is the mirror lobe's at the
    turned wo."""
    ax, ay, weight = lobe_params(lobe, wi[:, 2])
    dist = lobe.get("distribution", "ggx")
    wi, wo = torch.from_numpy(wi).double(), torch.from_numpy(wo).double()
    v = wo * torch.tensor([-1.0, -1.0, 1.0], dtype=wo.dtype) if lobe.get("retro") else wo
    h = frame.normalize(wi + v)
    visible = torch.cat(
        [  # one row at a time: analytic's Distribution takes scalar alphas
            Distribution(dist, a, b).pdf_visible(wi[k : k + 1], h[k : k + 1])
            for k, (a, b) in enumerate(zip(ax, ay))
        ]
    )
    weight = torch.from_numpy(np.asarray(weight, dtype=np.float64))
    p = (1.0 - weight) * frame.cosine_hemisphere_pdf(wo) + weight * visible / (
        4.0 * frame.dot(v, h)
    )
    return torch.where((wi[:, 2] > 0) & (wo[:, 2] > 0), p, 0.0).numpy()


# lobes unlike any fitted one, written into files: the code must follow the dict
# an anisotropic retro lobe (x is the tangent)
ANISO_RETRO = {"alpha": 0.2, "alpha_x": 0.1, "alpha_y": 0.4, "weight": 0.6, "retro": True}
# a per-incidence lobe: roughness (anisotropic) and share vary with cos theta_i
PER_INCIDENCE = {
    "alpha": 0.2,
    "weight": 0.5,
    "table": {
        "cos_theta": [0.1, 0.5, 0.9],
        "alpha_x": [0.5, 0.2, 0.05],
        "alpha_y": [0.3, 0.2, 0.1],
        "weight": [0.9, 0.5, 0.2],
    },
}
# both: a retro lobe whose roughness and share vary with cos theta_i
RETRO_TABLE = {**PER_INCIDENCE, "retro": True}
# a Beckmann lobe (visible normals), anisotropic and per incidence
BECKMANN = {**PER_INCIDENCE, "distribution": "beckmann"}
