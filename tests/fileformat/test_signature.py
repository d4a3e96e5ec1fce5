"""The graph's signature and the names only fileformat spells (issue 28).

* a reader accepts a graph with inputs (wi, wo) or (wi, wo, uv), in that order, each
  float32 [N, width], and the one output f [N, 3]; it refuses any other with one line;
* the portable rewrite and the opset conversion live beside the file format and need
  onnx and numpy only;
* the ``sampling_lobe`` key is spelled in fileformat/ alone.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

import neural_brdf
from cli_helpers import assert_one_line_error, cli
from neural_brdf import export, fileformat
from neural_brdf.errors import InputError
from neural_brdf.fileformat import portable, reader
from neural_brdf.train.model import RawBRDF

PACKAGE = Path(neural_brdf.__file__).parent


def _graph(inputs: list[tuple[str, list]], outputs=(("f", ["N", 3]),), dtype=TensorProto.FLOAT):
    """A graph whose output is the first input's first three columns (or the first input)."""
    ins = [helper.make_tensor_value_info(n, dtype, shape) for n, shape in inputs]
    outs = [helper.make_tensor_value_info(n, dtype, shape) for n, shape in outputs]
    nodes = [helper.make_node("Identity", [inputs[0][0]], [outputs[0][0]])]
    return helper.make_model(helper.make_graph(nodes, "g", ins, outs))


def test_an_exported_graph_has_the_two_inputs():
    raw = RawBRDF("isotropic", [8], "silu", init_value=0.2).eval()
    proto = onnx.load_from_string(export.to_onnx_bytes(raw, 17))
    assert reader.signature(proto) == fileformat.INPUTS == ("wi", "wo")


def test_the_optional_third_input_is_uv():
    assert fileformat.UV == "uv" and fileformat.OPTIONAL_INPUTS == ("uv",)
    assert fileformat.SIGNATURES == (("wi", "wo"), ("wi", "wo", "uv"))
    proto = _graph([("wi", ["N", 3]), ("wo", ["N", 3]), ("uv", ["N", 2])])
    assert reader.signature(proto) == ("wi", "wo", "uv")
    no_shape = _graph([("wi", None), ("wo", None), ("uv", None)], outputs=(("f", None),))
    assert reader.signature(no_shape) == ("wi", "wo", "uv")


@pytest.mark.parametrize(
    "inputs, outputs, needle",
    [
        ([("wi", ["N", 3])], (("f", ["N", 3]),), "expected inputs"),
        ([("wo", ["N", 3]), ("wi", ["N", 3])], (("f", ["N", 3]),), "expected inputs"),
        ([("wi", ["N", 3]), ("wo", ["N", 3]), ("st", ["N", 2])], (("f", ["N", 3]),), "got"),
        ([("wi", ["N", 3]), ("wo", ["N", 3])], (("rgb", ["N", 3]),), "output 'f'"),
        ([("wi", ["N", 3]), ("wo", ["N", 3]), ("uv", ["N", 3])], (("f", ["N", 3]),), "'uv'"),
        ([("wi", ["N", 4]), ("wo", ["N", 3])], (("f", ["N", 3]),), "'wi': expected float32"),
        ([("wi", [3]), ("wo", ["N", 3])], (("f", ["N", 3]),), "[N, 3]"),
    ],
)
def test_any_other_signature_is_one_line(inputs, outputs, needle):
    with pytest.raises(InputError) as e:
        reader.signature(_graph(inputs, outputs), source="x.onnx")
    assert str(e.value).startswith("x.onnx: ") and needle in str(e.value)
    assert "\n" not in str(e.value) and len(str(e.value)) < 300


def test_a_double_input_is_refused():
    proto = _graph([("wi", ["N", 3]), ("wo", ["N", 3])], dtype=TensorProto.DOUBLE)
    with pytest.raises(InputError, match="float32"):
        reader.signature(proto)


def test_long_names_are_cut_in_the_message():
    proto = _graph([("w" * 5000, ["N", 3])])
    with pytest.raises(InputError) as e:
        reader.signature(proto)
    assert len(str(e.value)) < 300


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
    return names


def test_the_portable_rewrite_is_pure_onnx_beside_the_file_format():
    imported = _imports(Path(portable.__file__))
    outside = {m.split(".")[0] for m in imported} - {"__future__", "copy", "numpy", "onnx"}
    assert outside <= {"neural_brdf"}, outside
    assert {m for m in imported if m.startswith("neural_brdf")} <= {"neural_brdf.fileformat"}
    assert export.portable_graph is portable.portable_graph  # what export runs
    assert not hasattr(export, "convert_opset")  # one home


def test_the_lobe_key_is_spelled_in_fileformat_only():
    spelled = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "fileformat" in path.relative_to(PACKAGE).parts:
            continue
        for n in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(n, ast.Constant) and n.value == fileformat.LOBE_KEY:
                spelled.append(f"{path.relative_to(PACKAGE)}:{n.lineno}")
    assert spelled == []


UV3 = [("wi", ["N", 3]), ("wo", ["N", 3]), ("uv", ["N", 2])]


def test_a_textured_graph_may_carry_the_normal_field_as_its_second_output():
    assert fileformat.NORMAL == "n"
    assert fileformat.OUTPUT_SIGNATURES == (("f",), ("f", "n"))
    proto = _graph(UV3, outputs=(("f", ["N", 3]), ("n", ["N", 3])))
    assert reader.signature(proto) == ("wi", "wo", "uv")
    assert reader.outputs(proto) == ("f", "n")


@pytest.mark.parametrize(
    "inputs, outputs, needle",
    [
        # a normal field needs uv: a homogeneous graph has no surface position
        (UV3[:2], (("f", ["N", 3]), ("n", ["N", 3])), "and 'n' with uv"),
        (UV3, (("n", ["N", 3]), ("f", ["N", 3])), "got"),  # the order is the contract's
        (UV3, (("f", ["N", 3]), ("normal", ["N", 3])), "got"),
        (UV3, (("f", ["N", 3]), ("n", ["N", 3]), ("x", ["N", 1])), "got"),
        (UV3, (("f", ["N", 3]), ("n", ["N", 2])), "'n': expected float32 [N, 3]"),
    ],
)
def test_a_wrong_normal_output_is_one_line(inputs, outputs, needle):
    with pytest.raises(InputError) as e:
        reader.signature(_graph(inputs, outputs=outputs))
    assert needle in str(e.value) and "\n" not in str(e.value)


# The contract is checked on load, for every consumer (the walkthrough's files): an
# output f that is not [N, 3] RGB, a non-float32 input, a non-finite weight and metadata
# that cannot be decoded each give one line naming the file, never a traceback, a grey
# material or NAN literals.

CONSUMERS = {
    "validate": [],
    "bake": ["-o", "x.binary"],
    "view": ["-o", "x.html"],
    "render": ["-o", "x.png"],
    "codegen": ["--target", "c", "-o", "x.h"],
}
META = {
    "metadata_version": "2",
    "format_version": str(fileformat.FORMAT_VERSION),
    "producer": fileformat.PRODUCER_NAME,
    "frame": fileformat.FRAME,
    "units": fileformat.UNITS,
    "encoding": "isotropic",
}


def _exported(**props) -> onnx.ModelProto:
    """A freshly exported small model with neural-brdf's metadata (``props`` override)."""
    raw = RawBRDF("isotropic", [8], "silu", init_value=0.2).eval()
    proto = onnx.load_from_string(export.to_onnx_bytes(raw, 17))
    helper.set_model_props(proto, {**META, **props})
    return proto


def _channels(proto: onnx.ModelProto, width: int) -> onnx.ModelProto:
    """``proto`` with f cut to its first ``width`` channels (1) or padded with one (4)."""
    g = proto.graph
    for n in g.node:
        n.output[:] = ["f_rgb" if o == "f" else o for o in n.output]
    tensor = onnx.numpy_helper.from_array
    if width < 3:
        g.initializer.extend(
            [
                tensor(np.array(v, np.int64), n)
                for n, v in [("s0", [0]), ("s1", [width]), ("s2", [1])]
            ]
        )
        g.node.append(helper.make_node("Slice", ["f_rgb", "s0", "s1", "s2"], ["f"]))
    else:
        g.initializer.extend(
            [tensor(np.array(v, np.int64), n) for n, v in [("s0", [0]), ("s1", [1]), ("s2", [1])]]
        )
        g.node.append(helper.make_node("Slice", ["f_rgb", "s0", "s1", "s2"], ["f_a"]))
        g.node.append(helper.make_node("Concat", ["f_rgb", "f_a"], ["f"], axis=1))
    g.output[0].type.tensor_type.shape.dim[1].dim_value = width
    return proto


def _float64_inputs(proto: onnx.ModelProto) -> onnx.ModelProto:
    """``proto`` with inputs wi, wo declared float64, cast to float32 inside."""
    g = proto.graph
    for n in g.node:
        n.input[:] = [{"wi": "wi32", "wo": "wo32"}.get(i, i) for i in n.input]
    casts = [helper.make_node("Cast", [x], [x + "32"], to=TensorProto.FLOAT) for x in ("wi", "wo")]
    nodes = casts + list(g.node)
    del g.node[:]
    g.node.extend(nodes)
    for v in g.input:
        v.type.tensor_type.elem_type = TensorProto.DOUBLE
    return proto


def _nan_weight(proto: onnx.ModelProto) -> onnx.ModelProto:
    """``proto`` with one NaN in its first weight matrix."""
    t = next(t for t in proto.graph.initializer if t.data_type == TensorProto.FLOAT and t.dims)
    a = onnx.numpy_helper.to_array(t).copy()
    a.flat[0] = np.nan
    t.CopyFrom(onnx.numpy_helper.from_array(a, t.name))
    return proto


BAD_LOBE = '{"kind": "cosine+ggx_vndf", "alpha": 0.3, "alpha_x": -3, "weight": 0.8}'
BROKEN = {
    "red1": (lambda: _channels(_exported(), 1), ["'f'", "[N, 1]"], CONSUMERS),
    "rgba4": (lambda: _channels(_exported(), 4), ["'f'", "[N, 4]"], CONSUMERS),
    "float64": (lambda: _float64_inputs(_exported()), ["'wi'", "float64"], CONSUMERS),
    "nan_init": (lambda: _nan_weight(_exported()), ["initializer", "non-finite"], CONSUMERS),
    "tc_bad": (lambda: _exported(training_config="[1,2"), ["training_config"], CONSUMERS),
    "tc_tab": (lambda: _exported(training_config="a:\tb: c"), ["training_config"], CONSUMERS),
    "mvabc": (lambda: _exported(metadata_version="abc"), ["metadata_version", "'abc'"], CONSUMERS),
    "tc_list": (
        lambda: _exported(training_config="[1, 2]"),
        ["training_config", "mapping"],
        CONSUMERS,
    ),
    # the sampling lobe: codegen's samplers, the Mitsuba plugin's, a renderer's
    "lobe_neg": (lambda: _exported(sampling_lobe=BAD_LOBE), ["'sampling_lobe'", "> 0"], CONSUMERS),
}
CASES = [
    (name, command)
    for name, (_, _, commands) in BROKEN.items()
    for command in commands
    # codegen reads no training_config and no metadata_version: the graph alone
    if not (command == "codegen" and name in ("tc_bad", "tc_tab", "tc_list", "mvabc"))
]


@pytest.mark.parametrize("name, command", CASES)
def test_a_file_breaking_the_contract_is_one_line_for_every_consumer(
    name, command, tmp_path, capsys, monkeypatch
):
    make, needles, _ = BROKEN[name]
    if command == "codegen" and name in ("red1", "rgba4"):  # the back end's own words
        needles = [f"{{'f': {1 if name == 'red1' else 4}}}"]
    path = tmp_path / f"{name}.onnx"
    path.write_bytes(make().SerializeToString())
    monkeypatch.chdir(tmp_path)
    code, _, err = cli(capsys, command, str(path), *CONSUMERS[command])
    assert_one_line_error(code, err, str(path), *needles)


def test_the_lowering_refuses_a_nan_weight_given_as_a_proto():
    from neural_brdf import graph

    with pytest.raises(InputError, match="'mlp.body.0.weight'.*non-finite"):
        graph.lower(_nan_weight(_exported()))
    graph.lower(_exported())  # the same model with finite weights lowers


def test_metadata_that_cannot_be_decoded_names_the_key():
    from neural_brdf.fileformat import metadata

    for props, key in [
        ({"training_config": "[1,2"}, "training_config"),
        ({"metadata_version": "abc"}, "metadata_version"),
        ({"metadata_version": "true"}, "metadata_version"),
        ({"training_config": '["train.steps", 5]'}, "training_config"),
        ({"sampling_lobe": BAD_LOBE}, "sampling_lobe"),
    ]:
        with pytest.raises(InputError, match=key):
            metadata.read_metadata(props)
        with pytest.raises(InputError, match=f"^x.onnx: .*{key}"):
            reader.metadata(_exported(**props), source="x.onnx")
    assert metadata.read_metadata({"training_config": "a: 1"})["training_config"] == {"a": 1}
