"""`neural-brdf bake` (MERL files) and `neural-brdf render` (Mitsuba previews), and the
configs they and validate / view take: a Mitsuba teacher's, a preset's name."""

from __future__ import annotations

import re
from pathlib import Path

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


def test_bake_refuses_a_table_its_own_reader_refuses(capsys, tmp_path):
    """A near-delta lobe (GGX alpha 1e-300) puts a bin above the readers' bound on a
    value: bake says so in one line and leaves the file it would replace as it was,
    rather than write a table that train, render and validate then refuse."""
    cfg = tmp_path / "mirror.yaml"
    cfg.write_text("target: {model: microfacet, params: {alpha: 1.0e-300}}\n")
    out = tmp_path / "mirror.binary"
    out.write_bytes(b"a user's file")
    code, _, err = cli(capsys, "bake", str(cfg), "-o", str(out))
    assert_one_line_error(code, err, str(out), "is above", "not written")
    assert out.read_bytes() == b"a user's file"
    # a rough one of the same model bakes, and its table reads back
    cfg.write_text("target: {model: microfacet, params: {alpha: 0.3}}\n")
    code, _, err = cli(capsys, "bake", str(cfg), "-o", str(out))
    assert code == 0, err
    assert merl.read_merl(out).values.max() > 0


@pytest.mark.parametrize(
    "command, out",
    [("render", "x.png"), ("export", "m.onnx"), ("bake", "x.binary"), ("codegen", "x.c")],
)
def test_an_output_in_a_missing_folder_is_refused_not_created(
    capsys, tiny_model, tmp_path, command, out
):
    """A mistyped -o folder is an error naming the folder, for every command that writes
    a file (render and export created it, codegen and view refused it)."""
    target = tmp_path / "typo" / "sub" / out
    source = str(tiny_model.parent if command == "export" else tiny_model)
    extra = ["--target", "c"] if command == "codegen" else []
    code, _, err = cli(capsys, command, source, *extra, "-o", str(target))
    assert_one_line_error(code, err, str(target), f"no folder {target.parent}")
    assert not (tmp_path / "typo").exists()
    # beside a file where the folder would be
    (tmp_path / "typo").write_text("mine")
    code, _, err = cli(capsys, command, source, *extra, "-o", str(tmp_path / "typo" / out))
    assert_one_line_error(code, err, "typo", "is a file, not a folder")
    assert (tmp_path / "typo").read_text() == "mine"


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


# ------------------------------------------------------------------ --reference: teachers, presets
# ``render --reference CFG`` whose target is a Mitsuba teacher, homogeneous or textured,
# renders the teacher with Mitsuba beside the model (it was refused: "target.mitsuba:
# only analytic targets here"); its panel is checked against Mitsuba's own render of the
# teacher's XML in the same scene, samples and seed, to the PNG's 8-bit rounding.  A
# preset's name (mitsuba/roughplastic, lambert, gold) is taken wherever train takes one:
# render, validate, view and bake give what the preset's file gives (they read the name
# as a missing file); a bare name that is neither is one line naming it.
CONFIGS = ROOT / "configs"
RES, SPP = 32, 4  # the render's size: the checks are of the panels, not of the quality
QUANTUM = 1.0 / 255.0  # a PNG's 8-bit rounding


@pytest.fixture(scope="module")
def mi():  # (Mitsuba's variant before the renderer's module is imported)
    import mitsuba

    if mitsuba.variant() is None:
        mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


def three_panels(path: Path) -> list[np.ndarray]:
    """The three RES x RES panels (neural, target, difference) under the label strip."""
    import matplotlib.image as mpimg

    img = mpimg.imread(path)[..., :3].astype(np.float64)
    strip = img.shape[0] - RES
    gap = (img.shape[1] - 3 * RES) // 2
    assert strip >= 16 and gap >= 2, img.shape
    return [img[strip:, i * (RES + gap) : i * (RES + gap) + RES] for i in range(3)]


def mitsuba_render(mi, xml: Path) -> np.ndarray:
    """The teacher's XML as Mitsuba loads it (its twosided wrapper included) in the
    preview scene, in display values."""
    from neural_brdf.renderers import render as nbr

    return nbr.to_display(nbr.render_scene(mi.load_file(str(xml)), resolution=RES, spp=SPP))


def render_with(capsys, model: Path, reference: str, out: Path) -> str:
    args = ["render", str(model), "--reference", reference, "-o", str(out)]
    code, stdout, err = cli(capsys, *args, "--spp", str(SPP), "--resolution", str(RES))
    assert code == 0, err
    return stdout


@pytest.fixture(scope="module")
def textured_config(tmp_path_factory) -> tuple[Path, Path]:
    """(config, teacher.xml) of a small procedural textured teacher (no normal map)."""
    from neural_brdf.measured.procedural import write_teacher

    folder = tmp_path_factory.mktemp("textured")
    xml = write_teacher(folder / "mat", "roughplastic", size=8)
    cfg = folder / "textured.yaml"
    cfg.write_text("target: {mitsuba: mat/teacher.xml}\n")
    return cfg, xml


@pytest.mark.mitsuba
@pytest.mark.parametrize("kind", ["homogeneous", "textured"])
def test_render_shows_a_mitsuba_teacher_beside_the_model(
    mi, capsys, tiny_model, tmp_path, textured_config, kind
):
    if kind == "homogeneous":  # the preset, by its name (a file of the same name is not here)
        reference, xml = "mitsuba/roughplastic", CONFIGS / "mitsuba" / "roughplastic.xml"
    else:
        reference, xml = str(textured_config[0]), textured_config[1]
    out = tmp_path / "teacher.png"
    stdout = render_with(capsys, tiny_model, reference, out)
    assert "PSNR" in stdout and "teacher" in stdout
    neural, target, _ = three_panels(out)
    teacher = mitsuba_render(mi, xml)
    assert np.abs(target - teacher).max() <= 2 * QUANTUM  # the teacher, as Mitsuba renders it
    assert np.abs(neural - teacher).mean() > 10 * QUANTUM  # (and the check can tell)
    psnr = float(re.search(r"PSNR ([0-9.]+) dB", stdout).group(1))
    mse = np.mean((neural - target) ** 2)
    assert psnr == pytest.approx(10 * np.log10(1 / mse), abs=0.2)  # of these two panels


@pytest.mark.mitsuba
def test_render_takes_an_analytic_preset_by_its_name(mi, capsys, tiny_model, tmp_path):
    by_name, by_file = tmp_path / "name.png", tmp_path / "file.png"
    render_with(capsys, tiny_model, "lambert", by_name)
    render_with(capsys, tiny_model, str(CONFIGS / "lambert.yaml"), by_file)
    a, b = three_panels(by_name)[1], three_panels(by_file)[1]
    # the same teacher: equal to one 8-bit step (two renders of one scene may differ in
    # the last bit, the film's atomic adds being ordered by the threads, and a value on
    # a step's edge then rounds either way)
    assert np.abs(a - b).max() <= QUANTUM


def test_validate_takes_a_preset_by_its_name(capsys, tiny_model):
    model = str(tiny_model)
    code, by_name, err = cli(capsys, "validate", model, "--reference", "lambert")
    assert code in (0, 1), err  # 1: the tiny model fails a check
    code, by_file, _ = cli(capsys, "validate", model, "--reference", str(CONFIGS / "lambert.yaml"))
    assert "rel_rmse" in by_name and by_name == by_file


def test_a_folder_of_a_presets_name_does_not_shadow_it(capsys, tiny_model, tmp_path, monkeypatch):
    # a run written with --out lambert: train lambert still trains the preset, and so
    # --reference lambert still names it (it read the folder: "Is a directory")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lambert").mkdir()
    code, by_name, err = cli(capsys, "validate", str(tiny_model), "--reference", "lambert")
    assert code in (0, 1), err
    _, by_file, _ = cli(
        capsys, "validate", str(tiny_model), "--reference", str(CONFIGS / "lambert.yaml")
    )
    assert "rel_rmse" in by_name and by_name == by_file


def test_view_takes_a_preset_by_its_name(capsys, tiny_model, tmp_path):
    model = str(tiny_model)
    pages = []
    for compare in ("gold", str(CONFIGS / "gold.yaml")):
        out = tmp_path / f"{len(pages)}.html"
        code, _, err = cli(capsys, "view", model, "--compare", compare, "-o", str(out))
        assert code == 0, err
        pages.append(out.read_text())
    from neural_brdf import config

    label = f"target: {config.load(CONFIGS / 'gold.yaml').target.model}"
    same = [re.sub(r"nbrdf-view-\w+", "TMP", p) for p in pages]  # a temporary folder
    assert label in pages[0] and same[0] == same[1]


def test_bake_takes_a_preset_by_its_name(capsys, tmp_path):
    tables = []
    for source in ("lambert", str(CONFIGS / "lambert.yaml")):
        out = tmp_path / f"{len(tables)}.bsdf"
        code, _, err = cli(capsys, "bake", source, "-o", str(out))
        assert code == 0, err
        tables.append(out.read_bytes())
    assert tables[0] == tables[1]


@pytest.mark.parametrize(
    "argv",
    [
        ["render", "{m}", "--reference", "nosuch", "-o", "{d}/r.png"],
        ["validate", "{m}", "--reference", "nosuch"],
        ["view", "{m}", "--compare", "nosuch", "-o", "{d}/v.html"],
        ["bake", "nosuch", "-o", "{d}/b.bsdf"],
    ],
    ids=["render", "validate", "view", "bake"],
)
def test_a_name_that_is_neither_file_nor_preset_is_one_line(capsys, tiny_model, tmp_path, argv):
    args = [a.format(m=tiny_model, d=tmp_path) for a in argv]
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, "nosuch", "preset")
    assert not list(tmp_path.iterdir())  # nothing written


@pytest.mark.parametrize("command", ["train", "bake"])
def test_a_run_folder_given_as_a_config_says_it_is_a_folder(
    capsys, tiny_model, tmp_path, monkeypatch, command
):
    """A bare folder name (a run's, most likely) was 'neither a config file nor a
    preset', with the list of presets; it is a folder, and its config is named."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "myrun").mkdir()
    (tmp_path / "myrun" / "config.yaml").write_text("target: {model: lambertian}\n")
    argv = ["train", "myrun"] if command == "train" else ["bake", "myrun", "-o", "b.bsdf"]
    code, _, err = cli(capsys, *argv)
    assert_one_line_error(code, err, "myrun: is a folder", "myrun/config.yaml")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["myrun"]


def test_a_run_folder_given_where_a_config_goes_names_its_files(capsys, tmp_path):
    """A run folder whose name has a dot (runs/g0.2) is read as a config file: it said
    "cannot read config (Is a directory)"; it now says it is a folder and names the
    run's config and model."""
    run = tmp_path / "g0.2"
    run.mkdir()
    (run / "config.yaml").write_text(LAMBERT.read_text())
    (run / "model.onnx").write_bytes(b"")
    code, _, err = cli(capsys, "bake", str(run), "-o", str(tmp_path / "x.binary"))
    assert_one_line_error(
        code, err, f"{run}: is a folder", str(run / "config.yaml"), str(run / "model.onnx")
    )
    code, _, err = cli(capsys, "train", str(run), "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, f"{run}: is a folder", str(run / "config.yaml"))
    assert not (tmp_path / "x.binary").exists()


@pytest.mark.parametrize(
    ("key", "value", "needle"),
    [
        ("format_version", "99", "format_version: 99, and this reader knows up to"),
        ("format_version", "abc", "format_version: expected a whole number >= 1"),
        ("format_version", "0", "format_version: expected a whole number >= 1"),
        ("metadata_version", "0", "metadata_version: expected a whole number >= 1"),
        ("metadata_version", "99", "metadata_version: 99, and this reader knows up to"),
    ],
)
def test_a_file_of_a_later_or_unreadable_contract_version_is_refused(
    capsys, tiny_model, tmp_path, key, value, needle
):
    """A format_version is the contract's (bumped when it changes): a file of a later one,
    or of none readable, was baked, validated, rendered and loaded by the plugin without a
    word; it may compute another thing through the same input names."""
    import onnx

    m = onnx.load(str(tiny_model))
    (prop,) = [p for p in m.metadata_props if p.key == key]
    prop.value = value
    path = tmp_path / "later.onnx"
    onnx.save(m, str(path))
    for argv in (
        ["bake", str(path), "-o", str(tmp_path / "x.bsdf")],
        ["validate", str(path)],
        ["codegen", str(path), "--target", "c", "-o", str(tmp_path / "x.h")],
    ):
        code, out, err = cli(capsys, *argv)
        assert code == 2, (argv, code, out, err)
        assert_one_line_error(code, err, str(path), needle)
    assert not (tmp_path / "x.bsdf").exists() and not (tmp_path / "x.h").exists()
