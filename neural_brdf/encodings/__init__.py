"""Input encodings of a direction pair: registered objects, one per ``model.encoding``.

An encoding is what the network sees of a pair (wi, wo).  Each is an :class:`Encoding`
that says everything the rest of the package needs to know about it:

    name         its ``model.encoding`` (configs, checkpoints, the ONNX metadata)
    width        features per pair, the network's input width
    anisotropic  whether it can depend on the azimuth; the albedo table is then 2-D and
                 the validator's furnace grid covers the azimuth
    reciprocal   whether its features are bit-exactly symmetric in (wi, wo), so that the
                 model is reciprocal by construction (every encoding but the raw ablation)
    grid_axes    ``model.grid.coords`` -> the two feature columns a learned grid is looked
                 up at: "theta" columns lie in [0, 1]^2, "half_disc" columns in the unit
                 disc; an encoding without an entry takes no grid of those coords
    compute      its torch function (wi, wo, peak) -> (..., width); ``peak`` is
                 ``model.peak_coordinate``

This module imports no torch: the config checks ``model.encoding`` against :func:`names`,
and ``neural-brdf --help`` stays light.  The built-in encodings' torch code is in
:mod:`.isotropic`, :mod:`.anisotropic` and :mod:`.raw` (:mod:`.angles`: the notation and
the shared helpers); ``compute`` names it as ``".module:function"`` and it is imported
when first used.

Adding an encoding: one module in this package with its features function, and its
``register(Encoding(...))`` line below.  Code that has torch loaded already (a test, a
plug-in) may register an ``Encoding`` whose ``compute`` is the function itself.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    FeatureFn = Callable[[torch.Tensor, torch.Tensor, str], torch.Tensor]


@dataclass(frozen=True, eq=False)
class Encoding:
    """One encoding; see the module docstring for the fields."""

    name: str
    width: int
    anisotropic: bool
    compute: str | FeatureFn  # ".module:function" of this package, or the function
    grid_axes: Mapping[str, tuple[int, int]] = field(default_factory=dict)
    reciprocal: bool = True

    def features(self, wi: torch.Tensor, wo: torch.Tensor, peak: str = "u_h") -> torch.Tensor:
        """(..., 3), (..., 3) -> (..., width)."""
        fn = _load(self.compute) if isinstance(self.compute, str) else self.compute
        return fn(wi, wo, peak)

    def __deepcopy__(self, memo: dict) -> Encoding:  # immutable: a copied model shares it
        return self


def _load(ref: str) -> FeatureFn:
    module, _, name = ref.partition(":")  # imported once: then sys.modules has it
    return getattr(importlib.import_module(module, __name__), name)


REGISTRY: dict[str, Encoding] = {}


def register(encoding: Encoding) -> Encoding:
    """Add ``encoding`` under its name (which must be new); returns it."""
    name, width = encoding.name, encoding.width
    if not (isinstance(name, str) and name.isidentifier()):
        raise ValueError(f"encoding name: a plain identifier, got {name!r}")
    if name in REGISTRY:
        raise ValueError(f"encoding {name!r}: already registered")
    if not (isinstance(width, int) and width >= 1):
        raise ValueError(f"encoding {name!r}: width must be an integer >= 1, got {width!r}")
    for coords, axes in encoding.grid_axes.items():
        if len(axes) != 2 or len(set(axes)) != 2 or not all(0 <= a < width for a in axes):
            raise ValueError(
                f"encoding {name!r}: grid_axes[{coords!r}] must be two distinct feature "
                f"columns in [0, {width}), got {axes!r}"
            )
    compute = encoding.compute
    if isinstance(compute, str) and not (compute.startswith(".") and ":" in compute):
        raise ValueError(f"encoding {name!r}: compute must be '.module:function' or a function")
    REGISTRY[name] = encoding
    return encoding


def names(*, reciprocal: bool | None = None, grid: str | None = None) -> tuple[str, ...]:
    """The registered encodings' names, in registration order; given ``reciprocal``, only
    those that are (or are not) reciprocal; given ``grid``, only those with axes for that
    ``model.grid.coords``."""
    return tuple(
        name
        for name, e in REGISTRY.items()
        if (reciprocal is None or e.reciprocal == reciprocal)
        and (grid is None or grid in e.grid_axes)
    )


def get(name: str) -> Encoding:
    """The encoding registered as ``name``; ValueError naming the choices if none is."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"encoding: must be one of {list(REGISTRY)}, got {name!r}") from None


# The built-in encodings (docs/model.md, "Reciprocity by construction: the encoding").
ISOTROPIC = register(
    Encoding(
        "isotropic",
        width=8,
        anisotropic=False,
        compute=".isotropic:features",
        grid_axes={"theta": (0, 1)},  # (u_h, theta_d / (pi/2))
    )
)
ANISOTROPIC = register(
    Encoding(
        "anisotropic",
        width=14,
        anisotropic=True,
        compute=".anisotropic:features",
        # theta: as isotropic; half_disc: the half vector's polar map sqrt(u_h) (cos phi_h,
        # sin phi_h), where an anisotropic distribution of normals lives
        grid_axes={"theta": (0, 1), "half_disc": (8, 9)},
    )
)
RAW = register(  # (wi, wo) as they are: NOT reciprocal, for ablations only; no grid
    Encoding("raw", width=6, anisotropic=True, compute=".raw:features", reciprocal=False)
)
