"""Config schema: defaults, presets, overrides and one-line errors naming the key."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import analytic
from analytic import physics
from neural_brdf import config, target
from neural_brdf.train import data

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
PRESETS = sorted(p for p in CONFIGS.glob("*.yaml"))


def test_defaults_file_lists_exactly_the_schema_defaults():
    on_disk = yaml.safe_load((CONFIGS / "defaults.yaml").read_text())
    on_disk.pop("name", None)
    expected = config.Config().model_dump()
    expected.pop("name")
    assert on_disk == expected


@pytest.fixture(scope="module")
def lambert_binary(tmp_path_factory):
    """A MERL file for the presets that fit measured data (their path is a placeholder)."""
    from neural_brdf.measured import merl

    path = tmp_path_factory.mktemp("merl") / "lambert.binary"
    merl.bake(analytic.create("lambertian"), path)
    return path


@pytest.mark.parametrize("path", PRESETS, ids=lambda p: p.stem)
def test_every_preset_validates(path, request):
    cfg = config.load(path)
    assert cfg.name == path.stem
    if cfg.target.data is not None:
        with pytest.raises(config.ConfigError, match="target.data"):
            data.build_target(cfg.target)  # the placeholder names no file here
        cfg = config.load(path, [f"target.data={request.getfixturevalue('lambert_binary')}"])
    else:
        assert cfg.target.model in analytic.available()
    brdf = data.build_target(cfg.target)
    assert cfg.target.kind == target.kind_of(brdf)  # the config's kind is the target's
    if cfg.model.encoding == "isotropic":
        # an isotropic encoding cannot represent a target that changes when both
        # directions rotate about the normal
        wi = physics.random_directions(2000, 1, grazing_fraction=0.0)
        wo = physics.random_directions(2000, 2, grazing_fraction=0.0)
        c, s = np.cos(0.9), np.sin(0.9)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        a, b = brdf.eval(wi, wo), brdf.eval(wi @ rot.T, wo @ rot.T)
        assert np.allclose(a, b, rtol=1e-6, atol=1e-9)


def test_every_model_family_has_a_preset():
    families = {config.load(p).target.model for p in PRESETS}
    missing = sorted(set(analytic.available()) - families)
    assert not missing, (
        f"add a preset for {missing}: configs/<name>.yaml and its twin configs/mlp/<name>.yaml "
        "(docs/architecture.md, 'Adding something')"
    )


@pytest.mark.parametrize(
    "override, key",
    [
        ("train.stepz=5", "train.stepz"),
        ("train.steps=2.5", "train.steps"),
        ("train.steps='10'", "train.steps"),
        ("train.lr=-1", "train.lr"),
        ("model.activation=swish", "model.activation"),
        ("model.hidden=[]", "model.hidden"),
        ("data.pool_size=16", "data.pool_size"),
        ("colour=red", "colour"),
        ("train=5", "train"),
    ],
)
def test_bad_override_names_the_key_in_one_line(override, key):
    with pytest.raises(config.ConfigError) as err:
        config.load(CONFIGS / "lambert.yaml", [override])
    msg = str(err.value)
    assert "\n" not in msg
    assert f"{key}:" in msg


def test_unknown_key_in_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("train:\n  steps: 10\n  learning_rate: 0.1\n")
    with pytest.raises(config.ConfigError, match=r"train\.learning_rate: unknown key"):
        config.load(p)


def test_invalid_yaml_and_missing_file(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("train: {steps: 10\n")
    with pytest.raises(config.ConfigError, match="invalid YAML"):
        config.load(p)
    with pytest.raises(config.ConfigError, match="cannot read"):
        config.load(tmp_path / "missing.yaml")


def test_overrides_parse_as_yaml_and_reach_nested_keys():
    cfg = config.load(
        CONFIGS / "lambert.yaml",
        [
            "train.lr=1e-3",
            "model.hidden=[8, 4]",
            "train.progress=false",
            "target.params.albedo=0.5",
        ],
    )
    assert cfg.train.lr == pytest.approx(1e-3) and isinstance(cfg.train.lr, float)
    assert cfg.model.hidden == [8, 4]
    assert cfg.train.progress is False
    assert cfg.target.params == {"albedo": 0.5}


def test_bad_target_parameters_are_config_errors():
    cfg = config.load(CONFIGS / "lambert.yaml", ["target.params.albedo=2.0"])
    with pytest.raises(config.ConfigError, match="albedo"):
        data.build_target(cfg.target)
    cfg = config.load(CONFIGS / "lambert.yaml", ["target.model=velvet"])
    with pytest.raises(config.ConfigError, match="target.model"):
        data.build_target(cfg.target)


def test_a_registered_model_that_cannot_be_imported_says_why(monkeypatch):
    """A registry line whose class or module is missing, or a module that fails to
    import, is one ConfigError naming target.model and the cause, not a traceback."""
    monkeypatch.setitem(analytic._MODELS, "ghost", ("lambertian", "Ghost"))
    monkeypatch.setitem(analytic._MODELS, "lost", ("no_such_module", "Lost"))
    for name, cause in [
        ("ghost", r"ImportError: analytic.lambertian has no class 'Ghost'"),
        ("lost", r"ModuleNotFoundError: No module named 'analytic.no_such_module'"),
    ]:
        cfg = config.load(CONFIGS / "lambert.yaml", [f"target.model={name}", "target.params={}"])
        with pytest.raises(config.ConfigError, match=rf"^target.model: '{name}' .*{cause}") as e:
            data.build_target(cfg.target)
        assert "\n" not in str(e.value)


def test_the_kind_of_a_target_section_is_the_one_field_it_sets(tmp_path):
    assert config.Target().kind == "analytic"
    assert config.Target(model="microfacet", params={"alpha": 0.2}).kind == "analytic"
    assert config.Target(data="x.binary").kind == "measured"
    assert config.Target(mitsuba="x.xml").kind == "mitsuba"
    assert config.Target(images=[{"scene": "s.xml", "image": "i.exr"}]).kind == "images"
    assert set(target.KINDS) == {"analytic", "measured", "mitsuba", "images"}


def test_resolved_config_round_trips():
    cfg = config.load(CONFIGS / "gold.yaml", ["train.steps=7"])
    again = config.from_dict(yaml.safe_load(cfg.to_yaml()))
    assert again == cfg


def test_every_name_list_of_the_schema_is_the_one_its_module_implements():
    # config.py stays free of torch, so it spells these names out (the encodings' it takes
    # from their torch-free registry); these tie them together
    from typing import get_args

    from neural_brdf import encodings
    from neural_brdf.train import encoding, loop, model

    fields = config.Model.model_fields
    assert set(get_args(fields["activation"].annotation)) == set(model.ACTIVATIONS)
    assert get_args(config.Train.model_fields["loss"].annotation) == loop.LOSSES
    # model.encoding is checked against the registry (no torch): every registered name
    # is accepted and computes its declared width; any other name is refused
    for name in encodings.names():
        assert config.load(None, [f"model.encoding={name}"]).model.encoding == name
        wi = wo = torch.tensor([[0.0, 0.0, 1.0]])
        assert encoding.features(wi, wo, name).shape == (1, encoding.num_features(name))
    with pytest.raises(config.ConfigError, match="model.encoding"):
        config.load(None, ["model.encoding=" + "_".join(encodings.names())])
    with pytest.raises(ValueError, match="train.loss"):
        loop.loss_fn("l2", *(torch.ones(2, 3),) * 3, 1e-3)


# ------------------------------------------------------------------ images: an images fit
IMAGES_CONFIG = """\
target:
  images:
    - {scene: view1.xml, image: view1.exr}
    - {scene: view2.xml, image: view2.exr}
    - {scene: view3.xml, image: view3.exr}
"""


@pytest.fixture
def images_config(tmp_path):
    path = tmp_path / "fit.yaml"
    path.write_text(IMAGES_CONFIG)  # the files need not exist: the schema does not read them
    return path


def test_the_default_start_chooses_by_a_split_and_refuses_to_run_without_one(images_config):
    # images.start: auto (the default) chooses the start on the validation split, so the
    # default config has one, and switching it off without naming a start is refused
    cfg = config.load(images_config)
    assert cfg.images.start == "auto" and cfg.images.split
    with pytest.raises(config.ConfigError) as err:
        config.load(images_config, ["images.validation_pixels=0"])
    assert "images.start: auto chooses the start by the validation split" in str(err.value)
    for named in ("constant", "ggx", "roughplastic"):
        assert not config.load(
            images_config, ["images.validation_pixels=0", f"images.start={named}"]
        ).images.split
    # an anisotropic family needs an encoding that can hold it
    with pytest.raises(
        config.ConfigError, match="images.start: roughconductor_aniso needs an anisotropic"
    ):
        config.load(images_config, ["images.start=roughconductor_aniso"])
    aniso = [
        "images.start=roughconductor_aniso",
        "model.encoding=anisotropic",
        "model.grid.coords=half_disc",
    ]
    assert config.load(images_config, aniso).images.start == "roughconductor_aniso"
    # auto with that family alone: every candidate left out, known before anything runs
    with pytest.raises(config.ConfigError, match="images.start_families: roughconductor_aniso"):
        config.load(images_config, ["images.start_families=[roughconductor_aniso]"])
    assert config.load(
        images_config,
        ["images.start_families=[roughconductor_aniso]", "model.encoding=anisotropic"],
    ).images.start_families == ["roughconductor_aniso"]


@pytest.mark.parametrize(
    "override, key, words",
    [
        ("images.start=mixture", "images.start", "'roughconductor_aniso' or 'blend'"),
        ("images.start_families=[glass]", "images.start_families", "'glass' is not a family"),
        ("images.start_families=[]", "images.start_families", "empty"),
        ("images.validation_block=0", "images.validation_block", "greater than or equal to 1"),
        ("images.spp=0", "images.spp", "greater than or equal to 1"),
        ("images.primal_spp=2.5", "images.primal_spp", "integer"),
        ("images.start_steps=0", "images.start_steps", "greater than or equal to 1"),
        ("images.start_lr_scale=0", "images.start_lr_scale", "greater than 0"),
        ("images.validation_pixels=1", "images.validation_pixels", "less than 1"),
        ("images.validation_pixels=-0.1", "images.validation_pixels", "greater than or equal"),
        ("images.validation_every=0", "images.validation_every", "greater than or equal to 1"),
        ("images.patience=0", "images.patience", "greater than or equal to 1"),
        ("images.validation_views=[3]", "images.validation_views", "3 is not an index"),
        ("images.validation_views=[-1]", "images.validation_views", "-1 is not an index"),
        ("images.validation_views=[1, 1]", "images.validation_views", "names a view twice"),
        ("images.validation_views=[0, 1, 2]", "images.validation_views", "at least one"),
        ("images.validation_view=[0]", "images.validation_view", "unknown key"),
        ("images.start_tie_tol=-0.1", "images.start_tie_tol", "greater than or equal to 0"),
        ("images.start_tie_max=-1", "images.start_tie_max", "greater than or equal to 0"),
        ("images.ggx_lr=0", "images.ggx_lr", "greater than 0"),
        ("images.albedo_weight=-1", "images.albedo_weight", "greater than or equal to 0"),
        ("images.albedo_incidences=[]", "images.albedo_incidences", "empty"),
        ("images.albedo_incidences=[0, 90]", "images.albedo_incidences", "90.0 is not an"),
        ("images.albedo_side=0", "images.albedo_side", "greater than or equal to 1"),
        ("images.evaluator=jax", "images.evaluator", "'auto', 'graph' or 'torch'"),
    ],
)
def test_bad_images_keys_name_the_key_and_the_override(images_config, override, key, words):
    with pytest.raises(config.ConfigError) as err:
        config.load(images_config, [override])
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"--set {override}: {key}:"), msg
    assert words in msg, msg


def test_held_out_views_need_an_images_target(images_config):
    with pytest.raises(config.ConfigError, match=r"images\.validation_views: only for target"):
        config.load(CONFIGS / "lambert.yaml", ["images.validation_views=[0]"])
    cfg = config.load(images_config, ["images.validation_views=[2]"])
    assert cfg.images.split and cfg.images.validation_views == [2]
    assert config.load(images_config, ["images.validation_pixels=0.1"]).images.split
    bad = images_config.with_name("bad.yaml")
    bad.write_text(IMAGES_CONFIG + "images: {validation_views: [5]}\n")
    with pytest.raises(config.ConfigError, match=r"^.*bad\.yaml: images\.validation_views: 5"):
        config.load(bad)


# ------------------------------------------------------------------ docs/config.md's defaults
DOCS = CONFIGS.parent / "docs"
ROW = re.compile(r"^\| `([\w.]+)` \| `([^`|]*)` \|", re.M)  # | `key` | `default` | ...


def _at(tree: object, key: str) -> object:
    for part in key.split("."):
        if not isinstance(tree, dict) or part not in tree:
            return KeyError
        tree = tree[part]
    return tree


def test_every_literal_default_in_config_md_is_the_schemas():
    """docs/config.md's default column (where it is one literal, not prose) equals
    configs/defaults.yaml, which holds exactly the schema's defaults (test above)."""
    defaults = yaml.safe_load((CONFIGS / "defaults.yaml").read_text())
    rows = ROW.findall((DOCS / "config.md").read_text())
    checked, wrong = 0, []
    for key, cell in rows:
        actual = _at(defaults, key)
        if actual is KeyError:
            continue  # a key documented under another name: test_docs covers the keys
        documented = config.parse_yaml(cell, source=f"docs/config.md: {key}")
        checked += 1
        if documented != actual:
            wrong.append(f"{key}: documented {cell}, schema {actual!r}")
    assert not wrong, wrong
    assert checked > len(rows) // 2, (checked, len(rows))  # the parse found the table


def test_the_quickstart_steps_in_config_md_are_the_presets():
    text = " ".join((DOCS / "config.md").read_text().split())
    m = re.search(r"`quickstart\.yaml` is `gold` with (\d+) steps instead of (\d+)", text)
    assert m, "docs/config.md: the quickstart sentence changed: update this test"
    quick, gold = (config.load(CONFIGS / f"{n}.yaml").train.steps for n in ("quickstart", "gold"))
    assert (int(m[1]), int(m[2])) == (quick, gold)


def test_model_md_names_the_default_network():
    """docs/model.md's "default WIDTHS ACTIVATION" is the schema's default MLP."""
    text = " ".join((DOCS / "model.md").read_text().split())
    m = re.search(r"`model\.activation`; default ([\d-]+) (\w+)", text)
    assert m, "docs/model.md: the default network's sentence changed: update this test"
    default = config.Config().model
    assert [int(w) for w in m[1].split("-")] == default.hidden
    assert m[2].lower() == default.activation
