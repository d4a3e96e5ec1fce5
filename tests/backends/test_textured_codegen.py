"""Code generation of a textured file (inputs wi, wo, uv): every source back end evaluates
the graph as onnxruntime does, its weight table bound by the host (docs/codegen.md,
"Textured files"), not written as literals.

* the bound data (``neural_brdf.backends.textures``, the CLI's ``.texture0.f32``) equal
  the ONNX initializer bit for bit, and the generated code holds no copy of it;
* C (gcc, ``-std=c99 -Wall -Werror``), WGSL (wgpu on lavapipe, the texture a storage
  buffer in group 1) and GLSL ES 3.00 (WebGL2 in headless Chromium, the texture an R32F
  sampler, a row width set by the host's #define) match onnxruntime to the tolerances
  of test_codegen.py at random uv (outside [0, 1) and negative), texel centres and
  edges, integers and the rounding cases next to them, with test_codegen's (wi, wo)
  rows; the same code with the texture's rows reversed does not (the data are read);
* the desktop GLSL (SSBO) and ES variants validate with glslangValidator;
* C with a prefix beside the default header in one translation unit, and C compiled with
  -ffast-math: NaN / inf uv and hostile directions still give exactly 0 (bit tests);
* a two-input file renders as before (no texture, no uv) and a table that cannot be
  bound (an int table at uv-dependent indices) is a one-line error.

The model: three small compact lobes (distinct random heads) and a 12 x 12 field
of 3 weights, random, built in torch (no training), exported by the project's exporter.
The mutations checked by hand while writing this: a channel read off by one, the rows
reversed (also a test below), the clamp one row short.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper
from test_codegen import C_TOL, GPU_TOL, pairs

from cli_helpers import assert_one_line_error, cli
from neural_brdf import backends, graph
from neural_brdf.backends.cstyle import CStyleRenderer
from neural_brdf.errors import InputError
from neural_brdf.export import relative_difference
from neural_brdf.fileformat import lobe as lobe_format

R, K = 12, 3  # texels per side (not a power of two), lobes
LOBE = {"kind": lobe_format.KIND, "alpha": 0.3, "weight": 0.5}
ES_WIDTH = 100  # floats per texel row of the WebGL texture: 432 floats -> 5 rows, padded


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    """(path of the model, its weight table [R * R, K] as the ONNX initializer holds it)."""
    import torch

    from neural_brdf import config as cfgmod
    from neural_brdf import export, fileformat
    from neural_brdf.train.model import RawBRDF
    from neural_brdf.train.textured_model import TexturedBRDF, WeightField, exportable

    torch.manual_seed(0)
    # the compact recipe, smaller (an 8 x 8 x 4 grid, 16 hidden): the shader compilers of
    # SwiftShader and lavapipe take minutes over the full one's 12k table literals
    recipe = cfgmod.Model(hidden=[16], grid=cfgmod.Grid(size=8))
    lobes = [RawBRDF.from_config(recipe, init_value=v) for v in (0.1, 0.3, 0.6)[:K]]
    with torch.no_grad():  # distinct, coloured lobes: a channel mixed up changes f
        for lobe in lobes:
            torch.nn.init.normal_(lobe.mlp.head.weight, std=0.3)
    model = TexturedBRDF(lobes, WeightField(R, K, init_std=2.0))
    payload = export.to_onnx_bytes(exportable(model), 17, inputs=fileformat.SIGNATURES[1])
    proto = onnx.load_from_string(payload)
    helper.set_model_props(proto, {lobe_format.KEY: lobe_format.to_json(LOBE)})
    path = tmp_path_factory.mktemp("textured") / "model.onnx"
    path.write_bytes(proto.SerializeToString())
    (table,) = [
        onnx.numpy_helper.to_array(t) for t in proto.graph.initializer if list(t.dims) == [R * R, K]
    ]
    return path, table


HOSTILE_UV = [
    [np.nan, 0.3],
    [0.2, np.nan],
    [np.inf, 0.1],
    [0.1, -np.inf],
    [3e38, 0.5],
    [-3e38, 0.5],
]


def uv_rows(n: int, seed: int = 0) -> np.ndarray:
    """(n, 2) float32: the first rows combine special coordinates (texel centres and
    edges in several periods, integers, the float32 neighbours of 0 and 1, large values),
    the last are HOSTILE_UV, the rest uniform in [-3, 3)."""
    rng = np.random.default_rng(seed)
    centres, edges = (np.arange(R) + 0.5) / R, np.arange(R + 1) / R
    special = np.concatenate(
        [
            centres,
            edges,
            centres - 1.0,
            edges + 2.0,
            -edges,
            [-2.0, -1.0, 0.0, 1.0, 3.0, 1000.375, -250.8125],
            np.nextafter(np.float32([0.0, 0.0, 1.0, 1.0, -1.0]), np.float32([1, -1, 0, 2, 0])),
        ]
    ).astype(np.float32)
    uv = rng.uniform(-3.0, 3.0, (n, 2)).astype(np.float32)
    m = min(n // 2, 4 * len(special))
    i = np.arange(m)
    uv[:m, 0] = special[i % len(special)]
    uv[:m, 1] = special[(7 * i + i // len(special)) % len(special)]
    uv[-len(HOSTILE_UV) :] = HOSTILE_UV  # the graph is total: f = 0 where uv is not finite
    return uv


def rows(seed: int = 1):
    wi, wo = pairs(seed)
    return wi, wo, uv_rows(len(wi), seed)


def onnx_ref(model, wi, wo, uv) -> np.ndarray:
    sess = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    return sess.run(None, {"wi": wi, "wo": wo, "uv": uv})[0]


@pytest.fixture(scope="module")
def reference(textured):
    wi, wo, uv = rows()
    ref = onnx_ref(textured[0], wi, wo, uv)
    assert (ref != 0).sum() > 1000
    assert (ref[-len(HOSTILE_UV) :][:4] == 0).all()  # NaN and inf uv
    return wi, wo, uv, ref


def check_parity(got, wrong, ref, tol):
    """``got`` (the right texture) meets ``tol``; ``wrong`` (rows reversed) does not."""
    assert np.isfinite(got).all()
    assert (got[ref == 0] == 0).all()  # below the horizon, non-finite uv: exactly 0
    assert relative_difference(got, ref) <= tol
    assert relative_difference(wrong, ref) > 10 * tol


# ------------------------------------------------------------------ the bound data
def test_the_bound_data_are_the_initializer(textured):
    path, table = textured
    (data,) = backends.textures(path)
    assert data.dtype == np.float32 and data.shape == (R * R, K)
    assert np.array_equal(data, table)
    (tex,) = graph.textures(graph.lower(path))
    assert sorted(tex.channels.values()) == list(range(K))
    for target in backends.TARGETS:  # no literal copy: no array of R * R values
        text = backends.generate(path, target)
        assert f"[{R * R}]" not in text and f", {R * R}>" not in text, target
        assert "neural_brdf_texture0" in text


def test_a_two_input_file_is_rendered_as_before(textured):
    """A two-input graph with a Gather (test_codegen's every-op model) binds nothing: its
    text equals a rendering that never binds, and its eval takes (wi, wo) only."""
    from test_codegen import EVERY_OP_LOBE, every_op_model

    class NeverBinds:
        def bind(self, textures):
            CStyleRenderer.bind(self, [])  # type: ignore[arg-type]

    payload = every_op_model()
    assert graph.textures(graph.lower(payload)) == []
    for target in backends.TARGETS:
        cls = backends.get(target)
        text = cls().generate(payload, lobe=EVERY_OP_LOBE)
        assert text == type("Plain", (NeverBinds, cls), {})().generate(payload, lobe=EVERY_OP_LOBE)
        assert "texture" not in text and "uv" not in text
        assert "neural_brdf_table0" in text  # its table stays a literal
    c = backends.generate(payload, "c", lobe=EVERY_OP_LOBE)
    assert "neural_brdf_eval(const float wi[3], const float wo[3], float f[3])" in c
    # the textured file: uv and the texture pointer come before f
    c = backends.generate(textured[0], "c")
    assert (
        "neural_brdf_eval(const float wi[3], const float wo[3], const float uv[2], "
        "const float *neural_brdf_texture0, float f[3])" in c
    )


def test_cli_writes_the_texture_beside_the_code(textured, tmp_path, capsys):
    path, table = textured
    code, out, _ = cli(
        capsys, "codegen", str(path), "--target", "glsl", "-o", str(tmp_path / "b.glsl")
    )
    assert code == 0 and "b.texture0.f32" in out
    data = np.fromfile(tmp_path / "b.texture0.f32", "<f4")
    assert np.array_equal(data, table.reshape(-1))
    code, out, err = cli(capsys, "codegen", str(path), "--target", "wgsl", "-o", "-")
    assert code == 0 and "neural_brdf_texture0" in out and "not written" in err
    # with a prefix the textures are written too (found from the file's inputs, not the
    # default names in the code)
    args = ["codegen", str(path), "--target", "c", "--prefix", "gold"]
    code, out, _ = cli(capsys, *args, "-o", str(tmp_path / "g.h"))
    assert code == 0 and "g.texture0.f32" in out, out
    assert np.array_equal(np.fromfile(tmp_path / "g.texture0.f32", "<f4"), table.reshape(-1))
    assert "gold_eval" in (tmp_path / "g.h").read_text()


def test_a_table_that_cannot_be_bound_is_one_line(tmp_path, capsys):
    """An int table gathered at uv-dependent indices: no float buffer holds it."""
    f32 = TensorProto.FLOAT
    nodes = [
        helper.make_node("Slice", ["uv", "s0", "s1", "ax"], ["u"]),
        helper.make_node("Mul", ["u", "four"], ["u4"]),
        helper.make_node("Floor", ["u4"], ["fl"]),
        helper.make_node("Clip", ["fl", "lo", "hi"], ["cl"]),
        helper.make_node("Cast", ["cl"], ["idx"], to=TensorProto.INT64),
        helper.make_node("Squeeze", ["idx", "ax"], ["i"]),
        helper.make_node("Gather", ["T", "i"], ["g"], axis=0),
        helper.make_node("Cast", ["g"], ["gf"], to=TensorProto.FLOAT),
        helper.make_node("Add", ["wi", "wo"], ["s"]),
        helper.make_node("Mul", ["s", "gf"], ["f"]),
    ]
    inits = {
        "s0": np.array([0], np.int64),
        "s1": np.array([1], np.int64),
        "ax": np.array([1], np.int64),
        "four": np.array([4.0], np.float32),
        "lo": np.array(0.0, np.float32),
        "hi": np.array(3.0, np.float32),
        "T": np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9], [1, 1, 1]], np.int32),
    }
    g = helper.make_graph(
        nodes,
        "int_texture",
        [
            helper.make_tensor_value_info("wi", f32, ["N", 3]),
            helper.make_tensor_value_info("wo", f32, ["N", 3]),
            helper.make_tensor_value_info("uv", f32, ["N", 2]),
        ],
        [helper.make_tensor_value_info("f", f32, ["N", 3])],
        [onnx.numpy_helper.from_array(v, k) for k, v in inits.items()],
    )
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    helper.set_model_props(model, {lobe_format.KEY: lobe_format.to_json(LOBE)})
    with pytest.raises(InputError, match="bound as a float buffer, got int32 \\[4, 3\\]"):
        backends.generate(model.SerializeToString(), "c")
    bad = tmp_path / "int.onnx"
    bad.write_bytes(model.SerializeToString())
    code, _, err = cli(capsys, "codegen", str(bad), "--target", "wgsl", "-o", str(tmp_path / "x"))
    assert_one_line_error(code, err, "bound as a float buffer")
    with pytest.raises(InputError, match="group"):
        backends.generate(bad, "c", group=2)


# ------------------------------------------------------------------ C
DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include "model.h"

/* driver N ROWS TEXTURE OUT: rows of 8 float32 (wi, wo, uv) -> f, 3 float32 a row */
int main(int argc, char **argv)
{
    static float texture[NEURAL_BRDF_TEXTURE0_ROWS * NEURAL_BRDF_TEXTURE0_CHANNELS];
    long n, i;
    float row[8], f[3];
    FILE *in, *tex, *res;
    if (argc != 5) return 2;
    n = atol(argv[1]);
    in = fopen(argv[2], "rb");
    tex = fopen(argv[3], "rb");
    res = fopen(argv[4], "wb");
    if (!in || !tex || !res) return 2;
    if (fread(texture, sizeof(float), sizeof texture / sizeof(float), tex)
        != sizeof texture / sizeof(float)) return 3;
    for (i = 0; i < n; i++) {
        if (fread(row, sizeof(float), 8, in) != 8) return 3;
        neural_brdf_eval(row, row + 3, row + 6, texture, f);
        fwrite(f, sizeof(float), 3, res);
    }
    fclose(in);
    fclose(tex);
    fclose(res);
    return 0;
}
"""


def c_eval(
    path,
    folder: Path,
    wi,
    wo,
    uv,
    textures: list[np.ndarray],
    *,
    flags: tuple[str, ...] = (),
    prefix: str | None = None,
) -> list[np.ndarray]:
    """The generated header compiled with DRIVER (and ``flags``), run once per texture
    given.  With ``prefix`` the header is generated with it and DRIVER calls its names;
    the default file of the same model is included too (before it: one translation
    unit, two headers)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc, "a C compiler (cc) is needed"
    driver = DRIVER
    if prefix is None:
        (folder / "model.h").write_text(backends.generate(path, "c"))
    else:
        (folder / "model.h").write_text(backends.generate(path, "c", prefix=prefix))
        (folder / "plain.h").write_text(backends.generate(path, "c"))
        driver = (
            driver.replace('#include "model.h"', '#include "plain.h"\n#include "model.h"')
            .replace("NEURAL_BRDF_", f"{prefix.upper()}_")
            .replace("neural_brdf_eval", f"{prefix}_eval")
        )
    (folder / "driver.c").write_text(driver)
    exe = folder / "driver"
    cmd = [cc, "-std=c99", "-O2", "-Wall", "-Werror", *flags, "-o", str(exe)]
    subprocess.run([*cmd, str(folder / "driver.c"), "-lm"], check=True, capture_output=True)
    np.concatenate([wi, wo, uv], 1).astype(np.float32).tofile(folder / "in.bin")
    out = []
    for data in textures:
        np.asarray(data, "<f4").tofile(folder / "tex.bin")
        args = [str(len(wi)), str(folder / "in.bin"), str(folder / "tex.bin")]
        subprocess.run([str(exe), *args, str(folder / "out.bin")], check=True)
        out.append(np.fromfile(folder / "out.bin", np.float32).reshape(-1, 3))
    return out


def test_c_matches_onnxruntime(textured, reference, tmp_path):
    path, table = textured
    wi, wo, uv, ref = reference
    got, wrong = c_eval(path, tmp_path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, C_TOL)


def test_c_with_a_prefix_beside_the_default_file(textured, reference, tmp_path):
    """The header generated with a prefix (its texture macros TEX_TEXTURE0_ROWS, ...)
    and the default one of the same model in one translation unit: the prefixed
    tex_eval matches onnxruntime."""
    path, table = textured
    wi, wo, uv, ref = reference
    got, wrong = c_eval(path, tmp_path, wi, wo, uv, [table, table[::-1]], prefix="tex")
    check_parity(got, wrong, ref, C_TOL)


# -ffast-math may reassociate and contract: measured 6e-7 relative against onnxruntime
FAST_MATH_TOL = 1e-4


def test_c_under_fast_math_gives_0_for_a_non_finite_uv(textured, tmp_path):
    """Compiled with -ffast-math (which folds isnan() and isinf() to 0), rows with a NaN
    or infinite uv, or a non-finite or zero-length direction, still give exactly 0: the
    generated tests are bit tests; the other rows match onnxruntime."""
    from test_codegen import HOSTILE

    path, table = textured
    rng = np.random.default_rng(5)
    n = 64
    wi, wo = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]) + 0.1, np.abs(wo[:, 2]) + 0.1
    good_uv = rng.uniform(-2.0, 2.0, (n, 2))
    bad = np.array(HOSTILE)
    # every hostile uv with good directions, every hostile direction on either side
    rows = [(wi, wo, good_uv)]
    rows += [(wi[:6], wo[:6], np.repeat([h], 6, 0)) for h in HOSTILE_UV]
    rows += [(bad, wo[: len(bad)], good_uv[: len(bad)]), (wi[: len(bad)], bad, good_uv[: len(bad)])]
    wi, wo, uv = (np.concatenate([r[k] for r in rows]).astype(np.float32) for k in range(3))
    (got,) = c_eval(path, tmp_path, wi, wo, uv, [table], flags=("-ffast-math",))
    ref = onnx_ref(path, wi, wo, uv)
    assert np.isfinite(got).all()
    hostile = ~np.isfinite(uv).all(1) | ~np.isfinite(wi).all(1) | ~np.isfinite(wo).all(1)
    hostile |= (wi == 0).all(1) | (wo == 0).all(1)
    assert hostile.sum() == 4 * 6 + 2 * len(bad)
    assert (got[hostile] == 0.0).all(), got[hostile]
    assert (ref[hostile] == 0.0).all()
    assert (ref[~hostile] != 0).all()
    assert relative_difference(got[~hostile], ref[~hostile]) <= FAST_MATH_TOL


# ------------------------------------------------------------------ WGSL (wgpu: naga + lavapipe)
WGSL_KERNEL = """
@group(0) @binding(0) var<storage, read> nb_rows: array<f32>;
@group(0) @binding(1) var<storage, read_write> nb_f: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= arrayLength(&nb_f) / 3u) {
        return;
    }
    let b = 8u * i;
    let wi = vec3<f32>(nb_rows[b], nb_rows[b + 1u], nb_rows[b + 2u]);
    let wo = vec3<f32>(nb_rows[b + 3u], nb_rows[b + 4u], nb_rows[b + 5u]);
    let f = neural_brdf_eval(wi, wo, vec2<f32>(nb_rows[b + 6u], nb_rows[b + 7u]));
    let s = neural_brdf_sample(wi, 0.5f, vec2<f32>(0.25f, 0.75f));   // compiled too
    nb_f[3u * i] = select(f.x, s.pdf, s.pdf < -1.0f);
    nb_f[3u * i + 1u] = f.y;
    nb_f[3u * i + 2u] = f.z;
}
"""


def wgsl_eval(device, source: str, wi, wo, uv, textures: list[np.ndarray]) -> list[np.ndarray]:
    """The generated WGSL in a compute shader: the rows in group 0, the texture a storage
    buffer at @group(1) @binding(0), as the generated declaration asks; one dispatch per
    texture given."""
    import wgpu

    pipe = device.create_compute_pipeline(
        layout="auto",
        compute={
            "module": device.create_shader_module(code=source + WGSL_KERNEL),
            "entry_point": "main",
        },
    )
    n = len(wi)
    data = np.concatenate([wi, wo, uv], 1).astype(np.float32)
    inp = device.create_buffer_with_data(data=data.tobytes(), usage=wgpu.BufferUsage.STORAGE)
    res = device.create_buffer(
        size=n * 12, usage=wgpu.BufferUsage.STORAGE | wgpu.BufferUsage.COPY_SRC
    )

    def group(k, buffers):
        entries = [
            {"binding": b, "resource": {"buffer": buf, "offset": 0, "size": buf.size}}
            for b, buf in enumerate(buffers)
        ]
        return device.create_bind_group(layout=pipe.get_bind_group_layout(k), entries=entries)

    out = []
    for table in textures:
        tex = device.create_buffer_with_data(
            data=np.asarray(table, "<f4").tobytes(), usage=wgpu.BufferUsage.STORAGE
        )
        enc = device.create_command_encoder()
        cpass = enc.begin_compute_pass()
        cpass.set_pipeline(pipe)
        cpass.set_bind_group(0, group(0, [inp, res]))
        cpass.set_bind_group(1, group(1, [tex]))
        cpass.dispatch_workgroups((n + 63) // 64)
        cpass.end()
        device.queue.submit([enc.finish()])
        out.append(np.frombuffer(device.queue.read_buffer(res), np.float32).reshape(n, 3).copy())
    return out


def test_wgsl_matches_onnxruntime(textured, reference, wgpu_device):
    path, table = textured
    wi, wo, uv, ref = reference
    source = backends.generate(path, "wgsl")
    assert "@group(1) @binding(0) var<storage, read> neural_brdf_texture0: array<f32>;" in source
    assert "@group(3) @binding(0)" in backends.generate(path, "wgsl", group=3)
    got, wrong = wgsl_eval(wgpu_device, source, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)


# ------------------------------------------------------------------ GLSL
GLSL_MAIN = """
{decl}vec4 v;
{out}vec4 color;
void main() {{
    vec3 w;
    float p = neural_brdf_sample(normalize(v.xyz), v.w, v.xy, w);
    color = vec4(neural_brdf_eval(normalize(v.xyz), normalize(v.zyx), v.yw) + w,
                 p + neural_brdf_pdf(v.xyz, w));
}}
"""


def test_glsl_validates_as_es_and_as_vulkan(textured, tmp_path):
    """ES 3.00 (the sampler) and desktop 4.50 for Vulkan (the std430 buffer, its binding
    moved by the host's #define)."""
    tool = shutil.which("glslangValidator")
    assert tool, "glslangValidator (Debian glslang-tools) is needed"
    source = backends.generate(textured[0], "glsl")
    es = tmp_path / "es.frag"
    es.write_text(
        "#version 300 es\nprecision highp float;\nprecision highp int;\n"
        + source
        + GLSL_MAIN.format(decl="uniform ", out="out ")
    )
    vk = tmp_path / "vk.frag"
    vk.write_text(
        "#version 450\n#define NEURAL_BRDF_TEXTURE0_BINDING 3\n"
        + source
        + GLSL_MAIN.format(decl="layout(location = 0) in ", out="layout(location = 0) out ")
    )
    for cmd in ([tool, str(es)], [tool, "-V", str(vk), "-o", str(tmp_path / "vk.spv")]):
        r = subprocess.run(cmd, capture_output=True, text=True)
        assert r.returncode == 0, r.stdout[-2000:]
    r = subprocess.run(
        [tool, "-V", "-H", str(vk), "-o", str(tmp_path / "vk.spv")], capture_output=True, text=True
    )
    assert "Binding 3" in r.stdout  # the #define moved it


def webgl_eval(path, wi, wo, uv, tables: list[np.ndarray]) -> list[np.ndarray]:
    """The generated GLSL ES in headless Chromium, once per table given as texture 0
    (an R32F sampler, ES_WIDTH floats a row: the host's #define)."""
    from harness import gpu_browser

    source = f"#define NEURAL_BRDF_TEXTURE_WIDTH {ES_WIDTH}\n" + backends.generate(path, "glsl")
    with gpu_browser.Session() as s:
        return [
            s.eval_glsl(
                source, wi, wo, uv=uv, textures={"neural_brdf_texture0": (t.reshape(-1), ES_WIDTH)}
            )
            for t in tables
        ]


def test_glsl_in_webgl2_matches_onnxruntime(textured, reference):
    """The ES variant: the texture an R32F sampler, ES_WIDTH floats a row (the host's
    #define NEURAL_BRDF_TEXTURE_WIDTH), read by texelFetch in headless Chromium."""
    path, table = textured
    wi, wo, uv, ref = reference
    got, wrong = webgl_eval(path, wi, wo, uv, [table, table[::-1]])
    check_parity(got, wrong, ref, GPU_TOL)
