"""What the images determine: how well the views pin the BRDF, bin by bin.

    python -m neural_brdf.inverse.determined runs/images/fit.yaml [-o determined.png]

The coverage (:mod:`neural_brdf.inverse.coverage`) says which (theta_h, theta_d) bins
the views *touch*.  A bin can be touched by every pixel and still be free: under a
constant sky a flat face's pixels all mix the same pairs, so the images give the sum of
f over them and nothing about its shape (a highlight no pixel sees is not known, though
every bin is "observed").  This module asks how well the views *determine* f there.

**The model.** Around a reference material f0 (the fit's chosen start; before a fit, a
``diffuse``), let f = f0 (1 + delta_b) for pairs in bin b of (theta_h, theta_d) bins
over [0, pi/2]^2: the coverage's 32 x 32 and coarser, :data:`LEVELS`. Pixel p's value
(direct light) is then I_p = sum_b S_pb (1 + delta_b), S_pb the part of the pixel that
f0 makes from its pairs in bin b. The fit's loss weighs a pixel's residual by 1 / (y_p^2
+ REL_EPS) (its relative MSE, :mod:`neural_brdf.inverse.views`), where the targets'
noise has variance sigma^2 (:func:`~neural_brdf.inverse.views.target_noise`). With a
prior delta_b ~ N(0, 1) (a bin's level unknown to within a factor of about e), the
posterior covariance of delta after the images is (the posterior of Bayesian linear
regression, Bishop 2006, Pattern Recognition and Machine Learning, eq. 3.54 with alpha =
1, beta = 1 / sigma^2)

    C = (J^T J / sigma^2 + I)^-1,        J_pb = S_pb / sqrt(I_p^2 + REL_EPS),

and a bin is **determined** when sqrt(C_bb) <= ``tol`` (:data:`TOL`, 0.05, the
benchmark's BRDF goal: the images fix f there to 5 %, one standard deviation, whatever
the other bins do: two bins that every pixel mixes in the same proportion are each free,
though their sum is known).  Finer bins are harder to fix (each pixel mixes more of
them); the coarse levels' J^T J are block sums of the finest's.  A bin's level is fixed
by the pixels that see part of it; the part of it that no view observes (the coverage's
32 x 32 bins, :func:`~neural_brdf.inverse.coverage.compute`) holds only the reference's
shape there, so it does not count: a bin determined is counted over its observed fine
bins (``Level.fine``), never more than the coverage.  The figure is the share of the
domain (both cosines > 0.1, by solid-angle measure, the coverage's) in those bins of
:data:`BINS` (11.25 degrees), and **the reference's determined energy** the share of
its f cos cos over that domain that lies there (a highlight no view resolves: a small
share for a glossy reference).

**The estimate.**  :data:`PIXELS` of each view's pixels that see the fit BSDF (evenly
strided), :data:`SPP` camera rays each with one emitter sample
(:func:`~neural_brdf.inverse.coverage.view_samples`); S_pb the mean over pixel p's rays
of c = f0 cos(theta_i) L / pdf over those in bin b.  J^T J built from such estimates is
biased upwards by their own noise (a bin a pixel sampled once looks seen, and noisy rows
make pixels look more different than they are); the sum over pairs of distinct samples
(a U-statistic, as :func:`~neural_brdf.inverse.coverage.mixing`) removes the bias:
[spp / (spp - 1)] (S_p S_p^T - diag(Q_p)), Q_pb the mean of c^2 / spp over its rays in
b.  Negative eigenvalues of the estimate are clipped to 0, and the sum over the sampled
pixels is scaled by the view's pixels on the BSDF over those sampled.  A pixel's weight
1 / (I_p^2 + REL_EPS) takes I_p from the same samples.

**Limits.**  Linear around f0 (a start far from the truth gives the map of a material
near it); isotropic bins (an anisotropic material's azimuth is not resolved here: the
coverage's phi_h shares say whether the views see it); direct light only; emitter
samples only (a mirror-sharp reference under an environment needs more ``spp``).
"""

from __future__ import annotations

import math
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from neural_brdf.errors import InputError, module_parser
from neural_brdf.inverse import coverage
from neural_brdf.inverse import views as inverse_views
from neural_brdf.measured.rgl.layout import Y_WEIGHTS

TOL = 0.05  # a bin is determined when the posterior std of its relative level <= TOL
FINE = 32  # the finest bins per axis (the coverage's); coarser levels halve it
LEVELS = (32, 16, 8, 4)  # bins per axis of the levels: 2.8, 5.6, 11.25, 22.5 degrees
BINS = 8  # the level of the figure: 11.25-degree bins
PIXELS = 1024  # pixels sampled per view (evenly strided over those on the fit BSDF)
SPP = 256  # camera rays per sampled pixel (one emitter sample each)
NOMINAL_NOISE = 1e-3  # sigma^2 when the targets' noise is unknown (scenes alone)
WARN_ENERGY = 0.5  # warning(): the reference's determined energy below this
QUAD = 6  # quadrature points per bin and axis of the reference's energy


@dataclass
class Level:
    """One resolution of :class:`Determined`: ``bins`` x ``bins`` (theta_h, theta_d)."""

    bins: int
    measure: np.ndarray  # (bins, bins): the domain's measure by bin (sums to 1)
    std: np.ndarray  # (bins, bins): sqrt(C_bb), the posterior std of delta_b
    determined: np.ndarray  # (bins, bins) bool: std <= tol, in the domain
    energy: np.ndarray  # (bins, bins): the reference's f cos cos over the domain (sums to 1)
    fine: np.ndarray  # (FINE, FINE) bool: the observed fine bins of determined bins
    figure: float  # the domain's share in ``fine``
    energy_figure: float  # the reference's energy share in ``fine``


@dataclass
class Determined:
    """What :func:`compute` found (module doc for the definitions)."""

    levels: dict[int, Level]  # by bins per axis (LEVELS)
    bins: int  # the level of the figure (BINS)
    min_cos: float
    tol: float
    noise: float  # sigma^2: the targets' relative noise variance used
    noise_source: str  # "targets" or "nominal"
    reference: str  # the reference material's name (brdf_of)
    pixels: list[int]  # per view: its pixels on the fit BSDF (before sampling)
    sampled: list[int]  # per view: the pixels sampled
    spp: int
    observed: np.ndarray  # (FINE, FINE) bool: the coverage's observed bins

    @property
    def level(self) -> Level:
        return self.levels[self.bins]

    @property
    def figure(self) -> float:
        return self.level.figure

    @property
    def energy_figure(self) -> float:
        return self.level.energy_figure

    def resolution(self) -> np.ndarray:
        """(FINE, FINE) [theta_h, theta_d]: the width in degrees of the finest level's
        bin that is determined there (NaN: none; outside the domain too)."""
        out = np.full((FINE, FINE), np.nan)
        for bins in sorted(self.levels, reverse=True):  # coarse after fine
            out = np.where(np.isnan(out) & self.levels[bins].fine, 90.0 / bins, out)
        return out


# f(wi, wo) in 1/sr without a cosine: (N, 3) local directions (wi towards the light, wo
# towards the camera) -> (N, 3) RGB
BRDF = Callable[[np.ndarray, np.ndarray], np.ndarray]


def brdf_of(reference: ET.Element | BRDF | None) -> tuple[BRDF, str]:
    """(f, its name) of a reference: a ``<bsdf>`` element (through Mitsuba: its type),
    a function f(wi, wo) ("network"), or None (a grey ``diffuse``)."""
    if callable(reference):
        return reference, "network"
    el = reference if reference is not None else inverse_views.bsdf_element("diffuse")
    bsdf = inverse_views.mitsuba_bsdf(el)

    def f(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        fc = inverse_views.mitsuba_f_cos(bsdf, wo, wi)  # f cos(theta_i): camera side first
        return fc / np.maximum(np.asarray(wi, np.float64)[:, 2:3], 1e-12)

    return f, str(el.get("type"))


def reference_energy(f: BRDF, bins: int, min_cos: float, quad: int = QUAD) -> np.ndarray:
    """(bins, bins): the luminance of f cos(theta_i) cos(theta_o) integrated
    over each bin's pairs with both cosines > ``min_cos`` (dwi dwo = 4 cos theta_d
    sin theta_h sin theta_d dtheta_h dphi_h dtheta_d dphi_d; phi_h = 0: isotropic),
    normalised to sum 1 (zeros when it is 0 everywhere)."""
    from neural_brdf.measured import merl

    n = bins * quad
    t = (np.arange(n) + 0.5) / n * (0.5 * math.pi)
    phi_d = (np.arange(2 * quad) + 0.5) / (2 * quad) * (2.0 * math.pi)
    th, td, pd = np.meshgrid(t, t, phi_d, indexing="ij")
    wi, wo = merl.directions(th.ravel(), 0.0, td.ravel(), pd.ravel())
    wi, wo = np.asarray(wi, np.float64), np.asarray(wo, np.float64)
    inside = (wi[:, 2] > min_cos) & (wo[:, 2] > min_cos)
    value = np.zeros(len(wi))
    if inside.any():
        fi = np.asarray(f(wi[inside], wo[inside]), np.float64)
        value[inside] = luminance(fi) * wi[inside, 2] * wo[inside, 2]
    dens = 4.0 * np.cos(td) * np.sin(th) * np.sin(td)
    e = (value.reshape(th.shape) * dens).sum(-1)
    e = e.reshape(bins, quad, bins, quad).sum(axis=(1, 3))
    total = e.sum()
    return e / total if total > 0 else e


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) linear RGB -> (N,) luminance (Rec. 709, the measured files' weights)."""
    return np.asarray(rgb, np.float64) @ Y_WEIGHTS


def _view_information(
    scene, f: BRDF, *, pixels: int, spp: int, seed: int
) -> tuple[np.ndarray, int, int]:
    """(J^T J at the FINE level, estimated for the view and scaled to all its pixels
    on the BSDF; those pixels; the pixels sampled)."""
    nb = FINE * FINE
    # the pixels on the fit BSDF: one ray at each pixel's centre
    first = coverage.view_samples(scene, spp=1, seed=seed, jitter=False)
    on = np.unique(first.pixel)
    if len(on) == 0:
        return np.zeros((nb, nb)), 0, 0
    chosen = on[np.unique(np.linspace(0, len(on) - 1, min(pixels, len(on))).astype(np.int64))]
    s = coverage.view_samples(scene, spp=spp, seed=seed + 1, pixels=chosen)
    keep = s.weight > 0
    wi, wo, w, pix = s.wi[keep], s.wo[keep], s.weight[keep], s.pixel[keep]
    c = np.zeros(len(w))
    if len(w):  # f w, w = lum(L / pdf) cos(theta_i)
        c = np.maximum(luminance(f(wi, wo)), 0.0) * w
    th, td, _ = coverage.half_diff(wi, wo)
    col = coverage.bin_index(th, FINE) * FINE + coverage.bin_index(td, FINE)
    row = np.searchsorted(chosen, pix)
    F = information(row, col, c, pixels=len(chosen), spp=spp, bins=nb)
    return F * (len(on) / len(chosen)), len(on), len(chosen)


def information(
    row: np.ndarray, col: np.ndarray, c: np.ndarray, *, pixels: int, spp: int, bins: int
) -> np.ndarray:
    """(bins, bins): the estimate of J^T J from samples (module doc): sample s of pixel
    ``row[s]`` (of ``pixels``, each traced with ``spp`` rays: the rays that found
    nothing are the ones missing here) in bin ``col[s]`` with contribution ``c[s]``.
    Unbiased for sum_p J_p^T J_p (the pairs of distinct samples only)."""
    flat = np.asarray(row, np.int64) * bins + np.asarray(col, np.int64)
    c = np.asarray(c, np.float64)
    S = np.bincount(flat, weights=c / spp, minlength=pixels * bins).reshape(pixels, bins)
    Q = np.bincount(flat, weights=(c / spp) ** 2, minlength=pixels * bins).reshape(pixels, bins)
    scale = 1.0 / (S.sum(1) ** 2 + inverse_views.REL_EPS)  # the loss's weight of a pixel
    F = (S * scale[:, None]).T @ S - np.diag((Q * scale[:, None]).sum(0))
    return F * (spp / (spp - 1.0))


def _coarsen(a: np.ndarray, bins: int) -> np.ndarray:
    """(FINE, FINE) -> (bins, bins) by sums of blocks."""
    f = FINE // bins
    return a.reshape(bins, f, bins, f).sum(axis=(1, 3))


def _level(
    F: np.ndarray,
    sigma2: float,
    bins: int,
    tol: float,
    min_cos: float,
    energy: np.ndarray,
    observed: np.ndarray,
) -> Level:
    """The posterior at ``bins`` per axis from the FINE level's J^T J; its figures
    over the ``observed`` (FINE, FINE) bins of the determined ones."""
    f = FINE // bins
    cell = (np.arange(FINE)[:, None] // f) * bins + np.arange(FINE)[None, :] // f
    A = np.zeros((FINE * FINE, bins * bins))
    A[np.arange(FINE * FINE), cell.ravel()] = 1.0  # each fine bin in its coarse one
    G = A.T @ F @ A
    lam, vec = np.linalg.eigh(0.5 * (G + G.T))
    lam = np.maximum(lam, 0.0) / sigma2  # the estimate's negative eigenvalues clipped
    std = np.sqrt((vec**2) @ (1.0 / (lam + 1.0))).reshape(bins, bins)
    measure = coverage.bin_measure(bins, min_cos)
    determined = (std <= tol) & (measure > 0)
    # a bin's level is fixed by the pixels that see part of it; the rest of it (no view
    # observes it) holds only the reference's shape, so it is not counted (the retro
    # lobe below theta_d 17 degrees under lights 34 degrees from their cameras)
    fine_measure = coverage.bin_measure(FINE, min_cos)
    fine = np.kron(determined, np.ones((f, f), bool)) & observed & (fine_measure > 0)
    return Level(
        bins=bins,
        measure=measure,
        std=std,
        determined=determined,
        energy=_coarsen(energy, bins),
        fine=fine,
        figure=float(fine_measure[fine].sum()),
        energy_figure=float(energy[fine].sum()),
    )


def compute(
    views: Sequence[Any],
    reference: ET.Element | BRDF | None = None,
    noise: float | None = None,
    *,
    pixels: int = PIXELS,
    spp: int = SPP,
    seed: int = 0,
    bins: int = BINS,
    min_cos: float = coverage.MIN_COS,
    tol: float = TOL,
    variant: str | None = None,
    observed: np.ndarray | None = None,
) -> Determined:
    """How well ``views`` (View objects or scene paths, as :func:`coverage.compute`)
    determine f near ``reference`` (:func:`brdf_of`: a ``<bsdf>`` element, a function
    f(wi, wo), or None: a grey ``diffuse``),
    given the targets' relative noise variance ``noise`` (None: :data:`NOMINAL_NOISE`),
    at every level of :data:`LEVELS`; ``bins`` (one of them) is the figure's.
    ``observed``: the coverage's observed (FINE, FINE) bins of the same views (a fit's
    ``training.coverage.observed_bins``); None: computed here (``seed``)."""
    if not views:
        raise InputError("determined: no views")
    if spp < 2:
        raise InputError(f"determined: spp must be at least 2, got {spp}")
    if bins not in LEVELS:
        raise InputError(f"determined: bins must be one of {list(LEVELS)}, got {bins}")
    coverage._use_variant(variant)
    if observed is None:
        observed = coverage.compute(views, seed=seed, bins=FINE, min_cos=min_cos).observed
    observed = np.asarray(observed, bool)
    if observed.shape != (FINE, FINE):
        raise InputError(f"determined: observed bins must be {FINE} x {FINE}, got {observed.shape}")
    f, name = brdf_of(reference)
    F = np.zeros((FINE * FINE, FINE * FINE))
    on, sampled = [], []
    for k, item in enumerate(views):
        _, path, tree = coverage._scene_of(item, k)
        scene = coverage.load(path, tree)
        Fv, n_on, n_k = _view_information(
            scene, f, pixels=pixels, spp=spp, seed=seed * 1_000_003 + 2 * k
        )
        F += Fv
        on.append(n_on)
        sampled.append(n_k)
    known = noise is not None and noise > 0
    sigma2 = float(noise) if known else NOMINAL_NOISE  # type: ignore[arg-type]
    energy = reference_energy(f, FINE, min_cos)
    return Determined(
        levels={b: _level(F, sigma2, b, tol, min_cos, energy, observed) for b in LEVELS},
        bins=bins,
        min_cos=min_cos,
        tol=tol,
        noise=sigma2,
        noise_source="targets" if known else "nominal",
        reference=name,
        pixels=on,
        sampled=sampled,
        spp=spp,
        observed=observed,
    )


def determined_mask(det: Determined, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """(N,) bool: which local pairs lie in the domain and in an observed fine bin of a
    determined bin of the figure's level."""
    return coverage.in_bins(det.level.fine, det.min_cos, wi, wo)


def summary_mask(info: dict[str, Any], wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """:func:`determined_mask` from a :func:`summary` (metrics.json's
    ``training.determined``; a summary from before ``determined_fine``: its
    ``determined_bins``)."""
    bins = np.asarray(info.get("determined_fine", info["determined_bins"]), bool)
    return coverage.in_bins(bins, float(info.get("min_cos", coverage.MIN_COS)), wi, wo)


# ------------------------------------------------------------------ reporting
DEFINITION = (
    "share of the (wi, wo) domain with both cosines > {min_cos:g} (by its solid-angle "
    "measure) in {bins} x {bins} (theta_h, theta_d) bins ({width:g} degrees) where the "
    "views fix f's level to {tol:g} (the posterior standard deviation of f / f0 - 1 in "
    "the bin, every bin free at once, a N(0, 1) prior, the targets' noise; f0 the "
    "reference material), over those bins' parts the coverage observes ({fine} x "
    "{fine} bins)"
)


def summary(det: Determined) -> dict[str, Any]:
    """The figures for metrics.json (JSON types only)."""
    lv = det.level
    step = 90.0 / FINE
    th = np.flatnonzero(lv.fine.any(1))
    return {
        "figure": round(det.figure, 4),
        "energy_figure": round(det.energy_figure, 4),
        "bins": [det.bins, det.bins],
        "definition": DEFINITION.format(
            min_cos=det.min_cos, bins=det.bins, width=90.0 / det.bins, tol=det.tol, fine=FINE
        ),
        "by_bin_width_deg": {
            f"{90.0 / b:g}": {
                "figure": round(det.levels[b].figure, 4),
                "energy_figure": round(det.levels[b].energy_figure, 4),
            }
            for b in LEVELS
        },
        "reference": det.reference,
        "min_cos": det.min_cos,
        "tol": det.tol,
        "noise": det.noise,
        "noise_source": det.noise_source,
        "warn_energy_below": WARN_ENERGY,
        "theta_h_determined_deg": (
            [float(th[0] * step), float((th[-1] + 1) * step)] if len(th) else None
        ),
        "observed_figure": round(float(det.levels[FINE].measure[det.observed].sum()), 4),
        "pixels_on_bsdf": det.pixels,
        "pixels_sampled": det.sampled,
        "spp": det.spp,
        # the figure's level, [theta_h][theta_d]: each bin's posterior std (3 digits) and
        # whether it is determined; the FINE bins counted (summary_mask reads them)
        "std": [[round(float(x), 3) for x in r] for r in lv.std],
        "determined_bins": [[int(x) for x in r] for r in lv.determined],
        "determined_fine": [[int(x) for x in r] for r in lv.fine],
    }


def warning(
    det: Determined, below: float = WARN_ENERGY, role: str = "start", label: str | None = None
) -> str | None:
    """A one-line warning when the reference's determined energy is below ``below``
    (``role``: what the reference is to the reader: a fit's start; ``label``: its name
    there, a fit's start family, where it is not the reference's Mitsuba type: a
    ``clearcoat`` start is a ``principled``)."""
    if det.energy_figure >= below:
        return None
    return (
        f"determined: in {90.0 / det.bins:g}-degree bins the images fix f to "
        f"{100 * det.tol:.0f} % over {100 * det.figure:.1f} % of the domain, holding "
        f"{100 * det.energy_figure:.1f} % of the reflected light of the "
        f"{label or det.reference} {role} "
        f"(below {100 * below:.0f} %): the rest of the BRDF comes from the start's family "
        "and the network's prior, not the images; add views or lights at other angles "
        "(docs/inverse.md)"
    )


def write_picture(det: Determined, path: str | Path) -> Path:
    """A PNG of the (theta_h, theta_d) map: the width of the finest bin determined
    there (:meth:`Determined.resolution`), black where none is, white outside the
    domain; the reference's energy as grey contours; the figures in the title."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.figure import Figure

    from neural_brdf.fileio import atomic_path

    path = Path(path)
    fig = Figure(figsize=(5.8, 4.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    extent = (0.0, 90.0, 0.0, 90.0)
    domain = det.levels[FINE].measure > 0
    ax.imshow(
        np.where(domain, 1.0, 0.0).T,
        origin="lower",
        extent=extent,
        cmap=ListedColormap(["white", "0.15"]),
        vmin=0,
        vmax=1,
        interpolation="nearest",
    )
    widths = sorted(90.0 / b for b in LEVELS)  # fine first
    res = det.resolution()
    code = np.full(res.shape, np.nan)
    for k, wd in enumerate(widths):
        code[np.isclose(res, wd)] = k
    colours = ["#fde725", "#5ec962", "#21918c", "#3b528b", "#440154"][: len(widths)]
    img = ax.imshow(
        np.ma.masked_invalid(code).T,
        origin="lower",
        extent=extent,
        cmap=ListedColormap(colours),
        norm=BoundaryNorm(np.arange(len(widths) + 1) - 0.5, len(widths)),
        interpolation="nearest",
    )
    fine = det.levels[FINE]
    if fine.energy.max() > 0:
        centre = (np.arange(FINE) + 0.5) * (90.0 / FINE)
        levels = fine.energy.max() * np.array([0.01, 0.1, 0.5])
        ax.contour(centre, centre, fine.energy.T, levels, colors="0.6", linewidths=0.8)
    ax.set_xlabel("theta_h (degrees)")
    ax.set_ylabel("theta_d (degrees)")
    ax.set_xlim(0, 90)
    ax.set_ylim(0, 90)
    ax.set_title(
        f"determined to {100 * det.tol:.0f} % in {90.0 / det.bins:g}° bins: "
        f"{100 * det.figure:.1f} % of the domain, {100 * det.energy_figure:.1f} % of the light"
        f"\nreference: {det.reference} (grey: its light, 1, 10, 50 % of the peak); "
        "black: none",
        fontsize=8.5,
    )
    bar = fig.colorbar(img, ax=ax, ticks=range(len(widths)))
    bar.ax.set_yticklabels([f"{w:g}" for w in widths])
    bar.set_label("finest bin determined (degrees)")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def assess(
    views: Sequence[Any],
    reference: ET.Element | BRDF | None = None,
    noise: float | None = None,
    *,
    picture: str | Path | None = None,
    role: str = "start",
    label: str | None = None,
    **kwargs: Any,
) -> tuple[dict[str, Any], str | None]:
    """:func:`compute`, the PNG when ``picture`` is a path, and (:func:`summary`,
    :func:`warning`; ``role`` and ``label`` name the reference there)."""
    t0 = time.perf_counter()
    det = compute(views, reference, noise, **kwargs)
    info = summary(det)
    info["seconds"] = round(time.perf_counter() - t0, 2)
    if picture is not None:
        info["picture"] = Path(write_picture(det, picture)).name
    return info, warning(det, role=role, label=label)


# ------------------------------------------------------------------ command line
def _inputs(paths: list[str]) -> tuple[list[Any], float | None]:
    """The views of the arguments (XML scenes, or a config's ``target.images``) and,
    from a config's target images, their noise (:func:`~neural_brdf.inverse.views.
    target_noise`; None for scenes alone)."""
    yaml = [p for p in paths if Path(p).suffix.lower() in (".yaml", ".yml")]
    if not yaml:
        return list(coverage._scenes(paths)), None
    if len(paths) > 1:
        raise InputError("determined: give one config, or scene files")
    from neural_brdf import config as cfgmod
    from neural_brdf.inverse import starts

    cfg = cfgmod.load(Path(yaml[0]))
    inverse_views.use_variant(inverse_views.variant_name(cfg), key=inverse_views.variant_key(cfg))
    views = inverse_views.read_views(cfg)
    for v in views:
        v.object = starts.object_mask(v)
    # the views held out whole are not fitted: the fit's map leaves them out too
    held = set(cfg.images.validation_views)
    fitted = [v for k, v in enumerate(views) if k not in held]
    return fitted, inverse_views.target_noise(fitted)


def main(argv: list[str] | None = None) -> int:

    ap = module_parser("neural_brdf.inverse.determined", __doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="+", help="scene XML files, or a config with target.images")
    ap.add_argument("-o", "--picture", help="write the (theta_h, theta_d) map as a PNG")
    ap.add_argument("--json", help="write the summary as JSON")
    ap.add_argument(
        "--reference",
        help="the reference material: a file holding one <bsdf> element (default: diffuse)",
    )
    ap.add_argument(
        "--noise",
        type=float,
        default=None,
        help=f"sigma^2 (default: a config's target images' own, else {NOMINAL_NOISE:g})",
    )
    ap.add_argument("--spp", type=int, default=SPP, help=f"rays per sampled pixel ({SPP})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variant", default=None, help=f"Mitsuba variant ({coverage.DEFAULT_VARIANT})")
    args = ap.parse_args(argv)
    if args.spp < 1:
        ap.error(f"--spp: must be >= 1, got {args.spp}")
    try:
        coverage.check_outputs(args.picture, args.json)
        reference = None
        if args.reference:
            try:
                reference = ET.parse(args.reference).getroot()
            except (OSError, ET.ParseError) as e:
                raise InputError(f"--reference {args.reference}: {e}") from None
            if reference.tag != "bsdf":
                raise InputError(f"--reference {args.reference}: the root is not a <bsdf>")
            coverage._use_variant(args.variant)
            # Mitsuba's own check of the element, before the views' work
            inverse_views.load_scene(Path(args.reference), inverse_views.bsdf_text(reference))
        scenes, noise = _inputs(args.inputs)
        info, message = assess(
            scenes,
            reference,
            args.noise if args.noise is not None else noise,
            picture=args.picture,
            role="reference",
            spp=args.spp,
            seed=args.seed,
            variant=args.variant,
        )
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(
        f"determined: {100 * info['figure']:.1f} % of the domain, "
        f"{100 * info['energy_figure']:.1f} % of the {info['reference']} reference's "
        f"light ({info['definition']})"
    )
    return coverage.cli_outputs(info, message, args.json)


if __name__ == "__main__":
    sys.exit(main())
