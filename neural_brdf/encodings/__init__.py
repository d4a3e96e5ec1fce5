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
import weakref
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from neural_brdf.errors import ConfigError

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
        return self._fn()(wi, wo, peak)

    def check(self, peak: str = "u_h") -> None:
        """Once per process and peak coordinate: that the features have ``width``
        columns, are finite and (``reciprocal``) bit-exactly symmetric on a few pairs;
        a ConfigError naming the encoding otherwise (:func:`_check`).  A network calls it
        when it is built (:class:`neural_brdf.train.model.RawBRDF`), outside any torch
        transform."""
        if peak not in _CHECKED.get(self, ()):
            _check(self, self._fn(), peak)

    def _fn(self) -> FeatureFn:
        return _load(self) if isinstance(self.compute, str) else self.compute

    def __deepcopy__(self, memo: dict) -> Encoding:  # immutable: a copied model shares it
        return self


def _load(encoding: Encoding) -> FeatureFn:
    """The function ``encoding.compute`` names (imported once: then sys.modules has
    it); a ConfigError naming the encoding and the cause when it cannot be found."""
    module, _, name = str(encoding.compute).partition(":")
    try:
        return getattr(importlib.import_module(module, __name__), name)
    except (ImportError, AttributeError) as e:
        raise ConfigError(
            f"model.encoding: {encoding.name!r}: compute {encoding.compute!r}: "
            f"{type(e).__name__}: {e}"
        ) from None


# encoding -> the peak coordinates its features passed :func:`_check` at, in this process
_CHECKED: weakref.WeakKeyDictionary[Encoding, set[str]] = weakref.WeakKeyDictionary()
CHECK_PAIRS = 64  # direction pairs of the first-use check


def _check(encoding: Encoding, fn: FeatureFn, peak: str) -> None:
    """On an encoding's first use (:meth:`Encoding.check`): its features of a few pairs
    above the horizon have its ``width`` columns, are finite, and (``reciprocal``) are
    bit-identical for (wi, wo) and (wo, wi).  Otherwise a ConfigError (one line, exit 2
    on the command line) naming ``model.encoding`` and the encoding: a wrong width would
    fail later as a matrix-shape error inside torch, and a feature that is not symmetric
    would train a model that the validator finds not reciprocal."""
    import torch

    # on the CPU whatever torch's default device (the generator is the CPU's)
    with torch.device("cpu"), torch.no_grad():
        gen = torch.Generator().manual_seed(0)
        wi, wo = (torch.randn(CHECK_PAIRS, 3, generator=gen) for _ in range(2))
        wi[:, 2], wo[:, 2] = wi[:, 2].abs() + 0.05, wo[:, 2].abs() + 0.05
        wi, wo = wi / wi.norm(dim=-1, keepdim=True), wo / wo.norm(dim=-1, keepdim=True)
        a, b = fn(wi, wo, peak), fn(wo, wi, peak)
    where = f"model.encoding: {encoding.name!r}"
    if a.shape != (CHECK_PAIRS, encoding.width):
        raise ConfigError(
            f"{where}: its features of {CHECK_PAIRS} pairs have shape {tuple(a.shape)}, "
            f"not ({CHECK_PAIRS}, {encoding.width}) (its width)"
        )
    if not bool(torch.isfinite(a).all()):
        raise ConfigError(f"{where}: its features of pairs above the horizon are not finite")
    if encoding.reciprocal and not torch.equal(a, b):
        col = int((a != b).any(dim=0).nonzero()[0])
        raise ConfigError(
            f"{where}: reciprocal, but its feature {col} differs between (wi, wo) and "
            "(wo, wi); make it symmetric, or register it with reciprocal=False"
        )
    _CHECKED.setdefault(encoding, set()).add(peak)


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
