"""Hostile input (issue 28, part 1): every case is exit 2, one short line naming the file
or key, and nothing that existed before is changed.

* an output that is one of the command's inputs, or one of a run's own files;
* a run name that is a path, empty or hidden;
* sizes: a YAML alias bomb, a huge config value, an ONNX file that declares more than it
  holds or computes a tensor of 256 GiB;
* smaller ones: ``render -o`` by the extension, ``render``/``bake`` of an ONNX without the
  project's metadata, Ctrl-C outside training, error texts bounded, ``train-many``'s
  config errors naming their file and its summary saying what passed.

The run these tests read is trained once (``tiny_run``, tests/conftest.py); a test that
could change it works on a copy.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from cli_helpers import SETS, assert_one_line_error, cli, run
from neural_brdf import export, limits
from neural_brdf.train.model import RawBRDF


def digest(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones too) -> its SHA-256: 'nothing changed'."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def run_copy(tiny_run, tmp_path):
    folder = tmp_path / "run"
    shutil.copytree(tiny_run, folder)
    return folder


# ------------------------------------------------------------------ output = input
# .lock and trial.json too: a lock replaced by rename is no lock (the run holds the old)
@pytest.mark.parametrize(
    "name", ["ckpt.pt", "config.yaml", "log.csv", "metrics.json", ".lock", "trial.json"]
)
def test_export_refuses_a_file_of_its_own_run(capsys, run_copy, name):
    before = digest(run_copy)
    code, _, err = cli(capsys, "export", str(run_copy), "-o", str(run_copy / name))
    assert_one_line_error(code, err, name, "file of the run")
    assert digest(run_copy) == before


def test_export_into_its_run_s_model_onnx_is_allowed(capsys, run_copy):
    code, out, err = cli(capsys, "export", str(run_copy), "-o", str(run_copy / "model.onnx"))
    assert code in (0, 1), err  # 1 only when a physics check fails; the write is allowed
    assert "wrote" in out


def test_export_view_and_report_write_only_into_their_own_run(capsys, tiny_run, tmp_path):
    # the files a command may write into a run (model.onnx, viewer.html, the report) are
    # its own run's: into another run they would leave it describing two runs
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(tiny_run, a)
    shutil.copytree(tiny_run, b)
    (b / "viewer.html").write_text("b's viewer")
    before = digest(b)
    code, _, err = cli(capsys, "export", str(a), "-o", str(b / "model.onnx"))
    assert_one_line_error(code, err, "model.onnx", "file of the run")
    code, _, err = cli(capsys, "view", str(a / "model.onnx"), "-o", str(b / "viewer.html"))
    assert_one_line_error(code, err, "viewer.html", "file of the run")
    code, _, err = cli(capsys, "report", str(a), "-o", str(b))
    assert_one_line_error(code, err, str(b), "another run")
    assert digest(b) == before
    # the run's viewer is its own model's: not another file's put into the run
    shutil.copy(b / "model.onnx", a / "other.onnx")
    code, _, err = cli(capsys, "view", str(a / "other.onnx"), "-o", str(a / "viewer.html"))
    assert_one_line_error(code, err, "viewer.html", "file of the run")
    (a / "other.onnx").unlink()
    # into their own run, as before
    code, _, err = cli(capsys, "view", str(a / "model.onnx"), "-o", str(a / "viewer.html"))
    assert code == 0, err
    code, _, err = cli(capsys, "report", str(a), "-o", str(a))
    assert code == 0, err
    assert (a / "viewer.html").is_file() and (a / "report.html").is_file()


def test_export_and_report_wait_for_no_run_still_going_in_their_folder(capsys, run_copy, tmp_path):
    # a run that holds its folder (training or resuming) keeps export and report out of
    # it; they replaced its model.onnx or report under it
    from neural_brdf import runfolder

    before = digest(run_copy)
    with runfolder.run_lock(run_copy):  # as a run still training holds it
        code, _, err = cli(capsys, "export", str(run_copy))
        assert_one_line_error(code, err, str(run_copy), "in use")
        code, _, err = cli(capsys, "report", str(run_copy))
        assert_one_line_error(code, err, str(run_copy), "in use")
        # a copy written elsewhere reads the checkpoint only
        code, _, err = cli(capsys, "export", str(run_copy), "-o", str(tmp_path / "m.onnx"))
        assert code in (0, 1), err
    assert {k: v for k, v in digest(run_copy).items() if k != ".lock"} == before


def test_codegen_refuses_to_write_over_its_model(capsys, run_copy):
    model = run_copy / "model.onnx"
    before = model.read_bytes()
    code, _, err = cli(capsys, "codegen", str(model), "--target", "c", "-o", str(model))
    assert_one_line_error(code, err, "model.onnx", "reads")
    # the same file under another name: a hard link
    alias = run_copy.parent / "alias.onnx"
    alias.hardlink_to(model)
    code, _, err = cli(capsys, "codegen", str(model), "--target", "glsl", "-o", str(alias))
    assert_one_line_error(code, err, "alias.onnx")
    assert model.read_bytes() == before


def test_validate_refuses_a_json_over_its_model(capsys, run_copy):
    model = run_copy / "model.onnx"
    before = model.read_bytes()
    code, _, err = cli(capsys, "validate", str(model), "--json", str(model))
    assert_one_line_error(code, err, "--json", "model.onnx")
    assert model.read_bytes() == before


def test_view_and_bake_refuse_their_inputs(capsys, run_copy, tmp_path):
    model = run_copy / "model.onnx"
    before = digest(run_copy)
    code, _, err = cli(capsys, "view", str(model), "-o", str(model))
    assert_one_line_error(code, err, "model.onnx")
    code, _, err = cli(capsys, "view", str(model), "-o", str(run_copy / "ckpt.pt"))
    assert_one_line_error(code, err, "ckpt.pt")
    code, _, err = cli(capsys, "bake", str(model), "-o", str(run_copy / "metrics.bsdf"))
    assert code == 0, err  # a new file beside the run's own: fine
    (run_copy / "metrics.bsdf").unlink()
    assert digest(run_copy) == before


# ------------------------------------------------------------------ run names
@pytest.mark.parametrize("name", ["../..", "/tmp/escaped", "", ".", "a/b", "-rf", ".hidden"])
def test_a_run_name_is_a_plain_folder_name(capsys, tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "cfg.yaml").write_text(f"name: {name!r}\ntarget: {{model: lambertian}}\n")
    code, _, err = cli(capsys, "train", "cfg.yaml", *SETS)
    assert_one_line_error(code, err, "name:")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.yaml"]  # no runs/ made


# ------------------------------------------------------------------ sizes
def alias_bomb(levels: int) -> str:
    """``levels`` lists of ten aliases of the one below: 10**levels values in ~60 bytes a
    level."""
    lines = ["defs:", "  a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    for i in range(1, levels):
        lines.append(f"  a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    return "\n".join(lines) + f"\ntarget:\n  params:\n    alpha: *a{levels - 1}\n"


@pytest.mark.parametrize("levels", [5, 9])
def test_a_yaml_alias_bomb_is_refused_in_one_short_line(capsys, tmp_path, levels):
    path = tmp_path / "bomb.yaml"
    path.write_text(alias_bomb(levels))
    code, _, err = cli(capsys, "train", str(path), "--out", str(tmp_path / "run"))
    assert_one_line_error(code, err, "bomb.yaml", "expands to more than")
    assert len(err) <= limits.MAX_MESSAGE + 1
    assert not (tmp_path / "run").exists()


def test_an_alias_bomb_in_a_set_value_is_refused(capsys, tmp_path):
    value = "[" + ", ".join(["&a [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]"] + ["*a"] * 20000) + "]"
    code, _, err = cli(capsys, "train", "lambert", "--set", f"target.params.x={value}")
    assert_one_line_error(code, err, "--set target.params.x", "expands to more than")


def test_error_texts_are_bounded(capsys, tmp_path):
    code, _, err = cli(capsys, "train", "lambert", "--set", f"train.{'x' * 5000}=1")
    assert_one_line_error(code, err, "unknown key")
    assert len(err.strip()) <= limits.MAX_MESSAGE
    code, _, err = cli(capsys, "train", "lambert", "--set", f"name={'n' * 5000}")
    assert_one_line_error(code, err, "name:")
    assert len(err.strip()) <= limits.MAX_MESSAGE


@pytest.mark.parametrize(
    "key, value",
    [
        ("model.hidden", "[100000000]"),
        ("data.pool_size", "10000000000000"),
        ("validation.accuracy_samples", "10000000000000"),
        ("data.batch_size", "1000000000000"),
    ],
)
def test_a_config_size_beyond_memory_is_refused_before_allocating(capsys, tmp_path, key, value):
    extra = ["--set", f"data.pool_size={value}"] if key == "data.batch_size" else []
    code, _, err = cli(
        capsys, "train", "lambert", "--out", str(tmp_path / "r"), "--set", f"{key}={value}", *extra
    )
    assert_one_line_error(code, err, key, "more than the limit")
    assert not (tmp_path / "r").exists()


def test_the_memory_budget_can_be_set(capsys, tmp_path, monkeypatch):
    """NEURAL_BRDF_MEMORY_LIMIT: the default config is refused under 1 MiB, trains under
    the default budget."""
    monkeypatch.setenv(limits.ENV_LIMIT, "1M")
    code, _, err = cli(capsys, "train", "lambert", "--out", str(tmp_path / "r"))
    assert_one_line_error(code, err, "lambert.yaml", "1.0 MiB", limits.ENV_LIMIT)
    monkeypatch.setenv(limits.ENV_LIMIT, "1G")
    code, _, err = cli(capsys, "train", "lambert", "--out", str(tmp_path / "r"), *SETS)
    assert code == 0, err


def graph_with(nodes, initializers, *, metadata=True) -> onnx.ModelProto:
    wi = helper.make_tensor_value_info("wi", TensorProto.FLOAT, ["N", 3])
    wo = helper.make_tensor_value_info("wo", TensorProto.FLOAT, ["N", 3])
    f = helper.make_tensor_value_info("f", TensorProto.FLOAT, ["N", 3])
    g = helper.make_graph(nodes, "hostile", [wi, wo], [f], initializers)
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    if metadata:
        helper.set_model_props(m, {"format_version": "2"})
    return m


def constant_of_shape_256_gib() -> onnx.ModelProto:
    shape = numpy_helper.from_array(np.array([1 << 26, 1024], np.int64), "shape")
    zero = numpy_helper.from_array(np.array([0.0], np.float32))
    return graph_with(
        [
            helper.make_node("ConstantOfShape", ["shape"], ["big"], value=zero),
            helper.make_node("ReduceSum", ["big"], ["s"], keepdims=0),
            helper.make_node("Add", ["wi", "wo"], ["a"]),
            helper.make_node("Add", ["a", "s"], ["f"]),
        ],
        [shape],
    )


def initializer_declaring(dims: list[int], nbytes: int) -> onnx.ModelProto:
    t = TensorProto(name="W", data_type=TensorProto.FLOAT, dims=dims, raw_data=b"\0" * nbytes)
    return graph_with(
        [
            helper.make_node("MatMul", ["wi", "W"], ["x"]),
            helper.make_node("Add", ["wi", "wo"], ["f"]),
        ],
        [t],
    )


HOSTILE = {
    "constant_of_shape": (constant_of_shape_256_gib, "ConstantOfShape", "more than the limit"),
    "huge_dims": (
        lambda: initializer_declaring([1 << 20, 1 << 20], 12),
        "'W'",
        "more than the limit",
    ),
    "short_data": (lambda: initializer_declaring([3, 1024], 12), "'W'", "but holds 12 bytes"),
}
COMMANDS = {
    "validate": ["validate", "{m}"],
    "codegen": ["codegen", "{m}", "--target", "c", "-o", "{d}/x.h"],
    "bake": ["bake", "{m}", "-o", "{d}/x.binary"],
    "view": ["view", "{m}", "-o", "{d}/v.html"],
    "render": ["render", "{m}", "-o", "{d}/r.png", "--spp", "1", "--resolution", "16"],
}


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("case", list(HOSTILE))
def test_an_onnx_that_declares_too_much_is_refused_by_every_command(
    capsys, tmp_path, case, command
):
    make, *needles = HOSTILE[case]
    path = tmp_path / f"{case}.onnx"
    onnx.save(make(), str(path))
    args = [a.format(m=path, d=tmp_path) for a in COMMANDS[command]]
    code, _, err = cli(capsys, *args)
    assert_one_line_error(code, err, f"{case}.onnx", *needles)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


# ------------------------------------------------------------------ smaller
def test_render_writes_png_or_jpeg_by_the_extension(capsys, tiny_run, tmp_path):
    model = str(tiny_run / "model.onnx")
    for name, magic in (
        ("a.png", b"\x89PNG"),
        ("b.jpg", b"\xff\xd8\xff"),
        ("c.JPEG", b"\xff\xd8\xff"),
    ):
        code, _, err = cli(
            capsys, "render", model, "-o", str(tmp_path / name), "--spp", "1", "--resolution", "16"
        )
        assert code == 0, err
        assert (tmp_path / name).read_bytes()[:3] == magic[:3], name
    for name in ("d.gif", "e", "/dev/full"):
        out = name if name.startswith("/") else str(tmp_path / name)
        code, _, err = cli(capsys, "render", model, "-o", out, "--spp", "1", "--resolution", "16")
        assert_one_line_error(code, err, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.jpg", "c.JPEG"]


def test_render_to_a_full_disk_is_one_line(tmp_path, tiny_run):
    """/dev/full as a .png (a link named like an image): ENOSPC, exit 2, no traceback."""
    link = tmp_path / "full.png"
    link.symlink_to("/dev/full")
    proc = run(
        "-m",
        "neural_brdf",
        "render",
        str(tiny_run / "model.onnx"),
        "-o",
        str(link),
        "--spp",
        "1",
        "--resolution",
        "16",
    )
    assert_one_line_error(proc.returncode, proc.stderr, "full.png", "No space left")


def test_render_and_bake_refuse_an_onnx_without_the_project_s_metadata(capsys, tmp_path):
    raw = RawBRDF("isotropic", [8], "silu", init_value=0.2).eval()
    path = tmp_path / "foreign.onnx"
    path.write_bytes(export.to_onnx_bytes(raw, 17))  # right inputs, no metadata
    code, _, err = cli(capsys, "bake", str(path), "-o", str(tmp_path / "x.binary"))
    assert_one_line_error(code, err, "foreign.onnx", "metadata")
    code, _, err = cli(capsys, "render", str(path), "-o", str(tmp_path / "x.png"))
    assert_one_line_error(code, err, "foreign.onnx", "metadata")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign.onnx"]


def test_ctrl_c_outside_training_names_itself(capsys, tiny_run, monkeypatch):
    from neural_brdf import validate

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt()  # as Python raises it on Ctrl-C: no message

    monkeypatch.setattr(validate, "report", interrupted)
    code, _, err = cli(capsys, "validate", str(tiny_run / "model.onnx"))
    assert code == 130
    assert err.strip() == "neural-brdf: interrupted (Ctrl-C)"


def test_train_many_says_which_file_holds_a_bad_config(capsys, tmp_path):
    good = tmp_path / "good.yaml"
    bad = tmp_path / "bad.yaml"
    good.write_text("target: {model: microfacet, params: {alpha: 0.3}}\n")
    bad.write_text("target: {model: microfacet, params: {alpah: 0.3}}\n")
    code, _, err = cli(
        capsys, "train-many", str(good), str(bad), "--out", str(tmp_path / "o"), *SETS
    )
    assert_one_line_error(code, err, "bad.yaml", "alpah")
    bad.write_text("target: {model: microfacet, params: {alpha: 0.3}}\ntrain: {lr: 0.5}\n")
    code, _, err = cli(
        capsys, "train-many", str(good), str(bad), "--out", str(tmp_path / "o"), *SETS
    )
    assert_one_line_error(code, err, "bad.yaml", "train.lr", "differs from", "good.yaml")
    assert not (tmp_path / "o").exists()


def test_train_many_summary_says_physics_and_reports_the_error(capsys, tmp_path):
    """A model trained 1 step is far from its target: the summary must not call it
    'passed' without saying that only the physics was judged, and it shows the error."""
    a = tmp_path / "a.yaml"
    a.write_text("target: {model: microfacet, params: {alpha: 0.1}}\n")
    code, out, err = cli(
        capsys, "train-many", str(a), "--out", str(tmp_path / "o"), *SETS, "--set", "train.steps=1"
    )
    last = out.strip().splitlines()[-1]
    assert "passed the physics checks" in last, last
    assert "worst rel_rmse" in last and "(a)" in last, last
    assert code in (0, 1), err


# ------------------------------------------------------------------ empty and huge values
@pytest.mark.parametrize(
    "argv, flag",
    [
        (["train", "lambert", "--out", ""], "--out"),
        (["validate", "MODEL", "--json", ""], "--json"),
        (["report", "RUN", "-o", " "], "--out"),
        (["render", "", "-o", "x.png"], "MODEL"),
        (["train-many", "lambert", "", "--out", "OUT"], "CONFIG"),
    ],
)
def test_an_empty_path_is_refused_not_taken_as_not_given(
    capsys, tiny_run, tmp_path, monkeypatch, argv, flag
):
    """An unset shell variable gives an empty path: the run went to runs/NAME, the JSON
    nowhere, exit 0."""
    monkeypatch.chdir(tmp_path)
    subs = {"MODEL": str(tiny_run / "model.onnx"), "RUN": str(tiny_run), "OUT": "out"}
    sets = SETS if argv[0].startswith("train") else []
    code, _, err = cli(capsys, *[subs.get(a, a) for a in argv], *sets)
    assert_one_line_error(code, err, f"{flag}: an empty path")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no runs/, no out/


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--resolution", "100000000"], "at most"),
        (["--spp", "2000000000", "--resolution", "8"], "2^32"),
    ],
)
def test_render_refuses_a_size_mitsuba_cannot_render(capsys, tiny_run, tmp_path, args, needle):
    """A huge --resolution or --spp gave Mitsuba's traceback (exit 1)."""
    out = tmp_path / "r.png"
    code, _, err = cli(capsys, "render", str(tiny_run / "model.onnx"), "-o", str(out), *args)
    assert_one_line_error(code, err, "render: --", needle)
    assert not out.exists()


@pytest.mark.parametrize("value", ["inf", "nan", "0", "-5G", "-inf", "abc"])
def test_a_memory_limit_that_is_no_size_is_refused(capsys, tiny_run, monkeypatch, value):
    """inf gave a traceback; 0, negative and nan fell back to the default in silence."""
    monkeypatch.setenv(limits.ENV_LIMIT, value)
    code, _, err = cli(capsys, "validate", str(tiny_run / "model.onnx"))
    assert_one_line_error(code, err, f"{limits.ENV_LIMIT}={value!r}", "positive number of bytes")
