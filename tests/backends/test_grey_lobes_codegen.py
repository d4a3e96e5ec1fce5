"""Code generation and the Dr.Jit plugin on a textured file with grey lobes
(``texture.lobe_color: grey``, docs/model.md "Grey lobes"): the C, WGSL and WebGL2 back
ends and the Mitsuba plugin evaluate it as onnxruntime does.

What is new to the back ends: the network's last layer has one output per lobe, and a
Gather at constant indices repeats each to the lobe's three RGB columns before the
per-channel weights colour them.  The model is random (no training), its field's rgb
weights and latent drawn wide so that the three channels differ; the texels' bound
(``lobe_bound: texel``) leaves no table in the graph, as the benchmark's recipe does.
The rows and the checks are test_textured_codegen's: random and special uv, test_codegen's
(wi, wo) rows, and the same code with the field's rows reversed must fail the tolerance.
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from test_codegen import C_TOL, GPU_TOL
from test_textured_codegen import (
    LOBE,
    c_eval,
    check_parity,
    onnx_ref,
    rows,
    webgl_eval,
    wgsl_eval,
)

from neural_brdf import export
from neural_brdf.fileformat import lobe as lobe_format

R, K = 12, 3  # R: test_textured_codegen's uv rows are built for its R = 12


@pytest.fixture(scope="module")
def grey(tmp_path_factory):
    """(path of the model, its field table [R * R, 3 K + 1] as the ONNX initializer holds it)."""
    import torch

    from neural_brdf import config as cfgmod
    from neural_brdf import fileformat
    from neural_brdf.train.model import RawBRDF
    from neural_brdf.train.textured_model import (
        TexturedBRDF,
        WeightField,
        exportable,
        normalized_textured,
    )

    torch.manual_seed(11)
    net = RawBRDF("isotropic", [16], "relu", grid_size=8, heads=K, latent=1, colors=1)
    assert net.mlp.head.weight.shape[0] == K  # one output per lobe
    with torch.no_grad():
        torch.nn.init.normal_(net.mlp.head.weight, std=0.3)
        net.mlp.head.bias.normal_(0.0, 1.0)
        net.grid.table.normal_(0.0, 0.5)
    field = WeightField(R, K, channels=3, init_std=2.0, latent=1)
    with torch.no_grad():
        field.latent_logits.normal_(0.0, 2.0)
    norm = cfgmod.Normalization(table_size=17, grid_size=5, samples=1024)
    model, _ = normalized_textured(
        TexturedBRDF([net.eval()], field).eval(), norm, seed=1, bound="texel"
    )
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=fileformat.SIGNATURES[1])
    proto = onnx.load_from_string(payload)
    onnx.helper.set_model_props(proto, {lobe_format.KEY: lobe_format.to_json(LOBE)})
    path = tmp_path_factory.mktemp("grey") / "model.onnx"
    path.write_bytes(proto.SerializeToString())
    (table,) = [
        onnx.numpy_helper.to_array(t)
        for t in proto.graph.initializer
        if list(t.dims) == [R * R, 3 * K + 1]
    ]
    return path, table


@pytest.fixture(scope="module")
def reference(grey):
    wi, wo, uv = rows()
    ref = onnx_ref(grey[0], wi, wo, uv)
    up = ref.sum(1) > 0
    assert up.sum() > 1000
    # coloured: the channels' ratios vary over uv (grey lobes, rgb weights)
    ratio = ref[up, 0] / np.maximum(ref[up, 2], 1e-12)
    assert np.ptp(ratio) > 0.5
    return wi, wo, uv, ref


def test_the_last_layer_has_one_output_per_lobe(grey):
    path, _ = grey
    proto = onnx.load(str(path))
    heads = [
        t for t in proto.graph.initializer if t.name.endswith("mlp.head.weight")
    ]  # the network's last layer: K rows, not 3 K
    assert [list(t.dims) for t in heads] == [[K, 16]]


def test_c_matches_onnxruntime(grey, reference, tmp_path):
    path, table = grey
    wi, wo, uv, ref = reference
    got, wrong = c_eval(path, tmp_path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, C_TOL)


def test_wgsl_matches_onnxruntime(grey, reference, wgpu_device):
    path, table = grey
    wi, wo, uv, ref = reference
    from neural_brdf import backends

    source = backends.generate(path, "wgsl")
    got, wrong = wgsl_eval(wgpu_device, source, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)


def test_glsl_in_webgl2_matches_onnxruntime(grey, reference):
    path, table = grey
    wi, wo, uv, ref = reference
    got, wrong = webgl_eval(path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)


@pytest.mark.mitsuba
def test_the_mitsuba_plugin_matches_onnxruntime(grey, reference):
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    import neural_brdf.renderers.mitsuba  # noqa: F401  (registers the plugins)

    path, _ = grey
    wi, wo, uv, ref = reference
    # the rows above the horizon with finite inputs (the hostile rows are the codegen's)
    keep = np.isfinite(np.c_[wi, wo, uv]).all(1) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
    wi, wo, uv, ref = wi[keep], wo[keep], uv[keep], ref[keep]
    assert len(wi) > 1000
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(path)})
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(np.ascontiguousarray(wi.T, np.float32))
    si.uv = mi.Point2f(np.ascontiguousarray(uv.T, np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    got = np.asarray(
        bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(np.ascontiguousarray(wo.T, np.float32))),
        np.float64,
    ).T
    # float32 on both sides (test_textured_plugin's tolerance)
    err = export.relative_difference(got, ref * wo[:, 2:3])
    assert err < 2e-5, err
