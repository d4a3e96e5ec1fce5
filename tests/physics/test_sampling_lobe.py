"""neural_brdf.physics.lobe_fit: the sampling-lobe fit (no renderer needed) and its metadata format.

* On analytic models with a known best proposal: a Lambertian is sampled exactly by the
  cosine lobe (weight 0, relative second moment 1), and a GGX reflector with F = 1 by
  the isotropic GGX visible-normal lobe of about its own roughness;
* an anisotropic target gets an anisotropic lobe stretched along its own long axis, and
  a retroreflector a retro lobe (turned by pi about the normal), each with a lower
  second moment than the best lobe without that freedom: measured here on fresh samples
  drawn with analytic's GGX sampler, not on the fit's own pool;
* the metadata round-trips, and malformed or unknown entries fail with a one-line
  InputError naming the key.

That the exporter stores the lobe and the Mitsuba plugin samples with the stored values
is tested in tests/renderers/test_mitsuba_plugin.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import analytic
from neural_brdf.errors import InputError
from neural_brdf.fileformat import lobe as lobe_format
from neural_brdf.physics import lobe_fit


def fitted(name, **params):
    return lobe_fit.fit(analytic.create(name, **params).eval)


def test_lambertian_is_sampled_by_the_cosine_lobe_alone():
    got = fitted("lambertian", albedo=0.7)
    assert got["kind"] == lobe_format.KIND
    assert got["weight"] == 0.0, got
    # f cos / p_cos is the albedo itself: no variance, up to the estimate of the albedo
    assert abs(got["second_moment"] - 1.0) < 0.02, got
    assert got["second_moment"] == got["second_moment_cosine"]


@pytest.mark.parametrize("alpha", [0.05, 0.3])
def test_ggx_is_sampled_by_a_ggx_lobe_of_its_roughness(alpha):
    got = fitted("microfacet", distribution="ggx", alpha=alpha, fresnel="none")
    assert got["weight"] >= 0.9, got  # nearly all samples from the lobe
    assert got["alpha_x"] == got["alpha_y"] == got["alpha"] and not got["retro"], got
    # within about one step of the alpha grid (a factor 1.21)
    assert abs(math.log(got["alpha"] / alpha)) <= math.log(1.3), got
    assert got["second_moment"] < 0.5 * got["second_moment_cosine"], got


# incident directions between and beyond the fit's (5 to 80 degrees), at other azimuths
THETA_OFF_NODES = (12.5, 27.5, 42.5, 57.5, 72.5, 85.0)


def fresh_second_moment(brdf, got: dict, n: int = 1 << 15, seed: int = 7) -> float:
    """E[(f cos / p)^2] / E[f cos / p]^2 of the lobe ``got``, averaged over incident
    directions other than the fit's, from n fresh samples each (analytic's GGX sampler
    and pdf)."""
    from analytic import frame
    from analytic.microfacet import Distribution

    gen = torch.Generator().manual_seed(seed)
    turn = torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64) if got["retro"] else 1.0
    out = []
    for k, theta in enumerate(THETA_OFF_NODES):
        t, phi = math.radians(theta), 0.4 + 0.9 * k
        ax, ay, w = got["alpha_x"], got["alpha_y"], got["weight"]
        if got.get("table"):  # this direction's values, interpolated with np.interp
            tab = got["table"]
            ax, ay, w = (
                float(np.interp(math.cos(t), tab["cos_theta"], tab[key]))
                for key in ("alpha_x", "alpha_y", "weight")
            )
        dist = Distribution(got["distribution"], ax, ay)
        wi = torch.tensor(
            [math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t)],
            dtype=torch.float64,
        ).expand(n, 3)
        u = torch.rand(n, 2, generator=gen, dtype=torch.float64)
        pick = torch.rand(n, generator=gen, dtype=torch.float64) < w
        wo_ggx = frame.reflect(wi, dist.sample_visible(wi, u)) * turn
        wo = torch.where(pick[:, None], wo_ggx, frame.square_to_cosine_hemisphere(u))
        v = wo * turn
        h = frame.normalize(wi + v)
        p_ggx = dist.pdf_visible(wi, h) / (4.0 * frame.dot(v, h).clamp_min(1e-12))
        pdf = (1 - w) * torch.where(wo[:, 2] > 0, frame.cosine_hemisphere_pdf(wo), 0.0)
        pdf = pdf + w * p_ggx
        fc = brdf.eval(wi, wo).mean(-1) * wo[:, 2].clamp_min(0.0)
        x = torch.where((fc > 0) & (pdf > 0), fc / pdf.clamp_min(1e-300), 0.0)
        out.append(float((x * x).mean() / x.mean() ** 2))
    return sum(out) / len(out)


@pytest.mark.parametrize("ax, ay", [(0.15, 0.45), (0.45, 0.15)])
def test_anisotropic_target_gets_an_anisotropic_lobe(ax, ay):
    brdf = analytic.create("microfacet", alpha_x=ax, alpha_y=ay, fresnel="conductor", material="Al")
    got = lobe_fit.fit(brdf.eval)
    iso = lobe_fit.fit(brdf.eval, anisotropic=False)
    assert iso["alpha_x"] == iso["alpha_y"] and not got["retro"], (got, iso)
    # stretched along the target's long axis, by at least half the target's aspect
    aspect = got["alpha_y"] / got["alpha_x"]
    assert (aspect > 1.5) if ay > ax else (aspect < 1 / 1.5), got
    assert got["alpha"] == pytest.approx(math.sqrt(got["alpha_x"] * got["alpha_y"]))
    assert fresh_second_moment(brdf, got) < 0.85 * fresh_second_moment(brdf, iso)


def test_retroreflector_gets_a_retro_lobe():
    brdf = analytic.create("retroreflective", kd=[0.3, 0.3, 0.05], kr=0.5, exponent=30.0)
    got = lobe_fit.fit(brdf.eval)
    mirror = lobe_fit.fit(brdf.eval, retro=False)
    assert got["retro"] and got["weight"] > 0 and not mirror["retro"], (got, mirror)
    assert fresh_second_moment(brdf, got) < 0.5 * fresh_second_moment(brdf, mirror)


@pytest.mark.parametrize(
    "name, params",
    [
        ("ashikhmin_shirley", {"rd": [0.6, 0.08, 0.05], "rs": 0.04, "nu": 200.0, "nv": 200.0}),
        ("phong", {"kd": [0.4, 0.3, 0.2], "ks": 0.3, "exponent": 50.0}),
    ],
)
def test_fresnel_and_phong_targets_get_a_per_incidence_lobe(name, params):
    """Plastic's specular share grows towards grazing (Fresnel) and a Phong lobe widens
    in half-vector space: one lobe for every incident direction fits neither."""
    brdf = analytic.create(name, **params)
    got = lobe_fit.fit(brdf.eval)
    single = lobe_fit.fit(brdf.eval, per_incidence=False)
    t = got["table"]
    assert "table" not in single and len(t["cos_theta"]) == len(lobe_fit.THETA_DEG), got
    assert len(set(t["weight"])) > 1 or len(set(t["alpha_x"])) > 1, t
    # scored off the table's nodes, so the interpolation is tested too
    assert fresh_second_moment(brdf, got) < 0.9 * fresh_second_moment(brdf, single)


@pytest.mark.parametrize("alpha, material", [(0.1, "Ag"), (0.6, "Cu")])
def test_beckmann_target_gets_a_beckmann_lobe(alpha, material):
    """A GGX lobe of any roughness differs from a Beckmann target in shape (most at
    grazing incidence); the Beckmann visible-normal lobe follows it."""
    brdf = analytic.create(
        "microfacet", distribution="beckmann", alpha=alpha, fresnel="conductor", material=material
    )
    got = lobe_fit.fit(brdf.eval)
    ggx = lobe_fit.fit(brdf.eval, distributions=("ggx",))
    assert got["distribution"] == "beckmann" and ggx["distribution"] == "ggx", (got, ggx)
    # relative variances (second moment - 1): the Beckmann lobe's is at most half
    assert fresh_second_moment(brdf, got) - 1 < 0.5 * (fresh_second_moment(brdf, ggx) - 1)


@pytest.mark.parametrize("theta", lobe_fit.THETA_DEG[::2])
def test_the_pools_lobe_densities_are_the_file_formats_bit_for_bit(theta):
    """The fit scores a lobe with the parts no alpha changes computed once per pool
    (``_Pool._density``); every value must be the file format's density
    (``lobe.ggx_pdf`` / ``lobe.beckmann_pdf``, what samplers are tested against) to the
    last bit, or the stored second moments, and so the lobes chosen, would move."""
    brdf = analytic.create("microfacet", distribution="beckmann", alpha=0.3)
    pool = lobe_fit._Pool(brdf.eval, lobe_fit._incident(theta, 0.4), np.random.default_rng(3))
    assert len(pool.wo) > 1000
    n = len(lobe_fit.ALPHAS)
    pairs = [(i, i) for i in range(n)] + [(i, n - 1 - i) for i in range(0, n, 3)]
    for dist, pdf in (("ggx", lobe_format.ggx_pdf), ("beckmann", lobe_format.beckmann_pdf)):
        extra = {"erf": lobe_fit._torch_erf} if dist == "beckmann" else {}
        for retro in (False, True):
            wo = lobe_format.turn(pool.wo) if retro else pool.wo
            for ia, ib in pairs:
                ax, ay = float(lobe_fit.ALPHAS[ia]), float(lobe_fit.ALPHAS[ib])
                want = pdf(pool.wi, wo, ax, ay, **extra)
                got = pool._density(ax, ay, retro, dist)
                assert got.shape == want.shape, (dist, retro, ax, ay)
                assert np.array_equal(got, want), (theta, dist, retro, ax, ay)


def test_the_pools_second_moments_are_the_plain_sum_bit_for_bit():
    """``_Pool.second_moments`` sums each share's c / ((1 - w) p_cos + w p) in place, the
    cosine part computed once; the values must be the plain expression's to the last bit
    (the lobes chosen depend on them)."""
    brdf = analytic.create("microfacet", distribution="beckmann", alpha=0.2)
    pool = lobe_fit._Pool(brdf.eval, lobe_fit._incident(35.0, 0.4), np.random.default_rng(5))
    n = len(lobe_fit.ALPHAS)
    for ia, ib, retro, dist in [
        (3, 3, False, "ggx"),
        (9, 9, True, "beckmann"),
        (2, n - 3, False, "ggx"),
    ]:
        got = pool.second_moments(ia, ib, retro, dist)
        if ia == ib and dist == "ggx":
            p = pool.p_iso[retro][ia]
        else:
            ax, ay = float(lobe_fit.ALPHAS[ia]), float(lobe_fit.ALPHAS[ib])
            p = pool._density(ax, ay, retro, dist).astype(np.float32)
        with np.errstate(divide="ignore"):
            want = np.array(
                [
                    np.sum(pool.c / ((1 - w) * pool.p_cos + w * p), dtype=np.float64)
                    for w in lobe_fit.WEIGHTS.astype(np.float32)
                ]
            )
        assert np.array_equal(got, want / pool.norm), (ia, ib, retro, dist)
        assert np.all(np.isfinite(got[1:])), got


def test_fit_is_deterministic():
    brdf = analytic.create("phong")
    assert lobe_fit.fit(brdf.eval) == lobe_fit.fit(brdf.eval)


def test_metadata_round_trip():
    got = fitted("blinn_phong")
    assert lobe_format.from_metadata({lobe_format.KEY: lobe_format.to_json(got)}) == got
    assert lobe_format.from_metadata({"other": "1"}) is None
    # a stored alpha below the floor is raised to it
    sharp = lobe_format.parse(lobe_format.to_json({**got, "alpha": 1e-4, "alpha_x": 1e-4}))
    assert sharp["alpha"] == sharp["alpha_x"] == lobe_format.MIN_ALPHA


def test_a_lobe_stored_before_anisotropy_reads_as_isotropic_mirror():
    old = lobe_format.parse('{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5}')
    assert (old["alpha_x"], old["alpha_y"], old["retro"]) == (0.3, 0.3, False)
    assert old["distribution"] == "ggx"
    assert lobe_format.complete({"alpha": 0.3, "weight": 0.5}) == old


@pytest.mark.parametrize(
    "text, words",
    [
        ("not json", "expected JSON"),
        ('{"alpha": 0.3, "weight": 0.5}', "expected JSON"),
        ('{"kind": "gaussian", "alpha": 0.3, "weight": 0.5}', "unknown lobe kind 'gaussian'"),
        ('{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 1.5}', "weight in [0, 1]"),
        ('{"kind": "cosine+ggx_vndf", "alpha": -1, "weight": 0.5}', "must be finite and > 0"),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "alpha_y": 0, "weight": 0.5}',
            "alpha_y must be finite and > 0",
        ),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5, "retro": "yes"}',
            "retro must be true or false",
        ),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "alpha_x": "a", "weight": 0.5}',
            "expected JSON",
        ),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5, '
            '"table": {"cos_theta": [0.5]}}',
            "table must hold lists",
        ),
        ('{"kind": "cosine+ggx_vndf", "alpha": ' + "9" * 400 + ', "weight": 0.5}', "expected JSON"),
        ('{"kind": "cosine+ggx_vndf", "alpha": Infinity, "weight": 0.5}', "must be finite"),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5, "distribution": "phong"}',
            "unknown distribution 'phong'",
        ),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5, "table": {"cos_theta": '
            '{"0.1": 1, "0.9": 2}, "alpha_x": [0.1, 0.2], "alpha_y": [0.1, 0.2], '
            '"weight": [0.5, 0.5]}}',
            "table must hold lists",
        ),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5, "table": {"cos_theta": '
            '[0.1, 0.9], "alpha_x": [0.1, 0.2], "alpha_y": [0.1, 0.2], "weight": [true, 0.5]}}',
            "table must hold lists",
        ),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5, "table": {"cos_theta": '
            '[0.9, 0.5], "alpha_x": [0.1, 0.2], "alpha_y": [0.1, 0.2], "weight": [0.5, 0.5]}}',
            "cos_theta ascending",
        ),
        (
            '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 0.5, "table": {"cos_theta": '
            '[0.5, 0.9], "alpha_x": [0.1, 0.2], "alpha_y": [0.1], "weight": [0.5, 0.5]}}',
            "equal length",
        ),
    ],
)
def test_bad_metadata_is_a_one_line_input_error(text, words):
    with pytest.raises(InputError) as e:
        lobe_format.from_metadata({lobe_format.KEY: text})
    msg = str(e.value)
    assert lobe_format.KEY in msg and words in msg and "\n" not in msg
