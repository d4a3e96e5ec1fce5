"""Many materials in one run (neural_brdf.train.many, issue 21): the batch trains each material
as its own run would, refuses configs it cannot batch by name, and its runs are exported,
validated and refused for resume like any other."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from neural_brdf import config, pipeline
from neural_brdf.tooling import cli
from neural_brdf.train import loop, many

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
TINY = [
    "train.steps=40",
    "train.warmup=5",
    "train.progress=false",
    "train.eval_every=0",
    "data.pool_size=8192",
    "normalization.samples=4096",
    "validation.furnace_dirs=9",
    "validation.furnace_samples=4096",
    "validation.pairs=1000",
    "validation.accuracy_samples=4096",
    "export.parity_pairs=256",
]
METALS = ("Au", "Cu", "Al")


def metals(*extra) -> list[config.Config]:
    return [
        config.load(
            CONFIGS / "gold.yaml",
            TINY + [f"target.params.material={m}", f"name={m}", f"train.seed={i}", *extra],
        )
        for i, m in enumerate(METALS)
    ]


def test_each_material_trains_as_its_own_run_would(tmp_path):
    cfgs = metals()
    batched = many.train_many(cfgs, [tmp_path / "b" / c.name for c in cfgs])
    for cfg, (raw, fig) in zip(cfgs, batched):
        alone, fig_alone = loop.train(cfg, tmp_path / "s" / cfg.name)
        # the same seeds, pools and initial weights; vmap's kernels may round otherwise
        for name, w in alone.state_dict().items():
            torch.testing.assert_close(raw.state_dict()[name], w, rtol=1e-3, atol=1e-4)
        assert fig["raw_val_rel_rmse"] == pytest.approx(fig_alone["raw_val_rel_rmse"], rel=1e-3)
        assert fig["batched_with"] == len(cfgs) and fig["steps"] == cfg.train.steps
    # and the materials are not the same model: each learned its own target
    a, b = (r.state_dict()["mlp.head.bias"] for r, _ in batched[:2])
    assert not torch.equal(a, b)


@pytest.mark.parametrize(
    "override, key",
    [
        ("model.hidden=[16]", "model.hidden"),
        ("data.batch_size=512", "data.batch_size"),
        ("train.lr=0.01", "train.lr"),
        ("train.steps=41", "train.steps"),
    ],
)
def test_a_setting_the_batch_must_share_is_named(override, key):
    cfgs = metals()
    cfgs[2] = config.load(CONFIGS / "gold.yaml", TINY + ["name=odd", override])
    with pytest.raises(config.ConfigError, match=rf"^odd: {key}: differs from Au"):
        many.check_batchable(cfgs)
    files = [f"m{i}.yaml" for i in range(len(cfgs))]  # the files, when the caller has them
    with pytest.raises(config.ConfigError, match=rf"^m2.yaml: {key}: differs from m0.yaml"):
        many.check_batchable(cfgs, files)


def test_seeds_targets_and_data_shares_may_differ():
    cfgs = metals()
    cfgs[1] = config.load(CONFIGS / "clay.yaml", TINY + ["data.batch_size=1024", "train.seed=9"])
    cfgs[1] = cfgs[1].model_copy(update={"data": cfgs[0].data})
    many.check_batchable(cfgs)  # a diffuse and two metals, one network: no error


def test_cli_trains_exports_and_validates_every_material(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["train-many", "gold", "beckmann_rough", "--out", str(out)]
    for s in TINY + ["data.batch_size=1024"]:
        args += ["--set", s]
    assert cli.main(args) == 0
    printed = capsys.readouterr().out
    assert "2 materials in one batch" in printed
    for name in ("gold", "beckmann_rough"):
        metrics = json.loads((out / name / "metrics.json").read_text())
        assert metrics["passed"] and metrics["training"]["batched_with"] == 2
        assert (out / name / "model.onnx").is_file() and (out / name / "log.csv").is_file()
    # a batched run keeps no optimizer or pool state: resume is refused in one line
    code = cli.main(["train", "gold", "--out", str(out / "gold"), "--resume", *args[5:]])
    err = capsys.readouterr().err
    assert code == 2 and "trained in a batch of 2" in err and err.count("\n") == 1


def test_two_materials_of_one_name_are_refused(tmp_path):
    cfg = metals()[0]
    with pytest.raises(config.ConfigError, match=r"^name: 'Au' is given to two materials"):
        pipeline.run_many([cfg, cfg], tmp_path / "out")
    assert not (tmp_path / "out").exists()
