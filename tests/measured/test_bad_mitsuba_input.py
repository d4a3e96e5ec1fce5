"""Bad input on the Mitsuba-teacher and textured paths: one line naming the file or key,
exit code 2, never a traceback or a silent wrong answer (docs/mitsuba.md).

* ``python -m neural_brdf.measured.procedural``: a size below 2 or too large for memory,
  a negative ``--steps``, an OUT that is a file: one line, exit 2 (was a traceback);
  a usage error is one line too (was argparse's usage and message);
* a bitmap texel of NaN or inf is refused naming the texture (a NaN read as "no change
  over uv", so the teacher was taken as uniform: a silent wrong teacher); so is a
  procedural texture that is NaN away from uv (0.5, 0.5) (the probes at random uv);
* a normal map of one channel, on which Mitsuba's sampler raises: one line that keeps
  Mitsuba's sentence (was a traceback with a 12-line dump of the texture);
* a rough plugin at roughness 0 (or negative), a delta lobe in all but name (trained
  with a 100 % error and exit code 0), and a roughness texture at 0 somewhere: a bitmap
  bound to alpha with texels at 0 (named; a quarter of a 16² PNG trained with physics
  PASSED and exit 0), a procedural one away from uv 0.5; alpha 1e-3 is kept;
* an XML file given where a config is expected (``validate --reference``, ``render
  --reference``, ``bake``): one line that says to give a config (was "expected a mapping
  of keys at the top level, got str");
* ``view --uv`` beyond +-1024, where float32 loses uv's fraction (the plots were drawn
  at another point than the one asked for and labelled);
* ``export`` and ``report`` of a run whose teacher file no longer matches its model (a
  textured run whose XML is now uniform, or the reverse): one line (export wrote a file
  that called the textured model's teacher uniform; report raised a TypeError);
* ``export`` of a run whose config.yaml was edited away from its checkpoint in a key the
  weights were trained with (``model.*``, a textured run's field and lobes): one line (a
  traceback, or for ``model.grazing_power`` a file computing another function); a
  validation setting may still change.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cli_helpers import SETS, assert_one_line_error, cli
from neural_brdf.errors import InputError

pytestmark = pytest.mark.mitsuba

UNIFORM = """<bsdf version="3.0.0" type="roughplastic">
    <float name="alpha" value="0.3"/>
    <rgb name="diffuse_reflectance" value="0.2, 0.3, 0.5"/>
</bsdf>"""
TEXTURED_SETS = [
    a
    for kv in (
        "texture.lobes=2",
        "texture.resolution=4",
        "texture.pool_per_texel=64",
        "texture.validation_uv=4",
        "train.steps=2",
    )
    for a in ("--set", kv)
]


@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


# ------------------------------------------------------------------ procedural's command
@pytest.mark.parametrize(
    "args, needle",
    [
        (["--size", "0"], "size: 0"),
        (["--size", "-3"], "size: -3"),
        (["--size", "1000000"], "size: 1000000"),  # refused before any allocation
        (["--size", "4", "--steps", "-5"], "--steps -5"),
    ],
)
def test_procedural_bad_arguments_are_one_line(mi, tmp_path, capsys, args, needle):
    from neural_brdf.measured import procedural

    code = procedural.main([str(tmp_path / "mat"), *args])
    assert_one_line_error(code, capsys.readouterr().err, needle)
    assert not (tmp_path / "mat" / "textured.yaml").exists()


@pytest.mark.parametrize("args", [["--kind", "glass"], ["--size", "abc"], [], ["--bogus"]])
def test_procedural_usage_errors_are_one_line(tmp_path, capsys, args):
    from neural_brdf.measured import procedural

    out = [str(tmp_path / "mat")] if args else []
    with pytest.raises(SystemExit) as e:  # argparse's: usage and message were 4 lines
        procedural.main([*out, *args])
    assert_one_line_error(e.value.code, capsys.readouterr().err, "see --help")


def test_procedural_out_that_is_a_file_is_one_line(mi, tmp_path, capsys):
    from neural_brdf.measured import procedural

    out = tmp_path / "afile"
    out.write_text("x")
    code = procedural.main([str(out), "--size", "4"])
    assert_one_line_error(code, capsys.readouterr().err, str(out))


# ------------------------------------------------------------------ non-finite textures
def _bitmap_teacher(mi, folder: Path, bad: float) -> Path:
    """A roughplastic whose diffuse bitmap is a constant 0.5 but for one texel of ``bad``."""
    data = np.full((32, 32, 3), 0.5, dtype=np.float32)
    data[5, 7] = bad
    mi.Bitmap(data).write(str(folder / "diffuse.exr"))
    xml = folder / "teacher.xml"
    xml.write_text(
        '<bsdf version="3.0.0" type="roughplastic"><float name="alpha" value="0.3"/>'
        '<texture type="bitmap" name="diffuse_reflectance">'
        '<string name="filename" value="diffuse.exr"/></texture></bsdf>'
    )
    return xml


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_non_finite_texel_is_refused_naming_the_texture(mi, tmp_path, capsys, bad):
    from neural_brdf.measured.mitsuba import MitsubaTarget, VariesOverSurface

    xml = _bitmap_teacher(mi, tmp_path, bad)
    with pytest.raises(InputError) as e:
        MitsubaTarget(xml)
    assert not isinstance(e.value, VariesOverSurface)
    msg = str(e.value)
    assert len(msg.splitlines()) == 1 and str(xml) in msg
    assert "diffuse_reflectance" in msg and "non-finite" in msg
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: teacher.xml}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, "target.mitsuba", "teacher.xml", "non-finite")


def test_a_procedural_texture_nan_away_from_the_centre_is_refused(mi, tmp_path):
    from neural_brdf.measured.mitsuba import MitsubaTarget, VariesOverSurface

    # uv (0.5, 0.5), the first probe's, reads color0: only the probes at random uv see NaN
    xml = tmp_path / "checker.xml"
    xml.write_text(
        '<bsdf version="3.0.0" type="diffuse"><texture type="checkerboard" '
        'name="reflectance"><rgb name="color0" value="0.5, 0.5, 0.5"/>'
        '<rgb name="color1" value="nan, 0.2, 0.2"/></texture></bsdf>'
    )
    with pytest.raises(InputError, match="negative or non-finite") as e:
        MitsubaTarget(xml)
    assert not isinstance(e.value, VariesOverSurface) and str(xml) in str(e.value)


# ------------------------------------------------------------------ a sampler that raises
def test_a_normal_map_of_one_channel_is_one_line(mi, tmp_path, capsys):
    # Mitsuba's sampler raises on it (eval_3 of a monochromatic bitmap) with a 12-line dump
    # of the texture: it escaped the probes as a traceback
    data = np.random.default_rng(0).random((8, 8, 1)).astype(np.float32)
    mi.Bitmap(data).write(str(tmp_path / "grey.exr"))
    (tmp_path / "nm.xml").write_text(
        '<bsdf version="3.0.0" type="normalmap"><texture type="bitmap" name="normalmap">'
        '<string name="filename" value="grey.exr"/><boolean name="raw" value="true"/>'
        '</texture><bsdf type="roughplastic"/></bsdf>'
    )
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: nm.xml}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    # the object's dump shortened, so that Mitsuba's sentence after it is kept
    assert_one_line_error(code, err, "nm.xml", "cannot evaluate", "[...]", "monochromatic")


# ------------------------------------------------------------------ a teacher walkthrough
@pytest.mark.parametrize(
    "xml",
    [
        '<bsdf version="3.0.0" type="diffuse"><rgb name="reflectance" value="0, 0, 0"/></bsdf>',
        '<bsdf version="3.0.0" type="diffuse"><texture type="mesh_attribute" '
        'name="reflectance"><string name="name" value="vertex_color"/></texture></bsdf>',
    ],
    ids=["black", "mesh_attribute"],
)
def test_a_teacher_that_reflects_nothing_is_refused(mi, tmp_path, capsys, xml):
    # it trained a black file with physics PASSED, an error of 3e146 % and exit 0 (a
    # mesh_attribute texture reads 0 where the teacher is evaluated on its own)
    (tmp_path / "t.xml").write_text(xml)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: t.xml}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, "t.xml", "reflects no light")
    assert not (tmp_path / "run").exists()


def test_a_normal_map_inside_a_blend_is_refused(mi, tmp_path, capsys):
    # it trained on Mitsuba's wrapper, not reciprocal there, to a 72 % error, and the file's
    # description claimed a normal field it did not have
    data = np.zeros((8, 8, 3), np.float32)
    data[..., 0], data[..., 2] = 0.6, 1.0
    mi.Bitmap(data).write(str(tmp_path / "n.exr"))
    (tmp_path / "t.xml").write_text(
        '<bsdf version="3.0.0" type="blendbsdf"><float name="weight" value="0.5"/>'
        '<bsdf type="normalmap"><texture type="bitmap" name="normalmap">'
        '<string name="filename" value="n.exr"/><boolean name="raw" value="true"/></texture>'
        '<bsdf type="roughplastic"/></bsdf><bsdf type="diffuse"/></bsdf>'
    )
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: t.xml}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, "t.xml", "normalmap inside", "move it outside")


def test_a_bump_map_teacher_warns_that_its_relief_depends_on_the_mesh(mi, tmp_path):
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    # three channels: a normal map's (x, y, z) near +z, a bump map's height its luminance
    h = np.random.default_rng(1).random((8, 8, 1)).astype(np.float32)
    mi.Bitmap((np.repeat(h, 3, -1) * 0.2 + [0.4, 0.4, 0.8]).astype(np.float32)).write(
        str(tmp_path / "h.exr")
    )
    wrapped = '<bsdf type="roughplastic"/>'
    for plugin, texture in [("bumpmap", ""), ("normalmap", ' name="normalmap"')]:
        (tmp_path / f"{plugin}.xml").write_text(
            f'<bsdf version="3.0.0" type="{plugin}"><texture type="bitmap"{texture}>'
            '<string name="filename" value="h.exr"/><boolean name="raw" value="true"/>'
            f"</texture>{wrapped}</bsdf>"
        )
    bump = TexturedMitsubaTarget(tmp_path / "bumpmap.xml")
    assert any("relief depends on the mesh" in w for w in bump.warnings), bump.warnings
    normal = TexturedMitsubaTarget(tmp_path / "normalmap.xml")
    assert not any("relief depends on the mesh" in w for w in normal.warnings)


# ------------------------------------------------------------------ a delta lobe in all but name
@pytest.mark.parametrize(
    "plugin, name, alpha",
    [
        ("roughplastic", "alpha", "0"),
        ("roughconductor", "alpha", "-0.3"),
        # principled's roughness 0 reached only f cos ~1e4 at the probes and trained to a
        # 99.9 % error with physics PASSED and exit code 0
        ("principled", "roughness", "0"),
    ],
)
def test_a_rough_plugin_at_roughness_zero_is_refused(mi, tmp_path, capsys, plugin, name, alpha):
    # Mitsuba clamps alpha near 1e-4: f cos reached 7e7 to 9e7 at the sampled directions,
    # and the run trained with a 100 % error and exit code 0
    xml = tmp_path / "sharp.xml"
    xml.write_text(
        f'<bsdf version="3.0.0" type="{plugin}"><float name="{name}" value="{alpha}"/></bsdf>'
    )
    cfg = tmp_path / "c.yaml"
    cfg.write_text("target: {mitsuba: sharp.xml}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, "target.mitsuba", str(xml), "nearly delta", "roughness")


def test_a_sharp_but_rough_lobe_is_kept(mi, tmp_path):
    from neural_brdf.measured.mitsuba import MitsubaTarget

    xml = tmp_path / "sharp.xml"  # alpha 1e-3: f cos up to ~1e6 at the probes
    xml.write_text(
        '<bsdf version="3.0.0" type="roughconductor"><float name="alpha" value="0.001"/></bsdf>'
    )
    MitsubaTarget(xml)


def _alpha_teacher(mi, folder: Path, alpha: np.ndarray, name: str) -> Path:
    """A roughconductor whose alpha is the bitmap ``name`` (raw) of ``alpha`` [rows, cols]:
    an 8-bit PNG or a float EXR, by the name's suffix."""
    rgb = np.repeat(alpha[..., None], 3, -1).astype(np.float32)
    if name.endswith(".png"):  # written now, not in a thread
        mi.util.write_bitmap(str(folder / name), rgb, write_async=False)
    else:
        mi.Bitmap(rgb).write(str(folder / name))
    xml = folder / f"{Path(name).stem}.xml"
    xml.write_text(
        '<bsdf version="3.0.0" type="roughconductor"><texture type="bitmap" name="alpha">'
        f'<string name="filename" value="{name}"/><boolean name="raw" value="true"/>'
        "</texture></bsdf>"
    )
    return xml


@pytest.mark.parametrize("layout", ["quadrant", "scattered"])
def test_a_roughness_bitmap_with_texels_at_zero_is_refused(mi, tmp_path, capsys, layout):
    # a quarter of a 16² PNG's texels at 0: the probe at uv 0.5 saw a rough lobe, and the run
    # trained to a 100 % error with physics PASSED and exit code 0.  Scattered, a zero texel
    # is ~0 only near its centre, where no probe looks: the bitmap itself is read
    from neural_brdf.measured.mitsuba import VariesOverSurface
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    alpha = np.full((16, 16), 0.3)
    if layout == "quadrant":
        alpha[:8, :8] = 0.0
    else:
        alpha[::2, ::2] = 0.0
    xml = _alpha_teacher(mi, tmp_path, alpha, "alpha.png")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"target: {{mitsuba: {xml.name}}}\n")
    run = tmp_path / "run"
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(run), *SETS, *TEXTURED_SETS)
    assert_one_line_error(code, err, "target.mitsuba", str(xml), "alpha", "roughness of 0")
    assert "64 of 256 texels" in err  # texels, not channels
    assert not (run / "model.onnx").exists()
    with pytest.raises(InputError) as e:  # built on its own (the viewer's --compare)
        TexturedMitsubaTarget(xml)
    assert not isinstance(e.value, VariesOverSurface) and str(xml) in str(e.value)
    # its twin with a sharp but rough floor (alpha 1e-3: f cos up to ~1e6) is taken
    alpha[alpha == 0.0] = 1e-3
    assert TexturedMitsubaTarget(_alpha_teacher(mi, tmp_path, alpha, "sharp.exr")).plugin


def test_a_procedural_roughness_of_zero_away_from_the_centre_is_refused(mi, tmp_path):
    # uv (0.5, 0.5) reads color1 (rough): only f cos at other uv, wo drawn from the sampler
    # there, sees the delta lobe (pairs drawn at uv 0.5 miss it)
    from neural_brdf.measured.mitsuba import MitsubaTarget, VariesOverSurface
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    xml = tmp_path / "checker.xml"
    xml.write_text(
        '<bsdf version="3.0.0" type="roughconductor"><texture type="checkerboard" '
        'name="alpha"><float name="color0" value="0"/><float name="color1" value="0.3"/>'
        "</texture></bsdf>"
    )
    for build in (MitsubaTarget, TexturedMitsubaTarget):
        with pytest.raises(InputError) as e:
            build(xml)
        msg = str(e.value)
        assert not isinstance(e.value, VariesOverSurface), msg
        assert len(msg.splitlines()) == 1 and str(xml) in msg
        assert "nearly delta" in msg and "at uv (" in msg and "roughness" in msg


# ------------------------------------------------------------------ view --uv
def test_a_uv_too_large_for_float32_is_refused(textured_run, tmp_path, capsys):
    from neural_brdf.viewer import page

    # float32(16777216.25) is 16777216: the plots were drawn at u = 0, labelled 1.68e+07
    assert np.float32(16777216.25) % 1 == 0
    assert page.parse_probes(["-1024,1024", "0.3,0.7"]) == ((-1024.0, 1024.0), (0.3, 0.7))
    with pytest.raises(InputError, match=r"^--uv 16777216.25,0.5: .*1024"):
        page.parse_probes(["16777216.25,0.5"])
    run, _ = textured_run
    out = tmp_path / "v.html"
    code, _, err = cli(capsys, "view", str(run / "model.onnx"), "--uv=0.5,-3e9", "-o", str(out))
    assert_one_line_error(code, err, "--uv 0.5,-3e9")
    assert not out.exists()


# ------------------------------------------------------------------ a teacher changed kind
class _Teacher:
    def __init__(self, varying: bool):
        self.spatially_varying = varying

    def describe(self) -> str:
        return "a teacher"


def test_check_textured_refuses_either_mismatch():
    from neural_brdf.target import check_textured

    check_textured(None, textured=True, where="x")
    check_textured(_Teacher(True), textured=True, where="x")
    check_textured(_Teacher(False), textured=False, where="x")
    with pytest.raises(InputError, match=r"^run/ckpt.pt: a textured model.*does not vary"):
        check_textured(_Teacher(False), textured=True, where="run/ckpt.pt")
    with pytest.raises(InputError, match=r"^run/model.onnx: a uniform model.* varies over"):
        check_textured(_Teacher(True), textured=False, where="run/model.onnx")


@pytest.fixture(scope="module")
def textured_run(mi, tmp_path_factory) -> tuple[Path, Path]:
    """(run folder, teacher.xml) of a 2-step textured run."""
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.tooling.cli import main

    folder = tmp_path_factory.mktemp("textured")
    xml = write_teacher(folder / "mat", "roughplastic", size=4)
    cfg = folder / "mat" / "c.yaml"
    cfg.write_text("target: {mitsuba: teacher.xml}\n")
    run = folder / "run"
    assert main(["train", str(cfg), "--out", str(run), *SETS, *TEXTURED_SETS]) == 0
    return run, xml


def test_an_xml_where_a_config_is_expected_says_so(textured_run, tmp_path, capsys):
    from neural_brdf import validate

    run, xml = textured_run
    with pytest.raises(InputError, match=r"^--reference .*teacher.xml: .*mitsuba: teacher.xml"):
        validate.reference_from(xml)  # was "expected a mapping of keys at the top level"
    code, _, err = cli(capsys, "validate", str(run / "model.onnx"), "--reference", str(xml))
    assert_one_line_error(code, err, "--reference", str(xml), "config")
    out = str(tmp_path / "r.png")
    code, _, err = cli(
        capsys, "render", str(run / "model.onnx"), "--reference", str(xml), "-o", out
    )
    assert_one_line_error(code, err, str(xml), "analytic target", "view")
    code, _, err = cli(capsys, "bake", str(xml), "-o", str(tmp_path / "b.binary"))
    assert_one_line_error(code, err, str(xml), "analytic target")


def test_export_and_report_refuse_a_textured_run_whose_teacher_became_uniform(textured_run, capsys):
    run, xml = textured_run
    before = (run / "model.onnx").read_bytes()
    teacher = xml.read_text()
    xml.write_text(UNIFORM)  # the same path, now a uniform material
    try:
        code, _, err = cli(capsys, "export", str(run))
        assert_one_line_error(code, err, str(run / "ckpt.pt"), "textured model", "does not vary")
        assert (run / "model.onnx").read_bytes() == before  # nothing written
        code, _, err = cli(capsys, "report", str(run))
        assert_one_line_error(code, err, str(run / "model.onnx"), "does not vary")
    finally:
        xml.write_text(teacher)


# ------------------------------------------------------------------ an edited config.yaml
@pytest.mark.parametrize(
    "old, new, key",
    [
        ("  grazing_power: 1.0\n", "  grazing_power: 3.0\n", "model.grazing_power"),  # silent
        ("  lobes: 2\n", "  lobes: 3\n", "texture.lobes"),  # a ValueError's traceback
        ("  resolution: 4\n", "  resolution: 8\n", "texture.resolution"),  # torch's
    ],
    ids=["grazing_power", "lobes", "resolution"],
)
def test_export_refuses_a_config_yaml_edited_away_from_its_checkpoint(
    textured_run, tmp_path, capsys, old, new, key
):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(textured_run[0], run)
    text = (run / "config.yaml").read_text()
    assert text.count(old) == 1
    (run / "config.yaml").write_text(text.replace(old, new))
    before = (run / "model.onnx").read_bytes()
    code, _, err = cli(capsys, "export", str(run))
    assert_one_line_error(code, err, key, str(run / "config.yaml"), "differs from the checkpoint")
    assert (run / "model.onnx").read_bytes() == before


def test_export_takes_an_edited_validation_setting(textured_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(textured_run[0], run)
    text = (run / "config.yaml").read_text()
    assert text.count("  validation_uv: 4\n") == 1
    (run / "config.yaml").write_text(text.replace("  validation_uv: 4\n", "  validation_uv: 6\n"))
    code, _, err = cli(capsys, "export", str(run))
    assert code == 0, err


@pytest.mark.parametrize("value", [0, 4097, 10**12])
def test_a_furnace_of_too_few_or_too_many_uv_is_refused_naming_the_key(value):
    """texture.validation_uv is a furnace quadrature per uv: 10^12 of them ran out of
    memory at export without naming the key, 10^5 would run for hours."""
    from neural_brdf import config as cfgmod

    with pytest.raises(cfgmod.ConfigError, match=r"texture\.validation_uv"):
        cfgmod.from_dict({"texture": {"validation_uv": value}})
    assert cfgmod.from_dict({"texture": {"validation_uv": 4096}}).texture.validation_uv == 4096
