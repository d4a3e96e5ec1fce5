"""The project's own procedural textured teachers (issue 30): Mitsuba XML files whose BSDF
parameters are bitmaps generated here, for
:class:`~neural_brdf.measured.textured.TexturedMitsubaTarget`.

    from neural_brdf.measured.procedural import write_teacher
    xml = write_teacher(folder, "principled", size=512, seed=0)   # folder/teacher.xml

    python -m neural_brdf.measured.procedural runs/textured   # + runs/textured/textured.yaml

Kinds (:data:`KINDS`):

* ``"principled"``: ``twosided > normalmap > principled`` with a base colour bitmap
  (<= :data:`MAX_BASE`, so the albedo stays near or below 1), a roughness bitmap in
  :data:`ROUGHNESS`, a metallic bitmap in [0, 1], specular 0.5, no sheen, no
  transmission, and a gentle normal map (tilts up to :data:`MAX_TILT_DEG`);
* ``"roughplastic"``: ``twosided > roughplastic`` (GGX, alpha :data:`ALPHA`, int_ior
  1.5) with a diffuse reflectance bitmap (<= :data:`MAX_BASE`).

The textures are smooth periodic value noise (a few octaves on a lattice that wraps, so
``wrap_mode`` repeat has no seam) mixed with tiles (a 4 x 4 grid of per-tile values), so
neighbouring texels differ and the tiles give sharp edges.  They are written as float32
OpenEXR files by ``mi.Bitmap(...).write`` (linear data: no sRGB curve, no 8-bit
quantisation), named relative to the XML, which sits beside them.

The bitmap plugin's parameters were checked in Mitsuba 3.9.1's own documentation (the
plugin doc block of src/textures/bitmap.cpp, which the docs site renders): ``raw``
"disables the transformation to the stored color data (e.g. sRGB to linear, spectral
upsampling)"; an EXR is stored linear (its sRGB flag is off), and float data is decoded
to linear at load time, so a float EXR reads back as written.  ``raw=true`` is set on
every non-colour map (roughness, metallic, the normal map, as normalmap.cpp's own doc
example does); the colour maps leave ``raw`` false (linear EXR: no conversion in RGB
variants, spectral upsampling in spectral ones).  Filtering is the default ``bilinear``
and ``wrap_mode`` the default ``repeat``, so a texel centre uv = ((i + 0.5) / W,
(j + 0.5) / H) reads that texel exactly.  Row j of the image is v = (j + 0.5) / H (the
tensor's first axis is v; tests/measured/test_textured.py checks it).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from neural_brdf import limits
from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write

KINDS = ("principled", "roughplastic")
MAX_BASE = 0.8  # base colours / diffuse reflectances at most this (albedo <= 1)
ROUGHNESS = (0.25, 0.8)  # the principled's roughness range
MAX_TILT_DEG = 4.0  # the normal map's largest tilt from (0, 0, 1)
ALPHA = 0.2  # the roughplastic's GGX alpha
TILES = 4  # tiles per side


def value_noise(size: int, rng: np.random.Generator, octaves: int = 3, base: int = 4) -> np.ndarray:
    """Periodic smooth value noise (size, size) in [0, 1]: random lattice values, base
    cells per side at the first octave (doubling per octave, amplitude halving),
    interpolated with the smoothstep 3t^2 - 2t^3; the lattice wraps, so the image tiles."""
    out = np.zeros((size, size))
    total = 0.0
    for o in range(octaves):
        cells = base * 2**o
        lattice = rng.random((cells, cells))
        x = (np.arange(size) + 0.5) / size * cells
        i0 = np.floor(x).astype(int)
        t = x - i0
        t = t * t * (3.0 - 2.0 * t)
        a, b = i0 % cells, (i0 + 1) % cells
        # rows (v) then columns (u)
        rows = lattice[a] * (1 - t)[:, None] + lattice[b] * t[:, None]
        layer = rows[:, a] * (1 - t)[None, :] + rows[:, b] * t[None, :]
        amp = 0.5**o
        out += amp * layer
        total += amp
    out /= total
    lo, hi = out.min(), out.max()
    return (out - lo) / max(hi - lo, 1e-12)


def tiles(size: int, rng: np.random.Generator, channels: int = 1) -> np.ndarray:
    """(size, size, channels) in [0, 1): one random value per tile of a TILES x TILES grid."""
    idx = (np.arange(size) * TILES) // size
    values = rng.random((TILES, TILES, channels))
    return values[idx[:, None], idx[None, :]]


def _colour(size: int, rng: np.random.Generator) -> np.ndarray:
    """(size, size, 3) RGB in [0.05, MAX_BASE]: tiles of random colours modulated by noise."""
    tint = tiles(size, rng, 3)
    noise = value_noise(size, rng)[..., None]
    c = 0.6 * tint + 0.4 * noise * rng.random(3)
    return 0.05 + (MAX_BASE - 0.05) * np.clip(c, 0.0, 1.0)


def _scalar(size: int, rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """(size, size) in [lo, hi]: noise mixed with tiles."""
    s = 0.5 * value_noise(size, rng) + 0.5 * tiles(size, rng)[..., 0]
    return lo + (hi - lo) * s


def normal_map(
    size: int, rng: np.random.Generator, max_tilt_deg: float = MAX_TILT_DEG
) -> np.ndarray:
    """(size, size, 3) encoded normals (n + 1) / 2 (the encoding Mitsuba's normalmap
    plugin reads back as 2 x - 1) of a smooth periodic height field, scaled so that the
    largest tilt is ``max_tilt_deg``: n = normalize(-dh/du, -dh/dv, 1)."""
    h = value_noise(size, rng, octaves=2, base=2)
    du = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) * 0.5  # central differences, periodic
    dv = (np.roll(h, -1, 0) - np.roll(h, 1, 0)) * 0.5
    slope = np.sqrt(du**2 + dv**2).max()
    k = math.tan(math.radians(max_tilt_deg)) / max(slope, 1e-12)
    n = np.stack([-k * du, -k * dv, np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return (n + 1.0) * 0.5


def _write_exr(path: Path, data: np.ndarray) -> None:
    import mitsuba as mi  # mi.Bitmap is core: it needs no variant set

    arr = np.ascontiguousarray(data if data.ndim == 3 else data[..., None], dtype=np.float32)
    mi.Bitmap(arr).write(str(path))


def _bitmap(name: str, filename: str, *, raw: bool) -> str:
    raw_line = '<boolean name="raw" value="true"/>' if raw else ""
    return (
        f'<texture type="bitmap" name="{name}">'
        f'<string name="filename" value="{filename}"/>{raw_line}</texture>'
    )


def write_teacher(folder: str | Path, kind: str, size: int = 512, seed: int = 0) -> Path:
    """Write the textures and ``teacher.xml`` of ``kind`` into ``folder`` (created if
    needed); returns the XML's path.  The same (kind, size, seed) gives the same files."""
    if kind not in KINDS:
        raise InputError(f"procedural kind: {kind!r}: one of {', '.join(KINDS)}")
    if size < 2:
        raise InputError(f"procedural size: {size}: at least 2 texels per side")
    # the noise and its temporaries: a few float64 RGB images at once (~256 bytes a texel)
    limits.check_bytes(f"procedural size: {size}", 256.0 * size * size, hint="give a smaller size")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    if kind == "principled":
        _write_exr(folder / "base_color.exr", _colour(size, rng))
        _write_exr(folder / "roughness.exr", _scalar(size, rng, *ROUGHNESS))
        _write_exr(folder / "metallic.exr", _scalar(size, rng, 0.0, 1.0))
        _write_exr(folder / "normal.exr", normal_map(size, rng))
        xml = (
            '<bsdf version="3.0.0" type="twosided">\n'
            ' <bsdf type="normalmap">\n'
            f"  {_bitmap('normalmap', 'normal.exr', raw=True)}\n"
            '  <bsdf type="principled">\n'
            f"   {_bitmap('base_color', 'base_color.exr', raw=False)}\n"
            f"   {_bitmap('roughness', 'roughness.exr', raw=True)}\n"
            f"   {_bitmap('metallic', 'metallic.exr', raw=True)}\n"
            '   <float name="specular" value="0.5"/>\n'
            '   <float name="sheen" value="0"/>\n'
            "  </bsdf>\n"
            " </bsdf>\n"
            "</bsdf>\n"
        )
    else:
        _write_exr(folder / "diffuse.exr", _colour(size, rng))
        xml = (
            '<bsdf version="3.0.0" type="twosided">\n'
            ' <bsdf type="roughplastic">\n'
            '  <string name="distribution" value="ggx"/>\n'
            f'  <float name="alpha" value="{ALPHA}"/>\n'
            '  <float name="int_ior" value="1.5"/>\n'
            f"  {_bitmap('diffuse_reflectance', 'diffuse.exr', raw=False)}\n"
            " </bsdf>\n"
            "</bsdf>\n"
        )
    path = folder / "teacher.xml"
    atomic_write(path, xml)
    return path


# The config written beside a teacher by ``python -m neural_brdf.measured.procedural DIR``:
# the texture section's defaults, and steps enough for a CPU run of a few minutes.
CONFIG = """\
# A textured material: Mitsuba's own BSDF (teacher.xml, procedural textures) as the teacher
# of K shared neural lobes times a field of their weights over uv (docs/mitsuba.md,
# "Textured materials").  Train with: neural-brdf train {config} --out runs/{name}
name: {name}
target:
  mitsuba: teacher.xml
texture:
  lobes: 4
  resolution: 32
  latent: 1      # conditioned lobes: a lobe can follow a roughness map (docs/model.md)
  weights: rgb   # a weight per lobe and RGB channel
  lobe_color: grey  # one output per lobe, coloured by those weights (cheaper to render)
  # the pool: texture.pool_per_texel (2048) pairs per texel, 2M at 32 x 32, drawn once
  # (against data.pool_size's 262144: the held-out principled 19.4 -> 14.1 %, docs/mitsuba.md)
  # after training, the field projected texel by texel onto the trained lobes at 128 x 128
  # (docs/mitsuba.md, "A finer field by projection"): on the development teachers the
  # principled 14.2 -> 10.2 % and the roughplastic 1.83 -> 1.67 %, for about 30 s
  project: 128
train:
  steps: {steps}
"""


def main(argv: list[str] | None = None) -> int:
    """``python -m neural_brdf.measured.procedural DIR [--kind K] [--size N]``: a
    procedural teacher (:func:`write_teacher`) and ``DIR/textured.yaml``, its config."""
    from neural_brdf.errors import module_parser

    ap = module_parser(
        "neural_brdf.measured.procedural", "Write a procedural textured Mitsuba teacher."
    )
    ap.add_argument("out", help="folder to write into")
    ap.add_argument("--kind", choices=KINDS, default="roughplastic", help="the BSDF")
    ap.add_argument("--size", type=int, default=512, help="texels per side of each texture")
    ap.add_argument("--steps", type=int, default=1500, help="train.steps of textured.yaml")
    args = ap.parse_args(argv)
    try:  # bad input: one line and exit code 2, as the neural-brdf command's
        if args.steps < 0:
            raise InputError(f"--steps {args.steps}: train.steps must be >= 0")
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
        xml = write_teacher(args.out, args.kind, size=args.size)
        cfg = Path(args.out) / "textured.yaml"
        name = "textured_" + args.kind
        atomic_write(cfg, CONFIG.format(config=cfg, name=name, steps=args.steps))
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # OUT is a file, a read-only folder, a full disk
        print(f"error: {e.filename or args.out}: {e.strerror or e}", file=sys.stderr)
        return 2
    print(f"wrote {xml} and its textures; train with: neural-brdf train {cfg}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
