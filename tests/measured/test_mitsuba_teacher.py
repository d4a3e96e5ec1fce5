"""A Mitsuba BSDF as the teacher: ``target: {mitsuba: FILE.xml}`` (neural_brdf/measured/mitsuba.py,
issue 30 item 1, the homogeneous part).

* the teacher's f is Mitsuba's own eval / cos(theta_o) (0 below the horizon), Lambertian
  reflectance / pi for a ``diffuse``; its sampler is Mitsuba's, with a pdf that matches;
* ``twosided`` is unwrapped to its front BSDF; anisotropy is probed;
* a dielectric, a smooth conductor, a smooth plastic and textured BSDFs (bitmap,
  checkerboard) are refused through ``neural-brdf train`` with one line naming the file;
* ``principled`` at base colour 1, roughness 0.5 exceeds albedo 1: the bounded teacher
  stays within 1, its divisor is symmetric bit for bit, and the description says where;
* a short run trains from an XML file, and validate scores the model against the teacher;
* the config key (relative paths, exclusivity, variants) and the lazy import need no
  Mitsuba.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import analytic
from cli_helpers import ROOT, SETS, assert_one_line_error, cli
from neural_brdf import config

ROUGHPLASTIC = """<bsdf version="3.0.0" type="roughplastic">
    <string name="distribution" value="ggx"/>
    <float name="alpha" value="0.2"/>
    <rgb name="diffuse_reflectance" value="0.1, 0.3, 0.6"/>
</bsdf>"""
PRINCIPLED = """<bsdf version="3.0.0" type="principled">
    <rgb name="base_color" value="1, 1, 1"/>
    <float name="roughness" value="0.5"/>
</bsdf>"""


def write(folder: Path, name: str, xml: str) -> Path:
    path = folder / name
    path.write_text(xml)
    return path


def teacher_config(folder: Path, xml_name: str) -> Path:
    """A config beside the XML, naming it by a relative path."""
    path = folder / f"{Path(xml_name).stem}.yaml"
    path.write_text(f"target:\n  mitsuba: {xml_name}\n")
    return path


def hemisphere(n: int, seed: int) -> np.ndarray:
    return analytic.physics.random_directions(n, seed)


# ------------------------------------------------------------------ no Mitsuba needed
def test_the_config_key_is_relative_to_the_config_file_and_alone(tmp_path):
    cfg = config.load(teacher_config(tmp_path, "m.xml"))
    assert cfg.target.mitsuba == str(tmp_path / "m.xml")
    assert config.load(None, ["target.mitsuba=/abs/m.xml"]).target.mitsuba == "/abs/m.xml"
    ok = config.load(None, ["target.mitsuba=/abs/m.xml", "target.variant=cuda_ad_rgb"])
    assert ok.target.variant == "cuda_ad_rgb"
    for clash in ("target.data=x.binary", "target.model=microfacet", "target.params={alpha: 1}"):
        with pytest.raises(config.ConfigError, match="target.mitsuba alone"):
            config.load(None, ["target.mitsuba=m.xml", clash])
    with pytest.raises(config.ConfigError, match="mitsuba: empty path"):
        config.load(None, ["target.mitsuba=' '"])


def test_a_non_rgb_variant_is_one_line(tmp_path, capsys):
    cfg = teacher_config(tmp_path, "m.xml")
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(tmp_path / "run"),
        "--set", "target.variant=scalar_spectral", *SETS,
    )  # fmt: skip
    assert_one_line_error(code, err, "target.variant", "scalar_spectral")


def test_a_missing_file_is_one_line_naming_it(tmp_path, capsys):
    cfg = teacher_config(tmp_path, "nowhere.xml")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, "target.mitsuba", "nowhere.xml", "no such file")
    (tmp_path / "a_folder").mkdir()  # said to be a folder, not "no such file"
    cfg = teacher_config(tmp_path, "a_folder")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, "target.mitsuba", "a_folder", "is a folder")


def test_nothing_but_a_mitsuba_teacher_imports_mitsuba(tmp_path):
    code = (
        "import sys\n"
        "from neural_brdf import config, validate, pipeline\n"
        "from neural_brdf.train import data\n"
        f"config.load({str(teacher_config(tmp_path, 'm.xml'))!r})\n"
        "data.build_target(config.load(None).target)\n"
        "assert 'mitsuba' not in sys.modules, 'mitsuba loaded'\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


# ------------------------------------------------------------------ Mitsuba
@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("teachers")


@pytest.fixture(scope="module")
def roughplastic(mi, folder):
    from neural_brdf.measured.mitsuba import MitsubaTarget

    return MitsubaTarget(write(folder, "roughplastic.xml", ROUGHPLASTIC))


@pytest.fixture(scope="module")
def principled(mi, folder):
    from neural_brdf.measured.mitsuba import MitsubaTarget

    return MitsubaTarget(write(folder, "principled.xml", PRINCIPLED))


def mitsuba_f(mi, xml: str, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Mitsuba's eval / cos(theta_o), computed here on its own."""
    import drjit as dr

    bsdf = mi.load_string(xml)
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(np.ascontiguousarray(wi.T, dtype=np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    value = bsdf.eval(
        mi.BSDFContext(), si, mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32))
    )
    return np.array(value, dtype=np.float64).T / wo[:, 2:3]


@pytest.mark.mitsuba
def test_eval_is_mitsubas_eval_over_the_cosine(mi, roughplastic, folder):
    from neural_brdf.measured.mitsuba import MitsubaTarget

    wi, wo = hemisphere(4000, 1), hemisphere(4000, 2)
    mine = roughplastic.eval(wi, wo)
    np.testing.assert_allclose(mine, mitsuba_f(mi, ROUGHPLASTIC, wi, wo), rtol=1e-6, atol=0)
    assert roughplastic.excess is None  # within 1: not bounded, f is the teacher's own
    assert np.array_equal(mine, roughplastic.teacher(wi, wo))
    torch_f = roughplastic.f(torch.from_numpy(wi), torch.from_numpy(wo))
    assert torch_f.dtype == torch.float64 and np.array_equal(torch_f.numpy(), mine)
    below = wo * np.array([1.0, 1.0, -1.0])
    assert np.all(roughplastic.eval(wi, below) == 0) and np.all(roughplastic.eval(below, wo) == 0)
    diffuse = MitsubaTarget(
        write(
            folder,
            "diffuse.xml",
            '<bsdf version="3.0.0" type="diffuse">'
            '<rgb name="reflectance" value="0.2, 0.5, 0.8"/></bsdf>',
        )
    )
    np.testing.assert_allclose(
        diffuse.eval(wi, wo), np.tile([0.2, 0.5, 0.8], (len(wi), 1)) / math.pi, rtol=1e-6
    )
    assert not diffuse.anisotropic and diffuse.excess is None


@pytest.mark.mitsuba
def test_the_sampler_is_mitsubas_with_a_matching_pdf(roughplastic):
    from neural_brdf.physics import quadrature

    # wo ~ sample_dir_t has the density pdf_t: the importance estimate of the albedo
    # agrees with a quadrature that does not use the teacher's sampler
    n = 1 << 16
    t = math.radians(50.0)
    wi = torch.tensor([[math.sin(t), 0.0, math.cos(t)]], dtype=torch.float64)
    u = torch.rand(n, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    wo = roughplastic.sample_dir_t(wi.expand(n, 3), u)
    assert wo.shape == (n, 3) and torch.equal(wo, roughplastic.sample_dir_t(wi.expand(n, 3), u))
    pdf = roughplastic.pdf_t(wi.expand(n, 3), wo)
    live = (wo[:, 2] > 0) & (pdf > 0)
    assert live.float().mean() > 0.95
    w = roughplastic.f(wi.expand(n, 3), wo) * (wo[:, 2] / pdf.clamp_min(1e-300))[:, None]
    estimate = torch.where(live[:, None], w, 0.0).mean(0)
    reference, err = quadrature.albedo(quadrature.from_numpy(roughplastic.teacher), wi, 1 << 16)
    np.testing.assert_allclose(estimate.numpy(), reference[0].numpy(), rtol=0.01)
    assert torch.all(roughplastic.pdf_t(wi.expand(4, 3), -wo[:4]) == 0)


@pytest.mark.mitsuba
def test_twosided_is_unwrapped_to_its_front_bsdf(mi, roughplastic, folder):
    from neural_brdf.measured.mitsuba import MitsubaTarget

    front = ROUGHPLASTIC.replace('<bsdf version="3.0.0" ', "<bsdf ")
    back = '<bsdf type="diffuse"><rgb name="reflectance" value="0.9, 0.1, 0.1"/></bsdf>'
    wrapped = MitsubaTarget(
        write(folder, "twosided.xml", f'<bsdf version="3.0.0" type="twosided">{front}{back}</bsdf>')
    )
    wi, wo = hemisphere(3000, 3), hemisphere(3000, 4)
    assert np.array_equal(wrapped.eval(wi, wo), roughplastic.eval(wi, wo))
    assert "twosided" in wrapped.describe() and "RoughPlastic" in wrapped.describe()
    u = torch.rand(3000, 2, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    w = torch.from_numpy(wi)
    assert torch.equal(wrapped.sample_dir_t(w, u), roughplastic.sample_dir_t(w, u))


@pytest.mark.mitsuba
def test_anisotropy_is_probed(mi, roughplastic, folder):
    from neural_brdf.measured.mitsuba import MitsubaTarget

    brushed = MitsubaTarget(
        write(
            folder,
            "brushed.xml",
            '<bsdf version="3.0.0" type="roughconductor">'
            '<float name="alpha_u" value="0.1"/><float name="alpha_v" value="0.3"/></bsdf>',
        )
    )
    assert brushed.anisotropic and not roughplastic.anisotropic
    assert "anisotropic" in brushed.describe()


def _bitmap(mi, folder: Path, *, one_texel: bool = False) -> str:
    """A bitmap texture file in ``folder``: random texels, or (``one_texel``) 256 x 256
    uniform ones but one, which random probes of the surface would all but miss."""
    if one_texel:
        texels = np.full((256, 256, 3), 0.5, dtype=np.float32)
        texels[100, 37] = 0.9
    else:
        texels = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    mi.Bitmap(texels).write(str(folder / "albedo.exr"))
    return (
        '<texture type="bitmap" name="diffuse_reflectance">'
        '<string name="filename" value="albedo.exr"/></texture>'
    )


REFUSED = {
    "dielectric": ('<bsdf version="3.0.0" type="dielectric"/>', "transmits"),
    "conductor": ('<bsdf version="3.0.0" type="conductor"/>', "delta-only"),
    "plastic": ('<bsdf version="3.0.0" type="plastic"/>', "delta lobe"),
    "unknown_plugin": ('<bsdf version="3.0.0" type="roughplastik"/>', "Mitsuba cannot load it"),
}


# teachers that vary over the surface: MitsubaTarget (homogeneous) refuses them, and the
# config's target builds a textured teacher instead (tests/train/test_textured_pipeline.py
# trains one)
VARYING = {
    "bitmap": (
        '<bsdf version="3.0.0" type="twosided"><bsdf type="roughplastic">{bitmap}</bsdf></bsdf>'
    ),
    "one_texel": '<bsdf version="3.0.0" type="roughplastic">{one_texel}</bsdf>',
    "checkerboard": (
        '<bsdf version="3.0.0" type="diffuse">'
        '<texture type="checkerboard" name="reflectance"/></bsdf>'
    ),
}


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", list(VARYING))
def test_teachers_that_vary_over_the_surface_build_a_textured_target(mi, name, tmp_path):
    from neural_brdf.measured.mitsuba import MitsubaTarget, VariesOverSurface
    from neural_brdf.measured.textured import TexturedMitsubaTarget
    from neural_brdf.train import data

    xml = VARYING[name]
    if "{bitmap}" in xml:
        xml = xml.format(bitmap=_bitmap(mi, tmp_path))
    if "{one_texel}" in xml:
        xml = xml.format(one_texel=_bitmap(mi, tmp_path, one_texel=True))
    path = write(tmp_path, f"{name}.xml", xml)
    with pytest.raises(VariesOverSurface, match="varies over the surface"):
        MitsubaTarget(path)
    cfg = config.load(teacher_config(tmp_path, f"{name}.xml"))
    target = data.build_target(cfg.target)
    assert isinstance(target, TexturedMitsubaTarget)
    assert target.spatially_varying


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", list(REFUSED))
def test_unusable_teachers_are_one_line_naming_the_file(mi, name, tmp_path, capsys):
    xml, why = REFUSED[name]
    if "{bitmap}" in xml:
        xml = xml.format(bitmap=_bitmap(mi, tmp_path))
    if "{one_texel}" in xml:
        xml = xml.format(one_texel=_bitmap(mi, tmp_path, one_texel=True))
    write(tmp_path, f"{name}.xml", xml)
    cfg = teacher_config(tmp_path, f"{name}.xml")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, str(tmp_path / f"{name}.xml"), why)


@pytest.mark.mitsuba
def test_a_principled_above_1_is_learned_bounded_and_reciprocal(principled):
    from neural_brdf.physics import quadrature

    x = principled.excess
    assert x is not None and 1.04 < x["max_albedo"] < 1.25, x
    assert f"{x['max_albedo']:.4f}" in principled.describe() and "theta_i" in principled.describe()
    # an independent quadrature, between the table's nodes too: the bounded teacher <= 1
    theta = np.radians(np.linspace(0.0, 89.7, 73))
    wi = torch.from_numpy(np.stack([np.sin(theta), 0 * theta, np.cos(theta)], -1))
    rho, err = quadrature.albedo(
        quadrature.from_numpy(principled.eval), wi, 8192, seed=21, target=principled
    )
    assert torch.all(rho <= 1.0 + 1e-3 + 3 * err), float(rho.max())
    before, _ = quadrature.albedo(
        quadrature.from_numpy(principled.teacher), wi, 8192, seed=21, target=principled
    )
    assert float(before.max()) > 1.04
    # reciprocal: the divisor is symmetric bit for bit, and the bounded f is the teacher's
    # over it, so the bound adds no asymmetry to the teacher's own
    a, b = hemisphere(20000, 8), hemisphere(20000, 9)
    assert np.array_equal(principled.bound(a, b), principled.bound(b, a))
    assert np.all(principled.bound(a, b) >= 1.0) and np.any(principled.bound(a, b) > 1.0)
    assert np.array_equal(principled.eval(a, b), principled.teacher(a, b) / principled.bound(a, b))
    assert analytic.reciprocity_error(principled.eval, seed=4) <= analytic.reciprocity_error(
        principled.teacher, seed=4
    ) * (1 + 1e-9)


@pytest.mark.mitsuba
def test_a_short_run_trains_from_a_mitsuba_xml(mi, tmp_path, capsys):
    xml = write(tmp_path, "roughplastic.xml", ROUGHPLASTIC)
    cfg = teacher_config(tmp_path, xml.name)
    run = tmp_path / "run"
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(run), *SETS)
    assert code in (0, 1), err  # 1: a physics check of the 10-step model failed
    from neural_brdf import load

    target = load(run / "model.onnx").target
    assert "Mitsuba" in target["description"] and str(xml) in target["description"], target
    assert target["kind"] == "mitsuba" and target["file"] == str(xml), target
    assert target["variant"] == "llvm_ad_rgb" and target["excess"] is None, target
    metrics = json.loads((run / "metrics.json").read_text())
    assert "Mitsuba" in metrics["reference"]
    assert 0.0 < metrics["accuracy"]["rel_rmse"] < 1.0
    code, out, err = cli(capsys, "validate", str(run / "model.onnx"), "--reference", str(cfg))
    assert code in (0, 1), err
    assert "rel_rmse" in out
    # the run's viewer draws the model beside Mitsuba's own eval of the teacher
    from neural_brdf.measured.mitsuba import MitsubaTarget
    from neural_brdf.viewer import page as viewer

    text = (run / "viewer.html").read_text()
    data = json.loads(text.split('id="nb-data">', 1)[1].split("</script>", 1)[0])
    name, table = data["models"][1]["name"], data["models"][1]["tabulated"]
    assert name == "teacher: roughplastic.xml"
    assert len(table["images"]) == len(viewer.TEACHER_LIGHTS)
    light = viewer.light_of(*viewer.TEACHER_LIGHTS[-1])
    raw = MitsubaTarget(xml).teacher
    expect = viewer.textured_radiance(lambda a, b, c: raw(a, b), None, viewer.SPHERE, light)
    inside = viewer.sphere_frames(viewer.SPHERE, light)[3]
    got = viewer.unpack_half(table["images"][-1]).reshape(-1, 3)
    assert np.abs(got - expect[inside]).max() <= 1e-3 * expect.max()


@pytest.mark.mitsuba
def test_measured_files_resolve_against_the_xml_folder_and_spectral_ones_are_refused(
    mi, tmp_path, monkeypatch, capsys
):
    from neural_brdf.measured import rgl
    from neural_brdf.measured.mitsuba import MitsubaTarget

    def lambert(wi, wo):
        return np.tile([0.2, 0.4, 0.6], (len(wi), 1)) / math.pi

    for name in ("lambert.bsdf", "lambert_spec.bsdf"):  # RGB, spectral (RGL's names)
        rgl.bake(lambert, tmp_path / name)
        xml = f'<string name="filename" value="{name}"/>'
        write(
            tmp_path,
            name.replace(".bsdf", ".xml"),
            f'<bsdf version="3.0.0" type="measured">{xml}</bsdf>',
        )
    monkeypatch.chdir(tmp_path.parent)  # not the XML's folder
    rgb = MitsubaTarget(tmp_path / "lambert.xml")
    wi, wo = (hemisphere(200, seed) for seed in (5, 6))
    inside = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)  # the table's interpolation: not at grazing
    ratio = rgb.eval(wi, wo)[inside] / lambert(wi, wo)[inside]  # Mitsuba's table lookup
    assert abs(np.median(ratio) - 1.0) < 0.02 and np.percentile(np.abs(ratio - 1), 90) < 0.1
    cfg = teacher_config(tmp_path, "lambert_spec.xml")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"), *SETS)
    assert_one_line_error(code, err, str(tmp_path / "lambert_spec.xml"), "spectral")
