"""WGSL (WebGPU): functions to paste into a shader module.

    let f = neural_brdf_eval(wi, wo);                 // vec3<f32>
    let s = neural_brdf_sample(wi, u1, u2);           // f32, vec2<f32> -> NeuralBrdfSample
    // s.wo, s.pdf

A textured file gives ``neural_brdf_eval(wi, wo, uv)`` (uv: vec2<f32>) and binds its weight
table as ``@group(1) @binding(k) var<storage, read> neural_brdf_texture<k>: array<f32>``
(the group: ``WGSLRenderer(group=...)``, ``backends.generate(..., group=...)``, an int
from 0 to 2^31 - 1, :func:`check_group`; WGSL has no preprocessor).  One with the
normal field (output n) also gives ``fn neural_brdf_normal(uv: vec2<f32>) ->
vec3<f32>``, its texels at binding 1.  docs/codegen.md, "Textured files".

WGSL has no isnan/isinf: they are bit tests on ``bitcast<u32>``; no erf either (a
polynomial, as in GLSL).

``WGSLRenderer(prefix="gold")`` names everything the file defines ``gold_...`` (and its
sample struct ``GoldSample``), so that the files of several models can be pasted into one
module (give each textured one its own ``group``); the default is ``neural_brdf``.
"""

from __future__ import annotations

import numpy as np

from neural_brdf import graph
from neural_brdf.backends.cstyle import PREFIX, CStyleRenderer, camel
from neural_brdf.backends.glsl import erf_helper
from neural_brdf.errors import InputError

VEC = {1: "f32", 2: "vec2<f32>", 3: "vec3<f32>", 4: "vec4<f32>"}
# WGSL: the value of @group is a non-negative i32.  A WebGPU device takes groups below
# its maxBindGroups limit, which is at least 4 (groups 0 to 3 work on every device).
MAX_GROUP = 2**31 - 1


def check_group(group) -> int:
    """``group`` if it is a WGSL bind group (an int, not a bool, from 0 to
    :data:`MAX_GROUP`), else a one-line InputError naming ``group``."""
    if (
        isinstance(group, (bool, np.bool_))
        or not isinstance(group, (int, np.integer))
        or not 0 <= group <= MAX_GROUP
    ):
        raise InputError(
            f"group: expected a WGSL bind group, an int from 0 to {MAX_GROUP} (groups 0 to 3 "
            f"work on every WebGPU device), got {group!r}"
        )
    return int(group)


class WGSLRenderer(CStyleRenderer):
    name = "wgsl"
    vectors = VEC  # width -> type name
    types = {"float": "f32", "int": "i32", "bool": "bool"}
    helper_ops = CStyleRenderer.helper_ops | {"erf"}  # WGSL has no erf
    float_suffix = "f"
    int_suffix = "i"

    def __init__(self, group: int = 1, *, prefix: str = PREFIX):
        super().__init__(prefix=prefix)
        # group 1: a host's own bindings are most often in group 0
        self.group = check_group(group)
        self.sample_struct = f"{camel(self.prefix)}Sample"  # NeuralBrdfSample

    def bitcast_float(self, bits: str) -> str:
        return f"bitcast<f32>({bits})"

    def select(self, c: str, a: str, b: str) -> str:
        return f"select({b}, {a}, {c})"

    def cast(self, x: str, src: str, dst: str) -> str:
        if dst == "bool":
            return f"({x} != {self.literal(0, src)})"
        return f"{self.types[dst]}({x})"

    def declare(self, dtype: str, name: str, expr: str) -> str:
        return f"let {name}: {self.types[dtype]} = {expr};"

    def helpers(self) -> list[str]:
        bits = "(bitcast<u32>(x) & 0x7fffffffu)"
        return [
            f"fn {self.fn('isnan')}(x: f32) -> bool {{ return {bits} > 0x7f800000u; }}",
            f"fn {self.fn('isinf')}(x: f32) -> bool {{ return {bits} == 0x7f800000u; }}",
            *erf_helper(f"fn {self.fn('erf')}(x: f32)", " -> f32", "let ", "f32", "f"),
            "",
            f"struct {self.sample_struct} {{",
            "    wo: vec3<f32>,",
            "    pdf: f32,",
            "}",
            "",
        ]

    def table(self, name: str, values: np.ndarray) -> str:
        t = "f32" if values.dtype.kind == "f" else "i32"
        body = "\n".join(f"    {row}" for row in self.table_values(values))
        # var<private>, not const: naga turns a dynamically indexed const array into a
        # copy of the whole array per access, which ran 100x slower on lavapipe
        ty = f"array<{t}, {len(values)}>"
        return f"var<private> {name}: {ty} = {ty}(\n{body}\n);\n"

    def texture_decls(self) -> list[str]:
        lines = [
            f"@group({self.group}) @binding({k}) var<storage, read> {self.texture_name(k)}: "
            "array<f32>;"
            for k in range(len(self.textures))
        ]
        return lines + [""] if lines else []

    def function(self, fname: str, prog: graph.Program, doc: str) -> list[str]:
        lines, rendered = self.body(prog)
        outs = list(prog.outputs.items())
        params = [f"{n}: {self.vectors[w]}" for n, w in prog.inputs.items()]
        body = [f"    {line}" for line in lines]
        if len(outs) == 1:
            ret = self.vectors[len(outs[0][1])]
            body.append(f"    return {self.vector(outs[0][1], rendered)};")
        else:
            ret = self.sample_struct
            fields = ", ".join(self.vector(c, rendered) for _, c in outs)
            body.append(f"    return {ret}({fields});")
        return [f"// {doc}", f"fn {fname}({', '.join(params)}) -> {ret} {{", *body, "}", ""]

    def vector(self, cols: list[int], rendered: list[str]) -> str:
        parts = [rendered[c] for c in cols]
        if len(parts) == 1:
            return parts[0]
        return f"{self.vectors[len(parts)]}({', '.join(parts)})"

    def usage(self) -> list[str]:
        ev, smp = self.fn("eval"), self.fn("sample")
        tail = [f"let s = {smp}(wi, u1, u2);      // s.wo, s.pdf (u2: vec2<f32>)"]
        if self.normal_reads is not None:
            return [
                f"let n = {self.fn('normal')}(uv);              // vec3<f32>; first: the frame",
                f"let f = {ev}(wi, wo, uv);        // wi, wo in n's frame",
                *tail,
            ]
        if self.textures:
            return [f"let f = {ev}(wi, wo, uv);        // vec3<f32> (uv: vec2<f32>)", *tail]
        return [f"let f = {ev}(wi, wo);            // vec3<f32>", *tail]
