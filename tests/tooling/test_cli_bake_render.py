"""`neural-brdf bake` (MERL files) and `neural-brdf render` (Mitsuba previews)."""

from __future__ import annotations

import re

import numpy as np
import pytest

import analytic
from cli_helpers import ROOT, SETS, assert_one_line_error, run
from neural_brdf.measured import merl
from neural_brdf.tooling.cli import main

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


def foreign_onnx(path):
    """A valid ONNX file that is not a BRDF: z = x + y."""
    import onnx
    from onnx import TensorProto, helper

    io = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [None, 3]) for n in "xyz"]
    graph = helper.make_graph([helper.make_node("Add", ["x", "y"], ["z"])], "add", io[:2], io[2:])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    return path


def test_render_refuses_an_empty_or_foreign_model_in_one_line(capsys, tmp_path):
    empty = tmp_path / "empty.onnx"
    empty.write_bytes(b"")
    for model in (empty, foreign_onnx(tmp_path / "add.onnx")):
        code, _, err = cli(capsys, "render", str(model), "-o", str(tmp_path / "x.png"))
        assert_one_line_error(code, err, model.name)
    assert not (tmp_path / "x.png").exists()


@pytest.mark.mitsuba
def test_render_writes_a_labelled_side_by_side_preview(capsys, tiny_model, tmp_path):
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
        "64",
        "-o",
        str(out),
    )
    assert code == 0, err
    assert "PSNR" in stdout
    gain = float(re.search(r"\|difference\| x ([0-9.e+-]+)", stdout).group(1))
    import matplotlib.image as mpimg

    img = mpimg.imread(out)[..., :3].astype(np.float64)
    strip = img.shape[0] - 64  # the label strip above the 64-pixel panels
    assert strip >= 16 and img.shape[1] > 3 * 64
    gap = (img.shape[1] - 3 * 64) // 2
    panels = [img[strip:, i * (64 + gap) : i * (64 + gap) + 64] for i in range(3)]
    labels = [img[:strip, i * (64 + gap) : i * (64 + gap) + 64] for i in range(3)]
    for label in labels:  # black text on white, in each panel's own header
        assert (label.mean(-1) > 0.95).mean() > 0.5 and (label.mean(-1) < 0.5).any()
    neural, target, diff = panels
    assert neural.std() > 0.01 and target.std() > 0.01  # not blank
    # the stated scale: 99 % of |neural - target| x K is at most 1, the rest saturates
    err_scaled = np.abs(neural - target).mean(-1) * gain
    assert np.percentile(err_scaled, 99) == pytest.approx(1.0, abs=0.15)
    assert diff.max() > 0.9  # inferno at 1: pale yellow, not black
