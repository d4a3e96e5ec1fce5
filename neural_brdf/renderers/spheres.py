"""Render-space metrics: a noise-free sphere under an environment, by quadrature.

    from neural_brdf.renderers import spheres
    ref = spheres.render(reference_fn)          # (R, R, 3) linear RGB
    fit = spheres.render(neural_brdf.load("model.onnx").eval)
    spheres.metrics(ref, fit)                   # {"psnr_db": ..., "flip": ...}

The scene is fixed: a unit sphere seen by an orthographic camera along -z, lit only by
a lat-long environment of ``ENV_HEIGHT`` x 2 ``ENV_HEIGHT`` texels (a sky gradient over a
darker ground, and a one-texel sun).  Each pixel's radiance is the sum over the texels
of f(wi, wo) L cos(theta_i) d omega, each texel a point light of its own solid angle, so
a render has no Monte-Carlo noise and two renders differ only where their BRDFs do.  A
BRDF narrower than a texel (about 5.6 degrees) is seen at the texel directions only,
the same directions for every BRDF compared; the metrics compare BRDFs in a render, not
renderings of a real scene.

Metrics (:func:`metrics`), over the sphere's pixels, after one exposure taken from the
reference (its mean over the sphere maps to 0.18):

* ``psnr_db``: PSNR of the sRGB display values, clipped to [0, 1];
* ``flip``: mean HDR-FLIP error (Andersson et al. 2020, 2021; NVIDIA's ``flip-evaluator``
  package) of the exposed linear images: a perceptual difference that accounts for
  colour, edges and the exposure range a viewer would use, 0 for identical images.

Only numpy (and ``flip-evaluator`` for ``flip``) is needed; any callable
``f(wi, wo) -> (N, 3)`` on numpy arrays is rendered, an exported model through
onnxruntime (:func:`neural_brdf.load`) or a reference function.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

RESOLUTION = 48  # pixels across the sphere
ENV_HEIGHT = 32  # environment texels from zenith to nadir (2 x as many around)
SUN = (40.0, 35.0, 400.0)  # elevation and azimuth (degrees), radiance of the sun texel
EXPOSURE_MEAN = 0.18  # the reference's mean over the sphere after the exposure
CHUNK = 1 << 19  # BRDF evaluations per call


def environment(height: int = ENV_HEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """The texels of the environment: world directions (K, 3) with +y up and +z toward
    the camera, and radiance times solid angle (K, 3)."""
    el = math.pi * (0.5 - (np.arange(height) + 0.5) / height)  # zenith -> nadir
    az = 2.0 * math.pi * (np.arange(2 * height) + 0.5) / (2 * height) - math.pi
    el, az = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)], -1)
    s = np.clip(np.sin(el), 0.0, 1.0)[..., None]
    sky = np.array([1.0, 0.95, 0.85]) * (1.0 - s) + np.array([0.25, 0.45, 0.9]) * s
    radiance = np.where(el[..., None] > 0.0, sky, np.array([0.18, 0.16, 0.14])) + 0.05
    sun_el, sun_az, sun_l = SUN
    i = int((0.5 - math.radians(sun_el) / math.pi) * height)
    j = int((math.radians(sun_az) + math.pi) / (2.0 * math.pi) * 2 * height)
    radiance[i, j] = sun_l
    d_omega = (math.pi / height) * (math.pi / height) * np.cos(el)  # (dtheta)(dphi) cos(el)
    return d.reshape(-1, 3), (radiance * d_omega[..., None]).reshape(-1, 3)


def sphere(resolution: int = RESOLUTION) -> tuple[np.ndarray, np.ndarray]:
    """The visible sphere: a mask (R, R) and, for its pixels, the local frames (P, 3, 3)
    whose rows are the tangent, the bitangent and the normal, in world coordinates."""
    c = (np.arange(resolution) + 0.5) / resolution * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)  # image rows run top (+y) to bottom
    mask = x * x + y * y < 1.0
    x, y = x[mask], y[mask]
    n = np.stack([x, y, np.sqrt(1.0 - x * x - y * y)], -1)
    t = np.stack([n[:, 2], np.zeros_like(x), -n[:, 0]], -1)  # (0, 1, 0) x n, never 0 here
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    b = np.cross(n, t)
    return mask, np.stack([t, b, n], 1)


def render(
    fn: Callable,
    *,
    resolution: int = RESOLUTION,
    env: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Render the sphere with the BRDF ``fn(wi, wo)`` (local frame, numpy (N, 3) float32 in,
    (N, 3) out): linear RGB (R, R, 3) float64, 0 off the sphere.  ``env``: directions and
    radiance times solid angle, as :func:`environment` returns (the default)."""
    mask, frames = sphere(resolution)
    dirs, light = environment() if env is None else env
    wo_world = np.array([0.0, 0.0, 1.0])
    cos_i = frames[:, 2] @ dirs.T  # (P, K)
    pix, tex = np.nonzero(cos_i > 0.0)  # only the texels above each pixel's horizon
    out = np.zeros((len(frames), 3))
    for s in range(0, len(pix), CHUNK):
        p, k = pix[s : s + CHUNK], tex[s : s + CHUNK]
        wi = np.einsum("pij,pj->pi", frames[p], dirs[k]).astype(np.float32)
        wo = (frames[p] @ wo_world).astype(np.float32)
        f = np.asarray(fn(wi, wo), dtype=np.float64).reshape(len(p), 3)
        np.add.at(out, p, f * light[k] * cos_i[p, k][:, None])
    img = np.zeros((resolution, resolution, 3))
    img[mask] = out
    return img


def _srgb(linear: np.ndarray) -> np.ndarray:
    # the sRGB transfer function (IEC 61966-2-1)
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def exposure(reference: np.ndarray) -> float:
    """The scale that maps the reference's mean over the sphere to ``EXPOSURE_MEAN``."""
    lit = reference[reference.any(-1)]
    mean = float(lit.mean()) if lit.size else 0.0
    return EXPOSURE_MEAN / mean if mean > 0.0 else 1.0


def display(linear: np.ndarray, scale: float) -> np.ndarray:
    """Exposed, clipped sRGB display values in [0, 1]."""
    return _srgb(linear * scale)


def metrics(reference: np.ndarray, test: np.ndarray) -> dict:
    """PSNR (dB, display values) and mean HDR-FLIP of ``test`` against ``reference`` over
    the sphere's pixels (those where the reference or the test is not 0), both exposed by
    :func:`exposure` of the reference."""
    import flip_evaluator

    if reference.shape != test.shape:
        raise ValueError(f"shapes differ: {reference.shape} and {test.shape}")
    scale = exposure(reference)
    mask = reference.any(-1) | test.any(-1)
    a, b = display(reference, scale)[mask], display(test, scale)[mask]
    mse = float(np.mean((a - b) ** 2))
    psnr = math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)
    err, _, _ = flip_evaluator.evaluate(
        np.ascontiguousarray(reference * scale, np.float32),
        np.ascontiguousarray(np.clip(test, 0.0, None) * scale, np.float32),
        "HDR",
        applyMagma=False,
        computeMeanError=False,
    )
    err = np.asarray(err)
    err = err.reshape(err.shape[0], err.shape[1], -1)[..., 0]
    return {"psnr_db": psnr, "flip": float(err[mask].mean())}
