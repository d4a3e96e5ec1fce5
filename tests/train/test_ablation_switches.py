"""The two ablation switches: ``model.encoding: raw`` (the network sees (wi, wo) as
they are, so reciprocity is no longer built in) and ``normalization.enabled: false``
(no albedo table, so nothing bounds the albedo).  Each is checked against the
construction it switches off, which must keep its guarantee."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import neural_brdf
from analytic import physics
from neural_brdf import config, encodings, export, validate
from neural_brdf.tooling import cli
from neural_brdf.train import encoding
from neural_brdf.train.model import NormalizedBRDF, RawBRDF

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

# Small everything: mechanics, not accuracy (as in test_neural_train.py).
TINY = [
    "train.steps=40",
    "train.warmup=2",
    "train.log_every=10",
    "train.eval_every=0",
    "train.progress=false",
    "train.threads=1",
    "model.hidden=[16,16]",
    "data.batch_size=256",
    "data.pool_size=2048",
    "normalization.table_size=17",
    "normalization.grid_size=7",
    "normalization.samples=1024",
    "validation.furnace_dirs=6",
    "validation.furnace_samples=2048",
    "validation.pairs=2000",
    "validation.accuracy_samples=2048",
    "export.parity_pairs=512",
]


def _random_raw(
    enc: str, *, bias: float = 0.0, scale: float = 1.0, seed: int = 0, grazing_power: float = 1.0
) -> RawBRDF:
    """A raw network with random weights (the head too: at init it is constant)."""
    torch.manual_seed(seed)
    raw = RawBRDF(enc, [16, 16], "silu", grazing_power=grazing_power)
    with torch.no_grad():
        for p in raw.parameters():
            p.normal_(0.0, scale)
        raw.mlp.head.bias.fill_(bias)
    return raw.eval()


def _numpy_fn(model):
    def fn(a, b):
        with torch.no_grad():
            return model(torch.as_tensor(a).float(), torch.as_tensor(b).float()).double().numpy()

    return fn


def test_raw_features_are_the_pair_in_order():
    wi = torch.from_numpy(physics.random_directions(100, 1)).float()
    wo = torch.from_numpy(physics.random_directions(100, 2)).float()
    x = encoding.features(wi, wo, "raw")
    assert x.shape == (100, encoding.num_features("raw")) == (100, 6)
    assert torch.equal(x[:, :3], wi) and torch.equal(x[:, 3:], wo)
    assert encoding.is_anisotropic("raw") and not encoding.is_anisotropic("isotropic")
    # the one non-reciprocal encoding: the symmetry tests cover every other one
    assert encodings.names(reciprocal=False) == ("raw",)


@pytest.mark.parametrize("enc", encodings.names())
def test_an_encoding_breaks_reciprocity_exactly_when_it_says_so(enc):
    # of the built-in ones, only the raw ablation says so (Encoding.reciprocal)
    raw = _random_raw(enc)
    err = physics.reciprocity_error(_numpy_fn(raw), n=20000)
    if not encodings.get(enc).reciprocal:
        assert err > 1e-2  # measurably non-reciprocal: the ablation has something to show
    else:
        assert err == 0.0  # bit-exact by construction


def test_raw_encoding_trains_exports_and_fails_only_reciprocity(tmp_path, capsys):
    """The CLI path: training and export work, the validator flags reciprocity (exit 1)."""
    out = tmp_path / "raw"
    sets = sum((["--set", s] for s in TINY + ["model.encoding=raw"]), [])
    code = cli.main(["train", str(CONFIGS / "gold.yaml"), "--out", str(out)] + sets)
    assert code == cli.EXIT_PHYSICS
    model = neural_brdf.load(out / "model.onnx")
    assert model.encoding == "raw"
    metrics = json.loads((out / "metrics.json").read_text())
    checks = metrics["checks"]
    assert not checks["reciprocity"]["passed"] and checks["reciprocity"]["value"] > 1e-3
    assert checks["min_value"]["passed"] and checks["max_albedo"]["passed"]
    # the albedo table is the 2-D (anisotropic) grid: 7 x 7 nodes, not 17
    assert metrics["export"]["normalization"]["nodes"] == 7 * 7
    # an independent measurement on the exported file agrees that f(a, b) != f(b, a)
    assert physics.reciprocity_error(model.eval, n=5000, seed=9) > 1e-3
    assert "FAIL" in capsys.readouterr().out


def _bright_net() -> RawBRDF:
    """About 1/sr everywhere (albedo about pi), varying with angle: far above 1."""
    return _random_raw("isotropic", bias=0.5, scale=0.3, seed=3, grazing_power=0.0)


def _furnace_max(fn) -> tuple[float, float]:
    rng = np.random.default_rng(4)
    theta = np.concatenate([rng.uniform(0, 0.5 * np.pi, 14), [0.0, 0.5 * np.pi - 1e-3]])
    wi = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1)
    rho, err = physics.albedo_of(fn, wi, n=8192, seed=6, return_error=True)
    return float(rho.max()), float(err.max())


@pytest.mark.parametrize("enabled", [True, False])
def test_normalisation_switch_on_a_bright_network(tmp_path, enabled):
    cfg = config.load(CONFIGS / "lambert.yaml", TINY + [f"normalization.enabled={enabled}"])
    raw = _bright_net()
    model, info = export.normalized_model(raw, cfg)
    assert info["enabled"] is enabled
    assert isinstance(model, NormalizedBRDF) is enabled
    rho, err = _furnace_max(_numpy_fn(model))
    if enabled:
        assert rho <= 1.0 + cfg.validation.albedo_tol + 3 * err
    else:
        assert rho > 2.0  # the raw network, untouched
    # the exported file is the same model, and its own metadata and validator say so
    path = tmp_path / "m.onnx"
    figures = export.export(
        model, cfg, path, measure=validate.physics, target_desc="bright test network"
    )
    onnx_model = neural_brdf.load(path)
    wi = physics.random_directions(3000, 7).astype(np.float32)
    wo = physics.random_directions(3000, 8).astype(np.float32)
    np.testing.assert_allclose(
        onnx_model.eval(wi, wo), _numpy_fn(model)(wi, wo), rtol=1e-5, atol=1e-6
    )
    assert onnx_model.metadata["normalization"].startswith("none") is not enabled
    assert figures["physics"]["checks"]["max_albedo"]["passed"] is enabled
    assert validate.report(path)["passed"] is enabled
