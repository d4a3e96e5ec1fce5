"""``python -m neural_brdf.measured.procedural DIR``: the teacher and the config it writes
beside it (docs/mitsuba.md "Textured materials") are valid and train, and the run's
pool is texture.pool_per_texel pairs per texel, larger than data.pool_size's default
(docs/mitsuba.md "The pool and the field's resolution": the example's error fell on
both sets with 2M pairs)."""

from __future__ import annotations

import json

import pytest

from cli_helpers import cli
from neural_brdf import config as cfgmod
from neural_brdf.measured import procedural

pytestmark = pytest.mark.mitsuba


def test_the_written_config_is_valid_trains_and_draws_a_large_pool(tmp_path, capsys):
    assert procedural.main([str(tmp_path / "mat"), "--size", "16", "--steps", "10"]) == 0
    cfg_path = tmp_path / "mat" / "textured.yaml"
    cfg = cfgmod.load(cfg_path)
    assert cfg.texture.latent == 1 and cfg.texture.weights == "rgb"
    assert cfg.texture.lobe_color == "grey"  # the benchmark recipe's choice (docs/mitsuba.md)
    assert cfg.texture.project == 128  # the tour's choice (textured_tour_dev.json)
    pool = cfg.texture.pool(cfg.data.pool_size)
    assert pool == cfg.texture.pool_per_texel * cfg.texture.resolution**2 > cfgmod.Data().pool_size
    code, _, err = cli(
        capsys, "train", str(cfg_path), "--out", str(tmp_path / "run"),
        "--set", "train.progress=false", "--set", "validation.pairs=2000",
        "--set", "validation.furnace_dirs=16", "--set", "validation.furnace_samples=2048",
        "--set", "validation.accuracy_samples=4096", "--set", "normalization.samples=2048",
        "--set", "export.parity_pairs=256", "--set", "texture.project=8",
    )  # fmt: skip
    assert code == 0, err
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["training"]["pool"] == pool
    assert m["training"]["lobe_color"] == "grey"
    assert m["training"]["projection"]["resolution"] == 8  # projected (smaller here)
