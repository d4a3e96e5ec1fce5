"""The encoding registry (neural_brdf/encodings/): each encoding is an object that knows
its width, whether it is anisotropic or reciprocal, and the feature columns a grid is
looked up at; the config, the model and the tests' lists come from it.  A toy encoding
registered here follows docs/architecture.md's recipe "An encoding" end to end."""

from __future__ import annotations

import json
import math
import sys
import unittest.mock
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import neural_brdf
from analytic import physics
from neural_brdf import config, encodings, export
from neural_brdf.encodings import Encoding
from neural_brdf.tooling import cli
from neural_brdf.train import encoding
from neural_brdf.train.model import RawBRDF

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _pairs(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    a = physics.random_directions(n, seed)
    b = physics.random_directions(n, seed + 1)
    return torch.from_numpy(a).float(), torch.from_numpy(b).float()


TOY = '''
"""A toy encoding: (cos_i + cos_o) / 2, cos_i cos_o, cos^2 theta_d.  Symmetric in (wi, wo)
bit for bit (s = wi + wo is, and a product commutes), each in [0, 1] above the horizon."""

import torch


def features(wi, wo, peak="u_h"):
    s = wi + wo
    return torch.stack([0.5 * s[..., 2], wi[..., 2] * wo[..., 2], 0.25 * (s * s).sum(-1)], -1)
'''


@pytest.fixture
def toy(tmp_path, monkeypatch) -> Iterator[Encoding]:
    """The recipe: encodings/toy.py (in a folder added to the package's path) and its
    register line; the registry is restored after."""
    (tmp_path / "toy.py").write_text(TOY)
    monkeypatch.setattr(encodings, "__path__", [*encodings.__path__, str(tmp_path)])
    monkeypatch.setattr(encodings, "REGISTRY", dict(encodings.REGISTRY))
    yield encodings.register(
        Encoding(
            "toy",
            width=3,
            anisotropic=False,
            compute=".toy:features",
            grid_axes={"theta": (0, 2)},  # any two columns in [0, 1]^2
        )
    )
    sys.modules.pop("neural_brdf.encodings.toy", None)


@pytest.mark.parametrize("name", encodings.names())
def test_an_encoding_computes_what_it_declares(name):
    spec = encodings.get(name)
    wi, wo = _pairs(5000, 21)
    x = spec.features(wi, wo)
    assert x.shape == (5000, spec.width) and torch.isfinite(x).all()
    assert torch.equal(x, encoding.features(wi, wo, name))  # training's view, by name
    # reciprocal: bit-exactly symmetric; the raw ablation is not, measurably
    assert torch.equal(x, spec.features(wo, wi)) == spec.reciprocal
    # the grid's axes lie where its coords say: theta in [0, 1]^2, half_disc in the disc
    for coords, (i, j) in spec.grid_axes.items():
        u, v = x[:, i], x[:, j]
        if coords == "theta":
            assert bool(((u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)).all()), coords
        else:
            assert coords == "half_disc" and bool((u * u + v * v <= 1.0 + 1e-6).all())
    # anisotropic: it sees a rotation of both directions about the normal
    c, s = math.cos(0.7), math.sin(0.7)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = (spec.features(wi @ rot.T, wo @ rot.T) - x).abs().max()
    assert (moved > 0.1) if spec.anisotropic else (moved < 2e-4)


@pytest.mark.parametrize("name", ["isotropic", "anisotropic"])
def test_torch_lays_the_features_out_by_column_and_the_export_traces_the_stack(name):
    """encodings.angles.columns: in torch the feature columns are copied whole (a
    column-major result, a faster copy than interleaving them), while an export traces
    the plain stack, so the file's graph has no transpose; both are the same values, bit
    for bit, and so is the model's input with its grid's columns (cat_columns)."""
    spec = encodings.get(name)
    wi, wo = _pairs(3000, 5)
    x = spec.features(wi, wo)
    with unittest.mock.patch("torch.onnx.is_in_onnx_export", return_value=True):
        stacked = spec.features(wi, wo)
        joined = encoding.cat_columns([stacked, stacked[:, :4]])
    assert stacked.is_contiguous() and x.stride() == (1, 3000)
    assert torch.equal(x, stacked)
    both = encoding.cat_columns([x, x[:, :4]])
    assert both.stride() == (1, 3000) and torch.equal(both, joined)
    torch.manual_seed(3)
    raw = RawBRDF(name, [16], "relu", grid_size=8, grid_channels=4).eval()
    ops = {n.op_type for n in onnx.load_from_string(export.to_onnx_bytes(raw, 17)).graph.node}
    assert "Transpose" not in ops and "Concat" in ops


def test_a_registered_toy_is_a_config_value_and_a_reciprocal_model(toy):
    # the lists the tests run over come from the registry, so they now hold the toy
    assert "toy" in encodings.names(reciprocal=True, grid="theta")
    assert "toy" not in encodings.names(grid="half_disc")
    cfg = config.load(None, ["model.encoding=toy", "model.cosine_grid.size=8"])
    assert cfg.model.encoding == "toy" and cfg.model.grid.size > 0  # it has theta axes
    with pytest.raises(config.ConfigError, match="'toy'"):  # named among the choices
        config.load(None, ["model.encoding=toy2"])
    with pytest.raises(config.ConfigError, match="grid.coords: half_disc needs the anisotropic"):
        config.load(None, ["model.encoding=toy", "model.grid.coords=half_disc"])

    torch.manual_seed(0)
    raw = RawBRDF.from_config(cfg.model)
    assert not raw.anisotropic and encoding.num_features("toy") == 3
    m = cfg.model
    assert raw.mlp.body[0].in_features == 3 + m.grid.channels + m.cosine_grid.channels
    assert raw.grid_features == (0, 2)
    with torch.no_grad():
        for p in raw.parameters():
            p.normal_(0.0, 1.0)
        wi, wo = _pairs(20000, 4)
        f, g = raw(wi, wo), raw(wo, wi)
    assert torch.isfinite(f).all() and float(f.std()) > 1e-3  # not a constant
    assert torch.equal(f, g)  # f(wi, wo) == f(wo, wi), bit for bit


def test_a_registered_toy_trains_exports_and_validates(toy, tmp_path, capsys):
    """The whole run with the toy: export writes its name, validate reads its anisotropy
    from the registry and finds the model exactly reciprocal in onnxruntime."""
    out = tmp_path / "toy"
    tiny = [
        "model.encoding=toy",
        "train.steps=10",
        "train.warmup=2",
        "train.log_every=5",
        "train.eval_every=0",
        "train.progress=false",
        "train.threads=1",
        "model.hidden=[8]",
        "model.grid.size=4",
        "data.batch_size=256",
        "data.pool_size=1024",
        "normalization.table_size=9",
        "normalization.samples=512",
        "validation.furnace_dirs=4",
        "validation.furnace_samples=1024",
        "validation.pairs=1000",
        "validation.accuracy_samples=1024",
        "export.parity_pairs=256",
    ]
    sets = sum((["--set", s] for s in tiny), [])
    code = cli.main(["train", str(CONFIGS / "lambert.yaml"), "--out", str(out)] + sets)
    assert code in (0, cli.EXIT_PHYSICS), capsys.readouterr().err  # a 10-step fit may miss
    model = neural_brdf.load(out / "model.onnx")
    assert model.encoding == "toy"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["checks"]["reciprocity"]["passed"]
    assert metrics["export"]["normalization"]["nodes"] == 9  # isotropic: the 1-D table
    wi, wo = (x.numpy().astype(np.float32) for x in _pairs(5000, 8))
    assert np.array_equal(model.eval(wi, wo), model.eval(wo, wi))


def test_register_refuses_what_it_cannot_honour(toy):
    def bad(**changes) -> Encoding:
        fields = dict(name="toy_b", width=3, anisotropic=False, compute=toy.features)
        return Encoding(**(fields | changes))

    for enc, match in [
        (bad(name="toy"), "already registered"),
        (bad(name="no way"), "identifier"),
        (bad(width=0), "width"),
        (bad(grid_axes={"theta": (0, 3)}), "grid_axes"),  # past the width
        (bad(grid_axes={"theta": (1, 1)}), "grid_axes"),  # one column twice
        (bad(compute="neural_brdf.train.loop:train"), "compute"),  # not of the package
    ]:
        with pytest.raises(ValueError, match=match):
            encodings.register(enc)
    assert encodings.names()[-1] == "toy"  # nothing of those was added
    with pytest.raises(ValueError, match="must be one of"):
        encodings.get("toy_b")
    # code with torch at hand may register the function itself (here: the toy's, bound)
    wi, wo = _pairs(10, 3)
    encodings.register(bad())
    assert torch.equal(encoding.features(wi, wo, "toy_b"), toy.features(wi, wo))


def test_an_encoding_is_checked_on_first_use(toy, tmp_path, capsys):
    """A registered encoding whose features do not match its width, are not finite, or
    (reciprocal) are not symmetric is refused on first use in one line naming it, not as
    a matrix-shape error inside torch or a model the validator finds not reciprocal; a
    ``compute`` that names no function says which and why."""

    def made(name, fn, **changes) -> Encoding:
        fields = dict(name=name, width=3, anisotropic=False, compute=fn)
        return encodings.register(Encoding(**(fields | changes)))

    def lopsided(wi, wo, peak="u_h"):  # wi's cosine twice: not symmetric in (wi, wo)
        return torch.stack([wi[..., 2] + wo[..., 2], wi[..., 2], wi[..., 2] * wo[..., 2]], -1)

    def grazing(wi, wo, peak="u_h"):
        return toy.features(wi, wo, peak) / (wi[..., 2] - wi[..., 2])[..., None]

    wi, wo = _pairs(10, 5)
    for enc, match in [
        (
            made("wide", toy.features, width=4),
            r"^model.encoding: 'wide'.*shape \(64, 3\).*\(64, 4\)",
        ),
        (made("lopsided", lopsided), r"^model.encoding: 'lopsided'.*feature 1 differs"),
        (made("grazing", grazing), r"^model.encoding: 'grazing'.*not finite"),
        (
            made("lost", ".toy:no_such"),
            r"^model.encoding: 'lost': compute '.toy:no_such'.*AttributeError",
        ),
        (made("gone", ".no_module:f"), r"^model.encoding: 'gone'.*ModuleNotFoundError"),
    ]:
        with pytest.raises(config.ConfigError, match=match):
            RawBRDF(enc.name, [8], "relu")  # a network of it: its first use
    # declared as not reciprocal, the same function is taken (an ablation, as raw is)
    x = made("lopsided_raw", lopsided, reciprocal=False).features(wi, wo)
    assert torch.equal(x, lopsided(wi, wo))
    assert RawBRDF("lopsided_raw", [8], "relu").spec.name == "lopsided_raw"
    assert torch.equal(toy.features(wi, wo), encoding.features(wi, wo, "toy"))  # the recipe's
    # on the command line: one line naming the key, exit 2 (not a traceback, not exit 1)
    code = cli.main(["train", "lambert", "--out", str(tmp_path / "run"), "--set",
                     "model.encoding=lopsided", "--set", "model.grid.size=0", "--set",
                     "train.steps=2"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "model.encoding: 'lopsided'" in err[0], err
    # and wherever torch's default device is (the check's pairs are the CPU's)
    with torch.device("meta"):
        made("on_meta", toy.features).check()
