"""An exported ONNX graph lowered once to a flat list of scalar-per-lane instructions.

    from neural_brdf import graph
    prog = graph.lower("model.onnx")           # a path, bytes or an onnx.ModelProto
    prog.outputs                               # {"f": [id_r, id_g, id_b]}
    for i, ins in enumerate(prog.instrs):      # SSA: ins.args are earlier indices
        print(prog.names[i], ins.op, ins.dtype, ins.args, ins.attr)

Every back end (:mod:`neural_brdf.backends`: Dr.Jit, C, GLSL, WGSL) evaluates THIS list,
so they all evaluate the exported graph, never a retyped copy of the model.

Lowering.  The graph is walked node by node once.  Constant sub-graphs (weights, shape
arithmetic) are folded with numpy.  A tensor of shape [N, k...] that depends on the
inputs is held as a numpy object array of shape (k...) whose elements are instruction
ids, one per column (the batch N is implicit: every instruction is evaluated per lane).
A Gemm or MatMul with constant weights becomes, per output column, DOT_CHAINS
interleaved fused multiply-add chains with the weights as literal constants.  A Gather
from a constant table at computed indices (the albedo-table look-up) becomes one
``gather`` instruction per table column.  The instruction list is deduplicated (equal
instructions share one id), folded (an instruction of constants is computed in float32
numpy) and pruned to what the outputs need.

Instruction set (``Instr.op``; dtypes "float" (float32), "int" (int32), "bool"):

    input     attr (name, column)                     -> float
    const     attr the value (a Python float/int/bool)
    UNARY     neg abs sqrt exp log floor ceil sin cos atan asin acos tanh erf
    BINARY    add sub mul div max min pow              (float, or int except div/pow)
    COMPARE   eq lt le gt ge                           -> bool
    LOGIC     and or xor (bool), not (bool)
    isnan, isinf                                       float -> bool
    fma       a * b + c
    select    cond ? a : b
    cast      attr the target dtype
    gather    args (index,), attr the table number: tables[attr][clamp(index, 0, K - 1)]

An op outside :data:`SUPPORTED_OPS`, or in a form the lowering lacks, raises
:class:`UnsupportedOnnxOp` (an InputError) naming the node and the op.  This module
imports numpy and onnx only.
"""

from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass, field

import numpy as np
import onnx
from onnx import numpy_helper

from .errors import InputError

# A shape vector (the value of an ONNX Shape op) holds this in place of the batch size N,
# which is unknown while lowering.  Far from -1 and 0, which Reshape and Expand give
# meanings of their own; multiplying it by -1 (torch's Expand pattern) cannot give -1.
BATCH = -(1 << 40)

# Independent partial sums per dot product.  One chain of K dependent multiply-adds is
# bound by the FMA latency (4 cycles); four chains of K/4 keep the FMA units busy.
# Measured on a 64-64-64 network (AVX-512, Dr.Jit llvm_ad_rgb): 1.4x the evaluation
# rate of one chain; 8 and 16 chains were no faster than 4.
DOT_CHAINS = 4

UNARY = (
    "neg",
    "abs",
    "sqrt",
    "exp",
    "log",
    "floor",
    "ceil",
    "sin",
    "cos",
    "atan",
    "asin",
    "acos",
    "tanh",
    "erf",
)
BINARY = ("add", "sub", "mul", "div", "max", "min", "pow")
COMPARE = ("eq", "lt", "le", "gt", "ge")
LOGIC = ("and", "or", "xor")
OPS = frozenset(
    UNARY
    + BINARY
    + COMPARE
    + LOGIC
    + ("input", "const", "not", "isnan", "isinf", "fma", "select", "cast", "gather")
)


class UnsupportedOnnxOp(InputError):
    """The graph uses an op (or an op in a form) that the lowering lacks."""


@dataclass(frozen=True)
class Instr:
    op: str
    dtype: str  # "float" | "int" | "bool"
    args: tuple[int, ...] = ()
    attr: object = None


@dataclass
class Program:
    """A lowered graph: SSA instructions, readable names, constant tables, outputs."""

    instrs: list[Instr]
    names: list[str]
    tables: list[np.ndarray]  # 1-D float32 or int32 arrays
    inputs: dict[str, int]  # input name -> width (columns)
    outputs: dict[str, list[int]]  # output name -> instruction id per column
    metadata: dict[str, str] = field(default_factory=dict)
    op_counts: dict[str, int] = field(default_factory=dict)  # ONNX ops of the source graph

    def count(self) -> dict[str, int]:
        """Instructions per op."""
        out: dict[str, int] = {}
        for ins in self.instrs:
            out[ins.op] = out.get(ins.op, 0) + 1
        return out


def _np_dtype(dtype: str):
    return {"float": np.float32, "int": np.int32, "bool": np.bool_}[dtype]


def _kind(value) -> str:
    v = np.asarray(value)
    if v.dtype == np.bool_:
        return "bool"
    if np.issubdtype(v.dtype, np.integer):
        return "int"
    return "float"


def _fold(op: str, dtype: str, vals: list, attr):
    """An instruction of constants, computed in numpy at the instruction's precision."""
    a = [np.asarray(v, dtype=_np_dtype(_kind(v))) for v in vals]
    with np.errstate(all="ignore"):
        if op in UNARY:
            if op == "erf":
                return None  # numpy lacks erf: keep it an instruction
            fn = {
                "neg": np.negative,
                "abs": np.abs,
                "sqrt": np.sqrt,
                "exp": np.exp,
                "log": np.log,
                "floor": np.floor,
                "ceil": np.ceil,
                "sin": np.sin,
                "cos": np.cos,
                "atan": np.arctan,
                "asin": np.arcsin,
                "acos": np.arccos,
                "tanh": np.tanh,
            }[op]
            r = fn(a[0])
        elif op in (
            "add",
            "sub",
            "mul",
            "max",
            "min",
            "pow",
            "div",
            "eq",
            "lt",
            "le",
            "gt",
            "ge",
            "and",
            "or",
            "xor",
        ):
            fn = {
                "add": np.add,
                "sub": np.subtract,
                "mul": np.multiply,
                "max": np.maximum,
                "min": np.minimum,
                "pow": np.power,
                "div": np.divide,
                "eq": np.equal,
                "lt": np.less,
                "le": np.less_equal,
                "gt": np.greater,
                "ge": np.greater_equal,
                "and": np.logical_and,
                "or": np.logical_or,
                "xor": np.logical_xor,
            }[op]
            r = fn(a[0], a[1])
        elif op == "not":
            r = np.logical_not(a[0])
        elif op == "isnan":
            r = np.isnan(a[0])
        elif op == "isinf":
            r = np.isinf(a[0])
        elif op == "fma":
            r = a[0] * a[1] + a[2]
        elif op == "select":
            r = a[1] if bool(a[0]) else a[2]
        elif op == "cast":
            r = a[0]
        else:
            return None
    return _py(np.asarray(r).astype(_np_dtype(dtype)))


def _py(v):
    """A numpy scalar -> a Python scalar (bool, int or float holding a float32 value)."""
    v = np.asarray(v).reshape(())
    if v.dtype == np.bool_:
        return bool(v)
    if np.issubdtype(v.dtype, np.integer):
        return int(v)
    return float(np.float32(v))


class Builder:
    """Appends instructions with folding and deduplication; ``hint`` names new ones."""

    def __init__(self):
        self.instrs: list[Instr] = []
        self.hints: list[str] = []
        self.memo: dict[tuple, int] = {}
        self.tables: list[np.ndarray] = []
        self.table_memo: dict[bytes, int] = {}
        self.hint = "t"

    def _add(self, ins: Instr) -> int:
        key = (
            ins.op,
            ins.dtype,
            ins.args,
            struct.pack("<f", ins.attr) if isinstance(ins.attr, float) else ins.attr,
        )
        if key in self.memo:
            return self.memo[key]
        self.instrs.append(ins)
        self.hints.append(self.hint)
        self.memo[key] = len(self.instrs) - 1
        return len(self.instrs) - 1

    def const(self, value, dtype: str | None = None) -> int:
        dtype = dtype or _kind(value)
        return self._add(Instr("const", dtype, (), _py(np.asarray(value).astype(_np_dtype(dtype)))))

    def input(self, name: str, column: int) -> int:
        return self._add(Instr("input", "float", (), (name, column)))

    def is_const(self, i: int) -> bool:
        return self.instrs[i].op == "const"

    def value(self, i: int):
        return self.instrs[i].attr

    def dtype(self, i: int) -> str:
        return self.instrs[i].dtype

    def emit(self, op: str, *args: int, attr=None) -> int:
        """One instruction; its dtype follows from the op and the arguments."""
        if op in COMPARE or op in ("isnan", "isinf", "not") or op in LOGIC:
            dtype = "bool"
        elif op == "cast":
            dtype = attr
        elif op == "select":
            dtype = self.dtype(args[1])
        elif op == "gather":
            dtype = "float" if self.tables[attr].dtype == np.float32 else "int"
        else:
            dtype = self.dtype(args[0])
        if op == "cast" and self.dtype(args[0]) == attr:
            return args[0]
        if all(self.is_const(a) for a in args) and op != "gather":
            folded = _fold(op, dtype, [self.value(a) for a in args], attr)
            if folded is not None:
                return self.const(folded, dtype)
        if op == "select" and self.is_const(args[0]):
            return args[1] if self.value(args[0]) else args[2]
        return self._add(Instr(op, dtype, tuple(args), attr))

    def table(self, values: np.ndarray) -> int:
        key = values.dtype.str.encode() + values.tobytes()
        if key not in self.table_memo:
            self.tables.append(values)
            self.table_memo[key] = len(self.tables) - 1
        return self.table_memo[key]

    # -- conveniences for hand-written programs (the sampling lobe)
    def scalar(self, v: float) -> int:
        return self.const(float(v), "float")

    def finish(
        self,
        inputs: dict[str, int],
        outputs: dict[str, list[int]],
        metadata: dict | None = None,
        op_counts: dict | None = None,
    ) -> Program:
        """Prune to what the outputs need, renumber, name."""
        live = set()
        stack = [i for cols in outputs.values() for i in cols]
        while stack:
            i = stack.pop()
            if i in live:
                continue
            live.add(i)
            stack.extend(self.instrs[i].args)
        order = sorted(live)
        new = {old: k for k, old in enumerate(order)}
        instrs = [
            Instr(
                self.instrs[i].op,
                self.instrs[i].dtype,
                tuple(new[a] for a in self.instrs[i].args),
                self.instrs[i].attr,
            )
            for i in order
        ]
        used_tables = sorted({ins.attr for ins in instrs if ins.op == "gather"})
        tmap = {old: k for k, old in enumerate(used_tables)}
        instrs = [
            Instr(ins.op, ins.dtype, ins.args, tmap[ins.attr]) if ins.op == "gather" else ins
            for ins in instrs
        ]
        names, counters = [], {}
        for i, ins in zip(order, instrs, strict=True):
            if ins.op == "input":
                name, col = ins.attr
                names.append(
                    f"{name}_{'xyzw'[col]}" if inputs.get(name, 1) <= 4 else f"{name}_{col}"
                )
            elif ins.op == "const":
                names.append("")
            else:
                h = self.hints[i]
                counters[h] = counters.get(h, -1) + 1
                names.append(f"{h}{counters[h]}")
        return Program(
            instrs,
            names,
            [self.tables[t] for t in used_tables],
            dict(inputs),
            {k: [new[i] for i in v] for k, v in outputs.items()},
            dict(metadata or {}),
            dict(op_counts or {}),
        )


# ====================================================================== lowering
class Lanes:
    """A tensor of shape (N,) + ``a.shape``: ``a`` is an object array of instruction ids."""

    __slots__ = ("a",)

    def __init__(self, a):
        if not isinstance(a, np.ndarray):  # numpy indexing returned one element
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


def _align(c: np.ndarray, rank: int, op: str) -> np.ndarray:
    """A constant broadcast against a lane tensor of trailing rank ``rank``.

    Its full shape is (N,) + trailing, so a constant of rank ``rank + 1`` lines up its
    first axis with the batch and must have size 1 there."""
    while c.ndim > rank:
        if c.shape[0] != 1:
            raise UnsupportedOnnxOp(
                f"{op}: a constant of shape {c.shape} does not broadcast "
                f"against a batch tensor of rank {rank + 1}"
            )
        c = c[0]
    return c


def _axis(axis: int, rank: int, op: str) -> int:
    """A full-rank axis (batch is axis 0) -> the trailing axis of a lane tensor."""
    a = axis + rank if axis < 0 else axis
    if not 0 <= a < rank:
        raise UnsupportedOnnxOp(f"{op}: axis {axis} out of range for rank {rank}")
    if a == 0:
        raise UnsupportedOnnxOp(f"{op}: operating along the batch axis is not supported")
    return a - 1


def _axes_arg(args, attrs, idx=1):
    if len(args) > idx and args[idx] is not None:
        return [int(v) for v in np.asarray(args[idx]).reshape(-1)]
    if "axes" in attrs:
        return [int(v) for v in attrs["axes"]]
    return None


_ONNX_FLOAT, _ONNX_INT32, _ONNX_INT64, _ONNX_BOOL, _ONNX_DOUBLE = 1, 6, 7, 9, 11
_NP_TYPES = {
    _ONNX_FLOAT: np.float32,
    _ONNX_DOUBLE: np.float64,
    _ONNX_INT32: np.int32,
    _ONNX_INT64: np.int64,
    _ONNX_BOOL: np.bool_,
}
_IR_TYPES = {
    _ONNX_FLOAT: "float",
    _ONNX_DOUBLE: "float",
    _ONNX_INT32: "int",
    _ONNX_INT64: "int",
    _ONNX_BOOL: "bool",
}


def _np_softplus(x):
    return np.logaddexp(np.zeros_like(x), x)


def _np_div(a, b):
    if np.issubdtype(np.asarray(a).dtype, np.integer):
        return (np.sign(a) * np.sign(b) * (np.abs(a) // np.abs(b))).astype(np.asarray(a).dtype)
    return np.divide(a, b)


_NP_UNARY = {
    "Identity": lambda x: x,
    "Neg": np.negative,
    "Abs": np.abs,
    "Sqrt": np.sqrt,
    "Exp": np.exp,
    "Log": np.log,
    "Floor": np.floor,
    "Ceil": np.ceil,
    "Sin": np.sin,
    "Cos": np.cos,
    "Atan": np.arctan,
    "Asin": np.arcsin,
    "Acos": np.arccos,
    "Tanh": np.tanh,
    "Erf": None,
    "Reciprocal": lambda x: (1.0 / x).astype(x.dtype),
    "Relu": lambda x: np.maximum(x, 0).astype(x.dtype),
    "Sigmoid": lambda x: (1.0 / (1.0 + np.exp(-x))).astype(x.dtype),
    "Softplus": _np_softplus,
    "Not": np.logical_not,
    "IsNaN": np.isnan,
    "IsInf": np.isinf,
}
_NP_BINARY = {
    "Add": np.add,
    "Sub": np.subtract,
    "Mul": np.multiply,
    "Pow": lambda a, b: np.power(a, b).astype(a.dtype),
    "Div": _np_div,
    "Equal": np.equal,
    "Greater": np.greater,
    "Less": np.less,
    "GreaterOrEqual": np.greater_equal,
    "LessOrEqual": np.less_equal,
    "And": np.logical_and,
    "Or": np.logical_or,
    "Xor": np.logical_xor,
    "Max": np.maximum,
    "Min": np.minimum,
    "Sum": np.add,
}
_IR_BINARY = {
    "Add": "add",
    "Sub": "sub",
    "Mul": "mul",
    "Div": "div",
    "Max": "max",
    "Min": "min",
    "Sum": "add",
    "Equal": "eq",
    "Greater": "gt",
    "Less": "lt",
    "GreaterOrEqual": "ge",
    "LessOrEqual": "le",
    "And": "and",
    "Or": "or",
    "Xor": "xor",
}
_IR_UNARY = {
    "Neg": "neg",
    "Abs": "abs",
    "Sqrt": "sqrt",
    "Exp": "exp",
    "Log": "log",
    "Floor": "floor",
    "Ceil": "ceil",
    "Sin": "sin",
    "Cos": "cos",
    "Atan": "atan",
    "Asin": "asin",
    "Acos": "acos",
    "Tanh": "tanh",
    "Erf": "erf",
    "Not": "not",
    "IsNaN": "isnan",
    "IsInf": "isinf",
}


class Lowering:
    """Walks the graph: numpy arrays for constants, :class:`Lanes` for batch tensors."""

    def __init__(self, b: Builder):
        self.b = b

    # -- elementwise
    def ids(self, x: Lanes | np.ndarray, rank: int, op: str) -> np.ndarray:
        if isinstance(x, Lanes):
            return x.a
        c = _align(np.asarray(x), rank, op)
        return _obj([self.b.const(v) for v in c.reshape(-1)], c.shape)

    def elementwise(self, op: str, fn_np, fn_ir, *xs):
        """numpy on constants; fn_ir(*ids) -> id per column otherwise."""
        if not any(isinstance(x, Lanes) for x in xs):
            if fn_np is None:
                raise UnsupportedOnnxOp(f"{op} of a constant")
            return fn_np(*xs)
        rank = max(len(x.shape) for x in xs if isinstance(x, Lanes))
        objs = [self.ids(x, rank, op) for x in xs]
        shape = np.broadcast_shapes(*(o.shape for o in objs))
        objs = [np.broadcast_to(o, shape) for o in objs]
        out = np.empty(shape, dtype=object)
        for idx in np.ndindex(*shape):
            out[idx] = fn_ir(*(o[idx] for o in objs))
        return Lanes(out)

    # -- scalar helpers (ids in, id out)
    def softplus(self, x: int) -> int:
        """log(1 + exp(x)), stable: max(x, 0) + log1p(exp(-|x|)).

        log1p(e) is evaluated as log(u) * e / (u - 1) with u = 1 + e (Goldberg 1991,
        "What every computer scientist should know about floating-point", Theorem 4),
        accurate to a few ulps where log(1 + e) alone would round e away."""
        b = self.b
        e = b.emit("exp", b.emit("neg", b.emit("abs", x)))
        u = b.emit("add", b.scalar(1.0), e)
        ratio = b.emit("div", e, b.emit("sub", u, b.scalar(1.0)))
        log1p = b.emit(
            "select", b.emit("eq", u, b.scalar(1.0)), e, b.emit("mul", b.emit("log", u), ratio)
        )
        return b.emit("add", b.emit("max", x, b.scalar(0.0)), log1p)

    def power(self, x: int, y: int) -> int:
        """x ** y; the exponents torch emits as constants (2, 0.5, ...) stay exact."""
        b = self.b
        if b.is_const(y) and not b.is_const(x):
            v = float(b.value(y))
            if v == 1.0:
                return x
            if v == 2.0:
                return b.emit("mul", x, x)
            if v == 3.0:
                return b.emit("mul", b.emit("mul", x, x), x)
            if v == 0.5:
                return b.emit("sqrt", x)
            if v == -1.0:
                return b.emit("div", b.scalar(1.0), x)
            y = b.scalar(v)
        return b.emit("pow", x, y)

    def div(self, x: int, y: int) -> int:
        if self.b.dtype(x) != "float" or self.b.dtype(y) != "float":
            raise UnsupportedOnnxOp("Div: integer division of batch tensors is not supported")
        return self.b.emit("div", x, y)

    def unary(self, op: str, x: int) -> int:
        b = self.b
        if op == "Identity":
            return x
        if op == "Reciprocal":
            return b.emit("div", b.scalar(1.0), x)
        if op == "Relu":
            return b.emit("max", x, b.scalar(0.0))
        if op == "Sigmoid":
            return b.emit(
                "div", b.scalar(1.0), b.emit("add", b.scalar(1.0), b.emit("exp", b.emit("neg", x)))
            )
        if op == "Softplus":
            return self.softplus(x)
        return b.emit(_IR_UNARY[op], x)

    def binary(self, op: str, x: int, y: int) -> int:
        if op == "Pow":
            return self.power(x, y)
        if op == "Div":
            return self.div(x, y)
        return self.b.emit(_IR_BINARY[op], x, y)

    def to_float(self, x: int) -> int:
        return self.b.emit("cast", x, attr="float")

    # -- linear algebra
    def dot(self, xs: list[int], ws: list[float], bias) -> int:
        """sum_i xs[i] * ws[i] (+ bias) as DOT_CHAINS interleaved FMA chains, summed
        pairwise."""
        b = self.b
        chains = []
        for c in range(min(DOT_CHAINS, len(xs))):
            acc = b.scalar(bias) if (c == 0 and bias is not None) else None
            for x, w in zip(xs[c::DOT_CHAINS], ws[c::DOT_CHAINS], strict=True):
                acc = (
                    b.emit("mul", x, b.scalar(w))
                    if acc is None
                    else b.emit("fma", x, b.scalar(w), acc)
                )
            chains.append(acc)
        while len(chains) > 1:
            chains = [
                b.emit("add", chains[i], chains[i + 1]) if i + 1 < len(chains) else chains[i]
                for i in range(0, len(chains), 2)
            ]
        return chains[0]

    def linear(self, x: Lanes, w: np.ndarray, bias, scale: float) -> Lanes:
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
                out.append(self.dot(xs, ws[j], None if bias is None else float(bias[j])))
        return Lanes(_obj(out, lead + (m,)))


# ---------------------------------------------------------------------- op kernels
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
    floating = np.issubdtype(data.dtype, np.floating)
    tables = [
        b.table(np.ascontiguousarray(cols[:, j], dtype=np.float32 if floating else np.int32))
        for j in range(cols.shape[1])
    ]
    out = []
    for i in idx.a.reshape(-1):
        i = b.emit("cast", i, attr="int")
        i = b.emit(
            "select", b.emit("lt", i, b.const(0, "int")), b.emit("add", i, b.const(k, "int")), i
        )
        out.extend(b.emit("gather", i, attr=t) for t in tables)
    return Lanes(_obj(out, idx.shape + rest))


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


def _gemm(lo, args, attrs):
    a, b = args[0], args[1]
    c = args[2] if len(args) > 2 else None
    alpha, beta = float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0))
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


def load(model) -> onnx.ModelProto:
    """A path, bytes or ModelProto -> ModelProto (a one-line InputError if unreadable)."""
    if isinstance(model, onnx.ModelProto):
        return model
    try:
        if isinstance(model, (bytes, bytearray)):
            return onnx.load_from_string(bytes(model))
        if isinstance(model, (str, os.PathLike)):
            return onnx.load(str(model))
    except Exception as e:  # onnx raises DecodeError, OSError and others on a bad file
        raise InputError(
            f"{model if not isinstance(model, bytes) else 'model bytes'}: not a "
            f"loadable ONNX model ({type(e).__name__})"
        ) from None
    raise TypeError(f"expected a path, bytes or onnx.ModelProto, got {type(model).__name__}")


def _hint(node) -> str:
    """A readable name prefix for the instructions of a node: its op in snake case."""
    special = {"Gemm": "dense", "MatMul": "dense", "IsNaN": "isnan", "IsInf": "isinf"}
    if node.op_type in special:
        return special[node.op_type]
    return re.sub(r"(?<!^)(?=[A-Z])", "_", node.op_type).lower()


def check(proto: onnx.ModelProto) -> list:
    """The graph's nodes as (op, inputs, outputs, attrs, name); unknown ops raise."""
    nodes = []
    for n in proto.graph.node:
        if n.domain not in ("", "ai.onnx"):
            raise UnsupportedOnnxOp(
                f"node {n.name!r}: op {n.domain}.{n.op_type} is not a standard ONNX op"
            )
        if n.op_type not in SUPPORTED_OPS:
            raise UnsupportedOnnxOp(
                f"node {n.name!r}: ONNX op {n.op_type!r} is not supported "
                f"(supported: {', '.join(sorted(SUPPORTED_OPS))})"
            )
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
        nodes.append((n.op_type, list(n.input), list(n.output), attrs, n))
    return nodes


def lower(model) -> Program:
    """Load, check, fold and lower an ONNX model (inputs [N, k], outputs [N, k...])."""
    proto = load(model)
    nodes = check(proto)
    g = proto.graph
    b = Builder()
    lo = Lowering(b)
    env: dict[str, object] = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    inputs: dict[str, int] = {}
    for i in g.input:
        if i.name in env:
            continue
        dims = i.type.tensor_type.shape.dim
        if len(dims) != 2 or not dims[1].HasField("dim_value"):
            raise UnsupportedOnnxOp(f"input {i.name!r}: expected shape [N, k] with a fixed k")
        width = int(dims[1].dim_value)
        inputs[i.name] = width
        b.hint = i.name
        env[i.name] = Lanes(_obj([b.input(i.name, c) for c in range(width)], (width,)))
    op_counts: dict[str, int] = {}
    for op, ins, outs, attrs, node in nodes:
        op_counts[op] = op_counts.get(op, 0) + 1
        args = [env[i] if i else None for i in ins]
        b.hint = _hint(node)
        try:
            res = _OPS[op](lo, args, attrs)
        except UnsupportedOnnxOp as e:
            raise UnsupportedOnnxOp(f"node {node.name!r} ({op}): {e}") from None
        if not isinstance(res, tuple):
            res = (res,)
        for o, v in zip(outs, res, strict=False):
            env[o] = v
    outputs = {}
    b.hint = "out"
    for o in g.output:
        v = env[o.name]
        if isinstance(v, Lanes):
            cols = [lo.to_float(x) for x in v.a.reshape(-1)]
        else:
            c = np.asarray(v)
            c = c[0] if c.ndim >= 1 and c.shape[0] == 1 else c
            cols = [b.const(float(x), "float") for x in c.reshape(-1)]
        outputs[o.name] = cols
    meta = {p.key: p.value for p in proto.metadata_props}
    return b.finish(inputs, outputs, meta, op_counts)
