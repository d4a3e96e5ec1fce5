"""An exported ONNX graph lowered once to a flat list of scalar-per-lane instructions.

    from neural_brdf import graph
    prog = graph.lower("model.onnx")           # a path, bytes or an onnx.ModelProto
    prog.outputs                               # {"f": [id_r, id_g, id_b]}
    for i, ins in enumerate(prog.instrs):      # SSA: ins.args are earlier indices
        print(prog.names[i], ins.op, ins.dtype, ins.args, ins.attr)

Every back end (:mod:`neural_brdf.backends`: Dr.Jit, C, GLSL, WGSL) evaluates THIS list,
so they all evaluate the exported graph, never a retyped copy of the model.

Layout: :mod:`.ir` holds the instruction set and the :class:`Builder`; :mod:`.lowering`
the lanes of instruction ids an ONNX tensor becomes; :mod:`.ops` one kernel per ONNX op;
this module loads and checks the graph and walks it (:func:`lower`).

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

Textures.  ``Program.sources`` records which ONNX tensor [rows, channels] each table is a
column of.  :func:`textures` picks the tensors that a gather at indices computed from an
input (``uv``: the weight field of a textured file) reads: the source generators bind
those as buffers instead of writing megabytes of literals (docs/codegen.md).

An op outside :data:`SUPPORTED_OPS`, or in a form the lowering lacks, raises
:class:`UnsupportedOnnxOp` (an InputError) naming the node and the op.  This module
imports numpy and onnx only.
"""

from __future__ import annotations

import re

import numpy as np
import onnx
from onnx import numpy_helper

from neural_brdf.fileformat.reader import (
    check_finite,
    load,  # the one ONNX loader (graph.load)
)
from neural_brdf.graph.ir import (
    BATCH,
    BINARY,
    COMPARE,
    DOT_CHAINS,
    LOGIC,
    OPS,
    UNARY,
    Builder,
    Instr,
    Program,
    Source,
    Texture,
    UnsupportedOnnxOp,
)
from neural_brdf.graph.lowering import Lanes, Lowering, Param, _obj
from neural_brdf.graph.ops import _OPS, SUPPORTED_OPS

__all__ = [
    "BATCH",
    "BINARY",
    "COMPARE",
    "DOT_CHAINS",
    "LOGIC",
    "OPS",
    "PARAM_OPS",
    "UNARY",
    "SUPPORTED_OPS",
    "Builder",
    "Instr",
    "Program",
    "Source",
    "Texture",
    "UnsupportedOnnxOp",
    "check",
    "load",
    "lower",
    "textures",
]


def _hint(node) -> str:
    """A readable name prefix for the instructions of a node: its op in snake case."""
    special = {"Gemm": "dense", "MatMul": "dense", "IsNaN": "isnan", "IsInf": "isinf"}
    if node.op_type in special:
        return special[node.op_type]
    return re.sub(r"(?<!^)(?=[A-Z])", "_", node.op_type).lower()


def node_text(node, index: int | None = None) -> str:
    """A node as a message names it: its name, or (unnamed, as another tool may write
    it) its place in the graph and its first output."""
    if node.name:
        return f"node {node.name!r}"
    where = f"#{index} " if index is not None else ""
    out = node.output[0] if len(node.output) else "?"
    return f"node {where}(unnamed, output {out!r})"


def check(proto: onnx.ModelProto) -> list:
    """The graph's nodes as (op, inputs, outputs, attrs, name); unknown ops raise."""
    nodes = []
    for k, n in enumerate(proto.graph.node):
        if n.domain not in ("", "ai.onnx"):
            raise UnsupportedOnnxOp(
                f"{node_text(n, k)}: op {n.domain}.{n.op_type} is not a standard ONNX op"
            )
        if n.op_type not in SUPPORTED_OPS:
            raise UnsupportedOnnxOp(
                f"{node_text(n, k)}: ONNX op {n.op_type!r} is not supported "
                f"(supported: {', '.join(sorted(SUPPORTED_OPS))})"
            )
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
        nodes.append((n.op_type, list(n.input), list(n.output), attrs, n))
    return nodes


# ONNX ops that may read a trained parameter (lower(..., params=...))
PARAM_OPS = frozenset({"Gemm", "MatMul", "Gather"})


def lower(model, outputs: tuple[str, ...] | None = None, params: tuple[str, ...] = ()) -> Program:
    """Load, check, fold and lower an ONNX model (inputs [N, k], outputs [N, k...]).

    ``outputs``: the graph outputs to keep (default all), in that order; the program is
    pruned to what they need, and its ``inputs`` to the inputs they read.  A textured
    file's normal field ``n`` depends on uv alone, so ``lower(model, ("n",))`` is a
    program of uv: a host evaluates it first, rotates its frame, then evaluates
    ``lower(model, ("f",))`` (docs/model.md, "The normal field").

    ``params``: initializers kept as trained parameters instead of folded constants
    (the differentiable plugin of :mod:`neural_brdf.inverse.bsdf`).  Each is read by
    ``gather`` instructions from tables that ``Program.params`` ties to it, so a back end
    can bind the parameter's live (differentiable) values in their place
    (:func:`neural_brdf.backends.drjit.run`); other back ends see ordinary tables.  Only
    Gemm/MatMul weights and biases of a batch input and Gather tables read at batch
    indices may be parameters: any other use (another op, a Gather at constant indices,
    a product with no batch operand, a graph output) raises, naming the parameter."""
    proto = load(model)  # a path or bytes: checked there, NaN weights included
    if isinstance(model, onnx.ModelProto):  # given as it is: its weights unchecked yet
        check_finite(proto)
    names = [o.name for o in proto.graph.output]
    if outputs is not None:
        unknown = [o for o in outputs if o not in names]
        if unknown:
            raise UnsupportedOnnxOp(f"outputs {unknown}: the graph has {names}")
    nodes = check(proto)
    g = proto.graph
    b = Builder()
    lo = Lowering(b)
    env: dict[str, object] = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    unknown = [p for p in params if p not in env]
    if unknown:
        raise UnsupportedOnnxOp(f"params {unknown}: not initializers of the graph")
    for p in params:
        env[p] = Param(p, np.asarray(env[p]))
    inputs: dict[str, int] = {}
    for i in g.input:
        if i.name in env:
            continue
        if i.type.tensor_type.elem_type != onnx.TensorProto.FLOAT:  # computed in float32
            kind = {onnx.TensorProto.DOUBLE: "float64"}.get(i.type.tensor_type.elem_type)
            raise UnsupportedOnnxOp(
                f"input {i.name!r}: expected float32, got "
                f"{kind or 'element type ' + str(i.type.tensor_type.elem_type)}"
            )
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
        trained = [i for i, a in zip(ins, args, strict=True) if isinstance(a, Param)]
        if trained and op not in PARAM_OPS:
            raise UnsupportedOnnxOp(
                f"{node_text(node)} ({op}) reads the trained parameter {trained[0]!r}; "
                f"only {', '.join(sorted(PARAM_OPS))} may"
            )
        b.hint = _hint(node)
        try:
            res = _OPS[op](lo, args, attrs)
        except UnsupportedOnnxOp as e:
            raise UnsupportedOnnxOp(f"{node_text(node)} ({op}): {e}") from None
        if not isinstance(res, tuple):
            res = (res,)
        for o, v in zip(outs, res, strict=False):
            env[o] = v
    kept = list(outputs) if outputs is not None else names
    outs = {}
    b.hint = "out"
    for name in kept:
        v = env[name]
        if isinstance(v, Param):
            raise UnsupportedOnnxOp(f"output {name!r} is the trained parameter {v.name!r}")
        if isinstance(v, Lanes):
            cols = [lo.to_float(x) for x in v.a.reshape(-1)]
        else:
            c = np.asarray(v)
            c = c[0] if c.ndim >= 1 and c.shape[0] == 1 else c
            cols = [b.const(float(x), "float") for x in c.reshape(-1)]
        outs[name] = cols
    meta = {p.key: p.value for p in proto.metadata_props}
    if outputs is not None:  # only the inputs that the kept outputs read
        read = _inputs_read(b, outs)
        inputs = {k: w for k, w in inputs.items() if k in read}
    return b.finish(inputs, outs, meta, op_counts)


def _inputs_read(b: Builder, outs: dict[str, list[int]]) -> set[str]:
    """The input names that the instructions ``outs`` need read."""
    seen: set[int] = set()
    stack = [i for cols in outs.values() for i in cols]
    read: set[str] = set()
    while stack:
        i = stack.pop()
        if i in seen:
            continue
        seen.add(i)
        ins = b.instrs[i]
        if ins.op == "input":
            read.add(ins.attr[0])
        stack.extend(ins.args)
    return read


def textures(prog: Program, name: str = "uv") -> list[Texture]:
    """The tensors to bind as buffers: every one with a table that a ``gather`` at an
    index computed from the input ``name`` reads, in the order of ``prog.sources``.
    "Computed from" is arithmetic on ``name`` alone: a table read at an index that also
    uses a value another gather returned does not count.

    Why this rule and not a size: a table indexed by directions alone is a fixed small
    function of the model (the albedo bound, a feature grid), written as literals as
    before; a table indexed by uv is the material's texture, which grows with its
    resolution (a 256 x 256 weight field of 8 lobes is 2 MB) and which a host may
    replace.  The tables of conditioned lobes (docs/model.md) are read at the latent s,
    a value of the weight field's texture: they are functions of the model as well, and
    stay literals.  A table that is a column of two equal tensors goes with the first.  Only
    float tables can be bound (an int one raises UnsupportedOnnxOp, one line)."""
    if name not in prog.inputs:
        return []
    dep, read = prog.depends_on(name), prog.reads_a_table()
    bound = {
        ins.attr
        for ins in prog.instrs
        if ins.op == "gather" and dep[ins.args[0]] and not read[ins.args[0]]
    }
    out: list[Texture] = []
    for src in prog.sources:
        channels = {t: c for c, t in enumerate(src.tables) if t is not None and t in bound}
        if not channels:
            continue
        if src.data.dtype != np.float32:
            rows, width = src.data.shape
            raise UnsupportedOnnxOp(
                f"a table gathered at {name}-dependent indices is bound as a float buffer, "
                f"got {src.data.dtype} [{rows}, {width}]"
            )
        bound -= set(channels)
        out.append(Texture(src.data, channels))
    if bound:  # a gather table without a source: only hand-built programs have those
        raise UnsupportedOnnxOp(
            f"tables {sorted(bound)}: gathered at {name}-dependent "
            "indices but not from a recorded tensor"
        )
    return out
