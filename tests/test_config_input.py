"""Config input that must be refused (or warned of) at load, in one line naming the key
or the file: non-finite numbers, an output scale the model cannot start from, a key
given twice, a ``target.images:`` with every entry commented out, and an ``images``
section that nothing reads."""

from __future__ import annotations

import re
import typing

import numpy as np
import pytest
import torch
from annotated_types import Ge, Gt, Le

from analytic import physics
from cli_helpers import ROOT, SETS, assert_one_line_error, cli
from neural_brdf import config
from neural_brdf.train.model import RawBRDF

CONFIGS = ROOT / "configs"
QUICKSTART = CONFIGS / "quickstart.yaml"


# ------------------------------------------------------------ non-finite numbers
def _float_keys(section: type, prefix: str = "") -> list[tuple[str, bool]]:
    """(dotted key, is a list) of every float setting of the schema, found by walking it."""
    out = []
    for name, field in section.model_fields.items():
        ann, key = field.annotation, f"{prefix}{name}"
        if isinstance(ann, type) and issubclass(ann, config._Section):
            out += _float_keys(ann, key + ".")
        elif typing.get_origin(ann) is list and typing.get_args(ann) == (float,):
            out.append((key, True))
        elif ann is float or float in typing.get_args(ann):  # float, float | None
            out.append((key, False))
    return out


FLOAT_KEYS = _float_keys(config.Config)


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan", "1e999"])
@pytest.mark.parametrize("key, is_list", FLOAT_KEYS, ids=[k for k, _ in FLOAT_KEYS])
def test_every_float_setting_refuses_a_non_finite_value(key, is_list, value):
    text = f"[{value}]" if is_list else value
    with pytest.raises(config.ConfigError) as err:
        config.load(QUICKSTART, [f"{key}={text}"])
    msg = str(err.value)
    assert "\n" not in msg
    assert f"{key}:" in msg or f"{key}.0:" in msg, msg
    assert "finite number" in msg, msg


@pytest.mark.parametrize(
    "key, value",
    [
        ("train.lr", ".inf"),
        ("model.grid.init_std", ".inf"),  # nested
        ("images.poor_start_loss", "-.inf"),  # optional
        ("images.albedo_incidences", "[0.0, .inf]"),  # a list
    ],
)
def test_an_infinite_setting_in_a_file_exits_2_naming_file_and_key(capsys, tmp_path, key, value):
    assert dict(FLOAT_KEYS)[key] is value.startswith("[")  # the walk above finds each kind
    *sections, name = key.split(".")
    text = f"{name}: {value}"
    for section in reversed(sections):
        text = f"{section}: {{{text}}}"
    cfg = tmp_path / "inf.yaml"
    cfg.write_text(f"target: {{model: lambertian}}\n{text}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"), *SETS)
    assert_one_line_error(code, err, str(cfg), key, "finite number")
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------ model.output_scale
def _bounds(model: type, name: str) -> tuple[float, float]:
    lo = hi = None
    for m in model.model_fields[name].metadata:
        lo = m.ge if isinstance(m, Ge) else m.gt if isinstance(m, Gt) else lo
        hi = m.le if isinstance(m, Le) else hi
    assert lo is not None and hi is not None, f"{name}: no documented range"
    return lo, hi


@pytest.mark.parametrize("which", [0, 1], ids=["lowest", "highest"])
def test_every_output_scale_accepted_builds_a_finite_model(which):
    scale = _bounds(config.Model, "output_scale")[which]
    cfg = config.load(QUICKSTART, [f"model.output_scale={scale!r}"])
    torch.manual_seed(0)
    net = RawBRDF.from_config(cfg.model)  # raised RuntimeError for 1e-300
    wi = torch.as_tensor(physics.random_directions(64, 1), dtype=torch.float32)
    wo = torch.as_tensor(physics.random_directions(64, 2), dtype=torch.float32)
    with torch.no_grad():
        f = net(wi, wo)
    assert torch.isfinite(f).all()
    # the head starts at output_scale * softplus(bias) = init_value (0.3) whatever the
    # scale, before the grazing factor divides it
    m = cfg.model
    cos = torch.stack([wi[:, 2], wo[:, 2]])
    cos = cos.mean(0) if m.grazing_cos == "mean" else cos.amax(0)
    undone = f * cos[:, None] ** m.grazing_power
    assert torch.allclose(undone, torch.full_like(undone, 0.3), rtol=1e-3)


@pytest.mark.parametrize(
    "override, key",
    [
        ("model.output_scale=1e-300", "model.output_scale"),
        ("model.output_scale=1e300", "model.output_scale"),
        ("model.grid.init_std=1e300", "model.grid.init_std"),
        ("model.cosine_grid.init_std=1e300", "model.cosine_grid.init_std"),
    ],
)
def test_a_finite_but_absurd_scale_is_refused_at_load(capsys, tmp_path, override, key):
    code, _, err = cli(
        capsys, "train", str(QUICKSTART), "--out", str(tmp_path / "r"), *SETS, "--set", override
    )
    assert_one_line_error(code, err, f"--set {override}", f"{key}:")
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------ a key given twice
@pytest.mark.parametrize(
    "text, key",
    [
        # the audit's case: a second train section replaced the first (steps 2, lr 0.01)
        ("train: {steps: 2, lr: 0.01}\nmodel: {hidden: [8]}\ntrain: {progress: false}\n", "train"),
        ("target: {model: lambertian}\ntrain:\n  steps: 2\n  lr: 0.01\n  steps: 3\n", "steps"),
        ("model:\n  grid:\n    size: 8\n    channels: 2\n    size: 4\n", "size"),
    ],
    ids=["top", "section", "nested"],
)
def test_a_key_given_twice_exits_2_naming_file_line_and_key(capsys, tmp_path, text, key):
    cfg = tmp_path / "twice.yaml"
    cfg.write_text(text)
    lines = text.splitlines()
    # the line of the key's second mention, counted from the text written here
    mentions = [i for i, s in enumerate(lines, 1) if s.strip().startswith(f"{key}:")]
    line = mentions[1]
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"), *SETS)
    assert_one_line_error(code, err, f"{cfg}: line {line}: duplicate key '{key}'")
    assert not (tmp_path / "r").exists()


def test_a_key_given_twice_in_a_set_value_is_refused_but_a_merge_may_override(tmp_path):
    with pytest.raises(config.ConfigError) as err:
        config.load(QUICKSTART, ["target.params={roughness: 0.1, roughness: 0.5}"])
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith("--set target.params:") and "duplicate key 'roughness'" in msg
    # a key beside a "<<:" merge overrides the merged one: that is not a key given twice
    cfg = tmp_path / "merge.yaml"
    cfg.write_text(
        "train: &t {steps: 7, lr: 0.01}\nvalidation: {seed: 3}\n"
        "export: {<<: {parity_pairs: 64, parity_tol: 0.001}, parity_pairs: 32}\n"
    )
    loaded = config.load(cfg)
    assert (loaded.train.steps, loaded.export.parity_pairs) == (7, 32)
    assert loaded.export.parity_tol == 0.001


# ------------------------------------------------------------ target.images: empty
def test_target_images_with_every_entry_commented_out_exits_2(capsys, tmp_path):
    cfg = tmp_path / "views.yaml"
    cfg.write_text("target:\n  images:\n  #  - {scene: v.xml, image: v.exr}\n")
    code, _, err = cli(capsys, "train", str(cfg), "--out", str(tmp_path / "r"), *SETS)
    assert_one_line_error(code, err, str(cfg), "target.images", "no views")
    assert not (tmp_path / "r").exists()
    # an explicit null (as defaults.yaml and every run's config.yaml write it) and an
    # absent key are still "no images fit"
    for text in ["target:\n  images: null\n", "target: {model: lambertian}\n"]:
        cfg.write_text(text)
        assert config.load(cfg).target.images is None


# ------------------------------------------------------------ images: ignored
def test_images_keys_for_an_analytic_target_warn_in_one_line(tmp_path):
    cfg = tmp_path / "ana.yaml"
    cfg.write_text("target: {model: microfacet}\nimages: {spp: 4}\n")
    warnings: list[str] = []
    config.load(cfg, warn=warnings.append)
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert warnings[0].startswith(f"{cfg}: images.spp: ignored"), warnings
    # none where nothing is ignored: defaults.yaml's images section lists every default,
    # a default spelled out changes nothing, and an images fit reads the section
    for path, sets in [
        (CONFIGS / "defaults.yaml", []),
        (QUICKSTART, [f"images.spp={config.Images().spp}"]),
        (None, ["target.images=[{scene: s.xml, image: i.exr}]", "images.spp=4"]),
    ]:
        warnings.clear()
        config.load(path, sets, warn=warnings.append)
        assert not warnings, (path, sets, warnings)


def test_an_images_key_from_set_is_blamed_on_the_set(capsys, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")  # the run stops at once, after the warning
    code, _, err = cli(
        capsys, "train", "lambert", "--out", str(a_file), "--set", "images.primal_spp=3"
    )
    warning, error = err.strip().splitlines()
    assert warning.startswith("warning: --set images.primal_spp=3: images.primal_spp: ignored")
    assert_one_line_error(code, error, str(a_file))


# ------------------------------------------------------------ texture: ignored
@pytest.mark.parametrize(
    "target, named",
    [
        ("{model: microfacet}", "an analytic target (microfacet)"),
        ("{data: x.binary}", "measured data (target.data)"),
        ("{images: [{scene: s.xml, image: i.exr}]}", "an images fit (target.images)"),
    ],
    ids=["analytic", "data", "images"],
)
def test_texture_keys_for_a_target_without_a_teacher_warn_in_one_line(tmp_path, target, named):
    """Only a Mitsuba teacher that varies over the surface reads ``texture``: on any other
    target the section trained a homogeneous model without a word (a homogeneous teacher
    said so: pipeline.teacher_warnings)."""
    cfg = tmp_path / "t.yaml"
    cfg.write_text(f"target: {target}\ntexture: {{lobes: 3, weights: rgb}}\n")
    warnings: list[str] = []
    config.load(cfg, warn=warnings.append)
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert warnings[0].startswith(f"{cfg}: texture.lobes, texture.weights: ignored"), warnings
    assert "target.mitsuba" in warnings[0] and named in warnings[0]


def test_texture_keys_warn_only_where_nothing_reads_them(tmp_path):
    """No warning where the section is read or says nothing: a Mitsuba teacher (its file
    decides whether it varies; the run says so if not), defaults.yaml (every default
    spelled out) and a default value given again."""
    (tmp_path / "teacher.xml").write_text('<bsdf version="3.0.0" type="diffuse"/>\n')
    teacher = tmp_path / "teacher.yaml"
    teacher.write_text("target: {mitsuba: teacher.xml}\ntexture: {lobes: 3}\n")
    warnings: list[str] = []
    for path, sets in [
        (teacher, ["texture.resolution=8"]),
        (CONFIGS / "defaults.yaml", []),
        (QUICKSTART, [f"texture.lobes={config.Texture().lobes}"]),
    ]:
        config.load(path, sets, warn=warnings.append)
        assert not warnings, (path, sets, warnings)


def test_a_texture_key_from_set_is_blamed_on_the_set(capsys, tmp_path):
    """``neural-brdf train gold --set texture.lobes=3``: the warning names the --set."""
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")  # the run stops at once, after the warning
    code, _, err = cli(capsys, "train", "gold", "--out", str(a_file), "--set", "texture.lobes=3")
    warning, error = err.strip().splitlines()
    assert warning.startswith("warning: --set texture.lobes=3: texture.lobes: ignored"), warning
    assert_one_line_error(code, error, str(a_file))


# ------------------------------------------------------------ seeds
def _seed_keys(section: type, prefix: str = "") -> list[str]:
    """Every integer seed of the schema (``seed``, ``*_seed``), found by walking it."""
    out = []
    for name, field in section.model_fields.items():
        ann, key = field.annotation, f"{prefix}{name}"
        if isinstance(ann, type) and issubclass(ann, config._Section):
            out += _seed_keys(ann, key + ".")
        elif (name == "seed" or name.endswith("_seed")) and int in (ann, *typing.get_args(ann)):
            out.append(key)
    return out


SEED_KEYS = _seed_keys(config.Config)


def _section_and_field(key: str):
    *sections, name = key.split(".")
    node: type = config.Config
    for s in sections:
        node = node.model_fields[s].annotation
    return node, name


def test_the_seed_walk_finds_the_training_and_validation_seeds():
    assert {"train.seed", "validation.seed"} <= set(SEED_KEYS)


@pytest.mark.parametrize("value", ["-1", str(2**63 - 1), "99999999999999999999"])
@pytest.mark.parametrize("key", SEED_KEYS)
def test_every_seed_refuses_a_value_that_cannot_seed(key, value):
    """torch and numpy take a seed in int64 (numpy: not negative); a larger one ended in
    "Overflow when unpacking long long", a traceback after training."""
    with pytest.raises(config.ConfigError) as err:
        config.load(QUICKSTART, [f"{key}={value}"])
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"--set {key}={value}: {key}:"), msg


def test_a_huge_train_seed_exits_2_before_training(capsys, tmp_path):
    over = "train.seed=9223372036854775807"
    code, _, err = cli(
        capsys, "train", "quickstart", "--out", str(tmp_path / "r"), *SETS, "--set", over
    )
    assert_one_line_error(code, err, f"--set {over}", "train.seed:")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("key", SEED_KEYS)
def test_the_largest_seed_accepted_survives_the_seeds_derived_from_it(key):
    """The largest seed each key accepts, through the largest derived seeds: the
    furnace's re-measurement (seed + 3 + REMEASURE_SEED, then times 7919 per replica in
    quadrature.albedo) and an images fit's albedo directions (seed * 7919 + step)."""
    from neural_brdf import validate
    from neural_brdf.physics import quadrature

    section, name = _section_and_field(key)
    hi = [m.lt - 1 for m in section.model_fields[name].metadata if hasattr(m, "lt")]
    hi += [m.le for m in section.model_fields[name].metadata if hasattr(m, "le")]
    assert hi, f"{key}: no upper bound"
    top = min(hi)
    config.load(QUICKSTART, [f"{key}={top}"])  # accepted
    wi = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], dtype=torch.float64)
    rho, _ = quadrature.albedo(
        lambda a, b: torch.ones(len(a), 1), wi, 64, seed=top + 3 + validate.REMEASURE_SEED
    )
    assert torch.isfinite(rho).all()
    quadrature.mis_directions(wi, 8, top * 7919 + 10**7)
    torch.Generator().manual_seed(top * 7919 + 10**7)
    np.random.default_rng(top * 1_000_003 + 10**7)


# ------------------------------------------------------------ whose error: the file or a --set
@pytest.mark.parametrize(
    "text, sets, blamed, key",
    [
        # the walkthrough's cases: an error in the file, an unrelated --set in its section
        ("train: {progress: maybe}\n", ["train.steps=5"], None, "train.progress"),
        ("model: {grid: {coords: half_disc}}\n", ["model.hidden=[8]"], None, "model.grid.coords"),
        # two --sets in one section: the one that failed
        ("", ["train.progress=maybe", "train.log_every=1"], 0, "train.progress"),
        # a section check that a --set broke through another key the message names
        (
            "model: {encoding: anisotropic, grid: {coords: half_disc}}\n",
            ["model.hidden=[8]", "model.encoding=isotropic"],
            1,
            "model.grid.coords",
        ),
        ("data: {pool_size: 4096}\n", ["data.batch_size=8192"], 0, "data.pool_size"),
        (
            "data: {pool_size: 4096, batch_size: 8192}\n",
            ["data.uniform=0.5"],
            None,
            "data.pool_size",
        ),
        # the key itself, or a section holding it, given by --set
        ("", ["train.steps=5", "model.grid={size: 1}"], 1, "model.grid.size"),
        # or a key under it, which made the value a section
        ("", ["train.steps.x=5"], 0, "train.steps"),
        ("", ["model.hidden.0=5", "train.steps=5"], 0, "model.hidden"),
    ],
)
def test_an_error_names_the_file_or_the_set_that_gave_it(tmp_path, text, sets, blamed, key):
    cfg = tmp_path / "mine.yaml"
    cfg.write_text(text or "target: {model: lambertian}\n")
    with pytest.raises(config.ConfigError) as err:
        config.load(cfg, sets)
    where = str(cfg) if blamed is None else f"--set {sets[blamed]}"
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"{where}: {key}"), msg


# ------------------------------------------------------------ a target's parameters
@pytest.mark.parametrize(
    "params, sets, blamed, needle",
    [
        ("alpha: 0.3", ["target.params.alpha=-1"], 0, "alpha: must lie in"),
        ("alpha: 0.3", ["train.steps=5", "target.params.albedo=[1, 1, 1]"], 1, "albedo: unknown"),
        ("roughness: 0.3", ["target.params.alpha=0.3", "train.steps=5"], None, "roughness"),
    ],
)
def test_a_bad_target_parameter_names_its_set_or_the_file(
    capsys, tmp_path, params, sets, blamed, needle
):
    """The analytic model checks its parameters when the target is built, after the
    schema: its error names the --set that gave the parameter, as the schema's do, else
    the config file (here the file's misspelt ``roughness``)."""
    cfg = tmp_path / "mine.yaml"
    cfg.write_text(f"target: {{model: microfacet, params: {{{params}}}}}\n")
    argv = ["train", str(cfg), "--out", str(tmp_path / "r")]
    code, _, err = cli(capsys, *argv, *[a for s in sets for a in ("--set", s)])
    where = str(cfg) if blamed is None else f"--set {sets[blamed]}"
    assert_one_line_error(code, err, f"error: {where}: target.params: ", needle)
    assert not (tmp_path / "r" / "ckpt.pt").exists()


@pytest.mark.parametrize("key", ["train..steps", ".train", "train.", "train. .steps"])
def test_a_set_key_with_an_empty_part_is_refused(tmp_path, key):
    with pytest.raises(config.ConfigError) as e:
        config.load(None, [f"{key}=5"])
    assert str(e.value).startswith(f"--set {key}=5: an empty part in the key")


def test_a_set_fills_a_section_the_file_leaves_empty(tmp_path):
    """``train:`` with nothing under it is null in YAML: a --set of a key under it fills
    it (it said the --set's section 'is a value'), and without one the file is named."""
    cfg = tmp_path / "t.yaml"
    cfg.write_text("target: {model: lambertian}\ntrain:\n")
    assert config.load(cfg, ["train.steps=3"]).train.steps == 3
    with pytest.raises(config.ConfigError, match=f"^{re.escape(str(cfg))}: train: "):
        config.load(cfg)


def test_blamed_names_a_key_once_and_leaves_a_files_message():
    """config.blamed prefixes an error that starts with a key of the schema, once; a
    message that starts with a file of a key's name (train.yaml, images.yaml) is kept."""
    e = config.ConfigError
    got = config.blamed(e("target.params: alpha: bad"), "c.yaml", ["target.params.alpha=-1"])
    assert str(got) == "--set target.params.alpha=-1: target.params: alpha: bad"
    assert str(config.blamed(e("target.params: alpha: bad"), "c.yaml", [])) == (
        "c.yaml: target.params: alpha: bad"
    )
    for msg, source in [
        ("train.yaml: target.params: alpha: bad", "/abs/train.yaml"),
        ("images.yaml: line 3: bad", "images.yaml"),
        ("c.yaml: target.params: alpha: bad", "c.yaml"),
        ("runs/x/ckpt.pt: damaged", "c.yaml"),
    ]:
        assert str(config.blamed(e(msg), source, [])) == msg


# ------------------------------------------------------------ a misspelt key
def test_a_misspelt_key_is_named_before_the_one_it_leaves_missing(tmp_path):
    """``imgae`` for ``image``: two errors, and the message named the missing ``image``
    ("Field required") without a word of the typo."""
    cfg = tmp_path / "fit.yaml"
    cfg.write_text("target:\n  images: [{scene: v1.xml, imgae: v1.exr}]\n")
    with pytest.raises(config.ConfigError) as e:
        config.load(cfg)
    assert str(e.value) == f"{cfg}: target.images.0.imgae: unknown key (and 1 more)"


# ------------------------------------------------------------ a target path left empty
@pytest.mark.parametrize("key", ["target.data", "target.mitsuba"])
def test_an_empty_target_path_given_by_set_is_refused(key):
    """``--set target.data=$UNSET``: YAML reads the empty text as null, and the run
    trained the default Lambertian without a word; ``null`` written out still means none."""
    with pytest.raises(config.ConfigError) as e:
        config.load(None, [f"{key}="])
    assert str(e.value) == f"--set {key}=: an empty path; give the file (or null for none)"
    assert config.load(None, [f"{key}=null"]).target.model == "lambertian"


def test_a_target_section_that_names_no_brdf_is_warned_of(tmp_path):
    cfg = tmp_path / "empty_data.yaml"
    cfg.write_text("target: {data: }\n")
    warned: list[str] = []
    config.load(cfg, warn=warned.append)
    assert warned == [
        f"{cfg}: target: names no BRDF (model, data, mitsuba and images empty): training "
        "the default target (a lambertian BRDF)"
    ]
    cfg.write_text("target: {model: lambertian}\n")  # named: no warning
    warned.clear()
    config.load(cfg, warn=warned.append)
    assert warned == []


@pytest.mark.parametrize(
    "item, needle",
    [
        ("train.threads=100000", "train.threads"),  # crashed torch (SIGSEGV)
        ("train.steps=99999999999999999999999999999999", "train.steps"),  # trained for ever
    ],
)
def test_absurd_sizes_are_refused_naming_the_key(item, needle):
    with pytest.raises(config.ConfigError) as e:
        config.load(None, [item])
    assert str(e.value).startswith(f"--set {item}: {needle}: ")
