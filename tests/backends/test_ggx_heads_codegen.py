"""Code generation of a textured file with analytic GGX heads (``texture.analytic_heads:
ggx``, docs/model.md "Analytic GGX heads"): the C, WGSL and WebGL2 back ends evaluate it
as onnxruntime does.

What is new to the back ends: the field's table has two latent columns (the lobes' s, then
the heads' alpha column t), and the heads' closed form (GGX D, Smith's masking, Schlick's
factor) is Sqrt, Div, Mul and Add on wi, wo and alpha(uv), beside the shared network.  The
model is random (no training), its alpha spanning [0.01, 1] so that sharp and broad
heads are both evaluated.  The rows and the checks are test_textured_codegen's: random
and special uv (texel centres, edges, integers, hostile values), test_codegen's (wi, wo)
rows, and the same code with the table's rows reversed must fail the tolerance (the data
are read).
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

from neural_brdf import backends
from neural_brdf.fileformat import lobe as lobe_format

R, K = 12, 2  # R: test_textured_codegen's uv rows are built for its R = 12
WIDTH = 3 * (K + 2) + 2  # per-channel weights of K lobes and two heads, s and t


@pytest.fixture(scope="module")
def with_heads(tmp_path_factory):
    """(path of the model, its field table [R * R, WIDTH] as the ONNX initializer holds it)."""
    import torch

    from neural_brdf import config as cfgmod
    from neural_brdf import export, fileformat
    from neural_brdf.train.ggx_heads import GGXLobes
    from neural_brdf.train.model import RawBRDF
    from neural_brdf.train.textured_model import (
        TexturedBRDF,
        WeightField,
        exportable,
        normalized_textured,
    )

    torch.manual_seed(6)
    net = RawBRDF("isotropic", [16], "relu", grid_size=8, heads=K, latent=1, colors=1)
    with torch.no_grad():
        torch.nn.init.normal_(net.mlp.head.weight, std=0.3)
        net.mlp.body[0].weight[:, -1].normal_(0.0, 2.0)
        net.grid.table.normal_(0.0, 0.5)
    field = WeightField(R, K + 2, channels=3, init_std=2.0, latent=2)
    with torch.no_grad():
        field.logits[..., K : K + 2] += 2.0  # the heads carry much of the weight
        field.latent_logits.normal_(0.0, 3.0)
    norm = cfgmod.Normalization(table_size=17, samples=1024)
    model, _ = normalized_textured(
        TexturedBRDF([GGXLobes(net.eval())], field).eval(), norm, seed=1, bound="texel"
    )
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=fileformat.SIGNATURES[1])
    proto = onnx.load_from_string(payload)
    onnx.helper.set_model_props(proto, {lobe_format.KEY: lobe_format.to_json(LOBE)})
    path = tmp_path_factory.mktemp("ggx_heads") / "model.onnx"
    path.write_bytes(proto.SerializeToString())
    (table,) = [
        onnx.numpy_helper.to_array(t)
        for t in proto.graph.initializer
        if list(t.dims) == [R * R, WIDTH]
    ]
    return path, table


@pytest.fixture(scope="module")
def reference(with_heads):
    wi, wo, uv = rows()
    ref = onnx_ref(with_heads[0], wi, wo, uv)
    assert (ref != 0).sum() > 1000
    return wi, wo, uv, ref


def test_the_texture_is_the_field_with_both_latent_columns(with_heads):
    path, table = with_heads
    (tex,) = backends.textures(path)
    np.testing.assert_array_equal(np.asarray(tex).reshape(table.shape), table)
    t = table[:, -1]  # alpha's column
    assert t.min() >= 0.0 and t.max() <= 1.0 and t.max() - t.min() > 0.5


def test_c_matches_onnxruntime(with_heads, reference, tmp_path):
    path, table = with_heads
    wi, wo, uv, ref = reference
    got, wrong = c_eval(path, tmp_path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, C_TOL)


def test_wgsl_matches_onnxruntime(with_heads, reference, wgpu_device):
    path, table = with_heads
    wi, wo, uv, ref = reference
    source = backends.generate(path, "wgsl")
    got, wrong = wgsl_eval(wgpu_device, source, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)


def test_glsl_in_webgl2_matches_onnxruntime(with_heads, reference):
    path, table = with_heads
    wi, wo, uv, ref = reference
    got, wrong = webgl_eval(path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)
