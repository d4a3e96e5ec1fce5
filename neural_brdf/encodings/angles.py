"""The angles every encoding is built from, in torch: reciprocal by construction.

Everything is built from two vectors (convention of :mod:`analytic.frame`):

    s = wi + wo      swapping wi and wo leaves s unchanged, bit for bit (IEEE + commutes);
    d = wi - wo      swapping negates d exactly (a - b == -(b - a) in IEEE arithmetic).

A feature that is a function of ``s`` and of *products of two components of d* (or of
``wi_z * wo_z``, whose product commutes) is therefore bit-exactly symmetric, in torch
and in the exported ONNX graph alike.  No symmetrisation pass and no angle with a
branch cut (atan2) is needed.  With |wi| = |wo| = 1 (Rusinkiewicz 1998):

    cos theta_d = |s| / 2,  h = s / |s|,  cos theta_h = s_z / |s|,
    tan(theta_h / 2) = |s_xy| / (|s| + s_z),  tan(theta_d / 2) = |d| / (2 + |s|),
    cos_i + cos_o = s_z,  (cos_i - cos_o)^2 = d_z^2,  cos_i cos_o = wi_z wo_z.

The encodings themselves: :mod:`.isotropic`, :mod:`.anisotropic`, :mod:`.raw`.  The
albedo table's coordinates (:func:`neural_brdf.train.model.table_coords`) and the peak
sampler of the training data use the helpers here too.
"""

from __future__ import annotations

import math

import torch

# |s| = 2 cos theta_d is >= 2 sin(min elevation) > 0 for two directions above the horizon;
# the clamp only protects masked-out pairs (below the horizon) from 0/0.
EPS_NORM = 1e-12

HALF_PI = 0.5 * math.pi

# The peak coordinate u_h = log(1 + t^2 / PEAK_EPS) / log(1 + 1 / PEAK_EPS), t = tan(theta_h/2).
# Why not sqrt(theta_h / (pi/2)), used before: its slope is infinite at theta_h = 0, so a
# network (piecewise linear in its inputs with ReLU) or a grid (linear within a cell) made
# a V-shaped cusp at the exact mirror direction, and pairs near u = 0 were so rare (their
# density in u vanishes like u^3) that the grid's first node was barely trained: compact
# gold read 0.13x its target at the mirror direction, 1.0x at 0.3 degrees off it.  u_h is
# a smooth function of t^2, which is itself smooth and even in the offset from the mirror
# direction, so every model built on it has a flat, not a notched, peak.  It is linear in
# t^2 up to t^2 ~ PEAK_EPS (theta_h ~ 1.1 degrees) and logarithmic beyond, where it spreads
# lobes from alpha ~ 0.02 to 1 evenly over [0, 1]; the density of lobe-sampled pairs
# near u_h = 0 stays finite.  u_h(0) = 0, u_h(90 degrees) = 1.
PEAK_EPS = 1e-4
PEAK_LOG_SCALE = 1.0 / math.log1p(1.0 / PEAK_EPS)


def columns(cols: list[torch.Tensor]) -> torch.Tensor:
    """``torch.stack(cols, -1)``: (...,) columns -> (..., k), the same values.  In torch
    (not an ONNX export) the k columns are laid out one after another, the result a
    column-major view: copying each column whole is about 9 times faster on the CPU than
    interleaving them (8 columns of 35k floats: 0.05 against 0.47 ms), and a matrix
    product reads either layout.  The exported graph is traced from the plain stack."""
    if torch.onnx.is_in_onnx_export():
        return torch.stack(cols, -1)
    return torch.stack(cols, 0).movedim(0, -1)


def cat_columns(parts: list[torch.Tensor]) -> torch.Tensor:
    """``torch.cat(parts, -1)`` of (..., k_i) tensors, laid out as :func:`columns` lays
    out its result (a part already column-major is copied whole)."""
    if torch.onnx.is_in_onnx_export():
        return torch.cat(parts, -1)
    return torch.cat([p.movedim(-1, 0) for p in parts], 0).movedim(0, -1)


def peak_coordinate(tan_half: torch.Tensor) -> torch.Tensor:
    """u_h from t = tan(theta_h / 2) (see PEAK_EPS): smooth in t^2, in [0, 1]."""
    return torch.log(1.0 + (tan_half * tan_half) * (1.0 / PEAK_EPS)) * PEAK_LOG_SCALE


def half_angle(sin_part: torch.Tensor, one_plus_cos: torch.Tensor) -> torch.Tensor:
    """theta = 2 atan(sin / (1 + cos)) (both scaled alike), for theta in [0, pi).

    Unlike acos(cos), this is well conditioned near theta = 0, where acos turns a
    1-ulp difference of cos into a ~30% difference of theta (float32, theta ~ 1e-3);
    that broke torch/onnxruntime parity at 2e-5.  ONNX has Atan but no Atan2.
    """
    return 2.0 * torch.atan(sin_part / one_plus_cos.clamp_min(EPS_NORM))
