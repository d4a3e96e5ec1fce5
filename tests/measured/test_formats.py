"""The registry of measured formats (neural_brdf/measured/formats.py) and what every
format shares (measured/base.py).

docs/architecture.md's recipe "A measured format" is exercised here as written: a toy
format (``.toy``: one line ``toy-lambert R G B``, an analytic Lambertian of that albedo)
is a reader returning a ``MeasuredBRDF``, a writer, and one ``formats.register`` call;
it is then a ``target.data`` to train on, a ``validate --reference`` and a ``bake``
output, with no other file changed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import analytic
from cli_helpers import SETS, assert_one_line_error, cli
from neural_brdf import config
from neural_brdf.errors import InputError
from neural_brdf.measured import formats, merl, rgl
from neural_brdf.measured.base import Pairs, eval_pairs
from neural_brdf.train import data

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
LAMBERT = CONFIGS / "lambert.yaml"  # albedo (0.8, 0.6, 0.4)


# ----------------------------------------------------------------- the toy format
class ToyError(ValueError):
    """Deliberately not an InputError: the registry turns it into one."""


class ToyBRDF:
    """A Lambertian read from a ``.toy`` file: the MeasuredBRDF protocol, nothing else."""

    anisotropic = False
    dense_at_peak = False  # training adds data.peak pairs near the mirror direction
    drawn = 0  # pairs handed out by sample_pairs, over all instances (the training test)

    def __init__(self, albedo, *, source: str):
        self.albedo = np.asarray(albedo, dtype=np.float64)
        self.source = source

    def describe(self) -> str:
        return f"TOY {self.source} (albedo {' '.join(f'{a:g}' for a in self.albedo)})"

    def eval(self, wi, wo) -> np.ndarray:
        def lookup(a, b):
            return np.tile(self.albedo / math.pi, (len(a), 1))

        return eval_pairs(wi, wo, lookup, chunk=4096)

    def sample_pairs(self, n: int, rng=None) -> Pairs:
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        u = rng.random((2, n, 2))
        wi, wo = (
            np.stack(
                [
                    np.sqrt(x[:, 0]) * np.cos(2 * math.pi * x[:, 1]),
                    np.sqrt(x[:, 0]) * np.sin(2 * math.pi * x[:, 1]),
                    np.sqrt(1.0 - x[:, 0] * (1 - 1e-9)),
                ],
                -1,
            )
            for x in u
        )
        ToyBRDF.drawn += n
        return wi, wo, self.eval(wi, wo)

    def grid_pairs(self, n: int | None = None, seed: int = 0) -> Pairs:
        t = np.radians(np.arange(5.0, 90.0, 10.0))
        wi = np.stack([np.sin(t), 0 * t, np.cos(t)], -1)
        wi, wo = (a.reshape(-1, 3) for a in np.broadcast_arrays(wi[:, None], wi[None]))
        if n is not None and n < len(wi):
            pick = np.sort(np.random.default_rng(seed).choice(len(wi), n, replace=False))
            wi, wo = wi[pick], wo[pick]
        return wi, wo, self.eval(wi, wo)


def read_toy(path) -> ToyBRDF:
    try:
        words = Path(path).read_text().split()
    except (OSError, UnicodeDecodeError) as e:
        raise ToyError(f"cannot read ({e})") from None
    if len(words) != 4 or words[0] != "toy-lambert":
        raise ToyError("not a toy file\n(expected: toy-lambert R G B)")  # two lines
    try:
        albedo = [float(w) for w in words[1:]]
    except ValueError:
        raise ToyError(f"{path}: albedo is not three numbers") from None
    return ToyBRDF(albedo, source=str(path))


def bake_toy(fn, path) -> None:
    """The albedo of ``fn`` from its value at normal incidence (exact for a Lambertian)."""
    f = fn if callable(fn) else fn.eval
    z = np.array([[0.0, 0.0, 1.0]])
    albedo = np.asarray(f(z, z), dtype=np.float64)[0] * math.pi
    Path(path).write_text("toy-lambert " + " ".join(repr(float(a)) for a in albedo) + "\n")


@pytest.fixture
def toy():
    fmt = formats.register(formats.Format("TOY", ".toy", read_toy, bake_toy, ToyError))
    try:
        yield fmt
    finally:
        formats.unregister(".toy")


# ------------------------------------------------------------ the recipe, exercised
def test_a_toy_format_trains_validates_and_bakes_through_the_public_paths(toy, tmp_path, capsys):
    # bake: a config's analytic target, written by the toy's writer (by the suffix)
    baked = tmp_path / "lambert.toy"
    code, out, err = cli(capsys, "bake", str(LAMBERT), "-o", str(baked))
    assert code == 0, err
    assert out.strip() == f"wrote {baked} (TOY)"
    np.testing.assert_allclose(formats.read(baked).albedo, [0.8, 0.6, 0.4], rtol=1e-12)

    # target.data: the toy file is the target, its pairs are what the network trains on
    cfg = config.load(CONFIGS / "merl.yaml", [f"target.data={baked}"])
    target = data.build_target(cfg.target)
    assert isinstance(target, data.MeasuredTarget) and isinstance(target.brdf, ToyBRDF)
    before = ToyBRDF.drawn
    run = tmp_path / "run"
    argv = ["train", str(CONFIGS / "merl.yaml"), "--out", str(run), *SETS]
    code, out, err = cli(capsys, *argv, "--set", f"target.data={baked}")
    assert code == 0, err
    assert ToyBRDF.drawn - before >= 2048  # the pool came from the toy's sample_pairs
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["reference"] == target.describe() == f"TOY {baked} (albedo 0.8 0.6 0.4)"
    assert metrics["accuracy"]["pairs"] == len(target.grid_pairs()[0]) == 81
    assert "peak" not in metrics  # measured data: no analytic peak probe
    # the bins are what training draws from: the report does not call them held out
    assert metrics["accuracy"]["pairs_from"] == "measured bins"
    report_md = (run / "report.md").read_text()
    assert "on 81 measured bin centres" in report_md and "held-out pairs" not in report_md
    # a metrics.json from before pairs_from: the reference, "TOY ...", names the format
    older = dict(
        metrics, accuracy={k: v for k, v in metrics["accuracy"].items() if k != "pairs_from"}
    )
    (run / "metrics.json").write_text(json.dumps(older))
    code, _, err = cli(capsys, "report", str(run))
    assert code == 0, err
    report_md = (run / "report.md").read_text()
    assert "on 81 measured bin centres" in report_md and "held-out pairs" not in report_md
    (run / "metrics.json").write_text(json.dumps(metrics))

    # validate --reference: the toy file, by its suffix (not read as a YAML config)
    report = tmp_path / "report.json"
    model = str(run / "model.onnx")
    code, out, err = cli(
        capsys, "validate", model, "--reference", str(baked), "--json", str(report)
    )
    assert code == 0, err
    report_json = json.loads(report.read_text())
    assert report_json["reference"] == target.describe()
    assert report_json["accuracy"]["pairs"] == 81


def test_a_data_path_is_the_config_folders_and_a_run_finds_it_from_anywhere(
    toy, tmp_path, capsys, monkeypatch
):
    # target.data in a config file is relative to the config's folder, as target.mitsuba
    # and target.images are; a --set value to the current folder; both made absolute
    (tmp_path / "cfg").mkdir()
    (tmp_path / "elsewhere").mkdir()
    bake_toy(lambda a, b: np.full((len(a), 3), 0.5 / math.pi), tmp_path / "cfg" / "m.toy")
    bake_toy(lambda a, b: np.full((len(a), 3), 0.2 / math.pi), tmp_path / "old.toy")
    cfg_file = tmp_path / "cfg" / "m.yaml"
    cfg_file.write_text("target:\n  data: m.toy\n")
    monkeypatch.chdir(tmp_path)
    assert config.load(cfg_file).target.data == str(tmp_path / "cfg" / "m.toy")
    assert config.load(cfg_file, ["target.data=old.toy"]).target.data == str(tmp_path / "old.toy")
    # a config written for the earlier rule (the current folder's) still finds its file
    (tmp_path / "cfg" / "old.yaml").write_text("target:\n  data: old.toy\n")
    assert config.load(tmp_path / "cfg" / "old.yaml").target.data == str(tmp_path / "old.toy")
    # ~ is the home folder, as a shell reads it (it was a folder "~" beside the config)
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "cfg" / "home.yaml").write_text("target:\n  data: ~/old.toy\n")
    assert config.load(tmp_path / "cfg" / "home.yaml").target.data == str(tmp_path / "old.toy")
    # a missing file is named by the path it was looked for at
    (tmp_path / "cfg" / "gone.yaml").write_text("target:\n  data: gone.toy\n")
    code, _, err = cli(capsys, "train", "cfg/gone.yaml", "--out", "r0", *SETS)
    assert_one_line_error(
        code, err, "target.data", str(tmp_path / "cfg" / "gone.toy"), "--set target.data=FILE"
    )

    # a run trained here is exported, reported and resumed from another folder
    code, _, err = cli(capsys, "train", "cfg/m.yaml", "--out", "run", *SETS)
    assert code == 0, err
    reference = json.loads((tmp_path / "run" / "metrics.json").read_text())["reference"]
    assert reference == f"TOY {tmp_path / 'cfg' / 'm.toy'} (albedo 0.5 0.5 0.5)"
    monkeypatch.chdir(tmp_path / "elsewhere")
    code, _, err = cli(capsys, "export", str(tmp_path / "run"))
    assert code == 0, err
    code, _, err = cli(capsys, "report", str(tmp_path / "run"))
    assert code == 0, err
    again = json.loads((tmp_path / "run" / "metrics.json").read_text())["reference"]
    assert again == reference

    # a checkpoint saved before paths were made absolute (target.data as given, read
    # against the current folder) still resumes with the same file, and not another
    from neural_brdf.train import session

    monkeypatch.chdir(tmp_path)
    cfg = config.load(cfg_file)
    saved = cfg.model_dump()
    saved["target"]["data"] = "cfg/m.toy"
    session.check_resumable(saved, cfg)
    saved["target"]["data"] = "old.toy"
    with pytest.raises(config.ConfigError, match=r"^target\.data: differs"):
        session.check_resumable(saved, cfg)


def test_unknown_suffixes_and_bad_files_are_one_line_errors(toy, tmp_path, capsys):
    with pytest.raises(InputError) as e:
        formats.format_of(tmp_path / "m.exr")
    msg = str(e.value)
    assert "\n" not in msg and str(tmp_path / "m.exr") in msg and "'.exr'" in msg
    # every registered format, the built-ins and the toy, in registration order
    assert msg.endswith(f"known: {formats.known()}") and ".toy (TOY)" in msg
    assert all(f"{suffix} ({name})" in msg for name, suffix in BUILTIN.items())
    assert formats.format_of(tmp_path / "M.TOY") is toy  # case-insensitive

    train = ["train", str(CONFIGS / "merl.yaml"), "--out", str(tmp_path / "run")]
    code, _, err = cli(capsys, *train, "--set", f"target.data={tmp_path / 'm.exr'}")
    assert_one_line_error(code, err, "target.data", "m.exr", ".toy (TOY)")

    # the toy's own error (a ValueError over two lines) becomes one InputError line
    bad = tmp_path / "bad.toy"
    bad.write_text("not a toy\n")
    with pytest.raises(InputError) as e:
        formats.read(bad)
    assert not isinstance(e.value, ToyError) and "\n" not in str(e.value)
    assert str(e.value).startswith(f"{bad}: not a toy file")
    code, _, err = cli(capsys, *train, "--set", f"target.data={bad}")
    assert_one_line_error(code, err, "target.data", str(bad), "not a toy file")
    code, _, err = cli(capsys, "validate", str(tmp_path / "m.onnx"), "--reference", str(bad))
    assert_one_line_error(code, err, "--reference", str(bad))
    missing = tmp_path / "missing.toy"
    code, _, err = cli(capsys, *train, "--set", f"target.data={missing}")
    assert_one_line_error(code, err, "target.data", str(missing), "cannot read")

    # bake lists every registered output format, the toy's included, and writes nothing
    code, _, err = cli(capsys, "bake", str(LAMBERT), "-o", str(tmp_path / "m.exr"))
    assert_one_line_error(code, err, "'.exr'", ".binary (MERL)", ".bsdf (RGL)", ".toy (TOY)")
    assert not (tmp_path / "m.exr").exists()


def test_the_cli_help_lists_every_registered_format(toy, capsys):
    # bake's and validate's help are built from the registry: the toy is in them
    for command in ("bake", "validate"):
        with pytest.raises(SystemExit) as e:
            cli(capsys, command, "--help")
        assert e.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        assert formats.known() in text and ".toy (TOY)" in text, text


def test_the_registry_refuses_a_taken_or_malformed_suffix(toy):
    names = [f.name for f in formats.all_formats()]
    assert set(BUILTIN) <= set(names) and names[-1] == "TOY"  # in registration order
    known = formats.known()
    assert known == ", ".join(f"{f.suffix} ({f.name})" for f in formats.all_formats())
    with pytest.raises(ValueError, match="already the suffix of TOY"):
        formats.register(formats.Format("TWO", ".toy", read_toy, bake_toy))
    for bad in ("toy", ".TOY", ".", "x/.toy"):
        with pytest.raises(ValueError, match="suffix"):
            formats.Format("BAD", bad, read_toy, bake_toy)
    formats.unregister(".toy")
    assert formats.find("x.toy") is None
    assert formats.known() == known.removesuffix(", .toy (TOY)") != known
    assert [f.name for f in formats.all_formats()] == names[:-1]


# ------------------------------------------------------------- the built-in formats
@pytest.fixture(scope="module")
def builtin(tmp_path_factory):
    """name -> (path, the file read back through the registry): a Lambertian of albedo
    (0.8, 0.6, 0.4) in each built-in format (RGL at a coarse resolution)."""
    folder = tmp_path_factory.mktemp("formats")
    lam = analytic.create("lambertian", albedo=[0.8, 0.6, 0.4])
    merl.write_merl(folder / "l.binary", np.full(merl.SHAPE + (3,), 0.1))
    rgl.bake(lam.eval, folder / "l.bsdf", theta_i=4, sample=8, vndf=8, ndf=8)
    return {n: (folder / f"l{s}", formats.read(folder / f"l{s}")) for n, s in BUILTIN.items()}


BUILTIN = {"MERL": ".binary", "RGL": ".bsdf"}


def test_builtin_formats_are_registered_by_suffix():
    # the built-ins are there (a format registered later does not change them)
    registered = {f.name: f.suffix for f in formats.all_formats()}
    assert {n: registered.get(n) for n in BUILTIN} == BUILTIN
    assert formats.MERL.read is not None and formats.find("X.BINARY") is formats.MERL
    assert formats.find("x.bsdf") is formats.RGL and formats.find("x.binary.gz") is None


@pytest.mark.parametrize("name", list(BUILTIN))
def test_builtin_readers_give_the_measured_brdf_protocol(builtin, name):
    path, brdf = builtin[name]
    assert brdf.anisotropic is False and brdf.source == str(path)
    if name == "MERL":  # the texts export writes into model.onnx's metadata: unchanged
        assert brdf.describe() == f"MERL {path} ({len(brdf.support)} measured bins)"
    else:
        assert brdf.describe() == f"RGL {path} (neural-brdf bake)"
    wi, wo, f = brdf.grid_pairs(40, seed=3)
    assert wi.shape == wo.shape == f.shape == (40, 3) and wi.dtype == np.float64
    assert bool((wi[:, 2] > 0).all() and (wo[:, 2] > 0).all())
    np.testing.assert_allclose(f, brdf.eval(wi, wo), rtol=1e-6)
    again = brdf.grid_pairs(40, seed=3)
    assert all(np.array_equal(a, b) for a, b in zip((wi, wo, f), again))
    assert len(brdf.grid_pairs()[0]) > 40
    wi, wo, f = brdf.sample_pairs(500, rng=1)
    assert f.shape == (500, 3) and bool((wi[:, 2] > 0).all() and (wo[:, 2] > 0).all())


def test_a_merl_file_without_measured_bins_above_the_horizon_is_refused(tmp_path):
    path = tmp_path / "empty.binary"
    merl.write_merl(path, np.full(merl.SHAPE + (3,), -1.0))  # every bin unmeasured
    assert len(merl.read_merl(path).support) == 0  # a valid file...
    with pytest.raises(InputError, match="no measured bins above the horizon"):
        formats.read(path)  # ...but not a measured BRDF


# ------------------------------------------------------- the edges every eval shares
UNIT = np.array([0.3, 0.1, 0.9]) / np.linalg.norm([0.3, 0.1, 0.9])
WO = np.array([-0.2, 0.4, 0.8]) / np.linalg.norm([-0.2, 0.4, 0.8])
ZERO_EDGES = {  # wi -> f must be exactly 0
    "grazing": [1.0, 0.0, 0.0],
    "below": [0.3, 0.1, -0.9],
    "zero vector": [0.0, 0.0, 0.0],
    "nan": [np.nan, 0.0, 1.0],
    "inf": [0.0, np.inf, 1.0],
    "-0 z": [0.5, 0.0, -0.0],
}
SCALES = [1e-200, 1e-160, 7.0, 1e160, 1e200]  # wi = UNIT * s: the same direction


@pytest.mark.parametrize("name", [*BUILTIN, "TOY"])
def test_every_format_shares_the_eval_edges(builtin, name):
    brdf = ToyBRDF([0.8, 0.6, 0.4], source="-") if name == "TOY" else builtin[name][1]
    wi = np.array(list(ZERO_EDGES.values()) + [UNIT * s for s in SCALES])
    with np.errstate(over="raise", divide="raise", invalid="raise"):  # none from the edges
        f = brdf.eval(wi, WO)
        swapped = brdf.eval(WO, wi)
    k = len(ZERO_EDGES)
    assert np.array_equal(f[:k], np.zeros((k, 3))) and np.array_equal(swapped[:k], f[:k])
    ref = brdf.eval(UNIT, WO)
    assert ref.shape == (3,) and bool((ref > 0).all())
    np.testing.assert_allclose(f[k:], np.tile(ref, (len(SCALES), 1)), rtol=1e-12)
    # broadcasting, and a wrong last axis
    assert brdf.eval(np.tile(UNIT, (4, 2, 1)), WO).shape == (4, 2, 3)
    with pytest.raises(ValueError, match="expected"):
        brdf.eval(np.zeros((5, 2)), np.zeros((5, 2)))


def test_eval_pairs_hands_the_lookup_unit_pairs_above_the_horizon_in_chunks():
    seen = []

    def lookup(a, b):
        seen.append(len(a))
        for v in (a, b):
            assert bool((v[:, 2] > 0).all())
            np.testing.assert_allclose(np.linalg.norm(v, axis=-1), 1.0, rtol=1e-15)
        return a + b

    wi = np.array(list(ZERO_EDGES.values()) + [UNIT * s for s in SCALES] * 3)
    out = eval_pairs(wi, WO * 3.0, lookup, chunk=4)
    k = len(ZERO_EDGES)
    assert seen == [4, 4, 4, 3]
    np.testing.assert_allclose(out[k:], np.tile(UNIT + WO, (3 * len(SCALES), 1)), rtol=1e-15)
    assert not out[:k].any()
