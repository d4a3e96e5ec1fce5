"""The graph as every consumer reads it, and at the opset a consumer needs (docs/portable.md).

    from neural_brdf.fileformat import portable
    proto = portable.portable_graph(proto)          # torch's graph, rewritten in place
    onnx.save(portable.convert_opset("model.onnx", 13), "model-opset13.onnx")

Pure ONNX (onnx and numpy only): the exporter runs :func:`portable_graph` on every graph
torch writes (``neural_brdf.export.to_onnx_bytes``); :func:`convert_opset` gives an
exported file at opsets 13 up.
"""

from __future__ import annotations

import copy

import numpy as np
import onnx
from onnx import numpy_helper

from neural_brdf.fileformat import reader

# ------------------------------------------------------------------ a portable graph
# The graph torch writes is rewritten so that every consumer reads it: onnxruntime from the
# oldest release pyproject allows (1.18) to the newest, onnxruntime-web, onnx2torch, the
# ONNX reference evaluator, onnx's version converter (opset 13 and up) and
# neural_brdf.graph (the C/GLSL/WGSL and Dr.Jit back ends).  docs/portable.md lists what
# each rewrite fixed; every one computes the same float32 operations as before.
PORTABLE_PREFIX = "portable/"  # names of the nodes and constants the rewrites add
REDUCE_UNROLL = 8  # ReduceSum over a static axis of at most this many entries is unrolled


def portable_graph(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Rewrite ``proto`` (in place, and returned) into the portable form:

    * ``ReduceSum`` over a short static axis becomes the sum of its entries, left to
      right (Gather + Add): onnxruntime before 1.32 returns a [0, 3] tensor for the sum
      over the last axis of a [0, 3] one, and the next Div then fails on a batch of 0
      rows.  neural_brdf.graph lowers ReduceSum to the same left-to-right sum, so
      generated code does not change.
    * ``Clip`` with an omitted bound (torch's clamp_min / clamp_max write the empty
      input name "") becomes ``Max(x, min)`` / ``Min(x, max)``: onnx2torch takes a
      Clip's bounds as constants and refuses the empty name.
    * ``ConstantOfShape(Shape(x))`` (torch's zeros_like / ones_like) feeding a ``Where``
      that also takes ``x`` becomes a scalar constant, which Where broadcasts to the same
      shape: onnx's version converter has no adapter for Shape below opset 15.

    Nodes and initializers that nothing uses any more are dropped.  The graph's inputs,
    outputs and metadata are untouched."""
    g = proto.graph
    inferred = onnx.shape_inference.infer_shapes(proto)
    shapes = {
        v.name: [
            d.dim_value if d.HasField("dim_value") else None for d in v.type.tensor_type.shape.dim
        ]
        for v in list(inferred.graph.value_info) + list(inferred.graph.input)
        if v.type.tensor_type.HasField("shape")
    }
    consts = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    for n in g.node:
        if n.op_type == "Constant" and n.attribute and n.attribute[0].name == "value":
            consts[n.output[0]] = numpy_helper.to_array(n.attribute[0].t)
    producer = {o: n for n in g.node for o in n.output}
    added: list[onnx.TensorProto] = []

    def const(value, dtype) -> str:
        name = f"{PORTABLE_PREFIX}c{len(added)}"
        added.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    nodes = []
    for n in g.node:
        nodes.extend(_portable_node(n, shapes, consts, producer, const))
    del g.node[:]
    g.node.extend(nodes)
    g.initializer.extend(added)
    _drop_unused(g)
    return proto


def _portable_node(n, shapes, consts, producer, const) -> list:
    """The node(s) that replace ``n`` in :func:`portable_graph` (``[n]`` when none do)."""
    make = onnx.helper.make_node
    name = n.name or n.output[0]
    if n.op_type == "Clip" and not n.attribute and (len(n.input) < 3 or not all(n.input[1:3])):
        bounds = [(op, n.input[i]) for op, i in (("Max", 1), ("Min", 2)) if len(n.input) > i]
        bounds = [(op, b) for op, b in bounds if b]
        if not bounds:
            return [make("Identity", [n.input[0]], list(n.output), name=name)]
        out, x = [], n.input[0]
        for k, (op, b) in enumerate(bounds):
            y = n.output[0] if k == len(bounds) - 1 else f"{PORTABLE_PREFIX}{name}/{op}"
            out.append(make(op, [x, b], [y], name=f"{name}/{op}"))
            x = y
        return out
    if n.op_type == "ReduceSum":
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
        axes = consts.get(n.input[1]) if len(n.input) > 1 and n.input[1] else None
        if axes is None and attrs.get("axes") is not None:  # opset < 13: an attribute
            axes = np.asarray(attrs["axes"])
        shape = shapes.get(n.input[0])
        if axes is None or axes.size != 1 or shape is None or attrs.get("noop_with_empty_axes"):
            return [n]
        axis = int(axes.reshape(-1)[0]) % len(shape)
        size = shape[axis]
        if size is None or not 1 <= size <= REDUCE_UNROLL:
            return [n]
        keep = bool(attrs.get("keepdims", 1))
        out, acc = [], None
        for k in range(size):
            idx = const([k] if keep else k, np.int64)
            part = f"{PORTABLE_PREFIX}{name}/{k}"
            out.append(
                make("Gather", [n.input[0], idx], [part], name=f"{name}/Gather{k}", axis=axis)
            )
            if acc is not None:
                y = n.output[0] if k == size - 1 else f"{PORTABLE_PREFIX}{name}/sum{k}"
                out.append(make("Add", [acc, part], [y], name=f"{name}/Add{k}"))
                part = y
            acc = part
        if size == 1:
            out.append(make("Identity", [str(acc)], [n.output[0]], name=f"{name}/Identity"))
        return out
    if n.op_type == "Where":
        inputs = list(n.input)
        changed = False
        for i in (1, 2):
            src = producer.get(inputs[i])
            if src is None or src.op_type != "ConstantOfShape":
                continue
            shape_node = producer.get(src.input[0])
            if shape_node is None or shape_node.op_type != "Shape" or shape_node.attribute:
                continue
            if shape_node.input[0] != inputs[3 - i]:  # where(c, x, zeros_like(x)) only
                continue
            fill = next((a.t for a in src.attribute if a.name == "value"), None)
            value = numpy_helper.to_array(fill).reshape(-1)[0] if fill is not None else 0.0
            dtype = numpy_helper.to_array(fill).dtype if fill is not None else np.float32
            inputs[i] = const(value, dtype)
            changed = True
        if changed:
            return [make("Where", inputs, list(n.output), name=name)]
    return [n]


def _drop_unused(g) -> None:
    """Remove nodes none of whose outputs is used, and unused initializers (not in a graph
    with subgraphs, whose uses this does not see)."""
    if any(
        a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
        for n in g.node
        for a in n.attribute
    ):
        return
    while True:
        used = {i for n in g.node for i in n.input} | {o.name for o in g.output}
        keep = [n for n in g.node if any(o in used for o in n.output)]
        if len(keep) == len(g.node):
            break
        del g.node[:]
        g.node.extend(keep)
    inits = [t for t in g.initializer if t.name in used]
    del g.initializer[:]
    g.initializer.extend(inits)


# Opset conversion (docs/portable.md, "Opsets").  onnx's version converter has no adapter
# down from opset 14 for even Add, Sub, Mul and Div (14 only admitted more types), so it
# cannot take any graph with arithmetic below 14.  Every op these graphs hold kept its
# meaning for float32 from opset 13 to the newest: the schema versions below only widened
# the types (bfloat16, float8, integers, optional and sequence types) or added an
# attribute whose default keeps the old behaviour (Reshape allowzero, Shape start/end,
# Cast saturate, which acts on float8 only).  Between two opsets that only such versions
# separate, conversion is a relabelling of the opset, checked by onnx's full check.
MIN_OPSET = 13  # below it ReduceSum, Unsqueeze, Squeeze, Split, Clip changed form
TYPES_ONLY_VERSIONS = {
    *{(op, 14) for op in ("Add", "Sub", "Mul", "Div", "Relu", "Identity", "Reshape")},
    *{(op, 15) for op in ("Pow", "Shape")},
    *{(op, 16) for op in ("Where", "Identity", "LessOrEqual", "GreaterOrEqual")},
    *{(op, 19) for op in ("Cast", "Constant", "Equal", "Identity", "Reshape", "Shape")},
    *{(op, 20) for op in ("IsNaN", "IsInf", "ConstantOfShape")},
    *{
        (op, v)
        for v in (21, 23, 24)
        for op in (
            "Cast",
            "Constant",
            "ConstantOfShape",
            "Identity",
            "Reshape",
            "Shape",
            "Squeeze",
            "Transpose",
            "Unsqueeze",
        )
    },
    *{
        (op, 22)
        for op in ("Softplus", "Atan", "Asin", "Acos", "Cos", "Sin", "Tan", "Softsign", "Elu")
    },
}


def _version_steps(op: str, lo: int, hi: int) -> list[int]:
    """The schema versions of ``op`` that took effect in the opsets (lo, hi]."""
    steps = []
    for v in range(lo + 1, hi + 1):
        try:
            since = onnx.defs.get_schema(op, v).since_version
        except onnx.defs.SchemaError:
            return [-1]  # the op does not exist at one end
        if since > lo and since not in steps:
            steps.append(since)
    return steps


def convert_opset(model, opset: int) -> onnx.ModelProto:
    """An exported model (a path, bytes or ModelProto) at ONNX opset ``opset``.

    Between opset 13 and the newest that onnx knows, a graph whose ops changed only in
    their types in between (:data:`TYPES_ONLY_VERSIONS`; an attribute that would change
    the meaning, such as Reshape's allowzero = 1, disqualifies) is relabelled; any other is
    left to onnx's version converter, which converts upwards.  The result passes
    ``onnx.checker.check_model(full_check=True)``; ``onnx.checker.ValidationError`` or a
    ValueError when it cannot be converted."""
    proto = copy.deepcopy(reader.load(model))
    current = next(o.version for o in proto.opset_import if o.domain in ("", "ai.onnx"))
    newest = onnx.defs.onnx_opset_version()
    if not MIN_OPSET <= opset <= newest:
        raise ValueError(f"opset {opset}: supported are {MIN_OPSET} to {newest}")
    lo, hi = sorted((current, opset))
    blocking = set()
    for n in proto.graph.node:
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
        changed = [(n.op_type, v) for v in _version_steps(n.op_type, lo, hi)]
        if any(c not in TYPES_ONLY_VERSIONS for c in changed) or (
            changed
            and (
                attrs.get("allowzero", 0)
                or "start" in attrs
                or "end" in attrs
                or "saturate" in attrs
            )
        ):
            blocking.add(n.op_type)
    if not blocking:
        # an attribute newer than the target opset left here holds its default (any other
        # value blocked above: Reshape's allowzero = 0, which torch writes): drop it
        for n in proto.graph.node:
            known = onnx.defs.get_schema(n.op_type, opset).attributes
            for a in [a for a in n.attribute if a.name not in known]:
                n.attribute.remove(a)
        for o in proto.opset_import:
            if o.domain in ("", "ai.onnx"):
                o.version = opset
        need = onnx.helper.find_min_ir_version_for(list(proto.opset_import))
        proto.ir_version = max(proto.ir_version, need)
    elif opset > current:
        proto = onnx.version_converter.convert_version(proto, opset)
    else:
        raise ValueError(
            f"opset {current} -> {opset}: ops {sorted(blocking)} changed meaning in between; "
            f"export at opset {opset} instead (export.opset)"
        )
    onnx.checker.check_model(proto, full_check=True)
    return proto
