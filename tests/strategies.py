"""Hypothesis strategies for model parameters, built from each class's ``param_space``."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import strategies as st

import analytic


def _one(spec):
    kind = spec[0]
    if kind == "float":
        return st.floats(spec[1], spec[2], allow_nan=False)
    if kind == "logfloat":
        lo, hi = math.log(spec[1]), math.log(spec[2])
        return st.floats(lo, hi, allow_nan=False).map(math.exp)
    if kind == "rgb":
        c = st.floats(spec[1], spec[2], allow_nan=False)
        return st.tuples(c, c, c)
    if kind == "choice":
        return st.sampled_from(spec[1])
    raise ValueError(f"unknown param_space kind {kind!r}")


def params(name: str):
    space = analytic.model_class(name).param_space
    return st.fixed_dictionaries({k: _one(v) for k, v in space.items()})


def directions(n: int, seed: int, grazing: float = 0.15) -> np.ndarray:
    """Upper-hemisphere directions: uniform, plus a share within 1 degree of grazing
    and the exact pole."""
    d = analytic.physics.random_directions(n, seed, grazing_fraction=grazing)
    d[-1] = (0.0, 0.0, 1.0)
    return d
