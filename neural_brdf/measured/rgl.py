"""RGL ``.bsdf`` material files (Dupuy & Jakob 2018): read, evaluate, bake.

    from neural_brdf.measured import rgl
    fields = rgl.read_tensor_file("material.bsdf")     # name -> numpy array
    m = rgl.read_rgl("material.bsdf")                  # RGLFormatError on a bad file
    f = m.eval(wi, wo)                                 # (..., 3) in 1/sr, no cosine
    rgl.bake(analytic.create("microfacet", alpha=0.3).eval, "ggx.bsdf")
    rgl.bake(neural_brdf.load("model.onnx").eval, "model.bsdf")

Mitsuba 3's built-in ``measured`` BSDF and pbrt-v4's ``measured`` material read the
files this module writes; docs/rgl.md tells how.  numpy only (no torch, no Mitsuba).

The container: Mitsuba's TensorFile (src/core/tensor.cpp, python/tensor_io.py)
------------------------------------------------------------------------------
Little-endian.  12 bytes ``b"tensor_file\\0"``, 2 bytes version ``(1, 0)``, uint32 field
count, then per field: uint16 name length, the UTF-8 name, uint16 ndim, uint8 dtype code
(1 uint8, 2 int8, 3 uint16, 4 int16, 5 uint32, 6 int32, 7 uint64, 8 int64, 9 float16,
10 float32, 11 float64), uint64 byte offset of the data from the file start, ndim uint64
sizes.  The data are C-ordered arrays at their offsets (8-byte aligned when written here).

The material (Dupuy & Jakob 2018, "An Adaptive Parameterization for Efficient Material
Acquisition and Rendering"; read as Mitsuba's src/bsdfs/measured.cpp evaluates it)
----------------------------------------------------------------------------------------
Angles map to the unit square by ``u(theta) = sqrt(theta / (pi/2))`` and
``v(phi) = (phi + pi) / (2 pi)``; a square point is ``(x, y) = (u, v)``.  Every 2D table
below is ``[..., rows = y, cols = x]`` and is a bilinear interpolant over [0, 1]^2 with
nodes at ``i / (n - 1)``; the leading axes ``[phi_i, theta_i]`` are interpolated
linearly in the incident angles (clamped at the ends; a size-1 axis is constant).

* ``theta_i`` (T,), ``phi_i`` (P,) float32: the incident angles of the slices (radians).
  ``P <= 2`` means isotropic: the microfacet azimuth is then relative, ``phi_m - phi_i``.
* ``ndf`` (H, W) float32: the microfacet distribution D at square point of m.
* ``sigma`` (H, W) float32: the projected area sigma(wi) = int D(m) <wi.m> dm at the square
  point of wi.
* ``vndf`` (P, T, H, W) float32: the visible-normal density D(m) <wi.m> / sigma(wi), as a
  density on the square (times the Jacobian 2 pi^2 u sin theta_m).  Mitsuba builds a
  *continuous marginal 2D warp* from it (Marginal2D<..., Continuous=true>: conditional
  CDFs along x per row, a marginal CDF along y, linear in each segment); its inverse
  maps the square point of m to the *sample square*, on which the values live.
* ``luminance`` (P, T, N, N) float32: a density on the sample square, sampled before
  the VNDF warp (importance sampling of the value).
* ``rgb`` (P, T, 3, N, N) float32 (RGB variants), or ``spectra`` (P, T, L, N, N) with
  ``wavelengths`` (L,) in nm (spectral variants): the value rho at each sample-square
  node.
* ``jacobian`` (1,) uint8: 1 when rho excludes the factor D(m) / (4 sigma(wi)).
* ``description`` (n,) uint8: UTF-8 text.

Evaluation (measured.cpp ``eval``): m = normalize(wi + wo); the square point of m is
inverted through the VNDF warp of the slice at (phi_i, theta_i) to a sample-square
point s; then ``f cos(theta_o) = rho(s) * D(m) / (4 sigma(wi))`` (jacobian = 1).  Mitsuba
returns that product (its eval includes the cosine); :meth:`RGLBRDF.eval` divides by
cos(theta_o) to give f in 1/sr as every f in this project.

What :func:`bake` writes (isotropic, ``jacobian = 1``; ``rgb``, or ``spectra`` by
:func:`rgb_to_spectra` for names ending in ``_spec.bsdf``)
----------------------------------------------------------------------------------
1. D from the retro-reflection by the power iteration of Dupuy et al. 2015 ("Extracting
   microfacet-based BRDF parameters from arbitrary materials with power iterations"),
   the method the 2018 paper uses: under a microfacet model the back-scattering is
   f(w, w) = D(w) / (4 cos(theta) sigma(w)), so D is the fixed point of
   D <- f_Y(w, w) cos(theta) sigma_D(w), normalised to int D cos(theta_m) dm = 1.  f_Y is
   the luminance of f.  sigma_D is integrated in closed form over the azimuth and by the
   midpoint rule in u.  D is floored at ``NDF_FLOOR`` times its maximum so that the
   ratio rho never divides by ~0.
2. sigma on its table from that D (the same quadrature).
3. Per theta_i slice (:func:`theta_i_nodes`): the VNDF table at its nodes; each
   sample-square node is warped forward (the same continuous marginal warp) to m,
   wo = reflect(wi, m), and
   ``rho = f(wi, wo) cos(theta_o) 4 sigma(wi) / D(m)``, with D and sigma *as interpolated
   from the written tables* (so that the product is exact at the nodes); 0 where wo is
   below the horizon.  The luminance table is the luminance (Rec. 709 Y) of rho, floored
   at ``LUMINANCE_FLOOR`` times the slice maximum.

The error of a baked file is the interpolation of rho between sample-square nodes and
theta_i slices; docs/rgl.md gives the measured figures per resolution.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write

# ------------------------------------------------------------------ tensor file
MAGIC = b"tensor_file\0"
VERSION = (1, 0)
ALIGN = 8  # data offsets are multiples of this (as Mitsuba's writer)
DTYPES = {
    1: np.uint8,
    2: np.int8,
    3: np.uint16,
    4: np.int16,
    5: np.uint32,
    6: np.int32,
    7: np.uint64,
    8: np.int64,
    9: np.float16,
    10: np.float32,
    11: np.float64,
}
DTYPE_CODES = {np.dtype(v): k for k, v in DTYPES.items()}
MAX_NDIM = 16  # a sanity bound on a field's rank (RGL files use <= 5)

# ----------------------------------------------------------------- RGL content
Y_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB luminance
# D is floored at this fraction of its maximum: rho = f cos 4 sigma / D must stay finite
# where the retro-reflection vanishes (e.g. at grazing m).
NDF_FLOOR = 1e-4
# The luminance (sampling) table is floored at this fraction of its slice maximum, so
# that no region where rho > 0 has zero sampling density (an unbiased estimator).
LUMINANCE_FLOOR = 1e-4
POWER_ITERATIONS = 32  # fixed-point iterations of the NDF (converged to ~1e-6)
QUAD_U = 1024  # midpoints in u of the sigma quadrature
# Incident slices stop short of grazing: at theta_i = pi/2 every reflection is below the
# horizon and the slice would be all zero.  Beyond the last slice Mitsuba clamps.
THETA_I_MAX = math.radians(89.5)
SAMPLE_EPS = 1e-7  # warp inputs are kept in [eps, 1 - eps] (as Mitsuba)
SEGMENT_CONST = 1e-4  # a segment is treated as constant when |v0-v1| < this (v0+v1)
CHUNK = 1 << 16  # pairs per call of the baked function

DEFAULTS = {"theta_i": 32, "sample": 64, "vndf": 128, "ndf": 256}
# Wavelengths (nm) of a spectral bake: Mitsuba's visible range 360-830 in 20 nm steps (the
# sigmoid spectra are smooth; Mitsuba interpolates linearly and clamps beyond the ends).
WAVELENGTHS = np.arange(360.0, 831.0, 20.0)
SPECTRAL_SUFFIX = "_spec.bsdf"  # the RGL database's name for spectral files

REQUIRED = ("theta_i", "phi_i", "ndf", "sigma", "vndf", "luminance", "description", "jacobian")


class RGLFormatError(InputError):
    """An RGL / tensor file that cannot be read.  The one-line message names the file."""


def read_tensor_file(path) -> dict[str, np.ndarray]:
    """Every field of a TensorFile, in file order, as native numpy arrays (copies)."""
    p = Path(path)
    try:
        buf = p.read_bytes()
    except FileNotFoundError:
        raise RGLFormatError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise RGLFormatError(f"{p}: is a directory, not a tensor file") from None
    except OSError as e:
        raise RGLFormatError(f"{p}: cannot read ({e.strerror or e})") from None
    return parse_tensor_file(buf, source=str(p))


def parse_tensor_file(buf: bytes, *, source: str = "<bytes>") -> dict[str, np.ndarray]:
    """:func:`read_tensor_file` on bytes in memory."""
    pos = 0

    def take(n: int, what: str) -> bytes:
        nonlocal pos
        if pos + n > len(buf):
            raise RGLFormatError(f"{source}: truncated ({len(buf)} bytes) while reading {what}")
        out = buf[pos : pos + n]
        pos += n
        return out

    if take(len(MAGIC), "the header") != MAGIC:
        raise RGLFormatError(f"{source}: not a tensor file (header is not 'tensor_file')")
    version = tuple(take(2, "the version"))
    if version != VERSION:
        raise RGLFormatError(f"{source}: tensor file version {version}, expected {VERSION}")
    (count,) = struct.unpack("<I", take(4, "the field count"))
    specs = []
    for k in range(count):
        (n,) = struct.unpack("<H", take(2, f"field {k}"))
        try:
            name = take(n, f"field {k}'s name").decode("utf-8")
        except UnicodeDecodeError:
            raise RGLFormatError(f"{source}: field {k}: name is not UTF-8") from None
        ndim, code, offset = struct.unpack("<HBQ", take(11, f"field {name!r}"))
        if code not in DTYPES:
            raise RGLFormatError(f"{source}: field {name!r}: unknown dtype code {code}")
        if ndim > MAX_NDIM:
            raise RGLFormatError(f"{source}: field {name!r}: rank {ndim} > {MAX_NDIM}")
        shape = struct.unpack(f"<{ndim}Q", take(8 * ndim, f"field {name!r}'s shape"))
        specs.append((name, np.dtype(DTYPES[code]).newbyteorder("<"), shape, offset))
    out = {}
    for name, dtype, shape, offset in specs:
        size = math.prod(shape) * dtype.itemsize
        if offset + size > len(buf):
            raise RGLFormatError(
                f"{source}: field {name!r}: data ends at byte "
                f"{offset + size}, file has {len(buf)} (truncated)"
            )
        arr = np.frombuffer(buf, dtype=dtype, count=math.prod(shape), offset=offset)
        out[name] = arr.reshape(shape).astype(dtype.newbyteorder("="))
    return out


def tensor_file_bytes(fields: Mapping[str, object]) -> bytes:
    """The TensorFile encoding of ``fields`` (name -> array, or str stored as uint8)."""
    arrays = {}
    for name, v in fields.items():
        a = (
            np.frombuffer(v.encode("utf-8"), np.uint8)
            if isinstance(v, str)
            else np.ascontiguousarray(v)
        )
        if a.dtype.newbyteorder("=") not in DTYPE_CODES:
            raise ValueError(f"{name}: unsupported dtype {a.dtype}")
        arrays[name] = a
    header = bytearray(MAGIC + bytes(VERSION) + struct.pack("<I", len(arrays)))
    header_size = len(header) + sum(
        2 + len(n.encode("utf-8")) + 11 + 8 * a.ndim for n, a in arrays.items()
    )
    body, offset = bytearray(), header_size
    for name, a in arrays.items():
        start = -(-offset // ALIGN) * ALIGN
        label = name.encode("utf-8")
        header += struct.pack("<H", len(label)) + label
        header += struct.pack("<HBQ", a.ndim, DTYPE_CODES[a.dtype.newbyteorder("=")], start)
        header += struct.pack(f"<{a.ndim}Q", *a.shape)
        body += bytes(start - offset) + a.astype(a.dtype.newbyteorder("<")).tobytes()
        offset = start + a.nbytes
    return bytes(header) + bytes(body)


def write_tensor_file(path, fields: Mapping[str, object]) -> None:
    """Write ``fields`` as a TensorFile, atomically."""
    atomic_write(path, tensor_file_bytes(fields))


# ------------------------------------------------- continuous marginal 2D warp
def _lerp(a, b, t):
    return a + (b - a) * t


def _first_false(pred: Callable, end: int, n: int) -> np.ndarray:
    """Per element, the smallest index i in [0, end] with pred(i) False, or end (a
    vectorised bisection; pred is monotone: True then False)."""
    lo, hi = np.zeros(n, np.int64), np.full(n, end, np.int64)
    for _ in range(int(math.log2(max(end, 1))) + 2):
        mid = (lo + hi) >> 1
        c = pred(mid)
        lo = np.where(c, np.minimum(mid + 1, hi), lo)
        hi = np.where(c, hi, mid)
    return lo


class Marginal2D:
    """A bilinear density on [0, 1]^2 tabulated at ``data[..., H, W]`` nodes, optionally
    conditioned on parameters (the leading axes, interpolated linearly at ``params``
    values), with the continuous marginal warp of Mitsuba's ``Marginal2D<..., true>``:
    ``sample`` maps the unit square to the density, ``invert`` is its inverse, ``eval``
    the (normalised, when ``normalize``) density.  float64 throughout."""

    def __init__(self, data, params=(), *, normalize: bool = True):
        d = np.array(data, dtype=np.float64)
        self.params = [np.asarray(p, dtype=np.float64).reshape(-1) for p in params]
        if d.ndim != 2 + len(self.params) or any(
            d.shape[k] != len(p) for k, p in enumerate(self.params)
        ):
            raise ValueError(
                f"data: shape {d.shape} does not match parameters "
                f"{[len(p) for p in self.params]} + (H, W)"
            )
        self.h, self.w = d.shape[-2:]
        if self.h < 2 or self.w < 2:
            raise ValueError(f"data: a 2D table needs at least 2 x 2 nodes, got {d.shape}")
        d = d.reshape(-1, self.h, self.w)
        sx, sy = 0.5 / (self.w - 1), 0.5 / (self.h - 1)  # trapezoids
        cond = np.cumsum(sx * (d[:, :, :-1] + d[:, :, 1:]), axis=2)  # (S, H, W-1)
        rows = cond[:, :, -1]
        marg = np.cumsum(sy * (rows[:, :-1] + rows[:, 1:]), axis=1)  # (S, H-1)
        self.normalized = normalize
        if normalize:
            total = marg[:, -1]
            if not np.all(total > 0):
                raise ValueError("data: a slice integrates to 0 (cannot be normalised)")
            norm = 1.0 / total
            d, cond, marg = (
                d * norm[:, None, None],
                cond * norm[:, None, None],
                marg * norm[:, None],
            )
        self.data = d.reshape(len(d), -1)
        self.cond = cond.reshape(len(d), -1)
        self.marg = marg

    # corner slices and weights of the parameter interpolation (C order over params)
    def _corners(self, params, n: int):
        corners = [(np.zeros(n, np.int64), np.ones(n))]
        for values, p in zip(self.params, params, strict=True):
            p = np.broadcast_to(np.asarray(p, dtype=np.float64), (n,))
            if len(values) == 1:
                corners = [(s * 1, w) for s, w in corners]
                continue
            i = np.clip(np.searchsorted(values, p, side="left") - 1, 0, len(values) - 2)
            t = np.clip((p - values[i]) / (values[i + 1] - values[i]), 0.0, 1.0)
            corners = [
                (s * len(values) + i + k, w * (t if k else 1.0 - t))
                for s, w in corners
                for k in (0, 1)
            ]
        return corners

    @staticmethod
    def _look(table, corners, idx):
        return sum(w * table[s, idx] for s, w in corners)

    def eval(self, pos, params=()) -> np.ndarray:
        """The density (or the raw interpolant, if not normalised) at ``pos`` (N, 2)."""
        pos = np.clip(np.asarray(pos, dtype=np.float64), 0.0, 1.0)
        c = self._corners(params, len(pos))
        x, y = pos[:, 0] * (self.w - 1), pos[:, 1] * (self.h - 1)
        ix = np.minimum(x.astype(np.int64), self.w - 2)
        iy = np.minimum(y.astype(np.int64), self.h - 2)
        fx, fy = x - ix, y - iy
        i = iy * self.w + ix
        lk = self._look
        return _lerp(
            _lerp(lk(self.data, c, i), lk(self.data, c, i + 1), fx),
            _lerp(lk(self.data, c, i + self.w), lk(self.data, c, i + self.w + 1), fx),
            fy,
        )

    @staticmethod
    def _segment_sample(s, inv_width, v0, v1):
        # invert the integral of a linear density over [0, t]: (v1-v0) t^2 + 2 v0 t = s
        s = s * (2.0 * inv_width)
        linear = np.abs(v0 - v1) > SEGMENT_CONST * (v0 + v1)
        num = np.where(linear, v0 - np.sqrt(np.maximum(v0 * v0 + s * (v1 - v0), 0.0)), s)
        den = np.where(linear, v0 - v1, v0 + v1)
        return np.divide(num, den, out=np.zeros_like(num), where=den != 0)

    def sample(self, u, params=()):
        """Unit square (N, 2) -> (points (N, 2), density (N,))."""
        u = np.clip(np.array(u, dtype=np.float64), SAMPLE_EPS, 1.0 - SAMPLE_EPS)
        n, w = len(u), self.w
        c = self._corners(params, n)
        lk = self._look
        ux, uy = u[:, 0], u[:, 1]
        if not self.normalized:
            uy = uy * lk(self.marg, c, np.full(n, self.h - 2))
        row = _first_false(lambda i: lk(self.marg, c, i) < uy, self.h - 2, n)
        uy = uy - np.where(row > 0, lk(self.marg, c, np.maximum(row - 1, 0)), 0.0)
        off = row * (w - 1)
        r0, r1 = lk(self.cond, c, off + w - 2), lk(self.cond, c, off + 2 * (w - 1) - 1)
        fy = self._segment_sample(uy, self.h - 1, r0, r1)
        ux = ux * _lerp(r0, r1, fy)

        def cdf(i):
            return _lerp(lk(self.cond, c, off + i), lk(self.cond, c, off + (w - 1) + i), fy)

        col = _first_false(lambda i: cdf(i) < ux, w - 2, n)
        ux = ux - np.where(col > 0, cdf(np.maximum(col - 1, 0)), 0.0)
        i = row * w + col
        c0 = _lerp(lk(self.data, c, i), lk(self.data, c, i + w), fy)
        c1 = _lerp(lk(self.data, c, i + 1), lk(self.data, c, i + w + 1), fy)
        fx = self._segment_sample(ux, w - 1, c0, c1)
        pts = np.stack([(col + fx) / (w - 1), (row + fy) / (self.h - 1)], -1)
        return pts, _lerp(c0, c1, fx)

    def invert(self, pts, params=()):
        """Points (N, 2) -> (unit square (N, 2), density (N,)): the inverse of sample."""
        pts = np.clip(np.asarray(pts, dtype=np.float64), 0.0, 1.0)
        n, w = len(pts), self.w
        c = self._corners(params, n)
        lk = self._look
        x, y = pts[:, 0] * (w - 1), pts[:, 1] * (self.h - 1)
        ix = np.minimum(x.astype(np.int64), w - 2)
        iy = np.minimum(y.astype(np.int64), self.h - 2)
        fx, fy = x - ix, y - iy
        i = iy * w + ix
        c0 = _lerp(lk(self.data, c, i), lk(self.data, c, i + w), fy)
        c1 = _lerp(lk(self.data, c, i + 1), lk(self.data, c, i + w + 1), fy)
        pdf = _lerp(c0, c1, fx)
        # the integral of the linear segment over [0, fx]
        sx = fx * _lerp(c0, c1, 0.5 * fx) / (w - 1)
        off = iy * (w - 1)

        def cdf(k):
            return _lerp(lk(self.cond, c, off + k), lk(self.cond, c, off + (w - 1) + k), fy)

        sx = sx + np.where(ix > 0, cdf(np.maximum(ix - 1, 0)), 0.0)
        r0, r1 = lk(self.cond, c, off + w - 2), lk(self.cond, c, off + 2 * (w - 1) - 1)
        row_total = _lerp(r0, r1, fy)
        sx = np.divide(sx, row_total, out=np.zeros_like(sx), where=row_total != 0)
        sy = fy * _lerp(r0, r1, 0.5 * fy) / (self.h - 1)
        sy = sy + np.where(iy > 0, lk(self.marg, c, np.maximum(iy - 1, 0)), 0.0)
        if not self.normalized:
            sy = sy / lk(self.marg, c, np.full(n, self.h - 2))
        return np.stack([sx, sy], -1), pdf


# --------------------------------------------------------------- angles <-> square
def theta_to_u(theta):
    return np.sqrt(np.maximum(theta, 0.0) * (2.0 / math.pi))


def u_to_theta(u):
    return np.square(u) * (math.pi / 2.0)


def phi_to_v(phi):
    return (phi + math.pi) / (2.0 * math.pi)


def v_to_phi(v):
    return (2.0 * v - 1.0) * math.pi


def elevation(d):
    """theta of unit vectors (..., 3), stable near the pole (2 asin(|d - z| / 2))."""
    dist = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + (d[..., 2] - 1.0) ** 2)
    return 2.0 * np.arcsin(np.clip(0.5 * dist, 0.0, 1.0))


def _spherical(theta, phi):
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], -1)


# ------------------------------------------------------------------- the reader
class RGLBRDF:
    """An RGL material in memory; ``eval`` follows Mitsuba's ``measured`` (isotropic RGB
    files).  ``fields`` is the tensor file's content."""

    def __init__(self, fields: dict[str, np.ndarray], *, source: str = "<memory>"):
        self.source = str(source)
        self.fields = fields
        f = fields

        def bad(msg):
            return RGLFormatError(f"{self.source}: {msg}")

        missing = [k for k in REQUIRED if k not in f]
        if missing:
            raise bad(f"not an RGL material: missing field(s) {missing}")
        if "wavelengths" in f:
            raise bad(
                "spectral RGL file (field 'wavelengths'): only RGB files (field "
                "'rgb', the *_rgb.bsdf of the RGL database) can be read here"
            )
        if "rgb" not in f:
            raise bad("missing field 'rgb'")

        def check(name, ndim, dtype=np.float32):
            a = f[name]
            if a.ndim != ndim or a.dtype != dtype:
                raise bad(
                    f"field {name!r}: expected {ndim}-D {np.dtype(dtype).name}, got "
                    f"{a.ndim}-D {a.dtype.name} {a.shape}"
                )
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                raise bad(f"field {name!r}: non-finite values")
            return a

        th, ph = check("theta_i", 1), check("phi_i", 1)
        ndf, sigma = check("ndf", 2), check("sigma", 2)
        vndf, lum, rgb = check("vndf", 4), check("luminance", 4), check("rgb", 5)
        check("description", 1, np.uint8)
        jac = check("jacobian", 1, np.uint8)
        lead = (len(ph), len(th))
        for name, a in (("vndf", vndf), ("luminance", lum), ("rgb", rgb)):
            if a.shape[:2] != lead:
                raise bad(
                    f"field {name!r}: leading shape {a.shape[:2]}, expected "
                    f"(len(phi_i), len(theta_i)) = {lead}"
                )
        if rgb.shape[2] != 3 or rgb.shape[3:] != lum.shape[2:] or lum.shape[2] != lum.shape[3]:
            raise bad(
                f"fields 'rgb' {rgb.shape} and 'luminance' {lum.shape}: expected "
                "(P, T, 3, N, N) and (P, T, N, N)"
            )
        if len(jac) != 1:
            raise bad(f"field 'jacobian': expected 1 value, got {len(jac)}")
        if len(ph) > 2:
            raise bad(
                f"anisotropic material ({len(ph)} phi_i slices): only isotropic "
                "files (phi_i of size 1 or 2) are supported"
            )
        if min(ndf.shape + sigma.shape + vndf.shape[2:] + lum.shape[2:]) < 2:
            raise bad("a 2D table has fewer than 2 nodes along an axis")
        if np.any(np.diff(th) <= 0):
            raise bad("field 'theta_i': not strictly increasing")
        self.description = bytes(f["description"]).decode("utf-8", "replace")
        self.jacobian = bool(jac[0])
        self.theta_i, self.phi_i = th.astype(np.float64), ph.astype(np.float64)
        try:
            self._ndf = Marginal2D(ndf, normalize=False)
            self._sigma = Marginal2D(sigma, normalize=False)
            self._vndf = Marginal2D(vndf, (self.phi_i, self.theta_i))
            self._lum = Marginal2D(lum, (self.phi_i, self.theta_i))
        except ValueError as e:
            raise bad(f"{e}") from None
        self._rgb = [
            Marginal2D(rgb[:, :, c], (self.phi_i, self.theta_i), normalize=False) for c in range(3)
        ]

    def __repr__(self) -> str:
        r = self.fields["rgb"].shape
        return (
            f"RGLBRDF({self.source!r}, theta_i {r[1]}, sample grid {r[3]}x{r[4]}, "
            f"{self.description!r})"
        )

    def _params(self, wi):
        return np.arctan2(wi[:, 1], wi[:, 0]), elevation(wi)

    def eval(self, wi, wo) -> np.ndarray:
        """f(wi, wo) in 1/sr (no cosine), (..., 3) float64; 0 below the horizon."""
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        wi, wo = np.broadcast_arrays(wi, wo)
        batch = wi.shape[:-1]
        wi, wo = wi.reshape(-1, 3), wo.reshape(-1, 3)
        out = np.zeros((len(wi), 3))
        ok = (
            np.all(np.isfinite(wi), -1)
            & np.all(np.isfinite(wo), -1)
            & (wi[:, 2] > 0)
            & (wo[:, 2] > 0)
        )
        rows = np.flatnonzero(ok)
        for s in range(0, len(rows), CHUNK):
            r = rows[s : s + CHUNK]
            a = wi[r] / np.linalg.norm(wi[r], axis=-1, keepdims=True)
            b = wo[r] / np.linalg.norm(wo[r], axis=-1, keepdims=True)
            out[r] = self._f_cos(a, b) / b[:, 2:3]
        return out.reshape(batch + (3,))

    def _f_cos(self, wi, wo) -> np.ndarray:
        """Mitsuba's ``measured`` eval (f cos theta_o) for unit directions above the horizon."""
        m = wi + wo
        m /= np.linalg.norm(m, axis=-1, keepdims=True)
        phi_i, theta_i = self._params(wi)
        u_wi = np.stack([theta_to_u(theta_i), phi_to_v(phi_i)], -1)
        u_m = np.stack(
            [theta_to_u(elevation(m)), phi_to_v(np.arctan2(m[:, 1], m[:, 0]) - phi_i)], -1
        )
        u_m[:, 1] -= np.floor(u_m[:, 1])
        params = (phi_i, theta_i)
        s, _ = self._vndf.invert(u_m, params)
        val = np.stack([ch.eval(s, params) for ch in self._rgb], -1)
        if self.jacobian:
            val *= (self._ndf.eval(u_m) / (4.0 * self._sigma.eval(u_wi)))[:, None]
        return val

    def sample(self, wi, u):
        """wo for ``wi`` (N, 3) from uniform ``u`` (N, 2) as Mitsuba's ``measured`` samples
        it (luminance warp, then VNDF warp, then reflection) -> (wo, pdf in 1/sr).  wo may
        lie below the horizon (then Mitsuba's sample is void)."""
        wi = np.asarray(wi, dtype=np.float64)
        phi_i, theta_i = self._params(wi)
        params = (phi_i, theta_i)
        s, p_lum = self._lum.sample(np.asarray(u, dtype=np.float64)[:, ::-1], params)
        u_m, p_vndf = self._vndf.sample(s, params)
        theta_m = u_to_theta(u_m[:, 0])
        m = _spherical(theta_m, v_to_phi(u_m[:, 1]) + phi_i)
        dot = np.sum(wi * m, -1)
        jac = np.maximum(2 * math.pi**2 * u_m[:, 0] * np.sin(theta_m), 1e-6) * 4 * dot
        wo = 2.0 * dot[:, None] * m - wi
        return wo, p_lum * p_vndf / jac

    def node_pairs(self, *, seed: int = 0):
        """(wi, wo), each (K, 3) float64: the direction pairs of the value nodes (every
        theta_i slice x sample-square node) with both directions above the horizon.  The
        file is exact there up to float32.  phi_i is random (isotropic files)."""
        rng = np.random.default_rng(seed)
        n = self.fields["rgb"].shape[-1]
        sx, sy = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
        s = np.stack([sx.ravel(), sy.ravel()], -1)
        wis, wos = [], []
        for th in self.theta_i:
            phi = rng.random() * 2 * math.pi
            params = (np.full(len(s), phi), np.full(len(s), th))
            u_m, _ = self._vndf.sample(s, params)
            m = _spherical(u_to_theta(u_m[:, 0]), v_to_phi(u_m[:, 1]) + phi)
            wi = np.broadcast_to(_spherical(np.array(th), np.array(phi)), m.shape)
            wo = 2.0 * np.sum(wi * m, -1, keepdims=True) * m - wi
            keep = (wo[:, 2] > 0) & (wi[:, 2] > 0)
            wis.append(wi[keep])
            wos.append(wo[keep] / np.linalg.norm(wo[keep], axis=-1, keepdims=True))
        return np.concatenate(wis), np.concatenate(wos)

    def sample_pairs(self, n: int, rng=None):
        """``n`` training pairs (wi, wo, f) (n, 3) each: wi uniform on the hemisphere, wo
        from the material's own sampler for half the pairs and cosine-distributed for the
        rest; pairs below the horizon are redrawn."""
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        wis, wos, got = [], [], 0
        while got < n:
            m = int((n - got) * 1.5) + 64
            u = rng.random((m, 2))
            wi = _spherical(np.arccos(1.0 - u[:, 0] * (1.0 - 1e-6)), 2 * math.pi * u[:, 1])
            half = m // 2
            wo_s, _ = self.sample(wi[:half], rng.random((half, 2)))
            v = rng.random((m - half, 2))
            wo_c = _spherical(np.arcsin(np.sqrt(v[:, 0])), 2 * math.pi * v[:, 1])
            wo = np.concatenate([wo_s, wo_c])
            keep = (wo[:, 2] > 0) & (wi[:, 2] > 0)
            wis.append(wi[keep])
            wos.append(wo[keep] / np.linalg.norm(wo[keep], axis=-1, keepdims=True))
            got += int(keep.sum())
        wi, wo = np.concatenate(wis)[:n], np.concatenate(wos)[:n]
        return wi, wo, self.eval(wi, wo)


def read_rgl(path) -> RGLBRDF:
    """Read an RGL ``.bsdf`` file (isotropic, RGB).  Any problem raises RGLFormatError."""
    return RGLBRDF(read_tensor_file(path), source=str(path))


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
    write_tensor_file(path, fields)
    if spectral:
        return None
    return RGLBRDF(parse_tensor_file(tensor_file_bytes(fields)), source=os.fspath(path))
