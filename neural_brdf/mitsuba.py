"""Mitsuba 3 plugins for exported neural BRDFs and for the analytic models.

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")            # or cuda_ad_rgb
    import neural_brdf.mitsuba               # registers the two plugins below
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": "runs/quickstart/model.onnx"})
    ref = mi.load_dict({"type": "analytic_brdf", "model": "microfacet",
                        "params": '{"alpha": 0.3, "fresnel": "conductor", "material": "Au"}'})

    from neural_brdf.mitsuba import render_preview
    psnr = render_preview("model.onnx", "preview.png", reference={"model": "microfacet", ...})

This is the only module of the package that imports mitsuba.  Importing it needs a
Mitsuba variant to be set already (``mi.set_variant``); the plugins are registered for
that variant, which must be a JIT one (``llvm_*`` or ``cuda_*``; scalar variants are
refused when a plugin loads).

Evaluation.  The plugin never evaluates a retyped copy of the model.  :class:`OnnxProgram`
walks the exported ONNX graph node by node and maps every op onto Dr.Jit arithmetic
over per-lane arrays: a tensor of shape [N, k...] is held as a numpy object array of
shape (k...) whose elements are Dr.Jit arrays of width N (one per column).  Constant
sub-graphs (shape arithmetic, weights) are folded with numpy.  A Gemm with constant
weights becomes fused multiply-adds over columns, with the weights as literals in the
kernel (four independent FMA chains per dot product, see DOT_CHAINS).  In JIT variants
the whole graph is traced into the render's kernel, so rendering calls no Python per
sample; it runs inside a conditional, skipped for SIMD packets in which no lane has
both directions above the horizon.  An op outside :data:`SUPPORTED_OPS` raises
:class:`UnsupportedOnnxOp` naming it when the model loads.

The ``analytic_brdf`` plugin exports the analytic model's own torch ``f(wi, wo)`` to
ONNX with ``torch.onnx`` (in memory) and runs it through the same interpreter, so it is
as fast as the neural plugin and never calls back into torch while rendering.

Sampling (both plugins).  The mixture of :mod:`neural_brdf.lobe`: cosine-weighted
hemisphere sampling (share 1 - w) and GGX visible-normal sampling of a reflection lobe
of roughness ``alpha`` (share w); ``pdf`` is the mixture density of ``sample``.  The
neural plugin reads ``(alpha, w)`` from the ONNX metadata key ``sampling_lobe``, which
the exporter writes; for files exported before it did, it fits them when the model
loads (about half a second), as the analytic plugin always does.  The sample weight is
computed by the very same traced functions as ``eval`` and ``pdf`` (value / pdf), so it
equals eval / pdf exactly.

Conventions (Mitsuba's; docs/mitsuba.md): ``eval`` returns f * cos(theta_o), 0 when wi or
wo is at or below the horizon (one-sided, like Mitsuba's built-in BSDFs); ``pdf`` is 0
below the horizon; a sample below it has weight 0.
"""

from __future__ import annotations

import io
import json
import math
import os
import warnings
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import onnx
from onnx import numpy_helper

from . import lobe as lobes
from .config import InputError
from .fileio import atomic_path
from .runtime import INPUTS, OUTPUT

if mi.variant() is None:
    raise ImportError("neural_brdf.mitsuba: set a Mitsuba variant first, e.g. "
                      "mi.set_variant('llvm_ad_rgb'); the plugins register for that variant")
if not mi.is_rgb:
    # The graph returns RGB.  In a spectral or monochrome variant a scene would load and
    # the render then die inside Mitsuba with a bare std::bad_cast, so refuse here.
    raise ImportError(f"neural_brdf.mitsuba: variant {mi.variant()!r} is not an RGB variant; "
                      "the neural BSDF returns RGB values: use llvm_ad_rgb or cuda_ad_rgb "
                      "(for spectral rendering, bake the model to an RGL .bsdf file for "
                      "Mitsuba's own 'measured' plugin)")

# A shape vector (the value of an ONNX Shape op) holds this in place of the batch size N,
# which is not known while a kernel is traced.  Far from -1 and 0, which Reshape and
# Expand give meanings of their own; multiplying it by -1 (torch's Expand pattern)
# cannot produce -1 either.
BATCH = -(1 << 40)


class UnsupportedOnnxOp(InputError):
    """The graph uses an op (or an op in a form) that the Dr.Jit interpreter lacks."""


# ====================================================================== interpreter
class Lanes:
    """A tensor of shape (N,) + ``a.shape``: ``a`` is an object array of Dr.Jit arrays."""

    __slots__ = ("a",)

    def __init__(self, a):
        if not isinstance(a, np.ndarray):       # numpy indexing returned one element
            a = _obj([a], ())
        self.a = a

    @property
    def shape(self) -> tuple[int, ...]:
        return self.a.shape


def _obj(items, shape) -> np.ndarray:
    out = np.empty(len(items), dtype=object)
    for i, v in enumerate(items):
        out[i] = v
    return out.reshape(shape)


def _scalar(v):
    """A numpy scalar -> the Python scalar Dr.Jit combines with its arrays exactly."""
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    if isinstance(v, (np.integer, int)):
        return int(v)
    return float(v)


def _const_as_obj(c: np.ndarray) -> np.ndarray:
    return _obj([_scalar(v) for v in c.reshape(-1)], c.shape)


def _align(c: np.ndarray, rank: int, op: str) -> np.ndarray:
    """A constant broadcast against a lane tensor of trailing rank ``rank``.

    Its full shape is (N,) + trailing, so a constant of rank ``rank + 1`` lines up its
    first axis with the batch and must have size 1 there."""
    while c.ndim > rank:
        if c.shape[0] != 1:
            raise UnsupportedOnnxOp(f"{op}: a constant of shape {c.shape} does not broadcast "
                                    f"against a batch tensor of rank {rank + 1}")
        c = c[0]
    return c


def _elementwise(op: str, fn_np, fn_dr, *xs):
    """Apply an elementwise op: numpy on constants, Dr.Jit per column otherwise."""
    if not any(isinstance(x, Lanes) for x in xs):
        return fn_np(*xs)
    rank = max(len(x.shape) for x in xs if isinstance(x, Lanes))
    objs = [x.a if isinstance(x, Lanes) else _const_as_obj(_align(np.asarray(x), rank, op))
            for x in xs]
    shape = np.broadcast_shapes(*(o.shape for o in objs))
    objs = [np.broadcast_to(o, shape) for o in objs]
    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        out[idx] = fn_dr(*(o[idx] for o in objs))
    return Lanes(out)


def _axis(axis: int, rank: int, op: str) -> int:
    """A full-rank axis (batch is axis 0) -> the trailing axis of a lane tensor."""
    a = axis + rank if axis < 0 else axis
    if not 0 <= a < rank:
        raise UnsupportedOnnxOp(f"{op}: axis {axis} out of range for rank {rank}")
    if a == 0:
        raise UnsupportedOnnxOp(f"{op}: operating along the batch axis is not supported")
    return a - 1


def _softplus(x):
    """log(1 + exp(x)), stable: max(x, 0) + log1p(exp(-|x|)).

    log1p(e) is evaluated as log(u) * e / (u - 1) with u = 1 + e (Goldberg 1991,
    "What every computer scientist should know about floating-point", Theorem 4),
    accurate to a few ulps where log(1 + e) alone would round e away."""
    e = dr.exp(-dr.abs(x))
    u = 1.0 + e
    log1p = dr.select(u == 1.0, e, dr.log(u) * (e / (u - 1.0)))
    return dr.maximum(x, 0.0) + log1p


def _np_softplus(x):
    return np.logaddexp(np.zeros_like(x), x)


def _power(x, y):
    """x ** y; the exponents torch emits as constants (2, 0.5, ...) stay exact."""
    if isinstance(y, float) and not isinstance(x, float):
        if y == 1.0:
            return x
        if y == 2.0:
            return x * x
        if y == 3.0:
            return x * x * x
        if y == 0.5:
            return dr.sqrt(x)
        if y == -1.0:
            return 1.0 / x
    return dr.power(x, y)


_UNARY = {
    # op: (numpy, Dr.Jit)
    "Identity": (lambda x: x, lambda x: x),
    "Neg": (np.negative, lambda x: -x),
    "Abs": (np.abs, dr.abs),
    "Sqrt": (np.sqrt, dr.sqrt),
    "Exp": (np.exp, dr.exp),
    "Log": (np.log, dr.log),
    "Floor": (np.floor, dr.floor),
    "Ceil": (np.ceil, dr.ceil),
    "Sin": (np.sin, dr.sin),
    "Cos": (np.cos, dr.cos),
    "Atan": (np.arctan, dr.atan),
    "Asin": (np.arcsin, dr.asin),
    "Acos": (np.arccos, dr.acos),
    "Tanh": (np.tanh, dr.tanh),
    "Erf": (None, dr.erf),
    "Reciprocal": (lambda x: (1.0 / x).astype(x.dtype), lambda x: 1.0 / x),
    "Relu": (lambda x: np.maximum(x, 0).astype(x.dtype), lambda x: dr.maximum(x, 0.0)),
    "Sigmoid": (lambda x: (1.0 / (1.0 + np.exp(-x))).astype(x.dtype),
                lambda x: 1.0 / (1.0 + dr.exp(-x))),
    "Softplus": (_np_softplus, _softplus),
    "Not": (np.logical_not, lambda x: ~x),
    "IsNaN": (np.isnan, dr.isnan),
    "IsInf": (np.isinf, dr.isinf),
}

_BINARY = {
    "Add": (np.add, lambda a, b: a + b),
    "Sub": (np.subtract, lambda a, b: a - b),
    "Mul": (np.multiply, lambda a, b: a * b),
    "Pow": (lambda a, b: np.power(a, b).astype(a.dtype), _power),
    "Equal": (np.equal, lambda a, b: a == b),
    "Greater": (np.greater, lambda a, b: a > b),
    "Less": (np.less, lambda a, b: a < b),
    "GreaterOrEqual": (np.greater_equal, lambda a, b: a >= b),
    "LessOrEqual": (np.less_equal, lambda a, b: a <= b),
    "And": (np.logical_and, lambda a, b: a & b),
    "Or": (np.logical_or, lambda a, b: a | b),
    "Xor": (np.logical_xor, lambda a, b: a ^ b),
}

_VARIADIC = {
    "Max": (np.maximum, dr.maximum),
    "Min": (np.minimum, dr.minimum),
    "Sum": (np.add, lambda a, b: a + b),
}


def _np_div(a, b):
    if np.issubdtype(np.asarray(a).dtype, np.integer):
        return (np.sign(a) * np.sign(b) * (np.abs(a) // np.abs(b))).astype(np.asarray(a).dtype)
    return np.divide(a, b)


def _dr_div(a, b):
    if dr.is_integral_v(a) or dr.is_integral_v(b) or (isinstance(a, int) and isinstance(b, int)):
        raise UnsupportedOnnxOp("Div: integer division of batch tensors is not supported")
    return a / b


class _Types:
    """The Dr.Jit array types of the variant in use, taken from an input array."""

    def __init__(self, like):
        self.Float = type(like)
        self.Int = dr.int32_array_t(self.Float)
        self.UInt = dr.uint32_array_t(self.Float)
        self.Bool = dr.mask_t(self.Float)


_ONNX_FLOAT, _ONNX_INT32, _ONNX_INT64, _ONNX_BOOL, _ONNX_DOUBLE = 1, 6, 7, 9, 11


class OnnxProgram:
    """An ONNX graph, evaluated on Dr.Jit arrays by walking it node by node.

    ``program(wi=[x, y, z], wo=[x, y, z])`` takes each [N, k] input as a list of its k
    columns (Dr.Jit Float arrays) and returns ``{output name: list of columns}``.
    """

    def __init__(self, model):
        if isinstance(model, (str, os.PathLike)):
            model = onnx.load(str(model))
        elif isinstance(model, (bytes, bytearray)):
            model = onnx.load_from_string(bytes(model))
        g = model.graph
        self.consts: dict[str, np.ndarray] = {t.name: numpy_helper.to_array(t)
                                              for t in g.initializer}
        self.inputs = [i.name for i in g.input if i.name not in self.consts]
        self.outputs = [o.name for o in g.output]
        self.nodes = []
        for n in g.node:
            if n.domain not in ("", "ai.onnx"):
                raise UnsupportedOnnxOp(f"node {n.name!r}: op {n.domain}.{n.op_type} is not "
                                        f"a standard ONNX op")
            if n.op_type not in SUPPORTED_OPS:
                raise UnsupportedOnnxOp(
                    f"node {n.name!r}: ONNX op {n.op_type!r} is not supported by the Dr.Jit "
                    f"interpreter (supported: {', '.join(sorted(SUPPORTED_OPS))})")
            attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
            self.nodes.append((n.op_type, list(n.input), list(n.output), attrs, n.name))
        self.op_counts: dict[str, int] = {}
        for op, *_ in self.nodes:
            self.op_counts[op] = self.op_counts.get(op, 0) + 1

    def __call__(self, **columns) -> dict[str, list]:
        missing = set(self.inputs) - set(columns)
        if missing:
            raise ValueError(f"missing graph inputs {sorted(missing)}")
        first = next(iter(columns.values()))[0]
        t = _Types(first)
        env: dict[str, object] = dict(self.consts)
        for name in self.inputs:
            env[name] = Lanes(_obj([t.Float(c) for c in columns[name]], (len(columns[name]),)))
        for op, ins, outs, attrs, name in self.nodes:
            args = [env[i] if i else None for i in ins]
            try:
                res = _OPS[op](t, args, attrs)
            except UnsupportedOnnxOp as e:
                raise UnsupportedOnnxOp(f"node {name!r} ({op}): {e}") from None
            if not isinstance(res, tuple):
                res = (res,)
            for o, v in zip(outs, res):
                env[o] = v
        result = {}
        for name in self.outputs:
            v = env[name]
            if not isinstance(v, Lanes):
                v = _expand(t, [v, np.array([BATCH] + list(np.shape(v))[1:])], {})
            result[name] = [_to_float(t, x) for x in v.a.reshape(-1)]
        return result


def _to_float(t, x):
    if dr.is_mask_v(x):
        return dr.select(x, t.Float(1.0), t.Float(0.0))
    return t.Float(x)


def _literal(t, v):
    """A Python scalar -> a width-1 Dr.Jit array of the matching type."""
    if isinstance(v, bool):
        return t.Bool(v)
    if isinstance(v, int):
        return t.Int(v)
    return t.Float(v)


# ---------------------------------------------------------------------- op kernels
def _unary(op):
    fn_np, fn_dr = _UNARY[op]

    def run(t, args, attrs):
        if fn_np is None and not isinstance(args[0], Lanes):
            raise UnsupportedOnnxOp(f"{op} of a constant")
        return _elementwise(op, fn_np, fn_dr, args[0])
    return run


def _binary(op):
    fn_np, fn_dr = _BINARY[op]
    return lambda t, args, attrs: _elementwise(op, fn_np, fn_dr, args[0], args[1])


def _variadic(op):
    fn_np, fn_dr = _VARIADIC[op]

    def run(t, args, attrs):
        acc = args[0]
        for b in args[1:]:
            acc = _elementwise(op, fn_np, fn_dr, acc, b)
        return acc
    return run


def _div(t, args, attrs):
    return _elementwise("Div", _np_div, _dr_div, args[0], args[1])


def _where(t, args, attrs):
    def sel(c, a, b):
        if not any(isinstance(v, dr.ArrayBase) for v in (a, b)):
            a = _literal(t, a)
        return dr.select(c if not isinstance(c, bool) else t.Bool(c), a, b)
    return _elementwise("Where", np.where, sel, *args)


def _clip(t, args, attrs):
    x = args[0]
    lo = args[1] if len(args) > 1 and args[1] is not None else attrs.get("min")
    hi = args[2] if len(args) > 2 and args[2] is not None else attrs.get("max")
    if lo is not None:
        x = _elementwise("Clip", lambda a, b: np.maximum(a, b).astype(np.asarray(a).dtype),
                         dr.maximum, x, np.asarray(lo))
    if hi is not None:
        x = _elementwise("Clip", lambda a, b: np.minimum(a, b).astype(np.asarray(a).dtype),
                         dr.minimum, x, np.asarray(hi))
    return x


_NP_TYPES = {_ONNX_FLOAT: np.float32, _ONNX_DOUBLE: np.float64, _ONNX_INT32: np.int32,
             _ONNX_INT64: np.int64, _ONNX_BOOL: np.bool_}


def _cast(t, args, attrs):
    to = attrs["to"]
    x = args[0]
    if to not in _NP_TYPES:
        raise UnsupportedOnnxOp(f"Cast to ONNX type {to}")
    if not isinstance(x, Lanes):
        return np.asarray(x).astype(_NP_TYPES[to])
    if to in (_ONNX_FLOAT, _ONNX_DOUBLE):     # double is evaluated in float32
        return _elementwise("Cast", None, lambda v: _to_float(t, v), x)
    if to in (_ONNX_INT32, _ONNX_INT64):
        return _elementwise("Cast", None,
                            lambda v: dr.select(v, t.Int(1), t.Int(0)) if dr.is_mask_v(v)
                            else t.Int(v), x)
    return _elementwise("Cast", None, lambda v: v if dr.is_mask_v(v) else v != 0, x)


def _constant(t, args, attrs):
    if "value" in attrs:
        return numpy_helper.to_array(attrs["value"])
    for key, dtype in (("value_float", np.float32), ("value_int", np.int64),
                       ("value_floats", np.float32), ("value_ints", np.int64)):
        if key in attrs:
            return np.asarray(attrs[key], dtype=dtype)
    raise UnsupportedOnnxOp(f"Constant with attributes {sorted(attrs)}")


def _shape(t, args, attrs):
    x = args[0]
    s = [BATCH] + list(x.shape) if isinstance(x, Lanes) else list(np.shape(x))
    s = s[attrs.get("start", 0):attrs.get("end", len(s))] if ("start" in attrs or "end" in attrs) \
        else s
    return np.asarray(s, dtype=np.int64)


def _constant_of_shape(t, args, attrs):
    value = numpy_helper.to_array(attrs["value"]) if "value" in attrs \
        else np.zeros(1, np.float32)
    shape = [int(v) for v in np.asarray(args[0]).reshape(-1)]
    if BATCH in shape[1:]:
        raise UnsupportedOnnxOp("ConstantOfShape: the batch must be the first axis")
    if shape and shape[0] == BATCH:
        lit = _literal(t, _scalar(value.reshape(-1)[0]))
        return Lanes(_obj([lit] * int(np.prod(shape[1:], dtype=np.int64)), tuple(shape[1:])))
    return np.full(shape, value.reshape(-1)[0], dtype=value.dtype)


def _expand(t, args, attrs):
    x, shape = args[0], [int(v) for v in np.asarray(args[1]).reshape(-1)]
    if BATCH in shape[1:]:
        raise UnsupportedOnnxOp("Expand: the batch must be the first axis")
    if not isinstance(x, Lanes):
        if shape and shape[0] == BATCH:
            c = np.asarray(x)
            rank = max(len(shape) - 1, c.ndim - 1)
            c = _align(c, rank, "Expand")
            tail = np.broadcast_shapes(c.shape, tuple(shape[1:]))
            lits = [_literal(t, _scalar(v)) for v in np.broadcast_to(c, tail).reshape(-1)]
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


def _reshape(t, args, attrs):
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


def _axes_arg(args, attrs, idx=1):
    if len(args) > idx and args[idx] is not None:
        return [int(v) for v in np.asarray(args[idx]).reshape(-1)]
    if "axes" in attrs:
        return [int(v) for v in attrs["axes"]]
    return None


def _unsqueeze(t, args, attrs):
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


def _squeeze(t, args, attrs):
    x, axes = args[0], _axes_arg(args, attrs)
    if not isinstance(x, Lanes):
        c = np.asarray(x)
        return np.squeeze(c, axis=None if axes is None else tuple(axes))
    if axes is None:
        return Lanes(np.squeeze(x.a))
    return Lanes(np.squeeze(x.a, axis=tuple(_axis(a, len(x.shape) + 1, "Squeeze")
                                            for a in axes)))


def _concat(t, args, attrs):
    axis = attrs["axis"]
    if not any(isinstance(x, Lanes) for x in args):
        return np.concatenate([np.asarray(x) for x in args], axis=axis)
    if not all(isinstance(x, Lanes) for x in args):
        raise UnsupportedOnnxOp("Concat of batch tensors with constants")
    ax = _axis(axis, len(args[0].shape) + 1, "Concat")
    return Lanes(np.concatenate([x.a for x in args], axis=ax))


def _slice(t, args, attrs):
    x = args[0]
    starts = [int(v) for v in np.asarray(args[1]).reshape(-1)]
    ends = [int(v) for v in np.asarray(args[2]).reshape(-1)]
    rank = x.ndim if not isinstance(x, Lanes) else len(x.shape) + 1
    axes = _axes_arg(args, {}, 3) or list(range(len(starts)))
    steps = [int(v) for v in np.asarray(args[4]).reshape(-1)] if len(args) > 4 and \
        args[4] is not None else [1] * len(starts)
    index = [slice(None)] * rank
    for s, e, a, st in zip(starts, ends, axes, steps):
        a = a + rank if a < 0 else a
        index[a] = slice(s, e, st)
    if not isinstance(x, Lanes):
        return np.asarray(x)[tuple(index)]
    b = index[0]
    if not (b.start in (0, None) and b.step in (1, None) and (b.stop is None or b.stop >= 2**31)):
        raise UnsupportedOnnxOp("Slice: slicing the batch axis is not supported")
    return Lanes(x.a[tuple(index[1:])])


def _gather(t, args, attrs):
    data, idx = args
    axis = attrs.get("axis", 0)
    if not isinstance(idx, Lanes):
        idx = np.asarray(idx)
        if not isinstance(data, Lanes):
            return np.take(np.asarray(data), idx, axis=axis)
        ax = _axis(axis, len(data.shape) + 1, "Gather")
        return Lanes(np.take(data.a, idx, axis=ax))
    if isinstance(data, Lanes):
        raise UnsupportedOnnxOp("Gather from a batch tensor at batch-dependent indices")
    data = np.asarray(data)
    axis = axis + data.ndim if axis < 0 else axis
    if axis != 0:
        raise UnsupportedOnnxOp("Gather of a constant at batch indices needs axis 0")
    k = data.shape[0]
    rest = data.shape[1:]
    cols = data.reshape(k, -1)
    bufs = [t.Float(np.ascontiguousarray(cols[:, j], dtype=np.float32))
            if np.issubdtype(data.dtype, np.floating) else t.Int(cols[:, j].astype(np.int32))
            for j in range(cols.shape[1])]
    kind = t.Float if np.issubdtype(data.dtype, np.floating) else t.Int
    out = []
    for i in idx.a.reshape(-1):
        i = dr.select(i < 0, i + k, i)
        ui = t.UInt(i)
        out.extend(dr.gather(kind, b, ui) for b in bufs)
    return Lanes(_obj(out, idx.shape + rest))


def _reduce(kind):
    def run(t, args, attrs):
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
            fn = {"ReduceSum": np.sum, "ReduceMean": np.mean, "ReduceMax": np.max,
                  "ReduceMin": np.min, "ReduceProd": np.prod,
                  "ReduceL2": lambda v, axis, keepdims: np.sqrt(np.sum(v * v, axis=axis,
                                                                        keepdims=keepdims))}[kind]
            return np.asarray(fn(c, axis=ax, keepdims=keep)).astype(c.dtype)
        rank = len(x.shape) + 1
        tax = tuple(sorted(_axis(a, rank, kind) for a in axes))
        a = x.a
        moved = np.moveaxis(a, tax, tuple(range(len(tax))))
        count = int(np.prod([a.shape[i] for i in tax], dtype=np.int64))
        flat = moved.reshape(count, -1)
        out = []
        for j in range(flat.shape[1]):
            col = list(flat[:, j])
            if kind == "ReduceL2":
                col = [v * v for v in col]
            acc = col[0]
            for v in col[1:]:
                if kind in ("ReduceSum", "ReduceMean", "ReduceL2"):
                    acc = acc + v
                elif kind == "ReduceMax":
                    acc = dr.maximum(acc, v)
                elif kind == "ReduceMin":
                    acc = dr.minimum(acc, v)
                else:
                    acc = acc * v
            if kind == "ReduceMean":
                acc = acc / float(count)
            elif kind == "ReduceL2":
                acc = dr.sqrt(acc)
            out.append(acc)
        shape = [n for i, n in enumerate(a.shape) if i not in tax]
        res = _obj(out, tuple(shape))
        if keep:
            for i in tax:
                res = np.expand_dims(res, i)
        return Lanes(res)
    return run


# Independent partial sums per dot product in _linear.  One chain of K dependent
# multiply-adds is bound by the FMA latency (4 cycles); four chains of K/4 keep the
# FMA units busy.  Measured on a 64-64-64 network (AVX-512, llvm_ad_rgb): 1.4x the
# evaluation rate of one chain; 8 and 16 chains were no faster than 4.
DOT_CHAINS = 4


def _dot(xs, ws, bias):
    """sum_i xs[i] * ws[i] (+ bias) as DOT_CHAINS interleaved FMA chains, summed pairwise."""
    chains = []
    for c in range(min(DOT_CHAINS, len(xs))):
        acc = float(bias) if (c == 0 and bias is not None) else None
        for x, w in zip(xs[c::DOT_CHAINS], ws[c::DOT_CHAINS]):
            acc = x * w if acc is None else dr.fma(x, w, acc)
        chains.append(acc)
    while len(chains) > 1:
        chains = [chains[i] + chains[i + 1] if i + 1 < len(chains) else chains[i]
                  for i in range(0, len(chains), 2)]
    return chains[0]


def _linear(x: Lanes, w: np.ndarray, bias, scale: float) -> Lanes:
    """x (trailing (..., K)) @ w (K, M) * scale + bias (M,) as fused multiply-adds."""
    k, m = w.shape
    if x.shape[-1] != k:
        raise UnsupportedOnnxOp(f"matrix product of width {x.shape[-1]} with weights {w.shape}")
    lead = x.shape[:-1]
    rows = x.a.reshape(-1, k)
    ws = [[float(v) for v in (w[:, j] * scale).astype(np.float32)] for j in range(m)]
    out = []
    for r in range(rows.shape[0]):
        xs = list(rows[r])
        for j in range(m):
            out.append(_dot(xs, ws[j], None if bias is None else bias[j]))
    return Lanes(_obj(out, lead + (m,)))


def _gemm(t, args, attrs):
    a, b = args[0], args[1]
    c = args[2] if len(args) > 2 else None
    alpha, beta = float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0))
    if not isinstance(a, Lanes):
        raise UnsupportedOnnxOp("Gemm of two constants") if not isinstance(b, Lanes) \
            else UnsupportedOnnxOp("Gemm with batch-dependent weights")
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
    return _linear(a, w.astype(np.float32), bias, alpha)


def _matmul(t, args, attrs):
    a, b = args
    if not isinstance(a, Lanes) and not isinstance(b, Lanes):
        return np.matmul(a, b)
    if isinstance(b, Lanes) or np.ndim(b) != 2:
        raise UnsupportedOnnxOp("MatMul needs constant 2-D weights on the right")
    return _linear(a, np.asarray(b, np.float32), None, 1.0)


def _transpose(t, args, attrs):
    x = args[0]
    perm = attrs.get("perm")
    if not isinstance(x, Lanes):
        return np.transpose(x, perm)
    if perm is None or perm[0] != 0:
        raise UnsupportedOnnxOp("Transpose that moves the batch axis")
    return Lanes(np.transpose(x.a, [p - 1 for p in perm[1:]]))


_OPS = {op: _unary(op) for op in _UNARY}
_OPS.update({op: _binary(op) for op in _BINARY})
_OPS.update({op: _variadic(op) for op in _VARIADIC})
_OPS.update({op: _reduce(op) for op in ("ReduceSum", "ReduceMean", "ReduceMax", "ReduceMin",
                                          "ReduceProd", "ReduceL2")})
_OPS.update({
    "Div": _div, "Where": _where, "Clip": _clip, "Cast": _cast, "Constant": _constant,
    "Shape": _shape, "ConstantOfShape": _constant_of_shape, "Expand": _expand,
    "Reshape": _reshape, "Unsqueeze": _unsqueeze, "Squeeze": _squeeze, "Concat": _concat,
    "Slice": _slice, "Gather": _gather, "Gemm": _gemm, "MatMul": _matmul,
    "Transpose": _transpose, "Dropout": lambda t, args, attrs: args[0],
})
SUPPORTED_OPS = frozenset(_OPS)


# ====================================================================== BSDF plugins
def _black(wi, wo):
    return mi.Color3f(0.0)


class _GraphBSDF(mi.BSDF):
    """A BSDF evaluated by an ONNX graph (f, no cosine) with the mixture sampler."""

    def _setup(self, program: OnnxProgram, lobe: dict, label: str):
        if not dr.is_jit_v(mi.Float):
            raise InputError(f"{label}: needs a JIT variant (llvm_ad_rgb, cuda_ad_rgb, ...); "
                             f"the interpreter traces Dr.Jit arrays, and {mi.variant()} has none")
        if program.inputs != list(INPUTS) or program.outputs != [OUTPUT]:
            raise InputError(f"{label}: expected inputs {list(INPUTS)} and output {OUTPUT!r}, "
                             f"got {program.inputs} -> {program.outputs}")
        self.program = program
        self.lobe = dict(lobe)
        self.label = label
        self.lobe_weight = float(lobe["weight"])
        self.distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, float(lobe["alpha"]), True)
        flags = (mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection
                 | mi.BSDFFlags.FrontSide)
        self.m_components = [flags]
        self.m_flags = flags

    # -- the three traced pieces; sample() reuses them so that weight == eval / pdf
    def _f_cos(self, si, wo, active):
        cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
        valid = active & (cos_i > 0.0) & (cos_o > 0.0)
        # The graph runs inside a conditional, which Dr.Jit skips for a SIMD packet
        # (LLVM) or warp (CUDA) where no lane needs it: the unlit side of a light,
        # light samples below the horizon, paths that left the surface.
        return dr.if_stmt((si.wi, wo), valid, self._graph_f_cos, _black, label="graph")

    def _graph_f_cos(self, wi, wo):
        out = self.program(wi=[wi.x, wi.y, wi.z], wo=[wo.x, wo.y, wo.z])[OUTPUT]
        return mi.Color3f(out[0], out[1], out[2]) * mi.Frame3f.cos_theta(wo)

    def _pdf(self, si, wo, active):
        wi = si.wi
        cos_i, cos_o = mi.Frame3f.cos_theta(wi), mi.Frame3f.cos_theta(wo)
        valid = active & (cos_i > 0.0) & (cos_o > 0.0)
        p = (1.0 - self.lobe_weight) * mi.warp.square_to_cosine_hemisphere_pdf(wo)
        if self.lobe_weight > 0.0:        # a Python float: decided once, not per lane
            m = dr.normalize(wi + wo)
            dot_om = dr.dot(wo, m)
            p_m = self.distr.pdf(wi, m)
            p_ggx = dr.select(dot_om > 0.0, p_m / (4.0 * dot_om), 0.0)
            p = p + self.lobe_weight * p_ggx
        return dr.select(valid, p, 0.0)

    def _enabled(self, ctx) -> bool:
        return ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0) or \
            ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0)

    def eval(self, ctx, si, wo, active=True):
        if not self._enabled(ctx):
            return mi.Color3f(0.0)
        return self._f_cos(si, wo, active)

    def pdf(self, ctx, si, wo, active=True):
        if not self._enabled(ctx):
            return mi.Float(0.0)
        return self._pdf(si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        if not self._enabled(ctx):
            return mi.Color3f(0.0), mi.Float(0.0)
        return self._f_cos(si, wo, active), self._pdf(si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = dr.zeros(mi.BSDFSample3f)
        if not self._enabled(ctx):
            return bs, mi.Color3f(0.0)
        wi = si.wi
        wo = mi.warp.square_to_cosine_hemisphere(sample2)
        glossy = mi.Bool(False)
        if self.lobe_weight > 0.0:
            m, _ = self.distr.sample(wi, sample2)
            glossy = sample1 < self.lobe_weight
            wo = dr.select(glossy, mi.reflect(wi, m), wo)
        active = active & (mi.Frame3f.cos_theta(wi) > 0.0)
        pdf = self._pdf(si, wo, active)
        value = self._f_cos(si, wo, active)
        ok = active & (pdf > 0.0)
        bs.wo = wo
        bs.pdf = dr.select(ok, pdf, 0.0)
        bs.eta = 1.0
        # which lobe of the mixture drew the sample (integrators such as the path
        # guiders and AOVs read it); both lobes are component 0 of the one BSDF
        bs.sampled_type = dr.select(glossy, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                    mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
        bs.sampled_component = mi.UInt32(0)
        return bs, dr.select(ok, value / pdf, 0.0)

    def traverse(self, callback):
        pass

    def to_string(self):
        return (f"{type(self).__name__}[{self.label}, sampling lobe GGX alpha="
                f"{self.lobe['alpha']:.4g} weight={self.lobe_weight:.3g} "
                f"({self.lobe_source})]")


def _resolve(filename: str) -> Path:
    path = Path(filename)
    if not path.is_absolute():
        # Mitsuba's resolver holds the scene file's folder while an XML scene loads.
        # mi.file_resolver() replaced Thread.file_resolver() (deprecated in 3.9, whose
        # warning escapes from a plugin constructor as a SystemError).
        resolver = (mi.file_resolver() if hasattr(mi, "file_resolver")
                    else mi.Thread.thread().file_resolver())
        resolved = Path(str(resolver.resolve(str(path))))
        if resolved.is_file():
            path = resolved
    if not path.is_file():
        raise InputError(f"neural_brdf: {filename}: no such model file")
    return path


def read_model(filename) -> tuple[Path, OnnxProgram, dict | None]:
    """Resolve, load and check an exported model: (path, program, stored lobe or None).

    A missing or unusable file raises a one-line InputError.  :func:`render_preview`
    calls this before it loads a scene, because Mitsuba reports an exception raised in a
    plugin's constructor as a RuntimeError carrying the Python traceback."""
    path = _resolve(str(filename))
    try:
        proto = onnx.load(str(path))
    except Exception as e:       # onnx raises DecodeError and others on a bad file
        raise InputError(f"neural_brdf: {path}: not a loadable ONNX model "
                         f"({type(e).__name__})") from None
    try:
        stored = lobes.from_metadata({p.key: p.value for p in proto.metadata_props})
    except InputError as e:
        raise InputError(f"neural_brdf: {path}: {e}") from None
    return path, OnnxProgram(proto), stored


class NeuralBSDF(_GraphBSDF):
    """``{'type': 'neural_brdf', 'filename': 'model.onnx'}``: an exported neural BRDF."""

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        if "filename" not in props:
            raise InputError("neural_brdf: the 'filename' property (an ONNX file) is required")
        path, program, stored = read_model(props["filename"])
        self.lobe_source = "metadata" if stored else "fitted at load"
        self._setup(program, stored or lobes.fit_onnx(path), str(path))


def analytic_onnx(model: str, params: dict | None = None) -> bytes:
    """The analytic model's own torch ``f(wi, wo)`` exported to ONNX bytes (the contract
    of :mod:`neural_brdf.export`: inputs wi, wo [N, 3], output f [N, 3], no cosine)."""
    import torch

    import analytic

    brdf = analytic.create(model, **(params or {}))

    class _F(torch.nn.Module):
        def forward(self, wi, wo):
            return brdf.f(wi, wo).float()

    buf = io.BytesIO()
    with warnings.catch_warnings():
        # The TorchScript exporter warns that it is deprecated (and about traced Python
        # values); it is used as neural_brdf.export uses it: one file, no onnxscript.
        warnings.simplefilter("ignore")
        torch.onnx.export(_F(), (torch.zeros(4, 3), torch.zeros(4, 3)), buf, dynamo=False,
                          opset_version=17, input_names=list(INPUTS), output_names=[OUTPUT],
                          dynamic_axes={"wi": {0: "N"}, "wo": {0: "N"}, OUTPUT: {0: "N"}})
    return buf.getvalue()


def _analytic_params(props) -> tuple[str, dict]:
    model = props["model"] if "model" in props else None
    if not model:
        raise InputError("analytic_brdf: the 'model' property is required")
    params = {}
    if "params" in props:
        try:
            params = json.loads(props["params"])
        except json.JSONDecodeError as e:
            raise InputError(f"analytic_brdf: 'params' is not valid JSON ({e})") from None
        if not isinstance(params, dict):
            raise InputError(f"analytic_brdf: 'params' must be a JSON object, got {params!r}")
    for key in props.keys():
        if key in ("model", "params", "type", "id"):
            continue
        value = props[key]
        if isinstance(value, (bool, int, float, str)):
            params[key] = value
        else:           # an RGB colour or a vector
            params[key] = [float(v) for v in value]
    return str(model), params


class AnalyticBSDF(_GraphBSDF):
    """``{'type': 'analytic_brdf', 'model': 'microfacet', 'params': '{...}'}``; parameters
    may also be given as plugin properties (``'alpha': 0.3``)."""

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        model, params = _analytic_params(props)
        payload = analytic_onnx(model, params)
        label = f"analytic {model} {json.dumps(params, sort_keys=True)}"
        self.lobe_source = "fitted at load"
        self._setup(OnnxProgram(payload), lobes.fit_onnx(payload), label)


mi.register_bsdf("neural_brdf", lambda props: NeuralBSDF(props))
mi.register_bsdf("analytic_brdf", lambda props: AnalyticBSDF(props))


# ====================================================================== preview render
def sky_bitmap(height: int = 64) -> np.ndarray:
    """A procedural lat-long environment (H, 2H, 3): a sky gradient over a dark ground.

    Rows run from the zenith (+y, Mitsuba's envmap up axis) to the nadir."""
    v = (np.arange(height) + 0.5) / height
    elev = (0.5 - v)[:, None] * math.pi                                   # (H, 1)
    horizon = np.array([1.0, 0.95, 0.85])
    zenith = np.array([0.25, 0.45, 0.9])
    ground = np.array([0.18, 0.16, 0.14])
    s = np.clip(np.sin(elev), 0.0, 1.0)[..., None]
    sky = horizon * (1.0 - s) + zenith * s
    img = np.where(elev[..., None] > 0, sky, ground)
    img = np.broadcast_to(img, (height, 2 * height, 3)) + 0.05            # a constant fill
    return np.ascontiguousarray(img, dtype=np.float32)


def preview_scene(bsdf: dict, *, resolution: int = 256, spp: int = 64, max_depth: int = 8,
                  seed: int = 0) -> dict:
    """The material-preview scene (a dict for ``mi.load_dict``): two spheres with ``bsdf``
    on a grey checkerboard floor, under :func:`sky_bitmap` and a directional key light."""
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": {
            "type": "perspective", "fov": 32.0,
            "to_world": T().look_at(origin=[0.0, 1.6, 6.5], target=[0.2, 0.1, 0.0],
                                    up=[0.0, 1.0, 0.0]),
            "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
            "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                     "rfilter": {"type": "gaussian"}},
        },
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap()), "scale": 1.0},
        "key": {"type": "directional", "direction": [-0.6, -1.0, -0.5],
                "irradiance": {"type": "rgb", "value": [2.5, 2.4, 2.2]}},
        "big": {"type": "sphere", "center": [-0.3, 0.0, 0.0], "radius": 1.0, "bsdf": bsdf},
        "small": {"type": "sphere", "center": [1.35, -0.5, 0.9], "radius": 0.5, "bsdf": bsdf},
        "floor": {
            "type": "rectangle",
            "to_world": T().translate([0.0, -1.0, 0.0]).rotate([1.0, 0.0, 0.0], -90.0)
            .scale(8.0),
            "bsdf": {"type": "diffuse", "reflectance": {
                "type": "checkerboard", "color0": {"type": "rgb", "value": 0.25},
                "color1": {"type": "rgb", "value": 0.5},
                "to_uv": mi.ScalarTransform4f().scale([8.0, 8.0, 1.0])}},
        },
    }


def render_scene(bsdf: dict, *, resolution: int = 256, spp: int = 64, seed: int = 0) -> np.ndarray:
    """Render :func:`preview_scene` with ``bsdf``; linear RGB (H, W, 3) float32."""
    scene = mi.load_dict(preview_scene(bsdf, resolution=resolution, spp=spp, seed=seed))
    img = mi.render(scene, spp=spp, seed=seed)
    return np.asarray(img, dtype=np.float32)[..., :3]


def to_display(linear: np.ndarray) -> np.ndarray:
    """Linear RGB -> sRGB display values in [0, 1] (Mitsuba's own conversion)."""
    bmp = mi.Bitmap(np.ascontiguousarray(np.clip(linear, 0.0, None), dtype=np.float32))
    srgb = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=True)
    return np.clip(np.asarray(srgb), 0.0, 1.0)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two display images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


# The error map shows |neural - reference| (display values, channel mean) times this.
ERROR_GAIN = 10.0


def write_png(path: Path, img: np.ndarray) -> None:
    import matplotlib.image

    with atomic_path(path, suffix=".png", parents=True) as tmp:
        matplotlib.image.imsave(tmp, np.clip(img, 0.0, 1.0))


def analytic_bsdf(reference: dict) -> dict:
    """The ``analytic_brdf`` plugin dict of an analytic target (``{"model": name,
    "params": {...}}``, as in a training config)."""
    if "model" not in reference:
        raise InputError(f"reference: expected {{'model': name, 'params': {{...}}}}, "
                         f"got {reference!r}")
    return {"type": "analytic_brdf", "model": reference["model"],
            "params": json.dumps(reference.get("params") or {})}


def side_by_side(neural: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Display images -> neural | reference | error map (|difference| of display values,
    channel mean, x ERROR_GAIN, 'inferno' colours), with thin white gaps."""
    import matplotlib

    err = np.abs(neural - ref).mean(-1) * ERROR_GAIN
    err_rgb = matplotlib.colormaps["inferno"](np.clip(err, 0.0, 1.0))[..., :3]
    gap = np.ones((neural.shape[0], max(2, neural.shape[0] // 64), 3))
    return np.concatenate([neural, gap, ref, gap, err_rgb], axis=1)


def render_preview(onnx_path, out_png, *, reference: dict | None = None, spp: int = 64,
                   resolution: int = 256) -> float | None:
    """Render the neural BRDF in the preview scene and write ``out_png``.

    With ``reference`` (an analytic target, see :func:`analytic_bsdf`) the PNG is
    :func:`side_by_side` and the PSNR (dB, sRGB display values) of neural against
    reference is returned; otherwise None.
    """
    path, _, _ = read_model(onnx_path)
    ref_bsdf = None if reference is None else analytic_bsdf(reference)
    neural = to_display(render_scene({"type": "neural_brdf", "filename": str(path)},
                                     resolution=resolution, spp=spp))
    if ref_bsdf is None:
        write_png(Path(out_png), neural)
        return None
    ref = to_display(render_scene(ref_bsdf, resolution=resolution, spp=spp))
    write_png(Path(out_png), side_by_side(neural, ref))
    return psnr(neural, ref)
