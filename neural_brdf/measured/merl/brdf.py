"""A MERL table as a BRDF (:class:`MerlBRDF`: lookup, pairs, validity) and its file
I/O (:func:`read_merl`, :func:`write_merl`)."""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path

import numpy as np

from neural_brdf import fileio
from neural_brdf.fileio import atomic_write
from neural_brdf.measured.base import MAX_VALUE, Pairs, eval_pairs
from neural_brdf.measured.merl.format import (
    CHUNK,
    FILE_BYTES,
    HEADER_BYTES,
    INTERPOLATIONS,
    N_BINS,
    RES_PHI_D,
    RES_THETA_D,
    RES_THETA_H,
    SAMPLE_SPACES,
    SCALE,
    SHAPE,
    UNMEASURED,
    MerlFormatError,
    _angles,
    _choice,
    _rng,
    _snap,
    bin_centres,
    directions,
    grid_above_horizon,
    phi_d_index,
    theta_d_index,
    theta_h_index,
    unravel,
)


# ------------------------------------------------------------------------ the BRDF
class MerlBRDF:
    """A MERL grid in memory.

    ``raw`` (3, 90, 90, 180) float64 is the file's content (channel-major, unscaled,
    negative = unmeasured); ``values`` (90, 90, 180, 3) is the BRDF in 1/sr (``raw * SCALE``,
    0 where not ``valid``); ``valid`` (90, 90, 180) marks measured bins.  A
    :class:`neural_brdf.measured.base.MeasuredBRDF`.
    """

    anisotropic = False  # a MERL grid has no phi_h
    # sample_pairs is dense at the mirror direction (1/90 of its pairs in the first
    # theta_h bin): training adds no peak pairs (train.data.MeasuredPairSource)
    dense_at_peak = True

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

    @functools.cached_property
    def support(self) -> np.ndarray:
        """Flat indices of the measured bins whose centre lies above the horizon."""
        out = np.flatnonzero(self._valid_flat & grid_above_horizon().reshape(-1))
        out.flags.writeable = False
        return out

    def describe(self) -> str:
        return f"MERL {self.source} ({len(self.support)} measured bins)"

    def grid_pairs(self, n: int | None = None, seed: int = 0) -> Pairs:
        """(wi, wo, f) float64 at the measured bin centres above the horizon, f the stored
        value (uninterpolated): all of them, or ``n`` drawn without replacement.  phi_h is
        random (an isotropic grid does not depend on it; an anisotropic network is then
        tested at every azimuth)."""
        rng = np.random.default_rng(seed)
        bins = self.support
        if n is not None and n < len(bins):
            bins = np.sort(rng.choice(bins, size=n, replace=False))
        th, td, pd = (c[i] for c, i in zip(bin_centres(), unravel(bins)))
        wi, wo = directions(th, rng.random(len(bins)) * (2 * math.pi), td, pd)
        return wi, wo, self._table[bins]

    # -- lookups
    def eval(self, wi, wo, *, interpolation: str = "trilinear") -> np.ndarray:
        """f(wi, wo) in 1/sr, shape (..., 3); numpy in, numpy out (float64).

        Directions are normalised; a pair with either z <= 0 (or a non-finite entry)
        gives 0 (:func:`neural_brdf.measured.base.eval_pairs`, the edges every format
        shares).
        """
        _choice("interpolation", interpolation, INTERPOLATIONS)

        def at(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return self.lookup(*_angles(a, b), interpolation=interpolation)

        return eval_pairs(wi, wo, at, chunk=CHUNK)

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
        with fileio.open_for_reading(p) as fh:
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
    except fileio.NotAFileError as e:
        raise MerlFormatError(str(e)) from None
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
    _check_values(raw, p)
    return MerlBRDF(raw, source=str(p))  # copies to native float64


def _check_values(raw: np.ndarray, p: Path) -> None:
    """MerlFormatError for measured bins (every channel >= 0) that cannot be a BRDF: a value
    above MAX_VALUE 1/sr, or none above 0 (a file with no measured bin at all reads; it is
    refused as a target or a reference, :mod:`neural_brdf.measured.formats`)."""
    valid = np.all(raw >= 0, axis=0)
    if not valid.any():
        return
    f = np.where(valid, raw * SCALE[:, None, None, None], -np.inf)  # 1/sr
    k = int(np.argmax(f))
    top = float(f.reshape(-1)[k])
    if top > MAX_VALUE:
        c, ih, id_, ip = (int(i) for i in np.unravel_index(k, f.shape))
        raise MerlFormatError(
            f"{p}: largest value {top:.3g} 1/sr (channel {'RGB'[c]}, bin theta_h {ih}, "
            f"theta_d {id_}, phi_d {ip}) is above {MAX_VALUE:.0e} 1/sr: not a BRDF"
        )
    if top <= 0:
        raise MerlFormatError(
            f"{p}: every measured bin is 0 (no positive value): the file reflects nothing"
        )


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
