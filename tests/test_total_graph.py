"""The exported graph is total: every input row gives a finite answer, alone.

* directions are normalised inside the graph: f(k wi, wo) == f(wi, wo) for k > 0;
* a row with a NaN, an infinity or a zero-length direction gives exactly 0, never NaN and
  never an exception, and leaves every other row of the batch as it was;
* a batch of 0 rows works;
* exact reciprocity survives, bit for bit.

Checked on onnxruntime directly, through ``neural_brdf.load(...).eval`` and through the
Mitsuba plugin's Dr.Jit evaluation of the same file; tests/fileformat/test_portable.py
checks the same rows (the batch of 0 rows included) in onnxruntime 1.18.1,
onnxruntime-web, onnx2torch and the ONNX reference evaluator.  The models are networks with random
weights (bright, so that the albedo table is active and its Gather runs): the graph's
plumbing is under test, not a fit.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch

import neural_brdf
from analytic import physics
from neural_brdf import encodings, export
from neural_brdf.train.model import NormalizedBRDF, RawBRDF, TotalBRDF, albedo_table

ENCODINGS = encodings.names(reciprocal=True)
HOSTILE = {
    "nan": [np.nan, 0.2, 0.9],
    "inf": [np.inf, 0.0, 1.0],
    "-inf": [0.1, -np.inf, 0.5],
    "inf_z": [0.0, 0.0, np.inf],
    "zero": [0.0, 0.0, 0.0],
    "all_nan": [np.nan, np.nan, np.nan],
}
N = 100_000  # "a large batch": the bad rows sit in its middle
SCALE_TOL = 1e-5  # the issue's bound for f(k wi, wo) vs f(wi, wo)


def _model(encoding: str) -> TotalBRDF:
    torch.manual_seed(3)
    raw = RawBRDF(encoding, [16, 16], "silu", init_value=3.0)
    with torch.no_grad():
        for p in raw.mlp.body.parameters():
            p.mul_(3.0)
    aniso = encodings.get(encoding).anisotropic
    table, _, _ = albedo_table(
        raw,
        size=9 if aniso else 16,
        anisotropic=aniso,
        samples=256,
        seed=0,
        sigmas=3.0,
        margin=1e-3,
    )
    assert float(table.max()) > 1.0  # the normalisation really divides
    return TotalBRDF(NormalizedBRDF(raw, table).eval())


@pytest.fixture(scope="module", params=ENCODINGS)
def model_file(request, tmp_path_factory):
    path = tmp_path_factory.mktemp(request.param) / "model.onnx"
    path.write_bytes(export.to_onnx_bytes(_model(request.param), 17))
    return path


@pytest.fixture(scope="module")
def session(model_file):
    return ort.InferenceSession(str(model_file), providers=["CPUExecutionProvider"])


def _run(session, wi, wo):
    return session.run(["f"], {"wi": np.asarray(wi, np.float32), "wo": np.asarray(wo, np.float32)})[
        0
    ]


def _pairs(n, seed=0):
    return (
        physics.random_directions(n, seed).astype(np.float32),
        physics.random_directions(n, seed + 100).astype(np.float32),
    )


@pytest.mark.parametrize("side", ["wi", "wo", "both"])
@pytest.mark.parametrize("kind", sorted(HOSTILE))
def test_hostile_row_in_a_large_batch_gives_zero_and_leaves_the_rest(session, kind, side):
    wi, wo = _pairs(N)
    clean = _run(session, wi, wo)
    assert np.isfinite(clean).all() and (clean > 0).mean() > 0.9
    rows = [1, N // 2, N - 2]
    if side in ("wi", "both"):
        wi[rows] = HOSTILE[kind]
    if side in ("wo", "both"):
        wo[rows] = HOSTILE[kind]
    got = _run(session, wi, wo)
    assert np.array_equal(got[rows], np.zeros((3, 3), np.float32))
    keep = np.ones(N, bool)
    keep[rows] = False
    assert np.array_equal(got[keep], clean[keep])  # bit for bit


def test_batch_of_zero_rows(session, model_file):
    empty = np.zeros((0, 3), np.float32)
    assert _run(session, empty, empty).shape == (0, 3)
    assert neural_brdf.load(model_file).eval(empty, empty).shape == (0, 3)


@pytest.mark.parametrize("k", [1e-30, 1e-3, 0.37, 2.5, 1e3, 1e30])
def test_unnormalised_directions_are_normalised_in_the_graph(session, k):
    wi, wo = _pairs(4096, seed=1)
    ref = _run(session, wi, wo)
    for a, b in [(k * wi, wo), (wi, k * wo), (k * wi, 0.5 * k * wo)]:
        got = _run(session, a, b)
        err = export.relative_difference(got.astype(np.float64), ref.astype(np.float64))
        assert err <= SCALE_TOL, (k, err)


def test_below_horizon_still_zero_and_values_finite_everywhere(session):
    rng = np.random.default_rng(5)
    wi = rng.normal(size=(20_000, 3)).astype(np.float32)
    wo = rng.normal(size=(20_000, 3)).astype(np.float32)
    got = _run(session, wi, wo)
    assert np.isfinite(got).all() and (got >= 0).all()
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    assert below.any() and not got[below].any()
    assert got[~below].all()


def test_reciprocity_is_bit_exact_after_the_change(session):
    wi, wo = _pairs(50_000, seed=2)
    rng = np.random.default_rng(2)
    wi *= rng.uniform(0.1, 10.0, size=(len(wi), 1)).astype(np.float32)  # unnormalised too
    assert np.array_equal(_run(session, wi, wo), _run(session, wo, wi))


def test_runtime_eval_handles_every_hostile_row(model_file):
    brdf = neural_brdf.load(model_file)
    wi, wo = _pairs(len(HOSTILE) + 2, seed=4)
    for i, v in enumerate(HOSTILE.values()):
        wi[i] = v
    got = brdf.eval(wi, wo)
    assert np.array_equal(got[: len(HOSTILE)], np.zeros((len(HOSTILE), 3), np.float32))
    assert np.isfinite(got).all() and got[len(HOSTILE) :].all()


@pytest.mark.parametrize("k", [1e-50, 1e-40, 1e40, 1e300])
def test_runtime_eval_keeps_a_float64_direction_float32_cannot_hold(model_file, k):
    # finite, non-zero directions beyond float32's range: f is the direction's (the
    # graph's first step, the scale by the largest component, done before the rounding);
    # they gave f = 0 (the zero vector, or infinity)
    brdf = neural_brdf.load(model_file)
    wi, wo = (x.astype(np.float64) for x in _pairs(256, seed=6))
    ref = brdf.eval(wi, wo)
    assert ref.any()
    for a, b in [(k * wi, wo), (wi, k * wo), (k * wi, k * wo)]:
        got = brdf.eval(a, b)
        err = export.relative_difference(got.astype(np.float64), ref.astype(np.float64))
        assert err <= SCALE_TOL, (k, err)
    assert np.array_equal(brdf.eval(wi, wo), brdf.eval(wi.astype(np.float32), wo))  # as before


@pytest.mark.parametrize(
    "wi, kwargs, named",
    [
        ("abc", {}, "wi: expected real numbers"),
        ([[0, 0, 1], [0, 1]], {}, "wi: expected an array of shape (..., 3)"),
        ([0j, 0, 1], {}, "wi: expected real numbers"),
        ([0, 1], {}, "wi: expected shape (..., 3), got (2,)"),
        ([0, 0, 1], {"threads": "2"}, "threads: expected a whole number from 1 to 1024, got '2'"),
        ([0, 0, 1], {"threads": 2.5}, "threads: expected a whole number from 1 to 1024, got 2.5"),
        ([0, 0, 1], {"threads": 0}, "threads: expected a whole number from 1 to 1024, got 0"),
        ([0, 0, 1], {"threads": 2**40}, "threads: expected a whole number from 1 to 1024, got"),
    ],
)
def test_runtime_names_the_bad_argument_in_one_line(model_file, wi, kwargs, named):
    from neural_brdf.errors import InputError

    with pytest.raises(InputError) as e:
        neural_brdf.load(model_file, **kwargs).eval(wi, [0.0, 0.0, 1.0])
    assert str(e.value).startswith(named) and "\n" not in str(e.value)


@pytest.mark.mitsuba
def test_drjit_plugin_evaluation_is_total_too(model_file, session):
    """The Mitsuba plugin runs the same graph through Dr.Jit: same zeros, same values."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from neural_brdf.renderers.mitsuba import read_model

    _, program, _ = read_model(model_file)
    wi, wo = _pairs(4096, seed=6)
    wi[10] = HOSTILE["nan"]
    wo[20] = HOSTILE["zero"]
    wi[30] = HOSTILE["inf"]
    wi[40:50] *= 7.5
    cols = program(
        wi=[mi.Float(wi[:, j]) for j in range(3)], wo=[mi.Float(wo[:, j]) for j in range(3)]
    )["f"]
    got = np.stack([np.asarray(dr.detach(c)) for c in cols], -1)
    ref = _run(session, wi, wo)
    assert np.array_equal(got[[10, 20, 30]], np.zeros((3, 3), np.float32))
    assert export.relative_difference(got.astype(np.float64), ref.astype(np.float64)) <= 1e-5
