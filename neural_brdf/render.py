"""The material-preview render of exported BRDFs in Mitsuba 3: scene, PNG, PSNR.

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from neural_brdf.render import render_preview
    psnr = render_preview("model.onnx", "preview.png",
                          reference={"model": "microfacet", "params": {"alpha": 0.3}})

Importing this module needs a Mitsuba variant to be set already; it imports
:mod:`neural_brdf.mitsuba`, which registers the ``neural_brdf`` and ``analytic_brdf``
plugins that the scenes use.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import mitsuba as mi
import numpy as np

from .config import InputError
from .fileio import atomic_path
from .mitsuba import read_model


def sky_bitmap(height: int = 64) -> np.ndarray:
    """A procedural lat-long environment (H, 2H, 3): a sky gradient over a dark ground.

    Rows run from the zenith (+y, Mitsuba's envmap up axis) to the nadir."""
    v = (np.arange(height) + 0.5) / height
    elev = (0.5 - v)[:, None] * math.pi  # (H, 1)
    horizon = np.array([1.0, 0.95, 0.85])
    zenith = np.array([0.25, 0.45, 0.9])
    ground = np.array([0.18, 0.16, 0.14])
    s = np.clip(np.sin(elev), 0.0, 1.0)[..., None]
    sky = horizon * (1.0 - s) + zenith * s
    img = np.where(elev[..., None] > 0, sky, ground)
    img = np.broadcast_to(img, (height, 2 * height, 3)) + 0.05  # a constant fill
    return np.ascontiguousarray(img, dtype=np.float32)


def preview_scene(
    bsdf: dict, *, resolution: int = 256, spp: int = 64, max_depth: int = 8, seed: int = 0
) -> dict:
    """The material-preview scene (a dict for ``mi.load_dict``): two spheres with ``bsdf``
    on a grey checkerboard floor, under :func:`sky_bitmap` and a directional key light."""
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": {
            "type": "perspective",
            "fov": 32.0,
            "to_world": T().look_at(
                origin=[0.0, 1.6, 6.5], target=[0.2, 0.1, 0.0], up=[0.0, 1.0, 0.0]
            ),
            "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
            "film": {
                "type": "hdrfilm",
                "width": resolution,
                "height": resolution,
                "rfilter": {"type": "gaussian"},
            },
        },
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap()), "scale": 1.0},
        "key": {
            "type": "directional",
            "direction": [-0.6, -1.0, -0.5],
            "irradiance": {"type": "rgb", "value": [2.5, 2.4, 2.2]},
        },
        "big": {"type": "sphere", "center": [-0.3, 0.0, 0.0], "radius": 1.0, "bsdf": bsdf},
        "small": {"type": "sphere", "center": [1.35, -0.5, 0.9], "radius": 0.5, "bsdf": bsdf},
        "floor": {
            "type": "rectangle",
            "to_world": T().translate([0.0, -1.0, 0.0]).rotate([1.0, 0.0, 0.0], -90.0).scale(8.0),
            "bsdf": {
                "type": "diffuse",
                "reflectance": {
                    "type": "checkerboard",
                    "color0": {"type": "rgb", "value": 0.25},
                    "color1": {"type": "rgb", "value": 0.5},
                    "to_uv": mi.ScalarTransform4f().scale([8.0, 8.0, 1.0]),
                },
            },
        },
    }


def render_scene(bsdf: dict, *, resolution: int = 256, spp: int = 64, seed: int = 0) -> np.ndarray:
    """Render :func:`preview_scene` with ``bsdf``; linear RGB (H, W, 3) float32."""
    scene = mi.load_dict(preview_scene(bsdf, resolution=resolution, spp=spp, seed=seed))
    img = mi.render(scene, spp=spp, seed=seed)
    return np.asarray(img, dtype=np.float32)[..., :3]


def to_display(linear: np.ndarray) -> np.ndarray:
    """Linear RGB -> sRGB display values in [0, 1] (Mitsuba's own conversion)."""
    bmp = mi.Bitmap(np.ascontiguousarray(np.clip(linear, 0.0, None), dtype=np.float32))
    srgb = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=True)
    return np.clip(np.asarray(srgb), 0.0, 1.0)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two display images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


# The error map shows |neural - reference| (display values, channel mean) times this.
ERROR_GAIN = 10.0


def write_png(path: Path, img: np.ndarray) -> None:
    import matplotlib.image

    with atomic_path(path, suffix=".png", parents=True) as tmp:
        matplotlib.image.imsave(tmp, np.clip(img, 0.0, 1.0))


def analytic_bsdf(reference: dict) -> dict:
    """The ``analytic_brdf`` plugin dict of an analytic target (``{"model": name,
    "params": {...}}``, as in a training config)."""
    if "model" not in reference:
        raise InputError(
            f"reference: expected {{'model': name, 'params': {{...}}}}, got {reference!r}"
        )
    return {
        "type": "analytic_brdf",
        "model": reference["model"],
        "params": json.dumps(reference.get("params") or {}),
    }


def side_by_side(neural: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Display images -> neural | reference | error map (|difference| of display values,
    channel mean, x ERROR_GAIN, 'inferno' colours), with thin white gaps."""
    import matplotlib

    err = np.abs(neural - ref).mean(-1) * ERROR_GAIN
    err_rgb = matplotlib.colormaps["inferno"](np.clip(err, 0.0, 1.0))[..., :3]
    gap = np.ones((neural.shape[0], max(2, neural.shape[0] // 64), 3))
    return np.concatenate([neural, gap, ref, gap, err_rgb], axis=1)


def render_preview(
    onnx_path, out_png, *, reference: dict | None = None, spp: int = 64, resolution: int = 256
) -> float | None:
    """Render the neural BRDF in the preview scene and write ``out_png``.

    With ``reference`` (an analytic target, see :func:`analytic_bsdf`) the PNG is
    :func:`side_by_side` and the PSNR (dB, sRGB display values) of neural against
    reference is returned; otherwise None.
    """
    path, _, _ = read_model(onnx_path)
    ref_bsdf = None if reference is None else analytic_bsdf(reference)
    neural = to_display(
        render_scene({"type": "neural_brdf", "filename": str(path)}, resolution=resolution, spp=spp)
    )
    if ref_bsdf is None:
        write_png(Path(out_png), neural)
        return None
    ref = to_display(render_scene(ref_bsdf, resolution=resolution, spp=spp))
    write_png(Path(out_png), side_by_side(neural, ref))
    return psnr(neural, ref)
