"""MERL ``.binary`` measured BRDFs: read, write, look up, bake; real-material fixtures.

    from neural_brdf.measured import merl
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

from neural_brdf.measured.merl.bake import bake, bake_brdf
from neural_brdf.measured.merl.brdf import MerlBRDF, read_merl, write_merl
from neural_brdf.measured.merl.fixtures import (
    ABCParams,
    abc_fixture,
    nbrdf_fixture,
    nbrdf_names,
    read_abc_params,
)
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
    SNAP,
    UNMEASURED,
    MerlFormatError,
    bin_centres,
    directions,
    fold_phi_d,
    grid_above_horizon,
    grid_directions,
    phi_d_index,
    theta_d_index,
    theta_h_index,
    unravel,
)

__all__ = [
    "CHUNK",
    "FILE_BYTES",
    "HEADER_BYTES",
    "INTERPOLATIONS",
    "MerlFormatError",
    "N_BINS",
    "RES_PHI_D",
    "RES_THETA_D",
    "RES_THETA_H",
    "SAMPLE_SPACES",
    "SCALE",
    "SHAPE",
    "SNAP",
    "UNMEASURED",
    "bin_centres",
    "directions",
    "fold_phi_d",
    "grid_above_horizon",
    "grid_directions",
    "phi_d_index",
    "theta_d_index",
    "theta_h_index",
    "unravel",
    "MerlBRDF",
    "read_merl",
    "write_merl",
    "bake",
    "bake_brdf",
    "ABCParams",
    "abc_fixture",
    "nbrdf_fixture",
    "nbrdf_names",
    "read_abc_params",
]
