"""`neural-brdf bake` (MERL files) and `neural-brdf render` (Mitsuba previews)."""

from __future__ import annotations

import numpy as np
import pytest

import analytic
from neural_brdf import merl
from neural_brdf.cli import main
from test_cli import ROOT, SETS, assert_one_line_error, run

LAMBERT = ROOT / "configs" / "lambert.yaml"


def cli(capsys, *args):
    code = main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    out = tmp_path_factory.mktemp("bake") / "lambert"
    proc = run("train.py", str(LAMBERT), "--out", str(out), *SETS)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out / "model.onnx"


def test_bake_a_config_target_round_trips(capsys, tmp_path):
    out = tmp_path / "lambert.binary"
    code, stdout, err = cli(capsys, "bake", str(LAMBERT), "-o", str(out))
    assert code == 0, err
    baked = merl.read_merl(out)
    target = analytic.create("lambertian", albedo=[0.8, 0.6, 0.4])
    wi = analytic.physics.random_directions(2000, 1, grazing_fraction=0.0)
    wo = analytic.physics.random_directions(2000, 2, grazing_fraction=0.0)
    keep = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)  # away from unmeasured horizon bins
    np.testing.assert_allclose(
        baked.eval(wi[keep], wo[keep]), target.eval(wi[keep], wo[keep]), rtol=1e-6
    )


def test_bake_a_neural_model_matches_onnxruntime(capsys, tiny_model, tmp_path):
    import neural_brdf

    out = tmp_path / "neural.binary"
    code, _, err = cli(capsys, "bake", str(tiny_model), "-o", str(out))
    assert code == 0, err
    baked = merl.read_merl(out)
    wi, wo = merl.grid_directions(0, 5000)
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    ref = neural_brdf.load(tiny_model).eval(wi[ok], wo[ok])
    np.testing.assert_allclose(baked.values.reshape(-1, 3)[:5000][ok], ref, rtol=1e-5, atol=1e-7)


def test_bake_and_render_bad_input_exit_2(capsys, tmp_path):
    assert_one_line_error(
        *cli(capsys, "bake", str(tmp_path / "none.onnx"), "-o", str(tmp_path / "x.binary"))[::2],
        "none.onnx",
    )
    assert_one_line_error(
        *cli(
            capsys, "bake", str(LAMBERT), "-o", str(tmp_path / "no" / "such" / "dir" / "x.binary")
        )[::2],
        "x.binary",
    )
    assert_one_line_error(*cli(capsys, "bake", str(LAMBERT))[::2], "-o")
    assert_one_line_error(
        *cli(capsys, "render", str(tmp_path / "none.onnx"), "-o", str(tmp_path / "x.png"))[::2],
        "none.onnx",
    )


@pytest.mark.mitsuba
def test_render_writes_a_side_by_side_preview(capsys, tiny_model, tmp_path):
    out = tmp_path / "preview.png"
    code, stdout, err = cli(
        capsys,
        "render",
        str(tiny_model),
        "--reference",
        str(LAMBERT),
        "--spp",
        "4",
        "--resolution",
        "32",
        "-o",
        str(out),
    )
    assert code == 0, err
    assert "PSNR" in stdout
    import matplotlib.image as mpimg

    img = mpimg.imread(out)
    assert img.shape[1] > img.shape[0] * 2  # neural | reference | error map
    assert img[..., :3].std() > 0.01  # not blank
