"""MERL ``.binary`` measured BRDFs: read, write, look up, bake; real-material fixtures.

    from neural_brdf import merl
    m = merl.read_merl("alum-bronze.binary")        # MerlFormatError on a bad file
    f = m.eval(wi, wo)                               # (..., 3) in 1/sr, trilinear
    wi, wo, f = m.sample_pairs(8192, rng=0)          # training pairs on the measured support
    merl.bake(analytic.create("microfacet", alpha=0.3), "ggx.binary")
    merl.bake(merl.nbrdf_fixture(npz, "gold-metallic-paint"), "gold.binary")

The format (Matusik et al. 2003, "A data-driven reflectance model"; MERL's BRDFRead.cpp)
-----------------------------------------------------------------------------------
A header of three little-endian int32, the grid dimensions ``(90, 90, 180)`` for
``(theta_h, theta_d, phi_d)``, then ``3 * 90 * 90 * 180`` float64, channel-major: all of R,
then G, then B.  Within a channel the flat index is
``(i_h * 90 + i_d) * 180 + i_p``.  A stored value times its channel's scale is the BRDF in
1/sr (no cosine): R 1/1500, G 1.15/1500, B 1.66/1500.  A negative stored value marks a
sample that was not measured.

Bins.  With the Rusinkiewicz (1998) half/difference angles of :func:`analytic.frame.rusinkiewicz`,

* theta_h: index ``sqrt(theta_h / (pi/2)) * 90`` (non-linear, dense near the specular peak);
* theta_d: index ``theta_d / (pi/2) * 90``;
* phi_d:   index ``(phi_d mod pi) / pi * 180``.  Swapping wi and wo sends phi_d to
  phi_d + pi (reciprocity), so MERL folds phi_d into [0, pi).

Bin ``i`` covers the index interval ``[i, i + 1)``; MERL's own lookup truncates the index, and
``interpolation="nearest"`` does the same.  The grid angles this module reports and bakes at
are the bin *centres* in index space, ``i + 0.5`` (for theta_h that is
``((i + 0.5) / 90)^2 * pi/2``).  Some tools (e.g. the NBRDF scripts) put a bin's value at
its lower edge ``i / 90`` instead; the truncating lookup reads both kinds of file the same,
but interpolating readers differ by half a bin.

Trilinear interpolation works in index space between bin centres.  theta_h and theta_d
clamp at the ends of their range (constant beyond the first and last centre); phi_d is
periodic with period pi, so bin 179 and bin 0 are neighbours across phi_d = 0 = pi.

Unmeasured bins.  ``valid`` is False where any channel is negative.  Such a bin takes no
part in interpolation: the eight weights are renormalised over the measured neighbours,
and where no measured neighbour carries weight the result is 0.  ``nearest`` returns 0 in
an unmeasured bin.  Lookups are never NaN, and are 0 below the horizon.

Reciprocity.  ``eval(wi, wo)`` puts the pair in a canonical order before computing its
angles, so ``eval(wi, wo) == eval(wo, wi)`` bit for bit; the phi_d fold is what makes
that order irrelevant to the value.
"""

from __future__ import annotations

import csv
import difflib
import functools
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from analytic import frame, fresnel
from neural_brdf.fileio import atomic_write

# ----------------------------------------------------------------------- the format
RES_THETA_H = 90
RES_THETA_D = 90
RES_PHI_D = 180
SHAPE = (RES_THETA_H, RES_THETA_D, RES_PHI_D)  # header dims, in file order
N_BINS = RES_THETA_H * RES_THETA_D * RES_PHI_D  # 1,458,000 per channel
SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])  # stored value * SCALE = f
HEADER_BYTES = 3 * 4
FILE_BYTES = HEADER_BYTES + 3 * N_BINS * 8
# The raw value written for a bin with no measurement (bake: centre below the horizon).
# Any negative value means "unmeasured"; MERL's own files use negative values too.
UNMEASURED = -1.0
# Index coordinates within this distance of a bin centre are snapped onto it, so that a
# lookup at a centre returns the stored value exactly.  The angles -> directions ->
# angles round trip in float64 is good to 2e-8 index units at worst (theta_h bin 0, where
# acos is ill-conditioned, and phi_d at tiny theta_d; measured over the whole grid);
# snapping within 1e-6 of a bin moves an interpolated value by at most 1e-6 of a
# neighbour difference.
SNAP = 1e-6
# Bins evaluated per chunk in bake and eval: 2^17 pairs take ~30 MB of temporaries.
CHUNK = 1 << 17

INTERPOLATIONS = ("trilinear", "nearest")
SAMPLE_SPACES = ("index", "angle")


class MerlFormatError(ValueError):
    """A MERL file that cannot be read.  The one-line message names the file."""


# ------------------------------------------------------------------ grid geometry
def theta_h_index(theta_h):
    """Continuous theta_h index in [0, 90]: sqrt(theta_h / (pi/2)) * 90."""
    t = np.clip(np.asarray(theta_h, dtype=np.float64) / (math.pi / 2), 0.0, 1.0)
    return np.sqrt(t) * RES_THETA_H


def theta_d_index(theta_d):
    """Continuous theta_d index in [0, 90]: theta_d / (pi/2) * 90."""
    return np.clip(np.asarray(theta_d, dtype=np.float64) / (math.pi / 2), 0.0, 1.0) * RES_THETA_D


def fold_phi_d(phi_d):
    """phi_d mod pi, in [0, pi) (the reciprocity fold)."""
    p = np.mod(np.asarray(phi_d, dtype=np.float64), math.pi)
    # np.mod(-1e-18, pi) rounds to pi itself, which is the same point as 0
    return np.where(p >= math.pi, 0.0, p)


def phi_d_index(phi_d):
    """Continuous phi_d index in [0, 180), after the fold."""
    return fold_phi_d(phi_d) / math.pi * RES_PHI_D


def bin_centres() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bin-centre angles (theta_h (90,), theta_d (90,), phi_d (180,)) in radians."""
    ih = (np.arange(RES_THETA_H) + 0.5) / RES_THETA_H
    theta_h = ih * ih * (math.pi / 2)
    theta_d = (np.arange(RES_THETA_D) + 0.5) / RES_THETA_D * (math.pi / 2)
    phi_d = (np.arange(RES_PHI_D) + 0.5) / RES_PHI_D * math.pi
    return theta_h, theta_d, phi_d


def unravel(flat) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat bin index -> (i_h, i_d, i_p)."""
    i_h, i_d, i_p = np.unravel_index(np.asarray(flat), SHAPE)
    return i_h, i_d, i_p


@functools.lru_cache(maxsize=1)
def _grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wi, wo) (N_BINS, 3) at every bin centre, and the above-horizon mask (N_BINS,).

    Computed once per process and kept read-only (70 MB): every bake, and every
    comparison against a grid, needs the same 1.458M direction pairs.
    """
    th_c, td_c, pd_c = bin_centres()
    wi = np.empty((N_BINS, 3))
    wo = np.empty((N_BINS, 3))
    for s in range(0, N_BINS, CHUNK):
        ih, id_, ip = unravel(np.arange(s, min(s + CHUNK, N_BINS)))
        wi[s : s + len(ih)], wo[s : s + len(ih)] = directions(
            th_c[ih], np.zeros(len(ih)), td_c[id_], pd_c[ip]
        )
    above = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    for a in (wi, wo, above):
        a.flags.writeable = False
    return wi, wo, above


def grid_directions(start: int = 0, stop: int = N_BINS) -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo), each (stop - start, 3) float64, at the centres of flat bins [start, stop)
    (flat index = ``(i_h * 90 + i_d) * 180 + i_p``, the order of ``values.reshape(-1, 3)``).

    phi_h = 0 (an isotropic BRDF does not depend on it).  Some centres lie below the
    horizon (a z <= 0); see :func:`grid_above_horizon`.
    """
    wi, wo, _ = _grid()
    return wi[start:stop].copy(), wo[start:stop].copy()


def grid_above_horizon() -> np.ndarray:
    """(90, 90, 180) bool: both directions of the bin centre are strictly above the horizon."""
    return _grid()[2].reshape(SHAPE).copy()


def directions(theta_h, phi_h, theta_d, phi_d) -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo) float64 numpy from Rusinkiewicz angles (broadcast together)."""
    t = [
        torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))
        for a in (theta_h, phi_h, theta_d, phi_d)
    ]
    wi, wo = frame.from_rusinkiewicz(*t)
    return wi.numpy(), wo.numpy()


def _canonical(wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The pair in a canonical order (lexicographic on x, y, z), so that (wi, wo) and
    (wo, wi) run the same arithmetic afterwards: reciprocity then holds bit for bit."""
    gt, eq = wi > wo, wi == wo
    swap = gt[..., 0] | (eq[..., 0] & (gt[..., 1] | (eq[..., 1] & gt[..., 2])))
    swap = swap[..., None]
    return torch.where(swap, wo, wi), torch.where(swap, wi, wo)


def _angles(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta_h, theta_d, phi_d) of the canonically ordered pair."""
    a, b = _canonical(torch.from_numpy(wi), torch.from_numpy(wo))
    th, _, td, pd = frame.rusinkiewicz(a, b)
    return th.numpy(), td.numpy(), pd.numpy()


def _snap(x: np.ndarray) -> np.ndarray:
    r = np.rint(x)
    return np.where(np.abs(x - r) < SNAP, r, x)


def _choice(name: str, value, options) -> str:
    if value not in options:
        raise ValueError(f"{name}: must be one of {list(options)}, got {value!r}")
    return value


def _rng(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


# ------------------------------------------------------------------------ the BRDF
class MerlBRDF:
    """A MERL grid in memory.

    ``raw`` (3, 90, 90, 180) float64 is the file's content (channel-major, unscaled,
    negative = unmeasured); ``values`` (90, 90, 180, 3) is the BRDF in 1/sr (``raw * SCALE``,
    0 where not ``valid``); ``valid`` (90, 90, 180) marks measured bins.
    """

    def __init__(self, raw, *, source: str = "<memory>"):
        raw = np.array(raw, dtype=np.float64)  # a private copy
        if raw.shape != (3,) + SHAPE:
            raise ValueError(f"raw: expected shape {(3,) + SHAPE}, got {raw.shape}")
        bad = ~np.isfinite(raw)
        if bad.any():
            raise ValueError(f"raw: {int(bad.sum())} non-finite values")
        raw.flags.writeable = False
        self.raw = raw
        self.source = str(source)
        self.valid = np.all(raw >= 0, axis=0)
        self.valid.flags.writeable = False
        table = (raw.reshape(3, N_BINS).T * SCALE).copy()  # (N, 3) f in 1/sr
        table[~self.valid.reshape(-1)] = 0.0
        table.flags.writeable = False
        self._table = table
        self._valid_flat = self.valid.reshape(-1)
        self._valid_bins: np.ndarray | None = None

    # -- construction
    @classmethod
    def from_values(cls, values, *, valid=None, source: str = "<memory>") -> MerlBRDF:
        """From BRDF values (90, 90, 180, 3) in 1/sr.  Bins where ``valid`` is False, or
        where a value is negative, are stored as unmeasured."""
        v = np.asarray(values, dtype=np.float64)
        if v.shape != SHAPE + (3,):
            raise ValueError(f"values: expected shape {SHAPE + (3,)}, got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"values: {int((~np.isfinite(v)).sum())} non-finite values")
        raw = np.moveaxis(v, -1, 0) / SCALE[:, None, None, None]
        if valid is not None:
            valid = np.asarray(valid, dtype=bool)
            if valid.shape != SHAPE:
                raise ValueError(f"valid: expected shape {SHAPE}, got {valid.shape}")
            raw = np.where(valid[None], raw, UNMEASURED)
        return cls(raw, source=source)

    def __repr__(self) -> str:
        return f"MerlBRDF({self.source!r}, measured bins {int(self.valid.sum())}/{N_BINS})"

    # -- grid
    @property
    def values(self) -> np.ndarray:
        return self._table.reshape(SHAPE + (3,))

    theta_h = property(lambda self: bin_centres()[0], doc="bin-centre theta_h (90,)")
    theta_d = property(lambda self: bin_centres()[1], doc="bin-centre theta_d (90,)")
    phi_d = property(lambda self: bin_centres()[2], doc="bin-centre phi_d (180,)")

    def write(self, path) -> None:
        write_merl(path, self)

    # -- lookups
    def eval(self, wi, wo, *, interpolation: str = "trilinear") -> np.ndarray:
        """f(wi, wo) in 1/sr, shape (..., 3); numpy in, numpy out (float64).

        Directions are normalised; a pair with either z <= 0 (or a non-finite entry)
        gives 0.
        """
        _choice("interpolation", interpolation, INTERPOLATIONS)
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        if wi.shape[-1:] != (3,) or wo.shape[-1:] != (3,):
            raise ValueError(f"wi, wo: expected (..., 3) arrays, got {wi.shape} and {wo.shape}")
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
            out[r] = self.lookup(*_angles(a, b), interpolation=interpolation)
        return out.reshape(batch + (3,))

    def lookup(self, theta_h, theta_d, phi_d, *, interpolation: str = "trilinear") -> np.ndarray:
        """f at Rusinkiewicz angles (broadcast together) -> (..., 3).  phi_d is folded."""
        _choice("interpolation", interpolation, INTERPOLATIONS)
        th, td, pd = np.broadcast_arrays(
            *(np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d))
        )
        batch = th.shape
        uh = theta_h_index(th.reshape(-1))
        ud = theta_d_index(td.reshape(-1))
        up = phi_d_index(pd.reshape(-1))
        if interpolation == "nearest":
            # MERL's truncating lookup (BRDFRead.cpp): bin floor(index), clamped
            ih = np.minimum(uh.astype(np.int64), RES_THETA_H - 1)
            id_ = np.minimum(ud.astype(np.int64), RES_THETA_D - 1)
            ip = np.minimum(up.astype(np.int64), RES_PHI_D - 1)
            return self._table[(ih * RES_THETA_D + id_) * RES_PHI_D + ip].reshape(batch + (3,))

        # trilinear between bin centres: centre i sits at index coordinate i + 0.5
        def clamped(u, n):
            x = np.clip(_snap(u - 0.5), 0.0, n - 1.0)
            i0 = np.minimum(np.floor(x).astype(np.int64), n - 2)
            return i0, i0 + 1, x - i0

        h0, h1, fh = clamped(uh, RES_THETA_H)
        d0, d1, fd = clamped(ud, RES_THETA_D)
        xp = _snap(up - 0.5)  # in [-0.5, 179.5)
        p0 = np.floor(xp).astype(np.int64)
        fp = xp - p0
        p0, p1 = p0 % RES_PHI_D, (p0 + 1) % RES_PHI_D  # periodic in phi_d

        acc = np.zeros((len(uh), 3))
        wsum = np.zeros(len(uh))
        for ih, wh in ((h0, 1.0 - fh), (h1, fh)):
            for id_, wd in ((d0, 1.0 - fd), (d1, fd)):
                base = (ih * RES_THETA_D + id_) * RES_PHI_D
                for ip, wp in ((p0, 1.0 - fp), (p1, fp)):
                    k = base + ip
                    w = wh * wd * wp * self._valid_flat[k]
                    acc += w[:, None] * self._table[k]
                    wsum += w
        has = wsum > 0
        out = np.zeros_like(acc)
        np.divide(acc, wsum[:, None], out=out, where=has[:, None])
        return out.reshape(batch + (3,))

    # -- training data
    def sample_pairs(
        self, n: int, rng=None, *, space: str = "index", interpolation: str = "trilinear"
    ):
        """Draw ``n`` direction pairs from the measured support -> (wi, wo, f), each (n, 3).

        A measured bin is drawn, then a point uniformly inside it; phi_h is uniform in
        [0, 2 pi).  ``space="index"`` draws bins uniformly and jitters uniformly in index
        coordinates (the grid's own density: dense near the specular peak);
        ``space="angle"`` is uniform in (theta_h, theta_d, phi_d) over the measured bins.
        Pairs that land below the horizon are redrawn.  f is ``eval`` at the pair
        (``interpolation="nearest"`` gives the bin's stored value).  ``rng``: a numpy
        Generator or a seed.
        """
        _choice("space", space, SAMPLE_SPACES)
        _choice("interpolation", interpolation, INTERPOLATIONS)
        n = int(n)
        if n < 0:
            raise ValueError(f"n: must be >= 0, got {n}")
        rng = _rng(rng)
        if self._valid_bins is None:
            self._valid_bins = np.flatnonzero(self._valid_flat)
        bins = self._valid_bins
        if len(bins) == 0:
            raise ValueError(f"{self.source}: no measured bins to sample")
        p = None
        if space == "angle":
            ih = unravel(bins)[0]
            p = 2.0 * ih + 1.0  # theta_h bin width ~ (i+1)^2 - i^2
            p = p / p.sum()
        wis, wos, got, tries = [], [], 0, 0
        while got < n:
            # draw a little more than is missing: some pairs land below the horizon
            m = int((n - got) * 1.3) + 64
            ih, id_, ip = unravel(rng.choice(bins, size=m, p=p))
            u = rng.random((m, 3))
            if space == "index":
                th = ((ih + u[:, 0]) / RES_THETA_H) ** 2 * (math.pi / 2)
            else:
                lo, hi = (ih / RES_THETA_H) ** 2, ((ih + 1) / RES_THETA_H) ** 2
                th = (lo + u[:, 0] * (hi - lo)) * (math.pi / 2)
            td = (id_ + u[:, 1]) / RES_THETA_D * (math.pi / 2)
            pd = (ip + u[:, 2]) / RES_PHI_D * math.pi
            ph = rng.random(m) * (2.0 * math.pi)
            wi, wo = directions(th, ph, td, pd)
            keep = (wi[:, 2] > 0) & (wo[:, 2] > 0)
            wis.append(wi[keep])
            wos.append(wo[keep])
            got += int(keep.sum())
            tries += 1
            if tries > 50 and got == 0:  # nothing above the horizon, ever
                raise ValueError(f"{self.source}: every measured bin lies below the horizon")
        wi = np.concatenate(wis)[:n]
        wo = np.concatenate(wos)[:n]
        return wi, wo, self.eval(wi, wo, interpolation=interpolation)


# ------------------------------------------------------------------------------ I/O
def read_merl(path) -> MerlBRDF:
    """Read a MERL ``.binary`` file.  Any problem raises :class:`MerlFormatError`."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            head = fh.read(HEADER_BYTES)
            if len(head) < HEADER_BYTES:
                raise MerlFormatError(
                    f"{p}: truncated header ({len(head)} bytes; a MERL "
                    f"file starts with 3 int32 dims)"
                )
            order = "<"
            dims = tuple(int(d) for d in np.frombuffer(head, "<i4"))
            if dims != SHAPE:
                if tuple(int(d) for d in np.frombuffer(head, ">i4")) != SHAPE:
                    raise MerlFormatError(
                        f"{p}: header dims {dims}, expected {SHAPE} (theta_h, theta_d, phi_d)"
                    )
                order = ">"  # a big-endian file
            if size != FILE_BYTES:
                what = "truncated" if size < FILE_BYTES else "trailing bytes after the data"
                raise MerlFormatError(
                    f"{p}: {size} bytes, expected {FILE_BYTES} for dims {SHAPE} ({what})"
                )
            body = fh.read()
    except FileNotFoundError:
        raise MerlFormatError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise MerlFormatError(f"{p}: is a directory, not a MERL file") from None
    except OSError as e:
        raise MerlFormatError(f"{p}: cannot read ({e.strerror or e})") from None
    if len(body) != FILE_BYTES - HEADER_BYTES:  # the file changed under us
        raise MerlFormatError(
            f"{p}: read {len(body) + HEADER_BYTES} bytes, expected {FILE_BYTES} (truncated)"
        )
    raw = np.frombuffer(body, order + "f8").reshape((3,) + SHAPE)
    bad = ~np.isfinite(raw)
    if bad.any():
        c, ih, id_, ip = (int(i[0]) for i in np.nonzero(bad))
        raise MerlFormatError(
            f"{p}: {int(bad.sum())} non-finite values (first: channel "
            f"{'RGB'[c]}, bin theta_h {ih}, theta_d {id_}, phi_d {ip})"
        )
    return MerlBRDF(raw, source=str(p))  # copies to native float64


def write_merl(path, brdf_or_array) -> None:
    """Write a MERL file atomically (a temporary file in the same folder, then
    ``os.replace``): readers never see a half-written file.

    ``brdf_or_array``: a :class:`MerlBRDF` (its ``raw`` is written bit for bit) or BRDF
    values (90, 90, 180, 3) in 1/sr (negative = unmeasured).
    """
    if isinstance(brdf_or_array, MerlBRDF):
        raw = brdf_or_array.raw
    else:
        raw = MerlBRDF.from_values(brdf_or_array).raw
    body = np.asarray(SHAPE, dtype="<i4").tobytes() + raw.astype("<f8").tobytes()
    atomic_write(path, body)


# ----------------------------------------------------------------------------- bake
def _as_function(fn) -> Callable:
    if callable(fn):
        return fn
    if hasattr(fn, "eval"):  # an analytic.BRDF or a MerlBRDF
        return fn.eval
    raise TypeError(f"fn: expected a callable f(wi, wo) or an object with .eval, got {fn!r}")


def bake_brdf(fn, *, chunk: int = CHUNK, source: str = "<baked>") -> MerlBRDF:
    """Evaluate ``fn(wi, wo)`` ((N, 3) float64 numpy in, (N, 3) out) at every bin centre.

    Bins whose centre lies below the horizon are stored as unmeasured; negative model
    values are clamped to 0 (a BRDF is non-negative, and a negative stored value would
    read back as "unmeasured").  A non-finite value raises ValueError.
    """
    f = _as_function(fn)
    if int(chunk) < 1:
        raise ValueError(f"chunk: must be >= 1, got {chunk!r}")
    wi_all, wo_all, above = _grid()
    raw = np.full((3, N_BINS), UNMEASURED)
    for s in range(0, N_BINS, int(chunk)):
        e = min(s + int(chunk), N_BINS)
        up = np.flatnonzero(above[s:e])
        if len(up) == 0:
            continue
        wi, wo = wi_all[s:e], wo_all[s:e]
        val = f(wi[up], wo[up])
        if isinstance(val, torch.Tensor):
            val = val.detach().cpu().numpy()
        val = np.asarray(val, dtype=np.float64)
        if val.shape != (len(up), 3):
            raise ValueError(
                f"fn: returned shape {val.shape} for {len(up)} pairs, expected ({len(up)}, 3)"
            )
        bad = ~np.all(np.isfinite(val), -1)
        if bad.any():
            k = s + int(up[np.argmax(bad)])
            th, td, pd = (c[i] for c, i in zip(bin_centres(), unravel(k)))
            raise ValueError(
                f"fn: non-finite value at bin {unravel(k)} (theta_h {th:.6g}, "
                f"theta_d {td:.6g}, phi_d {pd:.6g})"
            )
        raw[:, s + up] = (np.maximum(val, 0.0) / SCALE).T
    return MerlBRDF(raw.reshape((3,) + SHAPE), source=source)


def bake(fn, path, *, chunk: int = CHUNK) -> MerlBRDF:
    """:func:`bake_brdf`, then :func:`write_merl` to ``path``; returns the baked grid."""
    m = bake_brdf(fn, chunk=chunk, source=str(path))
    write_merl(path, m)
    return m


# ------------------------------------------------------------ real-material fixtures
def _edge_in(wi, wo):
    """Numpy or torch in -> (was it torch, wi, wo) as broadcast tensors of one dtype."""

    def tensor(x):
        if isinstance(x, torch.Tensor):
            return x
        return torch.from_numpy(np.array(x, dtype=np.float64))  # a copy: never read-only

    is_torch = isinstance(wi, torch.Tensor) or isinstance(wo, torch.Tensor)
    wi_t, wo_t = tensor(wi), tensor(wo)
    dtype = torch.promote_types(wi_t.dtype, wo_t.dtype)
    wi_t, wo_t = torch.broadcast_tensors(wi_t.to(dtype), wo_t.to(dtype))
    return is_torch, wi_t, wo_t


def _edge_out(f: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, is_torch: bool):
    f = torch.where(((wi[..., 2] > 0) & (wo[..., 2] > 0))[..., None], f, torch.zeros_like(f))
    return f if is_torch else f.detach().cpu().numpy()


def _closest(name: str, names) -> str:
    near = difflib.get_close_matches(name, list(names), n=3)
    return f"; closest: {near}" if near else ""


def nbrdf_names(npz_path) -> list[str]:
    with np.load(npz_path) as z:
        return sorted({k.split("/")[0] for k in z.files})


def nbrdf_fixture(npz_path, name: str, *, reciprocal: bool = False) -> Callable:
    """One pretrained NBRDF network (Sztrajman et al. 2021) as f(wi, wo) -> (..., 3).

    The published architecture: a 6-21-21-3 ReLU MLP on
    x = [sin th_h, 0, cos th_h, sin th_d cos ph_d, sin th_d sin ph_d, cos th_d]
    (Rusinkiewicz angles with phi_h = 0), y = relu(relu(x W0 + b0) W1 + b1) W2 + b2,
    f = exp(y) - 1 in 1/sr with the MERL colour scales applied.  The raw output is
    returned (it can dip slightly below 0; :func:`bake` clamps), and 0 below the horizon.
    Numpy in -> numpy out, torch in -> torch out (float64 for numpy); the angles are
    computed in the input's precision, the MLP runs in float32.

    The networks are not reciprocal: f(wi, wo) and f(wo, wi) (phi_d and phi_d + pi)
    differ by a few percent typically and by over 50% in places, while a MERL grid
    folds phi_d and holds one value for both.  ``reciprocal=True`` returns
    (g(phi_d) + g(phi_d + pi)) / 2 = (g(wi, wo) + g(wo, wi)) / 2, on the canonically
    ordered pair: exactly symmetric, smooth across the fold, and what a MERL grid can
    represent.
    """
    with np.load(npz_path) as z:
        keys = [f"{name}/{k}" for k in ("W0", "b0", "W1", "b1", "W2", "b2")]
        if keys[0] not in z.files:
            names = {k.split("/")[0] for k in z.files}
            raise ValueError(f"{npz_path}: no NBRDF network named {name!r}{_closest(name, names)}")
        # float32, as the networks were trained and shipped (and twice as fast as float64)
        params = [torch.from_numpy(np.asarray(z[k], dtype=np.float32)) for k in keys]
    w0, b0, w1, b1, w2, b2 = params
    if w0.shape != (6, 21) or w2.shape[1] != 3:
        raise ValueError(
            f"{npz_path}: {name}: unexpected weight shapes {tuple(w0.shape)}, {tuple(w2.shape)}"
        )

    def net(th, td, dx, dy):
        x = torch.stack(
            [torch.sin(th), torch.zeros_like(th), torch.cos(th), dx, dy, torch.cos(td)], -1
        ).to(w0.dtype)  # (..., 6)
        y = torch.relu(x @ w0 + b0)  # (..., 21)
        y = torch.relu(y @ w1 + b1)  # (..., 21)
        return torch.expm1(y @ w2 + b2).to(th.dtype)  # exp(y) - 1, (..., 3)

    def f(wi, wo):
        is_torch, wi_t, wo_t = _edge_in(wi, wo)
        if reciprocal:
            wi_t, wo_t = _canonical(wi_t, wo_t)
        th, _, td, pd = frame.rusinkiewicz(wi_t, wo_t)
        dx, dy = torch.sin(td) * torch.cos(pd), torch.sin(td) * torch.sin(pd)
        val = net(th, td, dx, dy)
        if reciprocal:  # phi_d + pi: the difference vector's x, y negated
            val = 0.5 * (val + net(th, td, -dx, -dy))
        return _edge_out(val, wi_t, wo_t, is_torch)

    f.__name__ = f"nbrdf[{name}]"
    return f


@dataclass(frozen=True)
class ABCParams:
    """One row of merl_abc_low2012_params.csv: kD and A per channel, B, C and ior shared."""

    name: str
    kd: tuple[float, float, float]
    a: tuple[float, float, float]
    b: float
    c: float
    ior: float


def read_abc_params(csv_path) -> dict[str, ABCParams]:
    """name -> :class:`ABCParams`, from the columns name,kD_r,kD_g,kD_b,A_r,A_g,A_b,B,C,ior."""
    cols = ["name", "kD_r", "kD_g", "kD_b", "A_r", "A_g", "A_b", "B", "C", "ior"]
    out = {}
    with open(csv_path, newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames != cols:
            raise ValueError(f"{csv_path}: expected columns {cols}, got {reader.fieldnames}")
        for row in reader:
            v = {k: float(row[k]) for k in cols[1:]}
            out[row["name"]] = ABCParams(
                row["name"],
                (v["kD_r"], v["kD_g"], v["kD_b"]),
                (v["A_r"], v["A_g"], v["A_b"]),
                v["B"],
                v["C"],
                v["ior"],
            )
    return out


def abc_fixture(csv_path, name: str) -> Callable:
    """The ABC-model fit (Low et al. 2012) of one MERL material as f(wi, wo) -> (..., 3).

    Formula source: jdupuy/dj_brdf, ``dj_brdf.h`` (``abc::eval``, ``abc__ndf``,
    ``abc::gaf``, ``fresnel::unpolarized``), the code the parameter table comes from and
    pairs with, written out here from its equations:

        f = (kD + F(wi.h) D(h) G / (cos_i cos_o)) / pi
        D = A / (1 + B (1 - cos th_h))^C          (A per channel; B, C shared)
        G = min(1, 2 cos th_h cos_i / (wi.h), 2 cos th_h cos_o / (wo.h))   (V-cavity)
        F = exact unpolarised dielectric Fresnel with the fitted scalar ior

    D has the ABC profile A / (1 + B x)^C of Low et al. 2012 ("BRDF models for accurate
    and efficient rendering of glossy surfaces"), here in x = 1 - cos th_h as dj_brdf
    codes it; the paper itself was not at hand, so dj_brdf is the reference.  The 1/pi
    placement is checked in the tests against the NBRDF fit of the same materials.  F is
    :func:`analytic.fresnel.dielectric`, the same function as dj_brdf's
    ``unpolarized__eval`` in another algebraic form.  0 below the horizon.
    """
    table = read_abc_params(csv_path)
    if name not in table:
        raise ValueError(f"{csv_path}: no ABC fit for {name!r}{_closest(name, table)}")
    p = table[name]

    def f(wi, wo):
        is_torch, wi_t, wo_t = _edge_in(wi, wo)
        kd = torch.tensor(p.kd, dtype=wi_t.dtype)
        a = torch.tensor(p.a, dtype=wi_t.dtype)
        h = frame.half_vector(wi_t, wo_t)
        ci = wi_t[..., 2].clamp_min(frame.EPS_COS)
        co = wo_t[..., 2].clamp_min(frame.EPS_COS)
        ch = h[..., 2].clamp(0.0, 1.0)
        di = frame.dot(wi_t, h).clamp_min(frame.EPS_COS)
        do = frame.dot(wo_t, h).clamp_min(frame.EPS_COS)
        g = torch.minimum(2.0 * ch * ci / di, 2.0 * ch * co / do).clamp(max=1.0)
        d = a / (1.0 + p.b * (1.0 - ch))[..., None] ** p.c
        fr = fresnel.dielectric(p.ior, di)
        val = (kd + fr * d * (g / (ci * co))[..., None]) / math.pi
        return _edge_out(val, wi_t, wo_t, is_torch)

    f.__name__ = f"abc[{name}]"
    return f
