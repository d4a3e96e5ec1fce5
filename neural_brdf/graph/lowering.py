"""ONNX tensors as lanes of instruction ids: :class:`Lanes` and the :class:`Lowering`
helpers the op kernels (:mod:`.ops`) build with."""

from __future__ import annotations

import numpy as np

from neural_brdf.graph.ir import DOT_CHAINS, Builder, UnsupportedOnnxOp


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
            # a constant folded to inf or NaN (1 / 0, log 0) is IEEE's value, which every
            # back end writes as such: not numpy's multi-line RuntimeWarning on stderr
            with np.errstate(all="ignore"):
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
    def dot(self, xs: list[int], ws: list, bias, *, ids: bool = False) -> int:
        """sum_i xs[i] * ws[i] (+ bias) as DOT_CHAINS interleaved FMA chains, summed
        pairwise.  ``ids``: ``ws`` and ``bias`` are instruction ids (a trained
        parameter's gathers, :func:`param_ids`), not float constants."""
        b = self.b

        def w_id(v) -> int:
            return v if ids else b.scalar(v)

        chains: list[int] = []
        for c in range(min(DOT_CHAINS, len(xs))):
            acc = w_id(bias) if (c == 0 and bias is not None) else None
            for x, w in zip(xs[c::DOT_CHAINS], ws[c::DOT_CHAINS], strict=True):
                acc = b.emit("mul", x, w_id(w)) if acc is None else b.emit("fma", x, w_id(w), acc)
            assert acc is not None  # each chain has at least one term: c < len(xs)
            chains.append(acc)
        while len(chains) > 1:
            chains = [
                b.emit("add", chains[i], chains[i + 1]) if i + 1 < len(chains) else chains[i]
                for i in range(0, len(chains), 2)
            ]
        return chains[0]

    def linear(self, x: Lanes, w: np.ndarray, bias, scale: float) -> Lanes:
        """x (trailing (..., K)) @ w (K, M) * scale + bias (M,) as fused multiply-adds."""
        ws = [[float(v) for v in (w[:, j] * scale).astype(np.float32)] for j in range(w.shape[1])]
        return self._rows(
            x, w.shape, lambda xs, j: self.dot(xs, ws[j], None if bias is None else float(bias[j]))
        )

    def linear_ids(self, x: Lanes, w: np.ndarray, bias: np.ndarray | None) -> Lanes:
        """x (trailing (..., K)) @ w (K, M) + bias (M,), ``w`` and ``bias`` object arrays
        of instruction ids (a trained parameter's gathers, :func:`param_ids`)."""
        return self._rows(
            x,
            w.shape,
            lambda xs, j: self.dot(xs, list(w[:, j]), None if bias is None else bias[j], ids=True),
        )

    def _rows(self, x: Lanes, shape: tuple[int, ...], column) -> Lanes:
        """A matrix product's outputs, row by row of x (trailing (..., K)) and column by
        column j of the (K, M) weights: ``column(x's row as a list, j)``'s instruction."""
        k, m = shape
        if x.shape[-1] != k:
            raise UnsupportedOnnxOp(f"matrix product of width {x.shape[-1]} with weights {shape}")
        rows = x.a.reshape(-1, k)
        out = [column(list(rows[r]), j) for r in range(rows.shape[0]) for j in range(m)]
        return Lanes(_obj(out, x.shape[:-1] + (m,)))


class Param:
    """An initializer kept as a trained parameter (``graph.lower(..., params=...)``):
    its name and current values.  Gemm/MatMul weights and biases and Gather tables may
    be parameters; :func:`param_ids` and the Gather kernel read them through tables that
    the program records in ``Program.params``, so a back end can bind the live values."""

    __slots__ = ("name", "value")

    def __init__(self, name: str, value: np.ndarray):
        self.name = name
        self.value = np.asarray(value, np.float32)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.value.shape


def param_ids(b: Builder, p: Param) -> np.ndarray:
    """Each element of ``p`` as one gather, at its row-major index, from a table that
    holds ``p`` flattened: an object array of instruction ids of ``p``'s shape."""
    table = b.param_table(p.name, p.value.reshape(-1), 0, 1)
    flat = [b.emit("gather", b.const(i, "int"), attr=table) for i in range(p.value.size)]
    return _obj(flat, p.shape)
