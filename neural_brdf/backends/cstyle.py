"""The base class of the source-code back ends: a lowered program -> a C-like function.

    from neural_brdf.backends.c import CRenderer
    text = CRenderer().generate("model.onnx")        # the whole header file, as a string

One lowered instruction list (:mod:`neural_brdf.graph`) is rendered as one named
temporary per instruction, one statement per line, with the constants inlined by one
rule per kind (:meth:`CStyleRenderer.literal`).  A dialect (C, GLSL, WGSL) is a short
subclass: type names, literal spellings, the few operators and functions that differ,
how a function binds its inputs and returns its outputs, and the file around them.
Adding a language (HLSL, Metal, ...) is one file with such a subclass and one line in
:data:`neural_brdf.backends.REGISTRY`.

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
"""

from __future__ import annotations

import math

import numpy as np

from neural_brdf import graph
from neural_brdf.backends import lobe_ir
from neural_brdf.errors import InputError
from neural_brdf.fileformat import INPUT_WIDTHS, OUTPUT, SIGNATURES, UV
from neural_brdf.fileformat import lobe as lobe_format  # the stored lobe: its schema

PREFIX = "neural_brdf"


class CStyleRenderer:
    """Renders programs into a C-like language; dialects override the class attributes
    and the hooks below."""

    name = "cstyle"
    comment = "//"
    types = {"float": "float", "int": "int", "bool": "bool"}
    # unary instruction -> function name (``neg`` and ``not`` are operators)
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
        "isnan": f"{PREFIX}_isnan",
        "isinf": f"{PREFIX}_isinf",
    }
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
    # the bound tables of the program being rendered (set by generate for the BRDF's
    # graph; the sampling programs have none): table number -> (texture, channel)
    textures: list[graph.Texture] = []
    fetches: dict[int, tuple[int, int]] = {}

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
        return f"{PREFIX}_table{k}"

    def texture_name(self, k: int) -> str:
        return f"{PREFIX}_texture{k}"

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
                value = " ".join(str(meta[key]).split())  # one line
                lines.append(f"{c} {key}: {value[:200]}")
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
            f"{c} Directions are unit vectors in the local shading frame (z = "
            f"normal, x = tangent), both pointing",
            f"{c} away from the surface.  neural_brdf_eval returns f(wi, wo) in 1/sr "
            f"per RGB channel WITHOUT",
            f"{c} the cosine (0 below the horizon).  neural_brdf_sample draws wo from "
            f"the lobe (u1, u2 uniform",
            f"{c} in [0, 1)) and returns its pdf, as neural_brdf_pdf would.  Estimator: "
            f"f * cos(theta_o) / pdf.",
        ]
        for k, tex in enumerate(self.textures):
            rows, width = tex.data.shape
            if k == 0:
                lines += [
                    f"{c}",
                    f"{c} Textured: neural_brdf_eval takes uv as well; its weight table is "
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
            )
        return lines + [f"{c}"] + [f"{c} {u}" for u in self.usage()]

    def usage(self) -> list[str]:
        return []

    def generate(self, model, *, lobe: dict | None = None, source: str | None = None) -> str:
        """The file's text for an ONNX model (path, bytes or ModelProto)."""
        proto = graph.load(model)
        prog = graph.lower(proto)
        # the file's contract (fileformat): inputs wi, wo [N, 3] (and uv [N, 2]: a
        # textured file), output f [N, 3]
        if (
            tuple(prog.inputs) not in SIGNATURES
            or list(prog.outputs) != [OUTPUT]
            or any(prog.inputs[name] != INPUT_WIDTHS[name] for name in prog.inputs)
            or len(prog.outputs[OUTPUT]) != 3
        ):
            raise InputError(
                "codegen: expected inputs wi, wo [N, 3] (and uv [N, 2]) and output "
                f"{OUTPUT} [N, 3], got {prog.inputs} -> "
                f"{ {k: len(v) for k, v in prog.outputs.items()} }"
            )
        if lobe is None:
            lobe = lobe_format.from_metadata(prog.metadata)
            if lobe is None:
                raise InputError(
                    "codegen: the model has no stored sampling lobe (metadata "
                    f"{lobe_format.KEY!r}); re-export it with this version"
                )
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
            self.bind(graph.textures(prog, UV))
            parts = self.helpers()
            parts += self.tables(prog)
            parts += self.texture_decls()
            parts += self.function(
                f"{PREFIX}_eval",
                prog,
                "f(wi, wo, uv): the BRDF in 1/sr per RGB channel, no cosine."
                if UV in prog.inputs
                else "f(wi, wo): the BRDF in 1/sr per RGB channel, no cosine.",
            )
            header = self.header(prog.metadata, lobe, source)
        finally:
            self.bind([])  # the sampling programs read no texture
        parts += self.function(
            f"{PREFIX}_pdf",
            lobe_ir.pdf_program(**shape),
            "The sampling lobe's solid-angle density of wo given wi.",
        )
        parts += self.function(
            f"{PREFIX}_sample",
            lobe_ir.sample_program(**shape),
            "Draws wo from the lobe (u1, u2 uniform in [0, 1)); returns its pdf (0: reject).",
        )
        return self.wrap(header, parts)

    def bind(self, textures: list[graph.Texture]) -> None:
        """Render the tables of ``textures`` as reads of bound buffers from now on."""
        self.textures = textures
        self.fetches = {
            t: (k, channel) for k, tex in enumerate(textures) for t, channel in tex.channels.items()
        }
