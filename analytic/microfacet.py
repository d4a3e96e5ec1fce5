"""Microfacet (Cook-Torrance / Torrance-Sparrow) reflection.

    f(wi, wo) = F(wi.h) D(h) G(wi, wo) / (4 cos_i cos_o)   # Walter et al. 2007; Pharr et al. 2016

The pieces belong to :class:`Distribution` (D, Lambda, G1, visible-normal sampling);
Fresnel terms are free functions in :mod:`analytic.fresnel`; :class:`Microfacet`
combines them.

* D: Beckmann or GGX, isotropic ``alpha`` or anisotropic ``alpha_x`` (along the
  tangent x) / ``alpha_y``.  # Walter et al. 2007; Heitz 2014
* G: ``smith_separable`` G1(wi) G1(wo), ``smith_correlated`` (height-correlated)
  1 / (1 + Lambda(wi) + Lambda(wo)), or ``v_cavity`` (Cook-Torrance).  # Heitz 2014;
  Cook & Torrance 1982.  Note: a tutorial (docs/references.md) prints the GGX G1 as
  2 cos / (1 + sqrt(1 + a^2 tan^2)), which is
  G1 * cos(theta) (a form that folds in a cosine of the denominator); we use the
  Smith G1 = 1 / (1 + Lambda) = 2 / (1 + sqrt(1 + a^2 tan^2)).
* Sampling: visible normals (Heitz & d'Eon 2014).  GGX by the spherical-cap method of
  Dupuy & Benyoub 2023; Beckmann by inverting the visible-slope CDF in the stretched
  configuration.  pdf(wo) = D_wi(h) / (4 wi.h), D_wi(h) = G1(wi) max(0, wi.h) D(h) / cos_i.
* ``multiscatter``: Kulla & Conty 2017 energy compensation (Kulla & Conty 2017):

      f_ms = F_add (1 - E(wi)) (1 - E(wo)) / (pi (1 - E_avg)),
      F_add = F_avg^2 E_avg / (1 - F_avg (1 - E_avg))

  The tutorial multiplies by F_avg alone; F_add is the sum of the Fresnel-weighted
  bounce series of Kulla & Conty and keeps rho <= 1.  E is tabulated per model
  (in mu = cos theta, and in the azimuth for anisotropic alphas) by quadrature of the
  single-scattering lobe, and E_avg is integrated from the *same* interpolant, so
  with F = 1 the total albedo is 1 up to the table's interpolation error: measured
  <= 1e-3 for isotropic alphas, and up to 5e-3 near grazing for strongly anisotropic
  ones (alpha_x / alpha_y = 1/100), where E(mu, phi) has a sharp feature that the
  64 x 17 table smooths.  That is the stated tolerance of the energy test for
  ``multiscatter=True`` with anisotropic alphas.

Reciprocal: yes for every option, bit for bit in float32 and float64: F depends on
wi.h = wo.h, computed as |wi + wo| / 2 (:func:`half_cos`), and D, G and the
compensation are evaluated in forms symmetric in (wi, wo) (1 + (Lambda(wi) +
Lambda(wo)), not (1 + Lambda(wi)) + Lambda(wo), which rounds differently when swapped).
Energy conserving: yes (single scattering loses energy; the compensation adds at
most what was lost, up to the table tolerance above).  Tested: rho <= 1 + 1e-3.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from . import frame
from . import fresnel as fr
from .base import BRDF, Lobe, ParameterError, choice, cosine_lobe, rgb, scalar

# Smallest alpha used in evaluation.  Below it the GGX peak 1/(pi a^2) and the slope
# terms h_x^2 / a^2 leave the comfortable float32 range; 1e-4 is already a mirror.
MIN_ALPHA = 1e-4

DISTRIBUTIONS = ("ggx", "beckmann")
MASKINGS = ("smith_correlated", "smith_separable", "v_cavity")
FRESNELS = ("none", "schlick", "dielectric", "conductor", "thin_film")

SQRT_PI = math.sqrt(math.pi)


class Distribution:
    """A microfacet normal distribution with its Smith masking and visible-normal sampling."""

    def __init__(self, kind: str, alpha_x: float, alpha_y: float):
        self.kind = kind
        self.alpha_x = max(alpha_x, MIN_ALPHA)
        self.alpha_y = max(alpha_y, MIN_ALPHA)

    def D(self, h: torch.Tensor) -> torch.Tensor:
        ax, ay = self.alpha_x, self.alpha_y
        hz = h[..., 2].clamp_min(frame.EPS_COS)
        if self.kind == "ggx":
            # Heitz 2014 (anisotropic GGX)
            t = (h[..., 0] / ax) ** 2 + (h[..., 1] / ay) ** 2 + hz * hz
            d = 1.0 / (math.pi * ax * ay * t * t)
        else:
            # Walter et al. 2007 (Beckmann), anisotropic slopes
            e = ((h[..., 0] / ax) ** 2 + (h[..., 1] / ay) ** 2) / (hz * hz)
            d = torch.exp(-e) / (math.pi * ax * ay * hz**4)
        return torch.where(h[..., 2] > 0, d, torch.zeros_like(d))

    def _a2(self, w: torch.Tensor) -> torch.Tensor:
        """alpha(phi)^2 tan^2(theta) of a direction."""
        wz = w[..., 2].clamp_min(frame.EPS_COS)
        return ((w[..., 0] * self.alpha_x) ** 2 + (w[..., 1] * self.alpha_y) ** 2) / (wz * wz)

    def Lambda(self, w: torch.Tensor) -> torch.Tensor:
        a2 = self._a2(w)
        if self.kind == "ggx":
            # Heitz 2014: Lambda = (-1 + sqrt(1 + a^2 tan^2)) / 2
            return 0.5 * (torch.sqrt(1.0 + a2) - 1.0)
        # Beckmann: a = 1 / (alpha tan), Lambda = (erf(a) - 1)/2 + exp(-a^2) / (2 a sqrt(pi))
        a = torch.rsqrt(a2.clamp_min(1e-30))
        return 0.5 * (torch.special.erf(a) - 1.0) + torch.exp(-a * a) / (2.0 * a * SQRT_PI)

    def G1(self, w: torch.Tensor) -> torch.Tensor:
        return 1.0 / (1.0 + self.Lambda(w))

    # -- visible normals
    def sample_visible(self, wi: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        ax, ay = self.alpha_x, self.alpha_y
        ws = frame.normalize(
            torch.stack([ax * wi[..., 0], ay * wi[..., 1], wi[..., 2].clamp_min(frame.EPS_COS)], -1)
        )
        if self.kind == "ggx":
            # Dupuy & Benyoub 2023: a point on the spherical cap below the stretched wi,
            # plus wi, is a visible normal of the unit-roughness GGX (a hemisphere).
            phi = 2.0 * math.pi * u[..., 0]
            z = (1.0 - u[..., 1]) * (1.0 + ws[..., 2]) - ws[..., 2]
            s = torch.sqrt((1.0 - z * z).clamp_min(0.0))
            hs = torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], -1) + ws
            return frame.normalize(
                torch.stack([ax * hs[..., 0], ay * hs[..., 1], hs[..., 2].clamp_min(0.0)], -1)
            )
        sx, sy = _beckmann_visible_slopes(ws, u)
        return frame.normalize(torch.stack([-ax * sx, -ay * sy, torch.ones_like(sx)], -1))

    def pdf_visible(self, wi: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        ci = wi[..., 2].clamp_min(frame.EPS_COS)
        return self.G1(wi) * frame.dot(wi, h).clamp_min(0.0) * self.D(h) / ci


def _beckmann_visible_slopes(ws: torch.Tensor, u: torch.Tensor):
    """Visible slopes of the unit Beckmann distribution seen from ``ws``.

    With ws at polar angle t and azimuth 0, the visible slope density is
    (cos t - x sin t) exp(-x^2 - y^2) / pi on x < cot t (Heitz & d'Eon 2014).  y is
    N(0, 1/2); x has the CDF (unnormalised)
        C(x) = cos t (1 + erf x) / 2 + sin t exp(-x^2) / (2 sqrt(pi)),
    inverted by 10 bisection steps on [-6, min(cot t, 6)] (the tails beyond 6 hold
    < 1e-16 of the mass) followed by 4 Newton steps kept inside the bracket, which
    converge quadratically to float64 resolution.  The slopes are then rotated to
    the azimuth of ws.
    """
    w = ws.to(torch.float64)
    uu = u.to(torch.float64)
    ct = w[..., 2].clamp(0.0, 1.0)
    st = torch.sqrt((1.0 - ct * ct).clamp_min(0.0))
    cot = ct / st.clamp_min(1e-300)

    def C(x):
        return ct * 0.5 * (1.0 + torch.special.erf(x)) + st * torch.exp(-x * x) / (2.0 * SQRT_PI)

    hi = cot.clamp_max(6.0)
    lo = torch.full_like(hi, -6.0)
    target = uu[..., 0] * C(hi)
    for _ in range(10):
        mid = 0.5 * (lo + hi)
        below = C(mid) < target
        lo = torch.where(below, mid, lo)
        hi = torch.where(below, hi, mid)
    x = 0.5 * (lo + hi)
    for _ in range(4):
        dC = (ct - x * st) * torch.exp(-x * x) / SQRT_PI
        x = torch.minimum(torch.maximum(x - (C(x) - target) / dC.clamp_min(1e-300), lo), hi)
    y = torch.special.erfinv((2.0 * uu[..., 1] - 1.0).clamp(-1.0 + 1e-15, 1.0 - 1e-15))
    r = torch.sqrt(w[..., 0] ** 2 + w[..., 1] ** 2)
    cp = torch.where(r > 0, w[..., 0] / r.clamp_min(1e-300), torch.ones_like(r))
    sp = torch.where(r > 0, w[..., 1] / r.clamp_min(1e-300), torch.zeros_like(r))
    sx = cp * x - sp * y
    sy = sp * x + cp * y
    return sx.to(ws.dtype), sy.to(ws.dtype)


def half_cos(wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """wi.h = wo.h, as |wi + wo| / 2 (equal for unit wi, wo).

    Computed from wi + wo alone, so it is the same bit for bit with wi and wo swapped,
    which frame.dot(wi, h) and frame.dot(wo, h) are not (they differ by rounding)."""
    return 0.5 * torch.linalg.vector_norm(wi + wo, dim=-1)


# ------------------------------------------------------------------- the model
class Microfacet(BRDF):
    """Torrance-Sparrow microfacet reflection (see the module docstring).

    Parameters (keyword-only; defaults in brackets):
      distribution ['ggx'] | 'beckmann'
      alpha [0.3] in (0, 1]; or alpha_x and alpha_y (x = tangent) for anisotropy
      masking ['smith_correlated'] | 'smith_separable' | 'v_cavity'
      fresnel ['none'] | 'schlick' (f0 RGB [0.04]) | 'dielectric' (eta [1.5])
              | 'conductor' (eta, k RGB, or material in Au/Ag/Cu/Al [Au])
              | 'thin_film' (film_eta [1.33], film_thickness nm [400], eta substrate [1.5])
      multiscatter [False]: Kulla-Conty energy compensation
    """

    name = "microfacet"
    reciprocal = True
    energy_conserving = True
    param_space = {
        "distribution": ("choice", list(DISTRIBUTIONS)),
        "alpha_x": ("logfloat", 1e-4, 1.0),
        "alpha_y": ("logfloat", 1e-4, 1.0),
        "masking": ("choice", list(MASKINGS)),
        "fresnel": ("choice", list(FRESNELS)),
        "multiscatter": ("choice", [False, True]),
    }
    notes = (
        "The tutorial's G1 is printed as G1*cos; Smith G1 = 1/(1+Lambda) is used. "
        "Kulla-Conty uses F_add = Favg^2 Eavg / (1 - Favg (1 - Eavg)) instead of the "
        "tutorial's Favg, which keeps the Fresnel-weighted albedo <= 1."
    )

    def __init__(
        self,
        *,
        distribution="ggx",
        alpha=None,
        alpha_x=None,
        alpha_y=None,
        masking="smith_correlated",
        fresnel="none",
        f0=None,
        eta=None,
        k=None,
        material=None,
        film_eta=None,
        film_thickness=None,
        multiscatter=False,
    ):
        distribution = choice("distribution", distribution, DISTRIBUTIONS)
        masking = choice("masking", masking, MASKINGS)
        fresnel = choice("fresnel", fresnel, FRESNELS)
        if alpha is not None and (alpha_x is not None or alpha_y is not None):
            raise ParameterError("alpha: give either alpha or alpha_x/alpha_y, not both")
        if alpha is None and alpha_x is None and alpha_y is None:
            alpha = 0.3
        if alpha is not None:
            alpha_x = alpha_y = scalar("alpha", alpha, lo=0.0, hi=1.0, lo_open=True)
        else:
            if alpha_x is None or alpha_y is None:
                raise ParameterError("alpha_x/alpha_y: give both (or a single alpha)")
            alpha_x = scalar("alpha_x", alpha_x, lo=0.0, hi=1.0, lo_open=True)
            alpha_y = scalar("alpha_y", alpha_y, lo=0.0, hi=1.0, lo_open=True)
        if not isinstance(multiscatter, bool):
            raise ParameterError(f"multiscatter: expected true or false, got {multiscatter!r}")

        params = dict(
            distribution=distribution,
            alpha_x=alpha_x,
            alpha_y=alpha_y,
            masking=masking,
            fresnel=fresnel,
            multiscatter=multiscatter,
        )
        used = {
            "f0": f0,
            "eta": eta,
            "k": k,
            "material": material,
            "film_eta": film_eta,
            "film_thickness": film_thickness,
        }
        allowed = {
            "none": (),
            "schlick": ("f0",),
            "dielectric": ("eta",),
            "conductor": ("eta", "k", "material"),
            "thin_film": ("film_eta", "film_thickness", "eta"),
        }[fresnel]
        for key, val in used.items():
            if val is not None and key not in allowed:
                raise ParameterError(f"{key}: not used with fresnel={fresnel!r}")
        if fresnel == "schlick":
            params["f0"] = rgb("f0", 0.04 if f0 is None else f0)
        elif fresnel == "dielectric":
            params["eta"] = rgb("eta", 1.5 if eta is None else eta, lo=1e-3, hi=10.0)
        elif fresnel == "conductor":
            if material is not None:
                if eta is not None or k is not None:
                    raise ParameterError("material: give either material or eta/k, not both")
                eta, k = fr.conductor_ior(material)
                params["material"] = material
            elif eta is None and k is None:
                eta, k = fr.conductor_ior("Au")
                params["material"] = "Au"
            elif eta is None or k is None:
                raise ParameterError("eta/k: a conductor needs both eta and k (or a material)")
            params["eta"] = rgb("eta", eta, lo=1e-3, hi=20.0)
            params["k"] = rgb("k", k, lo=0.0, hi=50.0)
        elif fresnel == "thin_film":
            params["film_eta"] = scalar(
                "film_eta", 1.33 if film_eta is None else film_eta, lo=1.0, hi=5.0
            )
            params["film_thickness"] = scalar(
                "film_thickness",
                400.0 if film_thickness is None else film_thickness,
                lo=0.0,
                hi=1e5,
            )
            params["eta"] = scalar("eta", 1.5 if eta is None else eta, lo=1.0, hi=5.0)
        super().__init__(**params)
        self.anisotropic = alpha_x != alpha_y
        self.dist = Distribution(distribution, alpha_x, alpha_y)
        self._ms = (
            _ms_table(distribution, self.dist.alpha_x, self.dist.alpha_y, masking)
            if multiscatter
            else None
        )
        self._f_add = self._fresnel_add() if multiscatter else None

    # -- pieces
    def fresnel(self, cos: torch.Tensor) -> torch.Tensor:
        p, kind = self.params, self.params["fresnel"]
        if kind == "none":
            return torch.ones(cos.shape + (3,), dtype=cos.dtype, device=cos.device)
        if kind == "schlick":
            return fr.schlick(p["f0"], cos)
        if kind == "dielectric":
            return fr.dielectric(p["eta"], cos)
        if kind == "conductor":
            return fr.conductor(p["eta"], p["k"], cos)
        return fr.thin_film(p["film_eta"], p["film_thickness"], p["eta"], cos)

    def G(self, wi: torch.Tensor, wo: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        m = self.params["masking"]
        if m == "smith_separable":
            return self.dist.G1(wi) * self.dist.G1(wo)
        if m == "smith_correlated":
            # Lambda(wi) + Lambda(wo) first: (1 + a) + b is not (1 + b) + a in floats
            return 1.0 / (1.0 + (self.dist.Lambda(wi) + self.dist.Lambda(wo)))
        # V-cavity (Cook & Torrance 1982):
        # min(1, 2 hz co / (wo.h), 2 hz ci / (wi.h))
        hz = h[..., 2]
        d = half_cos(wi, wo).clamp_min(frame.EPS_COS)  # wi.h == wo.h
        g = torch.minimum(2.0 * hz * wo[..., 2] / d, 2.0 * hz * wi[..., 2] / d)
        return g.clamp(0.0, 1.0)

    def single_scatter(self, wi: torch.Tensor, wo: torch.Tensor, with_fresnel: bool = True):
        h = frame.half_vector(wi, wo)
        ci = wi[..., 2].clamp_min(frame.EPS_COS)
        co = wo[..., 2].clamp_min(frame.EPS_COS)
        val = self.dist.D(h) * self.G(wi, wo, h) / (4.0 * ci * co)  # Walter et al. 2007
        val = val[..., None]
        if with_fresnel:
            val = val * self.fresnel(half_cos(wi, wo))
        return val.expand(val.shape[:-1] + (3,))

    def _f(self, wi, wo):
        val = self.single_scatter(wi, wo)
        if self._ms is not None:
            e_i, e_o = self._ms.E(wi), self._ms.E(wo)
            fadd = self.const(self._f_add, wi)
            # Kulla & Conty 2017
            ms = (1.0 - e_i) * (1.0 - e_o) / (math.pi * (1.0 - self._ms.e_avg))
            val = val + fadd * ms[..., None]
        return val

    def _lobes(self, wi):
        dist = self.dist

        def sample(u):
            h = dist.sample_visible(wi, u)
            return frame.reflect(wi, h)

        def pdf(wo):
            h = frame.half_vector(wi, wo)
            d = frame.dot(wi, h)
            p = dist.pdf_visible(wi, h) / (4.0 * d.clamp_min(frame.EPS_COS))
            return torch.where(d > 0, p, torch.zeros_like(p))

        if self._ms is None:
            return [Lobe(torch.ones_like(wi[..., 0]), sample, pdf)]
        e_i = self._ms.E(wi)
        w_ms = (1.0 - e_i) * float(np.mean(self._f_add))
        return [Lobe(e_i, sample, pdf), cosine_lobe(wi, w_ms)]

    def _fresnel_add(self) -> tuple[float, float, float]:
        # F_avg = 2 int_0^1 F(mu) mu dmu (midpoint rule, 4096 points: error < 1e-7)
        mu = (torch.arange(4096, dtype=torch.float64) + 0.5) / 4096
        f_avg = (2.0 * self.fresnel(mu) * mu[:, None]).mean(0)
        e_avg = self._ms.e_avg
        f_add = f_avg * f_avg * e_avg / (1.0 - f_avg * (1.0 - e_avg))
        return float(f_add[0]), float(f_add[1]), float(f_add[2])


class _EnergyTable:
    """E(mu, phi) of the single-scattering lobe with F = 1, and E_avg from the same
    interpolant.  Nodes: mu_j = (j / (N-1))^2 (dense near grazing, where E varies
    fastest) and, for anisotropic alphas, the projected roughness of the azimuth,
    alpha(phi) = sqrt(alpha_x^2 cos^2 phi + alpha_y^2 sin^2 phi), uniform between
    alpha_x and alpha_y (E varies with it roughly evenly; uniform nodes in phi leave
    2e-3 interpolation errors near phi = 0 when alpha_x << alpha_y).  The
    distributions are symmetric under x -> -x and y -> -y, so phi folds into [0, pi/2]."""

    def __init__(self, table: np.ndarray, e_avg: float, alpha_x: float, alpha_y: float):
        self.table = torch.from_numpy(table)  # (N_mu, N_phi) float64
        self.e_avg = min(e_avg, 1.0 - 1e-6)
        self.alpha_x, self.alpha_y = alpha_x, alpha_y

    def E(self, w: torch.Tensor) -> torch.Tensor:
        tab = self.table.to(dtype=w.dtype, device=w.device)
        n_mu, n_phi = tab.shape
        t = torch.sqrt(w[..., 2].clamp(0.0, 1.0)) * (n_mu - 1)
        i0 = t.floor().clamp(0, n_mu - 2).long()
        ft = (t - i0).clamp(0.0, 1.0)
        if n_phi == 1:
            col = tab[:, 0]
            return col[i0] * (1 - ft) + col[i0 + 1] * ft
        ax2, ay2 = self.alpha_x**2, self.alpha_y**2
        r2 = (w[..., 0] ** 2 + w[..., 1] ** 2).clamp_min(1e-30)
        a_phi = torch.sqrt((ax2 * w[..., 0] ** 2 + ay2 * w[..., 1] ** 2) / r2)
        phi = (a_phi - self.alpha_x) / (self.alpha_y - self.alpha_x) * (n_phi - 1)
        j0 = phi.floor().clamp(0, n_phi - 2).long()
        fp = (phi - j0).clamp(0.0, 1.0)

        def at(i, j):
            return tab[i, j]

        e0 = at(i0, j0) * (1 - ft) + at(i0 + 1, j0) * ft
        e1 = at(i0, j0 + 1) * (1 - ft) + at(i0 + 1, j0 + 1) * ft
        return e0 * (1 - fp) + e1 * fp


# Table size.  Quadrature points per node: 4096 (isotropic; 1e-4 accurate) or 1024
# (anisotropic, 17 x more nodes; its tolerance is set by interpolation anyway).
N_MU, N_PHI_ANISO, N_SAMPLES_ISO, N_SAMPLES_ANISO = 64, 17, 4096, 1024


@lru_cache(maxsize=256)
def _ms_table(distribution: str, alpha_x: float, alpha_y: float, masking: str) -> _EnergyTable:
    from .physics import sobol_points  # quadrature points (physics imports no models)

    ss = Microfacet(distribution=distribution, alpha_x=alpha_x, alpha_y=alpha_y, masking=masking)
    n_phi = 1 if alpha_x == alpha_y else N_PHI_ANISO
    mu = (torch.arange(N_MU, dtype=torch.float64) / (N_MU - 1)) ** 2
    mu = mu.clamp_min(1e-6)  # node 0 stands for the grazing limit mu -> 0
    if n_phi > 1:  # node azimuths: alpha(phi_j) uniform in [alpha_x, alpha_y]
        a_j = torch.linspace(alpha_x, alpha_y, n_phi, dtype=torch.float64)
        sin2 = ((a_j**2 - alpha_x**2) / (alpha_y**2 - alpha_x**2)).clamp(0.0, 1.0)
        phi = torch.asin(torch.sqrt(sin2))
    else:
        phi = torch.zeros(1, dtype=torch.float64)
    M, P = torch.meshgrid(mu, phi, indexing="ij")
    s = torch.sqrt(1.0 - M * M)
    wi = torch.stack([s * torch.cos(P), s * torch.sin(P), M], -1)[..., None, :]  # (N, P, 1, 3)
    n_samples = N_SAMPLES_ISO if n_phi == 1 else N_SAMPLES_ANISO
    u = sobol_points(n_samples, 12345)
    with torch.no_grad():
        wib = wi.expand(wi.shape[:-2] + (n_samples, 3))
        h = ss.dist.sample_visible(wib, u)
        wo = frame.reflect(wib, h)
        pdf = ss.dist.pdf_visible(wib, h) / (4.0 * frame.dot(wib, h).clamp_min(frame.EPS_COS))
        val = ss.single_scatter(wib, wo, with_fresnel=False)[..., 0] * wo[..., 2]
        contrib = torch.where((wo[..., 2] > 0) & (pdf > 0), val / pdf.clamp_min(1e-300), 0.0)
        table = contrib.mean(-1).clamp(0.0, 1.0).numpy()
    # E_avg = (1/pi) int E(w) cos dw = (2/pi) int_0^{pi/2} dphi int_0^1 E mu dmu,
    # from the interpolant
    et = _EnergyTable(table, 0.5, alpha_x, alpha_y)
    t = (torch.arange(8192, dtype=torch.float64) + 0.5) / 8192  # mu = t^2
    n_ph = 256 if n_phi > 1 else 1
    ph = (torch.arange(n_ph, dtype=torch.float64) + 0.5) * (0.5 * math.pi / n_ph)
    T, PH = torch.meshgrid(t, ph, indexing="ij")
    m = T * T
    sm = torch.sqrt(1.0 - m * m)
    w = torch.stack([sm * torch.cos(PH), sm * torch.sin(PH), m], -1)
    e_avg = float((2.0 * et.E(w) * m * 2.0 * T).mean())
    return _EnergyTable(table, e_avg, alpha_x, alpha_y)
