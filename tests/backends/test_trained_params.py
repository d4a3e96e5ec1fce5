"""Trained parameters in a lowered graph (``graph.lower(..., params=...)``) and their live
binding in the Dr.Jit back end (``backends.drjit.run(..., params=...)``), llvm_ad_rgb.

The differentiable plugin (neural_brdf/inverse/bsdf.py) renders its primal passes by
lowering the RawBRDF's exported ONNX graph once, with every ``state_dict`` entry kept as
a parameter, and binding the optimiser's current weights at each evaluation.  Checked:

* the lowering with parameters computes what the constant lowering computes (the same
  floats), and ``Program.params`` ties every parameter's tables to it;
* weights bound at run time are the ones used: a program lowered from an all-zero
  network (so every table has the same content) and then given random weights equals
  torch's RawBRDF holding those weights, for the compact recipe and for the anisotropic
  encoding with a half-disc grid; so no table of one parameter stands in for another's;
* gradients through the bound weights equal torch's autograd of the same function;
* a parameter no node may read as one (a Mul) and a name that is not an initializer are
  refused with one line naming them;
* so are the forms of Gather, MatMul and Gemm that would fold a parameter as a constant
  (a Gather at constant indices, a product with no batch operand, a parameter as the
  left factor or as the indices) and a parameter that is a graph output: one line naming
  the node and the parameter, where before they raised numpy's errors or, for a Gather at
  index 0, lowered the whole parameter in place of its row (a silent wrong answer).
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch
import yaml
from onnx import TensorProto, helper

from neural_brdf import config as cfgmod
from neural_brdf import export, graph
from neural_brdf.train.model import RawBRDF

pytestmark = pytest.mark.mitsuba

N = 2048
MODELS = {
    "compact": "{hidden: [32], activation: relu, grid: {size: 32, channels: 4}}",
    "anisotropic": "{encoding: anisotropic, hidden: [16], activation: softplus, "
    "grid: {coords: half_disc, size: 8, channels: 2}}",
}


@pytest.fixture(scope="module")
def dr():
    import drjit
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    return drjit


def _raw(text: str, scale: float) -> RawBRDF:
    section = cfgmod.Model.model_validate(yaml.safe_load(text))
    torch.manual_seed(3)
    raw = RawBRDF.from_config(section, init_value=0.3).eval()
    with torch.no_grad():
        for p in raw.parameters():
            if scale:
                p.copy_(scale * torch.randn_like(p))
            else:  # zero_, not 0 * randn: no -0.0, so every table has the same bytes
                p.zero_()
    return raw


def _rows(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    wi, wo = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    return wi.astype(np.float32), wo.astype(np.float32)


def _columns(dr, wi, wo):
    Float = dr.llvm.ad.Float
    return {"wi": [Float(wi[:, k]) for k in range(3)], "wo": [Float(wo[:, k]) for k in range(3)]}


def _bound(dr, state: dict[str, torch.Tensor], grad: bool = False) -> dict:
    out = {k: dr.llvm.ad.Float(v.detach().numpy().reshape(-1)) for k, v in state.items()}
    if grad:
        for v in out.values():
            dr.enable_grad(v)
    return out


def _f(cols) -> np.ndarray:
    return np.stack([c.numpy() for c in cols["f"]], axis=1)


def test_parameters_compute_what_constants_compute(dr):
    from neural_brdf.backends import drjit as backend

    raw = _raw(MODELS["compact"], 0.3)
    onnx_bytes = export.to_onnx_bytes(raw, 17)
    state = raw.state_dict()
    trained = graph.lower(onnx_bytes, ("f",), params=tuple(state))
    folded = graph.lower(onnx_bytes, ("f",))
    assert sorted({name for name, _, _ in trained.params.values()}) == sorted(state)
    assert not folded.params
    wi, wo = _rows(0)
    with_params = _f(backend.run(trained, _columns(dr, wi, wo), params=_bound(dr, state)))
    unbound = _f(backend.run(trained, _columns(dr, wi, wo)))  # the tables' own copies
    constants = _f(backend.run(folded, _columns(dr, wi, wo)))
    assert np.all(np.isfinite(constants)) and constants.max() > 0
    assert np.array_equal(with_params, constants)
    assert np.array_equal(unbound, constants)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_weights_bound_at_run_time_are_the_ones_used(dr, name):
    from neural_brdf.backends import drjit as backend

    zero = _raw(MODELS[name], 0.0)  # every parameter's tables alike
    program = graph.lower(export.to_onnx_bytes(zero, 17), ("f",), params=tuple(zero.state_dict()))
    live = _raw(MODELS[name], 0.3)
    wi, wo = _rows(1)
    got = _f(backend.run(program, _columns(dr, wi, wo), params=_bound(dr, live.state_dict())))
    with torch.no_grad():
        ref = live(torch.from_numpy(wi), torch.from_numpy(wo)).numpy()
    assert np.ptp(ref) > 0.1  # the random weights make a varied function
    np.testing.assert_allclose(got, ref, rtol=2e-5, atol=2e-5 * float(np.abs(ref).max()))


@pytest.mark.parametrize("name", sorted(MODELS))
def test_gradients_through_bound_weights_equal_torch(dr, name):
    from neural_brdf.backends import drjit as backend

    raw = _raw(MODELS[name], 0.3)
    state = raw.state_dict()
    program = graph.lower(export.to_onnx_bytes(raw, 17), ("f",), params=tuple(state))
    params = _bound(dr, state, grad=True)
    wi, wo = _rows(2)
    out = backend.run(program, _columns(dr, wi, wo), params=params)["f"]
    dr.backward(dr.sum(out[0] + 2.0 * out[1] + 3.0 * out[2], axis=None))
    f = raw(torch.from_numpy(wi), torch.from_numpy(wo))
    (f[:, 0] + 2.0 * f[:, 1] + 3.0 * f[:, 2]).sum().backward()
    for key, p in raw.named_parameters():
        assert p.grad is not None
        ref = p.grad.numpy().reshape(-1)
        got = dr.grad(params[key]).numpy()
        assert np.abs(ref).max() > 0, key
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-4 * float(np.abs(ref).max()))


def _mul_graph() -> bytes:
    """y = x * w (w an initializer): a parameter read by an op other than Gemm/Gather."""
    w = helper.make_tensor("w", TensorProto.FLOAT, [1, 3], [1.0, 2.0, 3.0])
    node = helper.make_node("Mul", ["x", "w"], ["f"], name="scale")
    g = helper.make_graph(
        [node],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3])],
        [helper.make_tensor_value_info("f", TensorProto.FLOAT, ["N", 3])],
        [w],
    )
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()


def test_a_parameter_only_gemm_or_gather_may_read_is_refused():
    model = _mul_graph()
    assert graph.lower(model).outputs  # as a constant it lowers
    with pytest.raises(graph.UnsupportedOnnxOp) as e:
        graph.lower(model, params=("w",))
    assert "'scale'" in str(e.value) and "'w'" in str(e.value) and "\n" not in str(e.value)
    onnx.checker.check_model(onnx.load_from_string(model))


def test_a_parameter_that_is_not_an_initializer_is_refused():
    with pytest.raises(graph.UnsupportedOnnxOp, match="not_there"):
        graph.lower(_mul_graph(), params=("not_there",))


def _model(nodes, inits, out_shape, inputs=(("x", 3),), extra=None) -> bytes:
    """A tiny checked ONNX graph: float inputs [N, k], the float output f of ``out_shape``
    and ``extra`` ones ({name: shape})."""
    g = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["N", k]) for n, k in inputs],
        [
            helper.make_tensor_value_info(o, TensorProto.FLOAT, shape)
            for o, shape in {"f": out_shape, **(extra or {})}.items()
        ],
        inits,
    )
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model, full_check=True)
    return model.SerializeToString()


def _refused(model: bytes, params: tuple[str, ...], node: str, param: str, form: str) -> None:
    with pytest.raises(graph.UnsupportedOnnxOp) as e:
        graph.lower(model, params=params)
    msg = str(e.value)
    assert f"node {node!r}" in msg and repr(param) in msg and form in msg, msg
    assert "\n" not in msg


def _table() -> onnx.TensorProto:
    return helper.make_tensor("w", TensorProto.FLOAT, [4, 3], [float(v) for v in range(12)])


def test_a_parameter_gathered_at_constant_indices_is_refused():
    # y = x * w[[2]]: lowers with w a constant; np.take of the parameter raised IndexError
    i = helper.make_tensor("i", TensorProto.INT64, [1], [2])
    rows = _model(
        [
            helper.make_node("Gather", ["w", "i"], ["row"], name="look"),
            helper.make_node("Mul", ["x", "row"], ["f"], name="scale"),
        ],
        [_table(), i],
        ["N", 3],
    )
    assert graph.lower(rows).outputs
    _refused(rows, ("w",), "look", "w", "constant indices")
    # y = x @ w[0]: the scalar index 0 took the whole parameter (a 0-d object array's
    # one element), so the MatMul lowered x @ w, three columns where ONNX has one
    w = helper.make_tensor("w", TensorProto.FLOAT, [3, 3], [float(v) for v in range(9)])
    zero = helper.make_tensor("i", TensorProto.INT64, [], [0])
    dot = _model(
        [
            helper.make_node("Gather", ["w", "i"], ["row"], name="look"),
            helper.make_node("MatMul", ["x", "row"], ["f"], name="dot"),
        ],
        [w, zero],
        ["N"],
    )
    _refused(dot, ("w",), "look", "w", "constant indices")


def test_a_parameter_as_gather_indices_is_refused():
    i = helper.make_tensor("i", TensorProto.INT64, [1], [0])
    pick = _model(
        [helper.make_node("Gather", ["x", "i"], ["f"], name="pick", axis=1)], [i], ["N", 1]
    )
    assert graph.lower(pick).outputs
    _refused(pick, ("i",), "pick", "i", "as indices")


def _product(op: str) -> bytes:
    """y = x @ (w @ v), the inner product of two initializers: no batch operand."""
    w = helper.make_tensor("w", TensorProto.FLOAT, [3, 3], [float(v) for v in range(9)])
    v = helper.make_tensor("v", TensorProto.FLOAT, [3, 3], [float(-v) for v in range(9)])
    return _model(
        [
            helper.make_node(op, ["w", "v"], ["wv"], name="inner"),
            helper.make_node("MatMul", ["x", "wv"], ["f"], name="outer"),
        ],
        [w, v],
        ["N", 3],
    )


@pytest.mark.parametrize("params", [("w",), ("v",), ("w", "v")])
def test_a_matmul_of_a_parameter_without_a_batch_operand_is_refused(params):
    model = _product("MatMul")
    assert graph.lower(model).outputs  # folded as constants it lowers
    _refused(model, params, "inner", params[0], "no batch operand")


@pytest.mark.parametrize("params", [("w",), ("v",), ("w", "v")])
def test_a_gemm_of_a_parameter_without_a_batch_operand_is_refused(params):
    _refused(_product("Gemm"), params, "inner", params[0], "no batch operand")


def test_a_parameter_left_of_a_batch_tensor_is_refused():
    w = helper.make_tensor("w", TensorProto.FLOAT, [3, 3], [float(v) for v in range(9)])
    left = _model([helper.make_node("MatMul", ["w", "x"], ["f"], name="left")], [w], ["N", 3])
    _refused(left, ("w",), "left", "w", "on the left of a batch tensor")
    gemm = _model([helper.make_node("Gemm", ["w", "x"], ["f"], name="left")], [w], ["N", 3])
    _refused(gemm, ("w",), "left", "w", "needs a batch input A")


def test_a_parameter_that_is_a_graph_output_is_refused():
    model = _model(
        [helper.make_node("Mul", ["x", "x"], ["f"], name="square")],
        [_table()],
        ["N", 3],
        extra={"w": [4, 3]},
    )
    with pytest.raises(graph.UnsupportedOnnxOp) as e:
        graph.lower(model, ("w",), params=("w",))
    assert "output 'w'" in str(e.value) and "trained parameter 'w'" in str(e.value)
    assert graph.lower(model, ("f",), params=("w",)).outputs  # unread, it is harmless
