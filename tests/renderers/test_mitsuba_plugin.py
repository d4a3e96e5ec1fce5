"""The Mitsuba 3 plugins of neural_brdf.renderers.mitsuba (variant llvm_ad_rgb).

* ``neural_brdf`` eval equals onnxruntime on the same file, times cos(theta_o), to
  1e-5 relative (the export parity metric, neural_brdf.export.relative_difference);
  the Dr.Jit ONNX interpreter matches onnxruntime on every analytic model's graph too;
* ``mitsuba.chi2.ChiSquareTest``: sample() is distributed as pdf() says, at incident
  angles of 10, 45 and 75 degrees;
* the sample weight equals eval / pdf (and bs.pdf equals pdf) at sampled directions;
* the exporter stores the fitted sampling lobe in the ONNX metadata; the plugin reads
  it (its pdf is the mixture with the stored alpha and weight, computed independently
  here with analytic's GGX), and fits it at load for files without it;
* furnace renders: a sphere in a constant environment of radiance 1 under a path
  tracer of unbounded depth; no pixel exceeds 1 beyond Monte Carlo noise, for the
  neural model and for analytic models; GGX with F = 1 and multiple scattering is 1
  and Lambertian 0.8 is 0.8 over the sphere.

The neural model is a tiny, short training run of configs/mlp/gold.yaml (GGX gold, the
3 x 64 network: a trained grid model reads up to 3e-5 apart from onnxruntime at grazing
pairs, float32 in both, see tests/backends/test_codegen.py), made once per module in a temporary
directory.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

import neural_brdf
from lobe_reference import ANISO_RETRO, BECKMANN, PER_INCIDENCE, RETRO_TABLE, mixture_pdf
from neural_brdf import config, pipeline
from neural_brdf.errors import InputError
from neural_brdf.export import relative_difference
from neural_brdf.fileformat import lobe as lobe_format
from neural_brdf.physics import lobe_fit

pytestmark = pytest.mark.mitsuba

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

# Short and small: the plugin, not the fit, is under test.  The normalisation keeps its
# defaults except the sample count (its 3-sigma margin keeps the albedo bound).
TINY_RUN = [
    "train.steps=150",
    "train.threads=1",
    "train.warmup=20",
    "train.progress=false",
    "train.checkpoint_every=1000",
    "train.eval_every=0",
    "model.hidden=[16,16]",
    "data.batch_size=1024",
    "data.pool_size=16384",
    "normalization.samples=4096",
    "validation.furnace_dirs=31",
    "validation.furnace_samples=2048",
    "validation.pairs=4000",
    "validation.accuracy_samples=8192",
    "export.parity_pairs=1024",
]

PARITY_TOL = 1e-5  # the export contract's parity tolerance
CHI2_THETA_DEG = (10.0, 45.0, 75.0)
CHI2_PHI = 0.6  # incident azimuth, off-axis
# Sub-intervals per cell edge of Mitsuba's pdf integration (tests/analytic/test_sampling.py
# explains why its default, 4, is too coarse for a GGX lobe).
CHI2_IRES = 10

FURNACE_RES = 32  # pixels per side
FURNACE_SPP = 256  # per render; two renders (seeds 0 and 1) per model
FURNACE_SCALE = 1.1  # half-width of the orthographic view (sphere radius 1)
# Monte Carlo allowance: the noise of a pixel of the two-render mean is estimated from
# the spread of the two renders over the sphere; a pixel may exceed 1 by this many
# standard errors (about 600 sphere pixels: 5 sigma is ~1e-4 false alarms per model).
FURNACE_SIGMAS = 5.0


# ------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    import neural_brdf.renderers.mitsuba  # noqa: F401  (registers the plugins)

    return mitsuba


@pytest.fixture(scope="module")
def plugin(mi):
    import neural_brdf.renderers.mitsuba as plugin_module

    return plugin_module


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("tiny_run")
    cfg = config.load(CONFIGS / "mlp" / "gold.yaml", TINY_RUN)
    pipeline.run(cfg, run_dir)
    return run_dir / "model.onnx"


def with_metadata(src, dst, key, value=None):
    """A copy of the model ``src`` at ``dst`` with metadata ``key`` set (None: removed)."""
    proto = onnx.load(str(src))
    meta = {p.key: p.value for p in proto.metadata_props if p.key != key}
    if value is not None:
        meta[key] = value
    onnx.helper.set_model_props(proto, meta)
    onnx.save(proto, str(dst))
    return dst


@pytest.fixture(scope="module")
def legacy_model(tiny_model, tmp_path_factory):
    """The tiny model as exported before the lobe was stored: no ``sampling_lobe``."""
    return with_metadata(
        tiny_model, tmp_path_factory.mktemp("legacy") / "model.onnx", lobe_format.KEY
    )


# ------------------------------------------------------------------ helpers
def vec3(mi, a):
    a = np.ascontiguousarray(a, dtype=np.float32)
    return mi.Vector3f(mi.Float(a[:, 0]), mi.Float(a[:, 1]), mi.Float(a[:, 2]))


def interaction(mi, wi):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = vec3(mi, wi)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    return si


def to_np(v, n=None):
    a = np.asarray(v.numpy(), dtype=np.float64)
    return a.T if a.ndim == 2 else a


def unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def incident(theta_deg):
    t = math.radians(theta_deg)
    return [math.sin(t) * math.cos(CHI2_PHI), math.sin(t) * math.sin(CHI2_PHI), math.cos(t)]


def pairs(seed, n=20000):
    """Direction pairs in float32: wi above the horizon, wo half above, half anywhere."""
    rng = np.random.default_rng(seed)
    wi, wo = unit(rng, n), unit(rng, n)
    wi[:, 2] = np.abs(wi[:, 2])
    wo[: n // 2, 2] = np.abs(wo[: n // 2, 2])
    return wi.astype(np.float32), wo.astype(np.float32)


def furnace(mi, bsdf: dict, seed: int) -> np.ndarray:
    T = mi.ScalarTransform4f
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": -1},
            "sensor": {
                "type": "orthographic",
                "to_world": T().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0])
                @ T().scale([FURNACE_SCALE, FURNACE_SCALE, 1.0]),
                "sampler": {"type": "independent", "sample_count": FURNACE_SPP},
                "film": {
                    "type": "hdrfilm",
                    "width": FURNACE_RES,
                    "height": FURNACE_RES,
                    "pixel_format": "rgb",
                    "rfilter": {"type": "box"},
                },
            },
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "ball": {"type": "sphere", "bsdf": bsdf},
        }
    )
    return np.asarray(mi.render(scene, seed=seed), dtype=np.float64)


def pixel_radius():
    """Distance of each pixel centre from the sphere's centre, in sphere radii."""
    c = ((np.arange(FURNACE_RES) + 0.5) / FURNACE_RES * 2.0 - 1.0) * FURNACE_SCALE
    x, y = np.meshgrid(c, c)
    return np.sqrt(x * x + y * y)


# A pixel is FURNACE_SCALE / FURNACE_RES * sqrt(2) ~ 0.05 radii from centre to corner:
# pixels with centres inside INNER lie wholly on the sphere, outside OUTER wholly off it.
INNER, OUTER = 0.95, 1.06


def furnace_stats(mi, bsdf):
    a, b = furnace(mi, bsdf, 0), furnace(mi, bsdf, 1)
    mean = 0.5 * (a + b)
    inside = pixel_radius() < INNER
    # std of (a - b) is sqrt(2) sigma_pixel; the mean of two has sigma_pixel / sqrt(2)
    sigma = float(np.std((a - b)[inside])) / 2.0
    return mean, inside, sigma


# ------------------------------------------------------------------ eval
def test_eval_matches_onnxruntime(mi, tiny_model):
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(tiny_model)})
    wi, wo = pairs(1)
    got = to_np(bsdf.eval(mi.BSDFContext(), interaction(mi, wi), vec3(mi, wo)))
    f = neural_brdf.load(tiny_model).eval(wi, wo).astype(np.float64)
    ref = f * np.clip(wo[:, 2:3].astype(np.float64), 0.0, None)
    err = relative_difference(got, ref)
    assert err <= PARITY_TOL, f"plugin vs onnxruntime: {err:.3g} relative"
    below = wo[:, 2] <= 0
    assert below.any() and (got[below] == 0).all()


@pytest.mark.parametrize(
    "name, params",
    [
        ("lambertian", {"albedo": [0.2, 0.5, 0.8]}),
        ("phong", {}),
        ("blinn_phong", {}),
        ("ward", {"alpha_x": 0.2, "alpha_y": 0.4}),
        ("ashikhmin_shirley", {}),
        ("coupled", {}),
        ("bank", {}),
        ("oren_nayar", {}),
        ("retroreflective", {}),
        ("microfacet", {"alpha_x": 0.3, "alpha_y": 0.1, "fresnel": "conductor", "material": "Au"}),
        ("microfacet", {"alpha": 0.5, "fresnel": "none", "multiscatter": True}),
    ],
)
def test_interpreter_matches_onnxruntime_on_analytic_graphs(mi, plugin, name, params):
    """The interpreter on graphs with a wider op set (Expand, Reshape, Pow, ReduceL2,
    table look-ups, ...) than the neural export, against onnxruntime on the same bytes."""
    payload = plugin.analytic_onnx(name, params)
    wi, wo = pairs(2, 4000)
    cols = plugin.OnnxProgram(payload)(
        wi=[mi.Float(wi[:, k]) for k in range(3)], wo=[mi.Float(wo[:, k]) for k in range(3)]
    )["f"]
    got = np.stack([to_np(c) for c in cols], -1)
    ref = (
        ort.InferenceSession(payload, providers=["CPUExecutionProvider"])
        .run(["f"], {"wi": wi, "wo": wo})[0]
        .astype(np.float64)
    )
    err = relative_difference(got, ref)
    assert err <= PARITY_TOL, f"{name} {params}: interpreter vs onnxruntime {err:.3g}"


def test_unsupported_op_is_named(mi, plugin):
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("wi", TensorProto.FLOAT, ["N", 3])
    y = helper.make_tensor_value_info("wo", TensorProto.FLOAT, ["N", 3])
    f = helper.make_tensor_value_info("f", TensorProto.FLOAT, ["N", 3])
    node = helper.make_node("Einsum", ["wi", "wo"], ["f"], equation="ni,ni->ni")
    model = helper.make_model(helper.make_graph([node], "g", [x, y], [f]))
    with pytest.raises(plugin.UnsupportedOnnxOp, match="Einsum"):
        plugin.OnnxProgram(model.SerializeToString())


# ------------------------------------------------------------------ sampling
def test_export_stores_the_lobe_and_the_plugin_reads_it(mi, tiny_model):
    meta = neural_brdf.load(tiny_model).metadata
    stored = lobe_format.from_metadata(meta)
    assert stored is not None, sorted(meta)
    # the fit is deterministic: fitting the exported file again gives the stored lobe
    assert stored == lobe_fit.fit_onnx(tiny_model)
    # GGX alpha = 0.3 gold: a glossy lobe of about that roughness
    assert 0.15 <= stored["alpha"] <= 0.5 and stored["weight"] >= 0.5, stored
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(tiny_model)})
    assert bsdf.lobe == stored and bsdf.lobe_source == "metadata"
    assert "(metadata)" in str(bsdf)


def test_a_file_without_the_lobe_is_fitted_at_load(mi, tiny_model, legacy_model):
    assert lobe_format.KEY not in neural_brdf.load(legacy_model).metadata
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(legacy_model)})
    assert bsdf.lobe_source == "fitted at load"
    # the same network, so the same fit as the exporter's
    assert bsdf.lobe == lobe_format.from_metadata(neural_brdf.load(tiny_model).metadata)


@pytest.mark.parametrize(
    "stored",
    [
        {"alpha": 0.08, "weight": 0.5},
        {"alpha": 0.6, "weight": 0.2},
        ANISO_RETRO,
        PER_INCIDENCE,
        RETRO_TABLE,
        BECKMANN,
    ],
)
def test_pdf_is_the_stored_mixture(mi, tiny_model, tmp_path, stored):
    """A lobe unlike the fitted one is written into the file: the plugin's pdf must be
    that mixture (so the metadata, not a fit, drives sampling)."""
    text = lobe_format.to_json({"kind": lobe_format.KIND, **stored})
    path = with_metadata(tiny_model, tmp_path / "model.onnx", lobe_format.KEY, text)
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(path)})
    assert all(bsdf.lobe[k] == v for k, v in stored.items())
    wi, _ = pairs(4, 6000)
    # wo near the mirror and retro directions (where the GGX lobe matters) and anywhere
    noise = np.random.default_rng(5).normal(0, 0.1, wi.shape)
    mirror, retro = wi * [-1.0, -1.0, 1.0] + noise, wi + noise
    wo = np.concatenate([mirror[:2000], retro[2000:4000], pairs(6, 6000)[1][:2000]])
    wo = wo.astype(np.float32)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    got = to_np(bsdf.pdf(mi.BSDFContext(), interaction(mi, wi), vec3(mi, wo)))
    ref = mixture_pdf(wi, wo, stored)
    assert (ref > 0).sum() > 3000
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-6)


def test_bad_lobe_metadata_is_a_one_line_input_error(mi, plugin, tiny_model, tmp_path):
    path = with_metadata(tiny_model, tmp_path / "model.onnx", lobe_format.KEY, '{"kind": "gauss"}')
    with pytest.raises(InputError) as e:
        plugin.read_model(path)
    assert "model.onnx" in str(e.value) and lobe_format.KEY in str(e.value)
    assert "\n" not in str(e.value)


def test_a_foreign_or_empty_file_is_the_plugins_one_line_error(mi, plugin, tmp_path):
    # before: onnxruntime's own error from the lobe's fit at load, naming neither
    import onnx
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 4])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 4])
    graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y])
    onnx.save(helper.make_model(graph), tmp_path / "foreign.onnx")
    (tmp_path / "empty.onnx").write_bytes(b"")
    for name, words in [("foreign.onnx", "expected inputs"), ("empty.onnx", "no graph")]:
        with pytest.raises(InputError) as e:
            plugin.read_model(tmp_path / name)
        assert name in str(e.value) and words in str(e.value) and "\n" not in str(e.value)
        with pytest.raises(Exception, match=words):  # the constructor, through Mitsuba
            mi.load_dict({"type": "neural_brdf", "filename": str(tmp_path / name)})


@pytest.mark.parametrize(
    "theta, stored",
    [(t, None) for t in CHI2_THETA_DEG]
    + [(45.0, ANISO_RETRO), (60.0, PER_INCIDENCE), (30.0, RETRO_TABLE), (70.0, BECKMANN)],
)
def test_chi2(mi, tiny_model, theta, stored, tmp_path, monkeypatch):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    path = tiny_model
    if stored is not None:  # the anisotropic retro lobe is sampled as its pdf says
        text = lobe_format.to_json({"kind": lobe_format.KIND, **stored})
        path = with_metadata(tiny_model, tmp_path / "model.onnx", lobe_format.KEY, text)
    props = {"type": "neural_brdf", "filename": str(path)}
    sample_fn, pdf_fn = BSDFAdapter("neural_brdf", props, wi=incident(theta))
    test = ChiSquareTest(
        domain=SphericalDomain(),
        sample_func=sample_fn,
        pdf_func=pdf_fn,
        sample_dim=3,
        sample_count=1_000_000,
        ires=CHI2_IRES,
        seed=int(theta),
    )
    ok = test.run(significance_level=0.01, test_count=len(CHI2_THETA_DEG) + 4, quiet=True)
    if not ok:
        monkeypatch.chdir(tmp_path)
        test._dump_tables()
    assert ok, f"chi2 at {theta} deg (p = {test.p_value}):\n{test.messages}"


@pytest.mark.parametrize("kind", ["neural", "analytic"])
def test_sample_weight_is_eval_over_pdf(mi, tiny_model, kind):
    import drjit as dr

    props = (
        {"type": "neural_brdf", "filename": str(tiny_model)}
        if kind == "neural"
        else {
            "type": "analytic_brdf",
            "model": "microfacet",
            "params": json.dumps({"alpha": 0.2, "fresnel": "conductor", "material": "Cu"}),
        }
    )
    bsdf = mi.load_dict(props)
    rng = np.random.default_rng(3)
    n = 20000
    wi = unit(rng, n)
    wi[:, 2] = np.abs(wi[:, 2])
    wi[:100] = [0.0, 0.0, 1.0]  # normal incidence
    wi[100:200] = [math.sqrt(1 - 1e-4), 0.0, 1e-2]  # grazing
    si = interaction(mi, wi)
    u = rng.random((n, 3)).astype(np.float32)
    ctx = mi.BSDFContext()
    bs, weight = bsdf.sample(
        ctx, si, mi.Float(u[:, 0]), mi.Point2f(mi.Float(u[:, 1]), mi.Float(u[:, 2]))
    )
    value_dr, pdf_dr = bsdf.eval_pdf(ctx, si, bs.wo)
    # eval / pdf as Dr.Jit computes it (a colour over a scalar: times the reciprocal)
    ratio = to_np(dr.select(pdf_dr > 0, value_dr / pdf_dr, 0.0))
    weight, value = to_np(weight), to_np(value_dr)
    pdf, bs_pdf = to_np(pdf_dr), to_np(bs.pdf)
    assert np.isfinite(weight).all() and (weight >= 0).all()
    np.testing.assert_array_equal(bs_pdf, pdf)
    live = pdf > 0
    assert live.mean() > 0.9
    np.testing.assert_array_equal(weight, ratio)
    assert (weight[~live] == 0).all()
    # and within float32 rounding of the correctly rounded quotient
    np.testing.assert_allclose(weight[live], value[live] / pdf[live, None], rtol=3e-7, atol=0)
    # eval and pdf alone give the same numbers as eval_pdf
    np.testing.assert_array_equal(to_np(bsdf.eval(ctx, si, bs.wo)), value)
    np.testing.assert_array_equal(to_np(bsdf.pdf(ctx, si, bs.wo)), pdf)


# ------------------------------------------------------------------ any direction
# The generated code's rule (neural_brdf.backends.lobe_ir, the graph's unit_or_invalid):
# a direction with a NaN or an infinity, or of zero length, is not one; any other is
# normalised (divided by its largest component, then by its length).  Scales stay off
# float32's subnormals, which Dr.Jit's vectorised LLVM kernels flush to 0.
HOSTILE = [
    [np.nan, 0.0, 1.0],
    [np.inf, 0.0, 1.0],
    [0.1, -np.inf, 0.5],
    [0.0, 0.0, np.inf],
    [0.0, 0.0, 0.0],
    [np.nan, np.nan, np.nan],
]
SCALES = (1e-30, 1e-3, 7.5, 1e4, 1e30)


def graph_unit(w: np.ndarray) -> np.ndarray:
    """Finite, non-zero float32 directions normalised by the graph's operations."""
    w = np.asarray(w, np.float32)
    u = w / np.abs(w).max(-1, keepdims=True)
    n = np.sqrt((u[:, 0:1] * u[:, 0:1] + u[:, 1:2] * u[:, 1:2]) + u[:, 2:3] * u[:, 2:3])
    return (u / n).astype(np.float64)


def test_eval_pdf_and_sample_take_any_direction_as_the_generated_code_does(mi, tiny_model):
    """A non-finite or zero-length wi or wo gives eval 0 and pdf 0, and as wi a refused
    sample (wo = (0, 0, -1), pdf 0, weight 0); a scaled direction, (3e38, 3e38, 3e38)
    included, gives what the unit one gives: eval = f (onnxruntime at the given floats)
    times the unit wo's cosine, pdf the stored mixture at the unit vectors, the same
    sample.  Before: pdf((NaN, 0, 1), wo) was the cosine share 0.0318, pdf((3e38, 3e38,
    3e38), (0, 0, 1)) too where the generated C gives 0.148, eval((0, 0, 5), (0, 3, 4))
    was 5 f cos, and a NaN wi drew a NaN wo."""
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(tiny_model)})
    ctx = mi.BSDFContext()
    wi, wo = pairs(11, 600)
    wo[:, 2] = np.abs(wo[:, 2])
    bad = np.array(HOSTILE, np.float32)
    good = np.repeat(wi[:1], len(bad), 0)
    huge = (wi / np.abs(wi).max(-1, keepdims=True) * 3e38).astype(np.float32)
    blocks = [(wi, wo), (bad, good), (good, bad), (huge, wo), (wi, huge)]
    for k in SCALES:
        blocks += [(wi * k, wo), (wi, wo * k), (wi * k, wo / k)]
    bwi = np.concatenate([a for a, _ in blocks]).astype(np.float32)
    bwo = np.concatenate([b for _, b in blocks]).astype(np.float32)
    hostile = ~np.isfinite(bwi).all(1) | ~np.isfinite(bwo).all(1)
    hostile |= (bwi == 0).all(1) | (bwo == 0).all(1)
    assert hostile.sum() == 2 * len(HOSTILE)
    si = interaction(mi, bwi)
    value = to_np(bsdf.eval(ctx, si, vec3(mi, bwo)))
    pdf = to_np(bsdf.pdf(ctx, si, vec3(mi, bwo)))
    assert np.isfinite(value).all() and np.isfinite(pdf).all()
    assert (value[hostile] == 0).all() and (pdf[hostile] == 0).all(), pdf[hostile]
    ok = ~hostile
    uwi, uwo = graph_unit(bwi[ok]), graph_unit(bwo[ok])
    np.testing.assert_allclose(pdf[ok], mixture_pdf(uwi, uwo, bsdf.lobe), rtol=2e-4, atol=1e-6)
    f = ort.InferenceSession(str(tiny_model), providers=["CPUExecutionProvider"]).run(
        ["f"], {"wi": bwi[ok], "wo": bwo[ok]}
    )[0]
    ref = f.astype(np.float64) * np.clip(uwo[:, 2:3], 0.0, None)
    assert relative_difference(value[ok], ref) <= PARITY_TOL
    assert (pdf[ok] > 0).mean() > 0.9
    # sample: a hostile wi is a refused sample; a scaled one draws what the unit one does
    n = len(wi)
    u = np.random.default_rng(12).random((n, 3)).astype(np.float32)
    given = [np.asarray(a, np.float32) for a, _ in blocks if len(a) == n]  # every wi of n
    swi = np.concatenate([*given, bad])
    su = np.concatenate([u] * len(given) + [u[: len(bad)]])
    bs, weight = bsdf.sample(
        ctx,
        interaction(mi, swi),
        mi.Float(su[:, 0]),
        mi.Point2f(mi.Float(su[:, 1]), mi.Float(su[:, 2])),
    )
    swo, spdf, weight = to_np(bs.wo), to_np(bs.pdf), to_np(weight)
    assert np.isfinite(swo).all() and np.isfinite(spdf).all() and np.isfinite(weight).all()
    last = slice(len(swi) - len(bad), None)
    assert (swo[last] == [0.0, 0.0, -1.0]).all() and (spdf[last] == 0).all()
    assert (weight[last] == 0).all()
    assert (spdf[:n] > 0).mean() > 0.9
    for k in range(1, len(given)):
        block = slice(k * n, (k + 1) * n)
        assert np.quantile(np.linalg.norm(swo[block] - swo[:n], axis=-1), 0.999) < 1e-4, k
        np.testing.assert_allclose(spdf[block], spdf[:n], rtol=2e-4, atol=1e-6)


@pytest.mark.parametrize("place", [0, 1, 2])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, -1.0, 2.0])
def test_a_random_number_that_is_not_one_is_a_refused_sample(mi, tiny_model, place, value):
    """Not finite, or outside [0, 1], in sample1, sample2.x or sample2.y: wo = (0, 0, -1),
    pdf 0, weight 0 (before: a NaN sample2 drew a NaN wo)."""
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(tiny_model)})
    wi, _ = pairs(13, 200)
    u = np.random.default_rng(14).random((len(wi), 3)).astype(np.float32)
    u[::2, place] = value
    bs, weight = bsdf.sample(
        mi.BSDFContext(),
        interaction(mi, wi),
        mi.Float(u[:, 0]),
        mi.Point2f(mi.Float(u[:, 1]), mi.Float(u[:, 2])),
    )
    swo, spdf, weight = to_np(bs.wo), to_np(bs.pdf), to_np(weight)
    assert (swo[::2] == [0.0, 0.0, -1.0]).all() and (spdf[::2] == 0).all()
    assert (weight[::2] == 0).all()
    assert np.isfinite(swo).all() and (spdf[1::2] > 0).mean() > 0.9


# ------------------------------------------------------------------ furnace
def furnace_cases():
    return [
        pytest.param("neural", None, id="neural"),
        pytest.param(
            "analytic",
            ("microfacet", {"alpha": 0.5, "fresnel": "none", "multiscatter": True}, 1.0),
            id="ggx-F1-multiscatter",
        ),
        pytest.param("analytic", ("lambertian", {"albedo": 0.8}, 0.8), id="lambertian-0.8"),
        pytest.param(
            "analytic",
            ("microfacet", {"alpha": 0.3, "fresnel": "conductor", "material": "Au"}, None),
            id="ggx-gold",
        ),
    ]


@pytest.mark.parametrize("kind, case", furnace_cases())
def test_furnace(mi, tiny_model, kind, case):
    if kind == "neural":
        bsdf = {"type": "neural_brdf", "filename": str(tiny_model)}
        expected = None
    else:
        name, params, expected = case
        bsdf = {"type": "analytic_brdf", "model": name, "params": json.dumps(params)}
    mean, inside, sigma = furnace_stats(mi, bsdf)
    limit = 1.0 + FURNACE_SIGMAS * sigma
    assert mean.max() <= limit, (
        f"{bsdf}: max pixel {mean.max():.4f} > 1 + {FURNACE_SIGMAS:g} sigma = {limit:.4f}"
    )
    background = pixel_radius() > OUTER
    np.testing.assert_allclose(mean[background], 1.0, atol=1e-6)
    if expected is not None:
        got = mean[inside].mean()
        # the sphere mean: about 600 pixels, so its noise is ~sigma / 25
        assert abs(got - expected) <= 0.01, f"{bsdf}: sphere mean {got:.4f}, expected {expected}"
        assert np.abs(mean[inside] - expected).max() <= FURNACE_SIGMAS * sigma + 0.01


def test_analytic_plugin_samples_with_a_given_lobe_instead_of_fitting_one(mi, plugin):
    # the report renders a target with its model's stored lobe (no second fit at load)
    params = json.dumps({"alpha": 0.2, "fresnel": "conductor", "material": "Cu"})
    given = {"alpha": 0.37, "weight": 0.5}
    bsdf = mi.load_dict(
        {
            "type": "analytic_brdf",
            "model": "microfacet",
            "params": params,
            "lobe": json.dumps(given),
        }
    )
    assert bsdf.lobe_source == "given"
    assert bsdf.lobe["alpha_x"] == pytest.approx(0.37) and bsdf.lobe["weight"] == 0.5
    fitted = mi.load_dict({"type": "analytic_brdf", "model": "microfacet", "params": params})
    assert fitted.lobe_source == "fitted at load" and fitted.lobe["alpha_x"] != 0.37
    with pytest.raises(Exception, match="analytic_brdf: 'lobe'"):
        mi.load_dict(
            {"type": "analytic_brdf", "model": "microfacet", "params": params, "lobe": "{oops"}
        )
