"""The MERL file format and its grid: header, scales, the half/difference-angle bins
(index maps, bin centres, the grid's directions).  See :mod:`neural_brdf.measured.merl`."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from analytic import frame
from neural_brdf.measured.base import FormatError

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


class MerlFormatError(FormatError):
    """A MERL file that cannot be read.  The one-line message names the file.  An
    InputError (exit code 2 on the command line), and so a ValueError."""


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
