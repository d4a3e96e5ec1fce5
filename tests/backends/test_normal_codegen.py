"""Code generation of a textured file with its teacher's normal field (outputs f and n,
docs/codegen.md, "Textured files"): ``neural_brdf_normal(uv)`` evaluates the graph's n
as onnxruntime does, its texels bound by the host like the weight field, and
``neural_brdf_eval`` still evaluates f.

* the bound data (``neural_brdf.backends.textures``, the CLI's ``.texture<k>.f32``) are
  the weight field (texture 0) and the normal texels (texture 1, [Rv * Ru, 3], row
  j * Ru + i), bit for bit, and the generated code holds no literal copy of either;
* C (gcc), WGSL (wgpu on lavapipe, both textures storage buffers in group 1) and GLSL
  ES 3.00 (WebGL2, the texels an R32F sampler) match onnxruntime's n (and f) to the
  tolerances of test_codegen.py at random uv (negative, wrapped, large), the texel
  centres and edges of a rectangular 7 x 5 table in several periods, integers and their
  float32 neighbours, and NaN/inf/huge uv; the same code with the texels' rows reversed
  does not match (the bound data are read);
* the desktop GLSL (SSBO) and ES variants validate with glslangValidator;
* a file whose outputs are f and n without the input uv is a one-line error.

The model: test_textured_codegen's small lobes and weight field, with a NormalField of
tilted normals (z = 1, x and y ~ N(0, 0.1)), exported by the project's exporter with
both outputs.
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
from test_textured_codegen import ES_WIDTH, HOSTILE_UV, LOBE, check_parity

from cli_helpers import assert_one_line_error, cli
from neural_brdf import backends
from neural_brdf.errors import InputError
from neural_brdf.export import relative_difference
from neural_brdf.fileformat import lobe as lobe_format

R, K = 12, 3  # the weight field: texels per side, lobes
RU, RV = 7, 5  # the normal texels: a rectangular table, columns along u, rows along v


@pytest.fixture(scope="module")
def normal_file(tmp_path_factory):
    """(path of the model, its weight table [R * R, K], its texels [RV, RU, 3])."""
    import torch

    from neural_brdf import config as cfgmod
    from neural_brdf import export, fileformat
    from neural_brdf.train.model import RawBRDF
    from neural_brdf.train.textured_model import (
        NormalField,
        TexturedBRDF,
        WeightField,
        exportable,
    )

    torch.manual_seed(0)
    recipe = cfgmod.Model(hidden=[16], grid=cfgmod.Grid(size=8))
    lobes = [RawBRDF.from_config(recipe, init_value=v) for v in (0.1, 0.3, 0.6)[:K]]
    with torch.no_grad():
        for lobe in lobes:
            torch.nn.init.normal_(lobe.mlp.head.weight, std=0.3)
    rng = np.random.default_rng(3)
    texels = np.ones((RV, RU, 3), np.float32)  # tilted normals: z = 1, x, y ~ N(0, 0.1)
    texels[..., :2] = rng.normal(0.0, 0.1, (RV, RU, 2))
    model = TexturedBRDF(lobes, WeightField(R, K, init_std=2.0), NormalField(texels))
    payload = export.to_onnx_bytes(
        exportable(model),
        17,
        inputs=fileformat.SIGNATURES[1],
        outputs=fileformat.OUTPUT_SIGNATURES[1],
    )
    proto = onnx.load_from_string(payload)
    helper.set_model_props(proto, {lobe_format.KEY: lobe_format.to_json(LOBE)})
    path = tmp_path_factory.mktemp("normal") / "model.onnx"
    path.write_bytes(proto.SerializeToString())
    (table,) = [
        onnx.numpy_helper.to_array(t) for t in proto.graph.initializer if list(t.dims) == [R * R, K]
    ]
    return path, table, texels


def normal_uv(n: int, seed: int = 0) -> np.ndarray:
    """(n, 2) float32: the first rows pair special u (texel centres and edges of RU in
    several periods, integers, the float32 neighbours of 0 and 1, large values) with
    special v (the same for RV), the last are HOSTILE_UV, the rest uniform in [-3, 3)."""
    rng = np.random.default_rng(seed)

    def special(res: int) -> np.ndarray:
        centres, edges = (np.arange(res) + 0.5) / res, np.arange(res + 1) / res
        return np.concatenate(
            [
                centres,
                edges,
                centres - 1.0,
                edges + 2.0,
                -edges,
                -centres - 5.0,
                [-2.0, -1.0, 0.0, 1.0, 3.0, 1000.375, -250.8125, 1e6 + 0.5],
                np.nextafter(np.float32([0.0, 0.0, 1.0, 1.0, -1.0]), np.float32([1, -1, 0, 2, 0])),
            ]
        ).astype(np.float32)

    su, sv = special(RU), special(RV)
    uv = rng.uniform(-3.0, 3.0, (n, 2)).astype(np.float32)
    grid = np.stack(np.meshgrid(su, sv, indexing="ij"), -1).reshape(-1, 2)
    m = min(n // 2, len(grid))
    uv[:m] = grid[:m]
    uv[-len(HOSTILE_UV) :] = HOSTILE_UV
    return uv


@pytest.fixture(scope="module")
def reference(normal_file):
    """(wi, wo, uv, f, n): onnxruntime's two outputs, the truth."""
    wi, wo = pairs(1)
    uv = normal_uv(len(wi), 1)
    sess = ort.InferenceSession(str(normal_file[0]), providers=["CPUExecutionProvider"])
    f, n = sess.run(["f", "n"], {"wi": wi, "wo": wo, "uv": uv})
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    assert (np.abs(n[:, :2]) > 0.01).sum() > 1000  # tilted: a texel mixed up shows
    assert (n[-len(HOSTILE_UV) :][:4] == [0.0, 0.0, 1.0]).all()  # NaN and inf uv
    assert (f != 0).sum() > 1000
    return wi, wo, uv, f, n


def wrong_texels(texels: np.ndarray) -> np.ndarray:
    """The bound normal data with their rows reversed: code that reads them must fail."""
    return texels.reshape(-1, 3)[::-1]


# ------------------------------------------------------------------ the bound data
def test_the_bound_data_are_the_weights_then_the_texels(normal_file, tmp_path, capsys):
    path, table, texels = normal_file
    data = backends.textures(path)
    assert [d.shape for d in data] == [(R * R, K), (RV * RU, 3)]
    assert all(d.dtype == np.float32 for d in data)
    assert np.array_equal(data[0], table)
    assert np.array_equal(data[1], texels.reshape(-1, 3))  # row j * Ru + i
    for target in backends.TARGETS:
        text = backends.generate(path, target)
        for rows in (R * R, RV * RU):  # no literal copy of either
            assert f"[{rows}]" not in text and f", {rows}>" not in text, target
        assert "neural_brdf_normal" in text and "neural_brdf_texture1" in text
    code, out, _ = cli(capsys, "codegen", str(path), "--target", "c", "-o", str(tmp_path / "b.h"))
    assert code == 0 and "b.texture0.f32" in out and "b.texture1.f32" in out
    assert np.array_equal(np.fromfile(tmp_path / "b.texture0.f32", "<f4"), table.reshape(-1))
    assert np.array_equal(np.fromfile(tmp_path / "b.texture1.f32", "<f4"), texels.reshape(-1))


def test_the_c_signatures(normal_file):
    c = backends.generate(normal_file[0], "c")
    assert (
        "static inline void neural_brdf_eval(const float wi[3], const float wo[3], "
        "const float uv[2], const float *neural_brdf_texture0, float f[3])" in c
    )
    assert (
        "static inline void neural_brdf_normal(const float uv[2], "
        "const float *neural_brdf_texture1, float n[3])" in c
    )
    assert "vec3 neural_brdf_normal(vec2 uv)" in backends.generate(normal_file[0], "glsl")
    wgsl = backends.generate(normal_file[0], "wgsl")
    assert "fn neural_brdf_normal(uv: vec2<f32>) -> vec3<f32>" in wgsl


def test_outputs_f_and_n_without_uv_is_one_line(tmp_path, capsys):
    f32 = TensorProto.FLOAT
    g = helper.make_graph(
        [helper.make_node("Add", ["wi", "wo"], ["f"]), helper.make_node("Identity", ["wi"], ["n"])],
        "no_uv",
        [helper.make_tensor_value_info(k, f32, ["N", 3]) for k in ("wi", "wo")],
        [helper.make_tensor_value_info(k, f32, ["N", 3]) for k in ("f", "n")],
    )
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {lobe_format.KEY: lobe_format.to_json(LOBE)})
    with pytest.raises(InputError, match="and n \\[N, 3\\] with uv"):
        backends.generate(model.SerializeToString(), "glsl")
    bad = tmp_path / "no_uv.onnx"
    bad.write_bytes(model.SerializeToString())
    code, _, err = cli(capsys, "codegen", str(bad), "--target", "c", "-o", str(tmp_path / "x.h"))
    assert_one_line_error(code, err, "expected inputs")


# ------------------------------------------------------------------ C
DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include "model.h"

/* driver N ROWS TEXTURE0 TEXTURE1 OUT: rows of 8 float32 (wi, wo, uv) -> f, n */
static int load(const char *path, float *data, size_t n)
{
    FILE *in = fopen(path, "rb");
    size_t got;
    if (!in) return 0;
    got = fread(data, sizeof(float), n, in);
    fclose(in);
    return got == n;
}

int main(int argc, char **argv)
{
    static float weights[NEURAL_BRDF_TEXTURE0_ROWS * NEURAL_BRDF_TEXTURE0_CHANNELS];
    static float texels[NEURAL_BRDF_TEXTURE1_ROWS * NEURAL_BRDF_TEXTURE1_CHANNELS];
    long n, i;
    float row[8], out[6];
    FILE *in, *res;
    if (argc != 6) return 2;
    n = atol(argv[1]);
    if (!load(argv[3], weights, sizeof weights / sizeof(float))) return 3;
    if (!load(argv[4], texels, sizeof texels / sizeof(float))) return 3;
    in = fopen(argv[2], "rb");
    res = fopen(argv[5], "wb");
    if (!in || !res) return 2;
    for (i = 0; i < n; i++) {
        if (fread(row, sizeof(float), 8, in) != 8) return 3;
        neural_brdf_normal(row + 6, texels, out + 3);
        neural_brdf_eval(row, row + 3, row + 6, weights, out);
        fwrite(out, sizeof(float), 6, res);
    }
    fclose(in);
    fclose(res);
    return 0;
}
"""


def c_eval(path, folder: Path, wi, wo, uv, bound) -> list[tuple[np.ndarray, np.ndarray]]:
    """The generated header compiled with DRIVER, run once per (weights, texels) given:
    (f, n) each."""
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc, "a C compiler (cc) is needed"
    (folder / "model.h").write_text(backends.generate(path, "c"))
    (folder / "driver.c").write_text(DRIVER)
    exe = folder / "driver"
    cmd = [cc, "-std=c99", "-O2", "-Wall", "-Werror", "-o", str(exe), str(folder / "driver.c")]
    r = subprocess.run([*cmd, "-lm"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    np.concatenate([wi, wo, uv], 1).astype(np.float32).tofile(folder / "in.bin")
    out = []
    for weights, texels in bound:
        np.asarray(weights, "<f4").tofile(folder / "t0.bin")
        np.asarray(texels, "<f4").tofile(folder / "t1.bin")
        args = [str(len(wi)), *(str(folder / p) for p in ("in.bin", "t0.bin", "t1.bin"))]
        subprocess.run([str(exe), *args, str(folder / "out.bin")], check=True)
        res = np.fromfile(folder / "out.bin", np.float32).reshape(-1, 6)
        out.append((res[:, :3], res[:, 3:]))
    return out


def test_c_matches_onnxruntime(normal_file, reference, tmp_path):
    path, table, texels = normal_file
    wi, wo, uv, f_ref, n_ref = reference
    (f, n), (f2, n_wrong) = c_eval(
        path, tmp_path, wi, wo, uv, [(table, texels), (table, wrong_texels(texels))]
    )
    check_parity(n, n_wrong, n_ref, C_TOL)
    assert np.isfinite(f).all() and relative_difference(f, f_ref) <= C_TOL
    assert np.array_equal(f2, f)  # f does not read the texels


# ------------------------------------------------------------------ WGSL (wgpu: naga + lavapipe)
WGSL_KERNEL = """
@group(0) @binding(0) var<storage, read> nb_rows: array<f32>;
@group(0) @binding(1) var<storage, read_write> nb_out: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= arrayLength(&nb_out) / 6u) {
        return;
    }
    let b = 8u * i;
    let wi = vec3<f32>(nb_rows[b], nb_rows[b + 1u], nb_rows[b + 2u]);
    let wo = vec3<f32>(nb_rows[b + 3u], nb_rows[b + 4u], nb_rows[b + 5u]);
    let uv = vec2<f32>(nb_rows[b + 6u], nb_rows[b + 7u]);
    let n = neural_brdf_normal(uv);
    let f = neural_brdf_eval(wi, wo, uv);
    nb_out[6u * i] = f.x;
    nb_out[6u * i + 1u] = f.y;
    nb_out[6u * i + 2u] = f.z;
    nb_out[6u * i + 3u] = n.x;
    nb_out[6u * i + 4u] = n.y;
    nb_out[6u * i + 5u] = n.z;
}
"""


def wgsl_eval(device, source: str, wi, wo, uv, bound) -> list[tuple[np.ndarray, np.ndarray]]:
    """The generated WGSL in a compute shader: the rows in group 0, the weights and the
    texels storage buffers at @group(1) @binding(0) and (1), as the generated
    declarations ask; one dispatch per (weights, texels) given: (f, n) each."""
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
        size=n * 24, usage=wgpu.BufferUsage.STORAGE | wgpu.BufferUsage.COPY_SRC
    )

    def group(k, buffers):
        entries = [
            {"binding": b, "resource": {"buffer": buf, "offset": 0, "size": buf.size}}
            for b, buf in enumerate(buffers)
        ]
        return device.create_bind_group(layout=pipe.get_bind_group_layout(k), entries=entries)

    out = []
    for tables in bound:
        texs = [
            device.create_buffer_with_data(
                data=np.asarray(t, "<f4").tobytes(), usage=wgpu.BufferUsage.STORAGE
            )
            for t in tables
        ]
        enc = device.create_command_encoder()
        cpass = enc.begin_compute_pass()
        cpass.set_pipeline(pipe)
        cpass.set_bind_group(0, group(0, [inp, res]))
        cpass.set_bind_group(1, group(1, texs))
        cpass.dispatch_workgroups((n + 63) // 64)
        cpass.end()
        device.queue.submit([enc.finish()])
        got = np.frombuffer(device.queue.read_buffer(res), np.float32).reshape(n, 6).copy()
        out.append((got[:, :3], got[:, 3:]))
    return out


def test_wgsl_matches_onnxruntime(normal_file, reference, wgpu_device):
    path, table, texels = normal_file
    wi, wo, uv, f_ref, n_ref = reference
    source = backends.generate(path, "wgsl")
    assert "@group(1) @binding(1) var<storage, read> neural_brdf_texture1: array<f32>;" in source
    (f, n), (_, n_wrong) = wgsl_eval(
        wgpu_device, source, wi, wo, uv, [(table, texels), (table, wrong_texels(texels))]
    )
    check_parity(n, n_wrong, n_ref, GPU_TOL)
    assert np.isfinite(f).all() and relative_difference(f, f_ref) <= GPU_TOL


# ------------------------------------------------------------------ GLSL
GLSL_MAIN = """
{decl}vec4 v;
{out}vec4 color;
void main() {{
    vec3 n = neural_brdf_normal(v.xy);
    color = vec4(neural_brdf_eval(normalize(v.xyz), normalize(v.zyx), v.yw) + n,
                 neural_brdf_pdf(v.xyz, n));
}}
"""


def test_glsl_validates_as_es_and_as_vulkan(normal_file, tmp_path):
    tool = shutil.which("glslangValidator")
    assert tool, "glslangValidator (Debian glslang-tools) is needed"
    source = backends.generate(normal_file[0], "glsl")
    es = tmp_path / "es.frag"
    es.write_text(
        "#version 300 es\nprecision highp float;\nprecision highp int;\n"
        + source
        + GLSL_MAIN.format(decl="uniform ", out="out ")
    )
    vk = tmp_path / "vk.frag"
    vk.write_text(
        "#version 450\n#define NEURAL_BRDF_TEXTURE1_BINDING 5\n"
        + source
        + GLSL_MAIN.format(decl="layout(location = 0) in ", out="layout(location = 0) out ")
    )
    for cmd in ([tool, str(es)], [tool, "-V", str(vk), "-o", str(tmp_path / "vk.spv")]):
        r = subprocess.run(cmd, capture_output=True, text=True)
        assert r.returncode == 0, r.stdout[-2000:]
    r = subprocess.run(
        [tool, "-V", "-H", str(vk), "-o", str(tmp_path / "vk.spv")], capture_output=True, text=True
    )
    assert "Binding 5" in r.stdout and "Binding 0" in r.stdout


def test_glsl_in_webgl2_matches_onnxruntime(normal_file, reference):
    """The ES variant in headless Chromium: the harness calls neural_brdf_eval(wi, wo, uv);
    a macro after the generated code turns that call into neural_brdf_normal(uv), the
    texels an R32F sampler ES_WIDTH floats a row.  f with the weights bound, once."""
    from harness import gpu_browser

    path, table, texels = normal_file
    wi, wo, uv, f_ref, n_ref = reference
    source = f"#define NEURAL_BRDF_TEXTURE_WIDTH {ES_WIDTH}\n" + backends.generate(path, "glsl")
    as_normal = source + "\n#define neural_brdf_eval(wi, wo, uv) neural_brdf_normal(uv)\n"
    with gpu_browser.Session() as s:
        n, n_wrong = (
            s.eval_glsl(
                as_normal,
                wi,
                wo,
                uv=uv,
                textures={"neural_brdf_texture1": (t.reshape(-1), ES_WIDTH)},
            )
            for t in (texels, wrong_texels(texels))
        )
        f = s.eval_glsl(
            source, wi, wo, uv=uv, textures={"neural_brdf_texture0": (table.reshape(-1), ES_WIDTH)}
        )
    check_parity(n, n_wrong, n_ref, GPU_TOL)
    assert np.isfinite(f).all() and relative_difference(f, f_ref) <= GPU_TOL
