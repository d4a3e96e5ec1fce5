"""What the images determine: the part of the (wi, wo) domain the views observe.

    python -m neural_brdf.inverse.coverage runs/images/fit.yaml [-o coverage.png]

Computed from the cameras, the shapes and the emitters alone, before any fit (the BSDF
to fit plays no part: a ``diffuse`` stands in for ``<bsdf id="fit">``).  For every view,
``rays`` camera rays (:data:`RAYS`) are spread evenly over the film's pixels, ``spp`` per
pixel (at least :data:`MIN_SPP`), jittered in the pixel (``sensor.sample_ray``) and
traced (``scene.ray_intersect``); where one hits a shape that uses the fit BSDF, one
emitter sample is drawn (``scene.sample_emitter_direction`` with the visibility
test: environment maps, area and point lights alike), giving in the hit's shading frame

    wo = si.to_local(-ray.d)     towards the camera
    wi = si.to_local(ds.d)       towards the light
    w  = luminance(L / pdf) * cos(theta_i)     (0 when occluded or below the surface)

so that the pixel's value is (1/spp) sum f(wi, wo) w over its samples.  Each pixel
counts once: a sample's **share** is its w over the sum of w of its pixel's samples
(the part of the pixel that f at that pair makes, were f constant), so a pixel's shares
add up to 1 whatever the light's brightness, as the fit's relative loss weighs pixels.

**The domain and its bins.**  The pairs are binned isotropically by the half and
difference angles (theta_h, theta_d) of Rusinkiewicz (1998), the two angles of the
project's encodings (:mod:`neural_brdf.encodings.isotropic`), in ``bins`` x ``bins``
bins over [0, pi/2]^2.  The domain D is the set of pairs with both cosines above
``min_cos`` (0.1: grazing pairs are left out, as images barely resolve them); each bin's
measure ``m_b`` is the share of D's (wi, wo) solid-angle measure in it (dwi dwo =
4 cos theta_d dw_h dw_d, the azimuths integrated: :func:`bin_measure`).

**The figure.**  View v's relative density in bin b is

    rho_v(b) = (W_v(b) / T_v) / m_b,

W_v(b) the shares of its pairs in D that fall in b, T_v its lit pixels (the sum of all
its shares): rho = 1 everywhere when a view spreads its weight over D as D's own measure
does.  The views' densities add, rho(b) = sum_v rho_v(b), and a bin is **observed** when
rho(b) >= ``threshold`` (:data:`THRESHOLD`, 0.05: a twentieth of a uniform spread).  The
coverage figure is the measure of the observed bins, sum of m_b over them: the share of
D (both cosines > 0.1, by solid-angle measure) that the images observe.  It does not
depend on the lights' brightness nor on the films' resolution (beyond the Monte Carlo
noise of the estimate), and a view added never lowers it (its rho_v >= 0 adds).

**Bins mixed per pixel** (:func:`mixing`) complements it: 1 / the chance that two of a
pixel's samples, weighted by their shares, fall in the same bin, pooled over the pixels.
About 1 to 3 under a point light (each pixel pins one pair, up to its footprint), tens
under an environment, where a pixel is an integral of f against the lighting and the
observed pairs are constrained only through such integrals.

``phi_h`` (the half vector's azimuth in the shading frame, which an anisotropic material
depends on) is summarised as the shares of the pairs in D by azimuth sector.  The pairs
themselves are kept too: a random subsample (``max_pairs``) of the samples with w > 0,
with their shares, their view and whether their bin is observed, so that a benchmark can
score a BRDF over the observed part of the domain (:func:`observed_mask` tells it for
any pairs).

One-call API for a fit (:func:`assess`)::

    info, message = coverage.assess(views, picture=run_dir / "coverage.png")

``info`` (:func:`summary`) goes into metrics.json, ``message`` (:func:`warning`, None
when coverage is at least :data:`WARN_BELOW`) is printed.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from neural_brdf.errors import InputError, module_parser
from neural_brdf.inverse import views as inverse_views

BINS = 32  # theta_h and theta_d bins over [0, pi/2] each
MIN_COS = 0.1  # the domain: both cosines above this
THRESHOLD = 0.05  # a bin is observed at rho >= THRESHOLD (1: a uniform spread)
WARN_BELOW = 0.25  # warning(): coverage below this
RAYS = 1 << 18  # camera rays per view (one emitter sample each), whole per pixel
MIN_SPP = 4  # ... and at least this many per pixel
PHI_BINS = 8  # azimuth sectors of phi_h over [0, 2 pi)
MAX_PAIRS = 20_000  # observed (wi, wo) pairs kept
CHUNK = 1 << 18  # samples traced at once
MEASURE_SUB = 16  # quadrature points per bin and axis of bin_measure
DEFAULT_VARIANT = "llvm_ad_rgb"


# ------------------------------------------------------------------ geometry
def half_diff(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta_h, theta_d, phi_h) of local directions (N, 3) (unit, upper hemisphere):
    the half vector's polar angle and azimuth, and the angle between wi and it."""
    wi = np.asarray(wi, np.float64)
    wo = np.asarray(wo, np.float64)
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-300)
    theta_h = np.arctan2(np.hypot(h[:, 0], h[:, 1]), h[:, 2])
    theta_d = np.arctan2(np.linalg.norm(np.cross(wi, h), axis=-1), np.sum(wi * h, -1))
    phi_h = np.mod(np.arctan2(h[:, 1], h[:, 0]), 2.0 * math.pi)
    return theta_h, theta_d, phi_h


def bin_index(theta: np.ndarray, bins: int) -> np.ndarray:
    """The bin of angles in [0, pi/2] (``bins`` equal bins; pi/2 in the last)."""
    return np.clip((theta / (0.5 * math.pi) * bins).astype(np.int64), 0, bins - 1)


def bin_measure(bins: int = BINS, min_cos: float = MIN_COS) -> np.ndarray:
    """(bins, bins) [theta_h, theta_d]: each bin's share of the measure dwi dwo of the
    pairs with both cosines > ``min_cos`` (sums to 1).

    With dwi dwo = 4 cos theta_d sin theta_h sin theta_d dtheta_h dphi_h dtheta_d dphi_d
    and cos theta_i, o = cos theta_h cos theta_d -+ sin theta_h sin theta_d cos phi_d,
    both cosines exceed c for the share (2/pi) asin(r) of phi_d, r = (cos theta_h
    cos theta_d - c) / (sin theta_h sin theta_d) clipped to [0, 1]; the rest is a
    midpoint rule of MEASURE_SUB^2 points per bin."""
    n = bins * MEASURE_SUB
    t = (np.arange(n) + 0.5) / n * (0.5 * math.pi)
    th, td = np.meshgrid(t, t, indexing="ij")
    num = np.cos(th) * np.cos(td) - min_cos
    den = np.sin(th) * np.sin(td)
    r = np.where(den > 0, num / np.maximum(den, 1e-300), np.where(num > 0, 1.0, 0.0))
    share = (2.0 / math.pi) * np.arcsin(np.clip(r, 0.0, 1.0))
    dens = 4.0 * np.cos(td) * np.sin(th) * np.sin(td) * share
    m = dens.reshape(bins, MEASURE_SUB, bins, MEASURE_SUB).sum(axis=(1, 3))
    return m / m.sum()


# ------------------------------------------------------------------ sampling a view
@dataclass
class Samples:
    """A view's samples that hit the fit BSDF (world vectors for checks)."""

    wi: np.ndarray  # (N, 3) towards the light, local shading frame
    wo: np.ndarray  # (N, 3) towards the camera, local shading frame
    weight: np.ndarray  # (N,) luminance(L / pdf) cos theta_i; 0: occluded, below
    pixel: np.ndarray  # (N,) the film pixel, y * width + x
    position: np.ndarray  # (N, 3) the hit point, world
    normal: np.ndarray  # (N, 3) the shading normal, world
    light: np.ndarray  # (N, 3) the direction to the light, world
    height: int
    width: int

    def shares(self) -> np.ndarray:
        """Each sample's share of its pixel (module doc); 0 for a pixel without light."""
        total = np.bincount(self.pixel, weights=self.weight, minlength=self.height * self.width)
        t = total[self.pixel]
        return np.where(t > 0, self.weight / np.where(t > 0, t, 1.0), 0.0)


def _np3(v) -> np.ndarray:
    return np.stack([np.asarray(v[j].numpy(), np.float64) for j in range(3)], -1)


def view_samples(
    scene,
    *,
    spp: int = MIN_SPP,
    seed: int = 0,
    jitter: bool = True,
    pixels: np.ndarray | None = None,
) -> Samples:
    """Trace ``spp`` camera rays per pixel of the first sensor's film (``jitter``: at
    random positions in the pixel, else at its centre) and draw one emitter sample
    where each ray hits a shape with ``<bsdf id="fit">``.  ``pixels``: only these
    (y * width + x), else every pixel.  Needs the scene loaded in the current variant
    (:func:`load`)."""
    import mitsuba as mi

    fit = inverse_views.fit_bsdf(scene)
    h, w = inverse_views.film_size(scene)
    sensor = scene.sensors()[0]
    rng = np.random.default_rng(seed)
    chosen = np.arange(h * w) if pixels is None else np.asarray(pixels, np.int64)
    n = len(chosen) * spp
    parts: list[tuple[np.ndarray, ...]] = []
    for start in range(0, n if fit is not None else 0, CHUNK):
        idx = chosen[np.arange(start, min(n, start + CHUNK)) // spp]
        m = len(idx)
        off = rng.random((m, 2)) if jitter else np.full((m, 2), 0.5)
        u = rng.random((m, 4))
        px = ((idx % w) + off[:, 0]) / w
        py = ((idx // w) + off[:, 1]) / h
        ray, _ = sensor.sample_ray(
            mi.Float(np.zeros(m, np.float32)),
            mi.Float(u[:, 0].astype(np.float32)),
            mi.Point2f(px.astype(np.float32), py.astype(np.float32)),
            mi.Point2f(u[:, 1].astype(np.float32), u[:, 2].astype(np.float32)),
        )
        si = scene.ray_intersect(ray)
        active = si.is_valid() & (si.bsdf() == mi.BSDFPtr(fit))
        v = rng.random((m, 2)).astype(np.float32)
        ds, spec = scene.sample_emitter_direction(si, mi.Point2f(v[:, 0], v[:, 1]), True, active)
        keep = np.asarray(active.numpy(), bool)
        if not keep.any():
            continue
        wo = _np3(si.to_local(-ray.d))[keep]
        wi = _np3(si.to_local(ds.d))[keep]
        lum = np.asarray(mi.luminance(spec).numpy(), np.float64)[keep]
        lum = np.where(np.isfinite(lum) & (lum > 0), lum, 0.0)
        weight = np.where((wi[:, 2] > 0) & (wo[:, 2] > 0), lum * wi[:, 2], 0.0)
        parts.append(
            (
                wi,
                wo,
                weight,
                idx[keep],
                _np3(si.p)[keep],
                _np3(si.sh_frame.n)[keep],
                _np3(ds.d)[keep],
            )
        )
    if not parts:
        z3, z1 = np.zeros((0, 3)), np.zeros(0)
        return Samples(z3, z3, z1, np.zeros(0, np.int64), z3, z3, z3, h, w)
    wi, wo, weight, pixel, position, normal, light = (np.concatenate(c) for c in zip(*parts))
    return Samples(wi, wo, weight, pixel, position, normal, light, h, w)


# ------------------------------------------------------------------ the coverage
@dataclass
class ViewCoverage:
    """One view's part of :class:`Coverage`."""

    scene: str
    pixels: int  # the film's pixels
    pixels_lit: int  # pixels with a lit hit on the fit BSDF (T_v: their shares add to 1)
    spp: int  # camera rays per pixel
    samples: int  # samples on the fit BSDF
    weight: np.ndarray  # (bins, bins) shares of its pairs in the domain, by bin
    density: np.ndarray  # (bins, bins) rho_v (module doc)
    figure: float  # the coverage of this view alone
    phi_h: np.ndarray  # (PHI_BINS,) shares of its pairs in the domain by phi_h sector
    mixing: tuple[float, float]  # (A, B) of the pooled collision estimate (see mixing())


@dataclass
class Coverage:
    """What :func:`compute` found (module doc for the definitions)."""

    views: list[ViewCoverage]
    bins: int
    min_cos: float
    threshold: float
    rays: int
    seed: int
    measure: np.ndarray  # (bins, bins) [theta_h, theta_d]: m_b, sums to 1
    density: np.ndarray  # (bins, bins) rho = sum over views of rho_v
    observed: np.ndarray  # (bins, bins) bool: rho >= threshold, in the domain
    figure: float  # sum of m_b over the observed bins
    wi: np.ndarray  # (P, 3) float32: a subsample of the pairs with w > 0, local frame
    wo: np.ndarray  # (P, 3) float32
    pair_share: np.ndarray  # (P,) float32: their shares of their pixels
    pair_view: np.ndarray  # (P,) int: their view (index into views)
    pair_observed: np.ndarray  # (P,) bool: in the domain and in an observed bin
    pairs_total: int  # the pairs with w > 0, before subsampling


def _scene_of(item, k: int) -> tuple[str, Any, Any]:
    """(name, scene path, parsed tree) of a View (inverse.fit.View) or a scene path."""
    if hasattr(item, "tree") and hasattr(item, "scene_path"):
        return str(item.scene_path), Path(item.scene_path), item.tree
    path = Path(item)
    tree, _ = inverse_views.read_scene(path, f"coverage: view {k + 1}")
    return str(path), path, tree


def load(path: Path, tree) -> Any:
    """The scene of ``path`` (parsed as ``tree``) with a ``diffuse`` as ``<bsdf id="fit">``
    (everything else as it is; its integrator is not used here)."""
    text = inverse_views.scene_text(tree, inverse_views.bsdf_element("diffuse"))
    return inverse_views.load_scene(path, text)


def percent_text(share: float) -> str:
    """``share`` in percent to one decimal, but a share below 1 never as "100.0" (the
    environment's 99.95 % read as full coverage): two decimals there, rounded down."""
    text = f"{100 * share:.1f}"
    if share < 1 and text == "100.0":
        text = f"{math.floor(share * 1e4) / 100:.2f}"
    return text


def _use_variant(variant: str | None) -> None:
    import mitsuba as mi

    current = mi.variant()
    if variant is None:
        if current is None:
            mi.set_variant(DEFAULT_VARIANT)
        return
    if not variant.startswith(("llvm_", "cuda_")) or "_rgb" not in variant:
        raise InputError(
            f"coverage: variant {variant}: needs a vectorised RGB variant (llvm_ad_rgb, "
            "cuda_ad_rgb, ...), as a fit does"
        )
    if current != variant:
        try:
            mi.set_variant(variant)
        except Exception as e:  # a missing LLVM or CUDA: Mitsuba raises several types
            raise InputError(f"coverage: variant {variant}: {str(e).splitlines()[0]}") from None


def _view_coverage(
    name: str,
    s: Samples,
    spp: int,
    measure: np.ndarray,
    bins: int,
    min_cos: float,
    threshold: float,
) -> tuple[ViewCoverage, np.ndarray]:
    share = s.shares()
    lit = np.bincount(s.pixel, weights=s.weight, minlength=s.height * s.width) > 0
    total = float(share.sum())  # = the lit pixels (up to rounding)
    pos = share > 0
    th, td, ph = half_diff(s.wi[pos], s.wo[pos])
    ih, id_ = bin_index(th, bins), bin_index(td, bins)
    sh = share[pos]
    in_d = (s.wi[pos, 2] > min_cos) & (s.wo[pos, 2] > min_cos)
    weight = np.zeros((bins, bins))
    np.add.at(weight, (ih[in_d], id_[in_d]), sh[in_d])
    phi = np.bincount(
        np.clip((ph[in_d] / (2 * math.pi) * PHI_BINS).astype(np.int64), 0, PHI_BINS - 1),
        weights=sh[in_d],
        minlength=PHI_BINS,
    )
    density = np.zeros((bins, bins))
    if total > 0:
        np.divide(weight / total, measure, out=density, where=measure > 0)
    # mixing: per pixel, the chance that two of its samples (weighted by share, drawn
    # without repeating a sample) share a bin, pooled over the pixels as A / B
    key = s.pixel[pos] * (bins * bins) + ih * bins + id_
    _, inv = np.unique(key, return_inverse=True)
    cell = np.bincount(inv.reshape(-1), weights=sh)
    self_sq = float(sh @ sh)
    view = ViewCoverage(
        scene=name,
        pixels=s.height * s.width,
        pixels_lit=int(lit.sum()),
        spp=spp,
        samples=len(share),
        weight=weight,
        density=density,
        figure=float(measure[density >= threshold].sum()),
        phi_h=phi / total if total > 0 else phi,
        mixing=(float(cell @ cell) - self_sq, total - self_sq),
    )
    return view, share


def compute(
    views: Sequence[Any],
    *,
    variant: str | None = None,
    rays: int = RAYS,
    seed: int = 0,
    bins: int = BINS,
    min_cos: float = MIN_COS,
    threshold: float = THRESHOLD,
    max_pairs: int = MAX_PAIRS,
) -> Coverage:
    """The coverage of ``views``: :class:`neural_brdf.inverse.fit.View` objects (as
    :func:`~neural_brdf.inverse.fit.read_views` returns them) or scene paths.

    ``rays``: camera rays per view, spread evenly over the film's pixels (at least
    MIN_SPP each).  ``variant``: the Mitsuba variant to use (None: the current one, else
    ``llvm_ad_rgb``); any RGB variant works.  View k draws its samples from ``seed`` and
    k alone, so a view added leaves the others' samples as they were.  A scene that
    cannot be read or loaded raises InputError naming it."""
    if not views:
        raise InputError("coverage: no views")
    _use_variant(variant)
    measure = bin_measure(bins, min_cos)
    rng = np.random.default_rng([seed, 7])
    out: list[ViewCoverage] = []
    density = np.zeros((bins, bins))
    kept: list[tuple[np.ndarray, ...]] = []
    for k, item in enumerate(views):
        name, path, tree = _scene_of(item, k)
        scene = load(path, tree)
        inverse_views.check_seen(scene, path)  # a camera to trace, a light to sample
        h, w = inverse_views.film_size(scene)
        spp = max(MIN_SPP, -(-rays // (h * w)))
        s = view_samples(scene, spp=spp, seed=seed * 1_000_003 + k)
        view, share = _view_coverage(name, s, spp, measure, bins, min_cos, threshold)
        out.append(view)
        density += view.density
        pos = np.flatnonzero(share > 0)
        kept.append((s.wi[pos], s.wo[pos], share[pos], np.full(len(pos), k)))
    observed = (density >= threshold) & (measure > 0)
    wi, wo, share, which = (np.concatenate(c) for c in zip(*kept))
    total = len(share)
    if total > max_pairs:
        pick = np.sort(rng.choice(total, size=max_pairs, replace=False))
        wi, wo, share, which = wi[pick], wo[pick], share[pick], which[pick]
    cov = Coverage(
        views=out,
        bins=bins,
        min_cos=min_cos,
        threshold=threshold,
        rays=rays,
        seed=seed,
        measure=measure,
        density=density,
        observed=observed,
        figure=float(measure[observed].sum()),
        wi=wi.astype(np.float32),
        wo=wo.astype(np.float32),
        pair_share=share.astype(np.float32),
        pair_view=which.astype(np.int64),
        pair_observed=np.zeros(len(share), bool),
        pairs_total=total,
    )
    cov.pair_observed = observed_mask(cov, wi, wo)
    return cov


def mixing(cov: Coverage, view: int | None = None) -> float:
    """How many (theta_h, theta_d) bins a pixel's value mixes: 1 / (the chance that two
    of a pixel's samples, weighted by their shares, fall in the same bin), pooled over
    the lit pixels (of ``view``, or of all views).  About 1 when each pixel pins one
    pair (a point light), hundreds under an environment, where a pixel is an integral
    over the lighting and f is observed only through such integrals.  inf when no two
    samples of a pixel ever share a bin (raise ``rays``)."""
    chosen = cov.views if view is None else [cov.views[view]]
    a = sum(v.mixing[0] for v in chosen)
    b = sum(v.mixing[1] for v in chosen)
    return b / a if a > 0 else (math.inf if b > 0 else math.nan)


def observed_mask(cov: Coverage, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """(N,) bool: which local pairs (N, 3), (N, 3) lie in the domain (both cosines >
    ``cov.min_cos``) and in a bin ``cov`` observes: "the observed part of the domain"."""
    return in_bins(cov.observed, cov.min_cos, wi, wo)


def in_bins(chosen: np.ndarray, min_cos: float, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """(N,) bool: which local pairs (N, 3), (N, 3) (normalised here) have both cosines >
    ``min_cos`` and fall in a (theta_h, theta_d) bin that ``chosen`` (bins x bins bool)
    marks."""
    wi = np.asarray(wi, np.float64).reshape(-1, 3)
    wo = np.asarray(wo, np.float64).reshape(-1, 3)
    wi = wi / np.linalg.norm(wi, axis=-1, keepdims=True)
    wo = wo / np.linalg.norm(wo, axis=-1, keepdims=True)
    in_d = (wi[:, 2] > min_cos) & (wo[:, 2] > min_cos)
    th, td, _ = half_diff(wi, wo)
    b = chosen.shape[0]
    return in_d & chosen[bin_index(th, b), bin_index(td, b)]


# ------------------------------------------------------------------ reporting
DEFINITION = (
    "share of the (wi, wo) domain with both cosines > {min_cos:g} (by its solid-angle "
    "measure), in {bins} x {bins} (theta_h, theta_d) bins, whose relative observed "
    "density rho (each pixel's light split over its sampled pairs, summed over views; "
    "1 = a uniform spread) is at least {threshold:g}"
)


def _round(x: float, digits: int = 4) -> float | None:
    return round(x, digits) if math.isfinite(x) else None


def summary(cov: Coverage) -> dict[str, Any]:
    """The figures for metrics.json (JSON types only; definitions in the module doc)."""
    step = 90.0 / cov.bins
    rows = np.flatnonzero(cov.observed.any(0))  # theta_d bins with an observed bin
    lit = np.array([v.pixels_lit for v in cov.views], float)
    phi = sum((v.phi_h * n for v, n in zip(cov.views, lit)), np.zeros(PHI_BINS))
    if lit.sum() > 0:
        phi = phi / lit.sum()
    return {
        "figure": round(cov.figure, 4),
        "definition": DEFINITION.format(
            min_cos=cov.min_cos, bins=cov.bins, threshold=cov.threshold
        ),
        "bins": [cov.bins, cov.bins],
        "min_cos": cov.min_cos,
        "threshold": cov.threshold,
        "warn_below": WARN_BELOW,
        "rays_per_view": cov.rays,
        "seed": cov.seed,
        "pairs_observed": cov.pairs_total,
        "pairs_kept": len(cov.pair_share),
        "theta_d_observed_deg": (
            [float(rows[0] * step), float((rows[-1] + 1) * step)] if len(rows) else None
        ),
        "theta_d_rows_observed": int(len(rows)),
        "bins_mixed_per_pixel": _round(mixing(cov), 2),
        "phi_h_shares": [round(float(x), 4) for x in phi],
        # [theta_h][theta_d]: the observed bins (the determined map counts within them)
        "observed_bins": [[int(x) for x in r] for r in cov.observed],
        "per_view": [
            {
                "scene": v.scene,
                "figure": round(v.figure, 4),
                "pixels": v.pixels,
                "pixels_lit": v.pixels_lit,
                "spp": v.spp,
                "samples": v.samples,
                "bins_mixed_per_pixel": _round(mixing(cov, k), 2),
            }
            for k, v in enumerate(cov.views)
        ],
    }


def warning(cov: Coverage, below: float = WARN_BELOW) -> str | None:
    """A one-line warning when the coverage figure is below ``below``, else None."""
    if cov.figure >= below:
        return None
    unlit = [v.scene for v in cov.views if v.pixels_lit == 0]
    lines = f"; no lit pixel of the fit BSDF in {', '.join(unlit)}" if unlit else ""
    return (
        f"coverage: the images observe {percent_text(cov.figure)} % of the (wi, wo) domain "
        f"with both cosines > {cov.min_cos:g} (below {100 * below:.0f} %){lines}: the "
        "rest of the BRDF comes from the start and the network's prior, not the images; "
        "add views or lights at other angles to the camera (docs/inverse.md)"
    )


def map_figure(cov: Coverage):
    """The matplotlib Figure of :func:`write_picture` (its first axes: the map)."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap, LogNorm
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.6, 4.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    extent = (0.0, 90.0, 0.0, 90.0)
    back = np.where(cov.measure > 0, 1.0, 0.0).T  # rows: theta_d
    ax.imshow(
        back,
        origin="lower",
        extent=extent,
        cmap=ListedColormap(["white", "0.78"]),
        vmin=0,
        vmax=1,
        interpolation="nearest",
    )
    shown = np.ma.masked_where(~cov.observed.T, cov.density.T)
    top = max(float(cov.density.max()), cov.threshold * 10.0)
    img = ax.imshow(
        shown,
        origin="lower",
        extent=extent,
        cmap=colormaps["viridis"],
        norm=LogNorm(vmin=cov.threshold, vmax=top),
        interpolation="nearest",
    )
    # The domain's edge, cos(theta_h) cos(theta_d) = min_cos: the smaller cosine of a
    # pair is cos(theta_h) cos(theta_d) - sin(theta_h) sin(theta_d) |cos(phi_d)|, at most
    # that at phi_d = 90 degrees.  A bin the edge crosses is in the domain in part; the
    # part beyond the edge is painted white, so no bin's colour reaches past the dashes.
    t = np.linspace(0.0, math.pi / 2, 400)
    edge = np.degrees(np.arccos(np.clip(cov.min_cos / np.maximum(np.cos(t), 1e-12), 0, 1)))
    ax.fill_between(np.degrees(t), edge, 90.0, color="white", lw=0, zorder=2)
    inside = np.cos(t) > cov.min_cos
    ax.plot(np.degrees(t[inside]), edge[inside], color="k", lw=0.8, ls="--", zorder=3)
    ax.set_xlabel("theta_h (degrees)")
    ax.set_ylabel("theta_d (degrees)")
    ax.set_xlim(0, 90)
    ax.set_ylim(0, 90)
    ax.set_title(
        f"observed: {percent_text(cov.figure)} % of the domain, {len(cov.views)} view(s)\n"
        f"grey: unobserved (rho < {cov.threshold:g}); white, beyond the dashes: "
        f"a cosine < {cov.min_cos:g}",
        fontsize=9,
    )
    fig.colorbar(img, ax=ax, label="rho: observed density / uniform")
    return fig


def write_picture(cov: Coverage, path: str | Path) -> Path:
    """A PNG of the (theta_h, theta_d) map: the relative density rho of the observed
    bins in colour (log scale), the domain's unobserved bins grey, outside the domain
    white; the figure in the title."""
    from neural_brdf.fileio import atomic_path

    path = Path(path)
    fig = map_figure(cov)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def assess(
    views: Sequence[Any], *, picture: str | Path | None = None, **kwargs: Any
) -> tuple[dict[str, Any], str | None]:
    """The one call of a fit: :func:`compute` (``kwargs``: its options), the PNG when
    ``picture`` is a path, and (:func:`summary`, :func:`warning`).  The summary names
    the picture's file (``picture``) when one was written."""
    cov = compute(views, **kwargs)
    info = summary(cov)
    if picture is not None:
        info["picture"] = Path(write_picture(cov, picture)).name
    return info, warning(cov)


# ------------------------------------------------------------------ command line
def _scenes(paths: list[str]) -> list[Path]:
    """Scene files from the arguments: XML scenes as they are, a config's
    ``target.images`` scenes."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.suffix.lower() in (".yaml", ".yml"):
            from neural_brdf import config as cfgmod

            cfg = cfgmod.load(p)
            held = set(cfg.images.validation_views)  # held out whole: not fitted, as the fit
            for k, item in enumerate(cfg.target.images or []):
                if k in held:
                    print(
                        f"{item.scene}: held out whole (images.validation_views): not counted",
                        file=sys.stderr,
                    )
                else:
                    out.append(Path(item.scene))
        else:
            out.append(p)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = module_parser("neural_brdf.inverse.coverage", __doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="+", help="scene XML files, or a config with target.images")
    ap.add_argument("-o", "--picture", help="write the (theta_h, theta_d) map as a PNG")
    ap.add_argument("--json", help="write the summary as JSON")
    ap.add_argument("--rays", type=int, default=RAYS, help=f"camera rays per view ({RAYS})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variant", default=None, help=f"Mitsuba variant ({DEFAULT_VARIANT})")
    args = ap.parse_args(argv)
    if args.rays < 1:
        ap.error(f"--rays: must be >= 1, got {args.rays}")
    try:
        check_outputs(args.picture, args.json)
        info, message = assess(
            _scenes(args.inputs),
            picture=args.picture,
            rays=args.rays,
            seed=args.seed,
            variant=args.variant,
        )
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for v in info["per_view"]:
        print(
            f"{v['scene']}: {percent_text(v['figure'])} % alone, {v['pixels_lit']} lit pixels, "
            f"{v['bins_mixed_per_pixel']} bins mixed per pixel"
        )
    print(
        f"coverage: {percent_text(info['figure'])} % ({info['definition']}); "
        f"{info['bins_mixed_per_pixel']} bins mixed per pixel"
    )
    return cli_outputs(info, message, args.json)


def check_outputs(picture: str | None, json_path: str | None) -> None:
    """Before any work: ``-o`` and ``--json`` name files whose folders exist (InputError)."""
    from neural_brdf.fileio import check_output_folder

    for flag, path in (("-o", picture), ("--json", json_path)):
        if path is None:
            continue
        if Path(path).is_dir():
            raise InputError(f"{flag} {path}: is a folder; give a file name")
        check_output_folder(path, flag)


def cli_outputs(info: dict[str, Any], message: str | None, json_path: str | None) -> int:
    """The end of this and determined's command line: the warning on stderr, the
    summary as JSON when asked; exit code 0."""
    import json

    if message:
        print(f"warning: {message}", file=sys.stderr)
    if json_path:
        from neural_brdf.fileio import atomic_write

        atomic_write(json_path, json.dumps(info, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
