"""RGL ``.bsdf`` files (neural_brdf/rgl.py): the TensorFile container, the baker, the
reader (Mitsuba's ``measured`` evaluation in numpy), ``bake`` / ``target.data`` /
``validate --reference`` through the CLI, and Mitsuba's own ``measured`` plugin on baked
files (eval against the analytic model, sample weight == eval / pdf, chi^2 of its pdf).

Tolerances.  A baked file is exact at its value nodes (float32); in between, the value
rho = f cos 4 sigma / D is interpolated bilinearly on the 64 x 64 sample square and
linearly across the 32 theta_i slices.  Measured on 50000 uniform pairs (rel. RMSE of
f cos, default resolutions): Lambertian 1.3%, GGX alpha 0.3 gold 2.8%, GGX alpha 0.1
0.3%; almost all of it at grazing incidence (theta_i > 87 deg), where part of each
slice's sample square reflects below the horizon (rho = 0) and the boundary falls
between nodes.  The tests allow 4%.  Mitsuba's float32 evaluation and the numpy reader
agree to ~1e-6 relative; the tests allow 1e-4.
"""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

import analytic
from neural_brdf import config, pipeline, validate
from neural_brdf.measured import merl, rgl
from neural_brdf.tooling import cli
from neural_brdf.train import data, loop

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
LAMBERT = CONFIGS / "lambert.yaml"  # albedo (0.8, 0.6, 0.4)

EVAL_TOL = 0.04  # rel. RMSE of f cos between nodes (see the module docstring)
MITSUBA_VS_READER = 1e-4  # float32 Mitsuba vs float64 numpy, relative to the peak
NODE_TOL = 1e-5  # at the value nodes a bake is exact up to float32

CASES = {
    "lambertian": ("lambertian", {"albedo": [0.8, 0.5, 0.2]}),
    "ggx-gold-0.3": ("microfacet", {"alpha": 0.3, "fresnel": "conductor", "material": "Au"}),
    "ggx-0.1": ("microfacet", {"alpha": 0.1}),
}


def hemisphere(n, seed):
    u = np.random.default_rng(seed).random((n, 2))
    th, ph = np.arccos(1.0 - u[:, 0]), 2 * math.pi * u[:, 1]
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def rel_rmse(a, b):
    return float(np.sqrt(np.sum((a - b) ** 2) / np.sum(b**2)))


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """name -> (analytic model, path of its .bsdf, the RGLBRDF read back)."""
    folder = tmp_path_factory.mktemp("rgl")
    out = {}
    for name, (model, params) in CASES.items():
        brdf = analytic.create(model, **params)
        path = folder / f"{name}.bsdf"
        rgl.bake(brdf.eval, path, description=name)
        out[name] = (brdf, path, rgl.read_rgl(path))
    return out


def cli_run(capsys, *args):
    code = cli.main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def assert_one_line_error(code, err, *needles):
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in err, err


# ------------------------------------------------------------------ tensor file
def test_tensor_file_round_trip_and_layout(tmp_path):
    rng = np.random.default_rng(0)
    fields = {
        "a": rng.random((3, 4, 5)).astype(np.float32),
        "text": "héllo",
        "b": rng.integers(0, 255, 7).astype(np.uint8),
        "c": rng.random(3),
        "d": rng.integers(-5, 5, (2, 2)).astype(np.int32),
        "e": np.arange(4, dtype=np.uint16),
    }
    path = tmp_path / "t.bsdf"
    rgl.write_tensor_file(path, fields)
    raw = path.read_bytes()
    assert raw[:12] == b"tensor_file\0" and tuple(raw[12:14]) == (1, 0)
    assert struct.unpack("<I", raw[14:18])[0] == len(fields)
    # first field: name length, name, ndim, dtype code 10 (float32), offset, shape
    assert struct.unpack("<H", raw[18:20])[0] == 1 and raw[20:21] == b"a"
    ndim, code, offset = struct.unpack("<HBQ", raw[21:32])
    assert (ndim, code) == (3, 10) and offset % rgl.ALIGN == 0
    assert struct.unpack("<3Q", raw[32:56]) == (3, 4, 5)
    assert raw[offset : offset + 60 * 4] == fields["a"].astype("<f4").tobytes()
    back = rgl.read_tensor_file(path)
    assert list(back) == list(fields)
    assert bytes(back["text"]).decode("utf-8") == "héllo" and back["text"].dtype == np.uint8
    for k, v in fields.items():
        if k != "text":
            assert back[k].dtype == v.dtype and back[k].shape == v.shape
            np.testing.assert_array_equal(back[k], v)


def garbage_cases(good: bytes):
    dtype_at = 20 + struct.unpack("<H", good[18:20])[0] + 2  # first field's dtype byte
    return {
        "empty": b"",
        "garbage": b"this is not a tensor file at all, just text",
        "bad-version": good[:12] + bytes([2, 0]) + good[14:],
        "cut-header": good[:40],
        "cut-data": good[: len(good) // 2],
        "bad-dtype": good[:dtype_at] + bytes([99]) + good[dtype_at + 1 :],
    }


def test_truncated_and_garbage_files_raise_one_line_errors(baked, tmp_path):
    good = baked["lambertian"][1].read_bytes()
    for case, content in garbage_cases(good).items():
        path = tmp_path / f"{case}.bsdf"
        path.write_bytes(content)
        with pytest.raises(rgl.RGLFormatError) as e:
            rgl.read_rgl(path)
        msg = str(e.value)
        assert str(path) in msg and "\n" not in msg, (case, msg)
    with pytest.raises(rgl.RGLFormatError, match="no such file"):
        rgl.read_rgl(tmp_path / "none.bsdf")


def test_bad_contents_are_named(baked, tmp_path):
    fields = rgl.read_tensor_file(baked["lambertian"][1])

    def refused(change, needle):
        f = dict(fields)
        change(f)
        path = tmp_path / "x.bsdf"
        rgl.write_tensor_file(path, f)
        with pytest.raises(rgl.RGLFormatError) as e:
            rgl.read_rgl(path)
        assert needle in str(e.value) and str(path) in str(e.value), str(e.value)

    refused(lambda f: f.pop("vndf"), "vndf")
    refused(lambda f: f.update(ndf=f["ndf"].astype(np.float64)), "ndf")
    refused(lambda f: f.update(wavelengths=np.arange(3, dtype=np.float32)), "spectral")
    refused(lambda f: f.update(phi_i=np.zeros(4, np.float32)), "phi_i")
    refused(lambda f: f.update(rgb=f["rgb"][:, :, :2]), "rgb")
    nan = fields["luminance"].copy()
    nan[0, 0, 0, 0] = np.nan
    refused(lambda f: f.update(luminance=nan), "non-finite")


MAX_VALUE = 1e10  # the documented bound on values (docs/rgl.md)


def test_values_that_cannot_be_a_brdf_are_named(baked, tmp_path, capsys):
    fields = rgl.read_tensor_file(baked["lambertian"][1])
    assert fields["jacobian"][0] == 1

    def read(change):
        f = {k: v.copy() for k, v in fields.items()}
        change(f)
        path = tmp_path / "odd.bsdf"
        rgl.write_tensor_file(path, f)
        return path, lambda: rgl.read_rgl(path)

    def refused(change, *needles):
        path, go = read(change)
        with pytest.raises(rgl.RGLFormatError) as e:
            go()
        msg = str(e.value)
        assert str(path) in msg and "\n" not in msg, msg
        for n in needles:
            assert n in msg, msg

    def put(name, value, at=(0,)):
        def change(f):
            f[name][at] = value

        return change

    refused(put("rgb", -1.0), "'rgb'", "negative")
    path = tmp_path / "odd.bsdf"  # as the CLI reports it: one line, exit code 2
    args = ("validate", tmp_path / "m.onnx", "--reference", path)
    assert_one_line_error(*cli_run(capsys, *args)[::2], str(path), "'rgb'", "--reference")
    refused(lambda f: f["rgb"].fill(-1.0), "'rgb'", "negative")
    refused(put("rgb", 0.0, at=...), "'rgb'", "reflects nothing")
    refused(put("rgb", 3e10, at=(0, 0, 1, 2, 3)), "'rgb'", "3e+10", "not a BRDF")
    refused(put("sigma", 0.0, at=...), "'sigma'", "<= 0")
    refused(put("sigma", 0.0, at=(-1, 1)), "'sigma'", "<= 0")
    refused(put("sigma", 1e-30, at=(-1, 1)), "'ndf'", "'sigma'", "not a BRDF")
    refused(put("ndf", 0.0, at=...), "'ndf'", "reflects nothing")
    refused(put("ndf", -1.0, at=(-1, 1)), "'ndf'", "negative")
    # the sampler's densities, named by field (a negated luminance said "data: a slice
    # integrates to 0" and named no field; a negative vndf value was read)
    refused(put("vndf", -1.0, at=(0, 0, 1, 1)), "'vndf'", "negative")
    refused(lambda f: f.update(luminance=-f["luminance"]), "'luminance'", "negative")
    refused(put("luminance", 0.0, at=...), "'luminance'", "integrates to 0")
    # incident elevations outside [0, pi/2] (read at other angles before: a file shifted
    # by -1 rad or in thrice the angle trained to 66 % and 25 % off) and a jacobian flag
    # of 7 (read as 1)
    refused(lambda f: f.update(theta_i=f["theta_i"] - 1.0), "'theta_i'", "outside [0, pi/2]")
    refused(lambda f: f.update(theta_i=f["theta_i"] * 3.0), "'theta_i'", "outside [0, pi/2]")
    refused(put("jacobian", 7), "'jacobian'", "7")
    top = {k: v.copy() for k, v in fields.items()}
    top["theta_i"][-1] = np.float32(np.pi / 2)  # float32's pi/2, above the float64 one
    rgl.write_tensor_file(tmp_path / "top.bsdf", top)
    assert rgl.read_rgl(tmp_path / "top.bsdf").theta_i[-1] > np.pi / 2
    # without the Jacobian, f cos = rgb: ndf and sigma divide nothing
    no_jac = {k: v.copy() for k, v in fields.items()}
    no_jac["jacobian"][:] = 0
    no_jac["sigma"][-1, 1] = 0.0
    rgl.write_tensor_file(tmp_path / "nojac.bsdf", no_jac)
    assert not rgl.read_rgl(tmp_path / "nojac.bsdf").jacobian
    # a value below the bound reads
    path, go = read(put("rgb", 1e3, at=(0, 0, 1, 2, 3)))
    assert go().fields["rgb"].max() == np.float32(1e3)


def test_a_file_beyond_the_memory_budget_is_refused_before_reading(baked, tmp_path, monkeypatch):
    good = baked["lambertian"][1].read_bytes()
    monkeypatch.setenv("NEURAL_BRDF_MEMORY_LIMIT", str(len(good) + 4096))
    path = tmp_path / "huge.bsdf"
    path.write_bytes(good)
    rgl.read_rgl(path)  # within the budget
    os.truncate(path, len(good) + 8192)  # sparse trailing bytes past the budget
    with pytest.raises(rgl.RGLFormatError) as e:
        rgl.read_rgl(path)
    msg = str(e.value)
    assert str(path) in msg and "\n" not in msg and "limit" in msg, msg


def test_a_real_tensor_file_is_read(data_dir):
    """The pBSDF file of the shared data (a polarised variant of the format)."""
    fields = rgl.read_tensor_file(data_dir / "spectralon_lowres.pbsdf")
    assert fields["M"].dtype == np.float32 and fields["M"].shape == (22, 9, 9, 5, 4, 4)
    assert fields["wvls"].dtype == np.uint16 and fields["wvls"].shape == (5,)
    assert np.all(np.isfinite(fields["M"]))
    assert 300 < fields["wvls"].min() and fields["wvls"].max() < 1000  # nanometres
    with pytest.raises(rgl.RGLFormatError, match="not an RGL material"):
        rgl.RGLBRDF(fields, source="spectralon")


# -------------------------------------------------------------------- the warp
def test_marginal_warp_inverts_its_sample_and_integrates_to_one():
    rng = np.random.default_rng(1)
    table = rng.random((3, 5, 7)) + 0.05  # 3 slices of a 5 x 7 table
    warp = rgl.Marginal2D(table, (np.array([0.0, 0.5, 1.2]),))
    u = rng.random((5000, 2))
    p = rng.random(5000) * 1.4 - 0.1
    pts, pdf = warp.sample(u, (p,))
    back, pdf2 = warp.invert(pts, (p,))
    # exact but for the near-constant segments, which sample treats as constant
    # (|v0 - v1| < SEGMENT_CONST (v0 + v1)) and invert does not
    np.testing.assert_allclose(back, u, atol=1e-5)
    np.testing.assert_allclose(pdf, pdf2, rtol=1e-9)
    np.testing.assert_allclose(warp.eval(pts, (p,)), pdf, rtol=1e-9)
    # the density integrates to 1 on the square (midpoint rule on a fine grid)
    g = (np.arange(400) + 0.5) / 400
    x, y = np.meshgrid(g, g)
    grid = np.stack([x.ravel(), y.ravel()], -1)
    for value in (0.0, 0.3, 1.2):
        assert abs(warp.eval(grid, (np.full(len(grid), value),)).mean() - 1.0) < 1e-3
    # sampled points follow the density (a coarse histogram against the integral)
    pts, _ = warp.sample(rng.random((200000, 2)), (np.full(200000, 0.5),))
    hist = np.histogram2d(pts[:, 1], pts[:, 0], bins=4, range=[[0, 1], [0, 1]])[0] / 200000
    dens = warp.eval(grid, (np.full(len(grid), 0.5),)).reshape(400, 400)
    expected = dens.reshape(4, 100, 4, 100).mean(axis=(1, 3)) / 16
    np.testing.assert_allclose(hist, expected, atol=4e-3)


# ------------------------------------------------------------ bake and reader
def test_bake_is_exact_at_the_value_nodes(baked):
    for name, (brdf, _, m) in baked.items():
        wi, wo = m.node_pairs(seed=2)
        ref = brdf.eval(wi, wo) * wo[:, 2:3]
        got = m.eval(wi, wo) * wo[:, 2:3]
        assert rel_rmse(got, ref) < NODE_TOL, name


@pytest.mark.parametrize("name", list(CASES))
def test_reader_matches_the_model_between_nodes(baked, name):
    brdf, _, m = baked[name]
    wi, wo = hemisphere(20000, 3), hemisphere(20000, 4)
    cos = wo[:, 2:3]
    err = rel_rmse(m.eval(wi, wo) * cos, brdf.eval(wi, wo) * cos)
    assert err < EVAL_TOL, err
    # and it is not trivially small: another roughness is far off
    other = analytic.create("microfacet", alpha=0.2)
    assert rel_rmse(other.eval(wi, wo) * cos, brdf.eval(wi, wo) * cos) > 10 * EVAL_TOL


def test_reader_edges_and_ndf(baked):
    _, _, m = baked["ggx-0.1"]
    wi = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.6, 0.0, 0.8], [np.nan, 0, 1]])
    wo = np.array([[0.0, 0.6, -0.8], [0.0, 0.0, 1.0], [-0.6, 0.0, 0.8], [0.0, 0, 1]])
    f = m.eval(wi, wo)
    assert f.shape == (4, 3) and np.all(f[[0, 1, 3]] == 0) and np.all(f[2] > 1.0)
    # the retro-reflection NDF of a GGX model is GGX (normalised: int D cos = 1)
    u = np.linspace(0, 1, rgl.DEFAULTS["ndf"])
    theta = rgl.u_to_theta(u)
    d = m.fields["ndf"][0].astype(np.float64)
    a2 = 0.01
    ggx = a2 / (math.pi * (np.cos(theta) ** 2 * (a2 - 1) + 1) ** 2)
    keep = theta < math.radians(60)
    np.testing.assert_allclose(d[keep], ggx[keep], rtol=0.02)


def test_sampler_weight_is_near_constant_for_gray_ggx(baked):
    """f cos / pdf of the file's own sampler (luminance then VNDF) is the albedo, nearly
    constant: the near-perfect importance sampling of the format."""
    _, _, m = baked["ggx-0.1"]
    n = 20000
    wi = np.tile([[math.sin(0.5), 0.0, math.cos(0.5)]], (n, 1))
    wo, pdf = m.sample(wi, np.random.default_rng(5).random((n, 2)))
    ok = wo[:, 2] > 0
    w = m.eval(wi[ok], wo[ok])[:, 0] * wo[ok, 2] / pdf[ok]
    assert ok.mean() > 0.99 and np.std(w) < 0.01 * np.mean(w)
    assert 0.9 < np.mean(w) <= 1.0 + 1e-3


# ------------------------------------------------------------------ CLI
def test_bake_dispatches_on_the_extension(capsys, tmp_path):
    code, out, err = cli_run(capsys, "bake", LAMBERT, "-o", tmp_path / "l.bsdf")
    assert code == 0, err
    assert "RGL" in out
    m = rgl.read_rgl(tmp_path / "l.bsdf")
    wi, wo = m.node_pairs()
    cos = wo[:, 2:3]
    assert rel_rmse(m.eval(wi, wo) * cos, np.array([0.8, 0.6, 0.4]) / math.pi * cos) < NODE_TOL
    code, out, err = cli_run(capsys, "bake", LAMBERT, "-o", tmp_path / "l.binary")
    assert code == 0 and "MERL" in out, err
    merl.read_merl(tmp_path / "l.binary")
    for bad in ("l.exr", "l"):
        assert_one_line_error(
            *cli_run(capsys, "bake", LAMBERT, "-o", tmp_path / bad)[::2],
            ".binary",
            ".bsdf",
            "extension",
        )
        assert not (tmp_path / bad).exists()
    assert "'.exr'" in cli_run(capsys, "bake", LAMBERT, "-o", tmp_path / "l.exr")[2]


def test_bad_files_exit_2_through_the_cli(baked, tmp_path, capsys):
    good = baked["lambertian"][1].read_bytes()
    for case, content in garbage_cases(good).items():
        path = tmp_path / f"{case}.bsdf"
        path.write_bytes(content)
        # --reference is read before the model: the model need not exist
        assert_one_line_error(
            *cli_run(capsys, "validate", tmp_path / "m.onnx", "--reference", path)[::2],
            str(path),
            "--reference",
        )
        argv = [
            "train",
            CONFIGS / "merl.yaml",
            "--out",
            tmp_path / "run",
            "--set",
            f"target.data={path}",
        ]
        assert_one_line_error(*cli_run(capsys, *argv)[::2], str(path), "target.data")


# ---------------------------------------------------------- training round trip
SHORT = [
    "train.steps=600",
    "train.warmup=20",
    "train.progress=false",
    "train.threads=1",
    "train.eval_every=0",
    "model.hidden=[32,32]",
    "data.batch_size=1024",
    "data.pool_size=32768",
    "normalization.table_size=33",
    "normalization.samples=4096",
    "validation.furnace_dirs=31",
    "validation.furnace_samples=4096",
    "validation.pairs=4000",
    "validation.accuracy_samples=8192",
    "export.parity_pairs=512",
]
ROUND_TRIP_TOL = 0.10  # rel. RMSE of f cos after a 600-step fit (measured 3.4%)


def test_train_on_a_bsdf_file_and_compare_with_the_analytic_model(baked, tmp_path, capsys):
    brdf, path, _ = baked["ggx-gold-0.3"]
    cfg = config.load(CONFIGS / "merl.yaml", [f"target.data={path}"] + SHORT)
    target = data.build_target(cfg.target)
    assert isinstance(target, data.MeasuredTarget) and isinstance(target.brdf, rgl.RGLBRDF)
    assert target.describe().startswith(f"RGL {path} (")
    report = pipeline.run(cfg, tmp_path / "run")
    assert report["passed"]
    model = tmp_path / "run" / "model.onnx"
    # against the analytic model the file was baked from
    acc = validate.accuracy(__import__("neural_brdf").load(model).eval, brdf, n=20000, seed=1)
    assert acc["rel_rmse"] < ROUND_TRIP_TOL, acc["rel_rmse"]
    # validate --reference material.bsdf scores against the file's nodes
    code, out, err = cli_run(capsys, "validate", model, "--reference", path)
    assert code == 0, err
    assert "rel_rmse" in out and "at the file's nodes" in out  # said in the table
    code, out, err = cli_run(capsys, "validate", model, "--reference", "gold")
    assert "rel_rmse" in out and "nodes" not in out, err  # an analytic reference's pairs


def test_training_pairs_of_a_bsdf_file_reach_the_mirror_direction(baked):
    """The file's own sampler seldom lands within a degree of the mirror direction, so
    data.peak's share of peak pairs is added (as for an analytic target): about
    data.peak / 10 more of the pairs on the first tenth of u_h; a MERL grid's draw, dense
    there already, gets none."""
    from neural_brdf.train import encoding as enc

    def share_near_peak(target, peak: float) -> float:
        cfg = config.from_dict({"target": {"model": "lambertian"}, "data": {"peak": peak}})
        src = data.pair_source(target, cfg.data, torch.Generator().manual_seed(0))
        wi, wo, f = src.draw(40000)
        assert wi.shape == wo.shape == f.shape == (40000, 3)
        assert bool(((wi[:, 2] > 0) & (wo[:, 2] > 0)).all())
        return float((enc.features(wi, wo, "isotropic")[:, 0] < 0.1).float().mean())

    target = data.MeasuredTarget(baked["ggx-gold-0.3"][2])
    alone = share_near_peak(target, 0.0)  # the file's sampler alone: 0.57 %
    assert alone < 0.01
    assert 0.01 < share_near_peak(target, 0.2) - alone < 0.03
    # the peak pairs' f is the file's own value
    src = data.pair_source(
        target, config.from_dict({"data": {"peak": 1.0}}).data, torch.Generator().manual_seed(1)
    )
    wi, wo, f = src.draw(500)
    np.testing.assert_allclose(
        f.numpy(), target.eval(wi.double().numpy(), wo.double().numpy()), rtol=1e-5
    )
    # data.peak the only share: every pair a peak pair (the file's draw of none failed)
    only = {"uniform": 0.0, "cosine": 0.0, "importance": 0.0, "peak": 1.0}
    src = data.pair_source(
        target, config.from_dict({"data": only}).data, torch.Generator().manual_seed(2)
    )
    wi, wo, f = src.draw(300)
    assert wi.shape == (300, 3) and bool(torch.isfinite(f).all())
    raw = np.full((3, 90, 90, 180), 0.1)
    merl_target = data.MeasuredTarget(merl.MerlBRDF(raw))
    merl_src = data.pair_source(
        merl_target,
        config.from_dict({"data": {"peak": 0.5}}).data,
        torch.Generator().manual_seed(0),
    )
    assert merl_src.peak == 0.0


def test_a_bsdf_file_trains_to_its_highlight_peak(baked, tmp_path):
    """The gold GGX baked to .bsdf and trained with the gold preset's data shares: the
    peak check against the analytic model it was baked from passes (3 %): 0.83 % in the
    run that chose nothing; 43.6 % at normal incidence without the peak pairs."""
    brdf, path, _ = baked["ggx-gold-0.3"]
    cfg = config.from_dict(
        {
            "target": {"data": str(path)},
            "data": {"batch_size": 1024, "importance": 0.6, "peak": 0.2},
            "train": {"progress": False, "eval_every": 0},
        }
    )
    raw, _ = loop.train(cfg, tmp_path / "run")

    def fn(wi, wo):
        with torch.no_grad():
            return raw(torch.from_numpy(wi).float(), torch.from_numpy(wo).float()).double().numpy()

    check = validate.peak(fn, brdf, anisotropic=False, tol=cfg.validation.peak_tol)
    assert check["passed"], check["value"]


# ------------------------------------------------------------------ Mitsuba
@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


def interaction(mi, wi):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(np.ascontiguousarray(wi.T, dtype=np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    return si


def to_np(x):
    return np.array(x, dtype=np.float64).T


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", list(CASES))
def test_mitsuba_measured_eval_matches_the_model(mi, baked, name):
    brdf, path, m = baked[name]
    bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
    wi, wo = hemisphere(20000, 6), hemisphere(20000, 7)
    value = to_np(
        bsdf.eval(
            mi.BSDFContext(),
            interaction(mi, wi),
            mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32)),
        )
    )
    cos = wo[:, 2:3]
    mine = m.eval(wi, wo) * cos
    assert np.max(np.abs(value - mine)) < MITSUBA_VS_READER * np.max(mine)
    assert rel_rmse(value, brdf.eval(wi, wo) * cos) < EVAL_TOL
    below = wo.copy()
    below[:, 2] *= -1
    assert np.all(
        to_np(
            bsdf.eval(
                mi.BSDFContext(),
                interaction(mi, wi),
                mi.Vector3f(np.ascontiguousarray(below.T, dtype=np.float32)),
            )
        )
        == 0
    )


@pytest.mark.mitsuba
def test_mitsuba_measured_sample_weight_is_eval_over_pdf(mi, baked):
    import drjit as dr

    bsdf = mi.load_dict({"type": "measured", "filename": str(baked["ggx-gold-0.3"][1])})
    rng = np.random.default_rng(8)
    n = 20000
    wi = hemisphere(n, 9)
    si = interaction(mi, wi)
    u = rng.random((n, 3)).astype(np.float32)
    ctx = mi.BSDFContext()
    bs, weight = bsdf.sample(
        ctx, si, mi.Float(u[:, 0]), mi.Point2f(mi.Float(u[:, 1]), mi.Float(u[:, 2]))
    )
    value, pdf = bsdf.eval(ctx, si, bs.wo), bsdf.pdf(ctx, si, bs.wo)
    weight, value, pdf = to_np(weight), to_np(value), np.array(pdf, dtype=np.float64)
    live = (pdf > 0) & (to_np(bs.wo)[:, 2] > 0)
    assert live.mean() > 0.9
    np.testing.assert_allclose(np.array(bs.pdf)[live], pdf[live], rtol=1e-3)  # float32 warps
    np.testing.assert_allclose(weight[live], value[live] / pdf[live, None], rtol=1e-3, atol=1e-6)
    assert np.all(np.isfinite(weight)) and np.all(weight >= 0)
    dr.eval()


@pytest.mark.mitsuba
@pytest.mark.parametrize("theta", (20.0, 70.0))
def test_mitsuba_measured_chi2(mi, baked, theta, tmp_path, monkeypatch):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    t = math.radians(theta)
    props = {"type": "measured", "filename": str(baked["ggx-gold-0.3"][1])}
    sample_fn, pdf_fn = BSDFAdapter(
        "measured",
        props,
        wi=[math.sin(t) * math.cos(0.6), math.sin(t) * math.sin(0.6), math.cos(t)],
    )
    test = ChiSquareTest(
        domain=SphericalDomain(),
        sample_func=sample_fn,
        pdf_func=pdf_fn,
        sample_dim=3,
        sample_count=1_000_000,
        ires=10,
        seed=int(theta),
    )
    ok = test.run(significance_level=0.01, test_count=2, quiet=True)
    if not ok:
        monkeypatch.chdir(tmp_path)
        test._dump_tables()
    assert ok, f"chi2 at {theta} deg (p = {test.p_value}):\n{test.messages}"


# ------------------------------------------------------------------ spectral
def test_rgb_to_spectra_is_mitsubas_sigmoid_model():
    import mitsuba

    m = mitsuba.scalar_spectral
    rgb = np.array(
        [[0.8, 0.5, 0.2], [0.1, 0.9, 0.3], [0.5, 0.5, 0.5], [2.0, 1.0, 0.5], [0.0, 0.0, 0.0]]
    )
    spec = rgl.rgb_to_spectra(rgb)
    assert spec.shape == (5, len(rgl.WAVELENGTHS))
    for k in range(3):  # Mitsuba's own evaluation of its coefficients
        top = rgb[k].max()
        c = m.srgb_model_fetch(m.ScalarColor3f(*map(float, rgb[k] / top)))
        ref = [top * m.srgb_model_eval(c, m.Spectrum(lam))[0] for lam in rgl.WAVELENGTHS]
        # (Mitsuba evaluates x = c0 l^2 + c1 l + c2 in float32, with cancellation)
        np.testing.assert_allclose(spec[k], ref, rtol=1e-3)
    np.testing.assert_allclose(spec[2], 0.5, rtol=1e-3)  # grey is flat
    np.testing.assert_allclose(spec[3], 2.0 * rgl.rgb_to_spectra(rgb[3] / 2.0), rtol=1e-9)
    assert np.all(spec[4] == 0)


@pytest.mark.mitsuba
@pytest.mark.parametrize("variant", ["scalar_spectral", "llvm_ad_spectral"])
def test_spectral_bake_loads_and_evaluates_in_spectral_variants(variant, tmp_path):
    import drjit as dr
    import mitsuba

    lambert = analytic.create("lambertian", albedo=[0.8, 0.5, 0.2])
    path = tmp_path / "lambert_spec.bsdf"
    assert rgl.bake(lambert.eval, path) is None  # spectral by its name
    fields = rgl.read_tensor_file(path)
    assert "rgb" not in fields and fields["spectra"].shape[2] == len(rgl.WAVELENGTHS)
    with pytest.raises(rgl.RGLFormatError, match="spectral"):
        rgl.read_rgl(path)
    previous = mitsuba.variant()
    mitsuba.set_variant(variant)
    try:
        bsdf = mitsuba.load_dict({"type": "measured", "filename": str(path)})
        wi = np.array([0.3, 0.1, 0.9])
        wi /= np.linalg.norm(wi)
        wo = np.array([-0.5, 0.2, 0.7])
        wo /= np.linalg.norm(wo)
        si = dr.zeros(mitsuba.SurfaceInteraction3f)
        si.wi = mitsuba.Vector3f(*map(float, wi))
        si.sh_frame = mitsuba.Frame3f(mitsuba.Vector3f(0.0, 0.0, 1.0))
        lam = [450.0, 520.0, 600.0, 680.0]
        si.wavelengths = mitsuba.Spectrum(*lam)
        wo_mi = mitsuba.Vector3f(*map(float, wo))
        value = np.ravel(np.array(bsdf.eval(mitsuba.BSDFContext(), si, wo_mi)))
    finally:
        mitsuba.set_variant(previous or "llvm_ad_rgb")
    expected = rgl.rgb_to_spectra(np.array([0.8, 0.5, 0.2]), np.array(lam)) / math.pi * wo[2]
    np.testing.assert_allclose(value, expected, rtol=0.02)
    assert not mitsuba.variant().endswith("spectral")
    with pytest.raises(Exception, match="spectral variant"):
        mitsuba.load_dict({"type": "measured", "filename": str(path)})  # not in RGB


def test_pbrt_convention_stores_the_incident_cosine(tmp_path):
    """cosine="incident": the stored product rho D / (4 sigma) is f cos(theta_i) of the
    slice direction (pbrt-v4 divides by that cosine), not f cos(theta_o) (Mitsuba)."""
    lambert = analytic.create("lambertian", albedo=[0.8, 0.5, 0.2])
    m = rgl.bake(
        lambert.eval, tmp_path / "pbrt.bsdf", cosine="incident", theta_i=8, sample=32, vndf=64
    )
    wi, wo = m.node_pairs(seed=1)
    product = m._f_cos(wi, wo)
    expected = lambert.eval(wi, wo) * wi[:, 2:3]
    assert rel_rmse(product, expected) < NODE_TOL
    assert rel_rmse(lambert.eval(wi, wo) * wo[:, 2:3], expected) > 0.1
    with pytest.raises(ValueError, match="cosine"):
        rgl.bake_fields(lambert.eval, cosine="light")


@pytest.mark.mitsuba
def test_mitsubas_own_tensor_reader_reads_our_files(baked, tmp_path):
    """mitsuba.tensor_io (Mitsuba's Python reader) sees the fields we wrote, and our
    reader sees the fields its writer wrote."""
    import mitsuba

    path = baked["ggx-0.1"][1]
    theirs = mitsuba.tensor_io.read(str(path))
    ours = rgl.read_tensor_file(path)
    assert sorted(theirs) == sorted(ours)
    for k in ours:
        np.testing.assert_array_equal(np.asarray(theirs[k]), ours[k])
    other = tmp_path / "theirs.bsdf"
    mitsuba.tensor_io.write(
        str(other),
        a=np.arange(6, dtype=np.float32).reshape(2, 3),
        b=np.array([7], np.uint8),
        text="abc",
    )
    back = rgl.read_tensor_file(other)
    np.testing.assert_array_equal(back["a"], np.arange(6, dtype=np.float32).reshape(2, 3))
    assert back["b"].tolist() == [7] and bytes(back["text"]) == b"abc"


def test_an_empty_incident_axis_is_named(baked, tmp_path, capsys):
    fields = rgl.read_tensor_file(baked["lambertian"][1])
    for name in ("theta_i", "phi_i"):
        f = dict(fields)
        f[name] = np.zeros(0, np.float32)
        f["vndf"] = f["vndf"][:0] if name == "phi_i" else f["vndf"][:, :0]
        f["luminance"] = f["luminance"][:0] if name == "phi_i" else f["luminance"][:, :0]
        f["rgb"] = f["rgb"][:0] if name == "phi_i" else f["rgb"][:, :0]
        path = tmp_path / f"{name}_empty.bsdf"
        rgl.write_tensor_file(path, f)
        with pytest.raises(rgl.RGLFormatError) as e:
            rgl.read_rgl(path)
        assert str(e.value) == f"{path}: field {name!r}: empty (no incident slices)"
        code, _, err = cli_run(capsys, "validate", tmp_path / "m.onnx", "--reference", path)
        assert_one_line_error(code, err, str(path), name)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_or_a_device_is_refused_before_reading(tmp_path, capsys):
    import signal

    def alarm(signum, frame):
        raise TimeoutError("blocked reading a FIFO")

    fifo = tmp_path / "x.bsdf"
    os.mkfifo(fifo)  # never opened for writing: a reader that opens it blocks
    zero = tmp_path / "zero.bsdf"
    zero.symlink_to("/dev/zero")  # st_size 0: the size check alone read it all
    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(20)
    try:
        for path, kind in ((fifo, "a FIFO"), (zero, "a character device")):
            with pytest.raises(rgl.RGLFormatError) as e:
                rgl.read_rgl(path)
            assert str(e.value) == f"{path}: is {kind}, not a file"
            code, _, err = cli_run(capsys, "validate", tmp_path / "m.onnx", "--reference", path)
            assert_one_line_error(code, err, f"{path}: is {kind}, not a file")
            argv = ["train", CONFIGS / "merl.yaml", "--out", tmp_path / "run"]
            code, _, err = cli_run(capsys, *argv, "--set", f"target.data={path}")
            assert_one_line_error(code, err, str(path), "target.data")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_a_tensor_file_of_another_suffix_is_known_by_its_header(data_dir, tmp_path):
    from neural_brdf.measured import formats

    assert formats.find(data_dir / "spectralon_lowres.pbsdf") is formats.RGL
    (tmp_path / "notes.pbsdf").write_bytes(b"not a tensor file")
    assert formats.find(tmp_path / "notes.pbsdf") is None
    assert formats.find(tmp_path / "missing.pbsdf") is None
