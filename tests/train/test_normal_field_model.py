"""The normal field of a textured file (docs/model.md, "The normal field"): the torch
module, its export as the graph's second output, and its lowering on its own.

The references are independent of the code under test: a numpy bilinear look-up written
here from the convention (texel centres at ((i + 0.5) / Ru, (j + 0.5) / Rv), repeat),
Mitsuba's own ``bitmap`` texture, and onnxruntime on the exported file.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch

from neural_brdf import config as cfgmod
from neural_brdf import export, fileformat, graph
from neural_brdf.train.model import RawBRDF
from neural_brdf.train.textured_model import NormalField, TexturedBRDF, WeightField, exportable

RU, RV = 7, 5


def texels(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = rng.normal(0.0, 0.2, (RV, RU, 3))
    t[..., 2] = 1.0 + rng.uniform(-0.2, 0.2, (RV, RU))  # unnormalised, as 2 t - 1 may be
    return t.astype(np.float32)


def numpy_normal(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """normalize(bilinear(tex, uv)), repeat, from the convention alone."""
    rv, ru = tex.shape[:2]
    x = (uv[:, 0] - np.floor(uv[:, 0])) * ru - 0.5
    y = (uv[:, 1] - np.floor(uv[:, 1])) * rv - 0.5
    i0, j0 = np.floor(x), np.floor(y)
    a, b = (x - i0)[:, None], (y - j0)[:, None]
    i0, j0 = i0.astype(int) % ru, j0.astype(int) % rv
    i1, j1 = (i0 + 1) % ru, (j0 + 1) % rv
    v = (
        tex[j0, i0] * (1 - a) * (1 - b)
        + tex[j0, i1] * a * (1 - b)
        + tex[j1, i0] * (1 - a) * b
        + tex[j1, i1] * a * b
    )
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_the_lookup_is_bilinear_then_normalised_on_a_rectangular_table():
    tex = texels()
    uv = np.random.default_rng(1).uniform(-2.0, 3.0, (3000, 2))
    with torch.no_grad():
        got = NormalField(tex)(torch.from_numpy(uv).float()).numpy()
    np.testing.assert_allclose(got, numpy_normal(tex.astype(np.float64), uv), atol=2e-6)


@pytest.mark.mitsuba
def test_the_lookup_matches_mitsubas_bitmap_then_normalize():
    """Mitsuba's normalmap evaluates its bitmap (bilinear, repeat) then normalises."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    tex = texels(2)
    bitmap = mi.load_dict(
        {
            "type": "bitmap",
            "bitmap": mi.Bitmap(np.ascontiguousarray((tex + 1.0) / 2.0)),
            "raw": True,
            "filter_type": "bilinear",
            "wrap_mode": "repeat",
        }
    )
    uv = np.random.default_rng(3).uniform(-2.0, 3.0, (3000, 2)).astype(np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, len(uv))
    si.uv = mi.Point2f(np.ascontiguousarray(uv.T))
    ref = 2.0 * np.array(bitmap.eval(si), np.float64).T - 1.0
    ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
    with torch.no_grad():
        got = NormalField(tex)(torch.from_numpy(uv)).numpy()
    assert np.abs(got - ref).max() < 2e-5


@pytest.fixture(scope="module")
def payload():
    torch.manual_seed(0)
    recipe = cfgmod.Model(hidden=[8], grid=cfgmod.Grid(size=4))
    lobes = [RawBRDF.from_config(recipe, init_value=v) for v in (0.2, 0.5)]
    model = TexturedBRDF(lobes, WeightField(4, 2, init_std=2.0), NormalField(texels(4))).eval()
    return (
        export.to_onnx_bytes(
            exportable(model),
            17,
            inputs=fileformat.SIGNATURES[1],
            outputs=fileformat.OUTPUT_SIGNATURES[1],
        ),
        model,
    )


def test_the_graph_outputs_f_and_n_and_n_depends_on_uv_alone(payload):
    data, model = payload
    session = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(5)
    uv = rng.uniform(-1.0, 2.0, (500, 2)).astype(np.float32)
    uv[:3] = [[np.nan, 0.1], [0.2, np.inf], [-np.inf, 0.5]]
    a = rng.normal(size=(500, 3)).astype(np.float32)
    b = rng.normal(size=(500, 3)).astype(np.float32)
    n1 = session.run(["n"], {"wi": a, "wo": b, "uv": uv})[0]
    n2 = session.run(["n"], {"wi": b * 0, "wo": a * 7, "uv": uv})[0]
    np.testing.assert_array_equal(n1, n2)  # the directions do not matter
    np.testing.assert_array_equal(n1[:3], [[0, 0, 1]] * 3)  # invalid uv: unperturbed
    np.testing.assert_allclose(
        n1[3:], numpy_normal(texels(4).astype(np.float64), uv[3:]), atol=3e-6
    )
    # f is the model's, unchanged by carrying n
    f = session.run(["f"], {"wi": a, "wo": b, "uv": uv})[0]
    with torch.no_grad():
        ref = exportable(model)(*(torch.from_numpy(x) for x in (a, b, uv)))[0].numpy()
    np.testing.assert_allclose(f, ref, rtol=1e-4, atol=1e-6)


def test_each_output_lowers_alone(payload):
    data, _ = payload
    n_prog = graph.lower(data, ("n",))
    assert list(n_prog.inputs) == ["uv"] and list(n_prog.outputs) == ["n"]
    f_prog = graph.lower(data, ("f",))
    assert list(f_prog.inputs) == ["wi", "wo", "uv"] and list(f_prog.outputs) == ["f"]
    both = graph.lower(data)
    assert list(both.outputs) == ["f", "n"]
    assert len(n_prog.instrs) < len(f_prog.instrs) < len(both.instrs) + 1
    with pytest.raises(graph.UnsupportedOnnxOp, match="'m'"):
        graph.lower(data, ("m",))


def test_the_normal_table_is_refused_in_the_wrong_shape():
    with pytest.raises(ValueError, match="texels"):
        NormalField(np.zeros((4, 4), np.float32))
