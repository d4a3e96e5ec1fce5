"""Fixtures shared by the images-fit tests (tests/inverse)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def mi():
    """Mitsuba in ``llvm_ad_rgb`` with the project's differentiable plugin registered
    (:func:`neural_brdf.inverse.fit.use_variant`)."""
    from neural_brdf.inverse import fit as inverse

    return inverse.use_variant("llvm_ad_rgb")
