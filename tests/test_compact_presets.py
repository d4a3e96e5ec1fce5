"""The compact presets (configs/compact/, issue 12): same targets as their presets, a
learned grid and a small network, and a recipe that holds on a target it was not tuned on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from neural_brdf import config, presets, train

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
COMPACT = sorted((CONFIGS / "compact").glob("*.yaml"))


def test_there_is_a_compact_preset_for_every_analytic_preset():
    analytic = {
        p.stem
        for p in CONFIGS.glob("*.yaml")
        if p.stem not in ("defaults", "quickstart")
        and not ((yaml.safe_load(p.read_text()) or {}).get("target") or {}).get("data")
    }
    measured = {p.stem for p in CONFIGS.glob("*.yaml")} - analytic - {"defaults", "quickstart"}
    compact = {p.stem for p in COMPACT}
    assert analytic and analytic <= compact
    assert compact - analytic <= measured  # and for measured data (compact/merl)


@pytest.mark.parametrize("path", COMPACT, ids=[p.stem for p in COMPACT])
def test_compact_preset_keeps_its_presets_target_and_encoding(path):
    compact = config.load(path)
    full = config.load(CONFIGS / path.name)
    assert compact.target == full.target
    assert compact.model.encoding == full.model.encoding
    assert compact.model.grid.size >= 2
    assert compact.model.activation == "relu"
    assert sum(compact.model.hidden) < sum(full.model.hidden) / 2
    assert presets.resolve(f"compact/{path.stem}") == path


def test_the_gold_recipe_holds_on_a_conductor_and_roughness_it_was_not_tuned_on(tmp_path):
    # configs/compact/gold.yaml was tuned on GGX alpha 0.3 gold; here copper at alpha 0.2
    cfg = config.load(
        CONFIGS / "compact" / "gold.yaml",
        [
            "target.params.alpha=0.2",
            "target.params.material=Cu",
            "train.progress=false",
            "validation.furnace_dirs=16",
            "validation.accuracy_samples=32768",
        ],
    )
    metrics = train.run(cfg, tmp_path / "cu")
    assert metrics["passed"], json.dumps(metrics["checks"])
    assert metrics["accuracy"]["rel_rmse"] <= 0.01
    # and right at the highlight's peak (issue 19: the old encoding read 0.12x there)
    peak = metrics["peak"]
    assert peak["passed"] and peak["value"] <= 0.03, json.dumps(peak["at"])
