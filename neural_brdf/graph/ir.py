"""The instruction set: :class:`Instr`, :class:`Program` and the :class:`Builder` that
deduplicates, folds and prunes them (see :mod:`neural_brdf.graph` for the set itself)."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from neural_brdf.errors import InputError

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
    attr: Any = None  # by op: (name, column), a constant, a dtype, a table number


@dataclass
class Source:
    """One constant ONNX tensor gathered at batch indices, as the tables it became: the
    lowering splits it into one table per column (deduplicated by content), and a back
    end that binds it as one buffer needs the tensor whole, in its own layout."""

    data: np.ndarray  # [rows, channels]: the tensor, rows along its axis 0, row-major
    tables: tuple[int | None, ...]  # per channel its table number (None: pruned)


@dataclass
class Texture:
    """A :class:`Source` that a back end binds as a buffer instead of literals
    (:func:`neural_brdf.graph.textures`): its data [rows, channels] float32, row-major,
    and which channel each of its tables is."""

    data: np.ndarray
    channels: dict[int, int]  # table number -> channel


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
    sources: list[Source] = field(default_factory=list)  # the tensors the tables came from
    # table number -> (parameter name, column, channels) for the tables of trained
    # parameters (graph.lower(..., params=...)): the table is column ``column`` of the
    # parameter flattened to [rows, channels], row-major
    params: dict[int, tuple[str, int, int]] = field(default_factory=dict)

    def depends_on(self, name: str) -> list[bool]:
        """Per instruction: whether its value depends on the input ``name``."""
        out: list[bool] = []
        for ins in self.instrs:
            if ins.op == "input":
                out.append(ins.attr[0] == name)
            else:
                out.append(any(out[a] for a in ins.args))
        return out

    def reads_a_table(self) -> list[bool]:
        """Per instruction: whether its value is computed from a value a ``gather``
        returned (the gather itself included)."""
        out: list[bool] = []
        for ins in self.instrs:
            out.append(ins.op == "gather" or any(out[a] for a in ins.args))
        return out

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
            fn: Any = {  # numpy ufuncs, one and two operands
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
        self.sources: dict[tuple[int, ...], np.ndarray] = {}  # tables -> [rows, channels]
        self.param_of: dict[int, tuple[str, int, int]] = {}  # table -> its parameter
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

    def param_table(self, name: str, values: np.ndarray, column: int, channels: int) -> int:
        """A table that is column ``column`` of the trained parameter ``name`` as
        [rows, channels]: never shared with another table, even of equal content."""
        key = f"param:{name}:{column}".encode()
        if key not in self.table_memo:
            self.tables.append(np.ascontiguousarray(values, dtype=np.float32))
            self.table_memo[key] = len(self.tables) - 1
            self.param_of[len(self.tables) - 1] = (name, column, channels)
        return self.table_memo[key]

    def source(self, data: np.ndarray, tables: list[int]) -> None:
        """Records that ``tables`` are the columns of ``data`` [rows, channels]."""
        self.sources.setdefault(tuple(tables), data)

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
        names: list[str] = []
        counters: dict[str, int] = {}
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
            [
                Source(data, tuple(tmap.get(t) for t in tables))
                for tables, data in self.sources.items()
                if any(t in tmap for t in tables)
            ],
            {tmap[t]: p for t, p in self.param_of.items() if t in tmap},
        )
