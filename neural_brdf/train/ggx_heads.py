"""Analytic GGX heads beside a textured model's shared neural lobes (``texture.analytic_heads:
ggx``; docs/model.md, "Analytic GGX heads").

A textured file's K neural lobes are shared by every texel, and the smoothest texels of
a principled teacher (GGX alpha near 0.06) need a lobe that grows like
1 / (cos theta_i cos theta_o) toward grazing: the shared lobes' bound and width cannot
follow it (docs/mitsuba.md, "Where the error that is left lives").  Two analytic heads,
whose roughness alpha(uv) is one more column of the field, are added to the K lobes:

    g_a(wi, wo; alpha) = D(h) G1(wi) G1(wo) / (4 cos theta_i cos theta_o)
                       = D(h) / ((c_i + S_i) (c_o + S_o))
    g_b(wi, wo; alpha) = g_a (1 - cos theta_d)^5

with h = (wi + wo) / |wi + wo|, c = cos theta, S_v = sqrt(alpha^2 (1 - c_v^2) + c_v^2),
GGX's D(h) = alpha^2 / (pi (cos^2 theta_h (alpha^2 - 1) + 1)^2) (Walter et al. 2007,
eq. 33), Smith's separable masking G1(v) = 2 c_v / (c_v + S_v) (Walter et al. 2007,
eq. 34, in the form of Heitz 2014, eq. 86; Mitsuba 3's ``MicrofacetDistribution::G`` is
the separable product), and cos theta_d = wi . h = |wi + wo| / 2 for unit directions.
``g_b`` is Schlick's grazing rise of the Fresnel term (Schlick 1994, F0 = 0): the field's
per-channel weights on ``g_a`` and ``g_b`` make F0 + (1 - F0)(1 - cos theta_d)^5.  Both
heads are grey: their colour is the field's.

Physics, in closed form for every alpha (so for any blend of texels):

* reciprocal bit for bit: wi + wo, |wi + wo|, (c_i + S_i)(c_o + S_o) and every other
  term are formed from sums and products whose operands swap, and float addition and
  multiplication commute;
* albedo <= 1: int g_a cos theta_o dwo = int D G1(wi) G1(wo) / (4 c_i) dwo
  <= int D(h) G1(wi) max(0, wi . h) / c_i dh = 1 (dwo = 4 (wi . h) dh, and the visible
  normals' density integrates to 1: Heitz 2014, eq. 38), and 0 <= (1 - cos theta_d)^5
  <= 1, so g_b's albedo is at most g_a's.  g_a's envelope (the ``texel`` bound's E) is 1
  at every node.  g_b's is measured (:func:`head_envelope`): its albedo is
  E_m[G1(wo) (1 - wi . m)^5] over wi's visible normals m, far below 1 except near
  grazing (about 0.005 at 45 degrees), so E_b at node j is the largest quadrature
  value over the node's cell of incidences and every alpha, plus a stated margin.  A
  texel's weights with sum_k z_k E_k <= 1 keep f's albedo <= 1 between texel centres as
  the neural lobes' tables do.

:class:`GGXLobes` wraps the shared network: (wi, wo, s) -> (N, 3 (K + 2)), the network's
K heads then the two analytic ones, so the textured model, its bound, the projection and
the export treat it as one network of K + 2 heads whose last latent input is alpha's
column t in [0, 1] (alpha = ALPHA_MIN + (1 - ALPHA_MIN) t).  The ONNX graph gains Sqrt,
Div, Mul and Add only; every back end lowers it as it lowers the network.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from neural_brdf.train.model import RawBRDF

HEADS = 2  # g_a and g_b
ALPHA_MIN = 0.01  # alpha = ALPHA_MIN + (1 - ALPHA_MIN) t, t in [0, 1] (a field column)
KINDS = ("none", "ggx")  # texture.analytic_heads


def alpha_of(t: torch.Tensor) -> torch.Tensor:
    """The field's column t in [0, 1] -> GGX alpha in [ALPHA_MIN, 1]."""
    return ALPHA_MIN + (1.0 - ALPHA_MIN) * t


def t_of(alpha: torch.Tensor) -> torch.Tensor:
    """GGX alpha in [ALPHA_MIN, 1] -> the field's column t (the inverse of :func:`alpha_of`)."""
    return (alpha - ALPHA_MIN) / (1.0 - ALPHA_MIN)


def ggx_heads(wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """(N, 3), (N, 3) unit directions, alpha (N, 1) -> (N, 2): g_a and g_b of the module
    doc, 0 where either direction is at or below the horizon."""
    ci, co = wi[:, 2:3], wo[:, 2:3]
    s = wi + wo
    ss = (s * s).sum(-1, keepdim=True)  # |wi + wo|^2
    a2 = alpha * alpha
    ok = (ci > 0) & (co > 0)
    safe = torch.where(ok, ss, torch.ones_like(ss))
    x = (s[:, 2:3] * s[:, 2:3] / safe).clamp(0.0, 1.0)  # cos^2 theta_h
    t = x * (a2 - 1.0) + 1.0
    d = a2 / (math.pi * t * t)  # GGX D(h), Walter et al. 2007 eq. 33
    pi_, po = ci.clamp_min(0.0), co.clamp_min(0.0)
    si = torch.sqrt(a2 * (1.0 - pi_ * pi_) + pi_ * pi_)  # S_i, S_o (module doc)
    so = torch.sqrt(a2 * (1.0 - po * po) + po * po)
    g_a = d / ((pi_ + si) * (po + so))
    one_minus = (1.0 - 0.5 * torch.sqrt(safe)).clamp_min(0.0)  # 1 - cos theta_d
    sq = one_minus * one_minus
    g_b = g_a * (sq * sq * one_minus)  # Schlick 1994: (1 - cos theta_d)^5
    out = torch.cat([g_a, g_b], -1)
    return torch.where(ok, out, torch.zeros_like(out))


class GGXLobes(nn.Module):
    """A shared lobe network ``net`` (a :class:`RawBRDF` of K heads, ``latent`` L) and the
    two analytic heads: (wi, wo, s) -> (N, 3 (K + 2)).  ``s`` (N, L + 1): the network's
    latent, then alpha's column t (module doc).  Looks like one network of K + 2 heads
    and latent L + 1 to the textured model (``heads``, ``latent``); ``searched_latent``
    (L) says which latent columns the projection may search (alpha's is kept)."""

    def __init__(self, net: RawBRDF):
        super().__init__()
        self.net = net
        self.heads = int(net.heads) + HEADS
        self.latent = int(net.latent) + 1
        self.searched_latent = int(net.latent)
        self.colors = int(getattr(net, "colors", 3))
        self.anisotropic = bool(getattr(net, "anisotropic", False))
        self.encoding = net.encoding

    def forward(
        self, wi: torch.Tensor, wo: torch.Tensor, s: torch.Tensor | None = None
    ) -> torch.Tensor:
        if s is None:
            raise ValueError(f"GGXLobes: {self.latent} latent inputs expected, got none")
        lat = self.searched_latent
        return self.joined(
            self.network_part(wi, wo, s[:, :lat]), self.head_part(wi, wo, s[:, lat:])
        )

    def network_part(self, wi: torch.Tensor, wo: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """The network's heads (N, 3K) at its latent ``s`` (N, L) (the searched columns)."""
        return self.net(wi, wo, s) if self.searched_latent else self.net(wi, wo)

    @staticmethod
    def head_part(wi: torch.Tensor, wo: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The analytic heads (N, 2) at alpha's column ``t`` (N, 1)."""
        return ggx_heads(wi, wo, alpha_of(t))

    @staticmethod
    def joined(g: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """:meth:`forward`'s columns from its two parts: each grey head's value three
        times, RGB columns like a grey neural head's."""
        return torch.cat([g, h[:, 0:1], h[:, 0:1], h[:, 0:1], h[:, 1:2], h[:, 1:2], h[:, 1:2]], -1)


def with_heads(lobe: nn.Module, kind: str) -> nn.Module:
    """``lobe`` (one shared RawBRDF) wrapped for ``texture.analytic_heads`` ``kind``."""
    if kind not in KINDS:
        raise ValueError(f"analytic_heads: one of {', '.join(KINDS)}, got {kind!r}")
    if kind == "none":
        return lobe
    if not isinstance(lobe, RawBRDF):
        raise TypeError(f"analytic_heads: a shared RawBRDF to wrap, got {type(lobe).__name__}")
    return GGXLobes(lobe)


# g_b's envelope (head_envelope): each node's cell of incidences sampled at
# ENVELOPE_SUBSTEPS points per node spacing, ENVELOPE_ALPHAS alphas (geometric, ALPHA_MIN
# to 1), ENVELOPE_STRATA^2 stratified visible normals; the largest value plus
# ENVELOPE_MARGIN (tests/train/test_ggx_heads.py samples g_b's albedo at random against it)
ENVELOPE_SUBSTEPS = 4
ENVELOPE_ALPHAS = 24
ENVELOPE_STRATA = 32
ENVELOPE_MARGIN = 0.01


@functools.lru_cache(maxsize=8)
def _schlick_head_envelope(size: int) -> tuple[float, ...]:
    """g_b's envelope at ``size`` isotropic nodes (theta_j = j / (size - 1) x 90 degrees,
    each node's cell its neighbours' span, as the A+ tables' neighbour maximum)."""
    from analytic.microfacet import Distribution

    fine = torch.linspace(
        0.0, 0.5 * math.pi, (size - 1) * ENVELOPE_SUBSTEPS + 1, dtype=torch.float64
    )
    cz = torch.cos(fine).clamp_min(1e-4)
    wi = torch.stack([torch.sqrt(1.0 - cz * cz), torch.zeros_like(cz), cz], -1)
    n = ENVELOPE_STRATA
    g = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    u = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)  # (M, 2)
    w = wi[:, None, :].expand(-1, len(u), 3).reshape(-1, 3)
    uu = u[None].expand(len(wi), -1, 2).reshape(-1, 2)
    best = torch.zeros(len(wi), dtype=torch.float64)
    for a in np.geomspace(ALPHA_MIN, 1.0, ENVELOPE_ALPHAS):
        dist = Distribution("ggx", float(a), float(a))
        m = dist.sample_visible(w, uu)
        c = (w * m).sum(-1)  # wi . m = cos theta_d
        wo = 2.0 * c[:, None] * m - w
        up = wo[:, 2] > 0
        val = torch.where(up, dist.G1(wo) * (1.0 - c).clamp_min(0.0) ** 5, 0.0)
        best = torch.maximum(best, val.reshape(len(wi), -1).mean(-1))
    step = ENVELOPE_SUBSTEPS
    out = []
    for j in range(size):
        lo, hi = max(0, (j - 1) * step), min(len(fine) - 1, (j + 1) * step)
        out.append(min(1.0, float(best[lo : hi + 1].max()) + ENVELOPE_MARGIN))
    return tuple(out)


def head_envelope(size: int, anisotropic: bool = False) -> torch.Tensor:
    """[J, 3 HEADS]: the analytic heads' columns of the ``texel`` bound's envelope at the
    nodes of a lobe table of ``size`` nodes (J = size, or size^2 for an anisotropic
    grid): g_a's 1, then g_b's measured envelope (module doc), each three times (RGB).
    An anisotropic grid's nodes get 1 for both (the measured one is per theta cell)."""
    if anisotropic:
        return torch.ones(size * size, 3 * HEADS)
    b = torch.tensor(_schlick_head_envelope(int(size)), dtype=torch.float32)[:, None]
    return torch.cat([torch.ones(size, 3), b.expand(size, 3)], -1)


def with_head_envelope(env: torch.Tensor, anisotropic: bool) -> torch.Tensor:
    """A neural lobe table's envelope [J, C] (``textured_model.lobe_envelope``) with the
    analytic heads' columns (:func:`head_envelope`) after it: [J, C + 3 HEADS]."""
    j = int(env.shape[0])
    size = math.isqrt(j) if anisotropic else j
    return torch.cat([env, head_envelope(size, anisotropic).to(env.dtype)], -1)


def analytic_count(lobe: nn.Module) -> int:
    """How many of a lobe module's heads are analytic (their envelope: :func:`head_envelope`)."""
    return HEADS if isinstance(lobe, GGXLobes) else 0


# alpha's start (alpha_from_teacher): f at normal incidence against wo tilted by 0 to
# 80 degrees, fitted by k_d + k_s g_a for each of ALPHA_GRID alphas (log-spaced)
ALPHA_TILTS_DEG = np.arange(0.0, 81.0, 2.0)
ALPHA_GRID = np.geomspace(ALPHA_MIN, 1.0, 60)


def alpha_from_teacher(teacher: Any, resolution: int) -> torch.Tensor:
    """A start for alpha's column of the field, as logits [R*R, 1]: at each texel centre
    (flat index j * R + i), the teacher's ``eval`` with wi at the normal and wo tilted by
    0 to 80 degrees (channel means) fitted, relative to f, by k_d + k_s g_a(alpha) with
    k_d, k_s >= 0 for each alpha of :data:`ALPHA_GRID`; the alpha of the least error.
    Any teacher works: it asks only ``eval``.  On the development principled's
    homogeneous texels it gave 0.065, 0.060, 0.166, 0.677 for alpha 0.0625, 0.0625, 0.16,
    0.64 (benchmarks/textured_ggx_heads.py)."""
    r = int(resolution)
    i = (np.arange(r * r) % r + 0.5) / r
    j = (np.arange(r * r) // r + 0.5) / r
    uv = np.stack([i, j], -1)
    t = np.radians(ALPHA_TILTS_DEG)
    m = len(t)
    wo = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], -1)
    wi = np.array([0.0, 0.0, 1.0])
    f = np.nan_to_num(
        np.asarray(
            teacher.eval(np.tile(wi, (r * r * m, 1)), np.tile(wo, (r * r, 1)), np.repeat(uv, m, 0)),
            np.float64,
        )
    ).mean(-1)
    f = f.reshape(r * r, m)
    w = 1.0 / np.maximum(f, 1e-9)  # relative error
    y = f * w  # ones
    best = np.full(r * r, np.inf)
    alpha = np.ones(r * r)
    wi_t = torch.tensor(wi)[None].expand(m, 3).double()
    for a in ALPHA_GRID:
        spec = ggx_heads(wi_t, torch.from_numpy(wo), torch.full((m, 1), float(a)).double())
        g = spec[:, 0].numpy()  # (M,)
        x1, x2 = w, g[None, :] * w  # the columns of k_d and k_s, (T, M)
        err = _nnls2(x1, x2, y)
        better = err < best
        best = np.where(better, err, best)
        alpha = np.where(better, a, alpha)
    t_col = t_of(torch.from_numpy(alpha)).clamp(1e-3, 1.0 - 1e-3)
    return torch.logit(t_col).float()[:, None]


def _nnls2(x1: np.ndarray, x2: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per row, the least ||a x1 + b x2 - y||^2 with a, b >= 0 (rows of (T, M))."""
    g11, g22, g12 = (x1 * x1).sum(-1), (x2 * x2).sum(-1), (x1 * x2).sum(-1)
    b1, b2, yy = (x1 * y).sum(-1), (x2 * y).sum(-1), (y * y).sum(-1)
    det = np.maximum(g11 * g22 - g12 * g12, 1e-300)
    a = (b1 * g22 - b2 * g12) / det
    b = (b2 * g11 - b1 * g12) / det
    both = yy - a * b1 - b * b2
    only1 = yy - np.maximum(b1, 0.0) ** 2 / np.maximum(g11, 1e-300)
    only2 = yy - np.maximum(b2, 0.0) ** 2 / np.maximum(g22, 1e-300)
    err = np.minimum(only1, only2)
    return np.where((a >= 0) & (b >= 0), np.minimum(both, err), err)
