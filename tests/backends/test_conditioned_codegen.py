"""Code generation of a textured file with conditioned lobes (``texture.latent: 1``,
docs/model.md "Conditioned lobes"): the C, WGSL and WebGL2 back ends evaluate it as
onnxruntime does.

What is new to the back ends: the weight field's table has one more column (the latent
s), sliced off after the look-up; s enters the network (a Concat); each head is
normalised by a table over (s, theta) (a Gather at an index computed from s and wi or
wo), which stays a literal: an index computed from a texture's value is not a texture.
The model is random (no training), deliberately bright so that the (s, theta) table is
in the graph, not the identity.  The
rows and the checks are test_textured_codegen's: random and special uv (texel centres,
edges, integers, hostile values), test_codegen's (wi, wo) rows, and the same code with
the table's rows reversed must fail the tolerance (the data are read).
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


@pytest.fixture(scope="module")
def conditioned(tmp_path_factory):
    """(path of the model, its field table [R * R, K + 1] as the ONNX initializer holds it)."""
    import torch

    from neural_brdf import config as cfgmod
    from neural_brdf import export, fileformat
    from neural_brdf.train.conditioned import ConditionedNormalizedBRDF
    from neural_brdf.train.model import RawBRDF
    from neural_brdf.train.textured_model import (
        TexturedBRDF,
        WeightField,
        exportable,
        normalized_textured,
    )

    torch.manual_seed(5)
    net = RawBRDF("isotropic", [16], "relu", grid_size=8, heads=K, latent=1)
    with torch.no_grad():
        torch.nn.init.normal_(net.mlp.head.weight, std=0.3)
        net.mlp.head.bias.fill_(2.5)  # bright: raw albedo above 1, the table in the graph
        net.mlp.body[0].weight[:, -1].normal_(0.0, 2.0)
        net.grid.table.normal_(0.0, 0.5)
    field = WeightField(R, K, init_std=2.0, latent=1)
    with torch.no_grad():
        field.latent_logits.normal_(0.0, 2.0)
    norm = cfgmod.Normalization(table_size=17, grid_size=5, samples=1024)
    model, _ = normalized_textured(TexturedBRDF([net.eval()], field).eval(), norm, seed=1)
    assert isinstance(model.lobes[0], ConditionedNormalizedBRDF) and not model.lobes[0].identity
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=fileformat.SIGNATURES[1])
    proto = onnx.load_from_string(payload)
    onnx.helper.set_model_props(proto, {lobe_format.KEY: lobe_format.to_json(LOBE)})
    path = tmp_path_factory.mktemp("conditioned") / "model.onnx"
    path.write_bytes(proto.SerializeToString())
    (table,) = [
        onnx.numpy_helper.to_array(t)
        for t in proto.graph.initializer
        if list(t.dims) == [R * R, K + 1]
    ]
    return path, table


@pytest.fixture(scope="module")
def reference(conditioned):
    wi, wo, uv = rows()
    ref = onnx_ref(conditioned[0], wi, wo, uv)
    assert (ref != 0).sum() > 1000
    return wi, wo, uv, ref


def test_the_texture_is_the_field_with_its_latent_column(conditioned):
    path, table = conditioned
    (tex,) = backends.textures(path)
    np.testing.assert_array_equal(np.asarray(tex).reshape(table.shape), table)
    s = table[:, K]
    assert s.min() >= 0.0 and s.max() <= 1.0 and s.max() - s.min() > 0.3


def test_c_matches_onnxruntime(conditioned, reference, tmp_path):
    path, table = conditioned
    wi, wo, uv, ref = reference
    got, wrong = c_eval(path, tmp_path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, C_TOL)


def test_wgsl_matches_onnxruntime(conditioned, reference, wgpu_device):
    path, table = conditioned
    wi, wo, uv, ref = reference
    source = backends.generate(path, "wgsl")
    got, wrong = wgsl_eval(wgpu_device, source, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)


def test_glsl_in_webgl2_matches_onnxruntime(conditioned, reference):
    path, table = conditioned
    wi, wo, uv, ref = reference
    got, wrong = webgl_eval(path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)
