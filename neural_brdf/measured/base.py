"""What every measured format shares: the :class:`MeasuredBRDF` protocol its reader
returns, the :class:`FormatError` a bad file raises, and :func:`eval_pairs`, the edges of
``eval`` (numpy only: importing this loads no format).

The edges, identical for every format: ``wi`` and ``wo`` are (..., 3) arrays broadcast
together; a pair with a non-finite entry or with a direction at or below the horizon
(z <= 0, the zero vector included) gives 0; the others are normalised (any length: one of
1e-200 is rescaled first, not divided by an underflowed 0) and handed to the format's own
lookup in chunks, which therefore sees unit directions strictly above the horizon only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from neural_brdf.errors import InputError

# |w| outside this range is rescaled before normalising: (1e-150)^2 and (1e150)^2 are
# normal float64 numbers, the squares beyond underflow to denormals (or 0) or overflow.
NORM_RANGE = (1e-150, 1e150)

Pairs = tuple[np.ndarray, np.ndarray, np.ndarray]  # (wi, wo, f), each (N, 3) float64

# The largest table value a reader accepts (f in 1/sr for MERL; rho, and the bound
# rho * max(ndf) / (4 min(sigma)) on f cos, for RGL): above it a file is refused as not a
# BRDF.  The sharpest lobe Mitsuba evaluates (GGX alpha ~1e-4) peaks near 3e7 /sr, and
# f cos above 1e7 is already a delta lobe (measured.mitsuba.MAX_F_COS); squares of values
# above ~1e19 overflow float32 and, near 1e154, float64 (error metrics, training losses).
MAX_VALUE = 1e10


class FormatError(InputError):
    """A measured file that cannot be read.  The one-line message names the file (exit
    code 2 on the command line).  Each format's own error derives from it."""


class MeasuredBRDF(Protocol):
    """A measured BRDF in memory, as a format's reader returns it (``merl.MerlBRDF``,
    ``rgl.RGLBRDF``): what training (``train.data.MeasuredTarget``), ``validate`` and the
    quadratures use.  numpy float64 in and out; f in 1/sr, no cosine; RGB."""

    source: str  # the file it was read from (or a label)
    anisotropic: bool  # False for every format so far: no phi_h dependence
    # whether sample_pairs puts many pairs within a degree of the mirror direction; if
    # not, training adds the data.peak share of peak pairs (train.data.MeasuredPairSource)
    dense_at_peak: bool

    def describe(self) -> str:
        """One line: the format, the file and its size (export's target description)."""
        ...

    def eval(self, wi, wo) -> np.ndarray:
        """f(wi, wo) (..., 3) with the edges of :func:`eval_pairs`."""
        ...

    def sample_pairs(self, n: int, rng=None) -> Pairs:
        """``n`` training pairs (wi, wo, f) above the horizon, on the measured support;
        ``rng``: a numpy Generator or a seed (the same seed gives the same pairs)."""
        ...

    def grid_pairs(self, n: int | None = None, seed: int = 0) -> Pairs:
        """The pairs where the file is exact (MERL: the measured bin centres; RGL: the
        value nodes), above the horizon, with the stored f: all of them, or ``n`` drawn
        without replacement.  Accuracy against the data is measured on these."""
        ...


def eval_pairs(
    wi, wo, lookup: Callable[[np.ndarray, np.ndarray], np.ndarray], *, chunk: int
) -> np.ndarray:
    """f (..., 3) float64 for broadcast ``wi``, ``wo`` (..., 3): 0 at the edges (module
    doc); ``lookup(a, b)`` on the other pairs, ``chunk`` rows at a time, with ``a``, ``b``
    (K, 3) unit vectors strictly above the horizon, returns (K, 3)."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    if wi.shape[-1:] != (3,) or wo.shape[-1:] != (3,):
        raise ValueError(f"wi, wo: expected (..., 3) arrays, got {wi.shape} and {wo.shape}")
    wi, wo = np.broadcast_arrays(wi, wo)
    batch = wi.shape[:-1]
    wi, wo = wi.reshape(-1, 3), wo.reshape(-1, 3)
    out = np.zeros((len(wi), 3))
    ok = np.all(np.isfinite(wi), -1) & np.all(np.isfinite(wo), -1) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
    rows = np.flatnonzero(ok)
    for s in range(0, len(rows), chunk):
        r = rows[s : s + chunk]
        out[r] = lookup(_unit(wi[r]), _unit(wo[r]))
    return out.reshape(batch + (3,))


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (K, 3), finite with z > 0, normalised.  A row whose squared length
    would under- or overflow (|v| outside [1e-150, 1e150]) is first divided by its largest
    entry: a direction of length 1e-200 or 1e200 is still a direction."""
    with np.errstate(over="ignore", under="ignore"):
        n = np.linalg.norm(v, axis=-1, keepdims=True)
    far = ~((n > NORM_RANGE[0]) & (n < NORM_RANGE[1]))[:, 0]
    if far.any():
        v = v.copy()
        v[far] /= np.abs(v[far]).max(-1, keepdims=True)
        n[far] = np.linalg.norm(v[far], axis=-1, keepdims=True)
    return v / n
