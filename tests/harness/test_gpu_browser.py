"""The shader harness: GLSL in headless Chromium's WebGL2, WGSL in its WebGPU.

The hand-written shaders below are a Blinn-Phong BRDF whose formula is repeated in
numpy (float64): the harness must move every pair there and back exactly and run the
shader as written.  Generated code from an exported ONNX graph is checked against
onnxruntime in tests/viewer/test_viewer.py.  Chromium is required (CI installs it); no skip.
"""

from __future__ import annotations

import numpy as np
import pytest

from harness import gpu_browser

KD = (0.8, 0.5, 0.2)
KS, EXPONENT = 0.04, 20.0
GLSL = f"""#version 300 es
vec3 neural_brdf_eval(vec3 wi, vec3 wo) {{
  if (wi.z <= 0.0 || wo.z <= 0.0) return vec3(0.0);
  vec3 h = normalize(wi + wo);
  return vec3{KD} / 3.14159265358979 +
         vec3({KS}) * ({EXPONENT} + 2.0) / 6.28318530717959 * pow(max(h.z, 0.0), {EXPONENT});
}}"""
WGSL = f"""fn neural_brdf_eval(wi: vec3<f32>, wo: vec3<f32>) -> vec3<f32> {{
  if (wi.z <= 0.0 || wo.z <= 0.0) {{ return vec3<f32>(0.0); }}
  let h = normalize(wi + wo);
  return vec3<f32>{KD} / 3.14159265358979 +
         vec3<f32>({KS}) * ({EXPONENT} + 2.0) / 6.28318530717959 * pow(max(h.z, 0.0), {EXPONENT});
}}"""
# Measured on SwiftShader: 1.9e-6 relative (float32 pow/normalize against float64).
REL_TOL = 1e-5


def blinn_phong(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Normalised Blinn-Phong, f = kd/pi + ks (n+2)/(2 pi) cos^n theta_h (Blinn 1977;
    normalisation as in Akenine-Moller et al., Real-Time Rendering, 3rd ed., eq. 7.49)."""
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    f = (
        np.asarray(KD) / np.pi
        + KS * (EXPONENT + 2) / (2 * np.pi) * np.maximum(h[..., 2:3], 0.0) ** EXPONENT
    )
    return np.where((wi[..., 2:3] > 0) & (wo[..., 2:3] > 0), f, 0.0)


def random_pairs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Uniform on the whole sphere: about three quarters have a side below the horizon."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(2, n, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return v[0].astype(np.float32), v[1].astype(np.float32)


@pytest.fixture(scope="module")
def session():
    with gpu_browser.Session() as s:
        yield s


def check(f: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> float:
    ref = blinn_phong(wi.astype(np.float64), wo.astype(np.float64))
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    assert below.sum() > len(wi) // 2 and (~below).sum() > len(wi) // 8
    assert np.all(f[below] == 0.0)  # zero below the horizon, no NaN
    rel = np.abs(f - ref).max() / np.abs(ref).max()
    assert rel <= REL_TOL, rel
    return rel


def test_glsl_in_webgl2_reproduces_numpy(session):
    wi, wo = random_pairs(3000)  # > TEXTURE_WIDTH: several rows and a padded tail
    f = session.eval_glsl(GLSL, wi, wo)
    assert f.shape == (3000, 3) and f.dtype == np.float32
    check(f, wi, wo)
    assert "SwiftShader" in session.renderer or "ANGLE" in session.renderer


def test_wgsl_in_webgpu_reproduces_numpy(session):
    wi, wo = random_pairs(1000, seed=1)
    check(session.eval_wgsl(WGSL, wi, wo), wi, wo)


def test_batch_shape_and_order_survive_the_round_trip(session):
    # a shader that returns its inputs exposes any transposition or row mix-up
    echo = "vec3 neural_brdf_eval(vec3 wi, vec3 wo) { return wi + 10.0 * wo; }"
    wi, wo = random_pairs(2 * 5 * 7 + 0, seed=2)
    f = session.eval_glsl(echo, wi.reshape(2, 5, 7, 3), wo.reshape(2, 5, 7, 3))
    np.testing.assert_allclose(f, (wi + 10.0 * wo).reshape(2, 5, 7, 3), rtol=1e-6, atol=1e-6)


def test_a_wrong_shader_raises_with_the_compiler_message(session):
    wi, wo = random_pairs(4)
    with pytest.raises(gpu_browser.ShaderError, match="shader compile"):
        session.eval_glsl("vec3 neural_brdf_eval(vec3 wi) { return wi; }", wi, wo)
    with pytest.raises(gpu_browser.ShaderError, match="WGSL compile"):
        session.eval_wgsl("fn neural_brdf_eval() {}", wi, wo)
    # and the session still works afterwards
    check(session.eval_glsl(GLSL, *random_pairs(600, seed=3)), *random_pairs(600, seed=3))
