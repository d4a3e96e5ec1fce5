"""Bad and unusual inputs of an images fit (target.images), llvm_ad_rgb.

* an images config where a reference BRDF is expected (``bake CONFIG``, ``render
  --reference``, ``validate --reference``) exits 2 in one line naming the file and
  ``target.images`` (its ``target.model`` is the unused default Lambertian, which was
  baked, rendered and validated against);
* a target image that holds no light (all black, all negative) exits 2 in one line; the
  negative-pixel warning gives its share as a plain percentage ("100 %", not "1e+02 %");
* one image file given to two entries with different scenes (under any spelling, a
  link too) exits 2 naming both entries; a flash/no-flash pair whose ``subtract`` is
  another entry's image is fitted as before;
* the scene checks read the scene as Mitsuba does: a ``<bsdf id="fit">`` in an
  ``<include>`` (nested, relative to the including file) and an integrator type from a
  ``<default>`` are accepted, and the fit renders its own BSDF in the included slot (the
  render equals that of the same scene written in one file); an unknown integrator given
  through a ``<default>``, an undefined ``$name`` and a file that includes itself exit 2
  in one line;
* a folder given as an image or a scene says so, and an empty ``subtract`` says it is
  empty.

The views are generated here (neural_brdf.inverse.scene, 16 x 16) in a temporary folder.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from neural_brdf import config
from neural_brdf.tooling import cli

pytestmark = pytest.mark.mitsuba

RES = 16


@pytest.fixture(scope="module")
def example(mi, tmp_path_factory) -> Path:
    from neural_brdf.inverse import scene as inverse_example

    folder = tmp_path_factory.mktemp("views")
    inverse_example.write(folder, resolution=RES, spp=16, steps=2)
    return folder


@pytest.fixture
def copy_of(example, tmp_path) -> Path:
    for p in example.iterdir():
        shutil.copy(p, tmp_path / p.name)
    return tmp_path


def _config(folder: Path, entries: list[str], name: str = "q.yaml") -> Path:
    """A config of ``entries`` (each the inside of one target.images {...})."""
    lines = ["target:", "  images:"] + [f"    - {{{e}}}" for e in entries]
    path = folder / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _one_line_exit_2(args: list[str], capsys, *needles: str) -> str:
    code = cli.main(args)
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [s for s in err.strip().splitlines() if s.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _train_exits_2(path: Path, capsys, *needles: str) -> str:
    out = path.parent / "run"
    line = _one_line_exit_2(["train", str(path), "--out", str(out)], capsys, *needles)
    assert not (out / "ckpt.pt").exists()
    return line


def _image(mi, path: Path) -> np.ndarray:
    return np.array(mi.Bitmap(str(path)), np.float32)[..., :3]


# ------------------------------------------------------------------ 1: no reference BRDF
def test_an_images_config_is_no_reference_brdf(copy_of, tiny_run, capsys):
    q = _config(copy_of, ["scene: view1.xml, image: view1.exr"])
    model = str(tiny_run / "model.onnx")
    for args in (
        ["bake", str(q), "-o", str(copy_of / "baked.bsdf")],
        ["render", model, "--reference", str(q), "--spp", "1", "-o", str(copy_of / "r.png")],
        ["validate", model, "--reference", str(q)],
    ):
        _one_line_exit_2(args, capsys, f"{q}: target.images:", "no target BRDF")
    assert not (copy_of / "baked.bsdf").exists() and not (copy_of / "r.png").exists()


# ------------------------------------------------------------------ 2: no light
def test_a_target_without_light_exits_2(mi, copy_of, capsys):
    from neural_brdf.inverse import scene as inverse_example

    img = _image(mi, copy_of / "view1.exr")
    assert img.max() > 0
    inverse_example.write_exr(copy_of / "black.exr", np.zeros_like(img))
    inverse_example.write_exr(copy_of / "allneg.exr", -np.abs(img) - 0.1)
    for name in ("black.exr", "allneg.exr"):
        q = _config(
            copy_of, ["scene: view1.xml, image: view1.exr", f"scene: view2.xml, image: {name}"]
        )
        _train_exits_2(q, capsys, "target.images[1].image", name, "holds no light")


def test_the_negative_pixel_warning_gives_a_plain_percentage(mi, copy_of, capsys):
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as inverse_example

    img = _image(mi, copy_of / "view1.exr")
    every = img.copy()
    every[..., 0] = -0.01  # every pixel has a negative channel; the image holds light
    some = img.copy()
    some[:3, :1, 0] = -0.01  # 3 of the 256 pixels
    for name, value, n in (("every.exr", every, RES * RES), ("some.exr", some, 3)):
        inverse_example.write_exr(copy_of / name, value)
        cfg = config.load(_config(copy_of, [f"scene: view1.xml, image: {name}"]))
        capsys.readouterr()
        inverse.read_views(cfg)
        (line,) = capsys.readouterr().err.strip().splitlines()
        shown = re.search(r"\(([^()]*) %\)", line)
        assert shown and re.fullmatch(r"\d+(\.\d+)?", shown.group(1)), line
        share = 100.0 * n / (RES * RES)
        assert abs(float(shown.group(1)) - share) <= 0.05 * max(share, 1.0), (line, share)
        if n == RES * RES:
            assert "(100 %)" in line, line


# ------------------------------------------------------------------ 3: one image, two scenes
def test_one_image_for_two_scenes_exits_2_but_a_flash_pair_does_not(mi, copy_of, capsys):
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as inverse_example

    q = _config(
        copy_of, ["scene: view1.xml, image: view1.exr", "scene: view2.xml, image: view1.exr"]
    )
    _train_exits_2(q, capsys, "target.images[1]", "target.images[0]", "view1.exr")
    os.symlink(copy_of / "view1.exr", copy_of / "alias.exr")  # another name, the same file
    q = _config(
        copy_of, ["scene: view1.xml, image: view1.exr", "scene: view2.xml, image: alias.exr"]
    )
    _train_exits_2(q, capsys, "target.images[1]", "target.images[0]")
    # the documented flash/no-flash pair: another entry's image as the photograph without
    # the flash is no slip
    inverse_example.write_exr(copy_of / "flash1.exr", 2.0 * _image(mi, copy_of / "view1.exr"))
    q = _config(
        copy_of,
        [
            "scene: view1.xml, image: view1.exr",
            "scene: view2.xml, image: view2.exr",
            "scene: view1.xml, image: flash1.exr, subtract: view1.exr",
        ],
    )
    assert len(inverse.read_views(config.load(q))) == 3


# ------------------------------------------------------------------ 4: scenes as Mitsuba reads them
FIT = re.compile(r'<bsdf type="roughconductor" id="fit">.*?</bsdf>', re.S)


@pytest.mark.parametrize("root", ["scene", "bsdf"])
def test_a_fit_bsdf_in_an_include_is_found_and_replaced(mi, copy_of, root):
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import views

    text = (copy_of / "view1.xml").read_text()
    bsdf = FIT.search(text).group(0)
    (copy_of / "parts").mkdir()
    # nested: parts/mat.xml includes fit.xml beside it (relative to the including file),
    # whose root is a <scene> holding the BSDF, or the BSDF itself (with the version
    # every file's root carries, which Mitsuba refuses inside a scene: dropped inlined)
    inner = (
        f'<scene version="3.0.0">\n{bsdf}\n</scene>\n'
        if root == "scene"
        else bsdf.replace("<bsdf ", '<bsdf version="3.0.0" ', 1)
    )
    (copy_of / "parts" / "fit.xml").write_text(inner)
    (copy_of / "parts" / "mat.xml").write_text(
        '<scene version="3.0.0">\n<include filename="fit.xml"/>\n</scene>\n'
    )
    (copy_of / "include.xml").write_text(text.replace(bsdf, '<include filename="parts/mat.xml"/>'))
    assert mi.load_file(str(copy_of / "include.xml"))  # a valid scene for Mitsuba
    q = _config(copy_of, ["scene: include.xml, image: view1.exr"])
    (view,) = inverse.read_views(config.load(q))
    q = _config(copy_of, ["scene: view1.xml, image: view1.exr"], "plain.yaml")
    (plain,) = inverse.read_views(config.load(q))
    assert view.integrator == plain.integrator
    views.check_films([view])  # the scene as the fit loads it: text of the expanded tree
    # the fit renders its BSDF in the included slot, not the included copper
    diffuse = views.bsdf_element("diffuse", reflectance=[0.2, 0.5, 0.8])
    got = views.render_view(view, diffuse, spp=4, seed=3)
    want = views.render_view(plain, diffuse, spp=4, seed=3)
    copper = views.render_view(plain, views.fit_element(plain.tree), spp=4, seed=3)
    assert not np.allclose(want, copper, rtol=1e-2)
    # the same scene, not bit for bit: the film's filter splats a sample into several
    # pixels with atomic adds, whose order across Dr.Jit's threads varies between renders
    # (CI saw last-bit differences), so equal to float32 rounding of a few sums
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)


def test_an_integrator_from_a_default_is_read_as_mitsuba_reads_it(mi, copy_of, capsys):
    from neural_brdf.inverse import views

    text = (copy_of / "view1.xml").read_text()
    start = '<integrator type="path">'
    assert text.count(start) == 1

    def scene(name: str, value: str, ref: str = "$integ") -> Path:
        head = f'<default name="integ" value="{value}"/>\n<integrator type="{ref}">'
        (copy_of / name).write_text(text.replace(start, head))
        return copy_of / name

    path = scene("defint.xml", "path")
    assert mi.load_file(str(path))
    _, integrator = views.read_scene(path, "test")
    assert integrator == views.read_scene(copy_of / "view1.xml", "test")[1]
    # the checks still refuse what they refused, given through a parameter
    q = _config(copy_of, [f"scene: {scene('volpath.xml', 'volpath').name}, image: view1.exr"])
    _train_exits_2(q, capsys, "volpath.xml", "integrator 'volpath'")
    q = _config(copy_of, [f"scene: {scene('undef.xml', 'path', '$nope').name}, image: view1.exr"])
    _train_exits_2(q, capsys, "undef.xml", "undefined parameter $nope")


def test_a_scene_that_includes_itself_exits_2(copy_of, capsys):
    text = (copy_of / "view1.xml").read_text()
    (copy_of / "loop.xml").write_text(
        text.replace("</scene>", '<include filename="loop.xml"/>\n</scene>')
    )
    q = _config(copy_of, ["scene: loop.xml, image: view1.exr"])
    _train_exits_2(q, capsys, "loop.xml", "nested includes")
    (copy_of / "gone.xml").write_text(
        text.replace("</scene>", '<include filename="no.xml"/>\n</scene>')
    )
    q = _config(copy_of, ["scene: gone.xml, image: view1.exr"])
    _train_exits_2(q, capsys, "gone.xml", "no.xml", "no such file")


@pytest.mark.parametrize(
    "version, needle",
    [
        (None, "missing version attribute"),
        ("0.6.0", "older than 2.0.0"),
        ("2.0", "not a version such as 3.0.0"),
    ],
    ids=["no version", "an older format", "two numbers"],
)
def test_an_include_mitsuba_reads_otherwise_exits_2(mi, copy_of, capsys, version, needle):
    """An included file without a version (Mitsuba refuses it), or in a format older
    than 2.0.0 in a 3.0.0 scene (Mitsuba upgrades that file alone, renaming alphaU to
    alpha_u; inlined into the scene it would not be): one line, exit 2, naming it."""
    text = (copy_of / "view1.xml").read_text()
    bsdf = FIT.search(text).group(0)
    head = "<bsdf " if version is None else f'<bsdf version="{version}" '
    (copy_of / "mat.xml").write_text(bsdf.replace("<bsdf ", head, 1))
    (copy_of / "inc.xml").write_text(text.replace(bsdf, '<include filename="mat.xml"/>'))
    if version is None or version == "2.0":  # Mitsuba refuses both
        with pytest.raises(RuntimeError, match="missing version|invalid version"):
            mi.load_file(str(copy_of / "inc.xml"))
    else:
        assert mi.load_file(str(copy_of / "inc.xml"))  # Mitsuba upgrades the include alone
    q = _config(copy_of, ["scene: inc.xml, image: view1.exr"])
    _train_exits_2(q, capsys, "inc.xml", "mat.xml", needle)


# ------------------------------------------------------------------ 5: messages
def test_a_folder_or_an_empty_path_is_named_as_such(copy_of, capsys):
    (copy_of / "adir.exr").mkdir()
    (copy_of / "adir.xml").mkdir()
    q = _config(copy_of, ["scene: view1.xml, image: adir.exr"])
    _train_exits_2(q, capsys, "target.images[0].image", "adir.exr", "is a folder, not a file")
    q = _config(copy_of, ["scene: adir.xml, image: view1.exr"])
    _train_exits_2(q, capsys, "target.images[0].scene", "adir.xml", "is a folder, not a file")
    q = _config(
        copy_of,
        ["scene: view1.xml, image: view1.exr", 'scene: view2.xml, image: view2.exr, subtract: ""'],
    )
    _train_exits_2(q, capsys, "target.images[1].subtract: empty")
