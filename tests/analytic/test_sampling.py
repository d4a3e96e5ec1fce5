"""Importance sampling of every analytic model: ``sample()`` against ``pdf()``.

For each model in ``analytic.available()``, at its defaults and at random valid
parameters drawn from its ``param_space`` (fixed seeds), and at incident angles from
near-normal to near-grazing:

* chi-square: the directions ``sample()`` draws are distributed as ``pdf()`` says,
  over the whole sphere (tests/chi2.py; Sidak-corrected over every chi-square test in
  this module);
* the pdf integrates to 1 over the whole sphere, to 1e-2 (deterministic quadrature);
* the pdf that ``sample()`` returns equals ``pdf(wi, wo)`` at the sampled ``wo``;
* the sample weight ``f cos(theta_o) / pdf`` is finite and non-negative, and so are
  the directions and densities in float32;
* Mitsuba's own ``mitsuba.chi2.ChiSquareTest`` agrees, on the ``llvm_ad_rgb`` variant,
  through a small ``mi.BSDF`` adapter (defined here, for tests only).

Random draws whose samples are too concentrated for the fixed sphere grid (a lobe
within a few cells) are replaced by the next seed for the chi-square and integral tests;
see ``MIN_EFFECTIVE_CELLS``.  The consistency and finiteness tests take every draw as it
comes, extreme ones included (alpha down to 1e-4).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import analytic
import chi2

REPO = Path(__file__).resolve().parents[2]
DUMP_DIR = REPO / "runs" / "chi2"  # failing chi-square tables land here (git-ignored)

MODELS = analytic.available()
PHI_I = 0.6  # incident azimuth: off-axis, so anisotropy shows
# (parameter draw, incident theta in degrees, samples): the defaults from near-normal to
# near-grazing incidence, then random draws from param_space with fixed seeds.
CHI2_CASES = (
    ("defaults", 5.0, 1_000_000),
    ("defaults", 45.0, 1_000_000),
    ("defaults", 85.0, 1_000_000),
    (1, 60.0, 500_000),
    (2, 85.0, 500_000),
    (3, 30.0, 500_000),
)
CHECK_THETA_DEG = (0.0, 5.0, 45.0, 85.0, 89.5)  # for the cheap consistency checks
CHECK_DRAWS = ("defaults", 1, 2, 3, 4, 5, 6, 7)
CHECK_SAMPLES = 4000  # per incident angle
MITSUBA_CASES = {  # model -> params, for Mitsuba's own chi2 test
    "lambertian": {"albedo": [0.2, 0.5, 0.8]},
    "microfacet": {"distribution": "ggx", "alpha_x": 0.4, "alpha_y": 0.15},
    "microfacet-beckmann": {"distribution": "beckmann", "alpha": 0.3},
}
MITSUBA_THETA_DEG = (30.0, 80.0)
# Sub-intervals per cell edge of Mitsuba's trapezoid-rule pdf integration.  Its default,
# 4, is too coarse for the GGX lobe at 80 deg (p ~ 1e-12 at 4; 0.05 at 6; 0.4 at 8).
MITSUBA_IRES = 10
# Every chi-square test run by this module, for the Sidak correction.
TEST_COUNT = len(MODELS) * len(CHI2_CASES) + len(MITSUBA_CASES) * len(MITSUBA_THETA_DEG)

# A random draw whose samples fill fewer than this many cells of the sphere grid
# (inverse Simpson index of a 20000-sample histogram) is too concentrated for the
# chi-square test to have degrees of freedom, or for the cell quadrature to resolve:
# for chi2 and the integral it is replaced by the next seed.  GGX alpha = 0.05 at
# 85 deg fills about 14 cells, alpha = 0.02 at 45 deg about 9.
MIN_EFFECTIVE_CELLS = 25.0
REDRAWS = 100


# ------------------------------------------------------------------ helpers
def model_class(name: str):
    """The class for a test id ``name`` (``model-variant``); every model must import."""
    return analytic.model_class(name.split("-")[0])


def draw_params(space: dict, seed: int) -> dict:
    """Random parameters from a ``param_space`` (see analytic.base.BRDF.param_space)."""
    rng = np.random.default_rng(seed)
    params = {}
    for key, spec in space.items():
        kind = spec[0]
        if kind == "float":
            params[key] = float(rng.uniform(spec[1], spec[2]))
        elif kind == "logfloat":
            params[key] = float(math.exp(rng.uniform(math.log(spec[1]), math.log(spec[2]))))
        elif kind == "rgb":
            params[key] = [float(v) for v in rng.uniform(spec[1], spec[2], 3)]
        elif kind == "choice":
            params[key] = spec[1][int(rng.integers(len(spec[1])))]
        else:
            raise AssertionError(f"param_space[{key!r}]: unknown kind {kind!r} in {spec!r}")
    return params


def incident(theta_deg: float) -> np.ndarray:
    t = math.radians(theta_deg)
    return np.array([math.sin(t) * math.cos(PHI_I), math.sin(t) * math.sin(PHI_I), math.cos(t)])


def make(name: str, draw):
    """The model at its defaults, or at random parameters: draw ``k`` seeds the generator
    with ``k`` and the model's registry position, so models with the same param_space
    still get different parameters."""
    cls = model_class(name)
    if draw == "defaults":
        return analytic.create(name)
    seed = 1009 * draw + MODELS.index(name.split("-")[0])
    return analytic.create(name, **draw_params(cls.param_space, seed))


def effective_cells(brdf, wi: np.ndarray, n: int = 20000) -> float:
    """How many grid cells the model's samples fill (inverse Simpson index)."""
    u = np.random.default_rng(12345).random((n, 2))
    wo, _ = brdf.sample(np.broadcast_to(wi, (n, 3)), u)
    p = chi2.SphereGrid().histogram(wo) / n
    return float(1.0 / np.sum(p * p))


def make_testable(name: str, draw, wi: np.ndarray):
    """Like ``make``, but a random draw too concentrated for the sphere grid is redrawn."""
    brdf = make(name, draw)
    if draw == "defaults":
        return brdf
    for k in range(REDRAWS):
        if effective_cells(brdf, wi) >= MIN_EFFECTIVE_CELLS:
            return brdf
        brdf = make(name, 1000 * (k + 1) + draw)
    raise AssertionError(f"{name}: no draw in {REDRAWS} fills {MIN_EFFECTIVE_CELLS} cells")


def sampler(brdf, wi):
    def sample_fn(u):
        wo, _ = brdf.sample(np.broadcast_to(wi, (len(u), 3)), u)
        return wo

    return sample_fn


def density(brdf, wi):
    def pdf_fn(wo):
        return brdf.pdf(np.broadcast_to(wi, wo.shape), wo)

    return pdf_fn


def chi2_cases():
    return [
        pytest.param(m, d, t, n, id=f"{m}-{d}-{t:g}deg") for m in MODELS for d, t, n in CHI2_CASES
    ]


def check_cases():
    return [pytest.param(m, d, id=f"{m}-{d}") for m in MODELS for d in CHECK_DRAWS]


def check_batch(dtype=np.float64, seed: int = 7):
    """Incident directions (every CHECK_THETA_DEG, CHECK_SAMPLES each) and variates."""
    wi = np.repeat(np.stack([incident(t) for t in CHECK_THETA_DEG]), CHECK_SAMPLES, 0)
    u = np.random.default_rng(seed).random((len(wi), 2))
    return wi.astype(dtype), u.astype(dtype)


# ------------------------------------------------------------------ tests
@pytest.mark.parametrize("name", MODELS)
def test_every_model_imports(name):
    """Every registered model exists, so no test below is skipped for a missing module."""
    cls = analytic.model_class(name)
    assert issubclass(cls, analytic.BRDF)
    assert isinstance(cls.param_space, dict) and cls.param_space, f"{name}: empty param_space"


@pytest.mark.parametrize("name, draw, theta, n_samples", chi2_cases())
def test_chi2_sample_matches_pdf(name, draw, theta, n_samples):
    wi = incident(theta)
    brdf = make_testable(name, draw, wi)
    seed = 1000 * MODELS.index(name) + 10 * int(theta) + (0 if draw == "defaults" else draw)
    result = chi2.chi2_test(
        sampler(brdf, wi),
        density(brdf, wi),
        name=f"{name}-{draw}-{theta:g}deg",
        n_samples=n_samples,
        seed=seed,
        test_count=TEST_COUNT,
        dump_dir=DUMP_DIR,
    )
    assert result.passed, f"{brdf!r}, wi={wi.tolist()}\n{result.summary()}"


@pytest.mark.parametrize("name, draw, theta, n_samples", chi2_cases())
def test_pdf_integrates_to_one_over_sphere(name, draw, theta, n_samples):
    wi = incident(theta)
    brdf = make_testable(name, draw, wi)
    total = chi2.sphere_integral(density(brdf, wi))
    assert abs(total - 1.0) <= 1e-2, f"{brdf!r}, wi={wi.tolist()}: integral {total:.6f}"


@pytest.mark.parametrize("name, draw", check_cases())
def test_sampled_pdf_equals_pdf(name, draw):
    brdf = make(name, draw)
    wi, u = check_batch()
    wo, pdf_s = brdf.sample(wi, u)
    assert np.isfinite(wo).all() and np.isfinite(pdf_s).all(), repr(brdf)
    assert np.abs(np.linalg.norm(wo, axis=-1) - 1.0).max() < 1e-9, repr(brdf)
    assert (pdf_s > 0).all(), (
        f"{brdf!r}: sampled directions with pdf <= 0 at wi={wi[pdf_s <= 0][:3].tolist()}"
    )
    pdf_e = brdf.pdf(wi, wo)
    np.testing.assert_allclose(pdf_s, pdf_e, rtol=1e-6, atol=0, err_msg=repr(brdf))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("name, draw", check_cases())
def test_sample_weight_is_finite(name, draw, dtype):
    brdf = make(name, draw)
    wi, u = check_batch(dtype, seed=11)
    wo, pdf = brdf.sample(wi, u)
    assert wo.dtype == dtype and pdf.dtype == dtype
    assert np.isfinite(wo).all() and np.isfinite(pdf).all() and (pdf >= 0).all(), repr(brdf)
    f = brdf.eval(wi, wo)
    assert np.isfinite(f).all() and (f >= 0).all(), repr(brdf)
    cos_o = np.clip(wo[:, 2], 0.0, None)[:, None]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        weight = np.where(pdf[:, None] > 0, f * cos_o / pdf[:, None], 0.0)
    bad = ~np.isfinite(weight).all(-1)
    assert not bad.any(), (
        f"{brdf!r}: non-finite f cos / pdf at wi={wi[bad][:3].tolist()}, wo={wo[bad][:3].tolist()}"
    )
    assert (weight >= 0).all()
    # zero density must mean zero contribution, else the estimator f cos / pdf is biased
    assert (f[pdf == 0] * cos_o[pdf == 0] == 0).all(), repr(brdf)


# ------------------------------------------------------------------ Mitsuba's chi2
def mitsuba_llvm():
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return mi


def register_adapter(mi) -> str:
    """Register ``analytic_adapter``: an ``mi.BSDF`` that evaluates an analytic model.

    Properties: ``model`` (registry name) and ``params`` (JSON).  Called directly from
    Python (as ``mitsuba.chi2.BSDFAdapter`` does) it converts Dr.Jit arrays to numpy,
    so it is a test harness, not a renderer plugin.  Following Mitsuba's convention its
    ``pdf`` and ``eval`` are 0 below the horizon and a sample there has weight 0.
    """
    import drjit as dr

    def to_np(v, n):
        """A Dr.Jit 3-vector of width 1 or n -> numpy (n, 3) float64."""
        return np.broadcast_to(np.asarray(v.numpy(), dtype=np.float64).T, (n, 3))

    def vec3(a):
        a = np.ascontiguousarray(a, dtype=np.float32)
        return mi.Vector3f(mi.Float(a[:, 0]), mi.Float(a[:, 1]), mi.Float(a[:, 2]))

    def col3(a):
        a = np.ascontiguousarray(a, dtype=np.float32)
        return mi.Color3f(mi.Float(a[:, 0]), mi.Float(a[:, 1]), mi.Float(a[:, 2]))

    class AnalyticBSDF(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.brdf = analytic.create(props["model"], **json.loads(props["params"]))
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _f_cos_pdf(self, si, wo_np, n):
            wi = to_np(si.wi, n)
            above = (wi[:, 2] > 0) & (wo_np[:, 2] > 0)
            f = self.brdf.eval(wi, wo_np) * np.clip(wo_np[:, 2], 0.0, None)[:, None]
            pdf = np.where(above, self.brdf.pdf(wi, wo_np), 0.0)
            return f, pdf

        def sample(self, ctx, si, sample1, sample2, active=True):
            u = np.asarray(sample2.numpy(), dtype=np.float64).T
            n = len(u)
            wo, _ = self.brdf.sample(to_np(si.wi, n), u)
            f, pdf = self._f_cos_pdf(si, wo, n)
            weight = np.where(pdf[:, None] > 0, f / np.where(pdf > 0, pdf, 1.0)[:, None], 0.0)
            bs = dr.zeros(mi.BSDFSample3f, n)
            bs.wo = vec3(wo)
            bs.pdf = mi.Float(pdf.astype(np.float32))
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = 0
            return bs, col3(weight)

        def eval(self, ctx, si, wo, active=True):
            wo_np = np.asarray(wo.numpy(), dtype=np.float64).T
            f, _ = self._f_cos_pdf(si, wo_np, len(wo_np))
            return col3(f)

        def pdf(self, ctx, si, wo, active=True):
            wo_np = np.asarray(wo.numpy(), dtype=np.float64).T
            _, pdf = self._f_cos_pdf(si, wo_np, len(wo_np))
            return mi.Float(pdf.astype(np.float32))

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def to_string(self):
            return f"AnalyticBSDF[{self.brdf!r}]"

    mi.register_bsdf("analytic_adapter", lambda props: AnalyticBSDF(props))
    return "analytic_adapter"


@pytest.mark.mitsuba
@pytest.mark.parametrize("case", list(MITSUBA_CASES))
@pytest.mark.parametrize("theta", MITSUBA_THETA_DEG)
def test_mitsuba_chi2(case, theta, monkeypatch):
    model_class(case)
    mi = mitsuba_llvm()
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    plugin = register_adapter(mi)
    wi = incident(theta)
    props = {"type": plugin, "model": case.split("-")[0], "params": json.dumps(MITSUBA_CASES[case])}
    sample_fn, pdf_fn = BSDFAdapter(plugin, props, wi=wi.tolist())
    test = ChiSquareTest(
        domain=SphericalDomain(),
        sample_func=sample_fn,
        pdf_func=pdf_fn,
        sample_dim=3,
        sample_count=1_000_000,
        ires=MITSUBA_IRES,
        seed=int(theta),
    )
    ok = test.run(significance_level=0.01, test_count=TEST_COUNT, quiet=True)
    if not ok:
        out = DUMP_DIR / f"mitsuba-{case}-{theta:g}deg"
        out.mkdir(parents=True, exist_ok=True)
        monkeypatch.chdir(out)
        test._dump_tables()  # writes chi2_data.py into the current directory
    assert ok, f"{case} at {theta} deg:\n{test.messages}"
