"""What a model is fitted to and compared with: the one type of a target (issue 28).

    from neural_brdf.target import Sampled, Target, kind_of

The pipeline, the exporter, the validator and the quadratures take it under one name,
``target`` (``None``: there is none, as for a network checked on its own).  A target
is structural, a :class:`typing.Protocol`: anything with these members is one.

* :class:`Described`, every target: ``describe()`` (one line: the metadata's
  ``target.description``) and ``anisotropic`` (it depends on the azimuth of the tangent
  frame, so the checks probe both tangent planes).
* :class:`Target`, a target that can be evaluated, numpy and torch: ``eval(wi, wo)`` and
  ``f(wi, wo)``, (N, 3) directions in the local frame (fileformat.FRAME) -> (N, 3) RGB in
  1/sr without the cosine, 0 below the horizon.  The validator compares a model with it
  (accuracy; peak unless it is measured data).
* :class:`Sampled`, a target with its own importance sampler: ``sample_dir_t(wi, u)``
  and ``pdf_t(wi, wo)`` (torch).  The quadratures add it to their proposals
  (physics.quadrature.albedo), the accuracy pairs draw wo from it.

Kinds (:data:`KINDS`; :func:`kind_of` reads a target's ``kind``):

* ``"analytic"``: an :class:`analytic.BRDF` (``analytic.create``), a :class:`Sampled`;
* ``"measured"``: a measured file (train.data.MeasuredTarget), a :class:`Target` with no
  sampler;
* ``"images"``: an inverse-rendering fit to photographs (neural_brdf.inverse): a
  :class:`Described` only.  Nothing evaluates it, so a model fitted to it is validated
  without a reference (physics only), the quadratures get no proposal, and the
  metadata's target is ``{"kind": "images", "views": N, ...}``;
* ``"mitsuba"``: a teacher that Mitsuba 3 evaluates (any BSDF of a scene): a
  :class:`Target`, possibly spatially varying.

A material that varies over the surface (a textured one: a ``"mitsuba"`` teacher, or a
future ``"images"`` fit of a textured object) is a :class:`SpatiallyVarying`: its
``spatially_varying`` is True and its ``eval`` and ``f`` take a third argument ``uv``,
(N, 2) texture coordinates, the values a model file takes as its optional input
``fileformat.UV``.  Every other target is uniform: it has no ``spatially_varying`` (or
it is False) and it is called with (wi, wo) alone; :func:`spatially_varying` is how the
stages ask (the textured teacher: neural_brdf.measured.textured).

Only the kinds decided here exist; a new kind of target adds its name to :data:`Kind`,
sets ``kind`` on its class and gives the members of its protocol.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal, Protocol, get_args, runtime_checkable

if TYPE_CHECKING:  # the protocols name these types; importing this module loads neither
    import numpy as np
    import torch

Kind = Literal["analytic", "measured", "images", "mitsuba"]
KINDS: tuple[Kind, ...] = get_args(Kind)


@runtime_checkable
class Described(Protocol):
    """Every target, an images fit included: what it is."""

    @property
    def anisotropic(self) -> bool:
        """It depends on the azimuth of the tangent frame."""
        ...

    def describe(self) -> str:
        """One line: what the model was fitted to (the metadata's description)."""
        ...


@runtime_checkable
class Target(Described, Protocol):
    """A target that can be evaluated: what validation compares a model with."""

    def eval(self, wi: Any, wo: Any) -> np.ndarray:
        """f(wi, wo) for (N, 3) arrays (numpy in, numpy out), 1/sr, no cosine."""
        ...

    def f(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """The same in torch (training, accuracy pairs, quadratures)."""
        ...


@runtime_checkable
class Sampled(Target, Protocol):
    """A target with its own importance sampler (the analytic models)."""

    def sample_dir_t(self, wi: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """wo for ``wi`` (..., 3) from ``u`` (..., 2) uniform in [0, 1)^2."""
        ...

    def pdf_t(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """The density of :meth:`sample_dir_t`'s wo, per solid angle."""
        ...


@runtime_checkable
class SpatiallyVarying(Described, Protocol):
    """A target that varies over the surface: ``eval`` and ``f`` take the texture
    coordinates ``uv`` (N, 2) too (as the model file's optional input fileformat.UV)."""

    @property
    def spatially_varying(self) -> Literal[True]: ...

    def eval(self, wi: Any, wo: Any, uv: Any) -> np.ndarray: ...

    def f(self, wi: torch.Tensor, wo: torch.Tensor, uv: torch.Tensor) -> torch.Tensor: ...


def kind_of(target: Described | None) -> Kind | None:
    """The target's ``kind`` (None for no target).  A target whose class does not say
    is ``"analytic"`` if it is an :class:`analytic.BRDF`, ``"measured"`` if it has the
    measured pairs (``grid_pairs``)."""
    if target is None:
        return None
    kind = getattr(target, "kind", None)
    if kind in KINDS:
        return kind
    import analytic  # torch: only once a target exists

    if isinstance(target, analytic.BRDF):
        return "analytic"
    if isinstance(target, Target) and hasattr(target, "grid_pairs"):
        return "measured"
    raise TypeError(f"{type(target).__name__}: a target without a kind (one of {KINDS})")


def spatially_varying(target: Described | None) -> bool:
    """Whether ``target`` varies over the surface (its ``eval`` and ``f`` take uv)."""
    return bool(getattr(target, "spatially_varying", False))


def check_textured(target: Described | None, *, textured: bool, where: str) -> None:
    """InputError naming ``where`` when a textured model's ``target`` is uniform, or a
    uniform model's varies over the surface: a run whose ``target.mitsuba`` file was
    changed since it trained (no target: nothing to check)."""
    if target is None or spatially_varying(target) == textured:
        return
    from neural_brdf.errors import InputError

    model = "a textured model" if textured else "a uniform model"
    does = "does not vary" if textured else "varies"
    raise InputError(
        f"{where}: {model}, and its teacher ({target.describe()}) {does} over the "
        "surface: was the file changed since the run trained? Train anew (--overwrite)"
    )


def sampler(target: Described | None) -> Sampled | None:
    """``target`` if it has its own importance sampler, else None."""
    return target if isinstance(target, Sampled) else None
