"""Analytic reflection models: the ground truth and training data of neural-brdf.

    import analytic
    analytic.available()                 # registry names
    brdf = analytic.create("microfacet", distribution="ggx", alpha=0.3, fresnel="conductor",
                           material="Au")
    brdf.eval(wi, wo)                    # f in 1/sr, no cosine, (..., 3)
    wo, pdf = brdf.sample(wi, u)         # u in [0,1)^2
    brdf.pdf(wi, wo)
    analytic.albedo(brdf, wi, n=4096)    # rho(wi) = int f cos(theta_o) dwo

See :mod:`analytic.base` for the conventions and :mod:`analytic.physics` for the
quadrature and the physics checkers.
"""

from __future__ import annotations

import importlib
import inspect
from typing import Any

from .base import BRDF, ParameterError

# registry name -> (module, class).  One model per module; imported on first use.
_MODELS: dict[str, tuple[str, str]] = {
    "lambertian": ("lambertian", "Lambertian"),
    "phong": ("phong", "Phong"),
    "blinn_phong": ("blinn_phong", "BlinnPhong"),
    "microfacet": ("microfacet", "Microfacet"),
    "ward": ("ward", "Ward"),
    "ashikhmin_shirley": ("ashikhmin_shirley", "AshikhminShirley"),
    "coupled": ("coupled", "Coupled"),
    "bank": ("bank", "Bank"),
    "oren_nayar": ("oren_nayar", "OrenNayar"),
    "retroreflective": ("retroreflective", "Retroreflective"),
}


def available() -> list[str]:
    """The registry names, in a stable order."""
    return list(_MODELS)


def model_class(name: str) -> type[BRDF]:
    if name not in _MODELS:
        raise ParameterError(f"model: unknown model {name!r}; available: {available()}")
    module, cls = _MODELS[name]
    mod = importlib.import_module(f".{module}", __name__)
    try:
        return getattr(mod, cls)
    except AttributeError:  # a registry line naming a class its module lacks
        raise ImportError(f"{mod.__name__} has no class {cls!r} (its _MODELS entry)") from None


def create(name: str, **params: Any) -> BRDF:
    """Create a model by registry name; every parameter has a documented default."""
    cls = model_class(name)
    accepted = inspect.signature(cls.__init__).parameters
    for key in params:
        if key not in accepted or key == "self":
            names = [k for k in accepted if k != "self"]
            raise ParameterError(f"{name}.{key}: unknown parameter; {name} takes {names}")
    return cls(**params)


from .physics import (  # noqa: E402  (physics uses the registry-free base only)
    albedo,
    hemispherical_albedo,
    min_value,
    reciprocity_error,
    weak_white_furnace,
)

__all__ = [
    "BRDF",
    "ParameterError",
    "available",
    "create",
    "model_class",
    "albedo",
    "hemispherical_albedo",
    "min_value",
    "reciprocity_error",
    "weak_white_furnace",
]
