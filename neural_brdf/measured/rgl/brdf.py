"""An RGL material as a BRDF: :class:`RGLBRDF` (evaluation, sampling pairs) and
:func:`read_rgl`."""

from __future__ import annotations

import math

import numpy as np

from neural_brdf.measured.base import MAX_VALUE, Pairs, eval_pairs
from neural_brdf.measured.rgl.layout import (
    CHUNK,
    REQUIRED,
    Marginal2D,
    _spherical,
    elevation,
    phi_to_v,
    theta_to_u,
    u_to_theta,
    v_to_phi,
)
from neural_brdf.measured.rgl.tensor import RGLFormatError, read_tensor_file


# ------------------------------------------------------------------- the reader
class RGLBRDF:
    """An RGL material in memory; ``eval`` follows Mitsuba's ``measured`` (isotropic RGB
    files).  ``fields`` is the tensor file's content.  A
    :class:`neural_brdf.measured.base.MeasuredBRDF`."""

    anisotropic = False  # anisotropic files are refused
    # sample_pairs draws wo from the file's sampler and the cosine, which seldom land
    # within a degree of the mirror direction: training adds data.peak's share of peak
    # pairs (train.data.MeasuredPairSource)
    dense_at_peak = False

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
        for name, a in (("theta_i", th), ("phi_i", ph)):
            if len(a) == 0:
                raise bad(f"field {name!r}: empty (no incident slices)")
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
        # incident elevations in radians on the upper hemisphere (float32's pi/2 rounds
        # up by 4e-8): a file in degrees, or shifted, would be read at other angles
        if float(th[0]) < 0.0 or float(th[-1]) > math.pi / 2 + 1e-6:
            raise bad(
                f"field 'theta_i': values from {float(th[0]):.4g} to {float(th[-1]):.4g}, "
                "outside [0, pi/2] (incident elevations in radians)"
            )
        if int(jac[0]) not in (0, 1):
            raise bad(f"field 'jacobian': {int(jac[0])}, expected 0 or 1")
        self.description = bytes(f["description"]).decode("utf-8", "replace")
        self.jacobian = bool(jac[0])
        self._check_values(rgb, ndf, sigma, bad)
        for name, a in (("vndf", vndf), ("luminance", lum)):  # densities of the sampler
            _nonnegative(bad, name, a, "a sampling density")  # (all 0: Marginal2D says)
        self.theta_i, self.phi_i = th.astype(np.float64), ph.astype(np.float64)
        tables = {}
        for name, a, params, norm in (
            ("ndf", ndf, (), False),
            ("sigma", sigma, (), False),
            ("vndf", vndf, (self.phi_i, self.theta_i), True),
            ("luminance", lum, (self.phi_i, self.theta_i), True),
        ):
            try:
                tables[name] = Marginal2D(a, params, normalize=norm)
            except ValueError as e:
                raise bad(f"field {name!r}: {e}") from None
        self._ndf, self._sigma = tables["ndf"], tables["sigma"]
        self._vndf, self._lum = tables["vndf"], tables["luminance"]
        self._rgb = [
            Marginal2D(rgb[:, :, c], (self.phi_i, self.theta_i), normalize=False) for c in range(3)
        ]

    def _check_values(self, rgb, ndf, sigma, bad) -> None:
        """Refuse finite values that cannot be a BRDF: negative or all-zero ``rgb`` (or
        ``ndf``), ``sigma`` <= 0 where it divides f, anything above MAX_VALUE."""

        def nonnegative(name, a):
            _nonnegative(bad, name, a, "a reflectance")
            top = float(a.max())
            if top <= 0:
                raise bad(f"field {name!r}: no positive value: the material reflects nothing")
            return top

        top = nonnegative("rgb", rgb)
        if top > MAX_VALUE:
            raise bad(f"field 'rgb': largest value {top:.3g} is above {MAX_VALUE:.0e}: not a BRDF")
        if not self.jacobian:  # f cos = rgb: ndf and sigma only steer sampling
            return
        if np.any(sigma <= 0):  # f cos = rgb * ndf / (4 sigma), sigma interpolated
            raise bad(
                f"field 'sigma': {int(np.sum(sigma <= 0))} values <= 0 (smallest "
                f"{float(sigma.min()):.3g}); sigma divides f (jacobian = 1)"
            )
        bound = top * nonnegative("ndf", ndf) / (4.0 * float(sigma.min()))
        if not bound <= MAX_VALUE:
            raise bad(
                f"fields 'rgb', 'ndf', 'sigma': f cos up to {bound:.3g} (max rgb x max ndf "
                f"/ (4 min sigma)) is above {MAX_VALUE:.0e}: not a BRDF"
            )

    def __repr__(self) -> str:
        r = self.fields["rgb"].shape
        return (
            f"RGLBRDF({self.source!r}, theta_i {r[1]}, sample grid {r[3]}x{r[4]}, "
            f"{self.description!r})"
        )

    def describe(self) -> str:
        return f"RGL {self.source} ({self.description})"

    def _params(self, wi):
        return np.arctan2(wi[:, 1], wi[:, 0]), elevation(wi)

    def eval(self, wi, wo) -> np.ndarray:
        """f(wi, wo) in 1/sr (no cosine), (..., 3) float64; 0 below the horizon (the edges
        of :func:`neural_brdf.measured.base.eval_pairs`, which every format shares)."""

        def at(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return self._f_cos(a, b) / b[:, 2:3]

        return eval_pairs(wi, wo, at, chunk=CHUNK)

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

    def grid_pairs(self, n: int | None = None, seed: int = 0) -> Pairs:
        """(wi, wo, f) float64 at the value nodes above the horizon (:meth:`node_pairs`,
        where the file is exact): all of them, or ``n`` drawn without replacement; phi_i
        is random (isotropic files)."""
        wi, wo = self.node_pairs(seed=seed)
        if n is not None and n < len(wi):
            pick = np.sort(np.random.default_rng(seed).choice(len(wi), size=n, replace=False))
            wi, wo = wi[pick], wo[pick]
        return wi, wo, self.eval(wi, wo)

    def sample_pairs(self, n: int, rng=None) -> Pairs:
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


def _nonnegative(bad, name: str, a: np.ndarray, what: str) -> None:
    """``bad(...)`` naming field ``name`` when ``a`` has a negative value (``what``
    cannot be negative: a reflectance, a sampling density)."""
    if np.any(a < 0):
        raise bad(
            f"field {name!r}: {int(np.sum(a < 0))} negative values (smallest "
            f"{float(a.min()):.3g}); {what} cannot be negative"
        )


def read_rgl(path) -> RGLBRDF:
    """Read an RGL ``.bsdf`` file (isotropic, RGB).  Any problem raises RGLFormatError."""
    return RGLBRDF(read_tensor_file(path), source=str(path))
