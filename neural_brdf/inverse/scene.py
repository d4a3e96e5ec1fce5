"""Scenes and target images for fitting a BRDF from images (docs/inverse.md).

    python -m neural_brdf.inverse.scene OUT_DIR [--resolution 32] [--spp 64]

writes ``OUT_DIR/sky.exr`` (a procedural environment), ``view1.xml`` .. ``view3.xml``
(a sphere of a GGX copper, roughconductor alpha 0.2, under that sky, seen from three
directions), their target images ``view1.exr`` .. ``view3.exr`` rendered by Mitsuba at
``--spp``, and ``fit.yaml``, a config that fits a compact neural BRDF to them
(``neural-brdf train OUT_DIR/fit.yaml``).  ``--heldout`` adds ``view4.xml`` and
``view4.exr``, a fourth direction the fit does not see.  The shipped example
``configs/images/`` was written by this command with its defaults.

The environment (:func:`sky`) is not the one the material preview uses
(:func:`neural_brdf.renderers.render.sky_bitmap`): a sky gradient over a dark ground plus a few
bright, coloured, soft blobs, so that the highlight's shape and colour are seen at
several angles.  Every file is written atomically (:mod:`neural_brdf.fileio`).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

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
FIT_CONFIG = """\
# Fit a compact neural BRDF to three images of a copper sphere (docs/inverse.md).
# Written by: python -m neural_brdf.inverse.scene {folder}
name: {name}
target:
  images:
    - {{scene: view1.xml, image: view1.exr}}
    - {{scene: view2.xml, image: view2.exr}}
    - {{scene: view3.xml, image: view3.exr}}
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
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(2 * height) + 0.5) / (2 * height)
    el = (0.5 - v)[:, None] * math.pi  # (H, 1)
    az = u[None, :] * 2.0 * math.pi  # (1, 2H)
    s = np.clip(np.sin(el), 0.0, 1.0)[..., None]
    horizon, zenith = np.array([0.9, 0.85, 0.75]), np.array([0.15, 0.3, 0.75])
    ground = np.array([0.12, 0.1, 0.08]) * (0.6 + 0.4 * np.cos(az))[..., None]
    img = np.where(el[..., None] > 0, horizon * (1.0 - s) + zenith * s, ground)
    img = np.broadcast_to(img, (height, 2 * height, 3)).copy()
    d = np.stack(
        np.broadcast_arrays(np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)), -1
    )
    for b_el, b_az, radius, rgb in BLOBS:
        e, a = math.radians(b_el), math.radians(b_az)
        c = np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])
        ang = np.arccos(np.clip(d @ c, -1.0, 1.0))
        img += np.exp(-0.5 * (ang / math.radians(radius)) ** 2)[..., None] * np.array(rgb)
    return np.ascontiguousarray(img, dtype=np.float32)


def scene_xml(
    azimuth: float,
    elevation: float,
    *,
    resolution: int,
    envmap: str = "sky.exr",
    bsdf: dict | None = None,
    max_depth: int = 3,
) -> str:
    """A Mitsuba 3 scene: the unit sphere with ``<bsdf id="fit">`` (``bsdf``: the
    roughconductor parameters, :data:`TRUTH` by default) under ``envmap``."""
    a, e = math.radians(azimuth), math.radians(elevation)
    o = [
        DISTANCE * math.cos(e) * math.sin(a),
        DISTANCE * math.sin(e),
        DISTANCE * math.cos(e) * math.cos(a),
    ]
    p = bsdf or TRUTH
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
    <emitter type="envmap">
        <string name="filename" value="{envmap}"/>
    </emitter>
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


def write(
    folder: str | Path,
    *,
    resolution: int = 32,
    spp: int = 64,
    heldout: bool = False,
    steps: int = 150,
    seed: int = 0,
) -> list[Path]:
    """Write the example into ``folder`` (see the module doc); returns the files written.

    Needs a Mitsuba variant set (any RGB one renders the targets)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = [folder / "sky.exr"]
    write_exr(written[0], sky())
    views = VIEWS if heldout else VIEWS[:3]
    for k, (az, el) in enumerate(views, start=1):
        xml, exr = folder / f"view{k}.xml", folder / f"view{k}.exr"
        atomic_write(xml, scene_xml(az, el, resolution=resolution))
        write_exr(exr, render_file(xml, spp, seed=seed + k))
        written += [xml, exr]
    cfg = folder / "fit.yaml"
    atomic_write(cfg, FIT_CONFIG.format(folder=folder, name="images_" + folder.name, steps=steps))
    return written + [cfg]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="folder to write into")
    ap.add_argument("--resolution", type=int, default=32, help="film width and height")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel of the targets")
    ap.add_argument("--heldout", action="store_true", help="also write view4, held out")
    ap.add_argument("--steps", type=int, default=150, help="train.steps of fit.yaml")
    args = ap.parse_args(argv)
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    files = write(
        args.out, resolution=args.resolution, spp=args.spp, heldout=args.heldout, steps=args.steps
    )
    print(f"wrote {len(files)} files to {args.out}; fit with: neural-brdf train {files[-1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
