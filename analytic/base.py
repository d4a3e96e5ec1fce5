"""The BRDF protocol shared by every analytic model.

A model is an object with

* ``eval(wi, wo)``  -> f in 1/sr, **without** the cosine, shape ``(..., 3)``;
* ``sample(wi, u)`` -> ``(wo, pdf)`` for ``u`` in ``[0, 1)^2``; pdf w.r.t. solid angle;
* ``pdf(wi, wo)``   -> ``(...)``, the density of ``sample``.

Inputs are numpy arrays or torch tensors, float32 or float64, any batch shape
``(..., 3)``; outputs have the input's type, dtype and device, and torch autograd
flows through ``eval``.  Each formula is written once, in torch (``_f``,
``_lobes``); numpy is converted only here, at the edge.

Sampling density.  ``pdf`` is the density of the directions ``sample`` produces over
the **whole sphere**, so it integrates to exactly 1 there.  A lobe centred on a
direction near the horizon (Phong, microfacet visible normals) can produce a ``wo``
below the horizon; such a sample has ``eval == 0`` and so carries zero weight, which
keeps the estimator ``f cos / pdf`` unbiased.  Over the upper hemisphere the pdf
integrates to 1 minus that lost fraction.  Lobes are mixed with weights that
approximate their albedo ("mixtures choose lobes by albedo weight").

Errors.  A bad model parameter raises :class:`ParameterError`.  A malformed array
argument of the public functions (``eval``, ``pdf``, ``sample``, ``delta_reflectance``,
:func:`analytic.albedo` ...): not real numbers, a last axis other than 3 for a direction
or 2 for ``u``, batch shapes that do not broadcast, raises ``ValueError``.  Both
messages are one line and name the parameter or argument.  The torch methods (``f``,
``pdf_t``, ``sample_t``, ``sample_dir_t``) are the hot loops of training and
quadrature, and check nothing.
"""

from __future__ import annotations

import functools
import math
import reprlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from . import frame


class ParameterError(ValueError):
    """A model parameter is invalid.  The message names the parameter."""


# ------------------------------------------------------------------ parameter checks
def _show(value) -> str:
    """A short, one-line description of a bad value for an error message."""
    if isinstance(value, (np.ndarray, torch.Tensor)):
        return f"an array of {value.dtype} of shape {tuple(value.shape)}"
    return " ".join(reprlib.repr(value).split())


def rgb(name: str, value, *, lo: float = 0.0, hi: float = 1.0) -> tuple[float, float, float]:
    """A scalar or 3-sequence -> an RGB triple, checked to lie in ``[lo, hi]``.  Each
    number is read as :func:`scalar` reads one, with ``float()``."""
    try:
        items = np.asarray(value, dtype=object)
        arr = np.array([float(v) for v in items.reshape(-1)], dtype=np.float64)
        arr = arr.reshape(items.shape)
    except (TypeError, ValueError):  # None, a string, a dict, a ragged list
        raise ParameterError(
            f"{name}: expected a number or 3 RGB numbers, got {_show(value)}"
        ) from None
    if arr.ndim == 0:
        arr = np.repeat(arr, 3)
    if arr.shape != (3,):
        raise ParameterError(f"{name}: expected a number or 3 RGB numbers, got {_show(value)}")
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{name}: must be finite, got {_show(value)}")
    if np.any(arr < lo) or np.any(arr > hi):
        raise ParameterError(f"{name}: must lie in [{lo}, {hi}], got {_show(value)}")
    return float(arr[0]), float(arr[1]), float(arr[2])


def scalar(
    name: str,
    value,
    *,
    lo: float = -math.inf,
    hi: float = math.inf,
    lo_open: bool = False,
    hi_open: bool = False,
) -> float:
    """A number checked to lie in ``[lo, hi]`` (``(`` / ``)`` where ``lo_open`` /
    ``hi_open``)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name}: expected a number, got {_show(value)}") from None
    if not math.isfinite(v):
        raise ParameterError(f"{name}: must be finite, got {_show(value)}")
    if (v <= lo if lo_open else v < lo) or (v >= hi if hi_open else v > hi):
        lb, rb = "(" if lo_open else "[", ")" if hi_open else "]"
        raise ParameterError(f"{name}: must lie in {lb}{lo}, {hi}{rb}, got {_show(value)}")
    return v


def rgb_pair(name_a: str, a, name_b: str, b) -> tuple[tuple, tuple]:
    """Two RGB albedos that share the energy: each in [0, 1], their sum <= 1 per channel."""
    a, b = rgb(name_a, a), rgb(name_b, b)
    if any(x + y > 1.0 + 1e-12 for x, y in zip(a, b)):
        raise ParameterError(
            f"{name_b}: {name_a} + {name_b} must be <= 1 per channel, "
            f"got {name_a}={a}, {name_b}={b}"
        )
    return a, b


def choice(name: str, value, options: Sequence[str]) -> str:
    if value not in options:
        raise ParameterError(f"{name}: must be one of {list(options)}, got {_show(value)}")
    return value


# ------------------------------------------------------------------ array edge
def _as_tensor(x, like: torch.Tensor | None = None, *, name: str = "x") -> torch.Tensor:
    """``x`` as a tensor (a tensor passes through); anything but real numbers (strings,
    objects, complex numbers, a ragged list) -> a one-line ValueError naming ``name``."""
    if isinstance(x, torch.Tensor):
        if x.is_complex():
            raise ValueError(f"{name}: expected real numbers, got {_show(x)}")
        return x
    try:
        arr = np.asarray(x)
    except (TypeError, ValueError):  # a ragged list
        raise ValueError(f"{name}: expected an array of real numbers, got {_show(x)}") from None
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name}: expected real numbers, got {_show(x)}")
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    t = torch.from_numpy(np.ascontiguousarray(arr).reshape(arr.shape))  # 0-d stays 0-d
    if like is not None:
        t = t.to(device=like.device)
    return t


def _common(*xs, names: Sequence[str] = (), widths: Sequence[int] = ()):
    """Convert inputs to tensors of one floating dtype; remember whether to return numpy.

    The public edge's checks: ``names`` name the inputs in errors, and with ``widths``
    input k must have shape ``(..., widths[k])`` and the batch shapes must broadcast;
    otherwise a one-line ValueError names the argument."""
    names = tuple(names) or tuple(f"x{k}" for k in range(len(xs)))
    is_numpy = not any(isinstance(x, torch.Tensor) for x in xs)
    ts = [_as_tensor(x, name=n) for x, n in zip(xs, names)]
    if widths:
        for t, n, w in zip(ts, names, widths):
            if t.shape[-1:] != (w,):
                raise ValueError(f"{n}: expected shape (..., {w}), got {tuple(t.shape)}")
        batches = [tuple(t.shape[:-1]) for t in ts]
        try:
            torch.broadcast_shapes(*batches)
        except RuntimeError:
            shapes = " and ".join(str(b) for b in batches)
            raise ValueError(
                f"{', '.join(names)}: batch shapes {shapes} do not broadcast"
            ) from None
    dtype = ts[0].dtype
    for t in ts[1:]:
        dtype = torch.promote_types(dtype, t.dtype)
    if dtype not in (torch.float32, torch.float64):
        dtype = torch.float64
    ts = [t.to(dtype) for t in ts]
    return is_numpy, ts


def _out(t: torch.Tensor, is_numpy: bool):
    return t.detach().cpu().numpy() if is_numpy else t


# ------------------------------------------------------------------ lobes
@dataclass
class Lobe:
    """One sampling strategy of a model: its mixture weight, sampler and density."""

    weight: torch.Tensor  # (...), >= 0, unnormalised
    sample: Callable[[torch.Tensor], torch.Tensor]  # u (..., 2) -> wo (..., 3)
    pdf: Callable[[torch.Tensor], torch.Tensor]  # wo (..., 3) -> (...)


def cosine_lobe(wi: torch.Tensor, weight) -> Lobe:
    w = torch.as_tensor(weight, dtype=wi.dtype, device=wi.device).expand(wi.shape[:-1])
    return Lobe(w, frame.square_to_cosine_hemisphere, frame.cosine_hemisphere_pdf)


def luminance(rgb_t: torch.Tensor) -> torch.Tensor:
    """Mixture weights use the plain channel mean: all channels count alike."""
    return rgb_t.mean(-1)


class BRDF:
    """Base class.  Subclasses set the class attributes and implement ``_f`` and ``_lobes``."""

    name: str = "brdf"
    reciprocal: bool = True  # f(wi, wo) == f(wo, wi) bit for bit, float32 and float64 (tested)
    energy_conserving: bool = True  # rho(wi) <= 1 for all wi (tested to 1e-3)
    anisotropic: bool = False  # depends on the azimuth of the tangent frame
    notes: str = ""  # what differs from the published formula, and why
    # The parameter ranges the property tests draw from (tests/strategies.py), also a
    # summary for users.  name -> ("float", lo, hi) | ("logfloat", lo, hi) |
    # ("rgb", lo, hi) | ("choice", [options]).  Ranges are chosen so that any draw is
    # a valid model (e.g. kd and ks each in [0, 0.5] where kd + ks <= 1 is required).
    param_space: dict = {}

    def __init__(self, **params):
        self.params: dict = params  # the resolved parameters (plain Python values)

    def __repr__(self) -> str:
        body = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"analytic.create({self.name!r}, {body})"

    def describe(self) -> str:
        return repr(self)

    # -- helpers for subclasses
    @staticmethod
    def const(value, like: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(value, dtype=like.dtype, device=like.device)

    # -- the three operations, torch in and out (no horizon test needed in _f)
    def _f(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _lobes(self, wi: torch.Tensor) -> list[Lobe]:
        return [cosine_lobe(wi, 1.0)]

    def f(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Torch evaluation with the horizon rule applied (0 below, never NaN)."""
        wi, wo = torch.broadcast_tensors(wi, wo)
        valid = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        # Evaluate on directions nudged above the horizon so that no branch produces
        # NaN (a NaN in the unused branch of torch.where still poisons gradients).
        safe = torch.tensor([0.0, 0.0, 1.0], dtype=wi.dtype, device=wi.device)
        wi_s = torch.where(valid[..., None], wi, safe)
        wo_s = torch.where(valid[..., None], wo, safe)
        val = self._f(wi_s, wo_s)
        return torch.where(valid[..., None], val, torch.zeros_like(val))

    def pdf_t(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        wi, wo = torch.broadcast_tensors(wi, wo)
        lobes = self._lobes(wi)
        total = functools.reduce(torch.add, [l.weight for l in lobes])  # as sum(), typed
        p = sum(l.weight * l.pdf(wo) for l in lobes) / total.clamp_min(1e-30)
        ok = (wi[..., 2] > 0) & (total > 0)
        return torch.where(ok, p, torch.zeros_like(p)).nan_to_num(0.0)

    def sample_t(self, wi: torch.Tensor, u: torch.Tensor):
        """(wo, pdf): :meth:`sample_dir_t` and the mixture pdf of what it drew."""
        wo = self.sample_dir_t(wi, u)
        return wo, self.pdf_t(wi.expand_as(wo), wo)

    def sample_dir_t(self, wi: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """wo drawn from the lobe mixture, without its pdf (which costs every lobe's pdf:
        the training data and the quadratures' proposals need only the direction)."""
        batch = torch.broadcast_shapes(wi.shape[:-1], u.shape[:-1])
        wi, u = wi.expand(batch + (3,)), u.expand(batch + (2,))
        lobes = self._lobes(wi)
        weights = torch.stack([l.weight for l in lobes], -1)
        total = weights.sum(-1, keepdim=True)
        cdf = torch.cumsum(weights, -1) / total.clamp_min(1e-30)
        u0 = u[..., 0:1]
        idx = (u0 >= cdf).sum(-1).clamp_max(len(lobes) - 1)  # chosen lobe
        lo = torch.where(idx > 0, cdf.gather(-1, (idx - 1).clamp_min(0)[..., None])[..., 0], 0.0)
        hi = cdf.gather(-1, idx[..., None])[..., 0]
        # Re-use the selection number so every lobe still sees a uniform u0.
        u0r = ((u[..., 0] - lo) / (hi - lo).clamp_min(1e-30)).clamp(0.0, 1.0 - 1e-7)
        ur = torch.stack([u0r, u[..., 1]], -1)
        if len(lobes) == 1:
            wo = lobes[0].sample(ur)
        else:
            cand = torch.stack([l.sample(ur) for l in lobes], -2)  # (..., L, 3)
            wo = cand.gather(-2, idx[..., None, None].expand(idx.shape + (1, 3)))[..., 0, :]
        return wo

    # -- public, array-typed API (malformed arrays: a ValueError naming the argument)
    def eval(self, wi, wo):
        """f(wi, wo), (..., 3), for directions wi, wo (..., 3) whose batch shapes broadcast."""
        is_np, (wi_t, wo_t) = _common(wi, wo, names=("wi", "wo"), widths=(3, 3))
        return _out(self.f(wi_t, wo_t), is_np)

    def pdf(self, wi, wo):
        """The density of :meth:`sample`'s wo, (...), for wi, wo (..., 3)."""
        is_np, (wi_t, wo_t) = _common(wi, wo, names=("wi", "wo"), widths=(3, 3))
        with torch.no_grad():
            return _out(self.pdf_t(wi_t, wo_t), is_np)

    def sample(self, wi, u):
        """Sample ``wo`` for ``wi`` (..., 3) from ``u`` (..., 2) in [0,1)^2 -> ``(wo, pdf)``.

        ``wo`` may lie below the horizon (see the module docstring); ``eval`` is 0 there.
        """
        is_np, (wi_t, u_t) = _common(wi, u, names=("wi", "u"), widths=(3, 2))
        with torch.no_grad():
            wo, p = self.sample_t(wi_t, u_t)
        return _out(wo, is_np), _out(p, is_np)

    # -- delta lobes (only `coupled` has one); not part of eval
    def delta_reflectance(self, wi):
        """Reflectance of a Dirac specular lobe at the mirror direction (0 if none)."""
        is_np, (wi_t,) = _common(wi, names=("wi",), widths=(3,))
        return _out(torch.zeros(wi_t.shape[:-1] + (3,), dtype=wi_t.dtype), is_np)
