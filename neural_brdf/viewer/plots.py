"""The figures of a run report, in the habits of BRDF Explorer: arrays in, figures out.

    from neural_brdf import load
    from neural_brdf.viewer import plots
    fig = plots.incidence_slices(load("model.onnx").eval, reference.eval)
    png = plots.png_bytes(fig)

Every plot takes the model as a callable ``f(wi, wo) -> (N, 3)`` on numpy arrays (an
exported model's ``eval``, an analytic model's ``eval``) and optionally a reference
callable, drawn dashed over the model (solid).  The figures:

* :func:`incidence_slices`: f cos(theta_o) in the incidence plane (the x-z plane) at
  several theta_i, log scale, per RGB channel.  theta_o is signed: wi lies at negative
  angles, the mirror direction at +theta_i.
* :func:`polar_lobes`: the same slices of the luminance as polar lobes, the radius
  log-compressed so that the dim tails stay visible beside the peak.
* :func:`rusinkiewicz_images`: (theta_h, theta_d) images at phi_d = 90 deg, as in BRDF
  Explorer and the MERL papers: log10 of the luminance of f, and the relative error.
* :func:`albedo_curve`: the directional albedo rho(theta_i) = int f cos dwo per channel,
  by the MIS quadrature of :mod:`neural_brdf.physics.quadrature`, with the furnace limit 1.
* :func:`loss_curve`: training loss and held-out relative RMSE against the step.
* :func:`spheres`: a Mitsuba 3 render of the model (and reference) on spheres.

The figures are built with matplotlib's object API (``Figure``, no pyplot): nothing
global, no window, and PNG output through the Agg canvas, so it runs headless.
"""

from __future__ import annotations

import importlib
import io
import math
from collections.abc import Callable

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from neural_brdf.measured import merl
from neural_brdf.physics import quadrature

Fn = Callable[[np.ndarray, np.ndarray], np.ndarray]

THETA_I_DEG = (0.0, 30.0, 60.0, 80.0)  # incidence angles of the slices and lobes
GRAZING_DEG = 89.5  # slices stop here: f cos -> 0 at 90 deg, which log scales cannot show
DYNAMIC_RANGE = 1e-4  # log axes show at most this fraction of the peak
LOBE_COMPRESSION = 100.0  # polar radius log10(1 + C x / max) / log10(1 + C): C sets the knee
REL_ERROR_RANGE = (1e-3, 1.0)  # colour range of the relative-error image
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 weights of linear RGB
CHANNELS = (("R", "tab:red"), ("G", "tab:green"), ("B", "tab:blue"))
DPI = 100


def luminance(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, dtype=np.float64) @ LUMINANCE


def png_bytes(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _eval(fn: Fn, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """fn on flattened pairs, float64, shape (..., 3)."""
    out = np.asarray(fn(wi.reshape(-1, 3), wo.reshape(-1, 3)), dtype=np.float64)
    return out.reshape(wi.shape[:-1] + (3,))


def _positive(x: np.ndarray) -> np.ndarray:
    """NaN where x <= 0, so that log axes leave gaps instead of warning."""
    return np.where(x > 0, x, np.nan)


# ------------------------------------------------------------------ incidence plane
def incidence_plane(theta_i_deg: float, n: int = 361) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta_o_deg (n,), wi (3,), wo (n, 3)) in the x-z plane; wi at -theta_i, the mirror
    direction at theta_o = +theta_i."""
    ti = math.radians(theta_i_deg)
    wi = np.array([-math.sin(ti), 0.0, math.cos(ti)])
    theta_o = np.linspace(-GRAZING_DEG, GRAZING_DEG, n)
    t = np.radians(theta_o)
    wo = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], -1)
    return theta_o, wi, wo


def slice_values(fn: Fn, theta_i_deg: float, n: int = 361) -> tuple[np.ndarray, np.ndarray]:
    """(theta_o_deg (n,), f cos(theta_o) (n, 3)) in the incidence plane."""
    theta_o, wi, wo = incidence_plane(theta_i_deg, n)
    f = _eval(fn, np.broadcast_to(wi, wo.shape), wo)
    return theta_o, f * wo[:, 2:3]


def incidence_slices(neural: Fn, reference: Fn | None = None, *, theta_i_deg=THETA_I_DEG) -> Figure:
    cols = 2
    rows = math.ceil(len(theta_i_deg) / cols)
    fig = Figure(figsize=(10, 3.2 * rows), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax, ti in zip(axes.flat, theta_i_deg):
        x, y = slice_values(neural, ti)
        curves = [y]
        for c, (name, colour) in enumerate(CHANNELS):
            ax.plot(x, _positive(y[:, c]), color=colour, lw=2.4, alpha=0.5, label=f"neural {name}")
        if reference is not None:
            _, r = slice_values(reference, ti)
            curves.append(r)
            for c, (name, colour) in enumerate(CHANNELS):
                ax.plot(
                    x,
                    _positive(r[:, c]),
                    color=colour,
                    lw=1.0,
                    ls=(0, (4, 3)),
                    label=f"reference {name}",
                )
        top = max(float(np.nanmax(v)) for v in curves)
        ax.set_yscale("log")
        if top > 0:
            ax.set_ylim(top * DYNAMIC_RANGE, top * 2.0)
        ax.axvline(ti, color="0.6", lw=0.8, ls=":")
        ax.set_xlim(-90, 90)
        ax.set_xticks(range(-90, 91, 30))
        ax.set_title(f"θi = {ti:g}°  (mirror direction dotted)", fontsize=10)
        ax.set_xlabel("θo in the incidence plane [deg]")
        ax.set_ylabel("f cos θo [1/sr]")
        ax.grid(True, which="major", alpha=0.3)
    for ax in list(axes.flat)[len(theta_i_deg) :]:
        ax.set_visible(False)
    _legend(fig, axes.flat[0], reference is not None)
    return fig


def _legend(fig: Figure, ax, with_reference: bool) -> None:
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(
        handles,
        labels,
        loc="outside upper center",
        ncols=6 if with_reference else 3,
        fontsize=9,
        frameon=False,
    )


# ------------------------------------------------------------------ polar lobes
def polar_lobes(neural: Fn, reference: Fn | None = None, *, theta_i_deg=THETA_I_DEG) -> Figure:
    """Luminance of f cos in the incidence plane as polar curves; radius
    log10(1 + C x / peak) / log10(1 + C) with the peak over all curves."""
    series = []
    for ti in theta_i_deg:
        x, y = slice_values(neural, ti)
        r = slice_values(reference, ti)[1] if reference is not None else None
        series.append((ti, x, luminance(y), None if r is None else luminance(r)))
    peak = max(max(np.nanmax(s[2]), 0.0 if s[3] is None else np.nanmax(s[3])) for s in series)
    peak = peak if peak > 0 else 1.0

    def radius(v):
        return np.log10(1.0 + LOBE_COMPRESSION * np.clip(v, 0.0, None) / peak) / math.log10(
            1.0 + LOBE_COMPRESSION
        )

    fig = Figure(figsize=(9, 4.4), layout="constrained")
    ax = fig.add_subplot()
    _polar_grid(ax)
    colours = colormaps["viridis"](np.linspace(0.0, 0.85, len(series)))
    for (ti, x, y, r), colour in zip(series, colours):
        t = np.radians(x)
        ax.plot(
            radius(y) * np.sin(t),
            radius(y) * np.cos(t),
            color=colour,
            lw=2.4,
            alpha=0.6,
            label=f"θi = {ti:g}°",
        )
        if r is not None:
            ax.plot(
                radius(r) * np.sin(t), radius(r) * np.cos(t), color="black", lw=0.9, ls=(0, (4, 3))
            )
        a = math.radians(ti)
        ax.plot([0.0, -1.05 * math.sin(a)], [0.0, 1.05 * math.cos(a)], color=colour, lw=0.9, ls=":")
    ax.set_title(
        "luminance x of f cos θo in the incidence plane: neural solid, reference "
        "dashed black, wi dotted\nradius log10(1 + 100 x / peak) / log10(101)",
        fontsize=10,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=9, frameon=False)
    return fig


def _polar_grid(ax) -> None:
    """A half disc drawn on Cartesian axes (matplotlib's polar axes keep the room of a
    full disc): rings of radius 0.25..1, spokes every 30 deg from the normal."""
    t = np.linspace(-0.5 * math.pi, 0.5 * math.pi, 181)
    for r in (0.25, 0.5, 0.75, 1.0):
        ax.plot(r * np.sin(t), r * np.cos(t), color="0.8" if r < 1 else "0.3", lw=0.7)
        ax.text(-r, -0.02, f"{r:g}", ha="center", va="top", fontsize=7, color="0.4")
    for deg in range(-90, 91, 30):
        a = math.radians(deg)
        ax.plot([0.0, math.sin(a)], [0.0, math.cos(a)], color="0.8", lw=0.7)
        ax.text(
            1.08 * math.sin(a), 1.08 * math.cos(a), f"{deg}°", ha="center", va="center", fontsize=9
        )
    ax.set_aspect("equal")
    ax.set_xlim(-1.15, 1.15)
    ax.set_ylim(-0.08, 1.15)
    ax.axis("off")


# ------------------------------------------------------------------ (theta_h, theta_d)
def rusinkiewicz_grid(n: int = 128, phi_d_deg: float = 90.0):
    """(wi, wo) of shape (n, n, 3): rows theta_d, columns theta_h, both on [0, 90) deg,
    phi_h = 0.  Pixel centres, so no pair sits exactly on the horizon."""
    a = (np.arange(n) + 0.5) * (0.5 * math.pi / n)
    th, td = np.meshgrid(a, a)  # (n, n): [row = theta_d, col = theta_h]
    return merl.directions(th, 0.0, td, math.radians(phi_d_deg))


def rusinkiewicz_values(fn: Fn, n: int = 128) -> np.ndarray:
    """Luminance of f on :func:`rusinkiewicz_grid`, NaN where a direction is below the
    horizon (outside the domain)."""
    wi, wo = rusinkiewicz_grid(n)
    y = luminance(_eval(fn, wi, wo))
    return np.where((wi[..., 2] > 0) & (wo[..., 2] > 0), y, np.nan)


def relative_error(model: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """|model - reference| / reference; NaN where the reference is not positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(reference > 0, np.abs(model - reference) / reference, np.nan)


def rusinkiewicz_images(neural: Fn, reference: Fn | None = None, *, n: int = 128) -> Figure:
    y = rusinkiewicz_values(neural, n)
    images = [("neural", y)]
    if reference is not None:
        images.append(("reference", rusinkiewicz_values(reference, n)))
    logs = [np.log10(_positive(v)) for _, v in images]
    hi = max(float(np.nanmax(v)) for v in logs)
    lo = max(min(float(np.nanmin(v)) for v in logs), hi + math.log10(DYNAMIC_RANGE))
    panels = len(images) + (reference is not None)
    fig = Figure(figsize=(4.1 * panels, 3.9), layout="constrained")
    axes = fig.subplots(1, panels, squeeze=False)[0]
    cmap = colormaps["magma"].with_extremes(bad="0.85")
    extent = (0.0, 90.0, 0.0, 90.0)
    for ax, (name, _), v in zip(axes, images, logs):
        im = ax.imshow(
            v, origin="lower", extent=extent, cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest"
        )
        ax.set_title(f"{name}: log10 luminance of f", fontsize=10)
    fig.colorbar(im, ax=list(axes[: len(images)]), shrink=0.85, label="log10 f [1/sr]")
    if reference is not None:
        err = relative_error(images[0][1], images[1][1])
        err = np.clip(err, *REL_ERROR_RANGE)
        im = axes[-1].imshow(
            err,
            origin="lower",
            extent=extent,
            interpolation="nearest",
            cmap=colormaps["viridis"].with_extremes(bad="0.85"),
            norm=LogNorm(*REL_ERROR_RANGE),
        )
        axes[-1].set_title("relative error |neural - ref| / ref", fontsize=10)
        fig.colorbar(im, ax=axes[-1], shrink=0.85, label="relative error")
    axes[0].set_ylabel("θd [deg]")
    for ax in axes:
        ax.set_xlabel("θh [deg]")
        ax.set_xticks(range(0, 91, 30))
        ax.set_yticks(range(0, 91, 30))
    fig.suptitle("(θh, θd) slice at φd = 90°, φh = 0 (grey: no value)", fontsize=10)
    return fig


# ------------------------------------------------------------------ albedo
def albedo_values(
    fn: Fn,
    theta_i_deg: np.ndarray,
    *,
    samples: int = 4096,
    seed: int = 0,
    sampler=None,
    azimuths: int = 0,
) -> np.ndarray:
    """rho(theta_i) (len, 3) by the MIS quadrature of :mod:`neural_brdf.physics.quadrature`;
    ``sampler`` (an analytic model) adds its importance sampler to the proposals.  With
    ``azimuths`` > 0, averaged over that many azimuths of wi (``quadrature.albedo_at``):
    what the validator's furnace measures (and metrics.json's furnace.curve holds) for an
    anisotropic model."""
    return quadrature.albedo_at(
        fn, theta_i_deg, samples, seed=seed, target=sampler, azimuths=azimuths
    )


def albedo_theta(n_theta: int = 46) -> np.ndarray:
    """The incidences of :func:`albedo_curve`, deg: [0, 89.9]."""
    return np.linspace(0.0, 89.9, n_theta)


def albedo_curve(
    neural: Fn,
    reference: Fn | None = None,
    *,
    n_theta: int = 46,
    samples: int = 4096,
    sampler=None,
    validated_max: tuple[float, float] | None = None,
    values: dict | None = None,
    measured: tuple[np.ndarray, np.ndarray] | None = None,
    azimuths: int = 0,
) -> Figure:
    """rho(theta_i) per channel, theta_i on [0, 89.9] deg; ``validated_max`` =
    (theta_deg, value) marks the validator's measured maximum.  ``values``, a dict, is
    filled with "theta" and the curves ("neural", "reference"), numpy arrays, for a
    caller that shows them elsewhere too (the report's viewer) without a second
    quadrature.  ``measured`` = (theta_deg, rho) is the neural curve as the validator
    measured it (metrics.json furnace.curve), drawn instead of a new quadrature.

    Both curves are in the incidence plane (wi in the x-z plane), except with
    ``azimuths`` > 0: both averaged over that many azimuths of wi (the validator's furnace
    of an anisotropic model; the reference then at the measured curve's incidences)."""
    theta = albedo_theta(n_theta)
    fig = Figure(figsize=(7, 4), layout="constrained")
    ax = fig.subplots()
    if measured is not None:
        theta_n, rho = (np.asarray(x, dtype=np.float64) for x in measured)
    elif azimuths > 0:
        theta_n = theta
        rho = albedo_values(neural, theta, samples=samples, sampler=sampler, azimuths=azimuths)
    else:
        theta_n, rho = theta, albedo_values(neural, theta, samples=samples, sampler=sampler)
    if values is not None:
        values.update(theta=theta, neural_theta=theta_n, neural=rho)
    for c, (name, colour) in enumerate(CHANNELS):
        ax.plot(theta_n, rho[:, c], color=colour, lw=2.4, alpha=0.5, label=f"neural {name}")
    if reference is not None:
        if azimuths > 0:  # like the neural curve: at its incidences, over azimuth
            theta = theta_n
        ref = albedo_values(reference, theta, samples=samples, sampler=sampler, azimuths=azimuths)
        if values is not None:
            values.update(reference=ref, reference_theta=theta)
        for c, (name, colour) in enumerate(CHANNELS):
            ax.plot(
                theta, ref[:, c], color=colour, lw=1.0, ls=(0, (4, 3)), label=f"reference {name}"
            )
    ax.axhline(1.0, color="black", lw=1.0, ls=":", label="furnace limit 1")
    if validated_max is not None:
        ax.plot(
            [validated_max[0]],
            [validated_max[1]],
            "kx",
            ms=8,
            label=f"validator max {validated_max[1]:.4f}",
        )
    ax.set_xlim(0, 90)
    ax.set_xticks(range(0, 91, 15))
    ax.set_ylim(0.0, max(1.1, float(np.nanmax(rho)) * 1.05))
    ax.set_xlabel("θi [deg]")
    ax.set_ylabel("directional albedo ρ(θi)")
    ax.set_title("directional albedo ∫ f cos θo dωo (white furnace)", fontsize=10)
    ax.grid(True, alpha=0.3)
    # beside the axes: inside, some corner holds data (a measured or teacher's curve
    # falls towards grazing, a furnace near 1 fills the top)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return fig


# ------------------------------------------------------------------ training
def loss_curve(
    step: np.ndarray, loss: np.ndarray, val_step: np.ndarray, val_rel_rmse: np.ndarray
) -> Figure:
    """Training loss (left, log) and the held-out relative RMSE of f cos (right, %)."""
    fig = Figure(figsize=(7, 4), layout="constrained")
    ax = fig.subplots()
    ax.plot(
        step,
        _positive(np.asarray(loss, dtype=np.float64)),
        color="tab:blue",
        lw=1.4,
        label="training loss",
    )
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss", color="tab:blue")
    ax.grid(True, alpha=0.3)
    handles = ax.get_legend_handles_labels()
    if len(val_step):
        ax2 = ax.twinx()
        ax2.plot(
            val_step,
            100.0 * np.asarray(val_rel_rmse),
            "o-",
            color="tab:orange",
            lw=1.4,
            ms=5,
            label="held-out rel. RMSE of f cos",
        )
        ax2.set_ylabel("rel. RMSE [%]", color="tab:orange")
        ax2.set_ylim(bottom=0.0)
        h2 = ax2.get_legend_handles_labels()
        handles = (handles[0] + h2[0], handles[1] + h2[1])
    ax.legend(*handles, fontsize=8, loc="upper right", frameon=False)
    ax.set_title("training", fontsize=10)
    return fig


# ------------------------------------------------------------------ Mitsuba
def mitsuba_unavailable() -> str | None:
    """None when Mitsuba 3 can render here, else the reason (one line)."""
    try:
        import mitsuba as mi

        if mi.variant() is None:
            mi.set_variant("llvm_ad_rgb")
        importlib.import_module("neural_brdf.renderers.render")  # registers the plugins
    except ImportError as e:
        return f"Mitsuba 3 is not available ({e}); install the mitsuba extra and libllvm19"
    return None


def spheres(
    model_path,
    out_png,
    *,
    reference: dict | None = None,
    reference_bsdf=None,
    spp: int = 16,
    resolution: int = 128,
) -> float | None:
    """Render the model (and an analytic ``reference`` = {"model", "params"}, or a Mitsuba
    BSDF object ``reference_bsdf``: a textured teacher's) on the Mitsuba preview scene
    into ``out_png``; returns the PSNR against the reference.  Call
    :func:`mitsuba_unavailable` first."""
    from neural_brdf.renderers.render import render_preview

    return render_preview(
        model_path,
        out_png,
        reference=reference,
        reference_bsdf=reference_bsdf,
        spp=spp,
        resolution=resolution,
    )
