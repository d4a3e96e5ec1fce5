"""The sampling lobe's schema, density and sampler: what the ``sampling_lobe`` metadata
entry holds, how a reader checks it, the pdf every importance sampler of it must have,
and a reference sampler in numpy.

The lobe is a mixture, cheap to sample, whose density is known exactly:

    pdf(wo) = (1 - w) cos(theta_o) / pi  [wo_z > 0]  +  w D_wi(m) / (4 |wo . m|),
    m = normalize(wi + R wo),   R = identity (a mirror lobe) or R (x, y, z) = (-x, -y, z)
    (a retro lobe),

a cosine-weighted hemisphere plus a GGX or Beckmann visible-normal lobe of roughness
(alpha_x, alpha_y) (x is the tangent) reflected about the sampled normal m; D_wi is the
distribution of visible normals (Heitz 2018, eq. 1; for Beckmann, Heitz & d'Eon 2014).
A per-incidence ``table`` gives (alpha_x, alpha_y, w) at nodes of cos theta_i,
interpolated linearly and clamped at its ends (:func:`at`).

The JSON form (docs/model.md, "Sampling lobe"):

    {"kind": "cosine+ggx_vndf", "alpha": 0.26, "alpha_x": 0.26, "alpha_y": 0.26,
     "retro": false, "distribution": "ggx", "weight": 0.9, "second_moment": 1.31,
     "second_moment_cosine": 3.9, "table": {...}}   (table optional)

Every alpha (alpha, alpha_x, alpha_y, the table's) is finite, > 0 (raised to MIN_ALPHA)
and at most MAX_ALPHA; anything else is a one-line InputError naming the key.

Who implements it: :mod:`neural_brdf.physics.lobe_fit` fits it; the Mitsuba plugin
(:mod:`neural_brdf.renderers.mitsuba`) samples it with Mitsuba's own
``MicrofacetDistribution``; the code generators (:mod:`neural_brdf.backends.lobe_ir`) emit
its pdf and sampler; each is tested against :func:`pdf`, and so is :func:`sample` here
(chi-square, tests/fileformat/test_lobe.py).  This module needs numpy only.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import numpy as np

from neural_brdf.errors import InputError
from neural_brdf.fileformat import LOBE_KEY as KEY  # the ONNX metadata key

KIND = "cosine+ggx_vndf"

# The GGX alpha is never below this: Mitsuba's float32 GGX sampling loses accuracy for
# much sharper lobes.  The cosine share is never below 1 - MAX_WEIGHT, which bounds the
# sample weight where the network has a diffuse tail that the GGX lobe misses; the fit
# takes a share that high only where its scored second moment says the lobe covers the
# BRDF (a polished metal: with a cap of 0.9 its noise was 10x that of the target's own
# sampler, 1.4x with 0.995).
MIN_ALPHA = 0.01
MAX_WEIGHT = 0.995
# The roughest lobe a file may hold: the fitter's grid (neural_brdf.physics.lobe_fit.ALPHAS)
# ends here, per-incidence tables included.  A larger alpha is refused (a one-line
# error naming the key) rather than evaluated: far above it the float32 pdf and sampler
# of every implementation overflow (alpha = 1e30 gave a NaN pdf at normal incidence),
# and making them finite for any finite alpha would rewrite each of them (the plugin's
# Mitsuba distribution included) for lobes no fit writes, all but the cosine lobe.
MAX_ALPHA = 1.0
# The microfacet distributions a lobe can sample: Mitsuba's MicrofacetType names.
DISTRIBUTIONS = ("ggx", "beckmann")


def at(lobe: dict, cos_theta_i) -> tuple:
    """(alpha_x, alpha_y, weight) of a lobe for incident cos(theta) (a float or an array):
    the per-incidence table interpolated linearly in cos theta (clamped at its ends), or
    the lobe's single values."""
    t = lobe.get("table")
    if not t:
        return lobe["alpha_x"], lobe["alpha_y"], lobe["weight"]
    c = np.asarray(cos_theta_i, dtype=np.float64)
    return tuple(np.interp(c, t["cos_theta"], t[k]) for k in ("alpha_x", "alpha_y", "weight"))


def half_parts(wi: np.ndarray, wo: np.ndarray) -> dict[str, np.ndarray]:
    """What the densities need of the half vector h = normalize(wi + wo), (N, 3) each:
    its squared x and y, its z, and the clamped cosines wi.h and wo.h, each (N,).  A
    caller scoring many roughnesses on the same directions computes them once
    (:mod:`neural_brdf.physics.lobe_fit`)."""
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    hx, hy, hz = h[:, 0], h[:, 1], h[:, 2]
    return {
        "hxx": hx * hx,
        "hyy": hy * hy,
        "hz": hz,
        "cos_ih": np.maximum(np.sum(wi * h, -1), 0.0),
        "cos_oh": np.maximum(np.sum(wo * h, -1), 1e-12),
    }


def ggx_pdf(
    wi: np.ndarray, wo: np.ndarray, ax: float | np.ndarray, ay: float | np.ndarray
) -> np.ndarray:
    """Density of wo = reflect(wi, m), m a GGX(ax, ay) visible normal seen from wi
    (Heitz 2018, eq. 1; GGX D and Smith G1 as in analytic.microfacet).  wi, wo: (N, 3);
    ax, ay: floats or (C, 1) arrays, giving (N,) or (C, N)."""
    return ggx_pdf_half(half_parts(wi, wo), wi, ax, ay)


def ggx_pdf_half(
    h: dict[str, np.ndarray], wi: np.ndarray, ax: float | np.ndarray, ay: float | np.ndarray
) -> np.ndarray:
    """:func:`ggx_pdf` from :func:`half_parts` of (wi, wo).  ``wi``: (N, 3), or (1, 3)
    where every row shares one incident direction (the same values, Smith's term once)."""
    t = h["hxx"] / (ax * ax) + h["hyy"] / (ay * ay) + h["hz"] * h["hz"]
    d = np.where(h["hz"] > 0, 1.0 / (math.pi * ax * ay * t * t), 0.0)
    wx, wy, wz = wi[:, 0], wi[:, 1], wi[:, 2]
    g1 = 2.0 * wz / (wz + np.sqrt(ax * ax * wx * wx + ay * ay * wy * wy + wz * wz))
    return g1 * h["cos_ih"] * d / (wz * 4.0 * h["cos_oh"])


def beckmann_pdf(
    wi: np.ndarray,
    wo: np.ndarray,
    ax: float | np.ndarray,
    ay: float | np.ndarray,
    *,
    erf: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """As :func:`ggx_pdf` for the Beckmann distribution: D (Walter et al. 2007, eq. 25,
    anisotropic slopes) and Smith Lambda(a) = (erf(a) - 1) / 2 + exp(-a^2) / (2 a
    sqrt(pi)), a = 1 / (alpha tan theta) (Walter et al. 2007, eq. 27).  ``erf``: a
    vectorised erf (default :func:`math.erf` per element)."""
    return beckmann_pdf_half(half_parts(wi, wo), wi, ax, ay, erf=erf)


def beckmann_pdf_half(
    h: dict[str, np.ndarray],
    wi: np.ndarray,
    ax: float | np.ndarray,
    ay: float | np.ndarray,
    *,
    erf: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """:func:`beckmann_pdf` from :func:`half_parts` of (wi, wo); ``wi`` as for
    :func:`ggx_pdf_half`."""
    hz = h["hz"]
    hz_safe = np.maximum(hz, 1e-6)
    e = (h["hxx"] / (ax * ax) + h["hyy"] / (ay * ay)) / (hz_safe * hz_safe)
    d = np.where(hz > 1e-6, np.exp(-e) / (math.pi * ax * ay * hz_safe**4), 0.0)
    wx, wy, wz = wi[:, 0], wi[:, 1], wi[:, 2]
    a = 1.0 / np.sqrt(np.maximum((ax * ax * wx * wx + ay * ay * wy * wy) / (wz * wz), 1e-30))
    erf_a = (erf or _erf)(a)
    lam = 0.5 * (erf_a - 1.0) + np.exp(-a * a) / (2.0 * a * math.sqrt(math.pi))
    return h["cos_ih"] * d / ((1.0 + lam) * wz * 4.0 * h["cos_oh"])


def _erf(a: np.ndarray) -> np.ndarray:
    out = np.frompyfunc(math.erf, 1, 1)(np.asarray(a, dtype=np.float64))
    return np.asarray(out, dtype=np.float64)


def turn(w: np.ndarray) -> np.ndarray:
    """R: a half turn about the normal, (x, y, z) -> (-x, -y, z) (a retro lobe's)."""
    return w * np.array([-1.0, -1.0, 1.0])


def pdf(lobe: dict, wi: np.ndarray, wo: np.ndarray, *, sphere: bool = False) -> np.ndarray:
    """The density (1/sr) with which the lobe samples ``wo`` given ``wi`` (:func:`sample`):
    (N, 3) unit vectors -> (N,) float64.  ``lobe`` as :func:`complete` returns it.  It
    is 0 where wi or wo is below the horizon, as in the Mitsuba plugin and the generated
    code (a visible normal may reflect wi below the horizon: such a sample is refused, so
    the density integrates to 1 minus that mass over the hemisphere).  ``sphere=True``
    keeps the lobe's density below the horizon too: the sampler's density over the whole
    sphere, which integrates to 1."""
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    up = wi[:, 2] > 0
    keep = up if sphere else up & (wo[:, 2] > 0)
    ax, ay, w = (np.asarray(v, dtype=np.float64) for v in at(lobe, wi[:, 2]))
    p_cos = np.clip(wo[:, 2], 0.0, None) / math.pi
    m = turn(wo) if lobe.get("retro") else wo
    dist = beckmann_pdf if lobe.get("distribution", "ggx") == "beckmann" else ggx_pdf
    with np.errstate(divide="ignore", invalid="ignore"):
        p_lobe = dist(np.where(up[:, None], wi, [0.0, 0.0, 1.0]), m, ax, ay)
    out = (1.0 - w) * p_cos + w * np.nan_to_num(p_lobe, nan=0.0, posinf=0.0)
    return np.where(keep, out, 0.0)


def sample(
    lobe: dict, wi: np.ndarray, u1: np.ndarray, u2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Draw wo from the lobe: (N, 3) wi above the horizon, u1 (N,) and u2 (N, 2) uniform in
    [0, 1) -> (wo (N, 3), pdf(wo) (N,)).  The lobe branch when u1 < w: a visible normal m
    from u2 (GGX: Heitz 2018, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4),
    listing 1; Beckmann: Heitz & d'Eon 2014, its slopes inverted by bisection), wo the
    reflection of wi about m, turned for a retro lobe; the cosine branch otherwise
    (r = sqrt(u2.x), phi = 2 pi u2.y).  The same algorithm as the generated code's sampler
    (:mod:`neural_brdf.backends.lobe_ir`), in float64.  A lobe sample may fall below the
    horizon; its pdf is then 0 (a renderer refuses it)."""
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
    u1 = np.asarray(u1, dtype=np.float64).reshape(-1)
    u2 = np.asarray(u2, dtype=np.float64).reshape(-1, 2)
    n = len(wi)
    r, phi = np.sqrt(u2[:, 0]), 2.0 * math.pi * u2[:, 1]
    wo = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.clip(1.0 - u2[:, 0], 0, None))], -1)
    ax, ay, w = (np.broadcast_to(np.asarray(v, np.float64), (n,)) for v in at(lobe, wi[:, 2]))
    pick = u1 < w
    if pick.any():
        vndf = _beckmann_vndf if lobe.get("distribution") == "beckmann" else _ggx_vndf
        m = vndf(wi[pick], u2[pick], ax[pick], ay[pick])
        v = 2.0 * np.sum(wi[pick] * m, -1, keepdims=True) * m - wi[pick]
        wo[pick] = turn(v) if lobe.get("retro") else v
    return wo, pdf(lobe, wi, wo)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _ggx_vndf(wi: np.ndarray, u: np.ndarray, ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
    """A visible normal of GGX(ax, ay) seen from wi (Heitz 2018, JCGT 7(4), listing 1)."""
    vh = _normalize(np.stack([ax * wi[:, 0], ay * wi[:, 1], wi[:, 2]], -1))
    lensq = vh[:, 0] ** 2 + vh[:, 1] ** 2
    inv = 1.0 / np.sqrt(np.maximum(lensq, 1e-300))
    has_xy = lensq > 0
    t1 = np.stack([np.where(has_xy, -vh[:, 1] * inv, 1.0), np.where(has_xy, vh[:, 0] * inv, 0.0)])
    t2 = np.stack([-vh[:, 2] * t1[1], vh[:, 2] * t1[0], vh[:, 0] * t1[1] - vh[:, 1] * t1[0]])
    r, phi = np.sqrt(u[:, 0]), 2.0 * math.pi * u[:, 1]
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + vh[:, 2])
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    pz = np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    nh = np.stack(
        [
            p1 * t1[0] + p2 * t2[0] + pz * vh[:, 0],
            p1 * t1[1] + p2 * t2[1] + pz * vh[:, 1],
            p2 * t2[2] + pz * vh[:, 2],
        ],
        -1,
    )
    return _normalize(np.stack([ax * nh[:, 0], ay * nh[:, 1], np.maximum(nh[:, 2], 0.0)], -1))


def _bisect(fn: Callable[[np.ndarray], np.ndarray], target, lo, hi, steps: int = 60):
    """x in [lo, hi] with fn(x) = target for an increasing fn (float64 bisection)."""
    lo, hi = np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)
    lo, hi = np.broadcast_arrays(lo, hi)
    lo, hi = lo.copy(), hi.copy()
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        below = fn(mid) < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def _beckmann_vndf(wi: np.ndarray, u: np.ndarray, ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
    """A visible normal of Beckmann(ax, ay) seen from wi (Heitz & d'Eon 2014): wi stretched
    to unit roughness at polar angle t has visible slopes of density (cos t - x sin t)
    exp(-x^2 - y^2) / pi on x < cot t, so y ~ N(0, 1/2) and x has the CDF
    C(x) = cos t (1 + erf x) / 2 + sin t exp(-x^2) / (2 sqrt(pi)); both are inverted by
    bisection on [-6, 6], then turned to wi's azimuth and unstretched."""
    ws = _normalize(np.stack([ax * wi[:, 0], ay * wi[:, 1], wi[:, 2]], -1))
    ct = ws[:, 2]
    st = np.sqrt(np.maximum(1.0 - ct * ct, 0.0))
    hi = np.minimum(ct / np.maximum(st, 1e-300), 6.0)

    def cdf(x: np.ndarray) -> np.ndarray:
        return ct * 0.5 * (1.0 + _erf(x)) + st * np.exp(-x * x) * (0.5 / math.sqrt(math.pi))

    x = _bisect(cdf, u[:, 0] * cdf(hi), -6.0, hi)
    y = _bisect(_erf, 2.0 * u[:, 1] - 1.0, np.full(len(u), -6.0), 6.0)
    r2 = ws[:, 0] ** 2 + ws[:, 1] ** 2
    inv = 1.0 / np.sqrt(np.maximum(r2, 1e-300))
    cp = np.where(r2 > 0, ws[:, 0] * inv, 1.0)
    sp = np.where(r2 > 0, ws[:, 1] * inv, 0.0)
    sx, sy = cp * x - sp * y, sp * x + cp * y
    return _normalize(np.stack([-(ax * sx), -(ay * sy), np.ones_like(sx)], -1))


def to_json(lobe: dict) -> str:
    return json.dumps(lobe, sort_keys=True)


def parse(text: str) -> dict:
    """The metadata value -> the lobe dict; a one-line InputError if it is malformed."""
    try:
        lobe = json.loads(text)
        kind, alpha, weight = lobe["kind"], float(lobe["alpha"]), float(lobe["weight"])
        ax, ay = float(lobe.get("alpha_x", alpha)), float(lobe.get("alpha_y", alpha))
        retro = lobe.get("retro", False)
    except (ValueError, KeyError, TypeError, AttributeError, OverflowError):
        raise InputError(
            f'metadata {KEY!r}: expected JSON {{"kind": "{KIND}", '
            f'"alpha": a, "weight": w}}, got {text!r}'
        ) from None
    if kind != KIND:
        raise InputError(f"metadata {KEY!r}: unknown lobe kind {kind!r} (known: {KIND!r})")
    finite = all(math.isfinite(v) for v in (alpha, ax, ay))
    if not (finite and alpha > 0 and ax > 0 and ay > 0 and 0.0 <= weight <= 1.0):
        raise InputError(
            f"metadata {KEY!r}: alpha, alpha_x and alpha_y must be finite and > 0 and weight "
            f"in [0, 1], "
            f"got {text!r}"
        )
    for key, value in (("alpha", alpha), ("alpha_x", ax), ("alpha_y", ay)):
        _check_max_alpha(key, value)
    if not isinstance(retro, bool):
        raise InputError(f"metadata {KEY!r}: retro must be true or false, got {text!r}")
    dist = lobe.get("distribution", "ggx")
    if dist not in DISTRIBUTIONS:
        raise InputError(
            f"metadata {KEY!r}: unknown distribution {dist!r} (known: {', '.join(DISTRIBUTIONS)})"
        )
    out = {
        **lobe,
        "alpha": max(alpha, MIN_ALPHA),
        "alpha_x": max(ax, MIN_ALPHA),
        "alpha_y": max(ay, MIN_ALPHA),
        "retro": retro,
        "distribution": dist,
        "weight": weight,
    }
    if lobe.get("table") is not None:
        out["table"] = _parse_table(lobe["table"], text)
    return out


def _check_max_alpha(key: str, value: float) -> None:
    if value > MAX_ALPHA:
        raise InputError(
            f"metadata {KEY!r}: {key} must be at most {MAX_ALPHA:g} (the roughest lobe the "
            f"fit writes), got {value!r}"
        )


def _parse_table(table, text: str) -> dict:
    """The per-incidence table: equal-length lists (>= 2 nodes) of finite numbers,
    cos_theta strictly ascending in [0, 1], alphas > 0 (raised to MIN_ALPHA) and at most
    MAX_ALPHA, weights in [0, 1]."""
    keys = ("cos_theta", "alpha_x", "alpha_y", "weight")
    try:
        if not all(isinstance(table[k], list) for k in keys) or any(
            isinstance(v, bool) for k in keys for v in table[k]
        ):
            raise TypeError
        cols = {k: [float(v) for v in table[k]] for k in keys}
    except (KeyError, TypeError, ValueError, OverflowError):
        raise InputError(
            f"metadata {KEY!r}: table must hold lists {', '.join(keys)}, got {text!r}"
        ) from None
    c = cols["cos_theta"]
    if (
        len({len(v) for v in cols.values()}) != 1
        or len(c) < 2
        or not all(math.isfinite(v) for col in cols.values() for v in col)
        or not all(0.0 <= a < b <= 1.0 for a, b in zip(c, c[1:]))
        or not all(a > 0 for k in ("alpha_x", "alpha_y") for a in cols[k])
        or not all(0.0 <= w <= 1.0 for w in cols["weight"])
    ):
        raise InputError(
            f"metadata {KEY!r}: table needs >= 2 nodes of equal length, cos_theta ascending "
            f"in [0, 1], alphas > 0 and weights in [0, 1], got {text!r}"
        )
    for k in ("alpha_x", "alpha_y"):
        for a in cols[k]:
            _check_max_alpha(f"table {k}", a)
        cols[k] = [max(a, MIN_ALPHA) for a in cols[k]]
    return cols


def complete(lobe: dict) -> dict:
    """A lobe dict, possibly partial ({"alpha": a, "weight": w}), checked and with every
    key: kind, alpha, alpha_x, alpha_y, retro, distribution, weight (and its table, if it
    has one)."""
    return parse(to_json({"kind": KIND, **lobe}))


# What sets a lobe's density and sampler (:func:`pdf`, :func:`sample`, the plugins'): the
# rest of its dict (the second moments) describes the fit that chose it.
DENSITY_KEYS = ("kind", "alpha_x", "alpha_y", "retro", "distribution", "weight", "table")


def same_density(a: dict, b: dict) -> bool:
    """Whether two lobes (complete or partial) sample with one density: a refit that lands
    on the same lobe of its grid (:mod:`neural_brdf.physics.lobe_fit`) draws the same
    directions from the same random numbers."""
    ca, cb = complete(a), complete(b)
    return all(ca.get(k) == cb.get(k) for k in DENSITY_KEYS)


def from_metadata(meta: dict) -> dict | None:
    """The stored lobe of a model's metadata (a dict of strings), or None (older files)."""
    text = meta.get(KEY)
    return None if text is None else parse(text)
