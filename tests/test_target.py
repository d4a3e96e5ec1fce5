"""The target: one protocol for what a model is fitted to (neural_brdf/target.py, issue 28).

Every target the pipeline builds is a Target (describe, anisotropic, eval, f); an
analytic one is Sampled as well, and the quadratures take its sampler exactly then;
measured data have no sampler.  Kinds and the spatially varying seam are decided here.
"""

from __future__ import annotations

import inspect

import pytest
import torch

import analytic
from neural_brdf import export, pipeline, validate
from neural_brdf import target as targets
from neural_brdf.measured import merl
from neural_brdf.physics import quadrature
from neural_brdf.train import data


@pytest.fixture(scope="module")
def measured():
    values = merl.bake_brdf(analytic.create("lambertian", albedo=[0.5, 0.5, 0.5])).values
    return data.MeasuredTarget(merl.MerlBRDF.from_values(values))


def test_an_analytic_target_is_sampled():
    for name in ("lambertian", "ward", "microfacet"):
        t = analytic.create(name)
        assert isinstance(t, targets.Sampled) and isinstance(t, targets.Target)
        assert targets.kind_of(t) == "analytic" and targets.sampler(t) is t
        assert targets.spatially_varying(t) is False
        assert isinstance(t.describe(), str) and isinstance(t.anisotropic, bool)


def test_measured_data_are_a_target_without_a_sampler(measured):
    assert isinstance(measured, targets.Target) and not isinstance(measured, targets.Sampled)
    assert targets.kind_of(measured) == "measured" and targets.sampler(measured) is None
    assert targets.spatially_varying(measured) is False


def test_kinds_and_the_spatially_varying_seam():
    assert targets.KINDS == ("analytic", "measured", "images", "mitsuba")
    assert targets.kind_of(None) is None and targets.sampler(None) is None

    class Images:  # an images fit: it describes itself and evaluates nothing
        kind = "images"
        anisotropic = False

        def describe(self) -> str:
            return "3 images"

    class Textured:  # a teacher that varies over the surface: uv is its third argument
        kind = "mitsuba"
        anisotropic = False
        spatially_varying = True

        def describe(self) -> str:
            return "a textured Mitsuba BSDF"

        def eval(self, wi, wo, uv):
            return wi

        def f(self, wi, wo, uv):
            return wi

    images, textured = Images(), Textured()
    assert isinstance(images, targets.Described) and not isinstance(images, targets.Target)
    assert targets.kind_of(images) == "images" and targets.sampler(images) is None
    assert isinstance(textured, targets.SpatiallyVarying) and targets.spatially_varying(textured)
    assert targets.kind_of(textured) == "mitsuba"
    with pytest.raises(TypeError, match="without a kind"):
        targets.kind_of(object())  # type: ignore[arg-type]


def test_the_quadrature_adds_the_target_sampler_exactly_when_it_has_one(measured):
    wi = torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64)
    ggx = analytic.create("microfacet", alpha=0.05)
    plain = quadrature.albedo(ggx.f, wi, 4096, seed=1)
    helped = quadrature.albedo(ggx.f, wi, 4096, seed=1, target=ggx)
    assert not torch.equal(plain[0], helped[0])  # one more proposal: other points
    no_sampler = quadrature.albedo(ggx.f, wi, 4096, seed=1, target=measured)
    assert torch.equal(plain[0], no_sampler[0])


@pytest.mark.parametrize(
    "fn",
    [
        validate.physics,
        validate.accuracy,
        validate.peak,
        validate.report,
        quadrature.albedo,
        quadrature.albedo_at,
        export.target_json,
        export.normalized_model,
        export.write,
        export.export,
        pipeline.finish,
    ],
)
def test_the_target_has_one_name(fn):
    """In the signatures of the stages the target is ``target`` (``extra`` and
    ``reference`` only as former names, after it)."""
    params = list(inspect.signature(fn).parameters)
    assert "target" in params and "sampler" not in params, params
    for old in ("extra", "reference"):
        if old in params:
            assert params.index(old) > params.index("target"), params


@pytest.mark.parametrize(
    "model, params",
    [("lambertian", {"albedo": 0.0}), ("oren_nayar", {"albedo": 0.0, "sigma": 0.3})],
)
def test_an_analytic_target_that_reflects_nothing_is_refused(model, params):
    # it trained a black file with "physics PASSED" and a relative error of 1e143 %
    from neural_brdf import config

    black = config.Config.model_validate({"target": {"model": model, "params": params}})
    brdf = analytic.create(model, **params)
    wi = torch.nn.functional.normalize(torch.rand(256, 3) + torch.tensor([0.0, 0.0, 0.1]), dim=-1)
    assert not bool((brdf.eval(wi, wi.flip(0)) > 0).any())  # black indeed, at these pairs
    with pytest.raises(config.ConfigError, match="target.params: .* reflects no light"):
        data.build_target(black.target)
    grey = config.Config.model_validate({"target": {"model": model, "params": {}}})
    assert data.reflects(data.build_target(grey.target))  # the defaults reflect
