"""Writing an RGL material for any ``f(wi, wo)``: its NDF, VNDF, luminance and RGB or
spectral tables (:func:`bake_fields`, :func:`bake`)."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from neural_brdf.errors import InputError
from neural_brdf.measured.rgl.brdf import RGLBRDF
from neural_brdf.measured.rgl.layout import (
    CHUNK,
    DEFAULTS,
    LUMINANCE_FLOOR,
    NDF_FLOOR,
    POWER_ITERATIONS,
    QUAD_U,
    SPECTRAL_SUFFIX,
    THETA_I_MAX,
    WAVELENGTHS,
    Y_WEIGHTS,
    Marginal2D,
    _spherical,
    phi_to_v,
    theta_to_u,
    u_to_theta,
    v_to_phi,
)
from neural_brdf.measured.rgl.tensor import (
    RGLFormatError,
    parse_tensor_file,
    tensor_file_bytes,
    write_tensor_file,
)


# -------------------------------------------------------------------- the writer
def _as_function(fn) -> Callable:
    if callable(fn):
        return fn
    if hasattr(fn, "eval"):
        return fn.eval
    raise TypeError(f"fn: expected a callable f(wi, wo) or an object with .eval, got {fn!r}")


def _call(f: Callable, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """f on (N, 3) float64 pairs in chunks -> (N, 3) float64, clamped at 0."""
    out = np.zeros((len(wi), 3))
    for s in range(0, len(wi), CHUNK):
        v = f(wi[s : s + CHUNK], wo[s : s + CHUNK])
        if hasattr(v, "detach"):  # a torch tensor
            v = v.detach().cpu().numpy()
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (len(wi[s : s + CHUNK]), 3):
            raise ValueError(
                f"fn: returned shape {v.shape}, expected ({len(wi[s : s + CHUNK])}, 3)"
            )
        if not np.all(np.isfinite(v)):
            raise ValueError("fn: non-finite values")
        out[s : s + CHUNK] = np.maximum(v, 0.0)
    return out


def _sigma_matrix(theta, u_nodes):
    """S (len(theta), len(u_nodes)) with sigma(theta) = S @ D_nodes, for D linear in u
    between nodes: int D(m) <w.m> dm, closed form over phi_m, midpoints in u."""
    uq = (np.arange(QUAD_U) + 0.5) / QUAD_U
    tq = u_to_theta(uq)
    # dm = sin(theta_m) d theta_m d phi_m, d theta_m = pi u du
    wq = np.sin(tq) * math.pi * uq / QUAD_U
    a = np.sin(theta)[:, None] * np.sin(tq)[None]  # <w.m> = a cos(phi) + b
    b = np.cos(theta)[:, None] * np.cos(tq)[None]
    ratio = np.divide(-b, a, out=np.full_like(a, -1.0), where=a > 0)
    phi0 = np.arccos(np.clip(ratio, -1.0, 1.0))  # <w.m> > 0 for |phi| < phi0
    g = 2.0 * (b * phi0 + a * np.sin(phi0))  # int max(0, a cos + b) dphi
    interp = np.zeros((QUAD_U, len(u_nodes)))  # D(uq) = interp @ D_nodes
    k = np.minimum(np.searchsorted(u_nodes, uq, side="right") - 1, len(u_nodes) - 2)
    t = (uq - u_nodes[k]) / (u_nodes[k + 1] - u_nodes[k])
    interp[np.arange(QUAD_U), k] = 1.0 - t
    interp[np.arange(QUAD_U), k + 1] = t
    return (g * wq[None]) @ interp


def retroreflection_ndf(f: Callable, *, nodes: int = DEFAULTS["ndf"]) -> np.ndarray:
    """D at the u nodes ``linspace(0, 1, nodes)`` (isotropic) from the back-scattering of
    ``f`` by the power iteration of Dupuy et al. 2015; int D cos(theta_m) dm = 1."""
    u = np.linspace(0.0, 1.0, nodes)
    theta = u_to_theta(u)
    w = _spherical(np.minimum(theta, THETA_I_MAX), np.zeros(nodes))
    f_bs = _call(f, w, w) @ Y_WEIGHTS
    s_mat = _sigma_matrix(theta, u)
    cos_mat = _sigma_matrix(np.zeros(1), u)  # int D cos(theta_m) dm
    d = np.ones(nodes)
    if not np.any(f_bs > 0):
        f_bs = np.ones(nodes)  # no retro-reflection: flat D
    for _ in range(POWER_ITERATIONS):
        d = f_bs * np.cos(theta) * (s_mat @ d)
        d = np.maximum(d, NDF_FLOOR * d.max())
        d /= (cos_mat @ d)[0]
    return d


def rgb_to_spectra(rgb, wavelengths=WAVELENGTHS) -> np.ndarray:
    """Linear sRGB values (..., 3) >= 0 -> spectra (..., L) at ``wavelengths`` (nm), by the
    sigmoid-polynomial upsampling of Jakob & Hanika 2019 ("A Low-Dimensional Function
    Space for Efficient Spectral Upsampling"), as Mitsuba upsamples RGB reflectances:
    s(l) = 1/2 + x / (2 sqrt(1 + x^2)), x = c0 l^2 + c1 l + c2, with (c0, c1, c2) from
    Mitsuba's precomputed table (``srgb_model_fetch``, so this needs Mitsuba 3).  The
    table covers [0, 1]^3; every value v is upsampled as max(v) s(v / max(v)), which is
    linear in the magnitude: nodes of one chromaticity (a Lambertian, a grey conductor)
    get proportional spectra, so that interpolating spectra between nodes is
    interpolating the RGB values.  The sRGB colour of max(v) s(v / max(v)) is v to the
    accuracy of the table.  0 stays 0."""
    try:
        import mitsuba

        variant: Any = mitsuba.scalar_spectral  # a variant module: untyped attributes
        fetch = variant.srgb_model_fetch
        color = variant.ScalarColor3f
    except (ImportError, AttributeError):
        raise InputError(
            "a spectral .bsdf needs Mitsuba 3 (its Jakob-Hanika RGB-to-spectrum "
            "table): pip install mitsuba"
        ) from None
    rgb = np.asarray(rgb, dtype=np.float64)
    flat = np.maximum(rgb.reshape(-1, 3), 0.0)
    scale = flat.max(axis=-1)
    unit = flat / np.where(scale > 0, scale, 1.0)[:, None]
    keys, inverse = np.unique(np.round(unit, 6), axis=0, return_inverse=True)
    coef = np.array([list(fetch(color(*k))) for k in keys])[inverse.reshape(-1)]
    lam = np.asarray(wavelengths, dtype=np.float64)
    x = coef[:, :1] * lam**2 + coef[:, 1:2] * lam + coef[:, 2:3]
    spec = (0.5 + x / (2.0 * np.sqrt(1.0 + x * x))) * scale[:, None]
    spec[flat.max(axis=-1) == 0] = 0.0
    return spec.reshape(rgb.shape[:-1] + (len(lam),))


def theta_i_nodes(n: int) -> np.ndarray:
    """The incident elevations of a bake: THETA_I_MAX sin(pi/2 t), t uniform in [0, 1]:
    denser towards grazing, where f changes fastest with theta_i (32 slices: 4.5 degrees
    apart at normal incidence, 0.1 at the last).  Measured against slices linear in theta
    (default resolutions, rel. RMSE of f cos): GGX alpha 0.1 1.04% -> 0.28%, Lambertian
    and GGX 0.3 gold unchanged (their error is within the slices, near the horizon)."""
    return THETA_I_MAX * np.sin(0.5 * math.pi * np.linspace(0.0, 1.0, n))


def bake_fields(
    fn,
    *,
    theta_i: int = DEFAULTS["theta_i"],
    sample: int = DEFAULTS["sample"],
    vndf: int = DEFAULTS["vndf"],
    ndf: int = DEFAULTS["ndf"],
    spectral: bool = False,
    cosine: str = "outgoing",
    description: str = "neural-brdf bake",
) -> dict[str, Any]:
    """The fields of an isotropic RGL file for ``fn(wi, wo)`` ((N, 3) numpy in, (N, 3)
    out, 1/sr).  ``theta_i`` slices, ``sample`` x ``sample`` value nodes, ``vndf`` x
    ``vndf`` VNDF nodes, ``ndf`` nodes along theta of the NDF and sigma tables.
    ``spectral``: ``spectra`` + ``wavelengths`` (for Mitsuba's spectral variants, by
    :func:`rgb_to_spectra`) instead of ``rgb`` (for its RGB variants).

    ``cosine``: the foreshortening factor stored in the value.  ``"outgoing"`` (Mitsuba's
    ``measured``: its eval, which includes the cosine, is the stored product, so the value
    is f cos(theta_o) of the direction reflected about m); ``"incident"`` (pbrt-v4's
    MeasuredBxDF divides the product by cos(theta_i) of the slice direction, its light
    direction, so the value must be f cos(theta_i) there).  For a reciprocal f the two
    files differ by the factor cos(theta_i) / cos(theta_o) at every node."""
    if cosine not in ("outgoing", "incident"):
        raise ValueError(f"cosine: must be 'outgoing' or 'incident', got {cosine!r}")
    f = _as_function(fn)
    for name, v, lo in (
        ("theta_i", theta_i, 2),
        ("sample", sample, 2),
        ("vndf", vndf, 2),
        ("ndf", ndf, 2),
    ):
        if int(v) < lo:
            raise ValueError(f"{name}: must be >= {lo}, got {v!r}")
    d_nodes = retroreflection_ndf(f, nodes=ndf)
    u_nodes = np.linspace(0.0, 1.0, ndf)
    sigma_nodes = _sigma_matrix(u_to_theta(u_nodes), u_nodes) @ d_nodes
    ndf_table = np.tile(d_nodes, (2, 1)).astype(np.float32)  # rows: phi (constant)
    sigma_table = np.tile(sigma_nodes, (2, 1)).astype(np.float32)
    ndf_map = Marginal2D(ndf_table, normalize=False)
    sigma_map = Marginal2D(sigma_table, normalize=False)

    thetas = theta_i_nodes(theta_i).astype(np.float32)
    # the VNDF table on the m square: D(m) <wi.m> 2 pi^2 u sin(theta_m) (density in u)
    ux, vy = np.meshgrid(np.linspace(0, 1, vndf), np.linspace(0, 1, vndf))  # [row, col]
    m_grid = _spherical(u_to_theta(ux), v_to_phi(vy))
    d_grid = ndf_map.eval(np.stack([ux.ravel(), vy.ravel()], -1)).reshape(ux.shape)
    jac_grid = 2 * math.pi**2 * ux * np.sin(u_to_theta(ux))
    sx, sy = np.meshgrid(np.linspace(0, 1, sample), np.linspace(0, 1, sample))
    s_nodes = np.stack([sx.ravel(), sy.ravel()], -1)

    vndf_t = np.zeros((1, theta_i, vndf, vndf), np.float32)
    lum_t = np.zeros((1, theta_i, sample, sample), np.float32)
    rgb_t = np.zeros((1, theta_i, 3, sample, sample), np.float32)
    for k, th in enumerate(thetas.astype(np.float64)):
        wi1 = _spherical(np.array(th), np.array(0.0))
        vis = np.maximum(m_grid @ wi1, 0.0)
        vndf_t[0, k] = (d_grid * vis * jac_grid).astype(np.float32)
        warp = Marginal2D(vndf_t[0, k])  # as Mitsuba builds the slice
        u_m, _ = warp.sample(s_nodes)
        m = _spherical(u_to_theta(u_m[:, 0]), v_to_phi(u_m[:, 1]))
        wi = np.broadcast_to(wi1, m.shape)
        wo = 2.0 * (m @ wi1)[:, None] * m - wi
        above = wo[:, 2] > 0
        rho = np.zeros((len(m), 3))
        if above.any():
            wo_a = wo[above] / np.linalg.norm(wo[above], axis=-1, keepdims=True)
            val = _call(f, np.ascontiguousarray(wi[above]), wo_a)
            val *= wo_a[:, 2:3] if cosine == "outgoing" else wi1[2]
            u_wi = np.array([[theta_to_u(th), phi_to_v(0.0)]])
            ratio = 4.0 * sigma_map.eval(u_wi)[0] / ndf_map.eval(u_m[above])
            rho[above] = val * ratio[:, None]
        rgb_t[0, k] = np.moveaxis(rho.reshape(sample, sample, 3), -1, 0)
        y = rho.reshape(sample, sample, 3) @ Y_WEIGHTS
        y = np.maximum(y, LUMINANCE_FLOOR * y.max()) if y.max() > 0 else np.ones_like(y)
        lum_t[0, k] = y
    out = {
        "description": description,
        "jacobian": np.array([1], np.uint8),
        "theta_i": thetas,
        "phi_i": np.zeros(1, np.float32),
        "ndf": ndf_table,
        "sigma": sigma_table,
        "vndf": vndf_t,
        "luminance": lum_t,
    }
    if spectral:
        spec = rgb_to_spectra(np.moveaxis(rgb_t, 2, -1))  # (1, T, N, N, L)
        out["spectra"] = np.moveaxis(spec, -1, 2).astype(np.float32)
        out["wavelengths"] = WAVELENGTHS.astype(np.float32)
    else:
        out["rgb"] = rgb_t
    return out


def bake(fn, path, *, spectral: bool | None = None, **options) -> RGLBRDF | None:
    """:func:`bake_fields`, written to ``path`` atomically.  ``spectral=None``: spectral
    when the name ends in ``_spec.bsdf`` (the RGL database's convention), else RGB.
    Returns the baked material (an RGB file; None for a spectral one, which
    :class:`RGLBRDF` does not read)."""
    if spectral is None:
        spectral = os.fspath(path).lower().endswith(SPECTRAL_SUFFIX)
    fields = bake_fields(fn, spectral=spectral, **options)
    baked = None
    if not spectral:  # what the reader refuses is not written (a value above MAX_VALUE)
        try:
            baked = RGLBRDF(parse_tensor_file(tensor_file_bytes(fields)), source=os.fspath(path))
        except RGLFormatError as e:
            raise RGLFormatError(f"{e} (not written: a reader refuses it)") from None
    write_tensor_file(path, fields)
    return baked
