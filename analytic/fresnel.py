"""Fresnel terms: free functions of the cosine between the incident direction and the
(micro)surface normal.  RGB parameters broadcast against ``cos (...)`` to ``(..., 3)``.

All return reflectance in [0, 1] (tested) for cos in [0, 1].
"""

from __future__ import annotations

import json
import math
from functools import cache
from importlib import resources

import torch

# RGB wavelengths (nm) at which a thin film is evaluated: red, green, blue.
FILM_WAVELENGTHS = (650.0, 550.0, 450.0)


def _rgb_like(value, cos: torch.Tensor) -> torch.Tensor:
    """A scalar or RGB parameter as a (3,) tensor on the cosine's dtype and device."""
    return torch.as_tensor(value, dtype=cos.dtype, device=cos.device).reshape(-1).expand(3)


def schlick(f0, cos: torch.Tensor) -> torch.Tensor:
    """Schlick 1994: F = F0 + (1 - F0)(1 - cos)^5.  # Shirley & Marschner 2009, eq. 24.6"""
    f0 = _rgb_like(f0, cos)
    m = (1.0 - cos.clamp(0.0, 1.0))[..., None]
    return f0 + (1.0 - f0) * m**5


def schlick_f0(eta: float) -> float:
    """F0 = ((eta - 1) / (eta + 1))^2 for an interface with air (Shirley & Marschner
    2009, sec. 24.3)."""
    return ((eta - 1.0) / (eta + 1.0)) ** 2


def dielectric(eta, cos: torch.Tensor) -> torch.Tensor:
    """Exact unpolarised Fresnel reflectance of a dielectric interface, eta = n_t / n_i.

    F = (rs^2 + rp^2) / 2 (Born & Wolf 1999, F = (Fs + Fp) / 2); total internal
    reflection (eta < 1 past the critical angle) gives 1.
    """
    eta = _rgb_like(eta, cos)
    ci = cos.clamp(0.0, 1.0)[..., None]
    sin2_t = (1.0 - ci * ci) / (eta * eta)  # Snell's law (Born & Wolf 1999)
    tir = sin2_t >= 1.0
    ct = torch.sqrt((1.0 - sin2_t).clamp_min(0.0))
    rs = (ci - eta * ct) / (ci + eta * ct).clamp_min(1e-30)
    rp = (eta * ci - ct) / (eta * ci + ct).clamp_min(1e-30)
    f = 0.5 * (rs * rs + rp * rp)
    return torch.where(tir, torch.ones_like(f), f)


def conductor(eta, k, cos: torch.Tensor) -> torch.Tensor:
    """Exact unpolarised Fresnel reflectance of a conductor with complex IOR eta + i k
    (relative to the outside medium), from the s and p amplitude reflectances."""
    eta = _rgb_like(eta, cos)
    k = _rgb_like(k, cos)
    c = cos.clamp(0.0, 1.0)[..., None]
    c2 = c * c
    s2 = 1.0 - c2
    t0 = eta * eta - k * k - s2
    a2b2 = torch.sqrt(t0 * t0 + 4.0 * eta * eta * k * k)  # a^2 + b^2
    a = torch.sqrt((0.5 * (a2b2 + t0)).clamp_min(0.0))
    rs = (a2b2 + c2 - 2.0 * a * c) / (a2b2 + c2 + 2.0 * a * c).clamp_min(1e-30)
    t1 = a2b2 * c2 + s2 * s2
    t2 = 2.0 * a * c * s2
    rp = rs * (t1 - t2) / (t1 + t2).clamp_min(1e-30)
    return 0.5 * (rs + rp)


def thin_film(
    film_eta: float, thickness_nm: float, eta, cos: torch.Tensor, wavelengths=FILM_WAVELENGTHS
) -> torch.Tensor:
    """Air / non-absorbing film (index ``film_eta``, ``thickness_nm``) / dielectric
    substrate (index ``eta``), with all internal reflections summed (Airy):

        R = (r1^2 + r2^2 + 2 r1 r2 cos d) / (1 + r1^2 r2^2 + 2 r1 r2 cos d),
        d = 4 pi n_f t cos(theta_f) / lambda                    # Born & Wolf 1999, thin films

    evaluated for s and p polarisation with signed amplitude coefficients and
    averaged; one wavelength per RGB channel.  Total internal reflection at either
    interface gives R = 1 (no transmitted wave, no loss).  With thickness 0 it
    reduces to ``dielectric(eta)``, and with ``film_eta == eta`` to
    ``dielectric(film_eta)`` (both tested).
    """
    lam = _rgb_like(wavelengths, cos)
    n1 = _rgb_like(film_eta, cos)
    n2 = _rgb_like(eta, cos)
    c0 = cos.clamp(0.0, 1.0)[..., None]
    s0sq = 1.0 - c0 * c0
    s1sq, s2sq = s0sq / (n1 * n1), s0sq / (n2 * n2)
    tir = (s1sq >= 1.0) | (s2sq >= 1.0)
    c1 = torch.sqrt((1.0 - s1sq).clamp_min(0.0))
    c2 = torch.sqrt((1.0 - s2sq).clamp_min(0.0))

    def amp(na, ca, nb, cb):  # s and p amplitude reflectances a -> b
        rs = (na * ca - nb * cb) / (na * ca + nb * cb).clamp_min(1e-30)
        rp = (nb * ca - na * cb) / (nb * ca + na * cb).clamp_min(1e-30)
        return rs, rp

    r1s, r1p = amp(1.0, c0, n1, c1)
    r2s, r2p = amp(n1, c1, n2, c2)
    cos_d = torch.cos(4.0 * math.pi * n1 * thickness_nm * c1 / lam)

    def airy(r1, r2):
        num = r1 * r1 + r2 * r2 + 2.0 * r1 * r2 * cos_d
        den = 1.0 + r1 * r1 * r2 * r2 + 2.0 * r1 * r2 * cos_d
        return num / den.clamp_min(1e-30)

    f = 0.5 * (airy(r1s, r2s) + airy(r1p, r2p))
    return torch.where(tir, torch.ones_like(f), f).clamp(0.0, 1.0)


@cache
def _presets() -> dict:
    text = resources.files("analytic").joinpath("data/conductors.json").read_text()
    return json.loads(text)


def conductor_presets() -> list[str]:
    return sorted(k for k in _presets() if not k.startswith("_"))


def conductor_ior(material: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(eta, k) RGB of a named conductor preset."""
    table = _presets()
    if material not in table or material.startswith("_"):
        from .base import ParameterError

        raise ParameterError(
            f"material: unknown conductor {material!r}; presets: {conductor_presets()}"
        )
    return tuple(table[material]["eta"]), tuple(table[material]["k"])
