"""The material-preview render of exported BRDFs in Mitsuba 3: scene, PNG, PSNR.

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from neural_brdf.renderers.render import render_comparison, render_preview
    psnr = render_preview("model.onnx", "preview.png",
                          reference={"model": "microfacet", "params": {"alpha": 0.3}})
    info = render_comparison("model.onnx", "preview.png", reference=...)  # gain: adaptive

The PNG with a reference holds three labelled panels: "neural", "target" and
"|difference| x K", the absolute difference of the display values times K.  K is fixed
(``gain=ERROR_GAIN``, the report's render) or chosen so that the 99th percentile of the
difference maps to 1 (``gain=None``, ``neural-brdf render``): a good model's difference
is a few per cent, black at any fixed gain that also suits a poor one.

Importing this module needs a Mitsuba variant to be set already; it imports
:mod:`neural_brdf.renderers.mitsuba`, which registers the ``neural_brdf`` and ``analytic_brdf``
plugins that the scenes use.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import mitsuba as mi
import numpy as np

from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_path
from neural_brdf.renderers.mitsuba import read_model


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
    img = mi.render(scene, spp=spp, seed=seed)  # type: ignore[arg-type]  # int is a UInt32
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


# The error map shows |neural - reference| (display values, channel mean) times this
# (render_preview's default, the report's render; neural-brdf render adapts it).
ERROR_GAIN = 10.0
GAIN_PERCENTILE = 99.0  # an adaptive gain maps this percentile of the difference to 1


# Image files a render writes, by the output's extension: suffix -> matplotlib format.
IMAGE_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg"}


def image_format(path: str | Path) -> str:
    """The format of an output image by its extension (InputError for any other)."""
    fmt = IMAGE_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        known = ", ".join(IMAGE_FORMATS)
        raise InputError(
            f"{path}: unknown image extension {Path(path).suffix or '(none)'!r}; known: {known}"
        )
    return fmt


def write_png(path: Path, img: np.ndarray) -> None:
    """Write ``img`` (display values in [0, 1]) atomically, as PNG or JPEG by the
    extension of ``path`` (:data:`IMAGE_FORMATS`; JPEG at quality 95, no alpha)."""
    import matplotlib.image

    fmt = image_format(path)
    rgb = np.clip(img, 0.0, 1.0)
    pil: dict[str, Any] | None = {"quality": 95} if fmt == "jpeg" else None
    if fmt == "jpeg" and rgb.ndim == 3 and rgb.shape[2] == 4:
        rgb = rgb[..., :3]
    with atomic_path(path, suffix=Path(path).suffix.lower(), parents=True) as tmp:
        matplotlib.image.imsave(tmp, rgb, format=fmt, pil_kwargs=pil)


def analytic_bsdf(reference: dict, *, lobe: dict | None = None) -> dict:
    """The ``analytic_brdf`` plugin dict of an analytic target (``{"model": name,
    "params": {...}}``, as in a training config); ``lobe``: its sampling lobe (else the
    plugin fits one when it loads)."""
    if "model" not in reference:
        raise InputError(
            f"reference: expected {{'model': name, 'params': {{...}}}}, got {reference!r}"
        )
    out = {
        "type": "analytic_brdf",
        "model": reference["model"],
        "params": json.dumps(reference.get("params") or {}),
    }
    if lobe is not None:
        out["lobe"] = json.dumps(lobe, sort_keys=True)
    return out


def difference(neural: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|neural - reference| of display values, channel mean (H, W)."""
    return np.abs(np.asarray(neural, np.float64) - np.asarray(ref, np.float64)).mean(-1)


def adaptive_gain(err: np.ndarray) -> float:
    """The gain that maps the GAIN_PERCENTILE-th percentile of ``err`` to 1 (the maximum
    when that percentile is 0; 1 for identical images), to two significant digits."""
    top = float(np.percentile(err, GAIN_PERCENTILE))
    if top <= 0.0:
        top = float(err.max())
    return 1.0 if top <= 0.0 else float(f"{1.0 / top:.2g}")


def side_by_side(neural: np.ndarray, ref: np.ndarray, gain: float = ERROR_GAIN) -> np.ndarray:
    """Display images -> neural | reference | error map (:func:`difference` x ``gain``,
    'inferno' colours), with thin white gaps; unlabelled (:func:`label_panels`)."""
    import matplotlib

    err = difference(neural, ref) * gain
    err_rgb = matplotlib.colormaps["inferno"](np.clip(err, 0.0, 1.0))[..., :3]
    gap = np.ones((neural.shape[0], _gap(neural.shape[0]), 3))
    return np.concatenate([neural, gap, ref, gap, err_rgb], axis=1)


def _gap(height: int) -> int:
    return max(2, height // 64)


def label_panels(image: np.ndarray, labels: list[str], gap: int) -> np.ndarray:
    """``image`` (H, W, 3): ``len(labels)`` equal panels side by side, ``gap`` pixels
    apart, with a white strip above them holding each panel's label, centred, in black
    (drawn by matplotlib's Agg renderer at one pixel per pixel; a label wider than its
    panel, at the smallest sizes, is cut at the panel's edges)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.transforms import Bbox

    h, w = image.shape[:2]
    n = len(labels)
    panel = (w - gap * (n - 1)) / n
    strip = max(16, round(0.1 * h))
    dpi = 100.0
    fig = Figure(figsize=(w / dpi, strip / dpi), dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    longest = max(len(t) for t in labels)
    # font size in pixels: 0.6 of the strip, smaller where a label would overflow
    px = max(6.0, min(0.6 * strip, 1.7 * panel / max(longest, 1)))
    for i, label in enumerate(labels):
        x0 = i * (panel + gap)
        text = fig.text(
            (x0 + panel / 2) / w,
            0.5,
            label,
            ha="center",
            va="center",
            fontsize=px * 72 / dpi,
            color="black",
            clip_on=True,
        )
        text.set_clip_box(Bbox.from_extents(x0, 0, x0 + panel, strip))
    canvas.draw()
    header = np.asarray(canvas.buffer_rgba(), dtype=np.float64)[..., :3] / 255.0
    return np.concatenate([header[:strip, :w], np.clip(image, 0.0, 1.0)], axis=0)


def render_comparison(
    onnx_path,
    out_png,
    *,
    reference: dict | None = None,
    reference_bsdf: Any = None,
    spp: int = 64,
    resolution: int = 256,
    gain: float | None = None,
) -> dict:
    """Render the neural BRDF in the preview scene and write ``out_png``.

    With ``reference`` (an analytic target, see :func:`analytic_bsdf`) the PNG is
    :func:`side_by_side`, labelled "neural", "target" and "|difference| x K" with K =
    ``gain`` (None: :func:`adaptive_gain`).  Returns {"psnr": dB of neural against the
    reference (sRGB display values), "gain": K}; both None without a reference.
    """
    path, _, stored = read_model(onnx_path)
    # the reference is sampled with the model's lobe (fitted to a model of the same
    # target): no second fit at load
    ref_bsdf = None if reference is None else analytic_bsdf(reference, lobe=stored)
    if reference_bsdf is not None:  # a Mitsuba BSDF object (a textured teacher's)
        ref_bsdf = reference_bsdf
    neural = to_display(
        render_scene({"type": "neural_brdf", "filename": str(path)}, resolution=resolution, spp=spp)
    )
    if ref_bsdf is None:
        write_png(Path(out_png), neural)
        return {"psnr": None, "gain": None}
    ref = to_display(render_scene(ref_bsdf, resolution=resolution, spp=spp))
    if gain is None:
        gain = adaptive_gain(difference(neural, ref))
    labels = ["neural", "target", f"|difference| x {gain:g}"]
    panels = side_by_side(neural, ref, gain)
    write_png(Path(out_png), label_panels(panels, labels, _gap(resolution)))
    return {"psnr": psnr(neural, ref), "gain": gain}


def render_preview(
    onnx_path,
    out_png,
    *,
    reference: dict | None = None,
    reference_bsdf: Any = None,
    spp: int = 64,
    resolution: int = 256,
    gain: float | None = ERROR_GAIN,
) -> float | None:
    """:func:`render_comparison` with a fixed gain by default; returns the PSNR (None
    without a reference)."""
    return render_comparison(
        onnx_path,
        out_png,
        reference=reference,
        reference_bsdf=reference_bsdf,
        spp=spp,
        resolution=resolution,
        gain=gain,
    )["psnr"]
