"""neural_brdf.lobe: the sampling-lobe fit (no renderer needed) and its metadata format.

* On analytic models with a known best proposal: a Lambertian is sampled exactly by the
  cosine lobe (weight 0, relative second moment 1), and a GGX reflector with F = 1 by
  the GGX visible-normal lobe of about its own roughness;
* the metadata round-trips, and malformed or unknown entries fail with a one-line
  InputError naming the key.

That the exporter stores the lobe and the Mitsuba plugin samples with the stored values
is tested in tests/test_mitsuba_plugin.py.
"""

from __future__ import annotations

import math

import pytest

import analytic
from neural_brdf import lobe
from neural_brdf.config import InputError


def fitted(name, **params):
    return lobe.fit(analytic.create(name, **params).eval)


def test_lambertian_is_sampled_by_the_cosine_lobe_alone():
    got = fitted("lambertian", albedo=0.7)
    assert got["kind"] == lobe.KIND
    assert got["weight"] == 0.0, got
    # f cos / p_cos is the albedo itself: no variance, up to the estimate of the albedo
    assert abs(got["second_moment"] - 1.0) < 0.02, got
    assert got["second_moment"] == got["second_moment_cosine"]


@pytest.mark.parametrize("alpha", [0.05, 0.3])
def test_ggx_is_sampled_by_a_ggx_lobe_of_its_roughness(alpha):
    got = fitted("microfacet", distribution="ggx", alpha=alpha, fresnel="none")
    assert got["weight"] == lobe.MAX_WEIGHT, got
    # within about one step of the alpha grid (a factor 1.21)
    assert abs(math.log(got["alpha"] / alpha)) <= math.log(1.3), got
    assert got["second_moment"] < 0.5 * got["second_moment_cosine"], got


def test_fit_is_deterministic():
    brdf = analytic.create("phong")
    assert lobe.fit(brdf.eval) == lobe.fit(brdf.eval)


def test_metadata_round_trip():
    got = fitted("blinn_phong")
    assert lobe.from_metadata({lobe.KEY: lobe.to_json(got)}) == got
    assert lobe.from_metadata({"other": "1"}) is None
    # a stored alpha below the floor is raised to it
    sharp = lobe.parse(lobe.to_json({**got, "alpha": 1e-4}))
    assert sharp["alpha"] == lobe.MIN_ALPHA


@pytest.mark.parametrize(
    "text, words",
    [
        ("not json", "expected JSON"),
        ('{"alpha": 0.3, "weight": 0.5}', "expected JSON"),
        ('{"kind": "gaussian", "alpha": 0.3, "weight": 0.5}', "unknown lobe kind 'gaussian'"),
        ('{"kind": "cosine+ggx_vndf", "alpha": 0.3, "weight": 1.5}', "weight in [0, 1]"),
        ('{"kind": "cosine+ggx_vndf", "alpha": -1, "weight": 0.5}', "alpha must be > 0"),
    ],
)
def test_bad_metadata_is_a_one_line_input_error(text, words):
    with pytest.raises(InputError) as e:
        lobe.from_metadata({lobe.KEY: text})
    msg = str(e.value)
    assert lobe.KEY in msg and words in msg and "\n" not in msg
