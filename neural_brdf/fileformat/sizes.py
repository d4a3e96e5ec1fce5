"""Sizes an ONNX file declares, checked before anything is allocated from them.

    from neural_brdf.fileformat import sizes
    sizes.check(proto, source="model.onnx")   # InputError / limits.TooLarge, one line

A file is a program: an initializer may declare dims ``[2**20, 2**20]`` over a few bytes
of data, and a ``ConstantOfShape`` may ask for 256 GiB.  Evaluating such a graph (in
onnxruntime, in the graph lowering, in a code generator) ends in an allocator traceback
or the out-of-memory killer.  :func:`check` refuses it first, naming the tensor:

* every initializer (and ``Constant`` value) holds exactly the bytes its dims and type
  declare, and no more than :func:`neural_brdf.limits.memory_budget`;
* every tensor the graph computes, with its shape inferred from the file (ONNX's shape
  inference, with constant shapes propagated), stays within the budget when its
  symbolic batch dimension is :data:`ROWS` rows, the most a consumer evaluates at once.
"""

from __future__ import annotations

import math

import onnx
from onnx import TensorProto

from neural_brdf import limits
from neural_brdf.errors import InputError

ROWS = 1 << 18  # rows evaluated at once by a consumer (runtime.CHUNK)

_TYPED_FIELDS = ("float_data", "int32_data", "string_data", "int64_data", "double_data")


def _itemsize(data_type: int) -> int:
    try:
        return int(onnx.helper.tensor_dtype_to_np_dtype(data_type).itemsize)
    except (KeyError, TypeError, ValueError):
        return 8  # an unknown or odd type: counted as the widest


def _numel(dims) -> int:
    return math.prod(int(d) for d in dims)


def _check_tensor(t: TensorProto, what: str, source: str) -> None:
    dims = list(t.dims)
    if any(d < 0 for d in dims):
        raise InputError(f"{source}: {what} declares negative dims {dims}")
    nbytes = _numel(dims) * _itemsize(t.data_type)
    limits.check_bytes(f"{source}: {what} (dims {dims})", nbytes)
    if t.data_location == TensorProto.EXTERNAL:
        return  # its bytes live beside the file; onnx checks them when it loads them
    if t.HasField("raw_data"):
        held = len(t.raw_data)
        if held != nbytes:
            raise InputError(
                f"{source}: {what} declares dims {dims} ({nbytes} bytes) but holds {held} bytes"
            )
        return
    held_values = max(len(getattr(t, f)) for f in _TYPED_FIELDS)
    if t.data_type in (TensorProto.FLOAT16, TensorProto.BFLOAT16, TensorProto.BOOL):
        held_values = max(held_values, len(t.int32_data))
    numel = _numel(dims)
    if held_values not in (0, numel):
        raise InputError(
            f"{source}: {what} declares dims {dims} ({numel} values) but holds {held_values}"
        )


def _graph_tensors(graph: onnx.GraphProto):
    for t in graph.initializer:
        yield t, f"initializer {t.name!r}"
    for node in graph.node:
        for a in node.attribute:
            if a.type == onnx.AttributeProto.TENSOR:
                yield a.t, f"{node.op_type} node {node.name or node.output[0]!r} value"
            elif a.type == onnx.AttributeProto.GRAPH:
                yield from _graph_tensors(a.g)
            elif a.type == onnx.AttributeProto.GRAPHS:
                for g in a.graphs:
                    yield from _graph_tensors(g)


def _value_bytes(vi: onnx.ValueInfoProto) -> int | None:
    t = vi.type.tensor_type if vi.type.HasField("tensor_type") else None
    if t is None or not t.HasField("shape"):
        return None
    n = 1
    for d in t.shape.dim:
        if d.HasField("dim_value"):
            if d.dim_value < 0:
                return None
            n *= d.dim_value
        else:
            n *= ROWS  # the batch dimension (or another unknown one), as a consumer sees it
    return n * _itemsize(t.elem_type)


def check(proto: onnx.ModelProto, *, source: str = "model") -> None:
    """InputError naming ``source`` and the tensor when the file's data or the tensors
    its graph computes exceed what they declare or the memory budget (module doc)."""
    for t, what in _graph_tensors(proto.graph):
        _check_tensor(t, what, source)
    try:
        inferred = onnx.shape_inference.infer_shapes(proto, data_prop=True)
    except Exception:  # a graph shape inference cannot follow: the consumer will say
        return
    producer = {o: n for n in inferred.graph.node for o in n.output}
    for vi in [*inferred.graph.value_info, *inferred.graph.output]:
        nbytes = _value_bytes(vi)
        if nbytes is None:
            continue
        node = producer.get(vi.name)
        made = f" (output of a {node.op_type} node)" if node is not None else ""
        limits.check_bytes(f"{source}: tensor {vi.name!r}{made}", nbytes)
