"""One kernel per supported ONNX op: ``_OPS[op](lowering, args, attrs)``; their names
are :data:`SUPPORTED_OPS`."""

from __future__ import annotations

import numpy as np
from onnx import numpy_helper

from neural_brdf.graph.ir import BATCH, UnsupportedOnnxOp
from neural_brdf.graph.lowering import (
    _IR_TYPES,
    _NP_BINARY,
    _NP_TYPES,
    _NP_UNARY,
    Lanes,
    Param,
    _align,
    _axes_arg,
    _axis,
    _obj,
    param_ids,
)


def _unary(op):
    def run(lo, args, attrs):
        return lo.elementwise(op, _NP_UNARY[op], lambda x: lo.unary(op, x), args[0])

    return run


def _binary(op):
    def run(lo, args, attrs):
        return lo.elementwise(
            op, _NP_BINARY[op], lambda x, y: lo.binary(op, x, y), args[0], args[1]
        )

    return run


def _variadic(op):
    def run(lo, args, attrs):
        acc = args[0]
        for b in args[1:]:
            acc = lo.elementwise(op, _NP_BINARY[op], lambda x, y: lo.binary(op, x, y), acc, b)
        return acc

    return run


def _where(lo, args, attrs):
    return lo.elementwise("Where", np.where, lambda c, a, b: lo.b.emit("select", c, a, b), *args)


def _clip(lo, args, attrs):
    x = args[0]
    lo_v = args[1] if len(args) > 1 and args[1] is not None else attrs.get("min")
    hi_v = args[2] if len(args) > 2 and args[2] is not None else attrs.get("max")
    if lo_v is not None:
        x = lo.elementwise(
            "Clip",
            lambda a, b: np.maximum(a, b).astype(np.asarray(a).dtype),
            lambda a, b: lo.b.emit("max", a, b),
            x,
            np.asarray(lo_v),
        )
    if hi_v is not None:
        x = lo.elementwise(
            "Clip",
            lambda a, b: np.minimum(a, b).astype(np.asarray(a).dtype),
            lambda a, b: lo.b.emit("min", a, b),
            x,
            np.asarray(hi_v),
        )
    return x


def _cast(lo, args, attrs):
    to = attrs["to"]
    x = args[0]
    if to not in _NP_TYPES:
        raise UnsupportedOnnxOp(f"Cast to ONNX type {to}")
    if not isinstance(x, Lanes):
        return np.asarray(x).astype(_NP_TYPES[to])  # double is evaluated in float32
    return lo.elementwise("Cast", None, lambda v: lo.b.emit("cast", v, attr=_IR_TYPES[to]), x)


def _constant(lo, args, attrs):
    if "value" in attrs:
        return numpy_helper.to_array(attrs["value"])
    for key, dtype in (
        ("value_float", np.float32),
        ("value_int", np.int64),
        ("value_floats", np.float32),
        ("value_ints", np.int64),
    ):
        if key in attrs:
            return np.asarray(attrs[key], dtype=dtype)
    raise UnsupportedOnnxOp(f"Constant with attributes {sorted(attrs)}")


def _shape(lo, args, attrs):
    x = args[0]
    s = [BATCH] + list(x.shape) if isinstance(x, Lanes) else list(np.shape(x))
    if "start" in attrs or "end" in attrs:
        s = s[attrs.get("start", 0) : attrs.get("end", len(s))]
    return np.asarray(s, dtype=np.int64)


def _constant_of_shape(lo, args, attrs):
    value = numpy_helper.to_array(attrs["value"]) if "value" in attrs else np.zeros(1, np.float32)
    shape = [int(v) for v in np.asarray(args[0]).reshape(-1)]
    if BATCH in shape[1:]:
        raise UnsupportedOnnxOp("ConstantOfShape: the batch must be the first axis")
    if shape and shape[0] == BATCH:
        lit = lo.b.const(value.reshape(-1)[0])
        return Lanes(_obj([lit] * int(np.prod(shape[1:], dtype=np.int64)), tuple(shape[1:])))
    return np.full(shape, value.reshape(-1)[0], dtype=value.dtype)


def _expand(lo, args, attrs):
    x, shape = args[0], [int(v) for v in np.asarray(args[1]).reshape(-1)]
    if BATCH in shape[1:]:
        raise UnsupportedOnnxOp("Expand: the batch must be the first axis")
    if not isinstance(x, Lanes):
        if shape and shape[0] == BATCH:
            c = np.asarray(x)
            rank = max(len(shape) - 1, c.ndim - 1)
            c = _align(c, rank, "Expand")
            tail = np.broadcast_shapes(c.shape, tuple(shape[1:]))
            lits = [lo.b.const(v) for v in np.broadcast_to(c, tail).reshape(-1)]
            return Lanes(_obj(lits, tail))
        return np.broadcast_to(x, np.broadcast_shapes(np.shape(x), tuple(shape))).copy()
    rank = len(x.shape)
    if len(shape) == rank + 1:
        if shape[0] not in (1, BATCH):
            raise UnsupportedOnnxOp(f"Expand: cannot expand the batch axis to {shape[0]}")
        shape = shape[1:]
    elif len(shape) > rank + 1:
        raise UnsupportedOnnxOp(f"Expand: target {shape} has more axes than the batch tensor")
    tail = np.broadcast_shapes(x.shape, tuple(shape))
    return Lanes(np.broadcast_to(x.a, tail).copy())


def _reshape(lo, args, attrs):
    x, shape = args[0], [int(v) for v in np.asarray(args[1]).reshape(-1)]
    allowzero = attrs.get("allowzero", 0)
    if not isinstance(x, Lanes):
        if BATCH in shape:
            raise UnsupportedOnnxOp("Reshape: a constant cannot take the batch size")
        c = np.asarray(x)
        shape = [c.shape[i] if (v == 0 and not allowzero) else v for i, v in enumerate(shape)]
        return c.reshape(shape)
    if not shape or shape[0] not in (BATCH, -1, 0):
        raise UnsupportedOnnxOp(f"Reshape: target {shape} does not keep the batch as axis 0")
    full = [BATCH] + list(x.shape)
    tail = [full[i + 1] if (v == 0 and not allowzero) else v for i, v in enumerate(shape[1:])]
    if BATCH in tail:
        raise UnsupportedOnnxOp("Reshape: the batch must stay the first axis")
    return Lanes(x.a.reshape(tail))


def _unsqueeze(lo, args, attrs):
    x, axes = args[0], _axes_arg(args, attrs)
    if not isinstance(x, Lanes):
        c = np.asarray(x)
        out_rank = c.ndim + len(axes)
        for a in sorted(a + out_rank if a < 0 else a for a in axes):
            c = np.expand_dims(c, a)
        return c
    out_rank = len(x.shape) + 1 + len(axes)
    a_obj = x.a
    for a in sorted(_axis(a, out_rank, "Unsqueeze") for a in axes):
        a_obj = np.expand_dims(a_obj, a)
    return Lanes(a_obj)


def _squeeze(lo, args, attrs):
    x, axes = args[0], _axes_arg(args, attrs)
    if not isinstance(x, Lanes):
        return np.squeeze(np.asarray(x), axis=None if axes is None else tuple(axes))
    if axes is None:
        return Lanes(np.squeeze(x.a))
    return Lanes(np.squeeze(x.a, axis=tuple(_axis(a, len(x.shape) + 1, "Squeeze") for a in axes)))


def _concat(lo, args, attrs):
    axis = attrs["axis"]
    if not any(isinstance(x, Lanes) for x in args):
        return np.concatenate([np.asarray(x) for x in args], axis=axis)
    rank = max(len(x.shape) for x in args if isinstance(x, Lanes))
    ax = _axis(axis, rank + 1, "Concat")
    parts = []
    for x in args:
        if isinstance(x, Lanes):
            parts.append(x.a)
        else:
            c = np.asarray(x)
            if c.ndim != rank + 1 or c.shape[0] != 1:
                raise UnsupportedOnnxOp(
                    "Concat of a batch tensor with a constant that does not have batch size 1"
                )
            parts.append(lo.ids(c, rank, "Concat"))
    return Lanes(np.concatenate(parts, axis=ax))


def _slice(lo, args, attrs):
    x = args[0]
    starts = [int(v) for v in np.asarray(args[1]).reshape(-1)]
    ends = [int(v) for v in np.asarray(args[2]).reshape(-1)]
    rank = np.ndim(x) if not isinstance(x, Lanes) else len(x.shape) + 1
    axes = _axes_arg(args, {}, 3) or list(range(len(starts)))
    steps = (
        [int(v) for v in np.asarray(args[4]).reshape(-1)]
        if len(args) > 4 and args[4] is not None
        else [1] * len(starts)
    )
    index = [slice(None)] * rank
    for s, e, a, st in zip(starts, ends, axes, steps, strict=False):
        a = a + rank if a < 0 else a
        index[a] = slice(s, e, st)
    if not isinstance(x, Lanes):
        return np.asarray(x)[tuple(index)]
    b = index[0]
    if not (b.start in (0, None) and b.step in (1, None) and (b.stop is None or b.stop >= 2**31)):
        raise UnsupportedOnnxOp("Slice: slicing the batch axis is not supported")
    return Lanes(x.a[tuple(index[1:])])


def _gather(lo, args, attrs):
    data, idx = args
    axis = attrs.get("axis", 0)
    b = lo.b
    if isinstance(idx, Param):
        raise UnsupportedOnnxOp(
            f"Gather at the trained parameter {idx.name!r} as indices "
            "(a parameter is gathered only as the table)"
        )
    if not isinstance(idx, Lanes):
        if isinstance(data, Param):  # np.take would fold the Param object itself
            raise UnsupportedOnnxOp(
                f"Gather of the trained parameter {data.name!r} at constant indices "
                "(a parameter is gathered only at batch-dependent indices)"
            )
        idx = np.asarray(idx)
        if not isinstance(data, Lanes):
            return np.take(np.asarray(data), idx, axis=axis)
        ax = _axis(axis, len(data.shape) + 1, "Gather")
        return Lanes(np.take(data.a, idx, axis=ax))
    if isinstance(data, Lanes):
        raise UnsupportedOnnxOp("Gather from a batch tensor at batch-dependent indices")
    if isinstance(data, Param):
        return _gather_param(b, data, idx, axis)
    data = np.asarray(data)
    axis = axis + data.ndim if axis < 0 else axis
    if axis != 0:
        raise UnsupportedOnnxOp("Gather of a constant at batch indices needs axis 0")
    k = data.shape[0]
    rest = data.shape[1:]
    cols = data.reshape(k, -1)
    floating = np.issubdtype(data.dtype, np.floating)
    tables = [
        b.table(np.ascontiguousarray(cols[:, j], dtype=np.float32 if floating else np.int32))
        for j in range(cols.shape[1])
    ]
    b.source(np.ascontiguousarray(cols, dtype=np.float32 if floating else np.int32), tables)
    return _rows_at(b, idx, k, tables, rest)


def _rows_at(b, idx: Lanes, k: int, tables: list[int], rest: tuple[int, ...]) -> Lanes:
    """Rows ``idx`` (negative ones from the end, as ONNX Gather) of a tensor of ``k`` rows
    held as ``tables``, one per column: a tensor of shape idx.shape + rest."""
    out: list[int] = []
    for i in idx.a.reshape(-1):
        i = b.emit("cast", i, attr="int")
        i = b.emit(
            "select", b.emit("lt", i, b.const(0, "int")), b.emit("add", i, b.const(k, "int")), i
        )
        out.extend(b.emit("gather", i, attr=t) for t in tables)
    return Lanes(_obj(out, idx.shape + rest))


def _gather_param(b, p: Param, idx: Lanes, axis: int) -> Lanes:
    """A trained parameter's rows at batch indices: one gather per column, from tables
    that ``Program.params`` ties to the parameter (graph.lower(..., params=...))."""
    if (axis + p.value.ndim if axis < 0 else axis) != 0:
        raise UnsupportedOnnxOp(f"Gather of parameter {p.name!r} at batch indices needs axis 0")
    k = p.shape[0]
    rest = p.shape[1:]
    cols = p.value.reshape(k, -1)
    tables = [b.param_table(p.name, cols[:, j], j, cols.shape[1]) for j in range(cols.shape[1])]
    return _rows_at(b, idx, k, tables, rest)


def _reduce(kind):
    def run(lo, args, attrs):
        b = lo.b
        x = args[0]
        keep = bool(attrs.get("keepdims", 1))
        axes = _axes_arg(args, attrs)
        if axes is None or not axes:
            if attrs.get("noop_with_empty_axes", 0):
                return x
            if isinstance(x, Lanes):
                raise UnsupportedOnnxOp(f"{kind} over every axis, batch included")
        if not isinstance(x, Lanes):
            c = np.asarray(x)
            ax = None if not axes else tuple(axes)
            fn = {
                "ReduceSum": np.sum,
                "ReduceMean": np.mean,
                "ReduceMax": np.max,
                "ReduceMin": np.min,
                "ReduceProd": np.prod,
                "ReduceL2": lambda v, axis, keepdims: np.sqrt(
                    np.sum(v * v, axis=axis, keepdims=keepdims)
                ),
            }[kind]
            return np.asarray(fn(c, axis=ax, keepdims=keep)).astype(c.dtype)
        rank = len(x.shape) + 1
        tax = tuple(sorted(_axis(a, rank, kind) for a in axes))
        a = x.a
        moved = np.moveaxis(a, tax, tuple(range(len(tax))))
        count = int(np.prod([a.shape[i] for i in tax], dtype=np.int64))
        flat = moved.reshape(count, -1)
        step = {
            "ReduceSum": "add",
            "ReduceMean": "add",
            "ReduceL2": "add",
            "ReduceMax": "max",
            "ReduceMin": "min",
            "ReduceProd": "mul",
        }[kind]
        out = []
        for j in range(flat.shape[1]):
            col = list(flat[:, j])
            if kind == "ReduceL2":
                col = [b.emit("mul", v, v) for v in col]
            acc = col[0]
            for v in col[1:]:
                acc = b.emit(step, acc, v)
            if kind == "ReduceMean":
                acc = b.emit("div", acc, b.scalar(float(count)))
            elif kind == "ReduceL2":
                acc = b.emit("sqrt", acc)
            out.append(acc)
        shape = [n for i, n in enumerate(a.shape) if i not in tax]
        res = _obj(out, tuple(shape))
        if keep:
            for i in tax:
                res = np.expand_dims(res, i)
        return Lanes(res)

    return run


def _param_linear(lo, x, w, bias, trans_b: bool) -> Lanes:
    """x @ w (+ bias) where ``w`` or ``bias`` is a trained parameter: weights as gathers
    from the parameter's table (:func:`param_ids`), constants as constants."""

    def ids(v):
        if isinstance(v, Param):
            return param_ids(lo.b, v)
        c = np.asarray(v, np.float32)
        return np.vectorize(lambda e: lo.b.scalar(float(e)), otypes=[object])(c)

    wi = ids(w)
    if wi.ndim != 2:
        raise UnsupportedOnnxOp(f"matrix product with weights of shape {wi.shape}")
    wi = wi.T if trans_b else wi
    bi = None
    if bias is not None:
        bi = np.broadcast_to(ids(bias).reshape(-1), (wi.shape[1],))
    return lo.linear_ids(x, wi, bi)


def _gemm(lo, args, attrs):
    a, b = args[0], args[1]
    c = args[2] if len(args) > 2 else None
    alpha, beta = float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0))
    p = next((v for v in (a, b, c) if isinstance(v, Param)), None)
    if p is not None:
        if not isinstance(a, Lanes) and not isinstance(b, Lanes):
            raise UnsupportedOnnxOp(
                f"Gemm of the trained parameter {p.name!r} with constant A and B "
                "(a product of parameters and constants, no batch operand)"
            )
        if (
            not isinstance(a, Lanes)
            or isinstance(b, Lanes)
            or isinstance(c, Lanes)
            or attrs.get("transA", 0)
            or alpha != 1.0
            or beta != 1.0
        ):
            raise UnsupportedOnnxOp(
                f"Gemm of the trained parameter {p.name!r} needs a batch input A, weights B "
                "and bias C that are not batch tensors, transA 0, alpha 1 and beta 1"
            )
        return _param_linear(lo, a, b, c, bool(attrs.get("transB", 0)))
    if not isinstance(a, Lanes):
        raise (
            UnsupportedOnnxOp("Gemm of two constants")
            if not isinstance(b, Lanes)
            else UnsupportedOnnxOp("Gemm with batch-dependent weights")
        )
    if isinstance(b, Lanes) or (c is not None and isinstance(c, Lanes)):
        raise UnsupportedOnnxOp("Gemm with batch-dependent weights or bias")
    if attrs.get("transA", 0):
        raise UnsupportedOnnxOp("Gemm with transA = 1 on a batch tensor")
    w = np.asarray(b, dtype=np.float64)
    if attrs.get("transB", 0):
        w = w.T
    bias = None
    if c is not None:
        bias = np.broadcast_to(_align(np.asarray(c, np.float64), 1, "Gemm"), (w.shape[1],)) * beta
        bias = bias.astype(np.float32)
    return lo.linear(a, w.astype(np.float32), bias, alpha)


def _matmul(lo, args, attrs):
    a, b = args
    if isinstance(b, Param) and isinstance(a, Lanes):
        return _param_linear(lo, a, b, None, False)
    if isinstance(a, Param) or isinstance(b, Param):  # np.matmul would fold the Param objects
        p = a if isinstance(a, Param) else b
        form = "on the left of a batch tensor" if isinstance(b, Lanes) else "with no batch operand"
        raise UnsupportedOnnxOp(
            f"MatMul of the trained parameter {p.name!r} {form} "
            "(a parameter is only the right-hand weights of a batch tensor)"
        )
    if not isinstance(a, Lanes) and not isinstance(b, Lanes):
        return np.matmul(a, b)
    if isinstance(b, Lanes) or np.ndim(b) != 2:
        raise UnsupportedOnnxOp("MatMul needs constant 2-D weights on the right")
    return lo.linear(a, np.asarray(b, np.float32), None, 1.0)


def _transpose(lo, args, attrs):
    x = args[0]
    perm = attrs.get("perm")
    if not isinstance(x, Lanes):
        return np.transpose(x, perm)
    if perm is None or perm[0] != 0:
        raise UnsupportedOnnxOp("Transpose that moves the batch axis")
    return Lanes(np.transpose(x.a, [p - 1 for p in perm[1:]]))


_OPS = {op: _unary(op) for op in _NP_UNARY}
_OPS.update(
    {
        op: _binary(op)
        for op in (
            "Add",
            "Sub",
            "Mul",
            "Pow",
            "Div",
            "Equal",
            "Greater",
            "Less",
            "GreaterOrEqual",
            "LessOrEqual",
            "And",
            "Or",
            "Xor",
        )
    }
)
_OPS.update({op: _variadic(op) for op in ("Max", "Min", "Sum")})
_OPS.update(
    {
        op: _reduce(op)
        for op in ("ReduceSum", "ReduceMean", "ReduceMax", "ReduceMin", "ReduceProd", "ReduceL2")
    }
)
_OPS.update(
    {
        "Where": _where,
        "Clip": _clip,
        "Cast": _cast,
        "Constant": _constant,
        "Shape": _shape,
        "ConstantOfShape": _constant_of_shape,
        "Expand": _expand,
        "Reshape": _reshape,
        "Unsqueeze": _unsqueeze,
        "Squeeze": _squeeze,
        "Concat": _concat,
        "Slice": _slice,
        "Gather": _gather,
        "Gemm": _gemm,
        "MatMul": _matmul,
        "Transpose": _transpose,
        "Dropout": lambda lo, args, attrs: args[0],
    }
)
SUPPORTED_OPS = frozenset(_OPS)
