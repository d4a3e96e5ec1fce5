"""The public API of `analytic`: array types, shapes, dtypes, autograd, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import analytic
from strategies import directions


def test_registry_lists_every_issue_model():
    # a superset: a model added by its own file and _MODELS line (docs/architecture.md,
    # "Adding something") is welcome; the issue's models must stay
    issue = {
        "lambertian",
        "phong",
        "blinn_phong",
        "microfacet",
        "ward",
        "ashikhmin_shirley",
        "coupled",
        "bank",
        "oren_nayar",
        "retroreflective",
    }
    missing = issue - set(analytic.available())
    assert not missing, f"analytic.available() lost {sorted(missing)}"


@pytest.mark.parametrize("name", analytic.available())
def test_numpy_in_numpy_out_any_batch_shape(name):
    brdf = analytic.create(name)
    wi = directions(24, 1).reshape(2, 3, 4, 3)
    wo = directions(24, 2).reshape(2, 3, 4, 3)
    for dtype in (np.float32, np.float64):
        f = brdf.eval(wi.astype(dtype), wo.astype(dtype))
        assert isinstance(f, np.ndarray) and f.dtype == dtype and f.shape == (2, 3, 4, 3)
        p = brdf.pdf(wi.astype(dtype), wo.astype(dtype))
        assert p.dtype == dtype and p.shape == (2, 3, 4)
        u = np.random.default_rng(0).random((2, 3, 4, 2)).astype(dtype)
        wo_s, pdf_s = brdf.sample(wi.astype(dtype), u)
        assert wo_s.dtype == dtype and wo_s.shape == (2, 3, 4, 3) and pdf_s.shape == (2, 3, 4)
        np.testing.assert_allclose(np.linalg.norm(wo_s, axis=-1), 1.0, atol=1e-5)
    # broadcasting: one wi against many wo
    assert brdf.eval(wi[0, 0, 0], wo).shape == (2, 3, 4, 3)


@pytest.mark.parametrize("name", analytic.available())
def test_torch_in_torch_out_matches_numpy(name):
    brdf = analytic.create(name)
    wi, wo = directions(50, 3), directions(50, 4)
    f_np = brdf.eval(wi, wo)
    f_t = brdf.eval(torch.from_numpy(wi), torch.from_numpy(wo))
    assert isinstance(f_t, torch.Tensor) and f_t.dtype == torch.float64
    np.testing.assert_array_equal(f_t.numpy(), f_np)
    f32 = brdf.eval(torch.from_numpy(wi).float(), torch.from_numpy(wo).float())
    assert f32.dtype == torch.float32
    np.testing.assert_allclose(f32.numpy(), f_np, rtol=2e-3, atol=1e-6)


@pytest.mark.parametrize("name", ["microfacet", "ashikhmin_shirley", "ward", "oren_nayar"])
def test_autograd_flows_through_eval(name):
    brdf = analytic.create(name)
    wi = torch.tensor(directions(32, 5), requires_grad=True)
    wo = torch.tensor(directions(32, 6), requires_grad=True)
    brdf.eval(wi, wo).sum().backward()
    assert wi.grad is not None and torch.isfinite(wi.grad).all()
    assert wo.grad.abs().sum() > 0


def test_autograd_matches_finite_differences():
    brdf = analytic.create("microfacet", alpha=0.4, fresnel="conductor", material="Cu")
    wi = torch.tensor([[0.3, 0.2, 0.9327379]], dtype=torch.float64, requires_grad=True)
    wo = torch.tensor([[-0.1, -0.4, 0.9110434]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: brdf.eval(a, wo), (wi,))


def test_output_follows_input_device():
    brdf = analytic.create("microfacet")
    wi = torch.tensor(directions(8, 1), device="cpu")
    assert brdf.eval(wi, wi).device == wi.device


@pytest.mark.parametrize(
    "name,params,field",
    [
        ("microfacet", {"alpha": 0.0}, "alpha"),
        ("microfacet", {"alpha": -0.1}, "alpha"),
        ("microfacet", {"distribution": "phong"}, "distribution"),
        ("microfacet", {"fresnel": "schlick", "eta": 1.5}, "eta"),
        ("microfacet", {"fresnel": "conductor", "material": "Unobtainium"}, "material"),
        ("microfacet", {"alpha": 0.2, "alpha_x": 0.1}, "alpha"),
        ("microfacet", {"alphax": 0.2}, "alphax"),
        ("lambertian", {"albedo": 1.2}, "albedo"),
        ("lambertian", {"albedo": [0.5, 0.5]}, "albedo"),
        ("lambertian", {"albedo": float("nan")}, "albedo"),
        ("phong", {"kd": 0.7, "ks": 0.5}, "ks"),
    ],
)
def test_bad_parameters_raise_naming_the_field(name, params, field):
    with pytest.raises(analytic.ParameterError, match=field):
        analytic.create(name, **params)


def test_unknown_model_names_the_choices():
    with pytest.raises(analytic.ParameterError, match="lambertian"):
        analytic.create("lambert")


def test_sample_pdf_consistency():
    """The pdf returned by sample() equals pdf() at the sampled direction."""
    for name in analytic.available():
        brdf = analytic.create(name)
        wi = directions(256, 9)
        u = np.random.default_rng(1).random((256, 2))
        wo, p = brdf.sample(wi, u)
        np.testing.assert_allclose(p, brdf.pdf(wi, wo), rtol=1e-9, err_msg=name)


def test_albedo_reports_its_error_and_converges():
    brdf = analytic.create("microfacet", alpha=0.2, fresnel="conductor", material="Au")
    wi = np.array([[0.5, 0.0, np.sqrt(0.75)]])
    rho_lo, err_lo = analytic.albedo(brdf, wi, n=1024, return_error=True)
    rho_hi, err_hi = analytic.albedo(brdf, wi, n=65536, return_error=True)
    assert err_hi.max() < err_lo.max()
    assert np.all(np.abs(rho_lo - rho_hi) <= 4 * err_lo + 1e-6)


def test_hemispherical_albedo_of_lambertian_is_its_albedo():
    brdf = analytic.create("lambertian", albedo=[0.1, 0.5, 0.9])
    np.testing.assert_allclose(analytic.hemispherical_albedo(brdf), [0.1, 0.5, 0.9], rtol=1e-10)


def test_checkers_detect_violations():
    """reciprocity_error and min_value can fail: a non-reciprocal, partly negative f."""

    def bad(wi, wo):
        return np.repeat((wi[..., 2] * 2.0 - wo[..., 2])[..., None], 3, -1)

    assert analytic.reciprocity_error(bad) > 0.1
    assert analytic.min_value(bad) < 0
    assert analytic.min_value(lambda a, b: np.full(a.shape, np.nan)) == -np.inf
