"""Fitting measured data: ``target: {data: material.binary}``, ``validate --reference
material.binary``, and real materials (NBRDF fits of MERL measurements, baked to MERL
files at test time) fitted and compared with the ABC analytic fits of the same materials."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import analytic
import conftest
from neural_brdf import config, pipeline, validate
from neural_brdf.measured import merl
from neural_brdf.tooling import cli
from neural_brdf.train import data, loop

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

# Short fits: mechanics and a fair comparison, not the benchmark's accuracy.
SHORT = [
    "train.steps=1000",
    "train.warmup=20",
    "train.progress=false",
    "train.threads=1",
    "train.eval_every=250",
    "model.hidden=[32,32]",
    "data.batch_size=2048",
    "data.pool_size=65536",
    "normalization.table_size=33",
    "normalization.samples=4096",
    "validation.furnace_dirs=31",
    "validation.furnace_samples=4096",
    "validation.pairs=4000",
    "export.parity_pairs=512",
]


def merl_config(path, *extra) -> config.Config:
    return config.load(CONFIGS / "merl.yaml", [f"target.data={path}"] + SHORT + list(extra))


@pytest.fixture(scope="module")
def ggx_binary(tmp_path_factory):
    """A GGX conductor baked to a MERL file, with half the theta_d range unmeasured."""
    ggx = analytic.create("microfacet", alpha=0.3, fresnel="conductor", material="Au")
    grid = merl.bake_brdf(ggx)
    valid = grid.valid.copy()
    valid[:, 60:, :] = False  # theta_d >= 60 deg: "not measured"
    path = tmp_path_factory.mktemp("ggx") / "ggx.binary"
    merl.write_merl(path, merl.MerlBRDF.from_values(grid.values, valid=valid))
    return ggx, path


# ----------------------------------------------------------------- the measured target
def test_measured_pairs_stay_on_the_measured_support(ggx_binary):
    ggx, path = ggx_binary
    target = data.MeasuredTarget.from_file(path)
    wi, wo, f = target.draw(20000, torch.Generator().manual_seed(0))
    assert wi.dtype == torch.float32 and f.shape == (20000, 3)
    _, _, theta_d, _ = analytic.frame.rusinkiewicz(wi.double(), wo.double())
    assert float(theta_d.max()) < math.radians(60.0) + 1e-6  # never in unmeasured bins
    assert bool((wi[:, 2] > 0).all() and (wo[:, 2] > 0).all())
    # f is the interpolated data, which is close to the model it was baked from
    ref = ggx.eval(wi.double().numpy(), wo.double().numpy())
    cos = wo[:, 2:3].double().numpy()
    err = np.sqrt(np.sum((f.numpy() - ref) ** 2 * cos**2) / np.sum((ref * cos) ** 2))
    assert err < 0.05


def test_grid_pairs_are_the_measured_bin_centres(ggx_binary):
    ggx, path = ggx_binary
    target = data.MeasuredTarget.from_file(path)
    wi, wo, f = target.grid_pairs(5000, seed=3)
    # at a bin centre the stored value is the model's value there (a bake is exact there)
    np.testing.assert_allclose(f.numpy(), ggx.eval(wi.numpy(), wo.numpy()), rtol=1e-9, atol=1e-12)
    everything = target.grid_pairs(None)[0]
    m = merl.read_merl(path)
    assert len(everything) == int((m.valid & merl.grid_above_horizon()).sum())


def test_accuracy_against_data_is_zero_for_the_baked_model_and_not_for_another(ggx_binary):
    ggx, path = ggx_binary
    target = data.MeasuredTarget.from_file(path)
    same = validate.accuracy(ggx.eval, target, n=0, seed=0)
    assert same["rel_rmse"] < 1e-9 and same["nbrdf_log_error"] < 1e-9
    assert same["pairs"] == len(target.grid_pairs(None)[0])
    rougher = analytic.create("microfacet", alpha=0.35, fresnel="conductor", material="Au")
    other = validate.accuracy(rougher.eval, target, n=0, seed=0)
    assert 0.05 < other["rel_rmse"] < 1.0


def test_resume_on_measured_data_continues_exactly(ggx_binary, tmp_path):
    _, path = ggx_binary
    extra = [
        "train.schedule=constant",
        "train.steps=12",
        "train.checkpoint_every=5",
        "data.batch_size=256",
        "data.pool_size=2048",
        "model.hidden=[8,8]",
    ]
    loop.train(merl_config(path, *extra), tmp_path / "straight")
    loop.train(merl_config(path, *extra, "train.steps=5"), tmp_path / "split")
    loop.train(merl_config(path, *extra), tmp_path / "split", resume=True)
    a = torch.load(tmp_path / "straight" / "ckpt.pt", weights_only=True)["model"]
    b = torch.load(tmp_path / "split" / "ckpt.pt", weights_only=True)["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)


# ------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("case", ["missing", "suffix", "truncated", "both"])
def test_bad_data_targets_exit_2_naming_the_key(case, tmp_path, capsys):
    path = tmp_path / "m.binary"
    sets = [f"target.data={path}"]
    if case == "suffix":
        path = tmp_path / "m.csv"
        path.write_text("x")
        sets = [f"target.data={path}"]
    elif case == "truncated":
        path.write_bytes(np.asarray((90, 90, 180), "<i4").tobytes() + b"\0" * 100)
    elif case == "both":
        sets += ["target.model=phong"]
    argv = ["train", str(CONFIGS / "merl.yaml"), "--out", str(tmp_path / "run")]
    for s in sets:
        argv += ["--set", s]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "target.data" in err
    assert "Traceback" not in err


def test_validate_reference_must_be_a_readable_merl_file(tmp_path, capsys):
    bad = tmp_path / "bad.binary"
    bad.write_bytes(b"\0" * 40)
    assert cli.main(["validate", str(tmp_path / "model.onnx"), "--reference", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "bad.binary" in err


# ----------------------------------------------------------------- real materials
@pytest.fixture(scope="module")
def fits(baked_materials, tmp_path_factory):
    """Each real-data fixture fitted with the short recipe: name -> (run dir, metrics)."""
    out = {}
    for name, (_, path) in baked_materials.items():
        run = tmp_path_factory.mktemp(name)
        out[name] = (run, pipeline.run(merl_config(path, f"name={name}"), run))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", conftest.MATERIALS)
def test_real_material_fit_is_physical_and_beats_the_abc_fit(fits, baked_materials, abc_csv, name):
    run, report = fits[name]
    assert report["passed"]
    checks = report["checks"]
    assert checks["reciprocity"]["value"] == 0.0
    assert checks["max_albedo"]["value"] <= 1.001
    acc = report["accuracy"]
    target = data.MeasuredTarget.from_file(baked_materials[name][1])
    assert acc["pairs"] == len(target.grid_pairs(None)[0])  # every measured bin
    # the ABC analytic fit of the same measured material, on the same bins
    abc = validate.accuracy(merl.abc_fixture(abc_csv, name), target, n=0, seed=0)
    assert acc["nbrdf_log_error"] < abc["nbrdf_log_error"]
    assert acc["rel_rmse"] < abc["rel_rmse"]
    assert acc["rel_rmse"] < 0.20  # a collapsed fit (floor at 0) measured 0.29


def test_validate_cli_against_the_measured_file(fits, baked_materials, tmp_path, capsys):
    name = "gold-metallic-paint"
    run, report = fits[name]
    out = tmp_path / "v.json"
    rc = cli.main(
        [
            "validate",
            str(run / "model.onnx"),
            "--reference",
            str(baked_materials[name][1]),
            "--json",
            str(out),
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "rel_rmse (f cos)" in text
    got = json.loads(out.read_text())
    # the same file against the same data gives the figures the training run reported
    assert got["accuracy"]["rel_rmse"] == pytest.approx(report["accuracy"]["rel_rmse"], rel=1e-6)
    assert got["reference"].startswith("MERL ")
