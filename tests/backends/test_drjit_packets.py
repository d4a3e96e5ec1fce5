"""The Dr.Jit back end's packet gathers (neural_brdf/backends/drjit.py, "Gathers"), variant
llvm_ad_rgb.

The lowering gives one ``gather`` per table column; the back end reads the columns of a
tensor of three or more float columns (a textured file's weight field, a lobe's feature
grid) as 4-wide packets from one padded, cache-line-aligned buffer.  Checked here on a
random textured file (RGB weights and a latent, so a 13-column field, and lobes with a
feature grid):

* the plan covers the field and the grid (none with ``PACKET_GATHERS`` off), each buffer
  starts on a 64-byte boundary, and every packed column equals the table it replaces;
* the whole program evaluated with packets equals the one-gather-per-column evaluation
  bit for bit, at uv in [0, 1), wrapped, on texel centres and edges, and at NaN / inf /
  huge uv (clamped indices);
* both equal onnxruntime to float32 precision (the parity every back end keeps);
* a Mitsuba scene holding a textured and a homogeneous file (the plugin inside Dr.Jit's
  symbolic virtual calls) renders the same image with packets and without, to float32
  rounding.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
import torch

from neural_brdf import export, graph
from neural_brdf.fileformat import OUTPUT, SIGNATURES
from neural_brdf.train.model import RawBRDF, TotalBRDF
from neural_brdf.train.textured_model import TexturedBRDF, WeightField, exportable

pytestmark = pytest.mark.mitsuba

UV_INPUTS = SIGNATURES[1]  # ("wi", "wo", "uv")
R = 8  # texels per side of the weight field
K = 4  # lobes
N = 4096  # rows
PARITY_TOL = 2e-5  # relative, against onnxruntime (as the plugin's parity tests)


@pytest.fixture(scope="module")
def dr():
    import drjit
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    return drjit


@pytest.fixture(scope="module")
def payload() -> bytes:
    """K random conditioned lobes with a 4 x 4 grid under a random R x R field of RGB
    weights and one latent: a field of 3K + 1 = 13 columns."""
    torch.manual_seed(7)
    lobes = RawBRDF("isotropic", [16], "relu", grid_size=4, heads=K, latent=1)
    with torch.no_grad():
        for p in lobes.parameters():
            p.normal_(0.0, 0.5)
    field = WeightField(R, K, channels=3, init_std=2.0, latent=1)
    model = TexturedBRDF([lobes.eval()], field).eval()
    return export.to_onnx_bytes(exportable(model), 17, inputs=UV_INPUTS)


def _rows(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    wi, wo = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    wi[:, 2] = np.abs(wi[:, 2])
    wo[:, 2] = np.abs(wo[:, 2])
    q = N // 4
    centres = (rng.integers(0, R, (q, 2)) + 0.5) / R
    edges = rng.integers(0, R + 1, (q, 2)) / R
    uv = np.concatenate(
        [rng.uniform(0.0, 1.0, (q, 2)), rng.uniform(-3.0, 3.0, (q, 2)), centres, edges]
    )
    uv[:8] = [[np.nan, 0.5], [0.5, np.inf], [-np.inf, 0.2], [1e30, -1e30]] * 2
    return wi.astype(np.float32), wo.astype(np.float32), uv.astype(np.float32)


def _run(dr, prog, plan, wi, wo, uv) -> np.ndarray:
    from drjit.llvm.ad import Float

    from neural_brdf.backends.drjit import run

    cols = {
        "wi": [Float(np.ascontiguousarray(wi[:, k])) for k in range(3)],
        "wo": [Float(np.ascontiguousarray(wo[:, k])) for k in range(3)],
        "uv": [Float(np.ascontiguousarray(uv[:, k])) for k in range(2)],
    }
    out = run(prog, cols, plan)[OUTPUT]
    return np.stack([np.asarray(c, dtype=np.float32) for c in out], axis=-1)


def _unpacked(prog):
    """A plan that packs nothing: every gather reads its own column."""
    from neural_brdf.backends.drjit import PacketPlan

    plan = PacketPlan(prog, enabled=False)
    assert not plan.where and not plan.buffers
    return plan


def test_plan_packs_the_field_and_the_grid_aligned(dr, payload):
    from neural_brdf.backends.drjit import CACHE_LINE, PACKET, PacketPlan

    prog = graph.lower(payload)
    plan = PacketPlan(prog)
    widths = sorted(src.data.shape[1] for src in prog.sources)
    assert 3 * K + 1 in widths and 4 in widths, widths
    packed = {tb for src in prog.sources if src.data.shape[1] >= 3 for tb in src.tables}
    assert packed and set(plan.where) == packed
    for b, buf in enumerate(plan.buffers):
        assert buf.ctypes.data % CACHE_LINE == 0
        assert buf.size == plan.rows[b] * plan.packets[b] * PACKET
    for tb, (b, k, lane) in plan.where.items():
        rows = plan.buffers[b].reshape(plan.rows[b], plan.packets[b] * PACKET)
        np.testing.assert_array_equal(rows[:, k * PACKET + lane], prog.tables[tb])


def test_packets_equal_one_gather_per_column_bit_for_bit(dr, payload):
    from neural_brdf.backends.drjit import PacketPlan

    prog = graph.lower(payload)
    wi, wo, uv = _rows(3)
    packets = _run(dr, prog, PacketPlan(prog), wi, wo, uv)
    columns = _run(dr, prog, _unpacked(prog), wi, wo, uv)
    assert np.isfinite(packets).all()
    assert (packets > 0).mean() > 0.5  # the rows are not all zero
    np.testing.assert_array_equal(packets.view(np.uint32), columns.view(np.uint32))


def test_the_switch_turns_packets_off_for_programs_loaded_after_it(dr, payload, monkeypatch):
    from neural_brdf.backends import drjit as backend

    monkeypatch.setattr(backend, "PACKET_GATHERS", False)
    off = backend.OnnxProgram(payload)
    monkeypatch.setattr(backend, "PACKET_GATHERS", True)
    on = backend.OnnxProgram(payload)
    assert not off.plan.where and on.plan.where


def test_packets_match_onnxruntime(dr, payload):
    from neural_brdf.backends.drjit import OnnxProgram

    wi, wo, uv = _rows(4)
    prog = OnnxProgram(payload)
    assert prog.plan.where  # the program's own plan packs
    ours = _run(dr, prog.program, prog.plan, wi, wo, uv).astype(np.float64)
    sess = ort.InferenceSession(payload, providers=["CPUExecutionProvider"])
    ref = sess.run([OUTPUT], dict(zip(UV_INPUTS, (wi, wo, uv))))[0].astype(np.float64)
    scale = np.maximum(np.abs(ref), 1e-3 * np.abs(ref).max())
    assert np.max(np.abs(ours - ref) / scale) < PARITY_TOL


def test_a_scene_of_two_files_renders_the_same_with_and_without_packets(
    dr, payload, tmp_path, monkeypatch
):
    import mitsuba as mi

    import neural_brdf.renderers.mitsuba  # noqa: F401  (registers neural_brdf)
    from neural_brdf.backends import drjit as backend

    textured = tmp_path / "textured.onnx"
    textured.write_bytes(payload)
    torch.manual_seed(11)
    plain_lobe = RawBRDF("isotropic", [16], "relu", grid_size=4).eval()
    plain = tmp_path / "plain.onnx"
    plain.write_bytes(export.to_onnx_bytes(TotalBRDF(plain_lobe).eval(), 17))
    T = mi.ScalarTransform4f

    def scene():
        return mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "path", "max_depth": 3},
                "sensor": {
                    "type": "perspective",
                    "fov": 45,
                    "to_world": T().look_at(origin=[0, 0, 6], target=[0, 0, 0], up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 32, "height": 24},
                },
                "emitter": {"type": "constant"},
                "a": {
                    "type": "sphere",
                    "center": [-1.1, 0, 0],
                    "bsdf": {"type": "neural_brdf", "filename": str(textured)},
                },
                "b": {
                    "type": "sphere",
                    "center": [1.1, 0, 0],
                    "bsdf": {"type": "neural_brdf", "filename": str(plain)},
                },
            }
        )

    monkeypatch.setattr(backend, "PACKET_GATHERS", True)
    packed = np.asarray(mi.render(scene(), spp=8, seed=3))
    monkeypatch.setattr(backend, "PACKET_GATHERS", False)
    columns = np.asarray(mi.render(scene(), spp=8, seed=3))
    assert np.isfinite(packed).all() and packed.mean() > 0.01
    # to float32 rounding, not bit for bit: the evaluations are bit-identical (above), but
    # the two render kernels are compiled apart, and in CI, after the rest of the suite,
    # 7 % of the values differed by up to 6e-7 relative (none did here on a fresh process)
    np.testing.assert_allclose(packed, columns, rtol=1e-5, atol=1e-6)
