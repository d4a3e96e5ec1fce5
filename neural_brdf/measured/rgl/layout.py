"""The RGL material's layout (Dupuy & Jakob 2018): its constants, the continuous
marginal 2D warp of its tables and the angle <-> square parametrisation."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

# ----------------------------------------------------------------- RGL content
Y_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB luminance
# D is floored at this fraction of its maximum: rho = f cos 4 sigma / D must stay finite
# where the retro-reflection vanishes (e.g. at grazing m).
NDF_FLOOR = 1e-4
# The luminance (sampling) table is floored at this fraction of its slice maximum, so
# that no region where rho > 0 has zero sampling density (an unbiased estimator).
LUMINANCE_FLOOR = 1e-4
POWER_ITERATIONS = 32  # fixed-point iterations of the NDF (converged to ~1e-6)
QUAD_U = 1024  # midpoints in u of the sigma quadrature
# Incident slices stop short of grazing: at theta_i = pi/2 every reflection is below the
# horizon and the slice would be all zero.  Beyond the last slice Mitsuba clamps.
THETA_I_MAX = math.radians(89.5)
SAMPLE_EPS = 1e-7  # warp inputs are kept in [eps, 1 - eps] (as Mitsuba)
SEGMENT_CONST = 1e-4  # a segment is treated as constant when |v0-v1| < this (v0+v1)
CHUNK = 1 << 16  # pairs per call of the baked function

DEFAULTS = {"theta_i": 32, "sample": 64, "vndf": 128, "ndf": 256}
# Wavelengths (nm) of a spectral bake: Mitsuba's visible range 360-830 in 20 nm steps (the
# sigmoid spectra are smooth; Mitsuba interpolates linearly and clamps beyond the ends).
WAVELENGTHS = np.arange(360.0, 831.0, 20.0)
SPECTRAL_SUFFIX = "_spec.bsdf"  # the RGL database's name for spectral files

REQUIRED = ("theta_i", "phi_i", "ndf", "sigma", "vndf", "luminance", "description", "jacobian")


# ------------------------------------------------- continuous marginal 2D warp
def _lerp(a, b, t):
    return a + (b - a) * t


def _first_false(pred: Callable, end: int, n: int) -> np.ndarray:
    """Per element, the smallest index i in [0, end] with pred(i) False, or end (a
    vectorised bisection; pred is monotone: True then False)."""
    lo, hi = np.zeros(n, np.int64), np.full(n, end, np.int64)
    for _ in range(int(math.log2(max(end, 1))) + 2):
        mid = (lo + hi) >> 1
        c = pred(mid)
        lo = np.where(c, np.minimum(mid + 1, hi), lo)
        hi = np.where(c, hi, mid)
    return lo


class Marginal2D:
    """A bilinear density on [0, 1]^2 tabulated at ``data[..., H, W]`` nodes, optionally
    conditioned on parameters (the leading axes, interpolated linearly at ``params``
    values), with the continuous marginal warp of Mitsuba's ``Marginal2D<..., true>``:
    ``sample`` maps the unit square to the density, ``invert`` is its inverse, ``eval``
    the (normalised, when ``normalize``) density.  float64 throughout."""

    def __init__(self, data, params=(), *, normalize: bool = True):
        d = np.array(data, dtype=np.float64)
        self.params = [np.asarray(p, dtype=np.float64).reshape(-1) for p in params]
        if d.ndim != 2 + len(self.params) or any(
            d.shape[k] != len(p) for k, p in enumerate(self.params)
        ):
            raise ValueError(
                f"data: shape {d.shape} does not match parameters "
                f"{[len(p) for p in self.params]} + (H, W)"
            )
        self.h, self.w = d.shape[-2:]
        if self.h < 2 or self.w < 2:
            raise ValueError(f"data: a 2D table needs at least 2 x 2 nodes, got {d.shape}")
        d = d.reshape(-1, self.h, self.w)
        sx, sy = 0.5 / (self.w - 1), 0.5 / (self.h - 1)  # trapezoids
        cond = np.cumsum(sx * (d[:, :, :-1] + d[:, :, 1:]), axis=2)  # (S, H, W-1)
        rows = cond[:, :, -1]
        marg = np.cumsum(sy * (rows[:, :-1] + rows[:, 1:]), axis=1)  # (S, H-1)
        self.normalized = normalize
        if normalize:
            total = marg[:, -1]
            if not np.all(total > 0):
                raise ValueError("data: a slice integrates to 0 (cannot be normalised)")
            norm = 1.0 / total
            d, cond, marg = (
                d * norm[:, None, None],
                cond * norm[:, None, None],
                marg * norm[:, None],
            )
        self.data = d.reshape(len(d), -1)
        self.cond = cond.reshape(len(d), -1)
        self.marg = marg

    # corner slices and weights of the parameter interpolation (C order over params)
    def _corners(self, params, n: int):
        corners = [(np.zeros(n, np.int64), np.ones(n))]
        for values, p in zip(self.params, params, strict=True):
            p = np.broadcast_to(np.asarray(p, dtype=np.float64), (n,))
            if len(values) == 1:
                corners = [(s * 1, w) for s, w in corners]
                continue
            i = np.clip(np.searchsorted(values, p, side="left") - 1, 0, len(values) - 2)
            t = np.clip((p - values[i]) / (values[i + 1] - values[i]), 0.0, 1.0)
            corners = [
                (s * len(values) + i + k, w * (t if k else 1.0 - t))
                for s, w in corners
                for k in (0, 1)
            ]
        return corners

    @staticmethod
    def _look(table, corners, idx):
        return sum(w * table[s, idx] for s, w in corners)

    def eval(self, pos, params=()) -> np.ndarray:
        """The density (or the raw interpolant, if not normalised) at ``pos`` (N, 2)."""
        pos = np.clip(np.asarray(pos, dtype=np.float64), 0.0, 1.0)
        c = self._corners(params, len(pos))
        x, y = pos[:, 0] * (self.w - 1), pos[:, 1] * (self.h - 1)
        ix = np.minimum(x.astype(np.int64), self.w - 2)
        iy = np.minimum(y.astype(np.int64), self.h - 2)
        fx, fy = x - ix, y - iy
        i = iy * self.w + ix
        lk = self._look
        return _lerp(
            _lerp(lk(self.data, c, i), lk(self.data, c, i + 1), fx),
            _lerp(lk(self.data, c, i + self.w), lk(self.data, c, i + self.w + 1), fx),
            fy,
        )

    @staticmethod
    def _segment_sample(s, inv_width, v0, v1):
        # invert the integral of a linear density over [0, t]: (v1-v0) t^2 + 2 v0 t = s
        s = s * (2.0 * inv_width)
        linear = np.abs(v0 - v1) > SEGMENT_CONST * (v0 + v1)
        num = np.where(linear, v0 - np.sqrt(np.maximum(v0 * v0 + s * (v1 - v0), 0.0)), s)
        den = np.where(linear, v0 - v1, v0 + v1)
        return np.divide(num, den, out=np.zeros_like(num), where=den != 0)

    def sample(self, u, params=()):
        """Unit square (N, 2) -> (points (N, 2), density (N,))."""
        u = np.clip(np.array(u, dtype=np.float64), SAMPLE_EPS, 1.0 - SAMPLE_EPS)
        n, w = len(u), self.w
        c = self._corners(params, n)
        lk = self._look
        ux, uy = u[:, 0], u[:, 1]
        if not self.normalized:
            uy = uy * lk(self.marg, c, np.full(n, self.h - 2))
        row = _first_false(lambda i: lk(self.marg, c, i) < uy, self.h - 2, n)
        uy = uy - np.where(row > 0, lk(self.marg, c, np.maximum(row - 1, 0)), 0.0)
        off = row * (w - 1)
        r0, r1 = lk(self.cond, c, off + w - 2), lk(self.cond, c, off + 2 * (w - 1) - 1)
        fy = self._segment_sample(uy, self.h - 1, r0, r1)
        ux = ux * _lerp(r0, r1, fy)

        def cdf(i):
            return _lerp(lk(self.cond, c, off + i), lk(self.cond, c, off + (w - 1) + i), fy)

        col = _first_false(lambda i: cdf(i) < ux, w - 2, n)
        ux = ux - np.where(col > 0, cdf(np.maximum(col - 1, 0)), 0.0)
        i = row * w + col
        c0 = _lerp(lk(self.data, c, i), lk(self.data, c, i + w), fy)
        c1 = _lerp(lk(self.data, c, i + 1), lk(self.data, c, i + w + 1), fy)
        fx = self._segment_sample(ux, w - 1, c0, c1)
        pts = np.stack([(col + fx) / (w - 1), (row + fy) / (self.h - 1)], -1)
        return pts, _lerp(c0, c1, fx)

    def invert(self, pts, params=()):
        """Points (N, 2) -> (unit square (N, 2), density (N,)): the inverse of sample."""
        pts = np.clip(np.asarray(pts, dtype=np.float64), 0.0, 1.0)
        n, w = len(pts), self.w
        c = self._corners(params, n)
        lk = self._look
        x, y = pts[:, 0] * (w - 1), pts[:, 1] * (self.h - 1)
        ix = np.minimum(x.astype(np.int64), w - 2)
        iy = np.minimum(y.astype(np.int64), self.h - 2)
        fx, fy = x - ix, y - iy
        i = iy * w + ix
        c0 = _lerp(lk(self.data, c, i), lk(self.data, c, i + w), fy)
        c1 = _lerp(lk(self.data, c, i + 1), lk(self.data, c, i + w + 1), fy)
        pdf = _lerp(c0, c1, fx)
        # the integral of the linear segment over [0, fx]
        sx = fx * _lerp(c0, c1, 0.5 * fx) / (w - 1)
        off = iy * (w - 1)

        def cdf(k):
            return _lerp(lk(self.cond, c, off + k), lk(self.cond, c, off + (w - 1) + k), fy)

        sx = sx + np.where(ix > 0, cdf(np.maximum(ix - 1, 0)), 0.0)
        r0, r1 = lk(self.cond, c, off + w - 2), lk(self.cond, c, off + 2 * (w - 1) - 1)
        row_total = _lerp(r0, r1, fy)
        sx = np.divide(sx, row_total, out=np.zeros_like(sx), where=row_total != 0)
        sy = fy * _lerp(r0, r1, 0.5 * fy) / (self.h - 1)
        sy = sy + np.where(iy > 0, lk(self.marg, c, np.maximum(iy - 1, 0)), 0.0)
        if not self.normalized:
            sy = sy / lk(self.marg, c, np.full(n, self.h - 2))
        return np.stack([sx, sy], -1), pdf


# --------------------------------------------------------------- angles <-> square
def theta_to_u(theta):
    return np.sqrt(np.maximum(theta, 0.0) * (2.0 / math.pi))


def u_to_theta(u):
    return np.square(u) * (math.pi / 2.0)


def phi_to_v(phi):
    return (phi + math.pi) / (2.0 * math.pi)


def v_to_phi(v):
    return (2.0 * v - 1.0) * math.pi


def elevation(d):
    """theta of unit vectors (..., 3), stable near the pole (2 asin(|d - z| / 2))."""
    dist = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + (d[..., 2] - 1.0) ** 2)
    return 2.0 * np.arcsin(np.clip(0.5 * dist, 0.0, 1.0))


def _spherical(theta, phi):
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], -1)
