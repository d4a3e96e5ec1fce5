"""Scenes and target images for fitting a BRDF from images (docs/inverse.md).

    python -m neural_brdf.inverse.scene OUT_DIR [--resolution 32] [--spp 64]

writes ``OUT_DIR/sky.exr`` (a procedural environment), ``view1.xml`` .. ``view3.xml``
(a sphere of a GGX copper, roughconductor alpha 0.2, under that sky, seen from three
directions), their target images ``view1.exr`` .. ``view3.exr`` rendered by Mitsuba at
``--spp``, and ``fit.yaml``, a config that fits a compact neural BRDF to them
(``neural-brdf train OUT_DIR/fit.yaml``).  ``--heldout`` adds ``view4.xml`` and
``view4.exr``, a fourth direction the fit does not see: fit.yaml lists it commented out,
saying how to score the fit on it (``images.validation_views``).

``--capture`` picks the lighting (docs/inverse.md, "What the images determine"):
``environment`` (the default: the sky above, the same in every view), ``lights`` (a
multi-light capture: no environment, each view lit by its own point or area light,
:data:`LIGHTS`), ``flash`` (a co-located flash: a point light at each camera) or
``flash_pair`` (the sky's three views and a flash/no-flash pair at the first camera:
``flash1.xml`` and ``flash1.exr``, the photograph with the flash, and a fourth fitted
view, ``pair1.xml``, lit by the flash alone, whose target is the difference
``flash1.exr`` - ``view1.exr``: ``subtract`` in fit.yaml).

The environment (:func:`sky`) is not the one the material preview uses
(:func:`neural_brdf.renderers.render.sky_bitmap`): a sky gradient over a dark ground plus a few
bright, coloured, soft blobs, so that the highlight's shape and colour are seen at
several angles.  Every file is written atomically (:mod:`neural_brdf.fileio`).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from neural_brdf import limits
from neural_brdf.errors import InputError, module_parser
from neural_brdf.fileio import atomic_path, atomic_write

# The true material: not a preset (the presets are GGX Au 0.3, Beckmann Cu 0.5 and Ag).
TRUTH = {"distribution": "ggx", "alpha": 0.2, "material": "Cu"}
# (azimuth, elevation) of the cameras in degrees; the last one is held out.
VIEWS = ((0.0, 15.0), (125.0, 35.0), (235.0, -5.0), (60.0, 50.0))
DISTANCE = 4.6  # camera distance from the unit sphere's centre
FOV = 28.0  # degrees: the sphere fills about 90 % of the frame
# The blobs: elevation, azimuth (degrees), angular radius (degrees), RGB radiance.
BLOBS = (
    (35.0, 20.0, 7.0, (30.0, 26.0, 20.0)),
    (12.0, 150.0, 10.0, (4.0, 9.0, 16.0)),
    (60.0, 250.0, 5.0, (40.0, 18.0, 10.0)),
    (5.0, 290.0, 12.0, (8.0, 12.0, 6.0)),
)
# The multi-light capture (--capture lights): per view, its lights as (kind, azimuth,
# elevation): a point light at LIGHT_DISTANCE, or a square area light of side
# 2 AREA_HALF_SIZE facing the sphere there.  The angles between camera and light, about
# 34, 62 and 105 degrees, set each view's theta_d (half that angle, for a distant light).
LIGHTS = (
    (("point", 30.0, 35.0),),
    (("area", 200.0, 30.0),),
    (("point", 340.0, 30.0),),
)
LIGHT_DISTANCE = 6.0
AREA_HALF_SIZE = 0.75
POINT_INTENSITY = 30.0  # W/sr: about 1 W/m^2 at the sphere from LIGHT_DISTANCE
AREA_RADIANCE = 12.0  # W/(m^2 sr) of the area light: about as bright at the sphere
FLASH_INTENSITY = 15.0  # W/sr of the co-located flash (DISTANCE - 1 from the surface)
CAPTURES = ("environment", "lights", "flash", "flash_pair")
FIT_CONFIG = """\
# Fit a compact neural BRDF to {count} images of a copper sphere (docs/inverse.md).
# Written by: {command}
name: {name}
target:
  images:
    - {{scene: view1.xml, image: view1.exr}}
    - {{scene: view2.xml, image: view2.exr}}
    - {{scene: view3.xml, image: view3.exr}}{extra}{heldout}
model:
  hidden: [32]
  activation: relu
  grid: {{size: 32, channels: 4, lr_scale: 10.0}}
train:
  steps: {steps}
  lr: 0.01
  warmup: 10
  checkpoint_every: 50
  log_every: 5
  eval_every: 0
"""


def sky(height: int = 128) -> np.ndarray:
    """The environment, lat-long (H, 2H, 3) float32: rows from the zenith (+y, Mitsuba's
    envmap up axis) to the nadir, columns over the azimuth."""
    ground = np.array([0.12, 0.1, 0.08])
    return latlong(
        np.array([0.15, 0.3, 0.75]),
        np.array([0.9, 0.85, 0.75]),
        lambda az: ground * (0.6 + 0.4 * np.cos(az))[..., None],
        BLOBS,
        height,
    )


def latlong(
    zenith: np.ndarray,
    horizon: np.ndarray,
    ground: Any,
    blobs: Sequence[tuple[float, float, float, Sequence[float]]],
    height: int = 128,
) -> np.ndarray:
    """A procedural environment, lat-long (H, 2H, 3) float32 as :func:`sky`: a gradient
    from ``horizon`` to ``zenith`` above the horizon, ``ground`` below (RGB, or a function
    of the azimuth (1, 2H) giving (1, 2H, 3)), plus soft round ``blobs`` (elevation,
    azimuth, angular radius in degrees, RGB radiance), each a Gaussian in the angle."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(2 * height) + 0.5) / (2 * height)
    el = (0.5 - v)[:, None] * math.pi  # (H, 1)
    az = u[None, :] * 2.0 * math.pi  # (1, 2H)
    s = np.clip(np.sin(el), 0.0, 1.0)[..., None]
    below = ground(az) if callable(ground) else np.asarray(ground)
    img = np.where(el[..., None] > 0, horizon * (1.0 - s) + zenith * s, below)
    img = np.broadcast_to(img, (height, 2 * height, 3)).copy()
    d = np.stack(
        np.broadcast_arrays(np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)), -1
    )
    for b_el, b_az, radius, rgb in blobs:
        e, a = math.radians(b_el), math.radians(b_az)
        c = np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])
        ang = np.arccos(np.clip(d @ c, -1.0, 1.0))
        img += np.exp(-0.5 * (ang / math.radians(radius)) ** 2)[..., None] * np.array(rgb)
    return np.ascontiguousarray(img, dtype=np.float32)


def direction(azimuth: float, elevation: float) -> list[float]:
    """The unit vector at ``azimuth``, ``elevation`` (degrees; +y up, azimuth 0 along +z,
    90 along +x): how the cameras and lights are placed."""
    a, e = math.radians(azimuth), math.radians(elevation)
    return [math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)]


def camera_origin(azimuth: float, elevation: float) -> list[float]:
    """Where :func:`scene_xml` puts the camera of a view (it looks at the origin)."""
    return [DISTANCE * c for c in direction(azimuth, elevation)]


def point_light(position: list[float] | tuple[float, ...], intensity: float) -> str:
    """A Mitsuba ``point`` emitter at ``position`` (white, ``intensity`` W/sr)."""
    p = ", ".join(f"{c:.6f}" for c in position)
    return f"""<emitter type="point">
        <point name="position" value="{p}"/>
        <rgb name="intensity" value="{intensity:g}"/>
    </emitter>"""


def area_light(position: list[float] | tuple[float, ...], half_size: float, radiance: float) -> str:
    """A square ``rectangle`` of side 2 ``half_size`` at ``position``, facing the origin,
    with an ``area`` emitter of ``radiance`` (white)."""
    p = ", ".join(f"{c:.6f}" for c in position)
    up = "0, 0, 1" if abs(position[1]) > 0.99 * math.dist(position, (0, 0, 0)) else "0, 1, 0"
    return f"""<shape type="rectangle">
        <transform name="to_world">
            <scale value="{half_size:g}"/>
            <lookat origin="{p}" target="0, 0, 0" up="{up}"/>
        </transform>
        <emitter type="area">
            <rgb name="radiance" value="{radiance:g}"/>
        </emitter>
    </shape>"""


def capture_emitters(capture: str, view: int) -> str | None:
    """The emitters of view ``view`` (0-based) of a ``capture`` (:data:`CAPTURES`) as
    XML, or None for ``environment`` and ``flash_pair`` (the sky of :func:`scene_xml`;
    :func:`write` adds the pair's flash)."""
    if capture in ("environment", "flash_pair"):
        return None
    if capture == "flash":
        return point_light(camera_origin(*VIEWS[view]), FLASH_INTENSITY)
    if capture != "lights":
        raise ValueError(f"capture {capture!r}: expected one of {', '.join(CAPTURES)}")
    parts = []
    for kind, az, el in LIGHTS[view % len(LIGHTS)]:
        pos = [LIGHT_DISTANCE * c for c in direction(az, el)]
        if kind == "point":
            parts.append(point_light(pos, POINT_INTENSITY))
        else:
            parts.append(area_light(pos, AREA_HALF_SIZE, AREA_RADIANCE))
    return "\n    ".join(parts)


def scene_xml(
    azimuth: float,
    elevation: float,
    *,
    resolution: int,
    envmap: str = "sky.exr",
    bsdf: dict | None = None,
    max_depth: int = 3,
    emitters: str | None = None,
    beside: str | None = None,
) -> str:
    """A Mitsuba 3 scene: the unit sphere with ``<bsdf id="fit">`` (``bsdf``: the
    roughconductor parameters, :data:`TRUTH` by default) under ``envmap``, or, when
    ``emitters`` (XML: :func:`point_light`, :func:`area_light`) is given, lit by those
    instead of an environment; ``beside``: emitters added to the environment (a flash
    in a lit room)."""
    o = camera_origin(azimuth, elevation)
    p = bsdf or TRUTH
    light = (
        f"""<emitter type="envmap">
        <string name="filename" value="{envmap}"/>
    </emitter>"""
        if emitters is None
        else emitters
    )
    if beside is not None:
        light = f"{light}\n    {beside}"
    return f"""<scene version="3.0.0">
    <integrator type="path">
        <integer name="max_depth" value="{max_depth}"/>
    </integrator>
    <sensor type="perspective">
        <float name="fov" value="{FOV:g}"/>
        <transform name="to_world">
            <lookat origin="{o[0]:.6f}, {o[1]:.6f}, {o[2]:.6f}" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="{resolution}"/>
            <integer name="height" value="{resolution}"/>
        </film>
    </sensor>
    {light}
    <bsdf type="roughconductor" id="fit">
        <string name="distribution" value="{p["distribution"]}"/>
        <float name="alpha" value="{p["alpha"]:g}"/>
        <string name="material" value="{p["material"]}"/>
    </bsdf>
    <shape type="sphere">
        <ref id="fit"/>
    </shape>
</scene>
"""


def write_exr(path: Path, img: np.ndarray) -> None:
    """A linear RGB float32 EXR, written atomically (Mitsuba picks the format by suffix)."""
    import mitsuba as mi

    bmp = mi.Bitmap(np.ascontiguousarray(img[..., :3], dtype=np.float32))
    with atomic_path(path, suffix=".exr", parents=True) as tmp:
        bmp.write(tmp)


def render_file(scene_path: Path, spp: int, seed: int = 0) -> np.ndarray:
    """Render an XML scene as it is (its own integrator and BSDFs): (H, W, 3) float32."""
    import mitsuba as mi

    scene = mi.load_file(str(scene_path))
    img = mi.render(scene, spp=spp, seed=seed)  # type: ignore[arg-type]  # stub: mi.UInt32
    return np.asarray(img, dtype=np.float32)[..., :3]


# fit.yaml's lines on view 4 (--heldout): not a view of target.images, which the fit would
# render, but commented out, with how to score the fit on it (docs/inverse.md, "The
# held-out split"); {index}: its index once added
HELDOUT_LINES = """
    # view4 (--heldout): a fourth camera, not fitted.  To score the fit on it, held out
    # whole (docs/inverse.md, "The held-out split"), uncomment the next line and add
    # the section  images: {{validation_views: [{index}]}}
    # - {{scene: view4.xml, image: view4.exr}}"""

# fit.yaml's entry of a flash/no-flash pair's fitted view (:func:`write_flash_pair`): its
# target is the flash photograph minus view 1's, the photograph without the flash
PAIR_ENTRY = "\n    - {scene: pair1.xml, image: flash1.exr, subtract: view1.exr}"


def write_flash_pair(folder: Path, both: str, alone: str, spp: int, seed: int) -> list[Path]:
    """A flash/no-flash pair at view 1's camera (docs/inverse.md, "A flash/no-flash
    pair"): ``flash1.xml`` (``both``: view 1's scene with the flash beside its light) and
    its photograph ``flash1.exr``, rendered at ``spp`` with its own ``seed``, and the
    scene ``pair1.xml`` (``alone``: lit by the flash alone) that fits the difference
    ``flash1.exr`` - ``view1.exr`` (:data:`PAIR_ENTRY`).  Returns the three files."""
    files = [folder / "flash1.xml", folder / "flash1.exr", folder / "pair1.xml"]
    atomic_write(files[0], both)
    write_exr(files[1], render_file(files[0], spp, seed=seed))
    atomic_write(files[2], alone)
    return files


# write()'s and the command's defaults (the command states only the options that differ)
WRITE_DEFAULTS: dict[str, Any] = {
    "resolution": 32,
    "spp": 64,
    "steps": 150,
    "capture": "environment",
}


def write(
    folder: str | Path,
    *,
    resolution: int = WRITE_DEFAULTS["resolution"],
    spp: int = WRITE_DEFAULTS["spp"],
    heldout: bool = False,
    steps: int = WRITE_DEFAULTS["steps"],
    seed: int = 0,
    capture: str = WRITE_DEFAULTS["capture"],
) -> list[Path]:
    """Write the example into ``folder`` (see the module doc); returns the files written.
    ``capture``: the lighting, one of :data:`CAPTURES` (:func:`capture_emitters`); only
    ``environment`` and ``flash_pair`` write ``sky.exr``.

    Needs a Mitsuba variant set (any RGB one renders the targets)."""
    if capture not in CAPTURES:
        raise ValueError(f"capture {capture!r}: expected one of {', '.join(CAPTURES)}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    if capture in ("environment", "flash_pair"):
        written.append(folder / "sky.exr")
        write_exr(written[0], sky())
    views = VIEWS if heldout else VIEWS[:3]
    for k, (az, el) in enumerate(views, start=1):
        xml, exr = folder / f"view{k}.xml", folder / f"view{k}.exr"
        emitters = capture_emitters(capture, k - 1)
        atomic_write(xml, scene_xml(az, el, resolution=resolution, emitters=emitters))
        write_exr(exr, render_file(xml, spp, seed=seed + k))
        written += [xml, exr]
    extra = ""
    if capture == "flash_pair":
        flash = capture_emitters("flash", 0)
        written += write_flash_pair(
            folder,
            scene_xml(*VIEWS[0], resolution=resolution, beside=flash),
            scene_xml(*VIEWS[0], resolution=resolution, emitters=flash),
            spp,
            seed=seed + len(VIEWS) + 1,
        )
        extra = PAIR_ENTRY
    cfg = folder / "fit.yaml"
    count = "four" if extra else "three"
    name = "images_" + folder.name
    command = regenerate_command(folder, resolution, spp, heldout, steps, seed, capture)
    held = HELDOUT_LINES.format(index=3 + bool(extra)) if heldout else ""
    text = FIT_CONFIG.format(
        command=command, name=name, steps=steps, extra=extra, heldout=held, count=count
    )
    atomic_write(cfg, text)
    return written + [cfg]


def regenerate_command(
    folder: Path, resolution: int, spp: int, heldout: bool, steps: int, seed: int, capture: str
) -> str:
    """The command that writes ``folder`` again as :func:`write` did (its options where
    they differ from the defaults; a seed other than 0 is :func:`write`'s alone)."""
    parts = ["python -m neural_brdf.inverse.scene", shlex.quote(str(folder))]
    given = {"resolution": resolution, "spp": spp, "steps": steps, "capture": capture}
    parts += [f"--{k} {v}" for k, v in given.items() if v != WRITE_DEFAULTS[k]]
    parts += ["--heldout"] if heldout else []
    return " ".join(parts) + (f"  (write(..., seed={seed}) from Python)" if seed else "")


def _at_least(low: int):
    """An argparse type: an integer >= ``low`` (else argparse's one-line error)."""

    def integer(text: str) -> int:
        value = int(text)  # (a ValueError: argparse says "invalid integer value")
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    return integer


def main(argv: list[str] | None = None) -> int:
    ap = module_parser("neural_brdf.inverse.scene", __doc__.splitlines()[0])
    ap.add_argument("out", help="folder to write into")
    d = WRITE_DEFAULTS
    ap.add_argument(
        "--resolution", type=_at_least(1), default=d["resolution"], help="film width, height"
    )
    ap.add_argument(
        "--spp", type=_at_least(1), default=d["spp"], help="samples per pixel of the targets"
    )
    ap.add_argument("--heldout", action="store_true", help="also write view4, held out")
    ap.add_argument("--steps", type=_at_least(0), default=d["steps"], help="fit.yaml's train.steps")
    ap.add_argument(
        "--capture",
        choices=CAPTURES,
        default=d["capture"],
        help="the lighting: the sky (default), a light per view, a flash at each camera, "
        "or the sky and a flash/no-flash pair at the first camera (flash_pair)",
    )
    args = ap.parse_args(argv)
    out = Path(args.out)
    there = next(p for p in (out, *out.parents) if p.exists())  # (the root, at least)
    if not there.is_dir():
        ap.error(f"{out}: {there} is a file, not a folder to write the example into")
    from neural_brdf.inverse import views as views_layer  # (torch: after the arguments)

    try:  # a target render's samples, before anything is written (one line, exit 2)
        limits.check_bytes(
            "--resolution and --spp", args.resolution**2 * args.spp * views_layer.LANE_BYTES
        )
    except InputError as e:
        ap.error(str(e))
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    files = write(
        args.out,
        resolution=args.resolution,
        spp=args.spp,
        heldout=args.heldout,
        steps=args.steps,
        capture=args.capture,
    )
    print(f"wrote {len(files)} files to {args.out}; fit with: neural-brdf train {files[-1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
