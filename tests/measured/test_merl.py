"""MERL .binary measured data: file format, lookups, sampling, baking, real-material fixtures.

Independent references used here (none of them is output of the code under test):
  * the byte layout: built in the tests with numpy byte packing, from the format description
    (three little-endian int32 dims (90, 90, 180), then float64, channel-major R, G, B);
  * bin indices: MERL's truncating index formulas (BRDFRead.cpp), re-typed below in
    ``merl_bin``: i_h = int(sqrt(theta_h / (pi/2)) * 90), i_d = int(theta_d / (pi/2) * 90),
    i_p = int(phi_d / pi * 180) after phi_d += pi for phi_d < 0;
  * baking: analytic models (Lambertian, GGX) are the ground truth of the round trip;
  * NBRDF: a numpy forward pass of the documented formula (tests/data/README.md) fed
    with the input vector built from the angles themselves;
  * ABC: the dj_brdf equations re-typed in scalar Python (with dj_brdf's algebraic form of
    the Fresnel term), and the NBRDF fit of the same measured material.

Tolerances (all measured on this code, then given a margin):
  * lookups at bin centres are exact (bit for bit) once the stored value is read;
  * trilinear midpoints: 1e-12 relative (three products and a sum);
  * GGX (alpha 0.3) baked and read back, random directions with both cos > 0.1:
    relative error median 8.5e-4, p99 5.5e-3, max 2.9e-2 (200k pairs); bounds 2e-3, 1.2e-2,
    6e-2.  Nearest-bin lookup, or a half-bin offset, gives a median of 1.3e-2, so these
    bounds separate correct trilinear interpolation from both;
  * NBRDF materials (reciprocal=True) baked and read back, 100k uniform pairs: NBRDF log
    error 0.8e-5 to 2.8e-5 and relative RMSE of f cos 0.1% to 2.4% (aluminium, from its
    specular peak); bounds 1e-4 and 5e-2.
"""

from __future__ import annotations

import csv
import math
import os

import numpy as np
import pytest
import torch

import analytic
import conftest
from analytic import frame
from neural_brdf.measured import merl
from neural_brdf.measured.merl import MerlBRDF, MerlFormatError

DIMS = (90, 90, 180)
N = 90 * 90 * 180
SCALE = (1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0)
FILE_BYTES = 12 + 3 * N * 8

MATERIALS = conftest.MATERIALS  # the four real-data fixtures (baked once per session)


# --------------------------------------------------------------------------- helpers
def merl_bin(theta_h, theta_d, phi_d):
    """MERL's BRDFRead.cpp index functions, vectorised: truncation, clamped to the grid."""
    phi_d = np.where(phi_d < 0.0, phi_d + math.pi, phi_d)
    ih = np.clip((np.sqrt(np.maximum(theta_h, 0.0) / (math.pi / 2)) * 90).astype(int), 0, 89)
    id_ = np.clip((theta_d / (math.pi / 2) * 90).astype(int), 0, 89)
    ip = np.clip((phi_d / math.pi * 180).astype(int), 0, 179)
    return ih, id_, ip


def random_bins(rng, n):
    return rng.integers(0, 90, n), rng.integers(0, 90, n), rng.integers(0, 180, n)


def stored(raw, ih, id_, ip):
    """f of bins (ih, id_, ip) from raw file values: raw * scale per channel -> (n, 3)."""
    return np.stack([raw[c, ih, id_, ip] * SCALE[c] for c in range(3)], -1)


def centre_angles(ih, id_, ip):
    """Bin centres in index space: index i + 0.5 on each axis."""
    return (
        ((ih + 0.5) / 90) ** 2 * (math.pi / 2),
        (id_ + 0.5) / 90 * (math.pi / 2),
        (ip + 0.5) / 180 * math.pi,
    )


def dirs_from_angles(th, ph, td, pd):
    t = [torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in (th, ph, td, pd)]
    wi, wo = frame.from_rusinkiewicz(*t)
    return wi.numpy(), wo.numpy()


def angles_of(wi, wo):
    th, _, td, pd = frame.rusinkiewicz(torch.from_numpy(wi), torch.from_numpy(wo))
    return th.numpy(), td.numpy(), pd.numpy()


def upper_hemisphere(n, seed):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_raw(seed, *, unmeasured=0.0):
    """Stored (unscaled) values: positive noise; a fraction marked unmeasured (negative)."""
    rng = np.random.default_rng(seed)
    raw = rng.uniform(1.0, 500.0, size=(3,) + DIMS)
    if unmeasured:
        raw[:, rng.random(DIMS) < unmeasured] = -1.0
    return raw


def file_bytes(raw, dims=DIMS, order="<"):
    """The format, packed by hand: int32 dims, then float64 channel-major."""
    return (
        np.asarray(dims, dtype=order + "i4").tobytes()
        + np.ascontiguousarray(raw, dtype=order + "f8").tobytes()
    )


def log_error(f_ref, f, cos):
    """NBRDF's metric: mean |log(1 + f_ref cos) - log(1 + f cos)|, cos = cos_i cos_o."""
    return float(np.mean(np.abs(np.log1p(f_ref * cos) - np.log1p(f * cos))))


def rel_rmse(f_ref, f, cos):
    """Relative RMSE of f * cos_i * cos_o."""
    return float(np.sqrt(np.mean(((f - f_ref) * cos) ** 2) / np.mean((f_ref * cos) ** 2)))


@pytest.fixture(scope="module")
def noise_brdf():
    """Every bin measured, independent random values: any lookup slip shows."""
    return MerlBRDF(random_raw(1))


# -------------------------------------------------------------------------- file I/O
def test_writer_produces_the_documented_layout(tmp_path):
    raw = random_raw(2, unmeasured=0.1)
    path = tmp_path / "m.binary"
    merl.write_merl(path, MerlBRDF(raw))
    data = path.read_bytes()
    assert len(data) == FILE_BYTES
    assert data == file_bytes(raw)


def test_round_trip_is_bit_exact(tmp_path):
    raw = random_raw(3, unmeasured=0.2)
    src = tmp_path / "hand.binary"
    src.write_bytes(file_bytes(raw))
    m = merl.read_merl(src)
    np.testing.assert_array_equal(m.raw, raw)
    np.testing.assert_array_equal(m.valid, np.all(raw >= 0, axis=0))
    out = tmp_path / "again.binary"
    merl.write_merl(out, m)
    assert out.read_bytes() == src.read_bytes()
    np.testing.assert_array_equal(merl.read_merl(out).raw, raw)


def test_channel_order_scale_and_bin_layout(tmp_path):
    # raw[c, ih, id, ip] encodes its own position; the scale makes f = code * SCALE[c]
    c, ih, id_, ip = np.meshgrid(
        np.arange(3), np.arange(90), np.arange(90), np.arange(180), indexing="ij"
    )
    code = (c * 1e7 + ih * 1e5 + id_ * 1e3 + ip).astype(np.float64)
    path = tmp_path / "code.binary"
    path.write_bytes(file_bytes(code))
    m = merl.read_merl(path)
    for ch in range(3):
        np.testing.assert_array_equal(m.values[..., ch], code[ch] * SCALE[ch])
    # nearest lookup at MERL's truncated index picks the same bin
    wi, wo = upper_hemisphere(20000, 5), upper_hemisphere(20000, 6)
    bh, bd, bp = merl_bin(*angles_of(wi, wo))
    got = m.eval(wi, wo, interpolation="nearest")
    np.testing.assert_array_equal(got, stored(code, bh, bd, bp))


def test_values_array_is_scaled_on_write(tmp_path):
    f = np.random.default_rng(7).uniform(0.0, 3.0, size=DIMS + (3,))
    f[0, 0, 0] = -1.0  # unmeasured
    path = tmp_path / "v.binary"
    merl.write_merl(path, f)
    raw = np.frombuffer(path.read_bytes(), "<f8", offset=12).reshape((3,) + DIMS)
    for ch in range(3):
        np.testing.assert_allclose(raw[ch] * SCALE[ch], f[..., ch], rtol=1e-15, atol=1e-300)
    assert not merl.read_merl(path).valid[0, 0, 0]


def test_big_endian_file_is_read(tmp_path):
    raw = random_raw(8)
    path = tmp_path / "be.binary"
    path.write_bytes(file_bytes(raw, order=">"))
    np.testing.assert_array_equal(merl.read_merl(path).raw, raw)


def _good(tmp_path):
    return file_bytes(random_raw(9))


BAD_FILES = {
    "empty": (lambda g: b"", "truncated header"),
    "short header": (lambda g: g[:8], "truncated header"),
    "wrong dims": (lambda g: np.asarray((90, 90, 360), "<i4").tobytes() + g[12:], "dims"),
    "garbage dims": (lambda g: b"\x00\x01\x02\x03" * 3 + g[12:], "dims"),
    "truncated": (lambda g: g[:-8], "truncated"),
    "half the data": (lambda g: g[: FILE_BYTES // 2], "truncated"),
    "trailing bytes": (lambda g: g + b"\x00" * 8, "trailing"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_files_raise_one_line_error_naming_the_file(tmp_path, case):
    make, words = BAD_FILES[case]
    path = tmp_path / f"bad {case}.binary"
    path.write_bytes(make(_good(tmp_path)))
    with pytest.raises(MerlFormatError) as err:
        merl.read_merl(path)
    msg = str(err.value)
    assert str(path) in msg and "\n" not in msg and words in msg
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_are_a_format_error(tmp_path, bad):
    raw = random_raw(10)
    raw[1, 40, 2, 17] = bad
    path = tmp_path / "nan.binary"
    path.write_bytes(file_bytes(raw))
    with pytest.raises(MerlFormatError, match="non-finite") as err:
        merl.read_merl(path)
    msg = str(err.value)
    assert str(path) in msg and "channel G" in msg and "theta_h 40" in msg


# Finite values that cannot be a BRDF (the documented bound, docs/merl.md)
MAX_F = 1e10  # 1/sr


def _refused_values(tmp_path, raw, *words):
    path = tmp_path / "odd values.binary"
    path.write_bytes(file_bytes(raw))
    with pytest.raises(MerlFormatError) as err:
        merl.read_merl(path)
    msg = str(err.value)
    assert str(path) in msg and "\n" not in msg, msg
    for w in words:
        assert w in msg, msg


def test_a_value_too_large_for_a_brdf_is_refused_naming_it(tmp_path):
    raw = random_raw(13)
    raw[2, 7, 55, 156] = 1e300  # squares to inf in float64: rel_rmse nan before the fix
    _refused_values(tmp_path, raw, "1e+10", f"{1e300 * SCALE[2]:.3g}", "channel B", "theta_h 7")
    raw[2, 7, 55, 156] = 2 * MAX_F / SCALE[2]
    _refused_values(tmp_path, raw, f"{2 * MAX_F:.3g}", "channel B", "phi_d 156")


def test_a_table_with_no_positive_value_is_refused(tmp_path):
    _refused_values(tmp_path, np.zeros((3,) + DIMS), "reflects nothing")
    raw = np.zeros((3,) + DIMS)
    raw[:, :, :, :90] = -1.0  # unmeasured bins do not count
    _refused_values(tmp_path, raw, "reflects nothing")


def test_negative_and_large_values_stay_accepted_where_they_are_valid(tmp_path):
    raw = random_raw(14, unmeasured=0.3)
    raw[0, 3, 4, 5], raw[1, 3, 4, 5] = 1e300, -1.0  # an unmeasured bin: its values unused
    raw[:, 6, 7, 8] = 1.0
    raw[0, 6, 7, 8] = 0.5 * MAX_F / SCALE[0]  # below the bound
    path = tmp_path / "ok.binary"
    path.write_bytes(file_bytes(raw))
    m = merl.read_merl(path)
    assert not m.valid[3, 4, 5] and m.valid[6, 7, 8]
    np.testing.assert_array_equal(m.raw, raw)


def test_missing_file_and_directory(tmp_path):
    for path, words in ((tmp_path / "nope.binary", "no such file"), (tmp_path, "directory")):
        with pytest.raises(MerlFormatError, match=words) as err:
            merl.read_merl(path)
        assert str(path) in str(err.value)


def test_write_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "keep.binary"
    old = file_bytes(random_raw(11))
    path.write_bytes(old)

    def fail(src, dst):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="simulated"):
        merl.write_merl(path, MerlBRDF(random_raw(12)))
    monkeypatch.undo()
    assert path.read_bytes() == old  # the old file is untouched
    assert sorted(os.listdir(tmp_path)) == ["keep.binary"]  # and no temporary is left
    merl.write_merl(path, MerlBRDF(random_raw(12)))
    assert sorted(os.listdir(tmp_path)) == ["keep.binary"]
    np.testing.assert_array_equal(merl.read_merl(path).raw, random_raw(12))


def test_invalid_arrays_are_refused(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        merl.write_merl(tmp_path / "x.binary", np.zeros((90, 90, 90, 3)))
    f = np.zeros(DIMS + (3,))
    f[3, 4, 5, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        merl.write_merl(tmp_path / "x.binary", f)
    assert not (tmp_path / "x.binary").exists()


# --------------------------------------------------------------------------- lookups
def test_bin_centres_lie_at_the_middle_of_their_bins():
    th, td, pd = merl.bin_centres()
    i = np.arange(90)
    np.testing.assert_allclose(np.sqrt(th / (math.pi / 2)) * 90, i + 0.5, rtol=0, atol=1e-12)
    np.testing.assert_allclose(td / (math.pi / 2) * 90, i + 0.5, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pd / math.pi * 180, np.arange(180) + 0.5, rtol=0, atol=1e-12)
    m = MerlBRDF(random_raw(13))
    np.testing.assert_array_equal(m.theta_h, th)
    assert m.phi_d.shape == (180,) and m.valid.shape == DIMS


@pytest.mark.parametrize("interpolation", ["trilinear", "nearest"])
def test_lookup_at_bin_centres_returns_the_stored_value(noise_brdf, interpolation):
    rng = np.random.default_rng(14)
    ih, id_, ip = random_bins(rng, 20000)
    # the corners of the grid too: theta_h bin 0 and 89, theta_d 0 and 89, phi_d 0 and 179
    ih[:8], id_[:8], ip[:8] = [0, 89, 0, 89, 0, 89, 0, 89], [0, 0, 89, 89] * 2, [0] * 4 + [179] * 4
    th, td, pd = centre_angles(ih, id_, ip)
    wi, wo = dirs_from_angles(th, rng.uniform(0, 2 * math.pi, len(ih)), td, pd)
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    assert up.sum() > 10000
    got = noise_brdf.eval(wi[up], wo[up], interpolation=interpolation)
    np.testing.assert_array_equal(got, stored(noise_brdf.raw, ih[up], id_[up], ip[up]))
    # by angles too, with phi_d given past the fold (phi_d - pi)
    got = noise_brdf.lookup(th, td, pd - math.pi, interpolation=interpolation)
    np.testing.assert_array_equal(got, stored(noise_brdf.raw, ih, id_, ip))


def test_trilinear_interpolates_between_centres(noise_brdf):
    v = noise_brdf.values
    rng = np.random.default_rng(15)
    ih, id_, ip = rng.integers(1, 88, 500), rng.integers(1, 88, 500), rng.integers(1, 178, 500)
    th, td, pd = centre_angles(ih, id_, ip)
    # halfway between centres i and i + 1 sits at index i + 1, on each axis in turn
    mid_h = ((ih + 1) / 90) ** 2 * (math.pi / 2)
    mid_d = (id_ + 1) / 90 * (math.pi / 2)
    mid_p = (ip + 1) / 180 * math.pi
    cases = [
        ((mid_h, td, pd), v[ih + 1, id_, ip]),
        ((th, mid_d, pd), v[ih, id_ + 1, ip]),
        ((th, td, mid_p), v[ih, id_, ip + 1]),
    ]
    for args, other in cases:
        np.testing.assert_allclose(
            noise_brdf.lookup(*args), 0.5 * (v[ih, id_, ip] + other), rtol=1e-12
        )
    # a quarter of the way along theta_d: weights 3/4 and 1/4
    q_d = (id_ + 0.75) / 90 * (math.pi / 2)
    np.testing.assert_allclose(
        noise_brdf.lookup(th, q_d, pd),
        0.75 * v[ih, id_, ip] + 0.25 * v[ih, id_ + 1, ip],
        rtol=1e-12,
    )
    # phi_d is periodic with period pi: phi_d = 0 sits halfway between bins 179 and 0
    for p0 in (0.0, math.pi, -math.pi):
        np.testing.assert_allclose(
            noise_brdf.lookup(th, td, np.full(500, p0)),
            0.5 * (v[ih, id_, 179] + v[ih, id_, 0]),
            rtol=1e-12,
        )
    # theta_h and theta_d clamp beyond the first and last centres
    np.testing.assert_array_equal(noise_brdf.lookup(0.0, td, pd), v[0, id_, ip])
    np.testing.assert_array_equal(noise_brdf.lookup(th, math.pi / 2, pd), v[ih, 89, ip])


def test_lookups_are_reciprocal_through_the_phi_d_fold(noise_brdf):
    wi, wo = upper_hemisphere(50000, 16), upper_hemisphere(50000, 17)
    for interpolation in ("trilinear", "nearest"):
        np.testing.assert_array_equal(
            noise_brdf.eval(wi, wo, interpolation=interpolation),
            noise_brdf.eval(wo, wi, interpolation=interpolation),
        )
    # the fold itself: phi_d and phi_d + pi are one configuration
    rng = np.random.default_rng(18)
    th, td = rng.uniform(0, 1.2, 20000), rng.uniform(0, 1.2, 20000)
    pd, ph = rng.uniform(-math.pi, math.pi, 20000), rng.uniform(0, 2 * math.pi, 20000)
    a = dirs_from_angles(th, ph, td, pd)
    b = dirs_from_angles(th, ph, td, pd + math.pi)
    np.testing.assert_allclose(noise_brdf.eval(*a), noise_brdf.eval(*b), rtol=1e-6)
    np.testing.assert_allclose(
        noise_brdf.lookup(th, td, pd), noise_brdf.lookup(th, td, pd + math.pi), rtol=1e-6
    )


def test_below_horizon_and_degenerate_inputs_give_zero(noise_brdf):
    up = upper_hemisphere(100, 19)
    down = up * np.array([1.0, 1.0, -1.0])
    flat = up * np.array([1.0, 1.0, 0.0])
    for wi, wo in (
        (up, down),
        (down, up),
        (down, down),
        (flat, up),
        (np.zeros((100, 3)), up),
        (np.full((100, 3), np.nan), up),
        (np.full((100, 3), np.inf), up),
    ):
        np.testing.assert_array_equal(noise_brdf.eval(wi, wo), 0.0)
    # batch shapes broadcast; unnormalised directions are normalised
    other = upper_hemisphere(1, 46)[0]
    f = noise_brdf.eval(up.reshape(10, 10, 3), 3.0 * other)
    assert f.shape == (10, 10, 3)
    np.testing.assert_allclose(f.reshape(100, 3), noise_brdf.eval(up, other), rtol=1e-9)


def test_unmeasured_bins_never_enter_the_interpolation():
    raw = np.full((3,) + DIMS, 2.0 / SCALE[0])
    raw[1] = 2.0 / SCALE[1]
    raw[2] = 2.0 / SCALE[2]
    mask = np.random.default_rng(20).random(DIMS) < 0.4
    raw[:, mask] = -1.0
    m = MerlBRDF(raw)
    np.testing.assert_array_equal(m.valid, ~mask)
    wi, wo = upper_hemisphere(100000, 21), upper_hemisphere(100000, 22)
    f = m.eval(wi, wo)
    assert np.all(np.isfinite(f))
    ok = np.isclose(f, 2.0, rtol=1e-12, atol=0) | (f == 0.0)
    assert ok.all(), f[~ok][:5]
    assert (f == 0).mean() < 0.01  # 0 only where all 8 neighbours are unmeasured
    # at an unmeasured centre the only weight is its own: 0; a tiny step away: 2
    ih, id_, ip = np.argwhere(mask[10:80, 10:80, 10:170])[0] + 10
    th, td, pd = centre_angles(ih, id_, ip)
    np.testing.assert_array_equal(m.lookup(th, td, pd), 0.0)
    if not mask[ih, id_ + 1, ip]:
        step = (id_ + 0.5 + 1e-3) / 90 * (math.pi / 2)
        np.testing.assert_allclose(m.lookup(th, step, pd), 2.0, rtol=1e-12)
    # a grid with nothing measured reads as 0, never NaN
    empty = MerlBRDF(np.full((3,) + DIMS, -1.0))
    np.testing.assert_array_equal(empty.eval(wi[:1000], wo[:1000]), 0.0)


# -------------------------------------------------------------------------- sampling
def _support_brdf():
    """Measured where theta_d bin < 45 and phi_d bin is even; values vary per bin."""
    raw = random_raw(23)
    mask = np.zeros(DIMS, dtype=bool)
    mask[:, :45, ::2] = True
    raw[:, ~mask] = -5.0
    return MerlBRDF(raw), mask


@pytest.mark.parametrize("space", ["index", "angle"])
def test_sample_pairs_stay_on_the_measured_support(space):
    m, mask = _support_brdf()
    wi, wo, f = m.sample_pairs(20000, rng=24, space=space)
    assert wi.shape == wo.shape == f.shape == (20000, 3)
    assert np.all(wi[:, 2] > 0) and np.all(wo[:, 2] > 0)
    np.testing.assert_allclose(np.linalg.norm(wi, axis=-1), 1.0, atol=1e-12)
    bh, bd, bp = merl_bin(*angles_of(wi, wo))
    assert mask[bh, bd, bp].all()
    assert np.all(f > 0)
    np.testing.assert_array_equal(f, m.eval(wi, wo))
    # nearest: f is the stored value of the drawn bin
    wi, wo, f = m.sample_pairs(5000, rng=25, space=space, interpolation="nearest")
    bh, bd, bp = merl_bin(*angles_of(wi, wo))
    np.testing.assert_array_equal(f, stored(m.raw, bh, bd, bp))
    # the same seed gives the same pairs
    a = m.sample_pairs(100, rng=np.random.default_rng(26), space=space)
    b = m.sample_pairs(100, rng=np.random.default_rng(26), space=space)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_sample_pairs_densities():
    # measured region theta_h < 40 deg and theta_d < 45 deg: never below the horizon
    raw = random_raw(27)
    mask = np.zeros(DIMS, dtype=bool)
    mask[:60, :45, :] = True
    raw[:, ~mask] = -1.0
    m = MerlBRDF(raw)
    n = 40000
    th_max = (60 / 90) ** 2 * (math.pi / 2)
    # index space: uniform over bins, so theta_h bins are equally often drawn
    wi, wo, _ = m.sample_pairs(n, rng=28, space="index")
    counts = np.bincount(merl_bin(*angles_of(wi, wo))[0], minlength=90)
    assert counts[60:].sum() == 0
    groups = counts[:60].reshape(6, 10).sum(1)
    np.testing.assert_allclose(groups, n / 6, rtol=0.05)
    # angle space: uniform in theta_h over [0, th_max)
    wi, wo, _ = m.sample_pairs(n, rng=29, space="angle")
    th = angles_of(wi, wo)[0]
    hist = np.histogram(th, bins=8, range=(0, th_max))[0]
    np.testing.assert_allclose(hist, n / 8, rtol=0.06)


def test_sample_pairs_errors():
    with pytest.raises(ValueError, match="no measured bins"):
        MerlBRDF(np.full((3,) + DIMS, -1.0)).sample_pairs(10, rng=0)
    m = MerlBRDF(random_raw(30))
    with pytest.raises(ValueError, match="space"):
        m.sample_pairs(10, rng=0, space="uniform")
    with pytest.raises(ValueError, match="interpolation"):
        m.eval(upper_hemisphere(2, 0), upper_hemisphere(2, 1), interpolation="cubic")


# ----------------------------------------------------------------------------- bake
@pytest.fixture(scope="module")
def baked_ggx(tmp_path_factory):
    model = analytic.create("microfacet", alpha=0.3)
    path = tmp_path_factory.mktemp("ggx") / "ggx.binary"
    merl.bake(model, path)
    return model, merl.read_merl(path)


def test_bake_lambertian_is_exact_everywhere(tmp_path):
    model = analytic.create("lambertian", albedo=(0.2, 0.5, 0.8))
    path = tmp_path / "lambert.binary"
    merl.bake(model, path)
    m = merl.read_merl(path)
    # bins whose centre pair lies below the horizon are stored as unmeasured
    np.testing.assert_array_equal(m.valid, merl.grid_above_horizon())
    assert 0.6 < m.valid.mean() < 0.9
    wi, wo = upper_hemisphere(100000, 31), upper_hemisphere(100000, 32)
    f = m.eval(wi, wo)
    want = np.array([0.2, 0.5, 0.8]) / math.pi
    # unmeasured neighbours carry no weight, so a constant stays constant up to the horizon
    nz = np.all(f > 0, -1)
    assert nz.mean() > 0.999
    np.testing.assert_allclose(f[nz], np.broadcast_to(want, f[nz].shape), rtol=1e-13)


def test_bake_reproduces_ggx_at_bin_centres(baked_ggx):
    model, m = baked_ggx
    rng = np.random.default_rng(33)
    ih, id_, ip = random_bins(rng, 20000)
    th, td, pd = centre_angles(ih, id_, ip)
    wi, wo = dirs_from_angles(th, rng.uniform(0, 2 * math.pi, len(ih)), td, pd)
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    assert m.valid[ih[up], id_[up], ip[up]].all()
    assert not m.valid[ih[~up], id_[~up], ip[~up]].any()
    # isotropic model: phi_h is free; the only differences are rounding
    np.testing.assert_allclose(m.eval(wi[up], wo[up]), model.eval(wi[up], wo[up]), rtol=1e-11)
    # the grid's own directions, in flat order, against the stored values
    flat = (ih * 90 + id_) * 180 + ip
    k = np.sort(flat[:50])
    gwi, gwo = merl.grid_directions(int(k[0]), int(k[-1]) + 1)
    gwi, gwo = gwi[k - k[0]], gwo[k - k[0]]
    th, td, pd = centre_angles(*np.unravel_index(k, DIMS))
    rwi, rwo = dirs_from_angles(th, np.zeros(len(k)), td, pd)  # phi_h = 0
    np.testing.assert_allclose(gwi, rwi, atol=1e-15)
    np.testing.assert_allclose(gwo, rwo, atol=1e-15)
    ok = m.valid.reshape(-1)[k]
    np.testing.assert_allclose(
        m.values.reshape(-1, 3)[k][ok], np.maximum(model.eval(gwi[ok], gwo[ok]), 0), rtol=1e-13
    )


def test_bake_reproduces_ggx_within_interpolation_error(baked_ggx):
    model, m = baked_ggx
    wi, wo = upper_hemisphere(200000, 34), upper_hemisphere(200000, 35)
    keep = (wi[:, 2] > 0.1) & (wo[:, 2] > 0.1)
    wi, wo = wi[keep], wo[keep]
    f = model.eval(wi, wo)
    rel = (np.abs(m.eval(wi, wo) - f) / f).max(-1)
    stats = np.median(rel), np.quantile(rel, 0.99), rel.max()
    assert stats[0] < 2e-3 and stats[1] < 1.2e-2 and stats[2] < 6e-2, stats
    cos = (wi[:, 2] * wo[:, 2])[:, None]
    assert rel_rmse(f, m.eval(wi, wo), cos) < 1.5e-3


def test_bake_clamps_negative_values_and_checks_the_callable(tmp_path):
    def signed(wi, wo):  # negative where wi.x < 0
        return np.where(wi[:, :1] < 0, -0.5, 0.25) * np.ones(3)

    m = merl.bake_brdf(signed)
    np.testing.assert_array_equal(m.valid, merl.grid_above_horizon())
    assert set(np.unique(m.values[m.valid])) == {0.0, 0.25}
    with pytest.raises(ValueError, match=r"shape \(\d+,\)"):
        merl.bake_brdf(lambda wi, wo: wi[:, 0])
    with pytest.raises(ValueError, match="non-finite value at bin"):
        merl.bake_brdf(lambda wi, wo: np.full(wi.shape, np.nan))
    with pytest.raises(ValueError, match="non-finite"):
        merl.bake(lambda wi, wo: np.full(wi.shape, np.inf), tmp_path / "x.binary")
    assert not (tmp_path / "x.binary").exists()
    with pytest.raises(TypeError):
        merl.bake_brdf(42)


# ------------------------------------------------------------- real-material fixtures
def test_fixture_materials_are_in_the_data(nbrdf_npz, abc_csv):
    names = merl.nbrdf_names(nbrdf_npz)
    assert len(names) == 100 and set(MATERIALS) <= set(names)
    assert set(merl.read_abc_params(abc_csv)) == set(names)


def test_nbrdf_fixture_follows_the_documented_formula(nbrdf_npz):
    rng = np.random.default_rng(36)
    th, td = rng.uniform(0, 1.2, 5000), rng.uniform(0, 1.2, 5000)
    pd, ph = rng.uniform(0, math.pi, 5000), rng.uniform(0, 2 * math.pi, 5000)
    wi, wo = dirs_from_angles(th, ph, td, pd)
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    x = np.stack(
        [
            np.sin(th),
            np.zeros_like(th),
            np.cos(th),
            np.sin(td) * np.cos(pd),
            np.sin(td) * np.sin(pd),
            np.cos(td),
        ],
        -1,
    )
    with np.load(nbrdf_npz) as z:
        for name in MATERIALS:
            w = [z[f"{name}/{k}"].astype(np.float64) for k in ("W0", "b0", "W1", "b1", "W2", "b2")]
            y = np.maximum(x @ w[0] + w[1], 0)
            y = np.maximum(y @ w[2] + w[3], 0)
            want = np.exp(y @ w[4] + w[5]) - 1
            got = merl.nbrdf_fixture(nbrdf_npz, name)(wi, wo)
            # the MLP runs in float32, as shipped
            np.testing.assert_allclose(got[up], want[up], rtol=2e-5, atol=2e-6)
            np.testing.assert_array_equal(got[~up], 0.0)
            # torch in, torch out
            got_t = merl.nbrdf_fixture(nbrdf_npz, name)(torch.from_numpy(wi), torch.from_numpy(wo))
            assert isinstance(got_t, torch.Tensor)
            np.testing.assert_array_equal(got_t.numpy(), got)


def test_nbrdf_reciprocal_option_averages_both_orders(nbrdf_npz):
    raw = merl.nbrdf_fixture(nbrdf_npz, "gold-metallic-paint")
    sym = merl.nbrdf_fixture(nbrdf_npz, "gold-metallic-paint", reciprocal=True)
    wi, wo = upper_hemisphere(20000, 37), upper_hemisphere(20000, 38)
    np.testing.assert_array_equal(sym(wi, wo), sym(wo, wi))
    # the mirrored difference vector equals the swapped pair up to rounding (the MLP is float32)
    np.testing.assert_allclose(sym(wi, wo), 0.5 * (raw(wi, wo) + raw(wo, wi)), rtol=1e-5, atol=1e-6)
    # the raw network is not reciprocal, which is why the option exists
    assert np.max(np.abs(raw(wi, wo) - raw(wo, wi))) > 1e-3
    with pytest.raises(ValueError, match="gold-metallic-paint"):
        merl.nbrdf_fixture(nbrdf_npz, "gold-metalic-paint")


@pytest.mark.parametrize("name", MATERIALS)
def test_nbrdf_material_written_and_read_back(baked_materials, name):
    fn, path = baked_materials[name]
    assert path.stat().st_size == FILE_BYTES
    m = merl.read_merl(path)
    np.testing.assert_array_equal(m.valid, merl.grid_above_horizon())
    # at bin centres: the network's value (clamped at 0, as a BRDF)
    rng = np.random.default_rng(39)
    ih, id_, ip = random_bins(rng, 5000)
    th, td, pd = centre_angles(ih, id_, ip)
    wi, wo = dirs_from_angles(th, rng.uniform(0, 2 * math.pi, 5000), td, pd)
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    np.testing.assert_allclose(
        m.eval(wi[up], wo[up]), np.maximum(fn(wi[up], wo[up]), 0.0), rtol=1e-9, atol=1e-12
    )
    # anywhere: within the grid's interpolation error, by the two metrics
    wi, wo = upper_hemisphere(100000, 40), upper_hemisphere(100000, 41)
    f_ref = np.maximum(fn(wi, wo), 0.0)
    f = m.eval(wi, wo)
    cos = (wi[:, 2] * wo[:, 2])[:, None]
    assert log_error(f_ref, f, cos) < 1e-4
    assert rel_rmse(f_ref, f, cos) < 5e-2
    # and the material is what its name says: a metal's peak dwarfs its diffuse floor
    peak = m.values[0, 30, 90].mean()
    floor = m.values[70, 20, 90].mean()
    if name == "aluminium":
        assert peak / floor > 1e4
    if name == "white-diffuse-bball":
        assert peak / floor < 1e3 and floor > 0.03


# ------------------------------------------------------------------------------ ABC
def test_abc_params_follow_the_csv_columns(abc_csv):
    table = merl.read_abc_params(abc_csv)
    with open(abc_csv, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["name", "kD_r", "kD_g", "kD_b", "A_r", "A_g", "A_b", "B", "C", "ior"]
    assert len(table) == len(rows) - 1 == 100
    for row in rows[1:]:
        p = table[row[0]]
        assert p.kd == tuple(float(x) for x in row[1:4])
        assert p.a == tuple(float(x) for x in row[4:7])
        assert (p.b, p.c, p.ior) == (float(row[7]), float(row[8]), float(row[9]))
    with pytest.raises(ValueError, match="alum-bronze"):
        merl.abc_fixture(abc_csv, "alum_bronze")


def _abc_scalar(p, wi, wo):
    """dj_brdf's abc::eval in scalar Python, Fresnel in dj_brdf's algebraic form."""
    h = [a + b for a, b in zip(wi, wo)]
    n = math.sqrt(sum(x * x for x in h))
    h = [x / n for x in h]
    c = sum(a * b for a, b in zip(wi, h))
    g = math.sqrt(p.ior**2 + c * c - 1)
    t1, t2 = c * (g + c) - 1, c * (g - c) + 1
    fres = 0.5 * (g - c) ** 2 / (g + c) ** 2 * (1 + t1 * t1 / (t2 * t2))
    G = min(1.0, 2 * h[2] * wi[2] / c, 2 * h[2] * wo[2] / c)
    out = []
    for k in range(3):
        D = p.a[k] / (1 + p.b * (1 - h[2])) ** p.c
        out.append((p.kd[k] + fres * D * G / (wi[2] * wo[2])) / math.pi)
    return out


@pytest.mark.parametrize("name", ["alum-bronze", "gray-plastic", "chrome", "white-paint"])
def test_abc_fixture_matches_the_dj_brdf_equations(abc_csv, name):
    p = merl.read_abc_params(abc_csv)[name]
    f = merl.abc_fixture(abc_csv, name)
    wi, wo = upper_hemisphere(200, 42), upper_hemisphere(200, 43)
    want = np.array([_abc_scalar(p, a, b) for a, b in zip(wi.tolist(), wo.tolist())])
    np.testing.assert_allclose(f(wi, wo), want, rtol=1e-10)
    np.testing.assert_array_equal(f(wi, wo * np.array([1, 1, -1])), 0.0)


@pytest.mark.parametrize(
    "name", ["white-diffuse-bball", "gray-plastic", "white-paint", "red-plastic", "blue-acrylic"]
)
def test_abc_and_nbrdf_fits_of_one_material_agree(abc_csv, nbrdf_npz, name):
    # Two independent fits of the same measurements agree away from the peak and the
    # horizon to ~20%.  A misplaced 1/pi would put the ratio near 3.1 or 0.32.
    abc = merl.abc_fixture(abc_csv, name)
    nb = merl.nbrdf_fixture(nbrdf_npz, name, reciprocal=True)
    wi, wo = upper_hemisphere(50000, 44), upper_hemisphere(50000, 45)
    th = angles_of(wi, wo)[0]
    keep = (th > 0.4) & (wi[:, 2] > 0.3) & (wo[:, 2] > 0.3)
    ratio = np.median(abc(wi[keep], wo[keep]) / np.maximum(nb(wi[keep], wo[keep]), 1e-4), 0)
    assert np.all((ratio > 0.75) & (ratio < 1.35)), ratio


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_is_refused_before_it_is_opened_for_reading(tmp_path):
    import signal

    def alarm(signum, frame):
        raise TimeoutError("blocked reading a FIFO")

    fifo = tmp_path / "x.binary"
    os.mkfifo(fifo)  # never opened for writing: a reader that opens it blocks
    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(20)
    try:
        with pytest.raises(MerlFormatError) as e:
            merl.read_merl(fifo)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert str(e.value) == f"{fifo}: is a FIFO, not a file"
