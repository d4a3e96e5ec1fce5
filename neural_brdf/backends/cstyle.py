"""The base class of the source-code back ends: a lowered program -> a C-like function.

    from neural_brdf.backends.c import CRenderer
    text = CRenderer().generate("model.onnx")        # the whole header file, as a string

One lowered instruction list (:mod:`neural_brdf.graph`) is rendered as one named
temporary per instruction, one statement per line, with the constants inlined by one
rule per kind (:meth:`CStyleRenderer.literal`).  A dialect (C, GLSL, WGSL) is a short
subclass: type names, literal spellings, the few operators and functions that differ,
how a function binds its inputs and returns its outputs, and the file around them.
Adding a language (HLSL, Metal, ...) is one file with such a subclass and its line in
:data:`neural_brdf.backends.REGISTRY` (:data:`neural_brdf.backends.TARGETS`, what
``neural-brdf codegen --target`` offers, follows from it), and its parity test
(docs/architecture.md, "Adding something").

Every generated file holds three functions built from the model (its graph, and its
stored sampling lobe, :mod:`neural_brdf.backends.lobe_ir`):

    neural_brdf_eval(wi, wo) -> f (RGB, 1/sr, no cosine)
    neural_brdf_pdf(wi, wo) -> the lobe's solid-angle density of wo
    neural_brdf_sample(wi, u1, u2) -> wo and its pdf

A textured file (inputs wi, wo, uv) gives ``neural_brdf_eval(wi, wo, uv)``; the tables it
gathers at uv-dependent indices (its weight field, :func:`neural_brdf.graph.textures`)
are not literals but buffers the host binds (``neural_brdf_texture0``, ...: a pointer
parameter in C, an SSBO or a float texture in GLSL, a storage buffer in WGSL; see
docs/codegen.md, "Textured files"), read at ``clamp(index, 0, rows - 1) * channels +
channel``, the same element as the ONNX Gather.

A textured file with the teacher's normal field (its second output ``n``,
:data:`neural_brdf.fileformat.NORMAL`) gives one more function, of uv alone:

    neural_brdf_normal(uv) -> n, the unit shading normal in the unperturbed frame

rendered from ``graph.lower(model, ("n",))`` while ``neural_brdf_eval`` is rendered from
``graph.lower(model, ("f",))``.  The file has ONE list of bound textures: those of
neural_brdf_eval first (numbered as in a file without n), then those that only
neural_brdf_normal reads (:func:`lower_file`).

``neural_brdf`` is the default prefix of every name the file defines (functions,
helpers, tables, textures, and in upper case its macros and C's include guard):
``CRenderer(prefix="gold")`` gives ``gold_eval``, ``gold_texture0``, ``GOLD_H``, ..., so
that files of several models can be used in one program (:func:`check_prefix`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from neural_brdf import graph
from neural_brdf.backends import lobe_ir
from neural_brdf.errors import InputError
from neural_brdf.fileformat import (
    INPUT_WIDTHS,
    NORMAL,
    OUTPUT,
    OUTPUT_SIGNATURES,
    SIGNATURES,
    UV,
)
from neural_brdf.fileformat import lobe as lobe_format  # the stored lobe: its schema

PREFIX = "neural_brdf"  # the default prefix of the generated names
# A prefix: lower-case words of letters and digits, each starting with a letter, joined
# by single underscores, so that it is an identifier in C, GLSL and WGSL (no "__", which
# GLSL reserves), and its upper case (the macros) and CamelCase (WGSL's struct, GLSL's
# block names) are as distinct as the prefixes themselves.
PREFIX_PATTERN = re.compile(r"[a-z][a-z0-9]*(_[a-z][a-z0-9]*)*")
# at most this many characters: a name is the prefix and a suffix, and GLSL ES allows
# 1024 in all (a 1,100-character prefix gave code glslang refuses, a 100,000 one 16 MB)
MAX_PREFIX = 64
# A metadata value in the header comment (the target's JSON, say) is cut to this many
# characters, at an item's or a word's end, and marked by ELLIPSIS.
HEADER_VALUE_CHARS = 200
ELLIPSIS = " ..."


def comment_value(value: object, limit: int = HEADER_VALUE_CHARS) -> str:
    """``value`` as one line of a header comment: its whitespace collapsed, and when it
    is longer than ``limit``, cut after its last whole item (``", "``) or word that fits,
    with :data:`ELLIPSIS` after it (never mid-key: ``"kind": `` and nothing).  It never
    ends in a backslash, which in C and GLSL would join the next line to the comment."""
    text = " ".join(str(value).split())
    if len(text) > limit:
        room = limit - len(ELLIPSIS)
        head = text[: room + 1]  # a boundary just after room characters still counts
        cut = head.rfind(", ")
        if cut < room // 2:  # no item ends in the second half: the last word's end
            cut = head.rfind(" ")
        text = text[: cut if cut > 0 else room].rstrip(" ,:\\") + ELLIPSIS
    if text.endswith("\\"):  # (a short value too: its backslashes are what is left out)
        text = text.rstrip("\\") + ELLIPSIS
    return text


def check_prefix(prefix: str) -> str:
    """``prefix`` if it can prefix the generated names (:data:`PREFIX_PATTERN`, not
    GLSL's reserved ``gl_``), else a one-line InputError."""
    if (
        not isinstance(prefix, str)
        or not PREFIX_PATTERN.fullmatch(prefix)
        or prefix == "gl"
        or prefix.startswith("gl_")
    ):
        raise InputError(
            "prefix: expected lower-case words of letters and digits joined by single "
            f"underscores, each starting with a letter (e.g. {PREFIX!r}, 'gold_v2'), "
            f"not 'gl' or 'gl_...', got {prefix!r}"
        )
    if len(prefix) > MAX_PREFIX:
        raise InputError(
            f"prefix: at most {MAX_PREFIX} characters (every generated name begins with "
            f"it), got {len(prefix)}: {prefix[:20]}..."
        )
    return prefix


def camel(prefix: str) -> str:
    """``neural_brdf`` -> ``NeuralBrdf``: the prefix of generated type and block names."""
    return "".join(word[:1].upper() + word[1:] for word in prefix.split("_"))


def source_name(model, source: str | None = None) -> str:
    """What an error names: ``source`` if given, a path as given, else ``codegen``."""
    if source is not None:
        return source
    if isinstance(model, (bytes, bytearray)) or hasattr(model, "graph"):
        return "codegen"
    return str(model)


@dataclass
class Part:
    """One generated function's program and the textures it reads: ``textures`` are
    :func:`neural_brdf.graph.textures` of ``prog`` (their channels are its table
    numbers), ``numbers`` each one's number in the file's list."""

    prog: graph.Program
    textures: list[graph.Texture]
    numbers: list[int]


def _declared_inputs(proto) -> dict[str, int]:
    """The graph's inputs (not initializers) -> their widths, in order."""
    inits = {t.name for t in proto.graph.initializer}
    out = {}
    for i in proto.graph.input:
        if i.name not in inits:
            dims = i.type.tensor_type.shape.dim
            out[i.name] = int(dims[1].dim_value) if len(dims) == 2 else -1
    return out


def lower_file(
    model, *, source: str | None = None
) -> tuple[Part, Part | None, list[graph.Texture]]:
    """The programs of a file's functions: f's (``neural_brdf_eval``), n's
    (``neural_brdf_normal``, None without the output n) and the file's bound textures.

    A file without n is lowered whole (``graph.lower(model)``), as it always was.  With
    n, f is ``graph.lower(model, ("f",))`` with the file's inputs (wi, wo, uv), n is
    ``graph.lower(model, ("n",))`` with the input uv.  Texture numbers: f's textures
    are 0, 1, ... in their order (the weight field is texture 0, as without n); n's
    follow, except one whose data equal one already listed, which shares its number.
    The file's contract (inputs wi, wo [N, 3] (and uv [N, 2]), output f [N, 3] (and n
    [N, 3] with uv)) is checked: a one-line InputError otherwise, naming ``source``
    (default: the path, or ``codegen`` for bytes and a ModelProto), as is an op the
    lowering does not know."""
    src = source_name(model, source)
    proto = graph.load(model)  # not ONNX, or empty: an error naming the path (reader.load)
    names = tuple(o.name for o in proto.graph.output)
    with_normal = names == OUTPUT_SIGNATURES[1]
    try:
        if with_normal:
            prog = graph.lower(proto, (OUTPUT,))
            prog.inputs = _declared_inputs(proto)  # the signature, whatever f reads
            nprog = graph.lower(proto, (NORMAL,))
            nprog.inputs = {UV: INPUT_WIDTHS[UV]}  # n is of uv alone
        else:
            prog = graph.lower(proto)
            nprog = None
    except graph.UnsupportedOnnxOp as e:
        raise graph.UnsupportedOnnxOp(f"{src}: {e}") from None
    # the file's contract (fileformat): inputs wi, wo [N, 3] (and uv [N, 2]: a
    # textured file), output f [N, 3] (and n [N, 3], a textured file's normal field)
    if (
        tuple(prog.inputs) not in SIGNATURES
        or list(prog.outputs) != [OUTPUT]
        or any(prog.inputs[name] != INPUT_WIDTHS[name] for name in prog.inputs)
        or len(prog.outputs[OUTPUT]) != 3
        or (
            nprog is not None
            and (tuple(prog.inputs) != SIGNATURES[1] or len(nprog.outputs[NORMAL]) != 3)
        )
    ):
        outs = {k: len(v) for k, v in prog.outputs.items()}
        if nprog is not None:
            outs[NORMAL] = len(nprog.outputs[NORMAL])
        raise InputError(
            f"{src}: expected inputs wi, wo [N, 3] (and uv [N, 2]) and output "
            f"{OUTPUT} [N, 3] (and {NORMAL} [N, 3] with uv), got {prog.inputs} -> {outs}"
            if nprog is not None
            else f"{src}: expected inputs wi, wo [N, 3] (and uv [N, 2]) and output "
            f"{OUTPUT} [N, 3], got {prog.inputs} -> {outs}"
        )
    try:
        textures = graph.textures(prog, UV)
        ntextures = graph.textures(nprog, UV) if nprog is not None else []
    except graph.UnsupportedOnnxOp as e:  # a table no float buffer can hold
        raise graph.UnsupportedOnnxOp(f"{src}: {e}") from None
    f = Part(prog, textures, list(range(len(textures))))
    listed = list(textures)
    if nprog is None:
        return f, None, listed
    numbers = []
    for tex in ntextures:
        same = [
            k
            for k, t in enumerate(listed)
            if t.data.shape == tex.data.shape and np.array_equal(t.data, tex.data)
        ]
        if same:
            numbers.append(same[0])
        else:
            numbers.append(len(listed))
            listed.append(tex)
    return f, Part(nprog, ntextures, numbers), listed


class CStyleRenderer:
    """Renders programs into a C-like language; dialects override the class attributes
    and the hooks below."""

    name = "cstyle"
    comment = "//"
    types = {"float": "float", "int": "int", "bool": "bool"}
    # unary instruction -> function name (``neg`` and ``not`` are operators); those in
    # ``helper_ops`` are the file's own helpers (:meth:`helpers`), <prefix>_<name>
    functions = {
        "abs": "abs",
        "sqrt": "sqrt",
        "exp": "exp",
        "log": "log",
        "floor": "floor",
        "ceil": "ceil",
        "sin": "sin",
        "cos": "cos",
        "atan": "atan",
        "asin": "asin",
        "acos": "acos",
        "tanh": "tanh",
        "erf": "erf",
        "pow": "pow",
        "max": "max",
        "min": "min",
        "isnan": "isnan",
        "isinf": "isinf",
    }
    # NaN and infinity tests are bit tests in every dialect: GLSL lets a compiler assume
    # isnan() is false, WGSL has none, and C's isnan() is removed by -ffast-math
    helper_ops: frozenset[str] = frozenset({"isnan", "isinf"})
    infix = {
        "add": "+",
        "sub": "-",
        "mul": "*",
        "div": "/",
        "eq": "==",
        "lt": "<",
        "le": "<=",
        "gt": ">",
        "ge": ">=",
        "and": "&&",
        "or": "||",
        "xor": "!=",
    }
    float_suffix = ""
    int_suffix = ""
    # the file's bound textures (set by generate; the sampling programs read none), the
    # numbers of those the function being rendered reads (C: its parameters), and its
    # table number -> (texture number, channel)
    textures: list[graph.Texture] = []
    reads: list[int] = []
    f_reads: list[int] = []  # those neural_brdf_eval reads
    fetches: dict[int, tuple[int, int]] = {}
    # with the output n: the numbers of the textures neural_brdf_normal reads (None: the
    # file has no normal field)
    normal_reads: list[int] | None = None
    table_stem = "table"  # the literal tables' names: neural_brdf_table<k>

    def __init__(self, *, prefix: str = PREFIX):
        # the prefix of every name the file defines (module doc, check_prefix)
        self.prefix = check_prefix(prefix)

    def fn(self, name: str) -> str:
        """A function the file defines: ``eval`` -> ``neural_brdf_eval``."""
        return f"{self.prefix}_{name}"

    def macro(self, name: str) -> str:
        """A macro the file defines: ``TEXTURE0_ROWS`` -> ``NEURAL_BRDF_TEXTURE0_ROWS``."""
        return f"{self.prefix.upper()}_{name}"

    # ------------------------------------------------------------------ literals
    def literal(self, value, dtype: str) -> str:
        """A constant, by one rule per kind; negative values are parenthesised."""
        if dtype == "bool":
            return self.bool_literal(bool(value))
        if dtype == "int":
            text = f"{int(value)}{self.int_suffix}"
            return f"({text})" if value < 0 else text
        v = np.float32(value)
        if not np.isfinite(v):
            text = self.special_float(float(v))
        else:
            text = str(v)  # numpy: the shortest float32 round trip
            if "." not in text and "e" not in text:
                text += ".0"
            if "e" in text and "." not in text.split("e")[0]:
                mant, exp = text.split("e")
                text = f"{mant}.0e{exp}"
            text += self.float_suffix
        return f"({text})" if text.startswith("-") else text

    def bool_literal(self, v: bool) -> str:
        return "true" if v else "false"

    def special_float(self, v: float) -> str:
        """+-inf or NaN from its IEEE-754 bits (GLSL and WGSL have no such literal)."""
        bits = {math.inf: "0x7f800000u", -math.inf: "0xff800000u"}.get(v, "0x7fc00000u")
        return self.bitcast_float(bits)

    def bitcast_float(self, bits: str) -> str:
        raise NotImplementedError

    # ------------------------------------------------------------------ expressions
    def call(self, fn: str, *args: str) -> str:
        return f"{fn}({', '.join(args)})"

    def expr(self, prog: graph.Program, ins: graph.Instr, a: list[str]) -> str:
        """The expression of one instruction over its rendered arguments."""
        op = ins.op
        if op in self.infix:
            return f"{a[0]} {self.infix[op]} {a[1]}"
        if op == "fma":
            return f"{a[0]} * {a[1]} + {a[2]}"
        if op == "neg":
            return f"-{a[0]}"
        if op == "not":
            return f"!{a[0]}"
        if op == "select":
            return self.select(a[0], a[1], a[2])
        if op == "cast":
            return self.cast(a[0], prog.instrs[ins.args[0]].dtype, ins.dtype)
        if op == "gather" and ins.attr in self.fetches:
            tex, channel = self.fetches[ins.attr]
            rows, width = self.textures[tex].data.shape
            clamped = self.clamp_index(a[0], rows - 1)
            return self.fetch(
                tex, f"{clamped} * {self.literal(width, 'int')} + {self.literal(channel, 'int')}"
            )
        if op == "gather":
            k = len(prog.tables[ins.attr])
            return f"{self.table_name(ins.attr)}[{self.clamp_index(a[0], k - 1)}]"
        if op in ("max", "min"):
            return self.minmax(op, ins.dtype, a[0], a[1])
        if op in self.helper_ops:
            return self.call(self.fn(op), *a)
        if op in self.functions:
            return self.call(self.functions[op], *a)
        raise graph.UnsupportedOnnxOp(f"{self.name} back end: instruction {op!r}")

    def select(self, c: str, a: str, b: str) -> str:
        return f"{c} ? {a} : {b}"

    def cast(self, x: str, src: str, dst: str) -> str:
        return f"{self.types[dst]}({x})"

    def minmax(self, op: str, dtype: str, a: str, b: str) -> str:
        return self.call(self.functions[op], a, b)

    def clamp_index(self, i: str, last: int) -> str:
        return self.call("clamp", i, self.literal(0, "int"), self.literal(last, "int"))

    def table_name(self, k: int) -> str:
        return self.fn(f"{self.table_stem}{k}")

    def texture_name(self, k: int) -> str:
        return self.fn(f"texture{k}")

    def fetch(self, k: int, element: str) -> str:
        """Element ``element`` (an int expression in [0, rows * channels)) of texture k."""
        return f"{self.texture_name(k)}[{element}]"

    def texture_decls(self) -> list[str]:
        """The module-scope declarations of the bound textures (none in C: parameters)."""
        return []

    # ------------------------------------------------------------------ statements
    def declare(self, dtype: str, name: str, expr: str) -> str:
        return f"{self.types[dtype]} {name} = {expr};"

    def body(self, prog: graph.Program) -> tuple[list[str], list[str]]:
        """One declaration per instruction (constants are inlined where used) and the
        rendered name or literal of every instruction."""
        rendered: list[str] = []
        lines = []
        for i, ins in enumerate(prog.instrs):
            if ins.op == "const":
                rendered.append(self.literal(ins.attr, ins.dtype))
                continue
            name = prog.names[i]
            rendered.append(name)
            if ins.op == "input":
                src, col = ins.attr
                lines.append(
                    self.declare("float", name, self.input_component(src, col, prog.inputs[src]))
                )
            else:
                lines.append(
                    self.declare(
                        ins.dtype, name, self.expr(prog, ins, [rendered[a] for a in ins.args])
                    )
                )
        return lines, rendered

    # dialect hooks: a function's inputs and outputs
    def input_component(self, name: str, col: int, width: int) -> str:
        return name if width == 1 else f"{name}.{'xyzw'[col]}"

    def function(self, fname: str, prog: graph.Program, doc: str) -> list[str]:
        raise NotImplementedError

    def tables(self, prog: graph.Program) -> list[str]:
        return [
            self.table(self.table_name(k), t)
            for k, t in enumerate(prog.tables)
            if k not in self.fetches
        ]

    def table(self, name: str, values: np.ndarray) -> str:
        raise NotImplementedError

    def table_values(self, values: np.ndarray, per_line: int = 6) -> list[str]:
        """The literals of a table, ``per_line`` to a line, comma-separated."""
        dtype = "float" if values.dtype.kind == "f" else "int"
        lits = [self.literal(v, dtype) for v in values.tolist()]
        return [
            ", ".join(lits[i : i + per_line]) + ("," if i + per_line < len(lits) else "")
            for i in range(0, len(lits), per_line)
        ]

    def helpers(self) -> list[str]:
        """Functions the rendered code calls (isnan, isinf, ...)."""
        return []

    def wrap(self, header: list[str], parts: list[str]) -> str:
        """The whole file around the header comment and the rendered parts."""
        return "\n".join(header + [""] + parts) + "\n"

    # ------------------------------------------------------------------ the file
    def header(self, meta: dict, lobe: dict, source: str) -> list[str]:
        c = self.comment
        lines = [
            f"{c} Neural BRDF generated by `neural-brdf codegen --target {self.name}` from "
            f"{source}.",
            f"{c} Generated code: do not edit; regenerate from the ONNX file instead.",
            f"{c}",
        ]
        for key in (
            "producer",
            "target",
            "encoding",
            "max_albedo",
            "hemispherical_albedo",
            "parity_rel_error",
        ):
            if key in meta:
                lines.append(f"{c} {key}: {comment_value(meta[key])}")
        lines.append(
            f"{c} sampling lobe: {lobe_format.KIND}, {lobe['distribution']}, "
            f"alpha_x={lobe['alpha_x']:.6g}, "
            f"alpha_y={lobe['alpha_y']:.6g}, weight={lobe['weight']:.6g}"
            + (", retro (turned by pi about the normal)" if lobe["retro"] else "")
            + (
                ", per-incidence table (alpha_x, alpha_y, weight by cos theta_i)"
                if lobe.get("table")
                else ""
            )
        )
        lines += [
            f"{c}",
            f"{c} Directions are in the local shading frame (z = normal, x = tangent), "
            "both pointing away from",
            f"{c} the surface; every function normalises them (a non-finite or "
            "zero-length one gives f = 0,",
            f"{c} pdf = 0).  {self.fn('eval')} returns f(wi, wo) in 1/sr per RGB channel "
            "WITHOUT the cosine",
            f"{c} (0 below the horizon).  {self.fn('sample')} draws wo from the lobe "
            "(u1, u2 uniform in [0, 1))",
            f"{c} and returns its pdf, as {self.fn('pdf')} would (0: reject the sample; "
            "a u not finite or not in",
            f"{c} [0, 1) gives wo = (0, 0, -1) and pdf 0).",
            f"{c} Estimator: f * cos(theta_o) / pdf.",
        ]
        if "format_version" not in meta:  # a graph of another tool: its f is its own
            lines += [
                f"{c}",
                f"{c} CAUTION: the file has no neural-brdf metadata (no format_version): "
                f"{self.fn('eval')} evaluates its graph",
                f"{c} as it is, and nothing says that the graph normalises its directions, "
                "gives 0 below the horizon",
                f"{c} or 0 for a non-finite one, as the files neural-brdf exports do.",
            ]
        for k, tex in enumerate(self.textures):
            rows, width = tex.data.shape
            if k == 0:
                lines += [
                    f"{c}",
                    f"{c} Textured: {self.fn('eval')} takes uv as well; its weight table is "
                    "bound by the host, not written",
                    f'{c} here (docs/codegen.md, "Textured files"): float32, row-major '
                    "[row][channel], row = the texel",
                    f"{c} j * R + i (column i along u, row j along v); the data: "
                    "`neural-brdf codegen -o NAME` writes",
                    f"{c} NAME's stem + .texture<k>.f32 (raw little-endian), or "
                    "neural_brdf.backends.textures(model).",
                ]
            lines.append(
                f"{c} {self.texture_name(k)}: {rows} rows x {width} channels = "
                f"{rows * width} floats ({rows * width * 4} bytes)"
                + (self.texture_role(k) if self.normal_reads is not None else "")
            )
        if self.normal_reads is not None:
            lines += self.normal_header()
        return lines + [f"{c}"] + [f"{c} {u}" for u in self.usage()]

    def texture_role(self, k: int) -> str:
        """Which functions read texture k (a file with the output n)."""
        users = [
            fname
            for fname, reads in (
                (self.fn("eval"), self.f_reads),
                (self.fn("normal"), self.normal_reads or []),
            )
            if k in reads
        ]
        what = "the normal texels, " if users == [self.fn("normal")] else ""
        return f"; {what}read by {' and '.join(users)}"

    def normal_header(self) -> list[str]:
        """The header's lines on neural_brdf_normal (a file with the output n)."""
        c = self.comment
        reads = ", ".join(self.texture_name(k) for k in self.normal_reads or [])
        return [
            f"{c}",
            f"{c} Normal field: {self.fn('normal')}(uv) returns the teacher's unit shading "
            "normal n at uv, in the",
            f"{c} unperturbed shading frame (a normal map: wrapping bilinear look-up of "
            "the texels, normalised;",
            f"{c} (0, 0, 1) where uv is not finite).  A renderer calls it first, rotates "
            "its frame to n",
            f"{c} (s = normalize(x - n n.x), t = n x s, as Mitsuba's normalmap), "
            "expresses wi and wo in it",
            f"{c} and calls {self.fn('eval')} (and _pdf, _sample) there; metadata "
            "texture.normal_field holds",
            f"{c} flip_invalid_normals and use_shadowing_function.  Its texels "
            f"({reads or 'none bound'}): [Rv * Ru, 3],",
            f"{c} row j * Ru + i (column i along u, row j along v; Ru, Rv: "
            "texture.normal_field.resolution).",
        ]

    def usage(self) -> list[str]:
        return []

    def generate(self, model, *, lobe: dict | None = None, source: str | None = None) -> str:
        """The file's text for an ONNX model (path, bytes or ModelProto).  ``source``
        names the model in the header comment and in errors (default: the path as
        given; an error of bytes or a ModelProto says ``codegen``)."""
        src = source_name(model, source)
        proto = graph.load(model)
        f, n, listed = lower_file(proto, source=src)  # checks the file's contract
        prog = f.prog
        if lobe is None:
            try:
                lobe = lobe_format.from_metadata(prog.metadata)
            except InputError as e:
                raise InputError(f"{src}: {e}") from None
            if lobe is None:
                # a file exported before the lobe was stored, or another tool's: fitted
                # to its graph, as render and the Mitsuba plugin do (about a second);
                # the sampler only needs a lobe whose pdf it knows, eval is the graph's
                from neural_brdf.physics import lobe_fit

                lobe = lobe_fit.fit_onnx(proto.SerializeToString())
        lobe = lobe_format.complete(lobe)
        shape = {k: lobe[k] for k in ("alpha_x", "alpha_y", "weight", "retro")}
        shape["table"] = lobe.get("table")
        shape["distribution"] = lobe["distribution"]
        if source is None:
            source = (
                str(model)
                if not isinstance(model, (bytes, bytearray)) and not hasattr(model, "graph")
                else "an ONNX model"
            )
        try:
            if n is None:
                self.bind(f.textures)
            else:  # one texture list for the file: f's numbers, then n's
                self.textures = listed
                self.f_reads = f.numbers
                self.normal_reads = n.numbers
                self.bind(f.textures, f.numbers)
            parts = self.helpers()
            parts += self.tables(prog)
            parts += self.texture_decls()
            parts += self.function(
                self.fn("eval"),
                prog,
                "f(wi, wo, uv): the BRDF in 1/sr per RGB channel, no cosine."
                if UV in prog.inputs
                else "f(wi, wo): the BRDF in 1/sr per RGB channel, no cosine.",
            )
            header = self.header(prog.metadata, lobe, source)
            if n is not None:  # its own literal tables (if any) just before it
                self.bind(n.textures, n.numbers)
                self.table_stem = "normal_table"
                parts += self.tables(n.prog)
                parts += self.function(
                    self.fn("normal"),
                    n.prog,
                    "n(uv): the unit shading normal at uv in the unperturbed frame "
                    "(evaluate f in the frame rotated to n).",
                )
        finally:
            self.bind([])  # the sampling programs read no texture
            self.table_stem = CStyleRenderer.table_stem
            self.normal_reads = None
        parts += self.function(
            self.fn("pdf"),
            lobe_ir.pdf_program(**shape),
            "The sampling lobe's solid-angle density of wo given wi (0 if either is not "
            "finite or has zero length).",
        )
        parts += self.function(
            self.fn("sample"),
            lobe_ir.sample_program(**shape),
            "Draws wo from the lobe (u1, u2 uniform in [0, 1)); returns its pdf (0: reject; "
            "a u not finite or not in [0, 1): wo = (0, 0, -1), pdf 0).",
        )
        return self.wrap(header, parts)

    def bind(self, textures: list[graph.Texture], numbers: list[int] | None = None) -> None:
        """Render the tables of ``textures`` (one program's, :func:`graph.textures`) as
        reads of bound buffers from now on.  ``numbers``: each one's number in the file's
        list ``self.textures``; None: they are the file's list, numbered 0, 1, ..."""
        if numbers is None:
            self.textures = list(textures)
            self.f_reads = numbers = list(range(len(textures)))
        self.reads = list(numbers)
        self.fetches = {
            t: (numbers[i], channel)
            for i, tex in enumerate(textures)
            for t, channel in tex.channels.items()
        }
