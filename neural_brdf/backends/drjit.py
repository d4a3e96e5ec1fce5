"""Execute a lowered graph (:mod:`neural_brdf.graph`) with Dr.Jit arrays.

    from neural_brdf.backends.drjit import OnnxProgram
    program = OnnxProgram("model.onnx")                   # lowers the graph once
    cols = program(wi=[x, y, z], wo=[x, y, z])            # Dr.Jit Float columns
    f_r, f_g, f_b = cols["f"]

Each instruction becomes one Dr.Jit operation on arrays of the input's width; constants
stay Python scalars, so in a JIT variant they are literals of the traced kernel (the
weights of a dense layer included) and the whole graph traces into the caller's
kernel: the Mitsuba plugin's render runs no Python per sample.

Gathers.  The lowering gives one ``gather`` per table column, all at one index when they
come from one ONNX tensor (a textured file's weight field: 13 columns, at each of four
bilinear corners).  Here the columns of each float tensor (``Program.sources``) of three
or more columns are laid out again row-major, padded to a multiple of 4, in a buffer that
starts on a cache line, and read as 4-wide packets (``dr.gather`` of an ``Array4f``: one
vector load per lane instead of four gathers), each packet once per index; the values are
the same floats, so the result is bit-identical (tests/backends/test_drjit_packets.py).
In the BSDF-bound scene (LLVM, 2 cores) this took the textured principled of the
benchmark from 0.39 s to 0.32 s and the compact principled from 0.24 s to 0.22 s.

Trained parameters.  A program lowered with ``graph.lower(..., params=...)`` reads each
parameter through tables that ``Program.params`` ties to it; :func:`run` given
``params={name: flat Float}`` reads those arrays instead, so one lowering serves every
value the weights take (the differentiable plugin, :mod:`neural_brdf.inverse.bsdf`).  A
weight (a gather at a constant index) is one scalar load broadcast to every lane when
its array tracks no gradient.  When it does, the index is repeated over the lanes, so
that its adjoint is a scatter-add inside the backward kernel: with a width-1 gather the
adjoint is a reduction over the lanes, and Dr.Jit launched one kernel per weight (about
a thousand a view; 2.8 s against 0.5 s a step of three 96^2 views, LLVM on 2 cores, a
development measurement).  Either is exact; both are slower to differentiate than
torch's matrix products, which is why the plugin differentiates with torch.
"""

from __future__ import annotations

import sys
from typing import Any

import drjit as dr
import numpy as np

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


# False before a model is loaded: its program reads one gather per column (a comparison,
# benchmarks/packet_gathers.py, or a fallback); read by OnnxProgram, not by run()
PACKET_GATHERS = True
PACKET = 4  # floats per packet gather
MIN_COLUMNS = 3  # a tensor of fewer distinct float columns keeps one gather per column
CACHE_LINE = 64  # bytes


class PacketPlan:
    """Where each float table of ``prog`` sits in a packed buffer (module doc, Gathers):
    ``buffers[b]`` is [rows, packets * PACKET] float32 flattened, and ``where[table]`` is
    (b, packet, lane).  Only tensors of MIN_COLUMNS or more distinct float columns are
    packed (a 3-column normal field of 512^2 texels, padded to 4, rendered faster packed:
    0.316 s against 0.337 s for the textured principled in the BSDF-bound scene, LLVM on
    2 cores); a table in several tensors (the lowering deduplicates columns) takes the
    first."""

    def __init__(self, prog: graph.Program, *, enabled: bool = True):
        self.buffers: list[np.ndarray] = []
        self.packets: list[int] = []
        self.rows: list[int] = []
        self.where: dict[int, tuple[int, int, int]] = {}
        for src in prog.sources if enabled else ():
            cols = [(c, tb) for c, tb in enumerate(src.tables) if tb is not None]
            if src.data.dtype.kind != "f" or len({tb for _, tb in cols}) < MIN_COLUMNS:
                continue
            rows, channels = src.data.shape
            n = -(-channels // PACKET)
            packed = _aligned_zeros(rows * n * PACKET).reshape(rows, n * PACKET)
            packed[:, :channels] = src.data
            b = len(self.buffers)
            self.buffers.append(packed.reshape(-1))
            self.packets.append(n)
            self.rows.append(rows)
            for c, tb in cols:
                self.where.setdefault(tb, (b, c // PACKET, c % PACKET))


def _aligned_zeros(n: int) -> np.ndarray:
    """n float32 zeros whose first element sits on a cache-line boundary.  A row of 16
    floats then fills one line: at numpy's own 16-byte alignment three buffers in four
    straddled two lines per row, and a textured render in the BSDF-bound scene took
    0.38 s against 0.33 s with the buffer aligned (LLVM, 2 cores; Dr.Jit reads a CPU
    array in place, so the alignment carries)."""
    raw = np.zeros(n + CACHE_LINE // 4, np.float32)
    skip = (-raw.ctypes.data % CACHE_LINE) // 4
    return raw[skip : skip + n]


def _packet_type(float_type):
    """The variant's Array4f (drjit.llvm.ad.Array4f, ...); None outside a JIT variant."""
    mod = sys.modules.get(getattr(float_type, "__module__", ""))
    return getattr(mod, "Array4f", None) if mod is not None else None


def run(
    prog: graph.Program,
    columns: dict[str, list],
    plan: PacketPlan | None = None,
    params: dict[str, Any] | None = None,
) -> dict[str, list]:
    """Evaluate ``prog`` on ``{input: [column arrays]}`` -> ``{output: [Float columns]}``;
    ``plan`` (default: built here) packs the gathers (module doc).

    ``params``: ``{name: flat Float array}`` for the trained parameters of a program
    lowered with ``graph.lower(..., params=...)`` (``Program.params``): their gathers
    read these arrays, row-major, instead of the tables' copies, so gradients reach them
    (Dr.Jit differentiates a gather as a scatter-add; a weight: :func:`_weight_index`)."""
    missing = set(prog.inputs) - set(columns)
    if missing:
        raise ValueError(f"missing graph inputs {sorted(missing)}")
    t = _Types(next(iter(columns.values()))[0])
    plan = PacketPlan(prog) if plan is None else plan
    array4 = _packet_type(t.Float)
    buffers = [t.Float(b) for b in plan.buffers] if array4 is not None else []
    packed = plan.where if buffers else {}
    width = max(dr.width(c) for cols in columns.values() for c in cols)
    bound = {tb: p for tb, p in prog.params.items() if params is not None and p[0] in params}
    # the packed tables are read from the buffers only (no copy of them is made here)
    tables = [
        None if (i in packed or i in bound) else (t.Float if tb.dtype.kind == "f" else t.Int)(tb)
        for i, tb in enumerate(prog.tables)
    ]
    fetched: dict[tuple[int, int, int], Any] = {}  # (index id, buffer, packet) -> Array4f
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
        elif op == "gather" and ins.attr in packed:
            b, k, lane = packed[ins.attr]
            key = (a[0], b, k)
            if key not in fetched:
                idx = t.UInt(dr.clip(vals[a[0]], 0, plan.rows[b] - 1))
                fetched[key] = dr.gather(array4, buffers[b], idx * plan.packets[b] + k)
            v = fetched[key][lane]
        elif op == "gather" and ins.attr in bound:
            name, column, channels = bound[ins.attr]
            rows = len(prog.tables[ins.attr])
            index = vals[a[0]]
            if _is_array(index):
                row = t.UInt(dr.clip(index, 0, rows - 1))
                v = dr.gather(t.Float, params[name], row * channels + column)  # type: ignore[index]
            else:  # a weight: the same element in every lane
                at = min(max(int(index), 0), rows - 1) * channels + column
                v = dr.gather(t.Float, params[name], _weight_index(t, at, params[name], width))  # type: ignore[index]
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


def _weight_index(t, at: int, param, width: int):
    """Where a weight's gather reads ``param`` (module doc, Trained parameters)."""
    if dr.grad_enabled(param):
        return dr.zeros(t.UInt, width) + at
    return t.UInt(at)


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
        self.plan = PacketPlan(self.program, enabled=PACKET_GATHERS)
        self.inputs = list(self.program.inputs)
        self.outputs = list(self.program.outputs)
        self.op_counts = dict(self.program.op_counts)

    def __call__(self, **columns) -> dict[str, list]:
        return run(self.program, columns, self.plan)


class DrJitBackend:
    """The registry's entry for Dr.Jit: ``DrJitBackend().load(model)`` -> OnnxProgram."""

    name = "drjit"

    def load(self, model) -> OnnxProgram:
        return OnnxProgram(model)
