"""Tabulating a BRDF (any ``f(wi, wo)``) on the MERL grid."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from neural_brdf.measured.merl.brdf import MerlBRDF, _check_values, write_merl
from neural_brdf.measured.merl.format import (
    CHUNK,
    N_BINS,
    SCALE,
    SHAPE,
    UNMEASURED,
    MerlFormatError,
    _grid,
    bin_centres,
    unravel,
)


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
    # what every reader refuses is not written (a near-delta lobe's bin above MAX_VALUE)
    try:
        _check_values(m.raw, Path(path))
    except MerlFormatError as e:
        raise MerlFormatError(f"{e} (not written: a reader refuses it)") from None
    write_merl(path, m)
    return m
