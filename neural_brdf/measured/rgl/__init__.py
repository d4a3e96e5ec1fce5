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
Little-endian.  12 bytes ``b"tensor_file\0"``, 2 bytes version ``(1, 0)``, uint32 field
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

from neural_brdf.measured.rgl.bake import (
    bake,
    bake_fields,
    retroreflection_ndf,
    rgb_to_spectra,
    theta_i_nodes,
)
from neural_brdf.measured.rgl.brdf import RGLBRDF, read_rgl
from neural_brdf.measured.rgl.layout import (
    CHUNK,
    DEFAULTS,
    LUMINANCE_FLOOR,
    NDF_FLOOR,
    POWER_ITERATIONS,
    QUAD_U,
    REQUIRED,
    SAMPLE_EPS,
    SEGMENT_CONST,
    SPECTRAL_SUFFIX,
    THETA_I_MAX,
    WAVELENGTHS,
    Y_WEIGHTS,
    Marginal2D,
    elevation,
    phi_to_v,
    theta_to_u,
    u_to_theta,
    v_to_phi,
)
from neural_brdf.measured.rgl.tensor import (
    ALIGN,
    DTYPE_CODES,
    DTYPES,
    MAGIC,
    MAX_NDIM,
    VERSION,
    RGLFormatError,
    parse_tensor_file,
    read_tensor_file,
    tensor_file_bytes,
    write_tensor_file,
)

__all__ = [
    "ALIGN",
    "DTYPES",
    "DTYPE_CODES",
    "MAGIC",
    "MAX_NDIM",
    "RGLFormatError",
    "VERSION",
    "parse_tensor_file",
    "read_tensor_file",
    "tensor_file_bytes",
    "write_tensor_file",
    "CHUNK",
    "DEFAULTS",
    "LUMINANCE_FLOOR",
    "Marginal2D",
    "NDF_FLOOR",
    "POWER_ITERATIONS",
    "QUAD_U",
    "REQUIRED",
    "SAMPLE_EPS",
    "SEGMENT_CONST",
    "SPECTRAL_SUFFIX",
    "THETA_I_MAX",
    "WAVELENGTHS",
    "Y_WEIGHTS",
    "elevation",
    "phi_to_v",
    "theta_to_u",
    "u_to_theta",
    "v_to_phi",
    "RGLBRDF",
    "read_rgl",
    "bake",
    "bake_fields",
    "retroreflection_ndf",
    "rgb_to_spectra",
    "theta_i_nodes",
]
