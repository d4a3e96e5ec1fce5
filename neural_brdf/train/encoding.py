"""Reciprocity-invariant input features of a (wi, wo) pair, by encoding name.

The encodings are registered objects (:mod:`neural_brdf.encodings`: each knows its
width, whether it is anisotropic or reciprocal, the feature columns a grid is looked up
at, and its torch features); this module is training's view of them by name, as a
checkpoint or a config spells it.  The maths, and why every feature of a reciprocal
encoding is bit-exactly symmetric in (wi, wo): :mod:`neural_brdf.encodings.angles`,
:mod:`~neural_brdf.encodings.isotropic` (8 features), :mod:`~neural_brdf.encodings.anisotropic`
(14) and :mod:`~neural_brdf.encodings.raw` (6, the non-reciprocal ablation).  The angle
helpers and constants of :mod:`neural_brdf.encodings.angles` are re-exported here.
"""

from __future__ import annotations

import torch

from neural_brdf import encodings
from neural_brdf.encodings.angles import (  # noqa: F401  (re-exported: enc.PEAK_EPS, ...)
    EPS_NORM,
    HALF_PI,
    PEAK_EPS,
    PEAK_LOG_SCALE,
    cat_columns,
    columns,
    half_angle,
    peak_coordinate,
)


def num_features(encoding: str) -> int:
    return encodings.get(encoding).width


def is_anisotropic(encoding: str) -> bool:
    """Whether a model with this encoding can depend on the azimuth (2-D albedo table).

    A name no encoding is registered under (a file from elsewhere) counts as
    anisotropic: its checks then cover the azimuth too."""
    return encoding not in encodings.REGISTRY or encodings.get(encoding).anisotropic


def features(wi: torch.Tensor, wo: torch.Tensor, encoding: str, peak: str = "u_h") -> torch.Tensor:
    """(..., 3), (..., 3) -> (..., F), bit-exactly invariant under wi <-> wo
    (except for the ``raw`` ablation encoding, which is (wi, wo) itself)."""
    return encodings.get(encoding).features(wi, wo, peak)
