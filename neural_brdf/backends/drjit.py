"""Execute a lowered graph (:mod:`neural_brdf.graph`) with Dr.Jit arrays.

    from neural_brdf.backends.drjit import OnnxProgram
    program = OnnxProgram("model.onnx")                   # lowers the graph once
    cols = program(wi=[x, y, z], wo=[x, y, z])            # Dr.Jit Float columns
    f_r, f_g, f_b = cols["f"]

Each instruction becomes one Dr.Jit operation on arrays of the input's width; constants
stay Python scalars, so in a JIT variant they are literals of the traced kernel (the
weights of a dense layer included) and the whole graph traces into the caller's
kernel: the Mitsuba plugin's render runs no Python per sample.
"""

from __future__ import annotations

import drjit as dr

from neural_brdf import graph


class _Types:
    """The Dr.Jit array types of the variant in use, taken from an input array."""

    def __init__(self, like):
        self.Float = type(like)
        self.Int = dr.int32_array_t(self.Float)
        self.UInt = dr.uint32_array_t(self.Float)
        self.Bool = dr.mask_t(self.Float)

    def of(self, dtype: str):
        return {"float": self.Float, "int": self.Int, "bool": self.Bool}[dtype]


_UNARY = {
    "neg": lambda x: -x,
    "abs": dr.abs,
    "sqrt": dr.sqrt,
    "exp": dr.exp,
    "log": dr.log,
    "floor": dr.floor,
    "ceil": dr.ceil,
    "sin": dr.sin,
    "cos": dr.cos,
    "atan": dr.atan,
    "asin": dr.asin,
    "acos": dr.acos,
    "tanh": dr.tanh,
    "erf": dr.erf,
    "not": lambda x: ~x,
    "isnan": dr.isnan,
    "isinf": dr.isinf,
}
_BINARY = {
    "add": lambda a, b: a + b,
    "sub": lambda a, b: a - b,
    "mul": lambda a, b: a * b,
    "div": lambda a, b: a / b,
    "max": dr.maximum,
    "min": dr.minimum,
    "pow": dr.power,
    "eq": lambda a, b: a == b,
    "lt": lambda a, b: a < b,
    "le": lambda a, b: a <= b,
    "gt": lambda a, b: a > b,
    "ge": lambda a, b: a >= b,
    "and": lambda a, b: a & b,
    "or": lambda a, b: a | b,
    "xor": lambda a, b: a ^ b,
}


def _is_array(v) -> bool:
    return isinstance(v, dr.ArrayBase)


def run(prog: graph.Program, columns: dict[str, list]) -> dict[str, list]:
    """Evaluate ``prog`` on ``{input: [column arrays]}`` -> ``{output: [Float columns]}``."""
    missing = set(prog.inputs) - set(columns)
    if missing:
        raise ValueError(f"missing graph inputs {sorted(missing)}")
    t = _Types(next(iter(columns.values()))[0])
    tables = [(t.Float if tb.dtype.kind == "f" else t.Int)(tb) for tb in prog.tables]
    vals: list = [None] * len(prog.instrs)
    for i, ins in enumerate(prog.instrs):
        op, a = ins.op, ins.args
        if op == "const":
            v = ins.attr
        elif op in _BINARY:
            v = _BINARY[op](vals[a[0]], vals[a[1]])
        elif op == "fma":
            x, w, c = vals[a[0]], vals[a[1]], vals[a[2]]
            v = dr.fma(x, w, c) if (_is_array(x) or _is_array(w)) else x * w + c
        elif op in _UNARY:
            v = _UNARY[op](vals[a[0]])
        elif op == "select":
            c, x, y = vals[a[0]], vals[a[1]], vals[a[2]]
            if not (_is_array(x) or _is_array(y)):
                x = t.of(ins.dtype)(x)
            v = dr.select(c, x, y)
        elif op == "input":
            name, col = ins.attr
            v = t.Float(columns[name][col])
        elif op == "cast":
            v = _cast(t, vals[a[0]], prog.instrs[a[0]].dtype, ins.dtype)
        elif op == "gather":
            table = tables[ins.attr]
            idx = dr.clip(vals[a[0]], 0, dr.width(table) - 1)
            v = dr.gather(type(table), table, t.UInt(idx))
        else:  # graph.OPS is checked by the tests
            raise graph.UnsupportedOnnxOp(f"Dr.Jit back end: instruction {op!r}")
        vals[i] = v
    return {
        name: [v if _is_array(v) else t.Float(v) for v in (vals[c] for c in cols)]
        for name, cols in prog.outputs.items()
    }


def _cast(t, x, src: str, dst: str):
    if dst == "float":
        return dr.select(x, t.Float(1.0), t.Float(0.0)) if src == "bool" else t.Float(x)
    if dst == "int":
        return dr.select(x, t.Int(1), t.Int(0)) if src == "bool" else t.Int(x)
    return x != 0


class OnnxProgram:
    """An ONNX graph lowered once, evaluated on Dr.Jit arrays.

    ``program(wi=[x, y, z], wo=[x, y, z])`` takes each [N, k] input as a list of its k
    columns (Dr.Jit Float arrays) and returns ``{output name: list of columns}``.
    """

    def __init__(self, model, outputs: tuple[str, ...] | None = None):
        # ``outputs``: the graph outputs to evaluate (default all; graph.lower)
        self.program = graph.lower(model, outputs)
        self.inputs = list(self.program.inputs)
        self.outputs = list(self.program.outputs)
        self.op_counts = dict(self.program.op_counts)

    def __call__(self, **columns) -> dict[str, list]:
        return run(self.program, columns)


class DrJitBackend:
    """The registry's entry for Dr.Jit: ``DrJitBackend().load(model)`` -> OnnxProgram."""

    name = "drjit"

    def load(self, model) -> OnnxProgram:
        return OnnxProgram(model)
