"""GLSL ES 3.00 (WebGL2), also valid desktop GLSL 4.50 / Vulkan: functions to paste or
include after the ``#version`` line and ``precision highp float; precision highp int;``.

    vec3 f = neural_brdf_eval(wi, wo);                 // vec3 wi, wo
    vec3 wo2;
    float pdf = neural_brdf_sample(wi, u1, u2, wo2);   // float u1, vec2 u2; out vec3 wo2

A textured file gives ``vec3 neural_brdf_eval(vec3 wi, vec3 wo, vec2 uv)``; its weight table
is bound by the host (docs/codegen.md, "Textured files"): under GLSL ES (WebGL2 has no
storage buffers) a ``highp sampler2D`` of one R32F texel per float, NEURAL_BRDF_TEXTURE_WIDTH
(default 1024) texels to a row, read with texelFetch; in desktop GLSL (4.30 and later, and
Vulkan) a std430 ``readonly buffer`` at binding NEURAL_BRDF_TEXTURE<k>_BINDING (default k).
One with the normal field (output n) also gives ``vec3 neural_brdf_normal(vec2 uv)``, its
texels bound the same way (texture 1).

NaN and infinity tests are bit tests (``floatBitsToUint``): GLSL lets a compiler assume
that isnan() is false.  GLSL has no erf; it is a polynomial (Abramowitz & Stegun 7.1.26).

``GLSLRenderer(prefix="gold")`` names everything the file defines ``gold_...`` (its macros
``GOLD_...``, its buffer blocks ``GoldTexture<k>``), so that the files of several models
can be pasted into one shader; the default is ``neural_brdf``.
"""

from __future__ import annotations

import numpy as np

from neural_brdf import graph
from neural_brdf.backends.cstyle import CStyleRenderer, camel

VEC = {1: "float", 2: "vec2", 3: "vec3", 4: "vec4"}


def erf_helper(fn: str, ret: str, decl: str, ftype: str, sfx: str) -> list[str]:
    """erf(x) = 1 - (a1 t + ... + a5 t^5) exp(-x^2), t = 1 / (1 + p |x|), |error| <
    1.5e-7 (Abramowitz & Stegun 1964, formula 7.1.26); odd in x."""
    k = {
        "p": "0.3275911",
        "a1": "0.254829592",
        "a2": "-0.284496736",
        "a3": "1.421413741",
        "a4": "-1.453152027",
        "a5": "1.061405429",
    }
    k = {n: f"{v}{sfx}" for n, v in k.items()}
    return [
        f"{fn}{ret} {{",
        f"    {decl}a = abs(x);",
        f"    {decl}t = 1.0{sfx} / (1.0{sfx} + {k['p']} * a);",
        f"    {decl}poly = t * ({k['a1']} + t * ({k['a2']} + t * ({k['a3']} + t * "
        f"({k['a4']} + t * {k['a5']}))));",
        f"    {decl}y = 1.0{sfx} - poly * exp(-a * a);",
        "    return sign(x) * y;",
        "}",
    ]


class GLSLRenderer(CStyleRenderer):
    name = "glsl"
    vectors = VEC  # width -> type name
    helper_ops = CStyleRenderer.helper_ops | {"erf"}  # GLSL has no erf

    def bitcast_float(self, bits: str) -> str:
        return f"uintBitsToFloat({bits})"

    def helpers(self) -> list[str]:
        return [
            f"bool {self.fn('isnan')}(float x) {{ return (floatBitsToUint(x) & 0x7fffffffu) > "
            "0x7f800000u; }",
            f"bool {self.fn('isinf')}(float x) {{ return (floatBitsToUint(x) & 0x7fffffffu) == "
            "0x7f800000u; }",
            *erf_helper(f"float {self.fn('erf')}(float x)", "", "float ", "float", ""),
            "",
        ]

    def table(self, name: str, values: np.ndarray) -> str:
        t = "float" if values.dtype.kind == "f" else "int"
        n = len(values)
        body = "\n".join(f"    {row}" for row in self.table_values(values))
        return f"const {t} {name}[{n}] = {t}[{n}](\n{body}\n);\n"

    def fetch(self, k: int, element: str) -> str:
        return self.call(self.fn(f"fetch{k}"), element)

    def texture_decls(self) -> list[str]:
        """Per bound texture a reader ``neural_brdf_fetch<k>(int e)`` of its float e, over
        a texture (GL_ES, which WebGL2 defines) or a storage buffer (desktop GLSL); the
        host can change the width and the binding with #defines before this file."""
        if not self.textures:
            return []
        width = self.macro("TEXTURE_WIDTH")
        lines = [f"#ifndef {width}", f"#define {width} 1024", "#endif"]
        for k in range(len(self.textures)):
            name = self.texture_name(k)
            binding = self.macro(f"TEXTURE{k}_BINDING")
            lines += [
                "#ifdef GL_ES",
                f"uniform highp sampler2D {name};",
                f"float {self.fn(f'fetch{k}')}(int e) {{ return texelFetch({name}, "
                f"ivec2(e % {width}, e / {width}), 0).r; }}",
                "#else",
                f"#ifndef {binding}",
                f"#define {binding} {k}",
                "#endif",
                f"layout(std430, binding = {binding}) readonly buffer "
                f"{camel(self.prefix)}Texture{k} "
                f"{{ float {name}[]; }};",
                f"float {self.fn(f'fetch{k}')}(int e) {{ return {name}[e]; }}",
                "#endif",
            ]
        return lines + [""]

    def function(self, fname: str, prog: graph.Program, doc: str) -> list[str]:
        lines, rendered = self.body(prog)
        outs = list(prog.outputs.items())
        ret_name, ret_cols = outs[-1]
        params = [f"{self.vectors[w]} {n}" for n, w in prog.inputs.items()]
        params += [f"out {self.vectors[len(c)]} {n}" for n, c in outs[:-1]]
        body = [f"    {line}" for line in lines]
        for n, cols in outs[:-1]:
            body.append(f"    {n} = {self.vector(cols, rendered)};")
        body.append(f"    return {self.vector(ret_cols, rendered)};")
        sig = f"{self.vectors[len(ret_cols)]} {fname}({', '.join(params)})"
        return [f"// {doc}", sig, "{", *body, "}", ""]

    def vector(self, cols: list[int], rendered: list[str]) -> str:
        parts = [rendered[c] for c in cols]
        if len(parts) == 1:
            return parts[0]
        return f"{self.vectors[len(parts)]}({', '.join(parts)})"

    def usage(self) -> list[str]:
        ev, smp = self.fn("eval"), self.fn("sample")
        head = [
            "#version 300 es  (or #version 450)",
            "precision highp float;",
            "precision highp int;",
            "<this file>",
        ]
        tail = [f"vec3 wo2; float p2 = {smp}(wi, u1, u2, wo2);  // vec2 u2"]
        if self.normal_reads is not None:
            return [
                *head,
                f"vec3 n = {self.fn('normal')}(uv);  // vec2 uv; first: rotate the frame to n",
                f"vec3 f = {ev}(wi, wo, uv);  // wi, wo in n's frame",
                *tail,
            ]
        if self.textures:
            return [*head, f"vec3 f = {ev}(wi, wo, uv);  // vec2 uv", *tail]
        return [*head, f"vec3 f = {ev}(wi, wo);", *tail]
