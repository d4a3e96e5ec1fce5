"""Code generation (neural_brdf.graph + neural_brdf.backends): every back end evaluates the
exported graph as onnxruntime does.

* C (``cc -std=c99 -O2 -Wall -Werror``, through a small driver program): parity with
  onnxruntime to 1e-5 relative (neural_brdf.export.relative_difference) on random pairs,
  below-horizon, near-grazing, equal and opposite pairs included; f(wi, wo) == f(wo, wi)
  bit for bit; rows with NaN / inf / zero-length directions give exactly 0; scaled
  (unnormalised) directions give f(wi, wo) to 1e-5;
* the C sampling functions: pdf is the stored lobe's mixture density (computed here with
  analytic's GGX), sample() returns pdf(wo) of the wo it draws, and the drawn directions
  follow pdf (a chi-square test over (cos theta, phi) bins, pdf integrated by quadrature);
* GLSL: ``glslangValidator`` accepts the file in an ES 3.00 fragment shader and in a
  desktop GLSL 4.50 shader compiled to SPIR-V for Vulkan;
* WGSL: wgpu (naga) validates it and runs it in a compute shader on the CPU Vulkan
  driver (lavapipe): parity with onnxruntime and the NaN / scale rows;
* Dr.Jit (the Mitsuba plugin's path): parity with onnxruntime, NaN / scale rows;
* a graph using every ONNX op the lowering supports (IsNaN and IsInf included) gives
  onnxruntime's values in C, WGSL and Dr.Jit and validates in GLSL; an unknown op is
  named; ``neural-brdf codegen`` writes files and exits 2 on bad input;
* the header comment: a long metadata value (the target's JSON) is cut at an item's end
  with an ellipsis, never in mid-key, never ends in a backslash, and still compiles;
* pdf and sample normalise their directions as eval does (C99 and -ffast-math, WGSL,
  WebGL2): scaled directions give the lobe's density and draws at the unit ones (the
  reference mixture density and the file format's sampler), a non-finite or zero-length
  direction gives pdf 0 (sample: wo below the horizon);
* sample refuses a random number that is not finite or not in [0, 1) (C99 and
  -ffast-math, WGSL, WebGL2): wo = (0, 0, -1) and pdf 0, never a NaN direction;
* prefixes: three C headers (two prefixes and the default) in one translation unit, three
  WGSL files in one module, three GLSL files in one shader, each with its own model's
  values; the default prefix is the unprefixed file; a bad prefix is one line;
* errors of a foreign, empty, lobe-less or unlowerable file name it (API and CLI).

Two tiny models (isotropic quickstart, anisotropic brushed_ggx) are trained once per
module (about 20 s each).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper

from lobe_reference import ANISO_RETRO, BECKMANN, PER_INCIDENCE, RETRO_TABLE, mixture_pdf
from neural_brdf import backends, config, graph, pipeline
from neural_brdf.backends.cstyle import ELLIPSIS, HEADER_VALUE_CHARS
from neural_brdf.errors import InputError
from neural_brdf.export import relative_difference

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
TINY_RUN = [
    "train.steps=60",
    "train.threads=1",
    "train.warmup=10",
    "train.progress=false",
    "train.checkpoint_every=1000",
    "train.eval_every=0",
    "model.hidden=[16,16]",
    "data.batch_size=512",
    "data.pool_size=4096",
    "normalization.samples=2048",
    "validation.furnace_dirs=15",
    "validation.furnace_samples=512",
    "validation.pairs=1000",
    "validation.accuracy_samples=2048",
    "export.parity_pairs=256",
]
# Trained 3 x 64 networks (configs/mlp/, with TINY_RUN's [16, 16]); the grid models' code
# is checked on random grids in test_grid_encoding.py.  A trained compact model read
# 1.4e-5 apart between C and onnxruntime at one pair 0.001 degrees above the horizon,
# each 0.9-1.2e-5 from the float64 network there (float32 through the grazing scale).
MODELS = {"isotropic": "mlp/gold.yaml", "anisotropic": "mlp/brushed_ggx.yaml"}

C_TOL = 1e-5  # the export contract's parity tolerance
# GPU transcendental functions are loose by specification (WGSL: exp 3 + 2|x| ULP, atan
# 4096 ULP).  lavapipe measured: atan about 2e-5 relative; the anisotropic network turns
# that into 4.4e-4 at one pair with wi == wo 0.01 degrees above the horizon (3e-5 at
# every other pair).  The C code, with libm, meets C_TOL on the same pairs.
GPU_TOL = 1e-3
# lavapipe's asin and acos are accurate to about 4e-4 (relative to this graph's values)
EVERY_OP_GPU_TOL = 1e-3
SCALE_TOL = 1e-5  # f(k wi, wo) against f(wi, wo)
# GPU division and sqrt need not be correctly rounded (WGSL: 2.5 ULP); lavapipe: 2e-5
GPU_SCALE_TOL = 1e-4
PDF_RTOL = 2e-4  # float32 pdf against the float64 reference
CHI2_SAMPLES = 200_000
CHI2_BINS = (10, 12)  # cos theta_o, phi_o
CHI2_SUB = 24  # quadrature points per bin edge
CHI2_MIN_EXPECTED = 5.0
CHI2_P = 1e-4
HOSTILE = [
    [np.nan, 0.2, 0.9],
    [np.inf, 0.0, 1.0],
    [0.1, -np.inf, 0.5],
    [0.0, 0.0, np.inf],
    [0.0, 0.0, 0.0],
    [np.nan, np.nan, np.nan],
]
SCALES = (1e-3, 7.5, 1e4)

DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "model.h"

/* driver MODE N IN OUT: eval (wi, wo -> f), pdf (wi, wo -> pdf),
   sample (wi, u1, u2 -> wo, pdf); float32 rows of 6 in, 3 / 1 / 4 out */
int main(int argc, char **argv)
{
    long n, i;
    float row[6], out[4];
    FILE *in, *res;
    if (argc != 5) return 2;
    n = atol(argv[2]);
    in = fopen(argv[3], "rb");
    res = fopen(argv[4], "wb");
    if (!in || !res) return 2;
    for (i = 0; i < n; i++) {
        int k = 0;
        if (fread(row, sizeof(float), 6, in) != 6) return 3;
        if (!strcmp(argv[1], "eval")) {
            neural_brdf_eval(row, row + 3, out);
            k = 3;
        } else if (!strcmp(argv[1], "pdf")) {
            out[0] = neural_brdf_pdf(row, row + 3);
            k = 1;
        } else {
            out[3] = neural_brdf_sample(row, row[3], row + 4, out);
            k = 4;
        }
        fwrite(out, sizeof(float), (size_t)k, res);
    }
    fclose(in);
    fclose(res);
    return 0;
}
"""


# ------------------------------------------------------------------ fixtures and helpers
@pytest.fixture(scope="module")
def models(tmp_path_factory):
    out = {}
    for enc, cfg_name in MODELS.items():
        run_dir = tmp_path_factory.mktemp(enc)
        pipeline.run(config.load(CONFIGS / cfg_name, TINY_RUN), run_dir)
        out[enc] = run_dir / "model.onnx"
    return out


def unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def graph_unit(w: np.ndarray) -> np.ndarray:
    """Finite, non-zero float32 directions normalised as the exported graph defines it
    (neural_brdf.train.model.unit_or_invalid: divided by the largest absolute component,
    then by the length (x^2 + y^2) + z^2), each operation rounded to float32 as IEEE
    arithmetic does (numpy; torch's vectorised division differs by an ulp), as float64:
    the directions the generated code evaluates, eval and pdf alike.  The float32 rounding
    moves a unit vector by up to an ulp, which changes the lobe's density by up to 3e-4
    where wi + wo nearly cancels (grazing pairs near the mirror direction)."""
    w = np.asarray(w, np.float32)
    m = np.abs(w).max(-1, keepdims=True)
    u = w / m
    n = np.sqrt((u[:, 0:1] * u[:, 0:1] + u[:, 1:2] * u[:, 1:2]) + u[:, 2:3] * u[:, 2:3])
    return (u / n).astype(np.float64)


def test_pairs(seed: int = 0, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Random pairs over the sphere (half below the horizon), near-grazing ones, exactly
    at the horizon, equal, opposite and mirrored pairs: float32 (N, 3) each."""
    rng = np.random.default_rng(seed)
    wi, wo = unit(rng, n), unit(rng, n)
    graze = unit(rng, 400)
    graze[:, 2] = 10.0 ** rng.uniform(-6, -1.5, 400)
    graze /= np.linalg.norm(graze, axis=-1, keepdims=True)
    up = unit(rng, 400)
    up[:, 2] = np.abs(up[:, 2])
    flat = up.copy()
    flat[:, 2] = 0.0
    flat /= np.linalg.norm(flat, axis=-1, keepdims=True)
    mirror = up * [-1.0, -1.0, 1.0]
    wi = np.concatenate([wi, graze, up, flat, up, up, up])
    wo = np.concatenate([wo, up, graze, up, up, -up, mirror])
    return wi.astype(np.float32), wo.astype(np.float32)


pairs = test_pairs
del test_pairs  # not a test


def onnx_ref(model, wi, wo) -> np.ndarray:
    sess = ort.InferenceSession(
        str(model) if not isinstance(model, bytes) else model, providers=["CPUExecutionProvider"]
    )
    return sess.run(None, {"wi": wi.astype(np.float32), "wo": wo.astype(np.float32)})[0]


class CProgram:
    """A generated header compiled with its driver: ``eval``, ``pdf``, ``sample``."""

    def __init__(self, model, folder: Path, *, lobe=None, flags: tuple[str, ...] = ()):
        cc = shutil.which("cc") or shutil.which("gcc")
        assert cc, "a C compiler (cc) is needed"
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "model.h").write_text(backends.generate(model, "c", lobe=lobe))
        (folder / "driver.c").write_text(DRIVER)
        self.exe = folder / "driver"
        self.folder = folder
        subprocess.run(
            [
                cc,
                "-std=c99",
                "-O2",
                "-Wall",
                "-Werror",
                *flags,
                "-o",
                str(self.exe),
                str(folder / "driver.c"),
                "-lm",
            ],
            check=True,
            capture_output=True,
        )

    def _run(self, mode: str, rows: np.ndarray, width: int) -> np.ndarray:
        rows = np.ascontiguousarray(rows, dtype=np.float32)
        src, dst = self.folder / "in.bin", self.folder / "out.bin"
        rows.tofile(src)
        subprocess.run([str(self.exe), mode, str(len(rows)), str(src), str(dst)], check=True)
        return np.fromfile(dst, dtype=np.float32).reshape(len(rows), width)

    def eval(self, wi, wo):
        return self._run("eval", np.concatenate([wi, wo], 1), 3)

    def pdf(self, wi, wo):
        return self._run("pdf", np.concatenate([wi, wo], 1), 1)[:, 0]

    def sample(self, wi, u1, u2):
        out = self._run("sample", np.concatenate([wi, u1[:, None], u2], 1), 4)
        return out[:, :3], out[:, 3]


@pytest.fixture(scope="module")
def c_programs(models, tmp_path_factory):
    return {
        enc: CProgram(path, tmp_path_factory.mktemp(f"c_{enc}")) for enc, path in models.items()
    }


def hostile_rows(n_good: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bad directions on either side among good rows; the mask marks the bad rows."""
    rng = np.random.default_rng(7)
    wi, wo = unit(rng, n_good), unit(rng, n_good)
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    bad = np.array(HOSTILE, dtype=np.float64)
    good = unit(rng, len(bad))
    good[:, 2] = np.abs(good[:, 2])
    wi = np.concatenate([wi[:25], bad, good, wi[25:]])
    wo = np.concatenate([wo[:25], good, bad, wo[25:]])
    mask = np.zeros(len(wi), bool)
    mask[25 : 25 + 2 * len(bad)] = True
    return wi.astype(np.float32), wo.astype(np.float32), mask


def check_total(evaluate, model, tol, scale_tol=SCALE_TOL):
    """Hostile rows give exactly 0 (not NaN), other rows onnxruntime's values; scaled
    directions give the unscaled values (generic pairs above the horizon: near grazing,
    renormalising in float32 moves f by more than 1e-5 in onnxruntime too) and
    onnxruntime's values for the scaled inputs (every kind of pair).  All of it is one
    call of ``evaluate`` (a GPU back end compiles its shader once)."""
    hwi, hwo, bad = hostile_rows()
    rng = np.random.default_rng(3)
    gwi, gwo = unit(rng, 2000), unit(rng, 2000)
    gwi[:, 2], gwo[:, 2] = np.abs(gwi[:, 2]), np.abs(gwo[:, 2])
    awi, awo = pairs(3, 500)
    blocks = [(hwi, hwo), (gwi, gwo)]
    for k in SCALES:
        blocks += [(gwi * k, gwo), (gwi, gwo * k), (awi * k, awo)]
    blocks = [(a.astype(np.float32), b.astype(np.float32)) for a, b in blocks]
    out = evaluate(np.concatenate([a for a, _ in blocks]), np.concatenate([b for _, b in blocks]))
    assert not np.isnan(out).any()
    got = np.split(out, np.cumsum([len(a) for a, _ in blocks])[:-1])
    assert (got[0][bad] == 0.0).all()
    assert relative_difference(got[0][~bad], onnx_ref(model, hwi, hwo)[~bad]) <= tol
    base = got[1]
    assert (base != 0).all()
    for j, k in enumerate(SCALES):
        scaled_wi, scaled_wo, any_pair = got[2 + 3 * j : 5 + 3 * j]
        assert relative_difference(scaled_wi, base) <= scale_tol, k
        assert relative_difference(scaled_wo, base) <= scale_tol, k
        swi, swo = blocks[4 + 3 * j]
        assert relative_difference(any_pair, onnx_ref(model, swi, swo)) <= tol, k


# ------------------------------------------------------------------ C
@pytest.mark.parametrize("enc", list(MODELS))
def test_c_matches_onnxruntime(models, c_programs, enc):
    wi, wo = pairs(1)
    got = c_programs[enc].eval(wi, wo)
    ref = onnx_ref(models[enc], wi, wo)
    assert np.isfinite(got).all()
    assert (ref != 0).sum() > 1000
    assert relative_difference(got, ref) <= C_TOL
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    assert (got[below] == 0).all() and below.sum() > 1000


@pytest.mark.parametrize("enc", list(MODELS))
def test_c_is_reciprocal_bit_for_bit(c_programs, enc):
    wi, wo = pairs(2)
    c = c_programs[enc]
    a, b = c.eval(wi, wo), c.eval(wo, wi)
    assert (a != 0).sum() > 1000
    assert np.array_equal(a, b)


@pytest.mark.parametrize("enc", list(MODELS))
def test_c_is_total(models, c_programs, enc):
    check_total(c_programs[enc].eval, models[enc], C_TOL)


def stored_lobe(model):
    from neural_brdf.fileformat import lobe as lobe_format

    return lobe_format.from_metadata({p.key: p.value for p in onnx.load(str(model)).metadata_props})


@pytest.mark.parametrize(
    "override",
    [None, {"alpha": 0.08, "weight": 0.5}, ANISO_RETRO, PER_INCIDENCE, RETRO_TABLE, BECKMANN],
)
def test_c_pdf_is_the_stored_lobe(models, c_programs, tmp_path, override):
    path = models["isotropic"]
    c = (
        c_programs["isotropic"]
        if override is None
        else CProgram(path, tmp_path / "c", lobe=override)
    )
    lobe = override or stored_lobe(path)
    rng = np.random.default_rng(4)
    wi = unit(rng, 6000)
    wi[:, 2] = np.abs(wi[:, 2])
    # wo near the mirror and the retro directions (where the GGX lobe matters) and anywhere
    mirror = wi * [-1.0, -1.0, 1.0] + rng.normal(0, 0.1, wi.shape)
    retro = wi + rng.normal(0, 0.1, wi.shape)
    wo = np.concatenate([mirror[:2000], retro[2000:4000], unit(rng, 2000)])
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    wi, wo = wi.astype(np.float32), wo.astype(np.float32)
    got = c.pdf(wi, wo)
    ref = mixture_pdf(graph_unit(wi), graph_unit(wo), lobe)  # pdf normalises, as eval
    assert (ref > 0).sum() > 3000
    np.testing.assert_allclose(got, ref, rtol=PDF_RTOL, atol=1e-6)


def expected_bin_probabilities(c: CProgram, wi1: np.ndarray) -> np.ndarray:
    """Integral of pdf over each (cos theta, phi) bin of the upper hemisphere
    (midpoint rule, CHI2_SUB^2 points per bin; d omega = d cos d phi)."""
    nz, nphi = CHI2_BINS
    z = (np.arange(nz * CHI2_SUB) + 0.5) / (nz * CHI2_SUB)
    phi = (np.arange(nphi * CHI2_SUB) + 0.5) / (nphi * CHI2_SUB) * 2.0 * math.pi
    Z, P = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1.0 - Z * Z)
    wo = np.stack([r * np.cos(P), r * np.sin(P), Z], -1).reshape(-1, 3).astype(np.float32)
    wi = np.broadcast_to(wi1, wo.shape).astype(np.float32)
    p = c.pdf(wi, wo).reshape(Z.shape).astype(np.float64)
    cell = (1.0 / (nz * CHI2_SUB)) * (2.0 * math.pi / (nphi * CHI2_SUB))
    return p.reshape(nz, CHI2_SUB, nphi, CHI2_SUB).sum((1, 3)) * cell


@pytest.mark.parametrize(
    "theta_deg, override",
    [
        (20.0, None),
        (70.0, None),
        (20.0, ANISO_RETRO),
        (70.0, ANISO_RETRO),
        (50.0, PER_INCIDENCE),
        (35.0, RETRO_TABLE),
        (15.0, BECKMANN),
        (75.0, BECKMANN),
    ],
)
def test_c_sample_follows_pdf(models, c_programs, theta_deg, override, tmp_path):
    from scipy import stats

    path = models["anisotropic"]
    c = c_programs["anisotropic"] if override is None else CProgram(path, tmp_path, lobe=override)
    lobe = override or stored_lobe(path)
    assert lobe["weight"] > 0.0  # both branches are drawn
    t = math.radians(theta_deg)
    wi1 = np.array([math.sin(t) * math.cos(0.6), math.sin(t) * math.sin(0.6), math.cos(t)])
    rng = np.random.default_rng(int(theta_deg))
    n = CHI2_SAMPLES
    wi = np.broadcast_to(wi1, (n, 3)).astype(np.float32)
    wo, pdf = c.sample(wi, rng.random(n).astype(np.float32), rng.random((n, 2)).astype(np.float32))
    ok = pdf > 0
    assert ok.mean() > 0.5
    # sample() returns pdf(wo) of its wo; below the horizon it reports 0 (rejected)
    np.testing.assert_allclose(pdf, c.pdf(wi, wo), rtol=1e-6, atol=0.0)
    assert (pdf[wo[:, 2] <= 0] == 0).all()
    np.testing.assert_allclose(np.linalg.norm(wo[ok], axis=-1), 1.0, atol=1e-5)
    # chi-square: counts over the bins against n * integral of pdf, plus a bin for the
    # rejected samples (probability 1 - integral of pdf over the hemisphere)
    nz, nphi = CHI2_BINS
    w = wo[ok].astype(np.float64)
    iz = np.minimum((w[:, 2] * nz).astype(int), nz - 1)
    iphi = np.minimum(
        (np.mod(np.arctan2(w[:, 1], w[:, 0]), 2 * math.pi) / (2 * math.pi) * nphi).astype(int),
        nphi - 1,
    )
    counts = np.bincount(iz * nphi + iphi, minlength=nz * nphi).astype(float)
    prob = expected_bin_probabilities(c, wi1).reshape(-1)
    assert 0.5 < prob.sum() <= 1.0 + 1e-3
    counts = np.append(counts, (~ok).sum())
    expected = np.append(prob, max(1.0 - prob.sum(), 0.0)) * n
    big = expected >= CHI2_MIN_EXPECTED
    obs = np.append(counts[big], counts[~big].sum())
    exp = np.append(expected[big], expected[~big].sum())
    keep = exp > 0
    obs, exp = obs[keep], exp[keep] * obs[keep].sum() / exp[keep].sum()
    chi2 = float(((obs - exp) ** 2 / exp).sum())
    p_value = float(stats.chi2.sf(chi2, len(obs) - 1))
    assert p_value > CHI2_P, (chi2, len(obs), p_value)


@pytest.mark.parametrize(
    "override", [{"alpha": 0.3, "weight": 0.7}, ANISO_RETRO, PER_INCIDENCE, RETRO_TABLE, BECKMANN]
)
def test_c_sample_is_the_file_formats_reference_sampler(models, override, tmp_path):
    # the same (wi, u1, u2) give the same branch and direction in the generated C (float32)
    # and in fileformat.lobe.sample (numpy float64): one algorithm, written twice for two
    # targets, kept together by this test
    from neural_brdf.fileformat import lobe as lobe_format

    c = CProgram(models["anisotropic"], tmp_path, lobe=override)
    stored = lobe_format.complete(override)
    rng = np.random.default_rng(11)
    n = 4000
    wi = unit(rng, n)
    wi[:, 2] = np.abs(wi[:, 2]) + 0.05
    wi = (wi / np.linalg.norm(wi, axis=-1, keepdims=True)).astype(np.float32)
    u1, u2 = rng.random(n).astype(np.float32), rng.random((n, 2)).astype(np.float32)
    wo_c, pdf_c = c.sample(wi, u1, u2)
    wo_r, pdf_r = lobe_format.sample(stored, wi.astype(np.float64), u1, u2)
    err = np.linalg.norm(wo_c - wo_r, axis=-1)
    # float32 against float64 (and 20 bisections against 60 for Beckmann): measured 1e-6
    # at the 99th percentile, 3e-6 at the 99.9th; a row may differ where u1 is within
    # rounding of the share w, hence a quantile
    assert np.quantile(err, 0.999) < 1e-4, np.quantile(err, [0.5, 0.99, 0.999])
    assert 0.3 < np.mean(u1 < lobe_format.at(stored, wi[:, 2])[2]) < 0.9  # both branches
    both = (pdf_r > 0) & (err < 1e-4)
    np.testing.assert_allclose(pdf_c[both], pdf_r[both], rtol=1e-3)


# ------------------------------------------------------------------ GLSL
ES_MAIN = """
uniform vec4 v;
out vec4 color;
void main() {
    vec3 w;
    float p = neural_brdf_sample(normalize(v.xyz), v.w, v.xy, w);
    color = vec4(neural_brdf_eval(normalize(v.xyz), normalize(v.zyx)) + w,
                 p + neural_brdf_pdf(v.xyz, w));
}
"""
VK_MAIN = ES_MAIN.replace("uniform vec4 v;", "layout(location = 0) in vec4 v;").replace(
    "out vec4 color;", "layout(location = 0) out vec4 color;"
)


def glsl_validate(source: str, folder: Path) -> None:
    tool = shutil.which("glslangValidator")
    assert tool, "glslangValidator (Debian glslang-tools) is needed"
    folder.mkdir(parents=True, exist_ok=True)
    es = folder / "es.frag"
    es.write_text(
        "#version 300 es\nprecision highp float;\nprecision highp int;\n" + source + ES_MAIN
    )
    r = subprocess.run([tool, str(es)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-2000:]
    vk = folder / "vk.frag"
    vk.write_text("#version 450\n" + source + VK_MAIN)
    r = subprocess.run(
        [tool, "-V", str(vk), "-o", str(folder / "vk.spv")], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stdout[-2000:]


@pytest.mark.parametrize("enc", list(MODELS))
def test_glsl_validates(models, tmp_path, enc):
    glsl_validate(backends.generate(models[enc], "glsl"), tmp_path)


def test_glsl_validator_rejects_broken_code(tmp_path):
    """The validation above can fail: a type error is reported."""
    with pytest.raises(AssertionError):
        glsl_validate("vec3 neural_brdf_eval(vec3 wi, vec3 wo) { return 1; }\n", tmp_path)


# ------------------------------------------------------------------ WGSL (wgpu: naga + lavapipe)
WGSL_KERNEL = """
@group(0) @binding(0) var<storage, read> pairs: array<f32>;
@group(0) @binding(1) var<storage, read_write> result: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= arrayLength(&result) / 3u) {
        return;
    }
    let wi = vec3<f32>(pairs[6u * i], pairs[6u * i + 1u], pairs[6u * i + 2u]);
    let wo = vec3<f32>(pairs[6u * i + 3u], pairs[6u * i + 4u], pairs[6u * i + 5u]);
    let f = neural_brdf_eval(wi, wo);
    let s = neural_brdf_sample(wi, 0.5f, vec2<f32>(0.25f, 0.75f));
    let keep = s.pdf + neural_brdf_pdf(wi, s.wo);      // the sampling code is compiled too
    result[3u * i] = select(f.x, keep, keep < -1.0f);
    result[3u * i + 1u] = f.y;
    result[3u * i + 2u] = f.z;
}
"""


def wgsl_eval(device, source: str, wi, wo) -> np.ndarray:
    from wgpu.utils.compute import compute_with_buffers

    device.create_shader_module(code=source)  # naga validation; raises on error
    n = len(wi)
    rows = np.concatenate([wi, wo], 1).astype(np.float32).reshape(-1)
    out = compute_with_buffers({0: rows}, {1: (n * 3, "f")}, source + WGSL_KERNEL, n=(n + 63) // 64)
    return np.frombuffer(out[1], np.float32).reshape(n, 3).copy()


@pytest.mark.parametrize(
    "lobe",
    [ANISO_RETRO, PER_INCIDENCE, RETRO_TABLE, BECKMANN],
    ids=["aniso_retro", "per_incidence", "both", "beckmann"],
)
def test_shaders_with_every_lobe_shape_compile(models, wgpu_device, tmp_path, lobe):
    """The sampling code of anisotropic, retro and per-incidence lobes is valid GLSL ES
    3.00, Vulkan GLSL and WGSL (the C of the same instructions is checked against a
    reference pdf and by chi-square above)."""
    glsl_validate(backends.generate(models["anisotropic"], "glsl", lobe=lobe), tmp_path)
    wgsl = backends.generate(models["anisotropic"], "wgsl", lobe=lobe)
    wgpu_device.create_shader_module(code=wgsl + WGSL_KERNEL)  # naga validation; raises


def test_wgsl_validator_rejects_broken_code(wgpu_device):
    with pytest.raises(Exception, match="(?i)valid"):
        wgpu_device.create_shader_module(code="fn f() -> f32 { return 1i; }")


@pytest.mark.parametrize("enc", list(MODELS))
def test_wgsl_validates_and_matches_onnxruntime(models, wgpu_device, enc):
    source = backends.generate(models[enc], "wgsl")
    wi, wo = pairs(1)
    got = wgsl_eval(wgpu_device, source, wi, wo)
    assert relative_difference(got, onnx_ref(models[enc], wi, wo)) <= GPU_TOL
    check_total(
        lambda a, b: wgsl_eval(wgpu_device, source, a, b), models[enc], GPU_TOL, GPU_SCALE_TOL
    )


# ------------------------------------------------------------------ Dr.Jit
@pytest.fixture(scope="module")
def drjit_eval():
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from neural_brdf.backends.drjit import OnnxProgram

    def run(model, wi, wo):
        cols = OnnxProgram(model)(
            wi=[mi.Float(wi[:, k]) for k in range(3)], wo=[mi.Float(wo[:, k]) for k in range(3)]
        )["f"]
        return np.stack([np.asarray(c) for c in cols], -1)

    return run


@pytest.mark.mitsuba
@pytest.mark.parametrize("enc", list(MODELS))
def test_drjit_matches_onnxruntime(models, drjit_eval, enc):
    wi, wo = pairs(1)
    got = drjit_eval(models[enc], wi, wo)
    assert relative_difference(got, onnx_ref(models[enc], wi, wo)) <= C_TOL
    check_total(lambda a, b: drjit_eval(models[enc], a, b), models[enc], C_TOL)


# ------------------------------------------------------------------ every op
def every_op_model() -> bytes:
    """wi, wo [N, 3] -> f [N, 3]: a sum of terms that use every op the lowering supports."""
    f32 = TensorProto.FLOAT
    inits = {
        "one": np.array([1.0], np.float32),
        "three": np.array([3.0], np.float32),
        "half": np.array([0.5], np.float32),
        "p17": np.array([1.7], np.float32),
        "two": np.array([2.0], np.float32),
        "lo": np.array(-1.0, np.float32),
        "hi": np.array(1.0, np.float32),
        "zero": np.array([0.0], np.float32),
        "W": np.array([[0.3, -0.2, 0.5], [0.1, 0.4, -0.6], [-0.7, 0.2, 0.9]], np.float32),
        "b": np.array([0.05, -0.1, 0.2], np.float32),
        "W2": np.array([[0.2, 0.1, 0.0], [-0.3, 0.5, 0.2], [0.4, -0.1, 0.6]], np.float32),
        "T": np.linspace(0.1, 2.0, 48, dtype=np.float32).reshape(16, 3),
        "four": np.array(4.0, np.float32),
        "tlo": np.array(0.0, np.float32),
        "thi": np.array(15.0, np.float32),
        "eight": np.array(8, np.int64),
        "ax1": np.array([1], np.int64),
    }
    nodes, terms = [], []

    def n(op, ins, out=None, **attrs):
        out = out or f"v{len(nodes)}"
        nodes.append(helper.make_node(op, ins, [out], name=f"{op}_{len(nodes)}", **attrs))
        return out

    s, d, p = n("Add", ["wi", "wo"]), n("Sub", ["wi", "wo"]), n("Mul", ["wi", "wo"])
    a = n("Abs", [d])
    a1 = n("Add", [a, "one"])
    terms += [
        n("Sqrt", [a]),
        n("Exp", [n("Neg", [a])]),
        n("Log", [a1]),
        n("Floor", [n("Mul", [s, "three"])]),
        n("Ceil", [n("Mul", [d, "three"])]),
        n("Sin", [s]),
        n("Cos", [d]),
        n("Atan", [p]),
        n("Asin", [n("Clip", [p, "lo", "hi"])]),
        n("Acos", [n("Mul", [p, "half"])]),
        n("Tanh", [s]),
        n("Erf", [d]),
        n("Reciprocal", [a1]),
        n("Relu", [d]),
        n("Sigmoid", [s]),
        n("Softplus", [d]),
        n("Pow", [a, "p17"]),
        n("Pow", [d, "two"]),
        n("Max", [s, d, p]),
        n("Min", [s, d]),
        n("Sum", [s, d, p]),
        n("Div", [s, a1]),
        n("Identity", [p]),
    ]
    nan = n("IsNaN", [n("Div", [d, d])])  # 0 / 0 where wi == wo
    inf = n("IsInf", [n("Div", ["one", d])])  # 1 / 0 there too
    gt, lt = n("Greater", [s, d]), n("Less", [s, p])
    ge, le = n("GreaterOrEqual", [d, p]), n("LessOrEqual", [s, d])
    eq = n("Equal", [n("Floor", [s]), n("Ceil", [d])])
    logic = [
        n("Not", [gt]),
        n("And", [gt, lt]),
        n("Or", [nan, inf]),
        n("Xor", [ge, le]),
        eq,
        nan,
        inf,
    ]
    terms += [n("Cast", [x], to=TensorProto.FLOAT) for x in logic]
    terms.append(n("Where", [n("Or", [nan, inf]), "zero", n("Div", [s, a1])]))
    as_int = n("Cast", [n("Floor", [n("Mul", [s, "three"])])], to=TensorProto.INT32)
    terms.append(n("Cast", [as_int], to=TensorProto.FLOAT))
    terms += [n("Gemm", [s, "W", "b"], transB=1, alpha=0.7), n("MatMul", [d, "W2"])]
    terms += [
        n("ReduceMax", [p], axes=[1]),
        n("ReduceMin", [p], axes=[1]),
        n("ReduceSum", [p, "ax1"]),
        n("ReduceMean", [s], axes=[1]),
        n("ReduceL2", [d], axes=[1]),
        n("ReduceProd", [s], axes=[1]),
    ]
    key = n("ReduceSum", [a, "ax1"], keepdims=0)
    idx = n(
        "Cast",
        [n("Clip", [n("Floor", [n("Mul", [key, "four"])]), "tlo", "thi"])],
        to=TensorProto.INT64,
    )
    terms.append(n("Gather", ["T", n("Sub", [idx, "eight"])], axis=0))  # negative: wraps
    acc = terms[0]
    for t in terms[1:]:
        acc = n("Add", [acc, t])
    n("Mul", [acc, "half"], out="f")
    g = helper.make_graph(
        nodes,
        "every_op",
        [
            helper.make_tensor_value_info("wi", f32, ["N", 3]),
            helper.make_tensor_value_info("wo", f32, ["N", 3]),
        ],
        [helper.make_tensor_value_info("f", f32, ["N", 3])],
        [onnx.numpy_helper.from_array(v, k) for k, v in inits.items()],
    )
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model.SerializeToString()


EVERY_OP_LOBE = {"alpha": 0.3, "weight": 0.5}


@pytest.fixture(scope="module")
def every_op(tmp_path_factory):
    payload = every_op_model()
    wi, wo = pairs(5, 1000)
    wi = np.concatenate([wi, wo[:200]])  # wi == wo rows: 0 / 0, 1 / 0
    wo = np.concatenate([wo, wo[:200]])
    return payload, wi, wo, onnx_ref(payload, wi, wo)


def test_every_op_is_lowered(every_op):
    prog = graph.lower(every_op[0])
    missing = graph.OPS - set(prog.count()) - {"const"}  # constants are folded away
    assert not missing, missing


def test_every_op_in_c(every_op, tmp_path):
    payload, wi, wo, ref = every_op
    assert np.isfinite(ref).all()
    got = CProgram(payload, tmp_path, lobe=EVERY_OP_LOBE).eval(wi, wo)
    assert relative_difference(got, ref) <= C_TOL


def test_every_op_in_glsl(every_op, tmp_path):
    glsl_validate(backends.generate(every_op[0], "glsl", lobe=EVERY_OP_LOBE), tmp_path)


def test_every_op_in_wgsl(every_op, wgpu_device):
    payload, wi, wo, ref = every_op
    got = wgsl_eval(wgpu_device, backends.generate(payload, "wgsl", lobe=EVERY_OP_LOBE), wi, wo)
    assert relative_difference(got, ref) <= EVERY_OP_GPU_TOL


@pytest.mark.mitsuba
def test_every_op_in_drjit(every_op, drjit_eval):
    payload, wi, wo, ref = every_op
    assert relative_difference(drjit_eval(payload, wi, wo), ref) <= C_TOL


def einsum_model() -> bytes:
    """wi, wo -> f by an Einsum (node 'mix'), an op the lowering does not know."""
    node = helper.make_node("Einsum", ["wi", "wo"], ["f"], name="mix", equation="ni,ni->ni")
    g = helper.make_graph(
        [node],
        "g",
        [helper.make_tensor_value_info(k, TensorProto.FLOAT, ["N", 3]) for k in ("wi", "wo")],
        [helper.make_tensor_value_info("f", TensorProto.FLOAT, ["N", 3])],
    )
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()


def test_unknown_op_is_named():
    with pytest.raises(graph.UnsupportedOnnxOp, match="'mix'.*'Einsum'"):
        backends.generate(einsum_model(), "c", lobe=EVERY_OP_LOBE)
    assert issubclass(graph.UnsupportedOnnxOp, InputError)


# ------------------------------------------------------------------ registry and CLI
REPO = Path(__file__).resolve().parents[2]
# back end -> the test that checks what it computes against onnxruntime.  Each language
# runs in its own harness (C through cc, WGSL on lavapipe, GLSL in WebGL2, Dr.Jit on
# LLVM), so a new back end brings its own test, named here.
PARITY = {
    "c": "tests/backends/test_codegen.py::test_c_matches_onnxruntime",
    "glsl": "tests/viewer/test_viewer.py::test_generated_glsl_and_wgsl_reproduce_onnxruntime",
    "wgsl": "tests/backends/test_codegen.py::test_wgsl_validates_and_matches_onnxruntime",
    "drjit": "tests/backends/test_codegen.py::test_drjit_matches_onnxruntime",
}


def test_every_back_end_has_an_onnxruntime_parity_test():
    # docs/codegen.md: every back end is tested against onnxruntime
    missing = [t for t in backends.REGISTRY if t not in PARITY]
    assert not missing, (
        f"back ends {missing} have no parity test: write one that compares the generated "
        "code with onnxruntime (tests/backends/test_codegen.py's test_c_matches_onnxruntime) "
        "and name it in PARITY in tests/backends/test_codegen.py"
    )
    stale = [t for t in PARITY if t not in backends.REGISTRY]
    assert not stale, f"PARITY in tests/backends/test_codegen.py names no back end {stale}"
    for target, test in PARITY.items():
        path, name = test.split("::")
        source = (REPO / path).read_text(encoding="utf-8")
        assert f"\ndef {name}(" in source, f"PARITY[{target!r}]: {test} does not exist"


def test_registry():
    assert set(backends.TARGETS) <= set(backends.REGISTRY)
    # TARGETS is every registered back end but the executors, in the registry's order
    assert backends.TARGETS == tuple(t for t in backends.REGISTRY if t not in backends.EXECUTORS)
    assert {"c", "glsl", "wgsl"} <= set(backends.TARGETS) and "drjit" not in backends.TARGETS
    assert backends.EXECUTORS <= set(backends.REGISTRY)
    for target in backends.TARGETS:
        assert backends.get(target)().name == target
    # a name no back end will take (hlsl is docs/codegen.md's example of a new one)
    with pytest.raises(InputError, match="no_such_target"):
        backends.get("no_such_target")


@pytest.mark.parametrize(
    "target",
    [
        t if t not in backends.EXECUTORS else pytest.param(t, marks=pytest.mark.mitsuba)
        for t in backends.REGISTRY
    ],
)
def test_each_registry_key_is_its_class_name(target):
    cls = backends.get(target)
    assert cls.name == target, (
        f"backends.REGISTRY[{target!r}] is {cls.__name__}, named {cls.name!r}"
    )


@pytest.mark.parametrize(
    "line, cause",
    [
        (
            ("neural_brdf.backends.no_such_module", "HLSLRenderer"),
            "neural_brdf.backends.no_such_module: No module named 'neural_brdf.backends.",
        ),
        (
            ("neural_brdf.backends.c", "CRender"),
            "neural_brdf.backends.c: has no class 'CRender'",
        ),
    ],
    ids=["module", "class"],
)
def test_a_broken_registry_line_is_one_line_naming_the_back_end(
    line, cause, monkeypatch, tiny_run, tmp_path, capsys
):
    # it was the raw ModuleNotFoundError / AttributeError of importlib and getattr
    monkeypatch.setitem(backends.REGISTRY, "hlsl", line)
    monkeypatch.setattr(backends, "TARGETS", (*backends.TARGETS, "hlsl"))
    with pytest.raises(InputError) as e:
        backends.get("hlsl")
    message = str(e.value)
    assert message.startswith("target 'hlsl': ") and cause in message and "\n" not in message
    from neural_brdf.tooling.cli import main

    out = tmp_path / "brdf.hlsl"
    args = ["codegen", str(tiny_run / "model.onnx"), "--target", "hlsl", "-o", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "target 'hlsl'" in err[0] and cause in err[0], err
    assert not out.exists()


def test_codegen_help_lists_every_target(monkeypatch, capsys):
    # the command's help and --target's are built from TARGETS: a new target is in them
    from neural_brdf.tooling.cli import main

    monkeypatch.setattr(backends, "TARGETS", (*backends.TARGETS, "hlsl"))
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert f"generate source code ({', '.join(backends.TARGETS)})" in text, text
    with pytest.raises(SystemExit) as e:
        main(["codegen", "--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "{" + ",".join(backends.TARGETS) + "}" in text  # the choices
    assert "c (a C99 header), " in text and ", hlsl " in text, text  # a target without a note


@pytest.mark.parametrize("out", ["-", "/dev/stdout"])
def test_codegen_into_a_closed_pipe_exits_quietly(models, out):
    # `neural-brdf codegen MODEL -o /dev/stdout | head -0`: the reader is gone before the
    # code is written; as for `-o -`, no error (it said "cannot write (Broken pipe)", exit 2)
    from cli_helpers import into_closed_pipe

    code, err = into_closed_pipe("codegen", str(models["isotropic"]), "--target", "c", "-o", out)
    assert code == 0, err
    assert "Traceback" not in err and "error" not in err


def test_cli_codegen(models, tmp_path, capsys):
    from neural_brdf.tooling.cli import main

    for target in backends.TARGETS:
        out = tmp_path / f"brdf.{target}"
        assert main(["codegen", str(models["isotropic"]), "--target", target, "-o", str(out)]) == 0
        text = out.read_text()
        assert "neural_brdf_eval" in text and "neural_brdf_sample" in text
        assert "max_albedo" in text
    unknown = ["--target", "no_such_target", "-o", str(tmp_path / "x")]
    assert main(["codegen", str(models["isotropic"]), *unknown]) == 2  # argparse's choices
    prefixed = tmp_path / "gold.h"
    args = ["codegen", str(models["isotropic"]), "--target", "c", "--prefix", "gold"]
    assert main([*args, "-o", str(prefixed)]) == 0
    text = prefixed.read_text()
    assert "gold_eval" in text and "GOLD_H" in text and "neural_brdf_eval" not in text
    bad = tmp_path / "bad.onnx"
    bad.write_text("not a model")
    assert main(["codegen", str(bad), "--target", "c", "-o", str(tmp_path / "x.h")]) == 2
    assert (
        main(
            [
                "codegen",
                str(tmp_path / "missing.onnx"),
                "--target",
                "c",
                "-o",
                str(tmp_path / "x.h"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("error: ") for line in err)
    assert not (tmp_path / "x.h").exists()


# ------------------------------------------------------------------ the header comment
# A long metadata value, the target's JSON, is cut at an item's end and marked with an
# ellipsis, never in mid-key (``"kind": `` and nothing), no value ends in a backslash (in
# GLSL and C it joins the next line to a // comment), and the header still compiles.  The
# model is the session's tiny run (conftest.tiny_run) with its ``target`` metadata
# replaced.
def long_target() -> str:
    """A target JSON whose character HEADER_VALUE_CHARS - 1 falls just after
    ``"kind": ``: a plain cut there leaves the key without its value."""
    head = {"description": "", "kind": "mitsuba", "path": "/data/teachers/tiles.xml"}
    text = json.dumps(head)
    pad = HEADER_VALUE_CHARS - text.index('"mitsuba"')  # "kind": then the limit
    head["description"] = "rough plastic " + "x" * (pad - len("rough plastic "))
    text = json.dumps(head)
    assert text[:HEADER_VALUE_CHARS].endswith('"kind": ')
    return text


def with_target(model: Path, target: str, out: Path) -> Path:
    proto = onnx.load(str(model))
    for prop in proto.metadata_props:
        if prop.key == "target":
            prop.value = target
            break
    else:
        raise AssertionError("the tiny run's model has no target metadata")
    onnx.save(proto, str(out))
    return out


def header_line(text: str, key: str) -> str:
    """The value of ``key`` in the header (C: `` * key: ``, GLSL, WGSL: ``// key: ``)."""
    (line,) = [ln for ln in text.splitlines() if ln.startswith((f" * {key}: ", f"// {key}: "))]
    return line.split(f"{key}: ", 1)[1]


@pytest.mark.parametrize("lang", ["c", "glsl", "wgsl"])
def test_a_long_target_is_cut_at_an_item_with_an_ellipsis(tiny_run, tmp_path, lang):
    target = long_target()
    model = with_target(tiny_run / "model.onnx", target, tmp_path / "long.onnx")
    text = backends.generate(model, lang)
    shown = header_line(text, "target")
    assert shown.endswith(ELLIPSIS) and len(shown) <= HEADER_VALUE_CHARS
    kept = shown.removesuffix(ELLIPSIS)
    # what is kept is the JSON up to the end of a whole item: never '"kind": ' alone
    assert target.startswith(kept) and target[len(kept) :].startswith(", ")
    assert not kept.rstrip().endswith(":")


def test_a_short_target_is_shown_whole(tiny_run, tmp_path):
    target = json.dumps({"kind": "analytic", "model": "ggx"})
    model = with_target(tiny_run / "model.onnx", target, tmp_path / "short.onnx")
    assert header_line(backends.generate(model, "c"), "target") == target


@pytest.mark.parametrize(
    "value",
    [
        "C:\\teachers\\" + "a" * HEADER_VALUE_CHARS,  # cut inside a Windows path
        "a" * (HEADER_VALUE_CHARS - 10) + " x\\\\\\ " + "b" * 20,  # cut at backslashes
        "a" * (HEADER_VALUE_CHARS - 1) + "\\" + "b" * 20,  # the limit's last character
        "C:\\teachers\\",  # short, and ending in one
    ],
)
def test_no_header_value_ends_in_a_backslash(tiny_run, tmp_path, value):
    """In GLSL (and C) a line that ends in a backslash joins the next one to it: a
    line comment (``//``) would swallow the line after it."""
    model = with_target(tiny_run / "model.onnx", value, tmp_path / "slash.onnx")
    shown = header_line(backends.generate(model, "glsl"), "target")
    assert not shown.endswith("\\") and len(shown) <= HEADER_VALUE_CHARS


def test_the_cut_header_compiles(tiny_run, tmp_path):
    """The header with the cut target is still a comment: the C file compiles."""
    cc = shutil.which("cc")
    assert cc, "a C compiler is needed (the codegen tests use it too)"
    model = with_target(tiny_run / "model.onnx", long_target(), tmp_path / "long.onnx")
    header = tmp_path / "brdf.h"
    header.write_text(backends.generate(model, "c"))
    main = tmp_path / "main.c"
    main.write_text('#include "brdf.h"\nint main(void) { return 0; }\n')
    r = subprocess.run(
        [cc, "-std=c99", "-Wall", "-Werror", "-fsyntax-only", str(main)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-2000:]


# ------------------------------------------------------------------ the lobe's directions
# neural_brdf_pdf and neural_brdf_sample normalise their directions as neural_brdf_eval
# does (the exported graph's unit_or_invalid): pdf(k wi, k' wo) is the lobe's density at
# the unit vectors, and a non-finite or zero-length direction gives pdf 0 (sample: pdf
# 0 and wo below the horizon, a rejected sample).  The references are the mixture density
# of analytic's distributions (lobe_reference.mixture_pdf) and the file format's sampler
# in float64, at the directions normalised by numpy.  The network plays no part: the
# file is the smallest one of the contract (f = wi * wo) with a lobe given.
LOBE_SCALES = (1e-30, 1e-3, 7.5, 1e4, 1e30)
SCALED_WO_TOL = 1e-4  # a scaled wi's sample against the unit wi's (float32 rounding)
# WebGL2 on SwiftShader: sin and cos of phi = 2 pi u2.y are loose near 2 pi, so the
# sampled directions are compared with the float64 sampler to 0.05 (measured 0.035 at
# most; the unscaled rows alike), and with the unit rows' to SCALED_WO_TOL
WEBGL_WO_TOL = 0.05
LOBE_SHAPES = [EVERY_OP_LOBE, ANISO_RETRO, PER_INCIDENCE, BECKMANN]
LOBE_IDS = ["ggx", "aniso_retro", "per_incidence", "beckmann"]


def product_model(scale: float = 1.0) -> bytes:
    """wi, wo [N, 3] -> f = scale * wi * wo: the smallest file of the contract, with no
    stored lobe (the tests give one)."""
    f32 = TensorProto.FLOAT
    nodes = [
        helper.make_node("Mul", ["wi", "wo"], ["p"]),
        helper.make_node("Mul", ["p", "k"], ["f"]),
    ]
    g = helper.make_graph(
        nodes,
        "product",
        [helper.make_tensor_value_info(k, f32, ["N", 3]) for k in ("wi", "wo")],
        [helper.make_tensor_value_info("f", f32, ["N", 3])],
        [onnx.numpy_helper.from_array(np.array([scale], np.float32), "k")],
    )
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model.SerializeToString()


def lobe_rows(seed: int = 21, n: int = 400):
    """Rows (wi, wo, u1, u2) as float32 and a mask of the rows whose wi or wo is not a
    direction: n unit pairs (wo near the mirror and the retro directions, and anywhere),
    then blocks of the same n scaled on either side and on both by LOBE_SCALES (the
    same (u1, u2) in every block), then test_codegen's HOSTILE rows as wi and as wo."""
    rng = np.random.default_rng(seed)
    wi = unit(rng, n)
    wi[:, 2] = np.abs(wi[:, 2]) + 0.05
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo = np.concatenate(
        [
            wi[: n // 3] * [-1.0, -1.0, 1.0] + rng.normal(0, 0.1, (n // 3, 3)),
            wi[n // 3 : 2 * n // 3] + rng.normal(0, 0.1, (2 * n // 3 - n // 3, 3)),
            unit(rng, n - 2 * n // 3),
        ]
    )
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    given = [(wi, wo)]
    for k in LOBE_SCALES:
        given += [(wi * k, wo), (wi, wo * k), (wi * k, wo / k)]
    bad = np.array(HOSTILE, dtype=np.float64)
    good = np.repeat(wi[:1], len(bad), 0)
    given += [(bad, good), (good, bad)]
    gwi = np.concatenate([a for a, _ in given]).astype(np.float32)
    gwo = np.concatenate([b for _, b in given]).astype(np.float32)
    hostile = np.zeros(len(gwi), bool)
    hostile[-2 * len(bad) :] = True
    reps = len(given) - 2
    u1 = np.concatenate([np.tile(rng.random(n), reps), rng.random(2 * len(bad))])
    u2 = np.concatenate([np.tile(rng.random((n, 2)), (reps, 1)), rng.random((2 * len(bad), 2))])
    return (gwi, gwo, u1.astype(np.float32), u2.astype(np.float32)), hostile


def check_lobe_directions(run, lobe: dict, tol: float, wo_tol: float, n: int = 400) -> None:
    """``run(wi, wo, u1, u2) -> (pdf(wi, wo), wo and pdf of sample(wi, u1, u2))`` of one
    back end on :func:`lobe_rows`, against the float64 references at the directions
    normalised (:func:`graph_unit`): pdf to ``tol`` (relative), a sampled direction to
    ``wo_tol`` (99.9th percentile); each block of scaled rows draws what the unit rows
    draw, to SCALED_WO_TOL; a non-finite or zero-length direction gives pdf 0 and, as
    wi, a rejected sample."""
    from neural_brdf.fileformat import lobe as lobe_format

    (wi, wo, u1, u2), hostile = lobe_rows(n=n)
    pdf, swo, spdf = run(wi, wo, u1, u2)
    assert np.isfinite(pdf).all() and np.isfinite(swo).all() and np.isfinite(spdf).all()
    ok = ~hostile
    ref = mixture_pdf(graph_unit(wi[ok]), graph_unit(wo[ok]), lobe)
    assert (ref > 0).mean() > 0.5
    np.testing.assert_allclose(pdf[ok], ref, rtol=tol, atol=1e-6)
    assert (pdf[hostile] == 0.0).all(), pdf[hostile]
    # sample: a hostile wi draws a rejected sample (pdf 0, wo below the horizon)
    bad_wi = hostile & (~np.isfinite(wi).all(1) | (wi == 0).all(1))
    assert bad_wi.sum() == len(HOSTILE)
    assert (spdf[bad_wi] == 0.0).all() and (swo[bad_wi][:, 2] < 0.0).all()
    # a scaled wi draws what the unit wi draws
    blocks = (len(wi) - 2 * len(HOSTILE)) // n
    for b in range(1, blocks):
        moved = np.linalg.norm(swo[b * n : (b + 1) * n] - swo[:n], axis=-1)
        assert np.quantile(moved, 0.999) < SCALED_WO_TOL, (b, np.quantile(moved, [0.5, 0.999]))
    # ... what the file format's sampler draws from the unit wi, a unit vector
    good = ~bad_wi
    uwi = graph_unit(wi[good])
    wo_r, _ = lobe_format.sample(lobe_format.complete(lobe), uwi, u1[good], u2[good])
    err = np.linalg.norm(swo[good] - wo_r, axis=-1)
    assert np.quantile(err, 0.999) < wo_tol, np.quantile(err, [0.5, 0.99, 0.999])
    drawn = spdf[good] > 0
    assert drawn.mean() > 0.5
    np.testing.assert_allclose(np.linalg.norm(swo[good][drawn], axis=-1), 1.0, atol=wo_tol)
    # and returns the density at the wo it drew
    at_drawn = mixture_pdf(uwi[drawn], graph_unit(swo[good][drawn]), lobe)
    np.testing.assert_allclose(spdf[good][drawn], at_drawn, rtol=tol, atol=1e-6)


@pytest.mark.parametrize("flags", [(), ("-ffast-math",)], ids=["c99", "fast_math"])
@pytest.mark.parametrize("lobe", LOBE_SHAPES, ids=LOBE_IDS)
def test_c_pdf_and_sample_normalise_their_directions(tmp_path, lobe, flags):
    c = CProgram(product_model(), tmp_path, lobe=lobe, flags=flags)

    def run(wi, wo, u1, u2):
        swo, spdf = c.sample(wi, u1, u2)
        return c.pdf(wi, wo), swo, spdf

    check_lobe_directions(run, lobe, PDF_RTOL, 1e-4)
    # sample() returns pdf(wo) of its wo for scaled and hostile wi too (bit for bit in
    # ISO C; -ffast-math may compile the same expressions differently in the two)
    (wi, _, u1, u2), _ = lobe_rows()
    swo, spdf = c.sample(wi, u1, u2)
    np.testing.assert_allclose(spdf, c.pdf(wi, swo), rtol=1e-4 if flags else 0.0, atol=0.0)


# Random numbers the sampler refuses: not finite, or outside [0, 1) (1 included), in
# u1, u2.x or u2.y; each gives a rejected sample, wo = (0, 0, -1) and pdf 0, never a NaN
# direction (before: wo = NaN for a bad u2, and a NaN u1 drew the GGX branch).
BAD_U = (np.nan, np.inf, -np.inf, -1.0, -1e-30, 1.0, 2.0, 1e30)
# ... and ones it takes: the ends of [0, 1), a subnormal
GOOD_U = (0.0, -0.0, float(np.nextafter(np.float32(1.0), np.float32(0.0))), 1e-45, 0.5)


def random_number_rows(seed: int = 23) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(wi, u1, u2) float32 rows: each value of BAD_U and GOOD_U in each of the three
    places, the other two ordinary, at four incident directions; the mask of bad rows."""
    rng = np.random.default_rng(seed)
    wi_list, us, bad = [], [], []
    for wi in ([0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.3, -0.2, 0.5], [0.9999, 0.0, 0.01414]):
        for value in BAD_U + GOOD_U:
            for place in range(3):
                u = rng.uniform(0.05, 0.95, 3)
                u[place] = value
                wi_list.append(wi)
                us.append(u)
                bad.append(value in BAD_U or np.isnan(value))
    u = np.array(us, dtype=np.float32)
    return np.array(wi_list, np.float32), u[:, 0], u[:, 1:], np.array(bad)


def check_random_numbers(sample) -> None:
    """``sample(wi, u1, u2) -> (wo, pdf)`` of one back end on :func:`random_number_rows`:
    a refused number gives wo = (0, 0, -1) and pdf 0; a good one a finite unit wo."""
    wi, u1, u2, bad = random_number_rows()
    wo, pdf = sample(wi, u1, u2)
    assert np.isfinite(wo).all() and np.isfinite(pdf).all()
    assert (wo[bad] == [0.0, 0.0, -1.0]).all(), wo[bad]
    assert (pdf[bad] == 0.0).all(), pdf[bad]
    np.testing.assert_allclose(np.linalg.norm(wo[~bad], axis=-1), 1.0, atol=1e-3)
    assert (pdf[~bad] > 0).mean() > 0.5


@pytest.mark.parametrize("flags", [(), ("-ffast-math",)], ids=["c99", "fast_math"])
@pytest.mark.parametrize("lobe", [ANISO_RETRO, BECKMANN, {"alpha": 0.3, "weight": 0.0}])
def test_c_sample_rejects_bad_random_numbers(tmp_path, lobe, flags):
    c = CProgram(product_model(), tmp_path, lobe=lobe, flags=flags)
    check_random_numbers(c.sample)


WGSL_LOBE_KERNEL = """
@group(0) @binding(0) var<storage, read> nb_rows: array<f32>;
@group(0) @binding(1) var<storage, read_write> nb_res: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= arrayLength(&nb_res) / 5u) {
        return;
    }
    let b = 9u * i;
    let wi = vec3<f32>(nb_rows[b], nb_rows[b + 1u], nb_rows[b + 2u]);
    let wo = vec3<f32>(nb_rows[b + 3u], nb_rows[b + 4u], nb_rows[b + 5u]);
    let s = neural_brdf_sample(wi, nb_rows[b + 6u], vec2<f32>(nb_rows[b + 7u], nb_rows[b + 8u]));
    nb_res[5u * i] = neural_brdf_pdf(wi, wo);
    nb_res[5u * i + 1u] = s.wo.x;
    nb_res[5u * i + 2u] = s.wo.y;
    nb_res[5u * i + 3u] = s.wo.z;
    nb_res[5u * i + 4u] = s.pdf;
}
"""


@pytest.mark.parametrize("lobe", [ANISO_RETRO, BECKMANN], ids=["aniso_retro", "beckmann"])
def test_wgsl_pdf_and_sample_normalise_their_directions(wgpu_device, lobe):
    from wgpu.utils.compute import compute_with_buffers

    source = backends.generate(product_model(), "wgsl", lobe=lobe) + WGSL_LOBE_KERNEL
    wgpu_device.create_shader_module(code=source)  # naga validation; raises on error

    def run(wi, wo, u1, u2):
        n = len(wi)
        rows = np.concatenate([wi, wo, u1[:, None], u2], 1).astype(np.float32).reshape(-1)
        out = compute_with_buffers({0: rows}, {1: (n * 5, "f")}, source, n=(n + 63) // 64)
        res = np.frombuffer(out[1], np.float32).reshape(n, 5)
        return res[:, 0], res[:, 1:4], res[:, 4]

    check_lobe_directions(run, lobe, GPU_TOL, 1e-3)
    check_random_numbers(lambda wi, u1, u2: run(wi, np.zeros_like(wi), u1, u2)[1:])


GLSL_LOBE_CALLS = {  # vec3 neural_brdf_eval(a, b) of the harness, over the lobe's functions
    "pdf": "return vec3(nb_lobe_pdf(a, b), 0.0, 0.0);",
    "wo": "vec3 w; nb_lobe_sample(a, b.x, b.yz, w); return w;",
    "spdf": "vec3 w; return vec3(nb_lobe_sample(a, b.x, b.yz, w), 0.0, 0.0);",
}


def test_glsl_pdf_and_sample_normalise_their_directions():
    """GLSL ES in WebGL2 (headless Chromium): the harness evaluates a function
    ``neural_brdf_eval(a, b)``, here one per output over the generated pdf and sample
    (renamed nb_lobe_*; b holds (u1, u2) for sample)."""
    import re

    from harness import gpu_browser

    lobe = ANISO_RETRO
    text = backends.generate(product_model(), "glsl", lobe=lobe)
    text = re.sub(r"\bneural_brdf_(pdf|sample|eval)\b", r"nb_lobe_\1", text)
    sources = {
        k: f"{text}\nvec3 neural_brdf_eval(vec3 a, vec3 b) {{ {call} }}\n"
        for k, call in GLSL_LOBE_CALLS.items()
    }

    def run(wi, wo, u1, u2):
        u = np.concatenate([u1[:, None], u2], 1).astype(np.float32)
        with gpu_browser.Session() as s:
            pdf = s.eval_glsl(sources["pdf"], wi, wo)[:, 0]
            swo = s.eval_glsl(sources["wo"], wi, u)
            spdf = s.eval_glsl(sources["spdf"], wi, u)[:, 0]
        return pdf, swo, spdf

    check_lobe_directions(run, lobe, GPU_TOL, WEBGL_WO_TOL)
    check_random_numbers(lambda wi, u1, u2: run(wi, np.zeros_like(wi), u1, u2)[1:])


# ------------------------------------------------------------------ prefixes
# The files of several models in one program: each file's names (functions, helpers,
# tables, textures, macros, C's include guard, WGSL's sample struct) carry its prefix, the
# default one (neural_brdf) giving the names of a file without one.  Three models with
# different values and lobes: the every-op graph, and f = k * wi * wo for two k.
PREFIXED = {  # prefix (None: the default) -> (model, lobe)
    "gold": (every_op_model, EVERY_OP_LOBE),
    "brushed_v2": (lambda: product_model(2.5), ANISO_RETRO),
    None: (lambda: product_model(-0.75), BECKMANN),
}

TWO_HEADERS_DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include "gold.h"
#include "brushed_v2.h"
#include "neural_brdf.h"

/* driver N IN OUT: rows of 6 float32 (wi, wo) -> f and pdf of each file (12 float32) */
int main(int argc, char **argv)
{
    long n, i;
    float row[6], out[12];
    FILE *in, *res;
    if (argc != 4) return 2;
    n = atol(argv[1]);
    in = fopen(argv[2], "rb");
    res = fopen(argv[3], "wb");
    if (!in || !res) return 2;
    for (i = 0; i < n; i++) {
        if (fread(row, sizeof(float), 6, in) != 6) return 3;
        gold_eval(row, row + 3, out);
        brushed_v2_eval(row, row + 3, out + 3);
        neural_brdf_eval(row, row + 3, out + 6);
        out[9] = gold_pdf(row, row + 3);
        out[10] = brushed_v2_pdf(row, row + 3);
        out[11] = neural_brdf_pdf(row, row + 3);
        fwrite(out, sizeof(float), 12, res);
    }
    fclose(in);
    fclose(res);
    return 0;
}
"""


def test_headers_with_different_prefixes_work_in_one_c_program(tmp_path):
    """Three headers in one translation unit (-Wall -Wextra -pedantic -Werror): each gives
    its own model's f (against onnxruntime) and its own lobe's pdf."""
    cc = shutil.which("cc") or shutil.which("gcc")
    assert cc, "a C compiler (cc) is needed"
    payloads = {}
    for prefix, (model, lobe) in PREFIXED.items():
        payloads[prefix] = model()
        text = backends.generate(payloads[prefix], "c", lobe=lobe, prefix=prefix)
        (tmp_path / f"{prefix or 'neural_brdf'}.h").write_text(text)
    (tmp_path / "driver.c").write_text(TWO_HEADERS_DRIVER)
    exe = tmp_path / "driver"
    flags = ["-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror"]
    r = subprocess.run(
        [cc, *flags, "-o", str(exe), str(tmp_path / "driver.c"), "-lm"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    wi, wo = pairs(9, 500)
    np.concatenate([wi, wo], 1).tofile(tmp_path / "in.bin")
    subprocess.run(
        [str(exe), str(len(wi)), str(tmp_path / "in.bin"), str(tmp_path / "out.bin")], check=True
    )
    out = np.fromfile(tmp_path / "out.bin", np.float32).reshape(-1, 12)
    for k, (prefix, (_, lobe)) in enumerate(PREFIXED.items()):
        ref = onnx_ref(payloads[prefix], wi, wo)
        assert relative_difference(out[:, 3 * k : 3 * k + 3], ref) <= C_TOL, prefix
        ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        np.testing.assert_allclose(
            out[:, 9 + k], mixture_pdf(wi, wo, lobe), rtol=PDF_RTOL, atol=1e-6
        )
        assert (out[~ok, 9 + k] == 0).all()
    # the three models differ: a header dropped for another would show
    assert relative_difference(out[:, 3:6], out[:, 0:3]) > 0.1
    assert relative_difference(out[:, 6:9], out[:, 3:6]) > 0.1


WGSL_PREFIXES_KERNEL = """
@group(0) @binding(0) var<storage, read> nb_rows: array<f32>;
@group(0) @binding(1) var<storage, read_write> nb_res: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= arrayLength(&nb_res) / 12u) {
        return;
    }
    let wi = vec3<f32>(nb_rows[6u * i], nb_rows[6u * i + 1u], nb_rows[6u * i + 2u]);
    let wo = vec3<f32>(nb_rows[6u * i + 3u], nb_rows[6u * i + 4u], nb_rows[6u * i + 5u]);
    let f0 = gold_eval(wi, wo);
    let f1 = brushed_v2_eval(wi, wo);
    let f2 = neural_brdf_eval(wi, wo);
    let s0: GoldSample = gold_sample(wi, 0.5f, vec2<f32>(0.25f, 0.75f));
    let s1: BrushedV2Sample = brushed_v2_sample(wi, 0.5f, vec2<f32>(0.25f, 0.75f));
    let s2: NeuralBrdfSample = neural_brdf_sample(wi, 0.5f, vec2<f32>(0.25f, 0.75f));
    let b = 12u * i;
    nb_res[b] = f0.x;
    nb_res[b + 1u] = f0.y;
    nb_res[b + 2u] = f0.z;
    nb_res[b + 3u] = f1.x;
    nb_res[b + 4u] = f1.y;
    nb_res[b + 5u] = f1.z;
    nb_res[b + 6u] = f2.x;
    nb_res[b + 7u] = f2.y;
    nb_res[b + 8u] = f2.z;
    nb_res[12u * i + 9u] = gold_pdf(wi, wo) + 0.0f * s0.pdf;
    nb_res[12u * i + 10u] = brushed_v2_pdf(wi, wo) + 0.0f * s1.pdf;
    nb_res[12u * i + 11u] = neural_brdf_pdf(wi, wo) + 0.0f * s2.pdf;
}
"""


def test_wgsl_files_with_different_prefixes_work_in_one_module(wgpu_device):
    from wgpu.utils.compute import compute_with_buffers

    payloads = {prefix: model() for prefix, (model, _) in PREFIXED.items()}
    source = "".join(
        backends.generate(payloads[prefix], "wgsl", lobe=lobe, prefix=prefix)
        for prefix, (_, lobe) in PREFIXED.items()
    )
    source += WGSL_PREFIXES_KERNEL
    wgpu_device.create_shader_module(code=source)  # naga validation; raises on error
    wi, wo = pairs(9, 500)
    n = len(wi)
    rows = np.concatenate([wi, wo], 1).astype(np.float32).reshape(-1)
    res = compute_with_buffers({0: rows}, {1: (n * 12, "f")}, source, n=(n + 63) // 64)
    out = np.frombuffer(res[1], np.float32).reshape(n, 12)
    for k, (prefix, (_, lobe)) in enumerate(PREFIXED.items()):
        tol = EVERY_OP_GPU_TOL if prefix == "gold" else GPU_TOL
        assert (
            relative_difference(out[:, 3 * k : 3 * k + 3], onnx_ref(payloads[prefix], wi, wo))
            <= tol
        )
        np.testing.assert_allclose(
            out[:, 9 + k], mixture_pdf(wi, wo, lobe), rtol=GPU_TOL, atol=1e-5
        )


def test_glsl_files_with_different_prefixes_validate_in_one_shader(tmp_path):
    """GLSL ES 3.00 and Vulkan GLSL 4.50: the three files pasted into one shader that calls
    each one's functions."""
    source = "".join(
        backends.generate(model(), "glsl", lobe=lobe, prefix=prefix)
        for prefix, (model, lobe) in PREFIXED.items()
    )
    for prefix in ("gold", "brushed_v2"):
        source += (
            f"vec3 {prefix}_calls(vec3 wi, vec3 wo) {{ vec3 w; "
            f"return {prefix}_eval(wi, wo) + vec3({prefix}_pdf(wi, wo) "
            f"+ {prefix}_sample(wi, 0.5, vec2(0.3), w)) + w; }}\n"
        )
    glsl_validate(source, tmp_path)  # its main() calls the default file's functions


def test_the_default_prefix_is_the_unprefixed_file():
    payload = product_model()
    for target in backends.TARGETS:
        plain = backends.generate(payload, target, lobe=ANISO_RETRO)
        assert plain == backends.generate(payload, target, lobe=ANISO_RETRO, prefix="neural_brdf")
        other = backends.generate(payload, target, lobe=ANISO_RETRO, prefix="gold")
        assert "neural_brdf_" not in other.replace("neural_brdf.backends", "")
        assert "NEURAL_BRDF" not in other and "NeuralBrdf" not in other
    assert "#ifndef NEURAL_BRDF_H" in backends.generate(payload, "c", lobe=ANISO_RETRO)
    assert "#ifndef GOLD_H" in backends.generate(payload, "c", lobe=ANISO_RETRO, prefix="gold")


@pytest.mark.parametrize(
    "prefix",
    ["", "Gold", "gold__v2", "gold_", "_gold", "2gold", "gold_2", "gl_x", "gold-x", "gold x"],
)
def test_a_bad_prefix_is_one_line(prefix):
    """A prefix that is not an identifier in every language, or whose upper case or
    CamelCase (the macros, WGSL's struct) another prefix could share."""
    for target in backends.TARGETS:
        with pytest.raises(InputError, match="prefix: expected") as e:
            backends.generate(product_model(), target, lobe=ANISO_RETRO, prefix=prefix)
        assert "\n" not in str(e.value)


def test_a_prefix_is_at_most_max_prefix_characters(tmp_path):
    """Every generated name begins with the prefix: a 1,100-character one gave GLSL that
    glslang refuses ('name too long'), a 100,000-character one a 16 MB header, both with
    exit 0.  The longest allowed validates."""
    from neural_brdf.backends.cstyle import MAX_PREFIX

    longest = "a" * MAX_PREFIX
    with pytest.raises(InputError, match=f"prefix: at most {MAX_PREFIX} characters"):
        backends.generate(product_model(), "glsl", lobe=ANISO_RETRO, prefix=longest + "b")
    code = backends.generate(product_model(), "glsl", lobe=ANISO_RETRO, prefix=longest)
    assert f"{longest}_" in code
    tool = shutil.which("glslangValidator")
    assert tool, "glslangValidator (Debian glslang-tools) is needed"
    es = tmp_path / "es.frag"
    main = ES_MAIN.replace("neural_brdf_", f"{longest}_")
    es.write_text("#version 300 es\nprecision highp float;\nprecision highp int;\n" + code + main)
    r = subprocess.run([tool, str(es)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-2000:]


@pytest.mark.parametrize("group", [-1, 1.5, True, np.bool_(False), "2", 2**31, [1], None], ids=repr)
def test_a_bad_wgsl_group_is_one_line(group):
    """WGSL's @group is a non-negative i32: a negative, fractional, boolean, string or
    too large group is refused in one line naming ``group`` (before: @group(-1) was
    written, 1.5 and True became 1, '2' was taken).  None is generate()'s default."""
    from neural_brdf.backends.wgsl import WGSLRenderer

    if group is not None:
        with pytest.raises(InputError, match=r"^group: expected a WGSL bind group") as e:
            backends.generate(product_model(), "wgsl", lobe=ANISO_RETRO, group=group)
        assert "\n" not in str(e.value)
    with pytest.raises(InputError, match=r"^group: expected a WGSL bind group"):
        WGSLRenderer(group=group)


def test_a_wgsl_group_is_an_int_from_0():
    from neural_brdf.backends.wgsl import MAX_GROUP, WGSLRenderer

    for group in (0, 3, np.int64(2), MAX_GROUP):
        assert WGSLRenderer(group=group).group == int(group)
        assert type(WGSLRenderer(group=group).group) is int
    text = backends.generate(product_model(), "wgsl", lobe=ANISO_RETRO, group=0)
    assert "@group" not in text  # a two-input file binds nothing


# ------------------------------------------------------------------ errors name the file
def test_errors_name_the_file(tmp_path, capsys):
    """A foreign graph, an empty file and one with an op the lowering does not know: one
    line that names the file, from the API (a path) and from ``neural-brdf codegen``;
    bytes are named ``codegen``.  A file of the contract without a stored lobe (an older
    export) is generated with a lobe fitted to its graph, as render and the Mitsuba
    plugin do (it was refused: "re-export it", which another tool's file cannot be)."""
    from cli_helpers import assert_one_line_error, cli

    f32 = TensorProto.FLOAT
    x, y = (helper.make_tensor_value_info(k, f32, ["N", 4]) for k in ("x", "y"))
    foreign = helper.make_model(
        helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y]),
        opset_imports=[helper.make_opsetid("", 17)],
    )
    files = {
        "foreign.onnx": foreign.SerializeToString(),
        "empty.onnx": b"",
        "einsum.onnx": einsum_model(),
    }
    for name, payload in files.items():
        path = tmp_path / name
        path.write_bytes(payload)
        with pytest.raises(InputError) as e:
            backends.generate(path, "c")
        assert str(e.value).startswith(f"{path}: "), str(e.value)
        code, _, err = cli(
            capsys, "codegen", str(path), "--target", "glsl", "-o", str(tmp_path / "x")
        )
        assert_one_line_error(code, err, f"error: {path}: ")
        assert not (tmp_path / "x").exists()
    from neural_brdf.physics import lobe_fit

    fitted = lobe_fit.fit_onnx(product_model())
    assert backends.generate(product_model(), "wgsl") == backends.generate(
        product_model(), "wgsl", lobe=fitted
    )
    no_lobe = tmp_path / "no_lobe.onnx"
    no_lobe.write_bytes(product_model())
    code, _, err = cli(
        capsys, "codegen", str(no_lobe), "--target", "c", "-o", str(tmp_path / "c.h")
    )
    assert code == 0 and (tmp_path / "c.h").is_file(), err
    with pytest.raises(
        InputError, match=r"^model\.onnx: expected inputs wi, wo .*got \{'x': 4\} -> \{'y': 4\}"
    ):
        backends.generate(foreign.SerializeToString(), "c", source="model.onnx")
    with pytest.raises(InputError, match=r"^m\.onnx: "):
        backends.textures(foreign.SerializeToString(), source="m.onnx")


def test_a_constant_folded_to_inf_warns_nothing(capsys):
    """A constant that folds to inf (1 / 0 in a graph of another tool) printed numpy's
    RuntimeWarning with lowering.py's source line, once per target; the code writes the
    IEEE value, and the folding says nothing."""
    import warnings

    proto = onnx.load_from_string(product_model())
    one = onnx.numpy_helper.from_array(np.array([1.0], np.float32), "one")
    zero = onnx.numpy_helper.from_array(np.array([0.0], np.float32), "zero")
    proto.graph.initializer.extend([one, zero])
    proto.graph.node[1].input[1] = "inf"  # f = wi * wo * (1 / 0)
    proto.graph.node.insert(0, helper.make_node("Div", ["one", "zero"], ["inf"]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning fails the test
        code = backends.generate(proto.SerializeToString(), "c", lobe=ANISO_RETRO)
    assert "INFINITY" in code


def test_a_file_without_the_projects_metadata_is_flagged_in_the_code():
    """A graph of another tool (here f = wi * wo, no format_version) was labelled with
    the contract of neural-brdf's files (directions normalised, 0 below the horizon),
    which its eval need not keep; a file with the metadata is not flagged."""
    bare = product_model()
    proto = onnx.load_from_string(bare)
    helper.set_model_props(proto, {"format_version": "1"})
    for target in backends.TARGETS:
        flagged = backends.generate(bare, target, lobe=ANISO_RETRO)
        assert "CAUTION: the file has no neural-brdf metadata" in flagged
        plain = backends.generate(proto.SerializeToString(), target, lobe=ANISO_RETRO)
        assert "CAUTION" not in plain and "0 below the horizon" in plain


def test_an_unnamed_node_is_named_by_its_place_and_output():
    """Another tool's unnamed node was named node '' in the error of an unsupported op."""
    proto = onnx.load_from_string(product_model())
    proto.graph.node.insert(0, helper.make_node("Det", ["wi"], ["d"]))  # unsupported, unnamed
    with pytest.raises(InputError, match=r"node #0 \(unnamed, output 'd'\): ONNX op 'Det'"):
        backends.generate(proto.SerializeToString(), "c", lobe=ANISO_RETRO)
