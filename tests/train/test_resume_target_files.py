"""``--resume`` and the files a run's target reads (neural_brdf/train/target_files.py).

A checkpoint records the sha256 of every file its target reads (``target_files``); a
resumed run whose file changed under the same path, or is gone, stops with exit 2 and
one line naming the file, where it trained on the other file without a word before:

* the fingerprint: none for an analytic target, the file for ``target.data``, and for a
  Mitsuba XML the file, the files it includes and the files it names (an envmap, a
  spectrum; an images fit's images too), each with the sha256 of its bytes;
* a measured run (an RGL ``.bsdf``, trained a few steps): its file rewritten or gone is
  refused; unchanged, the run resumes and records it again;
* a textured run (a 16 x 16 procedural teacher): its bitmap re-written, or its XML
  edited, is refused; unchanged, it resumes;
* an images fit (its checkpoint written by the session's own ``RunFiles.state``, no
  render): a target image re-rendered, or an included file edited, is refused;
* a checkpoint of an earlier version (no ``target_files``) resumes as before, and its
  next checkpoint records them.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch

from cli_helpers import TINY, assert_one_line_error, cli
from neural_brdf import config as cfgmod
from neural_brdf import runfolder
from neural_brdf.train import loop, session, target_files
from textured_helpers import one_torch_thread, small_run_config  # noqa: F401  (autouse)

STEPS = [*TINY, "train.steps=4", "train.checkpoint_every=2"]
MORE = ["train.steps=6"]
REFUSED = "changed since the checkpoint was written (sha256 differs)"


def sets(overrides: list[str]) -> list[str]:
    return [a for kv in overrides for a in ("--set", kv)]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def saved(run: Path) -> dict:
    return torch.load(run / "ckpt.pt", map_location="cpu", weights_only=True)


# ------------------------------------------------------------------ measured data
@pytest.fixture(scope="module")
def rgl_files(tmp_path_factory) -> tuple[Path, Path]:
    """Two measured files: a rough dielectric at alpha 0.4, and at 0.6 (its replacement)."""
    import analytic
    from neural_brdf.measured import formats

    folder = tmp_path_factory.mktemp("rgl")
    paths = (folder / "a.bsdf", folder / "b.bsdf")
    for path, alpha in zip(paths, (0.4, 0.6)):
        formats.bake(analytic.create("microfacet", alpha=alpha), path)
    return paths


@pytest.fixture
def rgl_file(rgl_files) -> Path:
    return rgl_files[0]


@pytest.fixture
def measured(rgl_files, tmp_path) -> tuple[Path, Path, Path]:
    """A measured run trained 4 steps: (its config file, its data file, its folder)."""
    data = tmp_path / "data" / "plastic.bsdf"
    data.parent.mkdir()
    data.write_bytes(rgl_files[0].read_bytes())
    cfg_path = tmp_path / "measured.yaml"
    cfg_path.write_text("target: {data: data/plastic.bsdf}\n")
    run = tmp_path / "run"
    loop.train(cfgmod.load(cfg_path, STEPS), run)
    return cfg_path, data, run


def test_a_measured_run_whose_file_changed_or_went_is_refused(measured, rgl_files, capsys):
    cfg_path, data, run = measured
    assert saved(run)["target_files"] == {str(data): sha(data)}
    before = (run / "ckpt.pt").read_bytes()
    args = ["train", str(cfg_path), "--out", str(run), "--resume", *sets(STEPS + MORE)]
    data.write_bytes(rgl_files[1].read_bytes())  # replaced: the same path, other bytes
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, f"target.data: {data} {REFUSED}", "--overwrite")
    data.unlink()
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, f"target.data: {data} is gone since the checkpoint")
    assert (run / "ckpt.pt").read_bytes() == before  # refused before any write


def test_a_measured_run_with_its_file_unchanged_resumes(measured):
    cfg_path, data, run = measured
    loop.train(cfgmod.load(cfg_path, STEPS + MORE), run, resume=True)
    ckpt = saved(run)
    assert ckpt["step"] == 6 and ckpt["target_files"] == {str(data): sha(data)}


def test_a_checkpoint_of_an_earlier_version_resumes_unchecked(measured, rgl_files):
    cfg_path, data, run = measured
    old = saved(run)
    del old["target_files"]  # as written before the files were fingerprinted
    session.save_checkpoint(run / "ckpt.pt", old)
    data.write_bytes(rgl_files[1].read_bytes())
    loop.train(cfgmod.load(cfg_path, STEPS + MORE), run, resume=True)
    ckpt = saved(run)  # the next checkpoint records the file as the run read it
    assert ckpt["step"] == 6 and ckpt["target_files"] == {str(data): sha(data)}


def test_export_does_not_write_over_its_runs_measured_file(measured, capsys):
    """export reads the run's target.data (its accuracy): -o onto it replaced the 35 MB
    MERL file with an ONNX model, and every later read of it failed."""
    _, data, run = measured
    before = data.read_bytes()
    code, _, err = cli(capsys, "export", str(run), "-o", str(data))
    assert_one_line_error(code, err, f"-o {data}: is the run's target.data ({data})")
    assert data.read_bytes() == before


def test_a_python_config_with_a_relative_data_path_resumes(rgl_file, tmp_path, monkeypatch):
    """A config built in Python keeps target.data as written (relative: the current
    folder's); its checkpoint resumes, the two sides compared by one rule."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plastic.bsdf").write_bytes(rgl_file.read_bytes())

    def built(overrides: list[str]) -> cfgmod.Config:
        raw = cfgmod.load(None, overrides).model_dump()
        raw["target"] = {"data": "plastic.bsdf"}
        return cfgmod.from_dict(raw)

    assert built(STEPS).target.data == "plastic.bsdf"
    loop.train(built(STEPS), tmp_path / "run")
    loop.train(built(STEPS + MORE), tmp_path / "run", resume=True)
    assert saved(tmp_path / "run")["step"] == 6


# ------------------------------------------------------------------ a textured teacher
@pytest.fixture
def textured(tmp_path) -> tuple[Path, Path, Path]:
    """A textured run trained 4 steps: (its config file, the teacher's XML, its folder)."""
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.train import data, textured_loop

    xml = write_teacher(tmp_path / "teacher", "roughplastic", size=16)
    cfg_path = tmp_path / "tx.yaml"
    small_run_config(
        cfg_path,
        xml,
        texture="lobes: 2, resolution: 4, validation_uv: 4",
        train="steps: 4, checkpoint_every: 2, log_every: 2, eval_every: 4, progress: false",
        normalization="samples: 1024",
    )
    cfg = cfgmod.load(cfg_path)
    run = tmp_path / "run"
    textured_loop.train(cfg, run, target=data.build_target(cfg.target))
    return cfg_path, xml, run


@pytest.mark.mitsuba
def test_a_textured_run_whose_bitmap_or_xml_changed_is_refused(textured, capsys):
    from neural_brdf.measured.procedural import write_teacher

    cfg_path, xml, run = textured
    bitmap = xml.parent / "diffuse.exr"
    assert saved(run)["target_files"] == {str(xml): sha(xml), str(bitmap): sha(bitmap)}
    args = ["train", str(cfg_path), "--out", str(run), "--resume", *sets(MORE)]
    kept = bitmap.read_bytes()
    write_teacher(xml.parent, "roughplastic", size=16, seed=1)  # another bitmap, same XML
    assert bitmap.read_bytes() != kept
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, f"target.mitsuba: {bitmap} {REFUSED}")
    bitmap.write_bytes(kept)
    xml.write_text(xml.read_text() + "<!-- edited -->\n")
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, f"target.mitsuba: {xml} {REFUSED}")


@pytest.mark.mitsuba
def test_a_textured_run_with_its_files_unchanged_resumes(textured):
    from neural_brdf.train import data, textured_loop

    cfg_path, xml, run = textured
    cfg = cfgmod.load(cfg_path, MORE)
    textured_loop.train(cfg, run, target=data.build_target(cfg.target), resume=True)
    ckpt = saved(run)
    bitmap = xml.parent / "diffuse.exr"
    assert ckpt["step"] == 6
    assert ckpt["target_files"] == {str(xml): sha(xml), str(bitmap): sha(bitmap)}


# ------------------------------------------------------------------ an images fit
SCENE = """\
<scene version="3.0.0">
    <include filename="parts/lights.xml"/>
    <bsdf type="diffuse" id="fit"/>
    <bsdf type="conductor" id="other"><spectrum name="eta" filename="eta.spd"/></bsdf>
    <shape type="sphere"><ref id="fit"/></shape>
    <shape type="obj"><string name="filename" value="$mesh"/></shape>
</scene>
"""
LIGHTS = """\
<scene version="3.0.0">
    <emitter type="envmap"><string name="filename" value="sky.exr"/></emitter>
</scene>
"""


@pytest.fixture
def images(tmp_path) -> tuple[Path, dict[str, Path]]:
    """An images fit's inputs (a scene that includes its lights, an envmap, a spectrum,
    an image and the photograph without the flash; bytes, not renders): (config, files)."""
    files = {
        "scene": tmp_path / "scene.xml",
        "lights": tmp_path / "parts" / "lights.xml",
        "sky": tmp_path / "sky.exr",
        "eta": tmp_path / "eta.spd",
        "image": tmp_path / "view.exr",
        "subtract": tmp_path / "ambient.exr",
    }
    files["lights"].parent.mkdir()
    files["scene"].write_text(SCENE)
    files["lights"].write_text(LIGHTS)
    for name in ("sky", "eta", "image", "subtract"):
        files[name].write_bytes(name.encode() * 100)
    cfg_path = tmp_path / "fit.yaml"
    cfg_path.write_text(
        "target:\n  images:\n    - {scene: scene.xml, image: view.exr, subtract: ambient.exr}\n"
    )
    return cfg_path, files


def test_the_fingerprint_of_each_kind_of_target(images, rgl_file):
    cfg_path, files = images
    cfg = cfgmod.load(cfg_path)
    # the $mesh of the obj shape is a parameter: left out (the file is not known here)
    assert target_files.digest(cfg) == {str(p): sha(p) for p in files.values()}
    assert target_files.where(cfg, str(files["image"])) == "target.images[0].image"
    assert target_files.where(cfg, str(files["sky"])) == "target.images"
    assert target_files.digest(cfgmod.load(None)) == {}  # analytic: no file
    measured = cfgmod.load(None, [f"target.data={rgl_file}"])
    assert target_files.digest(measured) == {str(rgl_file): sha(rgl_file)}


@pytest.mark.mitsuba
def test_an_images_fit_whose_image_or_included_file_changed_is_refused(images, tmp_path, capsys):
    from neural_brdf.inverse import fit

    cfg_path, files = images
    cfg = cfgmod.load(cfg_path)
    run = tmp_path / "run"
    folder = runfolder.Folder.open(run, resume=False, overwrite=False)
    rf = session.RunFiles(cfg, folder, kind=fit.KIND)  # as the image stage writes it
    rf.begin()
    rf.save(rf.state(4, 1.0, {}))
    ckpt = session.load_resumable(
        cfg, rf.ckpt_path, kind=fit.KIND, must_match=fit.RESUME_MUST_MATCH
    )
    assert ckpt["target_files"] == {str(p): sha(p) for p in files.values()}
    args = ["train", str(cfg_path), "--out", str(run), "--resume"]
    kept = files["image"].read_bytes()
    files["image"].write_bytes(kept[::-1])  # re-rendered
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, f"target.images[0].image: {files['image']} {REFUSED}")
    files["image"].write_bytes(kept)
    files["lights"].write_text(LIGHTS.replace("sky.exr", "sky2.exr"))
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, f"target.images: {files['lights']} {REFUSED}")


def test_export_says_when_the_target_file_changed_since_training(measured, rgl_files, capsys):
    """The weights stand (export writes them), but the accuracy it reports is against
    the file as it is now: a file changed since the run trained is named in a warning
    (export said nothing, and measured the weights against the other file)."""
    _, data, run = measured
    code, _, err = cli(capsys, "export", str(run), "-o", str(run / "a.onnx"))
    assert code == 0 and "warning" not in err, err
    data.write_bytes(rgl_files[1].read_bytes())
    code, _, err = cli(capsys, "export", str(run), "-o", str(run / "b.onnx"))
    assert code == 0, err
    assert f"warning: target.data: {data} {REFUSED}" in err, err
    assert (run / "b.onnx").is_file()
