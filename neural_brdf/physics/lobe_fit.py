"""Fitting the sampling lobe of a neural BRDF: done at export, stored in the ONNX file.

A renderer cannot invert a network, so it importance-samples a mixture that is cheap to
sample and whose density is known exactly: a cosine-weighted hemisphere plus a GGX or
Beckmann visible-normal lobe, mirror or retro, isotropic or not, possibly with a
roughness and share per incident direction.  The mixture, its JSON form in the file and
its pdf are the file format's: :mod:`neural_brdf.fileformat.lobe`.  This module chooses
the mixture for a given BRDF.

:func:`fit` minimises the relative second moment of the sample weight f cos / pdf
(1 + the relative variance of a one-sample albedo estimate), averaged over incident
directions.  Every candidate is scored on one pooled set of samples (a defensive mixture
of the cosine lobe and isotropic mirror and retro lobes of every alpha of the grid), so
the network is evaluated once per sample, not once per candidate:

1. isotropic GGX and Beckmann, mirror and retro lobes over the alpha grid, every share w;
2. if turning the best lobe anisotropic (alpha_x != alpha_y) lowers the score by more
   than ``ANISO_GAIN``, a coordinate search over (alpha_x, alpha_y) on the same grid;
3. if giving each incident direction its own roughness (same aspect) and share lowers
   the score by more than ``PER_INCIDENCE_GAIN``, a per-incidence ``table`` of
   (alpha_x, alpha_y, w) over cos theta_i at the fit's directions, interpolated linearly
   and clamped at the ends (:func:`neural_brdf.fileformat.lobe.at`).

It takes about a second.  :mod:`neural_brdf.export` stores the result in the metadata
key ``sampling_lobe``; ``second_moment`` and ``second_moment_cosine`` (the fitted lobe's
and cosine sampling's alone) say how much the lobe helps.  This module needs numpy, torch
and onnxruntime only: no renderer.
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import numpy as np
import torch

from analytic import frame
from analytic.microfacet import Distribution
from neural_brdf.fileformat import INPUTS, OUTPUT, SIGNATURES

# The lobe's schema, its density and its metadata key belong to the file format
# (neural_brdf.fileformat.lobe); the fit uses these of them.
from neural_brdf.fileformat.lobe import (
    DISTRIBUTIONS,
    KIND,
    MAX_WEIGHT,
    MIN_ALPHA,
    beckmann_pdf_half,
    ggx_pdf_half,
    half_parts,
    turn,
)

# The grid, and the incident directions it is scored at: theta from near-normal to
# near-grazing (degrees), each at its own azimuth so anisotropic models are probed
# off-axis too.
ALPHAS = np.geomspace(MIN_ALPHA, 1.0, 25)
WEIGHTS = np.r_[np.arange(10) / 10.0, 0.95, 0.98, 0.99, MAX_WEIGHT]  # 0, 0.1, ..., 0.9, ...
THETA_DEG = (5.0, 20.0, 35.0, 50.0, 65.0, 80.0)
SAMPLES = 512  # per proposal of the pool (cosine, mirror and retro per alpha) per direction
# An anisotropic lobe is kept only if it lowers the second moment by this share: an
# isotropic model keeps alpha_x == alpha_y whatever the sampling noise.
ANISO_GAIN = 0.03
ANISO_ROUNDS = 3  # coordinate-search rounds (alpha_x, then alpha_y)
# A per-incidence table (roughness and share per incident direction) is kept only if it
# lowers the mean second moment by this share.
PER_INCIDENCE_GAIN = 0.05


def fit(
    fn,
    *,
    seed: int = 0,
    anisotropic: bool = True,
    retro: bool = True,
    per_incidence: bool = True,
    distributions: tuple[str, ...] = DISTRIBUTIONS,
) -> dict:
    """Fit the lobe to ``fn(wi, wo) -> f`` (numpy float32 (N, 3) in, (N, 3) out, 1/sr).

    ``anisotropic`` / ``retro`` / ``per_incidence`` False restrict the search to
    alpha_x == alpha_y / mirror lobes / one lobe for every incident direction, and
    ``distributions`` to some of :data:`DISTRIBUTIONS`.  Returns the metadata dict (see
    the module docstring), with JSON-ready floats."""
    allow_retro = retro
    rng = np.random.default_rng(seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # these small ops ran 5x slower on 2 threads than on 1
    try:
        pools = [_Pool(fn, _incident(t, 0.9 * k), rng) for k, t in enumerate(THETA_DEG)]
        scores: dict[tuple, np.ndarray] = {}

        def per_pool(ia: int, ib: int, retro: bool, dist: str) -> np.ndarray:  # (pools, W)
            key = (ia, ib, retro, dist)
            if key not in scores:
                scores[key] = np.stack([p.second_moments(ia, ib, retro, dist) for p in pools])
            return scores[key]

        def best(keys) -> tuple[float, tuple, int]:
            return min(
                (float(per_pool(*k).mean(0).min()), k, int(np.argmin(per_pool(*k).mean(0))))
                for k in keys
            )

        n = len(ALPHAS)
        shapes = (False, True) if allow_retro else (False,)
        m2, (ia, ib, retro, dist), j = best(
            [(i, i, r, d) for d in distributions for r in shapes for i in range(n)]
        )
        cosine = float(per_pool(0, 0, False, "ggx").mean(0)[0])  # w = 0: the cosine lobe
        if j > 0 and anisotropic:  # a GGX lobe is used: try it anisotropic
            step = [
                (ia + d, ib - d, retro, dist)
                for d in (-2, 2)
                if 0 <= ia + d < n and 0 <= ib - d < n
            ]
            if step and best(step)[0] < (1.0 - ANISO_GAIN) * m2:
                for _ in range(ANISO_ROUNDS):
                    last = (ia, ib)
                    m2, (ia, ib, retro, dist), j = best([(i, ib, retro, dist) for i in range(n)])
                    m2, (ia, ib, retro, dist), j = best([(ia, i, retro, dist) for i in range(n)])
                    if (ia, ib) == last:
                        break
        if j == 0:  # the cosine lobe alone: no GGX or Beckmann part to describe
            ia, ib, retro, dist = 0, 0, False, "ggx"
        table = None
        if per_incidence and j > 0:
            # each incident direction's own roughness (same aspect) and share
            line = [
                (ia + t, ib + t, retro, dist)
                for t in range(-n, n)
                if 0 <= ia + t < n and 0 <= ib + t < n
            ]
            stack = np.stack([per_pool(*k) for k in line])  # (line, pools, WEIGHTS)
            flat = stack.transpose(1, 0, 2).reshape(len(pools), -1)
            pick = np.argmin(flat, axis=1)
            m2_table = float(flat[np.arange(len(pools)), pick].mean())
            if m2_table < (1.0 - PER_INCIDENCE_GAIN) * m2:
                rows = [(line[c // len(WEIGHTS)], c % len(WEIGHTS)) for c in pick]
                # where the cosine lobe alone is best (share 0) every roughness ties: keep
                # the single lobe's, so interpolation towards a glossy node stays smooth
                rows = [(k if j_k > 0 else (ia, ib, retro, dist), j_k) for k, j_k in rows]
                order = np.argsort(np.cos(np.radians(THETA_DEG)))  # cos theta ascending
                table = {
                    "cos_theta": [float(np.cos(np.radians(THETA_DEG[k]))) for k in order],
                    "alpha_x": [float(ALPHAS[rows[k][0][0]]) for k in order],
                    "alpha_y": [float(ALPHAS[rows[k][0][1]]) for k in order],
                    "weight": [float(WEIGHTS[rows[k][1]]) for k in order],
                }
                m2 = m2_table
    finally:
        torch.set_num_threads(threads)
    ax, ay = float(ALPHAS[ia]), float(ALPHAS[ib])
    out = {
        "kind": KIND,
        "alpha": math.sqrt(ax * ay) if ia != ib else ax,
        "alpha_x": ax,
        "alpha_y": ay,
        "retro": bool(retro),
        "distribution": dist,
        "weight": float(WEIGHTS[j]),
        "second_moment": m2,
        "second_moment_cosine": cosine,
    }
    if table is not None:
        out["table"] = table
    return out


def _incident(theta_deg: float, phi: float) -> torch.Tensor:
    t = math.radians(theta_deg)
    return torch.tensor(
        [math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t)], dtype=torch.float64
    )


def _turn(w: torch.Tensor) -> torch.Tensor:
    """R: a half turn about the normal, (x, y, z) -> (-x, -y, z) (numpy: ``turn``)."""
    return w * torch.tensor([-1.0, -1.0, 1.0], dtype=w.dtype)


def _torch_erf(a: np.ndarray) -> np.ndarray:
    """erf through torch: the values the fit has always scored with (math.erf differs from
    it in the last bit for a few per cent of arguments, which would change the stored
    second moments)."""
    return torch.special.erf(torch.from_numpy(np.ascontiguousarray(a))).numpy()


class _Pool:
    """Samples at one incident direction, pooled over the cosine lobe and the isotropic
    mirror and retro GGX lobes of every alpha of the grid (the defensive mixture q), with
    what every candidate lobe's second moment needs: (f cos)^2 / q and p_cos."""

    def __init__(self, fn, wi1: torch.Tensor, rng):
        n, k = SAMPLES, len(ALPHAS)
        u = torch.from_numpy(rng.random((2 * k + 1, n, 2)))
        wi_t = wi1.expand(n, 3)
        wos = [frame.square_to_cosine_hemisphere(u[0])]
        for r, uu in enumerate(u[1:]):
            d = Distribution("ggx", float(ALPHAS[r % k]), float(ALPHAS[r % k]))
            wo_t = frame.reflect(wi_t, d.sample_visible(wi_t, uu))
            wos.append(_turn(wo_t) if r >= k else wo_t)
        wo = torch.cat(wos, 0).numpy()  # (P n, 3)
        wi = np.broadcast_to(wi1.numpy(), wo.shape)
        p_cos = np.where(wo[:, 2] > 0, np.clip(wo[:, 2], 0.0, None) / math.pi, 0.0)
        a = ALPHAS[:, None]
        # the half vectors' parts of both lobe shapes, once (wi is one direction: its row)
        half = {r: half_parts(wi, turn(wo) if r else wo) for r in (False, True)}
        p_iso = {r: ggx_pdf_half(h, wi[:1], a, a) for r, h in half.items()}  # (A, N)
        # The pooled samples' density over the whole sphere: a visible normal may reflect
        # wi below the horizon; such samples count, with f cos = 0.
        q = (p_cos + p_iso[False].sum(0) + p_iso[True].sum(0)) / (2 * k + 1)
        f = np.asarray(fn(wi.astype(np.float32), wo.astype(np.float32)))
        fc = f.astype(np.float64).mean(-1) * np.clip(wo[:, 2], 0.0, None)
        live = (fc > 0) & (q > 0)
        albedo = np.sum(fc[live] / q[live]) / len(wo)
        self.black = not albedo > 0  # black at this angle: no preference
        self.wi, self.wo = wi[live], wo[live]
        self.p_iso = {r: p[:, live].astype(np.float32) for r, p in p_iso.items()}
        # (f cos)^2 / q per sample, then / p for every candidate; float32 suffices to rank
        self.c = (fc[live] ** 2 / q[live]).astype(np.float32)
        self.p_cos = p_cos[live].astype(np.float32)
        self.norm = len(wo) * albedo * albedo
        # _density's parts that no alpha changes, at the live samples
        self._half = {r: {name: v[live] for name, v in h.items()} for r, h in half.items()}
        # the cosine lobe's part of every share's mixture, (1 - w) p_cos, the same for every
        # candidate, and the buffer second_moments works in
        self._cos_part = [(1 - w) * self.p_cos for w in WEIGHTS.astype(np.float32)]
        self._buf = np.empty_like(self.p_cos)

    def _density(self, ax: float, ay: float, retro: bool, dist: str) -> np.ndarray:
        """The file format's density of the lobe (ax, ay, retro, dist) at the pool's
        samples, from the half vectors' parts computed once per lobe shape
        (:func:`neural_brdf.fileformat.lobe.half_parts`) and the Smith term once: every
        sample of a pool shares its wi.  The same values as ``ggx_pdf`` /
        ``beckmann_pdf`` on every sample, bit for bit (tests/physics/test_sampling_lobe.py);
        with the shares summed in place (:meth:`second_moments`) the fit takes 0.55 of
        its former time (benchmarks/lobe_refit.py)."""
        h, w1 = self._half[retro], self.wi[:1]  # the pool's one incident direction
        if dist == "ggx":
            return ggx_pdf_half(h, w1, ax, ay)
        return beckmann_pdf_half(h, w1, ax, ay, erf=_torch_erf)

    def second_moments(self, ia: int, ib: int, retro: bool, dist: str = "ggx") -> np.ndarray:
        """E_p[(f cos / p)^2] / A^2 for the lobe (ALPHAS[ia], ALPHAS[ib], retro, dist)
        and every share w of WEIGHTS (A = the albedo, RGB mean)."""
        if self.black:
            return np.zeros(len(WEIGHTS))
        if ia == ib and dist == "ggx":
            p = self.p_iso[retro][ia]
        else:
            p = self._density(float(ALPHAS[ia]), float(ALPHAS[ib]), retro, dist)
            p = p.astype(np.float32)
        m2, buf = np.empty(len(WEIGHTS)), self._buf
        with np.errstate(divide="ignore"):
            for j, w in enumerate(WEIGHTS.astype(np.float32)):
                # sum of c / ((1 - w) p_cos + w p), in place (the same values, bit for bit)
                np.multiply(w, p, out=buf)
                np.add(self._cos_part[j], buf, out=buf)
                np.divide(self.c, buf, out=buf)
                m2[j] = np.add.reduce(buf, dtype=np.float64)
        return m2 / self.norm


_FITTED: dict[tuple[str, int], dict] = {}  # fit_onnx's results by (SHA-256 of the file, seed)
_FITTED_MAX = 16


def fit_onnx(model, *, seed: int = 0) -> dict:
    """:func:`fit` on an ONNX model (a path or the bytes of one), through onnxruntime.
    A textured graph (inputs wi, wo, uv) gets one lobe for the whole surface, fitted to
    f at uniformly drawn texture coordinates in [0, 1)^2.

    The fit is deterministic, so its result is kept for the same bytes and seed: a
    report that draws an analytic target in the viewer and renders it in Mitsuba fits
    its lobe once (about a second each)."""
    import hashlib

    import onnxruntime as ort

    data = Path(model).read_bytes() if isinstance(model, (str, os.PathLike)) else bytes(model)
    key = (hashlib.sha256(data).hexdigest(), seed)
    if key in _FITTED:
        return copy.deepcopy(_FITTED[key])
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    session = ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])
    if [i.name for i in session.get_inputs()] == list(SIGNATURES[1]):
        # A textured graph: one lobe for the whole surface, fitted to f at texture
        # coordinates drawn uniformly over [0, 1)^2, one per pair (seeded: deterministic).
        uv_rng = np.random.default_rng(seed + 1)

        def fn(wi, wo):
            uv = uv_rng.random((len(wi), 2), dtype=np.float32)
            return session.run([OUTPUT], dict(zip(SIGNATURES[1], (wi, wo, uv))))[0]

    else:

        def fn(wi, wo):
            return session.run([OUTPUT], dict(zip(INPUTS, (wi, wo))))[0]

    lobe = fit(fn, seed=seed)
    if len(_FITTED) >= _FITTED_MAX:
        _FITTED.pop(next(iter(_FITTED)))
    _FITTED[key] = copy.deepcopy(lobe)
    return lobe
