"""The learning rates of a network's parameters, decided in one place
(``neural_brdf.train.model.grid_lr_scales``, ``lr_scale``, ``parameter_groups``) and read
by the training loop, the batched loop, the textured loop and the image fit."""

from __future__ import annotations

import torch

from neural_brdf import config
from neural_brdf.train import loop, many, textured_loop
from neural_brdf.train.model import RawBRDF, grid_lr_scales, lr_scale, parameter_groups

GRIDS = [
    "model.grid.size=8",
    "model.grid.lr_scale=7.0",
    "model.cosine_grid.size=4",
    "model.cosine_grid.lr_scale=3.0",
    "train.steps=2",
    "train.warmup=1",
    "train.progress=false",
    "train.eval_every=0",
    "data.pool_size=4096",
]


def _scale_by_tensor(groups) -> dict[int, float]:
    out: dict[int, float] = {}
    for g in groups:
        for p in g["params"]:
            assert id(p) not in out, "a parameter in two groups"
            out[id(p)] = g["lr_scale"]
    return out


def test_each_grid_gets_its_lr_scale_and_the_mlp_one():
    m = config.load(None, GRIDS).model
    raw = RawBRDF.from_config(m)
    groups = parameter_groups(raw.named_parameters(), grid_lr_scales(m))
    assert [g["lr_scale"] for g in groups] == [1.0, 7.0, 3.0]  # a checkpoint's order
    scale = _scale_by_tensor(groups)
    named = dict(raw.named_parameters())
    assert set(scale) == {id(p) for p in named.values()}  # every parameter, once
    for name, p in named.items():
        want = 7.0 if name.startswith("grid.") else 3.0 if name.startswith("cos_grid.") else 1.0
        assert scale[id(p)] == want == lr_scale(name, grid_lr_scales(m)), name
    # the image fit's one factor for both grids
    assert grid_lr_scales(m, 0.5) == {"grid.": 0.5, "cos_grid.": 0.5}
    # without grids, one group: the MLP's
    plain = RawBRDF.from_config(config.load(None, ["model.grid.size=0"]).model)
    assert [
        g["lr_scale"] for g in parameter_groups(plain.named_parameters(), grid_lr_scales(m))
    ] == [1.0]


def test_the_loops_train_with_those_groups(tmp_path, monkeypatch):
    """The single and the batched loop hand Adam the same groups; the textured loop
    scales its lobes' grids by the same rule."""
    seen: list[list[float]] = []
    real = torch.optim.Adam

    def spy(groups, **kw):
        groups = list(groups)
        seen.append([g["lr_scale"] for g in groups])
        return real(groups, **kw)

    monkeypatch.setattr(torch.optim, "Adam", spy)
    cfg = config.load(None, GRIDS)
    loop.train(cfg, tmp_path / "one")
    many.train_many([cfg, cfg], [tmp_path / "a", tmp_path / "b"])
    assert seen == [[1.0, 7.0, 3.0], [1.0, 7.0, 3.0]]
    model, _ = textured_loop._model_and_optimizer(
        cfg.model, 2, 4, torch.ones(8), 1e-3, field_lr_scale=5.0
    )
    by_id = _scale_by_tensor(textured_loop.parameter_groups(model, cfg.model, 5.0))
    for name, p in model.named_parameters():
        if name.startswith("field."):
            assert by_id[id(p)] == 5.0, name
        elif ".cos_grid." in name:
            assert by_id[id(p)] == 3.0, name
        elif ".grid." in name:
            assert by_id[id(p)] == 7.0, name
        else:
            assert by_id[id(p)] == 1.0, name
