"""`neural-brdf train` of a textured Mitsuba material, end to end (issue 30: the config and
CLI path, the file's metadata, validation at random uv, export, resume, the report).

One small run is trained once per module from a 16 x 16 procedural ``roughplastic``
(neural_brdf/measured/procedural.py) with 3 lobes on an 8 x 8 weight field and a few
dozen steps; every test reads it.  The references are independent of the code under test:
onnxruntime on the file itself, Mitsuba's own ``eval`` of the teacher, numpy quadrature
on the file, the raw ONNX inputs and initializers.

* the run writes a (wi, wo, uv) graph whose metadata says so (``texture``), with the
  physics measured at random uv: reciprocity 0, albedo <= 1 + tol, f >= 0;
* training learned: the held-out error against the teacher fell, and validate's own
  accuracy (Mitsuba's eval at random uv) is close to the loop's;
* f wraps in uv (uv + 1 gives f at uv) and varies over uv as the teacher does;
* ``validate --reference``, ``export``, ``--resume`` and ``report`` handle the run;
* a textured teacher in ``train-many`` or a homogeneous reference for a textured file:
  one line, exit 2.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from cli_helpers import ROOT, assert_one_line_error, cli
from neural_brdf import config as cfgmod
from neural_brdf import export, validate

pytestmark = pytest.mark.mitsuba

SETTINGS = """\
target: {{mitsuba: {xml}}}
texture: {{lobes: 3, resolution: 8, validation_uv: 8}}
train: {{steps: {steps}, checkpoint_every: 20, log_every: 10, eval_every: 20, progress: false}}
data: {{pool_size: 8192, batch_size: 1024}}
validation: {{pairs: 2000, furnace_dirs: 32, furnace_samples: 4096, accuracy_samples: 8192}}
normalization: {{samples: 4096}}
export: {{parity_pairs: 512}}
"""
STEPS = 60


def write_config(folder: Path, xml: Path, steps: int = STEPS, name: str = "tx") -> Path:
    path = folder / f"{name}.yaml"
    path.write_text(SETTINGS.format(xml=xml, steps=steps))
    return path


@pytest.fixture(scope="module")
def teacher(tmp_path_factory) -> Path:
    from neural_brdf.measured.procedural import write_teacher

    return write_teacher(tmp_path_factory.mktemp("teacher"), "roughplastic", size=16)


@pytest.fixture(scope="module")
def run(teacher, tmp_path_factory) -> Path:
    from neural_brdf.tooling.cli import main

    folder = tmp_path_factory.mktemp("textured_run")
    cfg = write_config(folder, teacher)
    assert main(["train", str(cfg), "--out", str(folder / "run")]) == 0
    return folder / "run"


def session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def rows(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)

    def hemi(k):
        v = rng.normal(size=(k, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.05
        return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)

    return hemi(n), hemi(n), rng.random((n, 2)).astype(np.float32)


def export_matches_the_run(
    capsys, run_dir: Path, out: Path, seed: int, says: str = ""
) -> np.ndarray:
    """``neural-brdf export RUN_DIR -o OUT`` rebuilds the run's model from its checkpoint:
    the same f as the run's model.onnx at ``rows(1024, seed)`` (returned); its stderr
    holds ``says``."""
    code, _, err = cli(capsys, "export", str(run_dir), "-o", str(out))
    assert code == 0, err
    assert says in err, err
    wi, wo, uv = rows(1024, seed)
    feeds = {"wi": wi, "wo": wo, "uv": uv}
    a = session(run_dir / "model.onnx").run(["f"], feeds)[0]
    np.testing.assert_allclose(a, session(out).run(["f"], feeds)[0], rtol=1e-6, atol=1e-7)
    return a


def test_the_file_is_a_textured_graph_with_its_metadata(run):
    proto = onnx.load(str(run / "model.onnx"))
    assert [i.name for i in proto.graph.input] == ["wi", "wo", "uv"]
    assert [o.name for o in proto.graph.output] == ["f"]
    props = {p.key: p.value for p in proto.metadata_props}
    tex = json.loads(props["texture"])
    assert tex["lobes"] == 3 and tex["resolution"] == [8, 8]
    assert tex["wrap"] == "repeat" and tex["filter"] == "bilinear"
    target = json.loads(props["target"])
    assert target["kind"] == "mitsuba" and target["spatially_varying"] is True
    # the weight table in the graph: 8 x 8 texels of 3 weights, each row >= 0, sum <= 1
    tables = [
        onnx.numpy_helper.to_array(t) for t in proto.graph.initializer if tuple(t.dims) == (64, 3)
    ]
    assert len(tables) == 1
    w = tables[0]
    assert w.min() >= 0.0 and w.sum(-1).max() <= 1.0 + 1e-6
    assert "uv" in proto.doc_string


def test_physics_at_random_uv(run):
    m = json.loads((run / "metrics.json").read_text())
    checks = m["checks"]
    assert checks["reciprocity"]["value"] == 0.0
    assert checks["min_value"]["value"] >= 0.0
    assert checks["max_albedo"]["passed"], checks["max_albedo"]
    assert len(m["furnace"]["uv"]) == 8 and len(m["furnace"]["uv_max_albedo"]) == 8
    # independently: f(wi, wo, uv) == f(wo, wi, uv) bit for bit in onnxruntime
    wi, wo, uv = rows(4096, 3)
    s = session(run / "model.onnx")
    a = s.run(["f"], {"wi": wi, "wo": wo, "uv": uv})[0]
    b = s.run(["f"], {"wi": wo, "wo": wi, "uv": uv})[0]
    assert np.array_equal(a, b)
    # and the albedo at 4 uv by a plain uniform-hemisphere quadrature stays <= 1
    rng = np.random.default_rng(5)
    n = 1 << 15
    u = rng.random((n, 2))
    z = u[:, 0]
    r = np.sqrt(1 - z**2)
    wo_s = np.stack([r * np.cos(2 * np.pi * u[:, 1]), r * np.sin(2 * np.pi * u[:, 1]), z], -1)
    for p in rng.random((4, 2)):
        for theta in (0.0, 60.0):
            t = math.radians(theta)
            wi_s = np.tile([math.sin(t), 0.0, math.cos(t)], (n, 1))
            f = s.run(
                ["f"],
                {
                    "wi": wi_s.astype(np.float32),
                    "wo": wo_s.astype(np.float32),
                    "uv": np.tile(p, (n, 1)).astype(np.float32),
                },
            )[0]
            albedo = (f * z[:, None]).mean(0) * 2 * np.pi
            assert albedo.max() <= 1.0 + 5e-2, (p, theta, albedo)


def test_training_learned_and_validate_agrees_with_the_teacher(run, teacher):
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    m = json.loads((run / "metrics.json").read_text())
    t = m["training"]
    assert t["raw_val_rel_rmse"] < 0.8 * t["init_val_rel_rmse"], t
    assert m["accuracy"]["rel_rmse"] < 0.8 * t["init_val_rel_rmse"]
    assert "uv" in m["accuracy"]["worst"][0]
    # the accuracy figure recomputed here from Mitsuba's eval and onnxruntime
    target = TexturedMitsubaTarget(teacher)
    wi, wo, uv = rows(4096, 11)
    ref = target.eval(wi, wo, uv) * wo[:, 2:3]
    got = session(run / "model.onnx").run(["f"], {"wi": wi, "wo": wo, "uv": uv})[0] * wo[:, 2:3]
    err = float(np.sqrt(((got - ref) ** 2).sum() / (ref**2).sum()))
    assert err < 0.8 * t["init_val_rel_rmse"], err


def test_f_wraps_and_varies_over_uv(run):
    import neural_brdf

    model = neural_brdf.load(run / "model.onnx")
    assert model.textured
    wi, wo, uv = rows(2048, 7)
    f = model.eval(wi, wo, uv)
    shifted = model.eval(wi, wo, uv + np.float32(1.0))
    np.testing.assert_allclose(shifted, f, rtol=2e-4, atol=1e-6)
    other = model.eval(wi, wo, (uv + np.float32(0.37)) % 1)
    assert np.abs(other - f).max() > 1e-3 * np.abs(f).max()
    with pytest.raises(Exception, match="give uv"):
        model.eval(wi, wo)


def test_validate_reference_export_and_report(run, capsys, tmp_path):
    code, out, _ = cli(
        capsys, "validate", str(run / "model.onnx"), "--reference", str(run / "config.yaml")
    )
    assert code == 0 and "rel_rmse" in out
    code, out, err = cli(capsys, "export", str(run), "-o", str(tmp_path / "again.onnx"))
    assert code == 0, err
    wi, wo, uv = rows(1024, 13)
    feeds = {"wi": wi, "wo": wo, "uv": uv}
    a = session(run / "model.onnx").run(["f"], feeds)[0]
    b = session(tmp_path / "again.onnx").run(["f"], feeds)[0]
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    html = (run / "report.html").read_text()
    assert "A textured model" in html and "report-render.png" in (run / "report.md").read_text()
    assert "grey: one output each" not in html  # rgb lobes, the default


def test_resume_trains_on_with_per_channel_weights(teacher, tmp_path, capsys):
    cfg = write_config(tmp_path, teacher, steps=20)
    rgb = ("--set", "texture.weights=rgb")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"), *rgb)
    assert code == 0, err
    code, _, err = cli(
        capsys,
        "train",
        str(cfg),
        "--out",
        str(tmp_path / "r"),
        "--resume",
        "--set",
        "train.steps=40",
        *rgb,
    )
    assert code == 0, err
    assert "resuming" in err and "at step 20" in err
    log = (tmp_path / "r" / "log.csv").read_text().strip().splitlines()
    steps = [int(line.split(",")[0]) for line in log[1:]]
    assert steps == [10, 20, 30, 40]
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert m["training"]["steps"] == 40
    # a set of weights per RGB channel: the table is [R*R, 3 K], and export rebuilds it
    proto = onnx.load(str(tmp_path / "r" / "model.onnx"))
    props = {p.key: p.value for p in proto.metadata_props}
    assert json.loads(props["texture"])["channels"] == 3
    assert any(tuple(t.dims) == (64, 9) for t in proto.graph.initializer)
    export_matches_the_run(capsys, tmp_path / "r", tmp_path / "e.onnx", 17)


@pytest.mark.parametrize("network", ["shared", "separate"])
def test_either_lobe_network_trains_exports_and_says_so(teacher, tmp_path, capsys, network):
    """texture.lobe_network: one network with 3 heads (shared, the default) or 3 networks
    trains, learns, and export from the checkpoint rebuilds it (the same f); the file's
    normalisation note says which."""
    cfg = write_config(tmp_path, teacher, steps=100)
    shared = ("--set", f"texture.lobe_network={network}")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "s"), *shared)
    assert code == 0, err
    m = json.loads((tmp_path / "s" / "metrics.json").read_text())
    assert m["training"]["raw_val_rel_rmse"] < 0.8 * m["training"]["init_val_rel_rmse"]
    assert m["checks"]["reciprocity"]["value"] == 0.0 and m["checks"]["max_albedo"]["passed"]
    proto = onnx.load(str(tmp_path / "s" / "model.onnx"))
    props = {p.key: p.value for p in proto.metadata_props}
    assert ("the 3 heads of one network" in props["normalization"]) == (network == "shared")
    heads = [t for t in proto.graph.initializer if tuple(t.dims)[-1:] == (9,)]  # 3 heads x RGB
    assert bool(heads) == (network == "shared")
    assert len(json.loads(props["texture"])["lobe_tables"]) == 3
    export_matches_the_run(capsys, tmp_path / "s", tmp_path / "e.onnx", 19)


def test_grey_lobes_train_export_and_say_so(teacher, tmp_path, capsys):
    """texture.lobe_color: grey (one output per lobe, coloured by rgb weights) trains,
    learns, says so in the metadata, and export from the checkpoint rebuilds it (the same
    f); with one weight per lobe it is one line and exit 2."""
    cfg = write_config(tmp_path, teacher, steps=100)
    grey = ("--set", "texture.lobe_color=grey", "--set", "texture.weights=rgb")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "g"), *grey)
    assert code == 0, err
    m = json.loads((tmp_path / "g" / "metrics.json").read_text())
    assert m["training"]["raw_val_rel_rmse"] < 0.8 * m["training"]["init_val_rel_rmse"]
    assert m["training"]["lobe_color"] == "grey"
    assert m["checks"]["reciprocity"]["value"] == 0.0 and m["checks"]["max_albedo"]["passed"]
    proto = onnx.load(str(tmp_path / "g" / "model.onnx"))
    props = {p.key: p.value for p in proto.metadata_props}
    assert json.loads(props["texture"])["lobe_color"] == "grey"
    assert "grey: one output each" in (tmp_path / "g" / "report.html").read_text()
    (head,) = [t for t in proto.graph.initializer if t.name.endswith("mlp.head.weight")]
    assert tuple(head.dims)[0] == 3  # 3 lobes, one output each
    a = export_matches_the_run(capsys, tmp_path / "g", tmp_path / "e.onnx", 29)
    assert np.ptp(a[:, 0] / np.maximum(a[:, 2], 1e-12)) > 0.05  # not grey: the weights colour
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(tmp_path / "bad"), "--set",
        "texture.lobe_color=grey",
    )  # fmt: skip
    assert_one_line_error(code, err, "lobe_color", "weights: rgb")
    assert not (tmp_path / "bad").exists()


def test_the_reports_albedo_figure_is_at_the_figures_uv(run, tmp_path, monkeypatch):
    """The neural albedo curve and its maximum were the validator's, at its worst texel,
    drawn beside the teacher's at uv (0.5, 0.5): both are now at the figures' uv."""
    from neural_brdf.viewer import plots
    from neural_brdf.viewer.report import write_report

    seen: dict = {}
    real = plots.albedo_curve

    def spy(neural, ref, **kw):
        seen.update(kw)
        return real(neural, ref, **kw)

    monkeypatch.setattr(plots, "albedo_curve", spy)
    paths = write_report(run, tmp_path / "r", render=False)
    assert seen["measured"] is None and seen["validated_max"] is None
    html = paths["html"].read_text()
    assert "per channel at uv (0.5, 0.5), the figures" in html
    assert "the texel of the maximum albedo" in html


def test_a_textured_teacher_is_refused_by_train_many(teacher, tmp_path, capsys):
    a = write_config(tmp_path, teacher, name="a")
    b = write_config(tmp_path, teacher, name="b")
    code, _, err = cli(capsys, "train-many", str(a), str(b), "--out", str(tmp_path / "many"))
    assert_one_line_error(code, err, "a.yaml", "trains alone")
    assert not (tmp_path / "many").exists()


def test_a_homogeneous_reference_for_a_textured_file(run, capsys):
    gold = ROOT / "configs" / "gold.yaml"
    code, _, err = cli(capsys, "validate", str(run / "model.onnx"), "--reference", str(gold))
    assert_one_line_error(code, err, "textured model", "does not vary over the surface")


def test_bake_refuses_a_textured_file_in_one_line(run, capsys, tmp_path):
    # an RGL or MERL table holds one BRDF (the viewer draws a textured file:
    # tests/viewer/test_textured_viewer.py)
    out = tmp_path / "x.bsdf"
    code, _, err = cli(capsys, "bake", str(run / "model.onnx"), "-o", str(out))
    assert_one_line_error(code, err, "a textured model", "bake")
    assert not out.exists()


def test_a_projected_field_is_the_files_and_export_makes_it_again(teacher, tmp_path, capsys):
    """``texture.project``: the file's field is the projected one (its resolution in the
    metadata and in the graph's table), its physics still pass, the projection's
    residual is below the trained field's on the same pairs, and ``export`` of the run
    projects again to the same f (seeded)."""
    cfg = write_config(tmp_path, teacher, steps=40, name="proj")
    run_dir = tmp_path / "run"
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(run_dir), "--set", "texture.project=12",
        "--set", "texture.refit_steps=20",
    )  # fmt: skip
    assert code == 0, err
    proto = onnx.load(str(run_dir / "model.onnx"))
    tex = json.loads({p.key: p.value for p in proto.metadata_props}["texture"])
    assert tex["resolution"] == [12, 12]
    assert any(tuple(t.dims) == (144, 3) for t in proto.graph.initializer)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    projection = metrics["training"]["projection"]
    assert projection["resolution"] == 12
    assert projection["residual"] < projection["residual_trained_field"]
    # the config's pairs and ridge reached the projection (the defaults: none given here)
    assert projection["pairs_per_texel"] == cfgmod.Texture().project_pairs
    assert projection["ridge"] == cfgmod.Texture().project_ridge > 0
    # and the lobes were refitted on the projected field (then bounded again: the checks)
    assert projection["refit"]["steps"] == 20 and projection["refit"]["final_loss"] > 0
    checks = metrics["checks"]
    assert checks["reciprocity"]["value"] == 0.0 and checks["max_albedo"]["passed"]
    page = (run_dir / "report.html").read_text()
    assert "projected onto the trained lobes at 12² texels" in page
    assert "trained 20 more steps on the projected field" in page
    # export RUN takes the run's kept projection (textured.pt): the run's file, without
    # projecting and refitting again
    assert (run_dir / "textured.pt").is_file()
    code, _, err = cli(capsys, "export", str(run_dir), "-o", str(tmp_path / "kept.onnx"))
    assert code == 0 and "projecting the field again" not in err, err
    assert (tmp_path / "kept.onnx").read_bytes() == (run_dir / "model.onnx").read_bytes()
    # a kept file whose table was changed does not give its probe's f: projected again,
    # and so is a missing one; both give the run's f
    import torch

    kept = torch.load(run_dir / "textured.pt", weights_only=True)
    kept["model"]["field.table"] *= 0.5
    torch.save(kept, run_dir / "textured.pt")
    _, _, err = cli(capsys, "export", str(run_dir), "-o", str(tmp_path / "tampered.onnx"))
    assert "projecting the field again: textured.pt does not give its model's f" in err
    # projected again from the checkpoint, not from the lobes the rejected file held
    assert (tmp_path / "tampered.onnx").read_bytes() == (run_dir / "model.onnx").read_bytes()
    (run_dir / "textured.pt").write_bytes(b"not a torch file")  # damaged: no traceback
    code, _, err = cli(capsys, "export", str(run_dir), "-o", str(tmp_path / "damaged.onnx"))
    assert code == 0 and "projecting the field again: textured.pt unreadable" in err, err
    (run_dir / "textured.pt").unlink()
    export_matches_the_run(
        capsys, run_dir, tmp_path / "again.onnx", seed=5, says="again: no textured.pt"
    )
    # a run written before texture.project_ridge (its resolved config.yaml lacks the key)
    # exports as that version projected, with no ridge; a user's config takes the default
    text = (run_dir / "config.yaml").read_text()
    older = "".join(ln for ln in text.splitlines(True) if "project_ridge" not in ln)
    assert older != text
    (run_dir / "config.yaml").write_text(older)
    info = export.export_run(
        run_dir,
        tmp_path / "older.onnx",
        measure=validate.physics,
        measure_textured=validate.physics_textured,
    )
    assert info["projection"]["ridge"] == 0.0 and not info["projection"]["kept_by_the_run"]
    capsys.readouterr()  # its line: projected again
    assert cfgmod.load(run_dir / "config.yaml").texture.project_ridge > 0
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(tmp_path / "bad"), "--set",
        "texture.project=12", "--set", "texture.lobe_network=separate",
    )  # fmt: skip
    assert_one_line_error(code, err, "texture.project", "lobe_network: shared")
    assert not (tmp_path / "bad").exists()
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(tmp_path / "bad"), "--set",
        "texture.project=12", "--set", "texture.project_ridge=-1",
    )  # fmt: skip
    assert_one_line_error(code, err, "texture.project_ridge")
    assert not (tmp_path / "bad").exists()
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(tmp_path / "bad"), "--set",
        "texture.refit_steps=20",
    )  # fmt: skip
    assert_one_line_error(code, err, "refit_steps", "set project")
    assert not (tmp_path / "bad").exists()


def test_the_run_prints_the_teachers_normal_field_warning(teacher, tmp_path, capsys, monkeypatch):
    """finish_textured hands the run's normal-field figures to the teacher's
    normal_field_warning and prints its line on stderr (the line's own wording and
    threshold: tests/measured/test_textured.py)."""
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    seen = []

    def warn(self, figures):
        seen.append(figures)
        return "the file's normal field is far from the teacher's"

    monkeypatch.setattr(TexturedMitsubaTarget, "normal_field_warning", warn)
    cfg = write_config(tmp_path, teacher, steps=20)
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "run"))
    assert code == 0, err
    assert "warning: the file's normal field is far from the teacher's" in err
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert seen == [metrics.get("normal_field")]


def test_every_training_pool_of_a_projected_run_draws_data_peaks_share(
    teacher, tmp_path, capsys, monkeypatch
):
    """Training and the lobes' refit on the projected field draw their pools with the
    config's data.peak (the refit's took the default share whatever the config said)."""
    from neural_brdf.train import textured_loop

    shares = []
    init = textured_loop.PairPool.__init__

    def recording(self, *args, **kwargs):
        init(self, *args, **kwargs)
        shares.append(self.peak)

    monkeypatch.setattr(textured_loop.PairPool, "__init__", recording)
    cfg = write_config(tmp_path, teacher, steps=20, name="peak")
    code, _, err = cli(
        capsys, "train", str(cfg), "--out", str(tmp_path / "run"), "--set", "data.peak=0.03",
        "--set", "texture.project=8", "--set", "texture.refit_steps=5",
    )  # fmt: skip
    assert code == 0, err
    assert len(shares) >= 2 and set(shares) == {0.03}, shares
