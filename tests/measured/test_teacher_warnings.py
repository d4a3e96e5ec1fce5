"""A Mitsuba teacher that the run takes, but whose file differs from what the config
suggests: one warning line each, and the run goes on (docs/mitsuba.md).

* an anisotropic teacher with an isotropic ``model.encoding`` (the file can only learn
  the average over the azimuth; it trained without a word);
* a ``texture:`` section with a teacher that does not vary over the surface (ignored
  without a word);
* a bitmap with ``wrap_mode`` clamp or mirror (the file's textures wrap by repeat);
* a teacher whose albedo exceeds 1 (the file learns its energy-bounded version);
* a bitmap filtered ``nearest`` (the file interpolates its textures bilinearly).

Each has its quiet twin: the same teacher where the file is what the config says gets
no warning.  A batch (``train-many``) prints the same lines as a run alone.  And one
refusal: a bitmap file that is not an image is named as such (one line, exit 2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cli_helpers import SETS, assert_one_line_error, cli
from neural_brdf import config as cfgmod
from neural_brdf.pipeline import teacher_warnings
from neural_brdf.target import spatially_varying
from neural_brdf.train import data

pytestmark = pytest.mark.mitsuba

ANISO = '<bsdf version="3.0.0" type="roughconductor"><float name="alpha_u" value="0.1"/>'
ANISO += '<float name="alpha_v" value="0.3"/></bsdf>'
ISO = '<bsdf version="3.0.0" type="roughconductor"><float name="alpha" value="0.2"/></bsdf>'


@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


def _warnings(folder: Path, xml: str, extra: str = "") -> list[str]:
    (folder / "teacher.xml").write_text(xml)
    cfg_path = folder / "c.yaml"
    cfg_path.write_text(f"target: {{mitsuba: teacher.xml}}\n{extra}")
    cfg = cfgmod.load(cfg_path)
    target = data.build_target(cfg.target)
    return teacher_warnings(cfg, target, textured=spatially_varying(target))


def _bitmap(mi, folder: Path, wrap: str | None) -> str:
    texels = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32) * 0.8
    mi.Bitmap(texels).write(str(folder / "albedo.exr"))
    mode = f'<string name="wrap_mode" value="{wrap}"/>' if wrap else ""
    return (
        '<bsdf version="3.0.0" type="diffuse"><texture type="bitmap" name="reflectance">'
        f'<string name="filename" value="albedo.exr"/>{mode}</texture></bsdf>'
    )


def test_an_anisotropic_teacher_with_an_isotropic_encoding_is_warned(mi, tmp_path):
    (line,) = _warnings(tmp_path, ANISO, "model: {encoding: isotropic}\n")
    assert line.startswith("model.encoding: isotropic") and "anisotropic" in line
    assert _warnings(tmp_path, ANISO, "model: {encoding: anisotropic}\n") == []
    assert _warnings(tmp_path, ISO, "model: {encoding: isotropic}\n") == []


def test_a_uniform_teacher_above_1_is_warned(mi, tmp_path):
    """Bounded to an albedo of 1 (its accuracy then measured against the bounded teacher),
    it was said only in metrics.json and the report; a textured teacher's run printed it."""
    above = '<bsdf version="3.0.0" type="principled"><rgb name="base_color" value="1, 1, 1"/>'
    above += '<float name="roughness" value="0.5"/></bsdf>'
    (line,) = _warnings(tmp_path, above)
    assert "teacher.xml: the teacher's albedo exceeds 1 (max 1." in line
    assert "energy-bounded" in line
    assert _warnings(tmp_path, ISO) == []  # within 1: no word


def test_a_texture_section_on_a_uniform_teacher_is_warned(mi, tmp_path):
    (line,) = _warnings(tmp_path, ISO, "texture: {lobes: 3}\n")
    assert line.startswith("texture: ignored") and "teacher.xml" in line
    assert _warnings(tmp_path, ISO) == []


@pytest.mark.parametrize("wrap", ["clamp", "mirror"])
def test_a_bitmap_that_does_not_repeat_is_warned(mi, tmp_path, wrap):
    (line,) = _warnings(tmp_path, _bitmap(mi, tmp_path, wrap))
    assert f"wrap_mode {wrap}" in line and "albedo.exr" in line and "reflectance" in line


@pytest.mark.parametrize("wrap", [None, "repeat"])
def test_a_repeating_bitmap_is_not_warned(mi, tmp_path, wrap):
    assert _warnings(tmp_path, _bitmap(mi, tmp_path, wrap)) == []


def test_a_bitmap_filtered_nearest_is_warned(mi, tmp_path):
    """The file blends its texels bilinearly; a nearest-filtered teacher steps between
    them (a walkthrough's run was 8 % off without a word)."""
    xml = _bitmap(mi, tmp_path, None).replace(
        "</texture>", '<string name="filter_type" value="nearest"/></texture>'
    )
    # (its steps also make the teacher finer than the field: that line too)
    (line,) = [w for w in _warnings(tmp_path, xml) if "filter_type" in w]
    assert "filter_type nearest" in line and "albedo.exr" in line and "bilinear" in line
    bilinear = xml.replace('value="nearest"', 'value="bilinear"')
    assert _warnings(tmp_path, bilinear) == []


CHECKER = (
    '<bsdf type="diffuse" version="3.0.0"><texture type="checkerboard" name="reflectance">'
    '<rgb name="color0" value="0.8, 0.1, 0.1"/><rgb name="color1" value="0.1, 0.1, 0.8"/>'
    '<transform name="to_uv"><scale x="2" y="3"/></transform></texture></bsdf>'
)


def test_a_teacher_finer_than_the_field_is_warned(mi, tmp_path):
    """The field is texture.project texels a side when set, else texture.resolution."""
    (line,) = _warnings(tmp_path, CHECKER)
    assert "more finely than the field of 32x32 texels" in line and "teacher.xml" in line
    assert _warnings(tmp_path, CHECKER, "texture: {resolution: 256, pool_per_texel: 16}\n") == []
    (line,) = _warnings(
        tmp_path, CHECKER, "texture: {resolution: 256, pool_per_texel: 16, project: 64}\n"
    )
    assert "64x64 texels" in line
    assert _warnings(tmp_path, CHECKER, "texture: {project: 256}\n") == []


def test_the_run_prints_the_warning_once_and_trains(mi, tmp_path, capsys):
    (tmp_path / "teacher.xml").write_text(ANISO)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("name: aniso\ntarget: {mitsuba: teacher.xml}\nmodel: {encoding: isotropic}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert code in (0, 1), err  # 1: a check failed (a tiny run), not bad input
    assert "Traceback" not in err
    warned = [x for x in err.splitlines() if "warning" in x]
    assert warned == [warned[0]] and warned[0].startswith("aniso: warning: model.encoding")
    assert (tmp_path / "run" / "model.onnx").is_file()


def test_a_batch_prints_each_configs_warning(mi, tmp_path, capsys):
    """train-many builds its targets in its own path: the same lines, named by config."""
    (tmp_path / "aniso.xml").write_text(ANISO)
    (tmp_path / "iso.xml").write_text(ISO)
    files = []
    for name in ("aniso", "iso"):
        f = tmp_path / f"{name}.yaml"
        f.write_text(
            f"name: {name}\ntarget: {{mitsuba: {name}.xml}}\nmodel: {{encoding: isotropic}}\n"
        )
        files.append(str(f))
    code, _, err = cli(capsys, "train-many", *files, "--out", str(tmp_path / "o"), *SETS)
    assert code in (0, 1), err
    assert "Traceback" not in err
    warned = [x for x in err.splitlines() if "warning" in x]
    assert len(warned) == 1 and warned[0].startswith("aniso: warning: model.encoding")
    assert (tmp_path / "o" / "iso" / "model.onnx").is_file()


# ------------------------------------------------------------------ and one refusal
def test_a_bitmap_that_is_not_an_image_is_named(mi, tmp_path, capsys):
    """Mitsuba's own message was its plugin error ending in "read 6 out of 8 bytes"."""
    (tmp_path / "albedo.png").write_text("hello")
    xml = _bitmap(mi, tmp_path, None).replace("albedo.exr", "albedo.png")
    (tmp_path / "teacher.xml").write_text(xml)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: teacher.xml}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(
        code, err, "target.mitsuba", "teacher.xml", "'albedo.png' cannot be read as an image"
    )
