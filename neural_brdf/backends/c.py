"""C99: one self-contained header (``<math.h>``, ``<stdint.h>`` and ``<string.h>`` only) of
``static inline`` functions.

    #include "brdf.h"                     // neural-brdf codegen model.onnx --target c -o brdf.h
    float f[3];
    neural_brdf_eval(wi, wo, f);          // const float wi[3], wo[3]
    float wo2[3];
    float pdf = neural_brdf_sample(wi, u1, u2, wo2);    // float u1, const float u2[2]

A textured file (inputs wi, wo, uv) binds its weight table through a pointer parameter
per bound texture, after uv (docs/codegen.md, "Textured files"):

    neural_brdf_eval(wi, wo, uv, weights, f);   // const float uv[2], const float *weights
                                                // (NEURAL_BRDF_TEXTURE0_ROWS x _CHANNELS)

and one with the normal field (output n) also gives, its texels a pointer too:

    neural_brdf_normal(uv, texels, n);          // const float *texels (texture 1), float n[3]

Booleans are ints; min/max are comparisons (no libm call); fused multiply-adds are
written ``a * b + c`` (a compiler contracts them only where its floating-point
contraction setting allows: GCC's ISO C modes, e.g. ``-std=c99``, do not).  NaN and
infinity tests are bit tests of the float's ``uint32_t`` (``memcpy``), not isnan() and
isinf(), which ``-ffast-math`` (``-ffinite-math-only``) folds to 0.

``CRenderer(prefix="gold")`` names everything the header defines ``gold_...`` (its
macros ``GOLD_...``, its include guard ``GOLD_H``), so that the headers of several models
can be included in one translation unit; the default is ``neural_brdf``.
"""

from __future__ import annotations

import numpy as np

from neural_brdf import graph
from neural_brdf.backends.cstyle import CStyleRenderer


class CRenderer(CStyleRenderer):
    name = "c"
    types = {"float": "float", "int": "int", "bool": "int"}
    functions = {
        **CStyleRenderer.functions,
        **{
            # the IR's functions (graph.UNARY, but neg, an operator, and abs) in
            # float: sqrtf, expf, ...
            op: f"{op}f"
            for op in (*(u for u in graph.UNARY if u not in ("neg", "abs")), "pow")
        },
        "abs": "fabsf",
    }
    float_suffix = "f"

    def bool_literal(self, v: bool) -> str:
        return "1" if v else "0"

    def special_float(self, v: float) -> str:
        return "NAN" if v != v else ("INFINITY" if v > 0 else "-INFINITY")

    def cast(self, x: str, src: str, dst: str) -> str:
        if dst == "bool":
            return f"({x} != {self.literal(0, src)})"
        return f"({self.types[dst]}){x}"

    def minmax(self, op: str, dtype: str, a: str, b: str) -> str:
        return self.call(self.fn(f"{op}{'f' if dtype == 'float' else 'i'}"), a, b)

    def clamp_index(self, i: str, last: int) -> str:
        return self.call(self.fn("clampi"), i, "0", str(last))

    def input_component(self, name: str, col: int, width: int) -> str:
        return name if width == 1 else f"{name}[{col}]"

    def helpers(self) -> list[str]:
        lines = []
        for t, s in (("float", "f"), ("int", "i")):
            sig = f"static inline {t} {self.prefix}_%s{s}({t} a, {t} b)"
            lines += [
                sig % "max" + " { return a > b ? a : b; }",
                sig % "min" + " { return a < b ? a : b; }",
            ]
        # bit tests, not isnan()/isinf(): -ffast-math folds those to 0 (module doc)
        bits = "uint32_t b; memcpy(&b, &x, sizeof b); return (b & 0x7fffffffu)"
        lines += [
            f"static inline int {self.prefix}_clampi(int i, int lo, int hi) "
            "{ return i < lo ? lo : (i > hi ? hi : i); }",
            f"static inline int {self.fn('isnan')}(float x) {{ {bits} > 0x7f800000u; }}",
            f"static inline int {self.fn('isinf')}(float x) {{ {bits} == 0x7f800000u; }}",
            "",
        ]
        return lines

    def table(self, name: str, values: np.ndarray) -> str:
        t = "float" if values.dtype.kind == "f" else "int"
        body = "\n".join(f"    {row}" for row in self.table_values(values))
        return f"static const {t} {name}[{len(values)}] = {{\n{body}\n}};\n"

    def function(self, fname: str, prog: graph.Program, doc: str) -> list[str]:
        lines, rendered = self.body(prog)
        outs = list(prog.outputs.items())
        ret = outs[-1] if len(outs[-1][1]) == 1 else None
        params = [
            f"float {n}" if w == 1 else f"const float {n}[{w}]" for n, w in prog.inputs.items()
        ]
        params += [f"const float *{self.texture_name(k)}" for k in self.reads]
        params += [f"float {n}[{len(cols)}]" for n, cols in outs if (n, cols) != ret]
        sig = f"static inline {'float' if ret else 'void'} {fname}({', '.join(params)})"
        body = [
            f"    const {line}"
            if line.startswith("float wi")
            or line.startswith("float wo")
            or line.startswith("float u")
            else f"    {line}"
            for line in lines
        ]
        for n, cols in outs:
            if (n, cols) != ret:
                body += [f"    {n}[{k}] = {rendered[c]};" for k, c in enumerate(cols)]
        if ret:
            body.append(f"    return {rendered[ret[1][0]]};")
        return [f"/* {doc} */", sig, "{", *body, "}", ""]

    def texture_decls(self) -> list[str]:
        """The size of each bound texture, for the host's buffer (the data are a
        parameter of neural_brdf_eval: a header has no place to keep a pointer that every
        translation unit shares)."""
        lines = []
        for k, tex in enumerate(self.textures):
            rows, width = tex.data.shape
            name = self.macro(f"TEXTURE{k}")
            lines += [f"#define {name}_ROWS {rows}", f"#define {name}_CHANNELS {width}"]
        return lines + [""] if lines else []

    def usage(self) -> list[str]:
        ev, pdf, smp = self.fn("eval"), self.fn("pdf"), self.fn("sample")
        include = '#include "this_file.h"   (C99, <math.h>, <stdint.h>, <string.h>; link with -lm)'
        tail = [
            f"float p = {pdf}(wi, wo);",
            f"float wo2[3]; float p2 = {smp}(wi, u1, u2, wo2);  (float u1, u2[2])",
        ]
        if self.normal_reads is not None:
            args = "".join(f"{self.texture_name(k)}, " for k in self.f_reads)
            nargs = "".join(f"{self.texture_name(k)}, " for k in self.normal_reads)
            return [
                include,
                f"float n[3]; {self.fn('normal')}(uv, {nargs}n);  (float uv[2]; first: the frame)",
                f"float f[3]; {ev}(wi, wo, uv, {args}f);  (wi, wo in n's frame)",
                *tail,
            ]
        if self.textures:
            args = ", ".join(self.texture_name(k) for k in range(len(self.textures)))
            return [include, f"float f[3]; {ev}(wi, wo, uv, {args}, f);  (float uv[2])", *tail]
        return [include, f"float f[3]; {ev}(wi, wo, f);", *tail]

    def wrap(self, header: list[str], parts: list[str]) -> str:
        guard = self.macro("H")  # NEURAL_BRDF_H: one per prefix
        # a comment marker inside a metadata value must not end the block comment
        body = [" *" + line[2:].replace("*/", "* /").replace("/*", "/ *") for line in header]
        text = [
            "/*",
            *body,
            " */",
            f"#ifndef {guard}",
            f"#define {guard}",
            "",
            "#include <math.h>",
            "#include <stdint.h>",
            "#include <string.h>",
            "",
            *parts,
            f"#endif /* {guard} */",
        ]
        return "\n".join(text) + "\n"
