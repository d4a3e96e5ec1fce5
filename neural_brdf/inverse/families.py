"""The analytic families an images fit can start from (issue 29, item 1;
docs/inverse-design.md, "The start"): one registry, :data:`FAMILIES`, simplest first.

    from neural_brdf.inverse import families
    fam = families.family("roughplastic")
    fam.params, fam.complexity, fam.element(fam.numbers(fam.free_of(fam.initial())))

A new family is one :class:`Family` entry in :data:`FAMILIES` (and its name in
:data:`neural_brdf.config.START_FAMILIES`, the config's list, which
tests/inverse/test_starts.py keeps equal to it): its plugin, its parameters with their
ranges, the maps to Mitsuba's parameter keys and to its XML, and, where its fit should
start from simpler families already fitted, those families (``warm_from``) and the
rule (``warm``).  :mod:`neural_brdf.inverse.starts` fits, scores and chooses them
without naming any.

A *family* (:data:`FAMILIES`) is one Mitsuba 3 BSDF plugin with its differentiable
parameters, each kept in its range by construction: a free variable z (what
``mi.ad.Adam`` steps) maps to ``lo + (hi - lo) s(z)``, or to its log-space analogue for a
roughness, with s(z) = (1 + tanh(z / 2)) / 2 the logistic function (for the principled's
metallic s(z) = sin^2 z, which reaches 0 and 1: a dielectric or a metal), so no step of
Adam can leave the valid domain and every reflectance is at most 1 (the albedo at most 1, but
for Mitsuba's ``principled``, which reaches 1.04 to 1.19 at base colour 1: its
distillation through :class:`neural_brdf.measured.mitsuba.MitsubaTarget` learns the
energy-bounded version, f / max(1, A+(wi), A+(wo))):

=======================  ==============  ==================================================
name                     plugin          fitted (free scalars)
=======================  ==============  ==================================================
``diffuse``              diffuse         reflectance RGB in [0, 1] (3)
``roughplastic``         roughplastic    diffuse_reflectance RGB in [0, 1], GGX alpha in
                                         [0.01, 1]; int_ior 1.5 fixed (4)
``principled``           principled      base_color RGB in [0, 1], roughness in
                                         [0.05, 1], metallic in [0, 1]; specular 0.5
                                         fixed (5)
``roughconductor``       roughconductor  GGX alpha in [0.01, 1], normal-incidence
                                         reflectance F0 RGB in [0.005, 0.98] and edge tint
                                         RGB in [0, 1], mapped to eta and k (7)
``clearcoat``            principled      the principled's five and its clear coat:
                                         clearcoat and clearcoat_gloss in [0, 1] (7)
``roughconductor_aniso`` roughconductor  alpha_u, alpha_v in [0.01, 1], F0, edge tint (8)
``blend``                blendbsdf       a diffuse (reflectance RGB) and a roughconductor
                                         (as above), the conductor's weight in [0, 1] (11)
=======================  ==============  ==================================================

The conductor's eta and k come from F0 = r and the edge tint g by Gulbrandsen's map
(2014, "Artist Friendly Metallic Fresnel", JCGT 3(4)): n = g (1 - r) / (1 + r) +
(1 - g) (1 + sqrt r) / (1 - sqrt r), k = sqrt((r (n + 1)^2 - (n - 1)^2) / (1 - r)), so
that the conductor Fresnel at normal incidence is exactly r whatever g; the free
variables are then well scaled, where raw eta and k are not.

``roughplastic``'s int_ior is fixed at 1.5: Mitsuba 3 computes the plugin's
transmittance table from scalar copies of alpha and eta (``dr::slice`` in
``parameters_changed``), so no gradient reaches eta through the diffuse term (measured:
-22 against a finite difference of +0.35, on 2,000 random pairs) and alpha's gradient
misses that part too (-64 against -141); alpha still converges, since the diffuse
reflectance absorbs the level the table sets (see the tests).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from neural_brdf.inverse import views as inverse

ROUGHPLASTIC_IOR = 1.5  # roughplastic's int_ior (ext_ior 1): see the module doc
EPS_K2 = 1e-12  # the conductor's k^2 is clamped here (sqrt's gradient stays finite)


# ------------------------------------------------------------------ ranges
def _logistic(z: Any, xp: Any) -> Any:
    """(1 + tanh(z / 2)) / 2: the logistic function, without overflow for any z."""
    return 0.5 * (1.0 + xp.tanh(0.5 * z))


SIN_Z_MAX = 1e4  # Bound(ends=True)'s free variable is clamped here (Adam never goes near)


@dataclass(frozen=True)
class Bound:
    """A parameter's range [lo, hi], linear or (``log``) in log space; with ``ends``,
    mapped by sin^2 instead of the logistic, so that either end is reached at a finite
    free variable (a metallic of 0: the logistic needs z -> -inf, which Adam's steps of
    a fixed size approach only slowly)."""

    lo: float
    hi: float
    log: bool = False
    ends: bool = False

    def value(self, z: Any, xp: Any) -> Any:
        """The parameter of free variable ``z`` (numpy or Dr.Jit: ``xp`` is np or dr),
        within [lo, hi] for every z."""
        if self.ends:  # (Dr.Jit's float32 sin is NaN far out: |z| <= 1e4 first)
            s = xp.square(xp.sin(xp.minimum(xp.maximum(z, -SIN_Z_MAX), SIN_Z_MAX)))
        else:
            s = _logistic(z, xp)
        if self.log:
            a, b = math.log(self.lo), math.log(self.hi)
            v = xp.exp(a + (b - a) * s)
        else:
            v = self.lo + (self.hi - self.lo) * s
        return xp.minimum(xp.maximum(v, self.lo), self.hi)  # rounding at the ends

    def free(self, value: Any) -> np.ndarray:
        """The free variable of ``value`` (clamped 1e-4 of the range inside it)."""
        v = np.asarray(value, dtype=np.float64)
        if self.log:
            s = (np.log(v) - math.log(self.lo)) / (math.log(self.hi) - math.log(self.lo))
        else:
            s = (v - self.lo) / (self.hi - self.lo)
        s = np.clip(s, 1e-4, 1.0 - 1e-4)  # (sin^2: off the ends, where its slope is 0)
        return np.arcsin(np.sqrt(s)) if self.ends else np.log(s / (1.0 - s))


@dataclass(frozen=True)
class Param:
    """One fitted parameter of a family: its channels (1 or 3), range and start."""

    channels: int
    bound: Bound
    init: float
    brightness: bool = False  # scaled by the first render's brightness ratio


Values = Mapping[str, Any]  # a family's parameters by name (numpy arrays or Dr.Jit values)
# (fitted, views, mask_train) -> the family's start values: ``fitted`` maps each family
# of its ``warm_from`` to its fitted candidate (``.params``: values by name as numbers;
# ``.images``: its render of each view, None where there is none), ``mask_train`` each
# view's training pixels (neural_brdf.inverse.starts.warm_start)
WarmRule = Callable[[Mapping[str, Any], Sequence[Any], Sequence[np.ndarray]], dict[str, Any]]


@dataclass(frozen=True)
class Family:
    """A candidate start: a Mitsuba plugin, its fitted parameters, and two maps of their
    values: to Mitsuba's parameter keys (``mi.traverse`` of the BSDF) and to its XML;
    where its fit starts from simpler families already fitted, those (``warm_from``,
    earlier in :data:`FAMILIES`) and the rule (``warm``: :data:`WarmRule`)."""

    name: str
    plugin: str
    about: str
    params: Mapping[str, Param]
    # (values, xp) -> {mi.traverse key: value}; xp is numpy or drjit
    to_mitsuba: Callable[[Values, Any], dict[str, Any]]
    # values (numpy) -> the <bsdf> element
    to_element: Callable[[Values], ET.Element]
    # values (numpy) -> derived figures worth reporting (a conductor's eta and k)
    derived: Callable[[Values], dict[str, Any]] = lambda values: {}
    warm_from: tuple[str, ...] = ()
    warm: WarmRule | None = None
    # varies with the half vector's azimuth: needs an anisotropic model.encoding (the
    # config's ANISOTROPIC_FAMILIES, kept equal by the tests) and gets the network's grid
    # over the half vector's disc (images.anisotropic_grid)
    anisotropic: bool = False

    @property
    def complexity(self) -> int:
        """The number of free scalars (a tie goes to the smaller)."""
        return sum(p.channels for p in self.params.values())

    def values(self, free: Mapping[str, Any], xp: Any) -> dict[str, Any]:
        """The parameters of the free variables ``free`` (by name)."""
        return {n: p.bound.value(free[n], xp) for n, p in self.params.items()}

    def initial(self, scale: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The start values, the brightness parameters times ``scale`` (RGB) if given."""
        out = {}
        for n, p in self.params.items():
            v = np.full(p.channels, p.init, dtype=np.float64)
            if scale is not None and p.brightness:
                v = v * (scale if p.channels == 3 else scale.mean())
            out[n] = v
        return out

    def free_of(self, values: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """The free variables of parameter values (clamped into their ranges)."""
        out = {}
        for n, p in self.params.items():
            v = np.broadcast_to(np.asarray(values[n], np.float64).reshape(-1), (p.channels,))
            out[n] = p.bound.free(np.clip(v, p.bound.lo, p.bound.hi))
        return out

    def numbers(self, free: Mapping[str, Any]) -> dict[str, Any]:
        """The parameters (floats, RGB as lists) of free variables given as numbers,
        with the derived figures."""
        vals = self.values({n: np.asarray(free[n], np.float64) for n in self.params}, np)
        out: dict[str, Any] = {n: _plain(v) for n, v in vals.items()}
        out.update(self.derived(vals))
        return out

    def element(self, params: Mapping[str, Any]) -> ET.Element:
        """The ``<bsdf>`` of the parameters ``params`` (as :meth:`numbers` gives them)."""
        return self.to_element({n: np.asarray(params[n], np.float64) for n in self.params})


def _plain(v: np.ndarray) -> float | list[float]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    return float(a[0]) if a.size == 1 else [float(x) for x in a]


def _rgb(v: Any) -> tuple[float, ...]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    return tuple(float(x) for x in (a if a.size == 3 else np.repeat(a, 3)))


def _f(v: Any) -> float:
    return float(np.asarray(v, dtype=np.float64).reshape(-1)[0])


# ------------------------------------------------------------------ the conductor
def eta_k(f0: Any, tint: Any, xp: Any) -> tuple[Any, Any]:
    """(eta, k) of a conductor whose Fresnel reflectance at normal incidence is ``f0``
    (< 1) and whose edge tint is ``tint`` in [0, 1] (Gulbrandsen 2014; module doc)."""
    s = xp.sqrt(f0)
    n = tint * (1.0 - f0) / (1.0 + f0) + (1.0 - tint) * (1.0 + s) / (1.0 - s)
    k2 = (f0 * (n + 1.0) * (n + 1.0) - (n - 1.0) * (n - 1.0)) / (1.0 - f0)
    return n, xp.sqrt(xp.maximum(k2, EPS_K2))


def conductor_f0(eta: Any, k: Any) -> np.ndarray:
    """The conductor Fresnel reflectance at normal incidence of (eta, k)."""
    n, kk = np.asarray(eta, np.float64), np.asarray(k, np.float64)
    return ((n - 1) ** 2 + kk**2) / ((n + 1) ** 2 + kk**2)


ALPHA = Bound(0.01, 1.0, log=True)
ALPHA_START = 0.3  # every roughness, without a warm start
REFLECTANCE = Bound(0.0, 1.0)
F0 = Bound(0.005, 0.98)
TINT = Bound(0.0, 1.0)
WEIGHT = Bound(0.0, 1.0)
WEIGHT_START = 0.5  # the blend's conductor weight, without a warm start
# principled: roughness (alpha = roughness^2 in Mitsuba), metallic; specular fixed
ROUGHNESS = Bound(0.05, 1.0)
ROUGHNESS_START = 0.5
# a real material's metallic is mostly 0 or 1 (a dielectric or a metal): reachable ends
METALLIC = Bound(0.0, 1.0, ends=True)
METALLIC_START = 0.3
PRINCIPLED_SPECULAR = 0.5
# clearcoat: the principled's clear coat, its weight and gloss (Mitsuba principled: a
# GTR1 lobe of roughness lerp(0.1, 0.001, gloss) and a fixed IOR of 1.5, after Burley
# 2012, "Physically-Based Shading at Disney", section 5.7), started halfway
CLEARCOAT = Bound(0.0, 1.0)
CLEARCOAT_START = 0.5
CLEARCOAT_GLOSS = Bound(0.0, 1.0)
CLEARCOAT_GLOSS_START = 0.5


def _principled_params(coat: bool = False) -> dict[str, Param]:
    """The principled's fitted parameters (``coat``: and its clear coat's two)."""
    out = {
        "base_color": Param(3, REFLECTANCE, 0.5, brightness=True),
        "roughness": Param(1, ROUGHNESS, ROUGHNESS_START),
        "metallic": Param(1, METALLIC, METALLIC_START),
    }
    if coat:
        out["clearcoat"] = Param(1, CLEARCOAT, CLEARCOAT_START)
        out["clearcoat_gloss"] = Param(1, CLEARCOAT_GLOSS, CLEARCOAT_GLOSS_START)
    return out


def _principled_keys(v: Values, xp: Any) -> dict[str, Any]:
    # every parameter of Mitsuba's principled is a texture: its value is "<name>.value"
    return {f"{name}.value": value for name, value in v.items()}


def _principled_element(v: Values) -> ET.Element:
    props = {n: _rgb(x) if n == "base_color" else _f(x) for n, x in v.items()}
    return inverse.bsdf_element("principled", specular=PRINCIPLED_SPECULAR, **props)


def _conductor_keys(v: Values, xp: Any, prefix: str = "", aniso: bool = False) -> dict[str, Any]:
    eta, k = eta_k(v["f0"], v["edge_tint"], xp)
    if aniso:
        out = {prefix + "alpha_u.value": v["alpha_u"], prefix + "alpha_v.value": v["alpha_v"]}
    else:
        out = {prefix + "alpha.value": v["alpha"]}
    out.update({prefix + "eta.value": eta, prefix + "k.value": k})
    return out


def _conductor_element(v: Values, aniso: bool = False) -> ET.Element:
    eta, k = eta_k(v["f0"], v["edge_tint"], np)
    alphas = (
        {"alpha_u": _f(v["alpha_u"]), "alpha_v": _f(v["alpha_v"])}
        if aniso
        else {"alpha": _f(v["alpha"])}
    )
    return inverse.bsdf_element(
        "roughconductor", distribution="ggx", **alphas, eta=_rgb(eta), k=_rgb(k)
    )


def _conductor_derived(v: Values) -> dict[str, Any]:
    eta, k = eta_k(v["f0"], v["edge_tint"], np)
    return {"eta": _plain(eta), "k": _plain(k)}


def _blend_element(v: Values) -> ET.Element:
    el = inverse.bsdf_element("blendbsdf", weight=_f(v["weight"]))
    el.append(inverse.bsdf_element("diffuse", reflectance=_rgb(v["reflectance"])))
    el.append(_conductor_element(v))
    return el


def _conductor_params(aniso: bool = False) -> dict[str, Param]:
    alphas = (
        {"alpha_u": Param(1, ALPHA, ALPHA_START), "alpha_v": Param(1, ALPHA, ALPHA_START)}
        if aniso
        else {"alpha": Param(1, ALPHA, ALPHA_START)}
    )
    return {
        **alphas,
        "f0": Param(3, F0, 0.6, brightness=True),
        "edge_tint": Param(3, TINT, 0.5),
    }


# ------------------------------------------------------------------ warm starts
def _coat_warm(fitted: Mapping[str, Any], views: Sequence[Any], mask_train: Any) -> dict:
    """The clear coat from the fitted ``principled``, its coat at the family's start."""
    coat = {"clearcoat": CLEARCOAT_START, "clearcoat_gloss": CLEARCOAT_GLOSS_START}
    return {**fitted["principled"].params, **coat}


def _aniso_warm(fitted: Mapping[str, Any], views: Sequence[Any], mask_train: Any) -> dict:
    """The anisotropic conductor from the isotropic one: alpha_u = alpha_v = alpha."""
    p = fitted["roughconductor"].params
    return {
        "alpha_u": p["alpha"],
        "alpha_v": p["alpha"],
        "f0": p["f0"],
        "edge_tint": p["edge_tint"],
    }


def _blend_warm(
    fitted: Mapping[str, Any], views: Sequence[Any], mask_train: Sequence[np.ndarray]
) -> dict:
    """The blend from the fitted ``diffuse`` and ``roughconductor``, its weight the least
    squares one on the training pixels of their renders (with the loss's weights; the
    image of a blend is the blend of the images where the object does not see itself,
    nearly so elsewhere)."""
    diff, cond = fitted["diffuse"], fitted["roughconductor"]
    num = den = 0.0
    for i, v in enumerate(views):
        a, b, m = diff.images[i], cond.images[i], mask_train[i]
        if a is None or b is None or not m.any():
            continue
        wgt = v.rel_weight()[m].astype(np.float64)
        r = (b[m] - a[m]).astype(np.float64)
        e = (v.target[m] - a[m]).astype(np.float64)
        num += float(np.sum(wgt * r * e))
        den += float(np.sum(wgt * r * r))
    weight = float(np.clip(num / den, 0.02, 0.98)) if den > 0 else WEIGHT_START
    return {
        "weight": weight,
        "reflectance": diff.params["reflectance"],
        **{k: cond.params[k] for k in ("alpha", "f0", "edge_tint")},
    }


FAMILIES: dict[str, Family] = {
    f.name: f
    for f in (
        Family(
            "diffuse",
            "diffuse",
            "Lambertian (Mitsuba diffuse): reflectance RGB",
            {"reflectance": Param(3, REFLECTANCE, 0.5, brightness=True)},
            lambda v, xp: {"reflectance.value": v["reflectance"]},
            lambda v: inverse.bsdf_element("diffuse", reflectance=_rgb(v["reflectance"])),
        ),
        Family(
            "roughplastic",
            "roughplastic",
            "a diffuse base under a GGX dielectric coating (Mitsuba roughplastic, int_ior "
            f"{ROUGHPLASTIC_IOR:g}): diffuse_reflectance RGB, alpha",
            {
                "diffuse_reflectance": Param(3, REFLECTANCE, 0.5, brightness=True),
                "alpha": Param(1, ALPHA, ALPHA_START),
            },
            lambda v, xp: {
                "diffuse_reflectance.value": v["diffuse_reflectance"],
                "alpha": v["alpha"],
            },
            lambda v: inverse.bsdf_element(
                "roughplastic",
                distribution="ggx",
                diffuse_reflectance=_rgb(v["diffuse_reflectance"]),
                alpha=_f(v["alpha"]),
                int_ior=ROUGHPLASTIC_IOR,
                ext_ior=1.0,
            ),
        ),
        Family(
            "principled",
            "principled",
            "Disney's principled BRDF (Mitsuba principled; paint, coated and dielectric "
            f"materials, metals in between): base_color RGB, roughness, metallic; specular "
            f"{PRINCIPLED_SPECULAR:g} (an IOR of 1.5), no sheen, clearcoat or transmission",
            _principled_params(),
            _principled_keys,
            _principled_element,
        ),
        Family(
            "roughconductor",
            "roughconductor",
            "an isotropic GGX conductor (Mitsuba roughconductor): alpha, F0 RGB, edge tint RGB",
            _conductor_params(),
            lambda v, xp: _conductor_keys(v, xp),
            _conductor_element,
            _conductor_derived,
        ),
        Family(
            "clearcoat",
            "principled",
            "Disney's principled BRDF under its clear coat (Mitsuba principled; varnish, "
            "lacquer, car paint): base_color RGB, roughness, metallic, clearcoat, "
            f"clearcoat_gloss; specular {PRINCIPLED_SPECULAR:g}, no sheen or transmission",
            _principled_params(coat=True),
            _principled_keys,
            _principled_element,
            warm_from=("principled",),
            warm=_coat_warm,
        ),
        Family(
            "roughconductor_aniso",
            "roughconductor",
            "an anisotropic GGX conductor (brushed; Mitsuba roughconductor): alpha_u, "
            "alpha_v, F0 RGB, edge tint RGB",
            _conductor_params(aniso=True),
            lambda v, xp: _conductor_keys(v, xp, aniso=True),
            lambda v: _conductor_element(v, aniso=True),
            _conductor_derived,
            warm_from=("roughconductor",),
            warm=_aniso_warm,
            anisotropic=True,
        ),
        Family(
            "blend",
            "blendbsdf",
            "a diffuse and an isotropic GGX conductor mixed (Mitsuba blendbsdf): the "
            "conductor's weight, reflectance RGB, alpha, F0 RGB, edge tint RGB",
            {
                "weight": Param(1, WEIGHT, WEIGHT_START),
                "reflectance": Param(3, REFLECTANCE, 0.5, brightness=True),
                **_conductor_params(),
            },
            lambda v, xp: {
                "weight.value": v["weight"],
                "bsdf_0.reflectance.value": v["reflectance"],
                **_conductor_keys(v, xp, prefix="bsdf_1."),
            },
            _blend_element,
            _conductor_derived,
            warm_from=("diffuse", "roughconductor"),
            warm=_blend_warm,
        ),
    )
}
DEFAULT = tuple(FAMILIES)  # every family, simplest first


def warm_sources(name: str) -> tuple[str, ...]:
    """The families the fit of family ``name`` starts from (none for a name that is no
    family)."""
    f = FAMILIES.get(name)
    return f.warm_from if f is not None else ()


def family(name: str) -> Family:
    """The family ``name``; ValueError naming the known ones otherwise."""
    try:
        return FAMILIES[name]
    except KeyError:
        raise ValueError(f"start family {name!r}: expected one of {', '.join(FAMILIES)}") from None
