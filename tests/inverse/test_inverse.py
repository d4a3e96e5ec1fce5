"""Neural BRDFs from images (neural_brdf.inverse.fit, neural_brdf.inverse.bsdf), llvm_ad_rgb.

* the differentiable plugin: ``mi.traverse`` exposes its weights; the gradient of a
  rendered loss (``dr.backward`` through Mitsuba's path tracer and ``dr.wrap`` into
  torch) matches central finite differences of the same render (same seed, so the
  Monte Carlo samples are the same) to 0.5 %, for the two largest entries of every
  weight tensor (grid, hidden layer, head);
* a primal render (no gradient tracked) with the ``graph`` evaluator (``auto`` in
  llvm_ad_rgb) evaluates the RawBRDF's lowered graph and never calls torch, and its
  image equals the torch evaluator's at the same seed; in symbolic mode every evaluator
  uses the graph; an unknown evaluator is refused; ``auto`` resolves per variant
  (``torch`` in cuda_ad_rgb); instances of one model section share one lowered program
  and each evaluates its own weights;
* a small fast fit end to end through the CLI (``neural-brdf train fit.yaml``): three
  16 x 16 views of the example's copper sphere, 30 steps (the default ``auto`` start:
  the families fitted and one chosen on the held-out pixels, a conductor here, then the
  network), a fifth of each view's tiles held out (``images.validation_pixels``); the image stage
  must do something: its held-out loss ends clearly below the start's (a learning rate
  of 0 fails this) and the exported network differs from the start's; the exported
  model's render of a fitted view comes within the stated error of its target, which
  the network's constant start is not; the export is exactly reciprocal (bit for bit,
  here and in the validator) and passes the white furnace; the coverage is in
  metrics.json and coverage.png;
* with a split, an image stage that only makes the start worse (a learning rate far too
  high) ends with the start's weights, exported as they were;
* the same small fit of a multi-light capture (each view lit by its own point or area
  light, no environment) brings the network's BRDF where both cosines exceed 0.5 within
  5 % of the truth;
* a capture that observes little of the domain (a co-located flash) warns on stderr;
* the albedo penalty's estimate is unbiased and reads a sharp anisotropic lobe of
  albedo 0.85 below 1 at every step (cosine-distributed directions read it up to 4.3);
* the split: seeded, a given share of each view's pixels, held out of the loss's
  weights; a resumed run cannot change it;
* bad inputs exit with code 2 and one line naming the file or the key: a missing EXR,
  an unreadable one, a one-channel one, one of the wrong size, a scene without
  ``<bsdf id="fit">`` or with no shape that uses it, a scalar and a spectral variant;
* config paths are relative to the config file.

The scenes and targets are generated here (neural_brdf.inverse.scene) in a temporary
folder; the whole file takes about two minutes on 2 cores.
"""

from __future__ import annotations

import json
import math
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from neural_brdf import config
from neural_brdf.tooling import cli

pytestmark = pytest.mark.mitsuba

RES = 16  # film size of the test views
TARGET_SPP = 64
FIT_STEPS = 30
# The stated error of the small fit: the exported model, rendered at 256 spp in the
# first view, is within this relative RMSE of the target over the sphere's pixels, and
# the network's constant start is not (measured: 0.19 against 0.78; the start is a
# conductor distilled for 30 steps only, about 20 % off, so that the image stage has
# work to do).
FIT_IMAGE_ERROR = 0.25
# The small fit holds out this share of each view's tiles; the image stage must bring
# their loss below HELDOUT_GAIN x the start's (measured: 0.31 x; with the image stage's
# learning rate at 0 it stays at 1 x), and move the network by at least NETWORK_CHANGE
# (relative RMS of f against the start's network).
HELDOUT_SHARE = 0.2
# The small fit of a multi-light capture (each view lit by its own light, the images
# section's defaults): the exported network's BRDF error where both cosines exceed 0.5
# is below the issue's goal (measured: 0.021; a constant f is 0.97 off).
LIGHTS_BRDF_ERROR = 0.05
HELDOUT_GAIN = 0.8
NETWORK_CHANGE = 0.02
BLOCK = 4  # images.validation_block's default
FIT_OVERRIDES = [
    f"train.steps={FIT_STEPS}",
    f"images.start_steps={FIT_STEPS}",
    "train.progress=false",
    "train.warmup=5",
    "train.lr=0.02",
    "normalization.samples=2048",
    "validation.furnace_dirs=31",
    "validation.furnace_samples=4096",
    "validation.pairs=4000",
    "export.parity_pairs=1024",
]


# ------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def example(mi, tmp_path_factory) -> Path:
    from neural_brdf.inverse import scene as inverse_example

    folder = tmp_path_factory.mktemp("views")
    inverse_example.write(folder, resolution=RES, spp=TARGET_SPP, steps=FIT_STEPS)
    return folder


def run_cli(args, capsys) -> tuple[int, str]:
    code = cli.main(args)
    return code, capsys.readouterr().err


# ------------------------------------------------------------------ the plugin
def test_traverse_exposes_every_weight(mi):
    import drjit as dr

    from neural_brdf.inverse import bsdf as ib

    bsdf = mi.load_dict({"type": ib.PLUGIN, "model": ib.COMPACT})
    params = mi.traverse(bsdf)
    state = bsdf.raw.state_dict()
    assert sorted(params.keys()) == sorted("raw." + k for k in state)
    for k, v in state.items():
        assert tuple(params["raw." + k].shape) == tuple(v.shape)
        assert not params.flags("raw." + k) & mi.ParamFlags.NonDifferentiable.value
        assert dr.is_diff_v(params["raw." + k])


def test_render_gradient_matches_finite_differences(mi, example):
    import drjit as dr

    from neural_brdf.inverse import bsdf as ib
    from neural_brdf.inverse import fit as inverse

    cfg = config.load(example / "fit.yaml")
    views = inverse.read_views(cfg)[:1]
    model = json.dumps(cfg.model.model_dump())
    inverse.prepare_views(views, inverse.bsdf_element(ib.PLUGIN, model=model, init_value=0.05))
    v = views[0]
    rng = np.random.default_rng(0)
    # move off the initialisation (zero head weights would leave the body without gradient)
    state = {
        k: t + 0.2 * rng.standard_normal(t.shape).astype(np.float32)
        for k, t in ((k, t.numpy()) for k, t in v.bsdf.state_dict().items())
    }

    def set_state(s):
        import torch

        v.bsdf.load_state_dict({k: torch.from_numpy(a) for k, a in s.items()})

    integrator, sensor = v.scene.integrator(), v.scene.sensors()[0]

    def loss(grad: bool):
        with ib.evaluated_mode():
            if grad:
                for k in v.params.keys():
                    dr.enable_grad(v.params[k])
            # the integrator itself, not mi.render: mi.render draws the gradient pass's
            # samples with another seed (decorrelated from the primal's, which keeps the
            # gradient of the loss unbiased), so its gradient is not that of this estimate
            img = integrator.render(v.scene, sensor, seed=11, spp=4, develop=True, evaluate=False)
            value = inverse.relative_mse(img, v.target_tensor, v.weight_tensor)
            if grad:
                dr.backward(value)
                return {
                    k[len("raw.") :]: np.asarray(dr.grad(v.params[k]).numpy())
                    for k in v.params.keys()
                }
            return float(value.array[0])

    set_state(state)
    grads = loss(grad=True)
    checked = 0
    for name in (
        "grid.table",
        "mlp.body.0.weight",
        "mlp.body.0.bias",
        "mlp.head.weight",
        "mlp.head.bias",
    ):
        g = grads[name].reshape(-1)
        for j in np.argsort(-np.abs(g))[:2]:  # the entries the loss depends on most
            h = 1e-2
            plus, minus = dict(state), dict(state)
            plus[name] = state[name].copy().reshape(-1)
            minus[name] = state[name].copy().reshape(-1)
            plus[name][j] += h
            minus[name][j] -= h
            plus[name] = plus[name].reshape(state[name].shape)
            minus[name] = minus[name].reshape(state[name].shape)
            set_state(plus)
            lp = loss(grad=False)
            set_state(minus)
            lm = loss(grad=False)
            fd = (lp - lm) / (2 * h)
            assert abs(g[j]) > 0, name
            assert fd == pytest.approx(float(g[j]), rel=5e-3), (name, int(j))
            checked += 1
    assert checked == 10


def _random_state(bsdf, seed: int) -> dict:
    import torch

    rng = np.random.default_rng(seed)
    return {
        k: torch.from_numpy(t.numpy() + 0.2 * rng.standard_normal(t.shape).astype(np.float32))
        for k, t in bsdf.state_dict().items()
    }


def test_a_primal_render_runs_the_lowered_graph_and_equals_torchs(mi, example):
    """Without a tracked gradient the 'graph' evaluator (and 'auto' in llvm_ad_rgb)
    evaluates the RawBRDF's lowered graph and never calls torch; the 'torch' evaluator
    calls torch; the images agree at the same seed.  In symbolic mode (which torch
    cannot take) all use the graph, so a live plugin does not break a symbolic render."""
    import drjit as dr

    from neural_brdf.inverse import bsdf as ib
    from neural_brdf.inverse import fit as inverse

    cfg = config.load(example / "fit.yaml")
    model = json.dumps(cfg.model.model_dump())
    images, calls = {}, {}
    for evaluator in ib.EVALUATORS:
        views = inverse.read_views(cfg)[:1]
        el = inverse.bsdf_element(ib.PLUGIN, model=model, init_value=0.05, evaluator=evaluator)
        inverse.prepare_views(views, el)
        v = views[0]
        v.bsdf.load_state_dict(_random_state(v.bsdf, 3))
        torch_network, count = v.bsdf._network_torch, [0]

        def counted(*args, _f=torch_network, _n=count):
            _n[0] += 1
            return _f(*args)

        v.bsdf._network_torch = counted
        with ib.evaluated_mode():
            images[evaluator] = np.asarray(mi.render(v.scene, spp=4, seed=5).numpy())
        calls[evaluator] = count[0]
        symbolic = np.asarray(mi.render(v.scene, spp=4, seed=5).numpy())
        assert count[0] == calls[evaluator]  # the symbolic render did not call torch
        np.testing.assert_allclose(symbolic, images[evaluator], rtol=1e-4, atol=1e-6)
        dr.sync_thread()
    assert mi.variant() == "llvm_ad_rgb"  # where 'auto' is 'graph' (ib.AUTO)
    assert calls == {"auto": 0, "graph": 0, "torch": calls["torch"]} and calls["torch"] > 0
    ref = images["torch"]
    assert ref.max() > 0.05
    for ev in ("auto", "graph"):
        np.testing.assert_allclose(images[ev], ref, rtol=1e-4, atol=1e-5 * float(ref.max()))


@pytest.mark.parametrize(
    "model",
    [
        None,  # the compact recipe, isotropic encoding as after an isotropic start
        "{encoding: anisotropic, hidden: [16], activation: relu, "
        "grid: {size: 8, coords: half_disc}, grazing_cos: max}",
        "{encoding: anisotropic, hidden: [16, 8], activation: relu, grid: {size: 8}, "
        "cosine_grid: {size: 8}, grazing_power: 0.5}",
    ],
)
def test_the_network_alone_in_torch_gives_the_whole_forwards_values_and_gradients(mi, model):
    """Where wi and wo track no gradient, torch runs the RawBRDF's network alone and
    Dr.Jit its weight-free parts (encode, finish) from their own lowered graphs
    (bsdf._torch_f_cos): f cos and the weights' gradients are those of the whole
    RawBRDF in torch (the path taken where a direction tracks a gradient, which still
    gets its adjoint) to float32 rounding, for the grids' coordinates of either kind,
    the cosine grid, both grazing forms."""
    import drjit as dr
    import torch

    from neural_brdf.inverse import bsdf as ib

    section = ib.model_section(ib.COMPACT if model is None else model)
    if model is None:
        section = section.model_copy(update={"encoding": "isotropic"})
    model_text = json.dumps(section.model_dump())
    bsdf = mi.load_dict({"type": ib.PLUGIN, "model": model_text, "seed": 2})
    bsdf.load_state_dict(_random_state(bsdf, 4))
    rng = np.random.default_rng(3)
    n = 700
    dirs = rng.normal(size=(2, 3, n))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs[:, 2] = np.abs(dirs[:, 2])
    dirs[0, :, :20] = [[0.0], [0.0], [1.0]]  # at the normal and the mirror direction
    dirs[1, :, :20] = [[0.0], [0.0], [1.0]]
    adj = [mi.Float(a) for a in rng.random((3, n))]

    def run(track: bool):
        wi = mi.Vector3f(*[mi.Float(c) for c in dirs[0]])
        wo = mi.Vector3f(*[mi.Float(c) for c in dirs[1]])
        if track:
            dr.enable_grad(wi)
        dr.enable_grad(bsdf.weights)
        with ib.evaluated_mode():
            calls = [0]
            net = bsdf._network_torch

            def counted(*args):
                calls[0] += 1
                return net(*args)

            bsdf._network_torch = counted
            try:
                fc = bsdf._torch_f_cos(wi, wo)
            finally:
                bsdf._network_torch = net
            dr.backward(dr.sum(fc[0] * adj[0] + fc[1] * adj[1] + fc[2] * adj[2]))
        out = np.stack([fc[c].numpy() for c in range(3)], -1)
        grads = {k: dr.grad(v).numpy() for k, v in bsdf.weights.items()}
        dr.disable_grad(bsdf.weights)
        return out, grads, calls[0], dr.grad(wi.x).numpy() if track else None

    split, split_grads, split_calls, _ = run(False)
    whole, whole_grads, whole_calls, wx_grad = run(True)
    assert (split_calls, whole_calls) == (1, 0)
    assert np.abs(whole).max() > 0.01
    np.testing.assert_allclose(split, whole, rtol=1e-5, atol=1e-7 * np.abs(whole).max())
    for k, ref in whole_grads.items():
        assert np.any(ref != 0.0), k
        np.testing.assert_allclose(
            split_grads[k], ref, rtol=1e-4, atol=1e-6 * np.abs(ref).max(), err_msg=k
        )
    assert np.any(wx_grad != 0.0)
    # and torch's own RawBRDF agrees (the plugin holds the same weights)
    raw = bsdf.torch_model()
    wi_t, wo_t = (torch.tensor(d.T, dtype=torch.float32) for d in dirs)
    with torch.no_grad():
        ref = (raw(wi_t, wo_t) * wo_t[:, 2:3].clamp_min(0.0)).numpy()
    np.testing.assert_allclose(split, ref, rtol=1e-5, atol=1e-7 * np.abs(ref).max())


def test_torch_sees_the_valid_lanes_only_with_the_same_values_and_gradients(mi):
    """The torch path evaluates the lanes with both directions above the horizon only
    (gathered, then scattered back): f cos and the weights' gradients are torch's own on
    the full batch, 0 and no gradient on the others, at a third of lanes below.  The
    plugin's features come from the encoding's lowered graph in Dr.Jit, a few ulps from
    torch's where they take an atan or a log; the grid's bilinear weights scale a
    coordinate 31-fold, so its table's gradients are compared to 1e-5 of their largest
    (3e-6 was the most seen over 20 draws of the head), the others as tightly as ever."""
    import drjit as dr
    import torch

    from neural_brdf.inverse import bsdf as ib

    bsdf = mi.load_dict({"type": ib.PLUGIN, "model": ib.COMPACT, "evaluator": "torch"})
    raw = bsdf.torch_model()
    with torch.no_grad():
        head = torch.randn(raw.mlp.head.weight.shape, generator=torch.Generator().manual_seed(7))
        raw.mlp.head.weight.copy_(0.3 * head)
    bsdf.load_state_dict(raw.state_dict())
    rng = np.random.default_rng(5)
    n = 600
    dirs = rng.normal(size=(2, n, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    dirs[:, :, 2] = np.abs(dirs[:, :, 2])
    dirs[0, : n // 6, 2] *= -1.0  # wi below the horizon
    dirs[1, n // 6 : n // 3, 2] *= -1.0  # wo below
    active = np.ones(n, bool)
    active[-20:] = False  # and lanes the caller masks
    adj = rng.random((n, 3))
    with ib.evaluated_mode():
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(*[mi.Float(c) for c in dirs[0].T])
        wo = mi.Vector3f(*[mi.Float(c) for c in dirs[1].T])
        dr.enable_grad(bsdf.weights)
        out = bsdf._f_cos(si, wo, mi.Bool(active))
        dr.backward(dr.sum(sum(out[c] * mi.Float(adj[:, c]) for c in range(3))))
        got = np.stack([out[c].numpy() for c in range(3)], -1)
        grads = {k: dr.grad(v).numpy().reshape(tuple(v.shape)) for k, v in bsdf.weights.items()}
        dr.disable_grad(bsdf.weights)
    valid = active & (dirs[0, :, 2] > 0) & (dirs[1, :, 2] > 0)
    assert 0.5 < valid.mean() < 0.7
    wi_t, wo_t = (torch.tensor(d, dtype=torch.float32) for d in dirs)
    fc = raw(wi_t, wo_t) * wo_t[:, 2:3].clamp_min(0.0)
    fc = fc * torch.from_numpy(valid[:, None])
    (fc * torch.from_numpy(adj).float()).sum().backward()
    want = fc.detach().numpy()
    assert np.all(got[~valid] == 0.0)
    assert np.allclose(got, want, rtol=1e-5, atol=1e-7)
    for k, p in raw.named_parameters():
        ref = p.grad.numpy()
        assert np.any(ref != 0.0), k
        atol = (1e-5 if k.endswith("grid.table") else 1e-6) * np.abs(ref).max()
        assert np.allclose(grads[k], ref, rtol=1e-4, atol=atol), k


def test_an_unknown_evaluator_is_refused(mi):
    from neural_brdf.inverse import bsdf as ib

    with pytest.raises(Exception, match="'evaluator': 'jax' is not one of auto, graph, torch"):
        mi.load_dict({"type": ib.PLUGIN, "model": ib.COMPACT, "evaluator": "jax"})


def test_instances_of_one_model_share_a_program_and_keep_their_own_weights(mi):
    """The lowered program is made once per model section (its weights are parameters
    bound at run time): two instances share it, and each evaluates its own weights, as
    torch's RawBRDF holding them does; another section gets its own program."""
    import drjit as dr
    import torch

    from neural_brdf.inverse import bsdf as ib

    a, b = (
        mi.load_dict({"type": ib.PLUGIN, "model": ib.COMPACT, "evaluator": "graph"})
        for _ in range(2)
    )
    other = mi.load_dict({"type": ib.PLUGIN, "model": "{hidden: [16], activation: relu}"})
    assert a.program is b.program and other.program is not a.program
    a.load_state_dict(_random_state(a, 1))
    b.load_state_dict(_random_state(b, 2))
    rng = np.random.default_rng(4)
    wi, wo = (_hemisphere(rng, 256) for _ in range(2))
    values = []
    for plugin in (a, b):
        got = plugin._graph_f_cos(mi.Vector3f(*wi.T), mi.Vector3f(*wo.T))
        got = np.stack([np.asarray(c) for c in (got.x, got.y, got.z)], -1)
        with torch.no_grad():
            raw = plugin.torch_model()
            ref = raw(torch.from_numpy(wi), torch.from_numpy(wo)).numpy() * wo[:, 2:]
        assert ref.max() > 0.01
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-6 * float(ref.max()))
        values.append(got)
        dr.sync_thread()
    assert np.abs(values[0] - values[1]).max() > 0.01 * float(values[0].max())


def _hemisphere(rng, n: int) -> np.ndarray:
    v = rng.standard_normal((n, 3)).astype(np.float32)
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def test_the_fit_builds_its_plugin_with_images_evaluator(mi, example, tmp_path, monkeypatch):
    """images.evaluator reaches the plugin that fit_neural builds; its choices are the
    plugin's."""
    import typing

    from neural_brdf.inverse import bsdf as ib
    from neural_brdf.inverse import fit as inverse

    assert typing.get_args(config.Images.model_fields["evaluator"].annotation) == ib.EVALUATORS
    seen = []

    def prepare(views, element):
        seen.append(element.find("string[@name='evaluator']").get("value"))
        raise RuntimeError("stop here")

    monkeypatch.setattr(inverse, "prepare_views", prepare)
    for ev in ib.EVALUATORS:
        cfg = config.load(example / "fit.yaml", [f"images.evaluator={ev}", "images.start=constant"])
        with pytest.raises(RuntimeError, match="stop here"):
            inverse.fit_neural(cfg, inverse.read_views(cfg), tmp_path / ev)
    assert seen == list(ib.EVALUATORS)


def test_auto_picks_the_primal_evaluator_per_variant(mi):
    """'auto' is the graph in llvm_ad_rgb and torch in cuda_ad_rgb (ib.AUTO, from
    benchmarks/image_step.py); 'graph' and 'torch' are kept in both; a plugin built in
    this variant holds what its variant's rule gives."""
    from neural_brdf.inverse import bsdf as ib

    assert ib.primal_evaluator("auto", "llvm_ad_rgb") == "graph"
    assert ib.primal_evaluator("auto", "cuda_ad_rgb") == "torch"
    for variant in ib.AUTO:
        for ev in ("graph", "torch"):
            assert ib.primal_evaluator(ev, variant) == ev
    for ev in ib.EVALUATORS:
        plugin = mi.load_dict({"type": ib.PLUGIN, "model": ib.COMPACT, "evaluator": ev})
        assert plugin.primal == ib.primal_evaluator(ev, mi.variant())


# ------------------------------------------------------------------ a fit end to end
def train_args(config_path: Path, run_dir: Path, overrides: list[str]) -> list[str]:
    args = ["train", str(config_path), "--out", str(run_dir)]
    for o in overrides:
        args += ["--set", o]
    return args


@pytest.fixture(scope="module")
def fitted(mi, example, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("fit") / "run"
    # a short distillation leaves the start about 20 % off, and the image stage runs at
    # train.lr, so that it has something to do in 30 steps (a full distillation of the
    # chosen roughconductor is already within the targets' noise at 16 x 16); the short
    # distillation runs at train.lr too (null), as the constants above were measured
    split = [
        f"images.validation_pixels={HELDOUT_SHARE}",
        "images.start_train_steps=30",
        "images.start_train_lr=null",
        "images.start_lr_scale=1",
    ]
    code = cli.main(train_args(example / "fit.yaml", run_dir, FIT_OVERRIDES + split))
    return code, run_dir


def scored_weights(views) -> np.ndarray:
    """The network's weights a held-out scoring renders with (those of the first held-out
    view's plugin, flattened in name order), for tests that replace ``heldout_loss``."""
    v = next(v for v in views if v.validation_mask() is not None)
    raw = sorted(k for k in v.params.keys() if k.startswith("raw."))
    return np.concatenate([np.array(v.params[k].numpy(), copy=True).ravel() for k in raw])


def scheduled_lobes(monkeypatch, schedule: str) -> list[dict]:
    """Replace the plugin's refit of the sampling lobe: its first refit's own lobe (A, the
    start's), then at each refit the lobe that ``schedule``'s next letter names: A, B (A's
    roughness 3 times, capped at 1) or C (a third of it), so that whether two lobes
    sample alike is the test's choice, not the grid's.  Returns the lobes handed out."""
    from neural_brdf.inverse import bsdf as ib

    fit_lobe = ib.NeuralBSDFAD.refit_lobe
    given: list[dict] = []

    def refit(self, seed=0, state=None):
        first = given[0] if given else dict(fit_lobe(self, seed, state))
        lobe = dict(first)
        scale = {"A": 1.0, "B": 3.0, "C": 1 / 3}[schedule[len(given)]]
        for k in ("alpha", "alpha_x", "alpha_y"):
            lobe[k] = min(lobe[k] * scale, 1.0)
        lobe.pop("table", None)  # (a per-incidence table would override the alphas)
        given.append(lobe)
        self.set_lobe(lobe, "scheduled by the test")
        return lobe

    monkeypatch.setattr(ib.NeuralBSDFAD, "refit_lobe", refit)
    return given


def run_scripted(example: Path, run_dir: Path, monkeypatch, script: list[float]) -> list:
    """A 6-step fit of the example into ``run_dir`` at the full rate whose held-out
    scores are ``script``'s, in order (``heldout_loss`` replaced; the lobe refitted every
    2 steps, a scoring at every step, no patience).  Returns the weights each scoring
    rendered with (:func:`scored_weights`); every score of ``script`` must be used."""
    from neural_brdf.inverse import fit as fitmod

    scores, scored = iter(script), []

    def scripted(views, *, spp, seed):
        scored.append(scored_weights(views))
        return next(scores)

    monkeypatch.setattr(fitmod, "heldout_loss", scripted)
    every_step = [
        "train.steps=6",
        "images.start_steps=10",
        "images.start_train_steps=60",
        "images.start_lr_scale=1",
        "images.lobe_every=2",
        "images.validation_pixels=0.2",
        "images.validation_every=1",
        "images.patience=null",
    ]
    code = cli.main(train_args(example / "fit.yaml", run_dir, FIT_OVERRIDES + every_step))
    assert code == 0 and next(scores, None) is None, (code, len(scored))
    return scored


def start_network_change(run_dir: Path) -> float:
    """Relative RMS difference of f between the exported model and the network the GGX
    start handed to the image stage (``init/ckpt.pt``)."""
    import torch

    import neural_brdf
    from analytic import physics
    from neural_brdf.train.model import RawBRDF

    state = torch.load(run_dir / "init" / "ckpt.pt", weights_only=True)
    raw = RawBRDF.from_config(config.from_dict(state["config"]).model)
    raw.load_state_dict(state["model"])
    wi = physics.random_directions(20000, 1).astype(np.float32)
    wo = physics.random_directions(20000, 2).astype(np.float32)
    with torch.no_grad():
        start = raw.eval()(torch.from_numpy(wi), torch.from_numpy(wo)).numpy()
    now = neural_brdf.load(run_dir / "model.onnx").eval(wi, wo)
    return float(np.sqrt(np.sum((now - start) ** 2) / np.sum(start**2)))


@pytest.mark.slow
def test_small_fit_reaches_the_stated_error(mi, example, fitted):
    from neural_brdf.inverse import bsdf as ib
    from neural_brdf.inverse import fit as inverse

    code, run_dir = fitted
    assert code == 0
    for name in ("config.yaml", "ckpt.pt", "log.csv", "model.onnx", "metrics.json"):
        assert (run_dir / name).is_file(), name
    rows = (run_dir / "log.csv").read_text().splitlines()[1:]
    losses = [float(r.split(",")[1]) for r in rows]
    assert len(losses) >= 2
    metrics = json.loads((run_dir / "metrics.json").read_text())
    training = metrics["training"]
    assert training["steps"] == FIT_STEPS
    # the default start (auto): the families the isotropic network can hold, fitted on
    # the training pixels and chosen by the held-out ones: a conductor for this copper
    start = training["init"]["start"]
    assert [c["family"] for c in start["candidates"]] == [
        "diffuse",
        "roughplastic",
        "principled",
        "roughconductor",
        "clearcoat",
        "blend",
    ]
    assert list(start["left_out"]) == ["roughconductor_aniso"]
    assert start["family"] in ("roughconductor", "blend"), start
    # the start was distilled at the stage's rate (images.start_train_lr: null)
    distilled = config.load(run_dir / "init" / "config.yaml").train
    stage = config.load(run_dir / "config.yaml").train
    assert distilled.steps == 30 and distilled.lr == stage.lr
    assert training["fit_seconds"] >= training["start_seconds"] > 0
    # where the stage's time goes: its renders, held-out scorings, albedo penalties and
    # lobe refits, each timed apart within it
    parts = [training[f"{k}_seconds"] for k in ("render", "validation", "albedo", "lobe")]
    assert min(parts[:3]) > 0 and parts[3] >= 0, parts
    assert sum(parts) <= training["train_seconds"], (parts, training["train_seconds"])
    assert all(math.isfinite(x) for x in losses)
    # the image stage did something: the held-out pixels' loss fell clearly below the
    # start's, and the network moved away from the start's
    val = training["validation"]
    tiles = (RES // BLOCK) ** 2  # the split holds out whole BLOCK x BLOCK tiles
    assert val["pixels"] == HELDOUT_SHARE
    assert val["heldout_pixels"] == 3 * round(HELDOUT_SHARE * tiles) * BLOCK * BLOCK
    # the start was chosen on that split, within the object: its record says so (it
    # recorded choose_start's own unused default share, 0.25, until session 88)
    split = training["init"]["start"]["split"]
    assert 0 < split["held_out_pixels"] <= val["heldout_pixels"], (split, val)
    assert split["val_share"] == split["held_out_pixels"] / split["pixels"], split
    assert val["best_step"] > 0, val
    assert val["best_loss"] < HELDOUT_GAIN * val["start_loss"], val
    assert start_network_change(run_dir) > NETWORK_CHANGE
    header, *rows = (run_dir / "log.csv").read_text().splitlines()
    assert header.split(",")[-1] == "heldout_loss"
    held = [float(r.split(",")[-1]) for r in rows if r.split(",")[-1]]
    assert len(held) == FIT_STEPS // 10 and min(held) == pytest.approx(val["best_loss"], rel=1e-5)
    # the coverage, computed before the start
    assert training["coverage"]["figure"] > 0.9
    covered = training["coverage"]["observed_bins"]
    assert training["coverage"]["picture"] == "coverage.png"
    assert (run_dir / "coverage.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # what the views determine, near the chosen start, with the targets' own noise
    determined = training["determined"]
    assert determined["reference"] == "network"  # near the fitted network; first the start's
    assert training["determined_start"]["reference"] == ET.fromstring(
        (run_dir / "init" / "teacher.xml").read_text()
    ).get("type")
    assert determined["noise_source"] == "targets" and determined["noise"] > 0
    assert determined["figure"] <= determined["by_bin_width_deg"]["22.5"]["figure"], determined
    assert determined["by_bin_width_deg"]["22.5"]["figure"] > 0, determined  # 16² views: little
    # counted only within the bins the fit's coverage observes: never more than it
    fine, seen = (np.asarray(x, bool) for x in (determined["determined_fine"], covered))
    assert not (fine & ~seen).any()
    for det in (determined, training["determined_start"]):
        assert det["observed_figure"] == training["coverage"]["figure"], det
        assert det["by_bin_width_deg"]["22.5"]["figure"] <= det["observed_figure"], det
    assert (run_dir / "determined.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = (run_dir / "report.md").read_text()
    assert "report-determined.png" in report and "observed (the coverage, at most)" in report
    # the run's times say where they went: the start, the image stage, the whole fit
    seconds = json.loads((run_dir / "metrics.json").read_text())["seconds"]
    assert seconds["start"] == training["start_seconds"] > 0
    assert seconds["fit"] == training["fit_seconds"] >= seconds["start"] + seconds["train"]
    assert seconds["total"] >= seconds["fit"] + seconds["export"] + seconds["validate"]
    line = cli.stage_times(seconds)
    assert line.startswith(f"fit {seconds['fit']:.1f} s: start {seconds['start']:.1f} s"), line
    for label in ("whole fit (start included)", "image stage", "start (the families' fits"):
        assert f"| {label}" in report, label
    cfg = config.load(example / "fit.yaml")
    view = inverse.read_views(cfg)[0]
    mask = inverse.sphere_mask(view, erode=1)
    assert mask.sum() > 60
    fitted_el = inverse.bsdf_element("neural_brdf", filename=str(run_dir / "model.onnx"))
    err = inverse.image_rel_rmse(
        view.target, inverse.render_view(view, fitted_el, spp=256, seed=3), mask
    )
    start_el = inverse.bsdf_element(
        ib.PLUGIN, model=json.dumps(cfg.model.model_dump()), init_value=inverse.INIT_VALUE
    )
    with ib.evaluated_mode():
        start = inverse.image_rel_rmse(
            view.target, inverse.render_view(view, start_el, spp=64, seed=3), mask
        )
    assert err < FIT_IMAGE_ERROR < start, (err, start)


@pytest.mark.slow
def test_fitted_export_is_reciprocal_and_passes_the_furnace(fitted):
    import neural_brdf
    from analytic import physics

    code, run_dir = fitted
    metrics = json.loads((run_dir / "metrics.json").read_text())
    checks = metrics["checks"]
    assert checks["reciprocity"]["value"] == 0.0
    assert checks["max_albedo"]["passed"] and checks["max_albedo"]["value"] <= 1.001
    assert checks["min_value"]["value"] >= 0.0
    assert metrics["passed"]
    brdf = neural_brdf.load(run_dir / "model.onnx")
    wi = physics.random_directions(5000, 1).astype(np.float32)
    wo = physics.random_directions(5000, 2).astype(np.float32)
    a, b = brdf.eval(wi, wo), brdf.eval(wo, wi)
    assert np.array_equal(a, b)  # bit for bit
    assert np.all(np.isfinite(a)) and a.max() > 0


@pytest.mark.slow
def test_the_start_is_kept_when_the_image_stage_only_makes_it_worse(mi, example, tmp_path):
    # a learning rate far too high: every scored step is worse than the start, so the
    # run ends with the start's weights (exported as they were) and says so
    run_dir = tmp_path / "run"
    worse = [
        "train.steps=10",
        "images.start_steps=10",
        "images.start_train_steps=300",
        "images.start_lr_scale=25",
        "images.validation_pixels=0.2",
        "images.validation_every=5",
    ]
    code = cli.main(train_args(example / "fit.yaml", run_dir, FIT_OVERRIDES + worse))
    assert code == 0
    val = json.loads((run_dir / "metrics.json").read_text())["training"]["validation"]
    assert val["last_loss"] > 2 * val["start_loss"], val  # the stage made it worse
    assert val["best_step"] == 0 and val["kept"] == "the start"
    assert val["best_loss"] == val["start_loss"]
    assert start_network_change(run_dir) < 1e-4  # the export's own float32 parity
    # the start was distilled at its own rate (images.start_train_lr), not the stage's
    distilled = config.load(run_dir / "init" / "config.yaml").train
    stage = config.load(run_dir / "config.yaml").train
    assert distilled.steps == 300 and distilled.lr == config.Images().start_train_lr
    assert distilled.lr != stage.lr and distilled.warmup == stage.warmup
    # ``neural-brdf export RUN`` exports the kept weights too, not the checkpoint's last
    # step (which --resume trains on from)
    import neural_brdf
    from analytic import physics

    out = tmp_path / "again.onnx"
    assert cli.main(["export", str(run_dir), "-o", str(out)]) == 0
    wi = physics.random_directions(2000, 5).astype(np.float32)
    wo = physics.random_directions(2000, 6).astype(np.float32)
    own = neural_brdf.load(run_dir / "model.onnx")(wi, wo)
    np.testing.assert_allclose(neural_brdf.load(out)(wi, wo), own, rtol=1e-6, atol=1e-7)


@pytest.mark.slow
def test_the_image_stage_stops_after_patience_scorings_without_a_better_one(
    mi, example, tmp_path, capsys
):
    # the same too-high rate: no scored step beats the start, so with patience 2 and a
    # scoring every 5 steps the stage stops at step 10 of 30, keeps the start, says so
    # once on stderr and records it; a resumed run does not train on
    run_dir = tmp_path / "run"
    worse = [
        "train.steps=30",
        "images.start_steps=10",
        "images.start_train_steps=300",
        "images.start_lr_scale=25",
        "images.validation_pixels=0.2",
        "images.validation_every=5",
        "images.patience=2",
    ]
    args = train_args(example / "fit.yaml", run_dir, FIT_OVERRIDES + worse)
    code, err = run_cli(args, capsys)
    assert code == 0, err
    stops = [line for line in err.splitlines() if "the image stage stops at step" in line]
    assert len(stops) == 1 and "step 10 " in stops[0], err
    training = json.loads((run_dir / "metrics.json").read_text())["training"]
    val = training["validation"]
    assert training["steps"] == 10, training["steps"]
    assert val["patience"] == 2 and val["stopped_at"] == 10 and val["last_step"] == 10, val
    assert val["best_step"] == 0 and val["kept"] == "the start"
    steps = [int(line.split(",")[0]) for line in (run_dir / "log.csv").read_text().splitlines()[1:]]
    assert max(steps) == 10, steps
    report = (run_dir / "report.md").read_text()
    assert "image stage stopped" in report and "at step 10 (images.patience 2)" in report
    assert "fit" in json.loads((run_dir / "metrics.json").read_text())["seconds"]
    # resumed as it is, the stopped stage has finished: nothing to do, nothing touched
    before = (run_dir / "metrics.json").read_bytes()
    code = cli.main(args + ["--resume"])
    out, err = capsys.readouterr()
    assert code == 0 and "already finished at step 10" in out, out + err
    assert (run_dir / "metrics.json").read_bytes() == before
    # a larger patience lets it train on, to its next stop (3 scorings after step 0)
    code, err = run_cli(args + ["--resume", "--set", "images.patience=3"], capsys)
    assert code == 0, err
    metrics = json.loads((run_dir / "metrics.json").read_text())
    again = metrics["training"]
    assert again["steps"] == 15 and again["validation"]["stopped_at"] == 15, again["steps"]
    # the resumed process timed its own part alone: no whole fit's time, not fit < start
    assert again["resumed"] and "fit" not in metrics["seconds"], metrics["seconds"]
    line = cli.stage_times(metrics["seconds"])
    assert line.startswith(f"start {metrics['seconds']['start']:.1f} s, image stage"), line


@pytest.mark.slow
def test_after_a_refit_of_the_lobe_the_best_is_scored_again_through_it(
    mi, example, tmp_path, monkeypatch
):
    # a rate so small that no weight moves, the sampling lobe refitted every 2 steps,
    # each refit's lobe made wider or narrower than the fit's (as a network's refit can
    # move it), and a scoring at every step.  The held-out loss's samples follow the
    # lobe (through these lobes it moved by 39 and 18 %, the weights unchanged: measured
    # on this example), so after each refit the best weights are scored again through
    # the new lobe, and the scores that follow are compared with that: here they equal it
    from neural_brdf.inverse import bsdf as ib

    fit_lobe = ib.NeuralBSDFAD.refit_lobe
    refits = []

    def other_lobe(self, seed=0, state=None):
        lobe = dict(fit_lobe(self, seed, state))
        scale = (1.0, 3.0, 1 / 3)[len(refits) % 3]
        for k in ("alpha", "alpha_x", "alpha_y"):
            lobe[k] = min(lobe[k] * scale, 1.0)
        refits.append(lobe)
        self.set_lobe(lobe, "made other by the test")
        return lobe

    monkeypatch.setattr(ib.NeuralBSDFAD, "refit_lobe", other_lobe)
    run_dir = tmp_path / "run"
    still = [
        "train.steps=6",
        "images.start_steps=10",
        "images.start_train_steps=60",
        "images.start_lr_scale=1e-9",
        "images.lobe_every=2",
        "images.validation_pixels=0.2",
        "images.validation_every=1",
        "images.patience=null",
    ]
    code = cli.main(train_args(example / "fit.yaml", run_dir, FIT_OVERRIDES + still))
    assert code == 0
    lines = (run_dir / "log.csv").read_text().splitlines()
    col = lines[0].split(",").index("heldout_loss")
    held = [float(line.split(",")[col]) for line in lines[1:] if line.split(",")[col]]
    val = json.loads((run_dir / "metrics.json").read_text())["training"]["validation"]
    assert len(held) == 6 and len(refits) == 3, (held, refits)  # lobes at steps 0, 2, 4
    rescored = val["best_rescored"]
    assert [step for step, _ in rescored] == [2, 4], rescored
    # steps 1-2 through the start's lobe, 3-4 through step 2's, 5-6 through step 4's
    for scores, again in ((held[0:2], val["start_loss"]), (held[2:4], rescored[0][1])):
        np.testing.assert_allclose(scores, again, rtol=1e-5)
    np.testing.assert_allclose(held[4:6], rescored[1][1], rtol=1e-5)
    # metrics.json's best_loss is the kept weights' score at their step, as log.csv has it
    at = {1 + k: x for k, x in enumerate(held)} | {0: val["start_loss"]}
    assert val["best_loss"] == pytest.approx(at[val["best_step"]], rel=1e-5), (val, held)
    assert abs(rescored[0][1] / val["start_loss"] - 1) > 0.05  # the lobes did differ


@pytest.mark.slow
def test_the_weights_scored_again_after_a_refit_are_the_best_so_far(
    mi, example, tmp_path, monkeypatch
):
    # a rate far too high (every step worse than the start), the lobe refitted every 2
    # steps and a scoring at every step: replaying the rule on the scores as they came,
    # each score right after a refit is of the best weights so far (the start's here,
    # not the weights now), and the scores after it are compared with it (each refit's
    # lobe another: one that samples as the lobe in use needs no new score, below)
    from neural_brdf.inverse import bsdf as ib
    from neural_brdf.inverse import fit as fitmod

    events: list[tuple[str, np.ndarray | None, float | None]] = []
    scheduled_lobes(monkeypatch, "ABC")
    refit_lobe, heldout = ib.NeuralBSDFAD.refit_lobe, fitmod.heldout_loss

    def marked_refit(self, seed=0, state=None):
        events.append(("refit", None, None))
        return refit_lobe(self, seed, state)

    def recorded(views, *, spp, seed):
        loss = heldout(views, spp=spp, seed=seed)
        events.append(("score", scored_weights(views), loss))
        return loss

    monkeypatch.setattr(ib.NeuralBSDFAD, "refit_lobe", marked_refit)
    monkeypatch.setattr(fitmod, "heldout_loss", recorded)
    run_dir = tmp_path / "run"
    worse = [
        "train.steps=6",
        "images.start_steps=10",
        "images.start_train_steps=300",
        "images.start_lr_scale=25",
        "images.lobe_every=2",
        "images.validation_pixels=0.2",
        "images.validation_every=1",
        "images.patience=null",
    ]
    code = cli.main(train_args(example / "fit.yaml", run_dir, FIT_OVERRIDES + worse))
    assert code == 0
    stage = events[next(i for i, e in enumerate(events) if e[0] == "refit") :]
    best_w, best_loss, now_w, after_refit, rescored = None, math.inf, None, False, []
    for kind, w, loss in stage:
        if kind == "refit":
            after_refit = best_w is not None
        elif after_refit:  # the best scored again through the new lobe
            np.testing.assert_array_equal(w, best_w)
            rescored.append(not np.array_equal(w, now_w))
            best_loss, after_refit = loss, False
        else:
            now_w = w
            if loss < best_loss:
                best_w, best_loss = w, loss
    val = json.loads((run_dir / "metrics.json").read_text())["training"]["validation"]
    assert [s for s, _ in val["best_rescored"]] == [2, 4] and len(rescored) == 2, stage
    assert all(rescored), "the weights scored again were the weights now, not the best"
    assert val["kept"] == "the start"


@pytest.mark.slow
@pytest.mark.parametrize("start_again, kept", [(0.75, "the start"), (0.9, "step 4")])
def test_at_the_end_the_start_is_scored_again_through_the_last_lobe_and_kept_if_no_worse(
    mi, example, tmp_path, monkeypatch, start_again, kept
):
    # scripted held-out scores (the lobe refitted every 2 steps, a scoring at every
    # step): step 1 beats the start through the start's lobe, step 4 beats step 1's score
    # again through step 2's lobe, and after the refit at step 4 no step beats step 4's
    # score again.  The chain never compared step 4 with the start through one lobe, so
    # at the end the start is scored again through the last lobe: kept when it scores no
    # worse than the kept weights' score through it (0.75: a tie keeps the start; against
    # step 4's score through the old lobe, 0.7, it would lose), else step 4 stays

    scheduled_lobes(monkeypatch, "ABC")  # three lobes that sample differently
    script = [1.0, 0.9, 0.95, 0.8, 0.85, 0.7, 0.75, 0.8, 0.9, start_again]
    run_dir = tmp_path / "run"
    scored = run_scripted(example, run_dir, monkeypatch, script)
    assert len(scored) == len(script), "the start was not scored again at the end"
    # the scores: the start, steps 1-2, step 1 again, steps 3-4, step 4 again, steps 5-6,
    # and the start again: the last is of the start's weights, not the kept or the last
    assert len(scored) == 10
    np.testing.assert_array_equal(scored[-1], scored[0])
    assert not np.array_equal(scored[-1], scored[5])
    np.testing.assert_array_equal(scored[6], scored[5])  # step 4 scored again at its refit
    val = json.loads((run_dir / "metrics.json").read_text())["training"]["validation"]
    assert val["start_rescored"] == [6, start_again]
    assert val["best_rescored"] == [[2, 0.8], [4, 0.75]]
    assert val["kept"] == kept
    # metrics.json's best_loss: the kept weights' score at their step (log.csv's)
    assert val["best_loss"] == (1.0 if kept == "the start" else 0.7)
    # the run's model is the kept weights: the start's (to the export's float32 parity),
    # or step 4's, which the full rate has moved well away from it
    change = start_network_change(run_dir)
    assert change < 1e-4 if kept == "the start" else change > 1e-3, change


@pytest.mark.slow
@pytest.mark.parametrize(
    "lobes, script, kept",
    [
        # step 4 beats step 1 through B, then scores 1.1 through A again, above the
        # start's own 1.0 through A: the start is kept, its step-0 score used again
        ("ABA", [1.0, 0.9, 0.95, 0.8, 0.85, 0.7, 1.1, 1.2, 1.3], "the start"),
        ("ABA", [1.0, 0.9, 0.95, 0.8, 0.85, 0.7, 0.75, 0.8, 0.9], "step 4"),
        # no refit changes the lobe: every score shares the start's samples
        ("AAA", [1.0, 0.9, 0.95, 0.85, 0.7, 0.8, 0.9], "step 4"),
    ],
)
def test_a_refit_that_samples_as_before_scores_nothing_again(
    mi, example, tmp_path, monkeypatch, lobes, script, kept
):
    # scripted held-out scores (the lobe refitted every 2 steps, a scoring at every
    # step), the refits' lobes chosen by the test.  A refit whose lobe samples as the one
    # in use leaves the best's score standing (no scoring: the same samples), and at the
    # end, where the last lobe samples as the start's did, the start's own score is
    # compared with the kept weights' without scoring it again

    given = scheduled_lobes(monkeypatch, lobes)
    run_dir = tmp_path / "run"
    scored = run_scripted(example, run_dir, monkeypatch, script)
    assert len(scored) == len(script), len(scored)
    assert len(given) == 3  # the lobes of steps 0, 2 and 4
    val = json.loads((run_dir / "metrics.json").read_text())["training"]["validation"]
    assert val["kept"] == kept
    if lobes == "AAA":
        assert val["lobe_unchanged"] == [2, 4] and val["best_rescored"] == []
        assert val["start_rescored"] is None  # every score was through the start's lobe
    else:
        assert val["lobe_unchanged"] == []
        assert [step for step, _ in val["best_rescored"]] == [2, 4]
        # the start's score through the last lobe is its own of step 0 (A's samples)
        assert val["start_rescored"] == [6, 1.0] and val["start_lobe_same"] is True
        np.testing.assert_array_equal(scored[6], scored[5])  # step 4 scored again at 4
    change = start_network_change(run_dir)
    assert change < 1e-4 if kept == "the start" else change > 1e-3, change


@pytest.mark.parametrize("capture, heldout", [("lights", True), ("environment", False)])
def test_the_examples_config_names_the_command_that_writes_it_again(mi, tmp_path, capture, heldout):
    # fit.yaml's "Written by" line: run as it stands (into another folder), it writes
    # the same scenes and the same config (it named the folder alone until session 88,
    # which wrote an environment capture whatever the first had been)
    import shlex

    from neural_brdf.inverse import scene as inverse_example

    first = tmp_path / "first"
    inverse_example.write(first, resolution=8, spp=4, steps=3, capture=capture, heldout=heldout)
    text = (first / "fit.yaml").read_text()
    line = next(x for x in text.splitlines() if x.startswith("# Written by: "))
    argv = shlex.split(line.removeprefix("# Written by: "))
    assert argv[:3] == ["python", "-m", "neural_brdf.inverse.scene"], argv
    assert argv[3] == str(first), argv
    again = tmp_path / "again"
    assert inverse_example.main([str(again), *argv[4:]]) == 0
    for f in sorted(first.glob("*.xml")):
        assert (again / f.name).read_text() == f.read_text(), f.name
    assert sorted(p.name for p in again.iterdir()) == sorted(p.name for p in first.iterdir())
    assert (again / "fit.yaml").read_text() == text.replace(str(first), str(again)).replace(
        "images_first", "images_again"
    )


@pytest.mark.parametrize(
    "args, says",
    [
        (["--resolution", "0"], "--resolution: must be >= 1, got 0"),
        (["--spp", "-1"], "--spp: must be >= 1, got -1"),
        (["--steps", "-2"], "--steps: must be >= 0, got -2"),
        (["--resolution", "x"], "--resolution: invalid integer value: 'x'"),
        (["--resolution", "100000"], "--resolution and --spp: would need"),
    ],
)
def test_the_example_writer_refuses_bad_options_in_one_line(tmp_path, capsys, args, says):
    # each was a Dr.Jit traceback (exit 1) after a partial folder had been written
    from neural_brdf.inverse import scene as inverse_example

    out = tmp_path / "example"
    with pytest.raises(SystemExit) as e:
        inverse_example.main([str(out), *args])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1, err
    assert says in err and not out.exists(), err
    target = tmp_path / "a_file"
    target.write_text("mine")
    for out in (target, target / "sub"):  # the folder itself, or one above it
        with pytest.raises(SystemExit) as e:
            inverse_example.main([str(out)])
        err = capsys.readouterr().err
        assert e.value.code == 2 and f"{target} is a file, not a folder" in err, err
    assert target.read_text() == "mine"


def test_a_thin_coverage_warns_in_one_line(mi, tmp_path, capsys):
    from neural_brdf.inverse import scene as inverse_example

    inverse_example.write(tmp_path, resolution=RES, spp=16, steps=1, capture="flash")
    run_dir = tmp_path / "run"
    quick = FIT_OVERRIDES + ["train.steps=1", "train.warmup=0", "images.start=constant"]
    code, err = run_cli(train_args(tmp_path / "fit.yaml", run_dir, quick), capsys)
    assert code == 0, err
    warnings = [line for line in err.splitlines() if line.startswith("warning: coverage:")]
    assert len(warnings) == 1, err
    assert "below 25 %" in warnings[0]
    # what the views determine, measured near a grey stand-in (the constant start has no
    # analytic form): said so, not "the diffuse start" of a run without one, as before
    determined = [line for line in err.splitlines() if line.startswith("warning: determined:")]
    assert len(determined) == 1, err
    assert "stand-in for the constant start" in determined[0], determined[0]
    coverage = json.loads((run_dir / "metrics.json").read_text())["training"]["coverage"]
    assert coverage["figure"] < 0.25 and len(coverage["per_view"]) == 3
    assert (run_dir / "coverage.png").is_file()


def test_a_flash_no_flash_pair_is_fitted_as_the_flash_alone(mi, tmp_path, capsys):
    """The example's flash_pair capture (docs/inverse.md, "A flash/no-flash pair"): the
    sky's three views and a fourth, the first camera's photograph with its flash minus
    the one without (``subtract``), fitted with a scene lit by the flash alone.  The
    difference is the flash's light: a render of that scene agrees with it, the
    photograph without the flash does not; the loss weighs the pair by the flash
    photograph's light, whose noise it carries; a fit of the four views observes the
    flash's theta_d = 0 row beside the sky's many."""
    import dataclasses

    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as inverse_example
    from neural_brdf.inverse import starts

    inverse_example.write(tmp_path, resolution=RES, spp=TARGET_SPP, steps=1, capture="flash_pair")
    cfg = config.load(tmp_path / "fit.yaml")
    entries = [
        (Path(v.scene).name, Path(v.image).name, v.subtract and Path(v.subtract).name)
        for v in cfg.target.images
    ]
    assert entries == [
        ("view1.xml", "view1.exr", None),
        ("view2.xml", "view2.exr", None),
        ("view3.xml", "view3.exr", None),
        ("pair1.xml", "flash1.exr", "view1.exr"),
    ]
    assert cfg.target.images[3].label() == "flash1.exr - view1.exr"
    kinds = {
        name: [e.get("type") for e in ET.parse(tmp_path / name).getroot().iter("emitter")]
        for name in ("view1.xml", "flash1.xml", "pair1.xml")
    }
    assert kinds == {
        "view1.xml": ["envmap"],
        "flash1.xml": ["envmap", "point"],
        "pair1.xml": ["point"],
    }, kinds
    views = inverse.read_views(cfg)
    lit = inverse.read_image(tmp_path / "flash1.exr", "flash1")
    assert np.array_equal(views[3].target, lit - views[0].target)
    assert views[3].name() == "flash1.exr - view1.exr" and views[0].name() == "view1.exr"
    # every loss of the fit (the image stage's, the split's, the starts') weighs the pair
    # by the flash photograph: fit_weight, and the targets' noise estimate from it
    inverse.split_views(views, cfg.images, seed=0)
    keep = ~views[3].held_out_pixels
    share = keep.size / keep.sum()
    assert np.allclose(views[3].fit_weight(), inverse.rel_weight(lit) * keep[..., None] * share)
    assert not np.allclose(inverse.rel_weight(lit), inverse.rel_weight(views[3].target))
    assert views[0].photograph is None
    assert np.array_equal(views[0].rel_weight(), inverse.rel_weight(views[0].target))
    for v in views:
        v.object = starts.object_mask(v)
    as_difference = dataclasses.replace(views[3], photograph=None)
    pair_noise = inverse.target_noise(views[3:])
    assert pair_noise is not None and pair_noise != inverse.target_noise([as_difference])
    # the pair's expectation is the flash's light: a render of pair1.xml, not view1
    mask = inverse.sphere_mask(views[3])
    assert mask.sum() > 50
    alone = inverse_example.render_file(tmp_path / "pair1.xml", 1024, seed=99)
    total = views[3].target[mask].sum()
    assert abs(alone[mask].sum() - total) < 0.03 * total
    assert abs(views[0].target[mask].sum() - total) > 0.3 * total

    run_dir = tmp_path / "run"
    quick = FIT_OVERRIDES + ["train.steps=1", "train.warmup=0", "images.start=constant"]
    code, err = run_cli(train_args(tmp_path / "fit.yaml", run_dir, quick), capsys)
    assert code == 0, err
    per_view = json.loads((run_dir / "metrics.json").read_text())["training"]["coverage"]
    per_view = {Path(v["scene"]).name: v["figure"] for v in per_view["per_view"]}
    assert set(per_view) == {"view1.xml", "view2.xml", "view3.xml", "pair1.xml"}
    assert 0 < per_view["pair1.xml"] < 0.02  # theta_d = 0 alone
    assert per_view["view1.xml"] > 0.5


def brdf_error_where_both_cosines_exceed_half(f_fn, seed: int = 7) -> float:
    """Relative RMSE of f cos(theta_o) of ``f_fn(wi, wo) -> f`` against Mitsuba's eval of
    the example's true copper, over the benchmark's pairs (both cosines > 0.5)."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as inverse_example

    truth = inverse.mitsuba_bsdf(inverse.bsdf_element("roughconductor", **inverse_example.TRUTH))
    wi, wo = inverse.brdf_pairs(truth, 8192, seed=seed)
    fc_true = inverse.mitsuba_f_cos(truth, wi, wo)
    fc = np.asarray(f_fn(wi.astype(np.float32), wo.astype(np.float32)), np.float64) * wo[:, 2:3]
    return inverse.brdf_rel_rmse(fc, fc_true)


@pytest.mark.slow
def test_a_multi_light_capture_fits_the_brdf_where_both_cosines_exceed_half(mi, tmp_path, capsys):
    """Three views, each lit by its own point or area light and no environment (the
    multi-light capture of docs/inverse.md), fitted with the images section's defaults:
    the coverage sees the capture's bands, the start is a conductor, and the exported
    network's BRDF where both cosines exceed 0.5 is within the issue's 5 % of the truth
    (issue 29: "with a multi-light capture, <= 5 % over every such pair").  It checks the
    capture, the start and its distillation and the export; the image stage here keeps
    the start (test_small_fit_reaches_the_stated_error checks that the stage works)."""
    import neural_brdf
    from neural_brdf.inverse import scene as inverse_example

    inverse_example.write(
        tmp_path, resolution=RES, spp=TARGET_SPP, steps=FIT_STEPS, capture="lights"
    )
    run_dir = tmp_path / "run"
    split = [f"images.validation_pixels={HELDOUT_SHARE}"]
    code, err = run_cli(train_args(tmp_path / "fit.yaml", run_dir, FIT_OVERRIDES + split), capsys)
    assert code == 0, err
    training = json.loads((run_dir / "metrics.json").read_text())["training"]
    assert 0.25 < training["coverage"]["figure"] < 0.6  # three bands of theta_d
    assert training["init"]["start"]["family"] in ("roughconductor", "blend")
    net = brdf_error_where_both_cosines_exceed_half(neural_brdf.load(run_dir / "model.onnx").eval)
    assert net < LIGHTS_BRDF_ERROR, net


def test_the_pixel_split_is_seeded_and_out_of_the_loss(mi, example):
    from neural_brdf.inverse import fit as inverse

    cfg = config.load(example / "fit.yaml", ["images.validation_pixels=0.25"])
    views = inverse.read_views(cfg)
    inverse.split_views(views, cfg.images, seed=0)
    n = RES * RES
    masks = [v.validation_mask() for v in views]
    tiles = (RES // BLOCK) ** 2
    assert all(m is not None and m.sum() == round(0.25 * tiles) * BLOCK * BLOCK for m in masks)
    # whole tiles: every held-out pixel's tile is held out with it
    for m in masks:
        blocks = m.reshape(RES // BLOCK, BLOCK, RES // BLOCK, BLOCK).any(axis=(1, 3))
        assert np.array_equal(np.repeat(np.repeat(blocks, BLOCK, 0), BLOCK, 1), m)
    assert not np.array_equal(masks[0], masks[1])  # each view its own draw
    again = inverse.read_views(cfg)
    inverse.split_views(again, cfg.images, seed=0)
    assert all(np.array_equal(a.validation_mask(), m) for a, m in zip(again, masks))
    inverse.split_views(again, cfg.images, seed=1)
    assert not np.array_equal(again[0].validation_mask(), masks[0])
    for v, m in zip(views, masks):
        w, full = v.fit_weight(), inverse.rel_weight(v.target)
        assert np.all(w[m] == 0)
        # the loss stays a mean over the fitted pixels
        assert w.sum() == pytest.approx(full[~m].sum() * n / (n - m.sum()), rel=1e-5)
    # whole views: held out, not fitted, every pixel scored
    cfg = config.load(
        example / "fit.yaml", ["images.validation_views=[1]", "images.validation_pixels=0"]
    )
    views = inverse.read_views(cfg)
    inverse.split_views(views, cfg.images, seed=0)
    assert [v.held_out for v in views] == [False, True, False]
    assert inverse.fitted_views(views) == [views[0], views[2]]
    assert views[1].validation_mask().all() and views[0].validation_mask() is None
    # no split: the fit's weights as before
    cfg = config.load(example / "fit.yaml", ["images.validation_pixels=0", "images.start=ggx"])
    views = inverse.read_views(cfg)
    inverse.split_views(views, cfg.images, seed=0)
    assert all(v.validation_mask() is None for v in views)
    assert np.array_equal(views[0].fit_weight(), inverse.rel_weight(views[0].target))


@pytest.mark.slow
def test_a_resumed_run_keeps_its_split(fitted, example, tmp_path, capsys):
    import shutil

    _, run_dir = fitted
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    before = (copy / "ckpt.pt").read_bytes()
    # the split's share, and its tiles' size (a new split, scored against the old
    # split's best: no step after the resume could be kept; it resumed before)
    for key, value in [("validation_pixels", "0.3"), ("validation_block", "8")]:
        other = FIT_OVERRIDES + ["train.steps=40", f"images.{key}={value}"]
        code, err = run_cli(train_args(example / "fit.yaml", copy, other) + ["--resume"], capsys)
        assert code == 2, err
        lines = [s for s in err.strip().splitlines() if s.strip()]
        assert len(lines) == 1 and f"images.{key}" in lines[0], err
        assert (copy / "ckpt.pt").read_bytes() == before


@pytest.mark.slow
def test_resuming_a_finished_images_run_touches_nothing(fitted, example, tmp_path, capsys):
    # docs/cli.md: "already finished ...; nothing to do", exit 0, no file touched; an
    # images run exported, validated and reported again before, rewriting its timings
    import shutil

    code, run_dir = fitted
    assert code == 0
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    split = [
        f"images.validation_pixels={HELDOUT_SHARE}",
        "images.start_train_steps=30",
        "images.start_train_lr=null",
        "images.start_lr_scale=1",
    ]
    files = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in copy.rglob("*") if p.is_file()}
    args = train_args(example / "fit.yaml", copy, FIT_OVERRIDES + split) + ["--resume"]
    code = cli.main(args)
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "already finished" in out and "nothing to do" in out, out + err
    now = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in copy.rglob("*") if p.is_file()}
    assert now == files


@pytest.mark.slow
def test_a_run_stopped_after_its_last_step_keeps_its_final_figures(
    fitted, example, tmp_path, capsys
):
    """Stopped after the image stage's last step, before its export (here: model.onnx
    and metrics.json not yet written), the resume has no step left: metrics.json's
    final_loss, final_image_loss, final_albedo_penalty and final_max_albedo_estimate
    were NaN (the figures lived in the loop alone); they come from the checkpoint."""
    import json
    import shutil

    code, run_dir = fitted
    assert code == 0
    before = json.loads((run_dir / "metrics.json").read_text())["training"]
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    (copy / "model.onnx").unlink()
    (copy / "metrics.json").unlink()
    split = [
        f"images.validation_pixels={HELDOUT_SHARE}",
        "images.start_train_steps=30",
        "images.start_train_lr=null",
        "images.start_lr_scale=1",
    ]
    args = train_args(example / "fit.yaml", copy, FIT_OVERRIDES + split) + ["--resume"]
    code = cli.main(args)
    out, err = capsys.readouterr()
    assert code == 0, err
    after = json.loads((copy / "metrics.json").read_text())["training"]
    for key in ("final_loss", "final_image_loss", "final_albedo_penalty"):
        assert isinstance(after[key], float) and math.isfinite(after[key]), (key, after[key])
        assert after[key] == before[key], key
    assert after["final_max_albedo_estimate"] == before["final_max_albedo_estimate"]


def test_a_run_stopped_during_its_start_resumes_by_starting_again(
    mi, example, tmp_path, capsys, monkeypatch
):
    """Ctrl-C while the start is chosen or distilled (before the image stage has a
    checkpoint) said "continue with --resume", and --resume then refused the folder
    (no ckpt.pt): now it fits again from the start's choice, saying so in one line.  A
    folder that is no such run still has nothing to resume."""
    from neural_brdf.inverse import starts

    run_dir = tmp_path / "run"
    real = starts.network_start

    def stopped(cfg, views, init_dir, **kw):
        Path(init_dir).mkdir(parents=True, exist_ok=True)  # as distill's run folder
        raise KeyboardInterrupt

    monkeypatch.setattr(starts, "network_start", stopped)
    overrides = FIT_OVERRIDES + ["images.start=diffuse", "images.start_train_steps=30"]
    code, err = run_cli(train_args(example / "fit.yaml", run_dir, overrides), capsys)
    assert code == 130, err
    assert not (run_dir / "ckpt.pt").exists() and (run_dir / "init").is_dir()
    monkeypatch.setattr(starts, "network_start", real)
    args = train_args(example / "fit.yaml", run_dir, overrides) + ["--resume"]
    code, err = run_cli(args, capsys)
    assert code == 0, err
    assert "does not exist yet (the run was stopped during its start" in err, err
    assert "the fit starts again" in err and (run_dir / "model.onnx").is_file()
    code, err = run_cli(
        train_args(example / "fit.yaml", tmp_path / "none", overrides) + ["--resume"], capsys
    )
    assert code == 2 and "no checkpoint" in err, err


# ------------------------------------------------------------------ bad inputs
def _config(folder: Path, views: list[tuple[str, str]], extra: str = "") -> Path:
    lines = ["target:", "  images:"]
    lines += [f"    - {{scene: {s}, image: {i}}}" for s, i in views]
    path = folder / "bad.yaml"
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


def _expect_exit_2(path: Path, out: Path, capsys, *needles: str) -> None:
    code, err = run_cli(["train", str(path), "--out", str(out)], capsys)
    assert code == 2, err
    lines = [s for s in err.strip().splitlines() if s.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert not (out / "ckpt.pt").exists()


@pytest.fixture
def copy_of(example, tmp_path):
    import shutil

    for p in example.iterdir():
        shutil.copy(p, tmp_path / p.name)
    return tmp_path


def test_a_prb_scene_fits_without_dr_jit_s_notes_on_every_step(copy_of, capfd):
    """prb (run as prb_basic) in the evaluated mode of an image step: Mitsuba 3.9 makes
    Dr.Jit warn at every render and adjoint pass (ad_call ... forcefully running the
    vectorized call in symbolic mode), two lines per view and step; the stage keeps
    Dr.Jit's warnings off for such views (views.jit_notes_off), and the fit runs."""
    for xml in copy_of.glob("view*.xml"):
        text = xml.read_text()
        assert '<integrator type="path">' in text
        xml.write_text(text.replace('<integrator type="path">', '<integrator type="prb">'))
    quick = ["train.steps=3", "images.start=constant", "images.start_train_steps=20"]
    code = cli.main(train_args(copy_of / "fit.yaml", copy_of / "run", FIT_OVERRIDES + quick))
    out, err = capfd.readouterr()
    assert code == 0, err
    assert "ad_call" not in err, err[:2000]
    import drjit as dr

    assert dr.log_level() == dr.LogLevel.Warn  # restored after the stage


def test_missing_exr_exits_2(copy_of, capsys):
    path = _config(copy_of, [("view1.xml", "nowhere.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "nowhere.exr", "no such image")


def test_unreadable_exr_exits_2(copy_of, capsys):
    (copy_of / "broken.exr").write_bytes(b"v/1\x01 not an exr at all" * 10)
    path = _config(copy_of, [("view1.xml", "broken.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "broken.exr", "unreadable EXR")


def test_one_channel_exr_exits_2(mi, copy_of, capsys):
    grey = np.ones((RES, RES, 1), np.float32)
    bmp = mi.Bitmap(grey, mi.Bitmap.PixelFormat.Y)
    bmp.write(str(copy_of / "grey.exr"))
    path = _config(copy_of, [("view1.xml", "grey.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "grey.exr", "expected linear RGB")


def test_negative_pixels_are_warned_in_one_line_and_fitted(mi, copy_of, capsys):
    """A radiance is never negative, but noise about 0 is (a subtracted ambient frame):
    the run goes on, saying how many pixels and how far; a clean image says nothing."""
    from neural_brdf import config as cfgmod
    from neural_brdf.inverse import fit as inverse

    img = np.array(mi.Bitmap(str(copy_of / "view1.exr")), np.float32)[..., :3]
    noisy = img - 0.02 * float(img.max())  # the darkest pixels go below 0
    mi.Bitmap(np.ascontiguousarray(noisy)).write(str(copy_of / "noisy.exr"))
    expected = int((noisy < 0).any(-1).sum())
    assert 0 < expected < noisy.shape[0] * noisy.shape[1]
    for name, warned in (("view1.exr", False), ("noisy.exr", True)):
        cfg = cfgmod.load(_config(copy_of, [("view1.xml", name)]))
        capsys.readouterr()
        (view,) = inverse.read_views(cfg)
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        if not warned:
            assert lines == [], err
            continue
        assert len(lines) == 1 and lines[0].startswith("warning: target.images[0].image:"), err
        assert "noisy.exr" in lines[0] and f"{expected} pixels" in lines[0]
        assert np.array_equal(view.target, noisy)  # fitted as it is, not clamped


def test_a_view_listed_twice_exits_2(copy_of, capsys):
    # (it was fitted, weighing twice in every loss)
    path = _config(
        copy_of,
        [("view1.xml", "view1.exr"), ("view2.xml", "view2.exr"), ("view1.xml", "view1.exr")],
    )
    _expect_exit_2(path, copy_of / "run", capsys, "target.images[2]", "target.images[0]")


def test_a_png_named_exr_or_a_pixel_beyond_float32s_reach_exits_2(mi, copy_of, capsys):
    """Mitsuba reads an image by its content, whatever its name: a PNG named .exr was
    fitted (8-bit, clipped at 1, sRGB-decoded) without a word; a pixel of 1e30 made the
    loss overflow and the run diverge at step 0 with advice about the learning rate."""
    from neural_brdf.inverse import scene as inverse_example

    img = np.array(mi.Bitmap(str(copy_of / "view1.exr")), np.float32)[..., :3]
    png = mi.Bitmap(np.ascontiguousarray(img)).convert(
        mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True
    )
    png.write(str(copy_of / "png.png"))
    (copy_of / "png.exr").write_bytes((copy_of / "png.png").read_bytes())
    path = _config(copy_of, [("view1.xml", "png.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "png.exr", "not an OpenEXR file")
    huge = img.copy()
    huge[0, 0] = 1e30
    inverse_example.write_exr(copy_of / "huge.exr", huge)
    path = _config(copy_of, [("view1.xml", "huge.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "huge.exr", "1e+30", "overflow")


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda t: re.sub(r"<sensor .*?</sensor>", "", t, flags=re.S), "no <sensor>"),
        (lambda t: re.sub(r"<emitter .*?</emitter>", "", t, flags=re.S), "no emitter"),
        (lambda t: t.replace("</film>", _pixel_format("rgba")), "pixel_format is 'rgba'"),
        (lambda t: t.replace("</film>", _pixel_format("luminance")), "'luminance'"),
        (lambda t: t.replace("</film>", _pixel_format("xyz")), "'xyz'"),
    ],
    ids=["no sensor", "no emitter", "rgba film", "luminance film", "xyz film"],
)
def test_a_scene_without_camera_light_or_rgb_film_exits_2(copy_of, capsys, edit, needle):
    # (a traceback, or a film of other channels fitted against RGB images, before)
    (copy_of / "edited.xml").write_text(edit((copy_of / "view1.xml").read_text()))
    path = _config(
        copy_of,
        [("edited.xml", "view1.exr")],
        "train: {steps: 1, progress: false}\nimages: {start: constant}\n",
    )
    _expect_exit_2(path, copy_of / "run", capsys, "edited.xml", needle)


def test_a_scene_with_two_sensors_is_warned_in_one_line(mi, copy_of, capsys):
    from neural_brdf import config as cfgmod
    from neural_brdf.inverse import fit as inverse

    text = (copy_of / "view1.xml").read_text()
    sensor = re.search(r"<sensor .*?</sensor>", text, flags=re.S).group(0)
    (copy_of / "two.xml").write_text(text.replace(sensor, sensor + "\n" + sensor))
    for name, warned in (("view1.xml", False), ("two.xml", True)):
        views = inverse.read_views(cfgmod.load(_config(copy_of, [(name, "view1.exr")])))
        capsys.readouterr()
        inverse.check_films(views)
        lines = capsys.readouterr().err.strip().splitlines()
        if not warned:
            assert lines == [], lines
            continue
        assert len(lines) == 1, lines
        assert lines[0].startswith(f"warning: {copy_of / 'two.xml'}: 2 sensors;"), lines
        assert "the fit renders the first (scene.sensors()[0])" in lines[0]


def test_a_film_of_one_tile_says_how_to_hold_out_instead():
    import types

    from neural_brdf import config as cfgmod
    from neural_brdf.errors import InputError
    from neural_brdf.inverse import fit as inverse

    view = types.SimpleNamespace(target=np.zeros((1, 1, 3)), image_path=Path("dot.exr"))
    for block, advice in ((4, "give a smaller block"), (1, "images.validation_views")):
        images = cfgmod.Images(validation_block=block)
        with pytest.raises(InputError, match=r"dot.exr \(1x1 pixels\) is one tile") as e:
            inverse.split_views([view], images, seed=0)
        assert advice in str(e.value) and (block > 1 or "smaller" not in str(e.value))


def _pixel_format(value: str) -> str:
    return f'<string name="pixel_format" value="{value}"/></film>'


def test_a_pair_whose_subtracted_photograph_is_missing_of_another_size_or_no_darker_exits_2(
    mi, copy_of, capsys
):
    from neural_brdf.inverse import scene as inverse_example

    path = _config(copy_of, [("view1.xml", "view1.exr")])
    text = path.read_text().replace("image: view1.exr}", "image: view1.exr, subtract: gone.exr}")
    path.write_text(text)
    _expect_exit_2(path, copy_of / "run", capsys, "target.images[0].subtract", "gone.exr")
    inverse_example.write_exr(copy_of / "small.exr", np.ones((RES // 2, RES, 3), np.float32))
    path.write_text(text.replace("gone.exr", "small.exr"))
    _expect_exit_2(
        path, copy_of / "run", capsys, "target.images[0].subtract", f"{RES}x{RES // 2}", "view1.exr"
    )
    # the same photograph twice, or the two swapped: no light left, not fitted as it is
    img = np.array(mi.Bitmap(str(copy_of / "view1.exr")), np.float32)[..., :3]
    inverse_example.write_exr(copy_of / "bright.exr", 2.0 * img)
    for other in ("view1.exr", "bright.exr"):
        path.write_text(text.replace("gone.exr", other))
        _expect_exit_2(
            path, copy_of / "run", capsys, "target.images[0].subtract", other, "holds no light"
        )


def test_image_of_another_size_exits_2(copy_of, capsys):
    from neural_brdf.inverse import scene as inverse_example

    inverse_example.write_exr(copy_of / "small.exr", np.ones((RES // 2, RES, 3), np.float32))
    path = _config(copy_of, [("view1.xml", "view1.exr"), ("view2.xml", "small.exr")])
    _expect_exit_2(
        path,
        copy_of / "run",
        capsys,
        "small.exr",
        f"{RES}x{RES // 2}",
        "view2.xml",
        f"{RES}x{RES}",
    )


def test_scene_without_fit_bsdf_exits_2(copy_of, capsys):
    text = (copy_of / "view1.xml").read_text().replace('id="fit"', 'id="copper"')
    (copy_of / "nofit.xml").write_text(text)
    path = _config(copy_of, [("nofit.xml", "view1.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "nofit.xml", 'id="fit"')


def test_scene_whose_fit_bsdf_no_shape_uses_exits_2(copy_of, capsys):
    # Mitsuba 3.9's mi.traverse lists the unused BSDF too: the check reads the XML
    text = (copy_of / "view1.xml").read_text()
    assert text.count('<ref id="fit"/>') == 1
    (copy_of / "unused.xml").write_text(text.replace('<ref id="fit"/>', '<bsdf type="diffuse"/>'))
    path = _config(
        copy_of,
        [("unused.xml", "view1.exr")],
        "train: {steps: 2, progress: false}\nimages: {start: constant}\n",
    )
    _expect_exit_2(path, copy_of / "run", capsys, "unused.xml", "no <shape> uses")


def test_a_fit_used_through_a_referenced_wrapper_is_named(copy_of, capsys):
    """A shape that refers to a twosided holding the fit uses it, through the wrapper:
    the message says so (it said that no shape uses the fit)."""
    text = (copy_of / "view1.xml").read_text()
    start = text.index('<bsdf type="roughconductor" id="fit">')
    end = text.index("</bsdf>", start) + len("</bsdf>")
    wrapped = f'<bsdf type="twosided" id="ts">{text[start:end]}</bsdf>'
    text = text[:start] + wrapped + text[end:]
    (copy_of / "ts.xml").write_text(text.replace('<ref id="fit"/>', '<ref id="ts"/>'))
    path = _config(copy_of, [("ts.xml", "view1.exr")])
    _expect_exit_2(
        path,
        copy_of / "run",
        capsys,
        "ts.xml",
        '<bsdf type="twosided" id="ts">',
        "which a shape uses",
    )


@pytest.mark.parametrize(
    ("rfilter", "reach"),
    [
        ("", 2),
        ('<rfilter type="box"/>', 0),
        ('<rfilter type="gaussian"><float name="stddev" value="0.75"/></rfilter>', 3),
    ],
)
def test_the_object_mask_leaves_out_as_much_outline_as_the_films_filter_reaches(
    copy_of, rfilter, reach
):
    """The object's pixels exclude those a splat of the background can reach: the
    film's filter's border (Mitsuba's default Gaussian 2 pixels, a box none, a Gaussian
    of stddev 0.75 three); a fixed 2 let a wide filter's background in and cut a box's
    edge pixels for nothing."""
    from neural_brdf.inverse import starts
    from neural_brdf.inverse import views as inverse

    text = (copy_of / "view1.xml").read_text()
    assert text.count('<film type="hdrfilm">') == 1
    (copy_of / "f.xml").write_text(
        text.replace('<film type="hdrfilm">', f'<film type="hdrfilm">{rfilter}')
    )
    path = _config(copy_of, [("f.xml", "view1.exr")])
    (view,) = inverse.read_views(config.load(path))
    hit, front, got = inverse.fit_hits(view)
    assert got == reach
    mask = starts.seen_object_mask(view, "target.images[0].scene")
    assert np.array_equal(mask, inverse.eroded(hit, reach)) and mask.any()
    assert np.array_equal(inverse.sphere_mask(view), mask)
    if reach == 0:
        assert np.array_equal(mask, hit)
    else:
        assert mask.sum() < inverse.eroded(hit, reach - 1).sum()


@pytest.mark.parametrize(
    ("share", "side", "needle"),
    [(0.02, "held", "view1.exr"), (0.99, "fitted", "keep no pixel")],
    ids=["held-out-tiles-off-the-object", "fitted-tiles-off-the-object"],
)
def test_a_split_whose_tiles_miss_the_object_exits_2(copy_of, capsys, share, side, needle):
    """One view, 2 % of its tiles held out: at a seed whose one held-out tile lies off
    the sphere the held-out loss had nothing to score (an assertion failed after the run
    folder was written, exit 1); 99 % held out: at a seed whose one fitted tile lies off
    it, the start raised "no training pixels".  Both exit 2 now, before any write,
    naming images.validation_pixels."""
    from neural_brdf.inverse import starts, views

    path = _config(
        copy_of, [("view1.xml", "view1.exr")], f"images: {{validation_pixels: {share}}}\n"
    )
    cfg = config.load(path)
    (view,) = views.read_views(cfg)
    view.object = starts.seen_object_mask(view, "target.images[0].scene")
    for seed in range(40):
        views.split_views([view], cfg.images, seed)
        mask = view.validation_mask() if side == "held" else ~view.validation_mask()
        if not (mask & view.object).any():
            break
    else:
        pytest.fail(f"no seed of 40 puts every {side} tile off the sphere")
    path.write_text(path.read_text() + f"train: {{seed: {seed}}}\n")
    _expect_exit_2(path, copy_of / "run", capsys, "images.validation_pixels", needle)


def test_an_object_with_no_pixel_inside_its_outline_exits_2(copy_of, capsys):
    text = (copy_of / "view1.xml").read_text()
    assert text.count('<shape type="sphere">') == 1
    small = '<shape type="sphere"><float name="radius" value="0.3"/>'
    (copy_of / "small.xml").write_text(text.replace('<shape type="sphere">', small))
    path = _config(copy_of, [("small.xml", "view1.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "small.xml", "covers no pixel")


@pytest.mark.parametrize("depth", ["0", "1"])
def test_an_integrator_that_renders_no_reflected_light_exits_2(copy_of, capsys, depth):
    """max_depth 1 sees the emitters alone: the object rendered black and the fit ran,
    exit 0, on the albedo penalty alone."""
    text = (copy_of / "view1.xml").read_text()
    text, n = re.subn(r'(<integer name="max_depth" value=")[^"]*(")', rf"\g<1>{depth}\2", text)
    assert n == 1
    (copy_of / "shallow.xml").write_text(text)
    path = _config(copy_of, [("shallow.xml", "view1.exr")])
    _expect_exit_2(path, copy_of / "run", capsys, "shallow.xml", f"max_depth is {depth}")


@pytest.mark.parametrize(
    "key",
    [
        "images.primal_spp",
        "images.validation_spp",
        "images.start_spp",
        "images.start_primal_spp",
        "images.start_refine_spp",
    ],
)
def test_samples_beyond_the_memory_budget_exit_2(copy_of, capsys, key):
    # (a short constant-start fit, were the check missing)
    name = key.removeprefix("images.")
    extra = (
        f"train: {{steps: 1, progress: false}}\nimages: {{start: constant, {name}: 100000000}}\n"
    )
    path = _config(copy_of, [("view1.xml", "view1.exr")], extra)
    _expect_exit_2(path, copy_of / "run", capsys, key, "would need", f"{RES}x{RES}")


def test_a_fit_bsdf_is_used_by_reference_or_nested():
    from neural_brdf.inverse import fit as inverse

    def used(body: str) -> bool:
        return inverse.fit_is_used(ET.fromstring(f'<scene version="3.0.0">{body}</scene>'))

    fit = '<bsdf type="diffuse" id="fit"/>'
    assert used(fit + '<shape type="sphere"><ref id="fit"/></shape>')
    assert used('<shape type="sphere"><bsdf type="diffuse" id="fit"/></shape>')
    assert used(fit + '<shape type="sphere"><bsdf type="twosided"><ref id="fit"/></bsdf></shape>')
    assert not used(fit + '<shape type="sphere"><bsdf type="diffuse"/></shape>')
    assert not used(fit + '<bsdf type="twosided" id="other"><ref id="fit"/></bsdf>')
    assert not used(fit + '<shape type="sphere"><ref id="other"/></shape>')


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_spectral"])
def test_non_rgb_or_scalar_variant_exits_2(copy_of, capsys, variant):
    path = _config(copy_of, [("view1.xml", "view1.exr")], f"  variant: {variant}\n")
    _expect_exit_2(path, copy_of / "run", capsys, "bad.yaml", "target.variant", variant)


def test_a_variant_from_train_device_names_train_device(copy_of, capsys, monkeypatch):
    """No target.variant: train.device chose cuda_ad_rgb, so the error names it (and its
    fix), not a target.variant the config does not have."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    path = _config(copy_of, [("view1.xml", "view1.exr")], "train: {device: cuda}\n")
    _expect_exit_2(path, copy_of / "run", capsys, "train.device", "cuda_ad_rgb", "cpu")


def test_paths_are_relative_to_the_config_file(copy_of):
    path = _config(copy_of, [("view1.xml", "view1.exr")])
    cfg = config.load(path)
    assert cfg.target.images[0].scene == os.path.abspath(copy_of / "view1.xml")
    assert cfg.target.images[0].image == os.path.abspath(copy_of / "view1.exr")
    with pytest.raises(config.ConfigError, match="target.images"):
        config.load(path, ["target.model=microfacet"])


# ------------------------------------------------------------------ a poor start
def test_poor_start_marks_only_a_start_whose_loss_exceeds_the_noise_by_the_limit(capsys):
    from neural_brdf.inverse import fit as inverse

    info = {"start": {"family": "diffuse", "val_loss": 0.25}}
    assert not inverse.poor_start(info, None) and "poor" not in info["start"]
    assert not inverse.poor_start(info, 0.3) and "poor" not in info["start"]
    # 0.25 is 0.05 above a noise of 0.2: not poor under 0.06, poor under 0.04
    assert not inverse.poor_start(info, 0.06, 0.2) and "poor" not in info["start"]
    assert info["start"]["target_noise"] == 0.2
    assert inverse.poor_start(info, 0.04, 0.2)
    poor = info["start"]["poor"]
    assert poor["val_loss"] == 0.25 and poor["limit"] == 0.04 and poor["target_noise"] == 0.2
    assert poor["excess"] == pytest.approx(0.05)
    err = capsys.readouterr().err
    assert "images.poor_start_loss" in err and "diffuse" in err and "noise" in err


def test_a_start_far_above_its_noise_but_not_poor_is_warned_of(capsys):
    """Under point lights a start can be hundreds of times the targets' noise and still
    under images.poor_start_loss (an excess): it is warned of, once, with the value to
    set, and recorded; a start near its noise, or a poor one, is not."""
    from neural_brdf.inverse import fit as inverse

    noise = 1e-6
    far = {"start": {"family": "diffuse", "val_loss": 600 * noise}}
    assert not inverse.poor_start(far, 0.0015, noise)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("warning: start diffuse")
    assert "600 times" in err and "images.poor_start_loss" in err and "below 0.0006" in err
    rec = far["start"]["far_above_noise"]
    assert rec["ratio"] == pytest.approx(600) and rec["limit"] == 0.0015
    assert rec["excess"] == pytest.approx(599 * noise)
    near = {"start": {"family": "roughplastic", "val_loss": 0.9 * inverse.FAR_ABOVE_NOISE * noise}}
    assert not inverse.poor_start(near, 0.0015, noise)
    assert capsys.readouterr().err == "" and "far_above_noise" not in near["start"]
    poor = {"start": {"family": "diffuse", "val_loss": 0.01}}
    assert inverse.poor_start(poor, 0.0015, noise)
    assert "far_above_noise" not in poor["start"] and "warning" not in capsys.readouterr().err
    unknown = {"start": {"family": "diffuse", "val_loss": 600 * noise}}
    assert not inverse.poor_start(unknown, 0.0015, None)
    assert "far_above_noise" not in unknown["start"]
    broken = {"start": {"family": "diffuse", "val_loss": float("nan")}}
    assert not inverse.poor_start(broken, 0.0015, noise)
    assert "far_above_noise" not in broken["start"] and capsys.readouterr().err == ""


@pytest.mark.parametrize("capture", ["environment", "lights"])
def test_target_noise_estimates_the_targets_own_noise_from_one_image(mi, tmp_path, capture):
    """The estimate from each target alone (inverse.fit.target_noise) against the noise
    measured by a second render of every view with another seed: the mean over the
    object's pixels of the relative MSE's weight times (y1 - y2)^2 / 2, at 16 and 256
    samples per pixel.  Within 35 % of it plus 1e-4 (a fifteenth of the default
    images.poor_start_loss: the rule needs no finer figure), under an environment and
    under point and area lights (whose sharp highlights leave a residue of about 5e-5
    at 64^2); and under the environment, where the noise is larger than that residue,
    the target of 16 times the samples is estimated at least 5 times quieter."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as inverse_example
    from neural_brdf.inverse import starts

    def estimate_and_truth(folder, spp):
        inverse_example.write(folder, resolution=64, spp=spp, steps=5, capture=capture)
        views = inverse.read_views(config.load(folder / "fit.yaml"))
        truth = []
        for k, v in enumerate(views, start=1):
            v.object = starts.object_mask(v)
            again = inverse_example.render_file(v.scene_path, spp, seed=1000 + k)
            w = inverse.rel_weight(v.target)
            truth.append((w * (v.target - again) ** 2)[v.object].mean() / 2)
        return inverse.target_noise(views), float(np.mean(truth))

    found = {spp: estimate_and_truth(tmp_path / str(spp), spp) for spp in (16, 256)}
    for spp, (est, truth) in found.items():
        assert truth > 0 and abs(est - truth) < 0.35 * truth + 1e-4, (spp, est, truth)
    if capture == "environment":
        assert found[256][0] < found[16][0] / 5, found


@pytest.mark.parametrize("limit, poor", [("1e-9", True), ("null", False)])
def test_a_poor_start_runs_the_image_stage_at_the_full_rate(
    mi, example, tmp_path, capsys, limit, poor
):
    """Every start is poor under a limit of 1e-9: it is distilled at
    images.poor_start_train_lr for images.poor_start_train_steps, and the image stage
    runs at train.lr (the grids at images.poor_start_grid_lr_scale) for
    images.poor_start_steps (the run's config.yaml says so), and a resumed run keeps
    that rate and those steps; no limit keeps
    images.start_train_lr, images.start_train_steps, images.start_lr_scale and
    train.steps."""
    run_dir = tmp_path / "run"
    sets = [
        *FIT_OVERRIDES,
        "train.steps=4",
        "images.start=diffuse",
        "images.start_steps=5",
        "images.start_train_steps=20",
        "images.poor_start_steps=6",
        "images.poor_start_grid_lr_scale=2.5",
        "images.poor_start_train_lr=0.007",
        "images.poor_start_train_steps=15",
        f"images.poor_start_loss={limit}",
    ]
    code, err = run_cli(train_args(example / "fit.yaml", run_dir, sets), capsys)
    assert code == 0, err
    tr = json.loads((run_dir / "metrics.json").read_text())["training"]
    assert tr["lr_factor"] == (1.0 if poor else 0.05)
    # the grids' rate: images.poor_start_grid_lr_scale after a poor start, else
    # images.start_grid_lr_scale (1.0 by default)
    assert tr["grid_lr_scales"] == dict.fromkeys(("grid.", "cos_grid."), 2.5 if poor else 1.0)
    assert ("poor" in tr["init"]["start"]) == poor
    assert ("no family fits the views" in err) == poor
    assert tr["steps"] == (6 if poor else 4)
    assert ("runs at train.lr for up to 6 steps" in err) == poor
    assert tr["init"]["start"].get("poor", {}).get("steps") == (6 if poor else None)
    assert config.load(run_dir / "config.yaml").train.steps == (6 if poor else 4)
    # the distillation's rate, decided before it ran by the verdict the stage then took
    distilled = config.load(run_dir / "init" / "config.yaml").train
    assert distilled.lr == tr["init"]["lr"] == (0.007 if poor else config.Images().start_train_lr)
    assert distilled.steps == tr["init"]["steps"] == (15 if poor else 20)
    if poor:  # resumed: the rate and the steps come from the checkpoint's start
        more = train_args(example / "fit.yaml", run_dir, [*sets, "images.poor_start_steps=8"])
        code, err = run_cli([*more, "--resume"], capsys)
        assert code == 0, err
        again = json.loads((run_dir / "metrics.json").read_text())["training"]
        assert again["lr_factor"] == 1.0 and again["steps"] == 8
        assert again["grid_lr_scales"] == tr["grid_lr_scales"]


def test_a_poor_start_is_distilled_at_its_own_rate_else_train_lr():
    from neural_brdf.inverse import views

    cfg = config.Config.model_validate({"name": "x", "train": {"lr": 0.004}})
    assert views.start_training(cfg, 5)["lr"] == cfg.images.start_train_lr != cfg.train.lr
    assert cfg.images.poor_start_train_lr is None  # the default: train.lr
    assert views.start_training(cfg, 5, poor=True)["lr"] == 0.004
    own = cfg.model_copy(
        update={"images": cfg.images.model_copy(update={"poor_start_train_lr": 0.02})}
    )
    assert views.start_training(own, 5, poor=True)["lr"] == 0.02
    # the verdict: a loss above the noise by more than the limit (None: never poor)
    assert views.is_poor(0.25, 0.04, 0.2) and not views.is_poor(0.25, 0.06, 0.2)
    assert not views.is_poor(0.25, None, 0.2) and not views.is_poor(None, 0.04, 0.2)
    assert views.is_poor(0.05, 0.04, None)


def test_poor_start_config_raises_the_steps_of_a_poor_start_only():
    from neural_brdf.inverse import fit as inverse

    cfg = config.Config.model_validate({"name": "x", "train": {"steps": 100}})
    poor = {"start": {"family": "blend", "poor": {"excess": 0.1}}}
    good = {"start": {"family": "blend"}}
    assert inverse.poor_start_config(cfg, poor).train.steps == cfg.images.poor_start_steps
    assert inverse.poor_start_config(cfg, poor).train.lr == cfg.train.lr  # the rest kept
    assert inverse.poor_start_config(cfg, good) is cfg
    assert inverse.poor_start_config(cfg, None) is cfg
    off = cfg.model_copy(
        update={"images": cfg.images.model_copy(update={"poor_start_steps": None})}
    )
    assert inverse.poor_start_config(off, poor) is off
    longer = cfg.model_copy(update={"train": cfg.train.model_copy(update={"steps": 5000})})
    assert inverse.poor_start_config(longer, poor) is longer  # never lowered


@pytest.mark.parametrize(
    "family, given, trained",
    [
        # an anisotropic start: the grid over the half vector's disc (same shapes: a
        # config.yaml still saying theta would load the weights into the other grid)
        ("roughconductor_aniso", ("anisotropic", "theta"), ("anisotropic", "half_disc")),
        # an isotropic start: the isotropic encoding (images.isotropic_encoding)
        ("diffuse", ("anisotropic", "theta"), ("isotropic", "theta")),
        ("diffuse", ("isotropic", "theta"), ("isotropic", "theta")),
    ],
)
def test_the_start_s_grid_and_encoding_are_trained_exported_and_resumed(
    mi, example, tmp_path, capsys, family, given, trained
):
    """The start sets the network's grid and encoding (inverse.starts.model_for_start):
    the run's config.yaml, its checkpoint and its start's distillation say so;
    ``neural-brdf export`` of the run rebuilds the same f as its model.onnx;
    ``--resume`` trains on with them."""
    import neural_brdf
    from analytic import physics
    from neural_brdf.train.session import load_checkpoint

    def model_of(cfg):
        return (cfg.model.encoding, cfg.model.grid.coords)

    run_dir = tmp_path / "run"
    sets = [
        *FIT_OVERRIDES,
        "train.steps=4",
        f"model.encoding={given[0]}",
        f"images.start={family}",
        "images.start_steps=5",
        "images.start_refine_steps=0",
        "images.start_train_steps=20",
        "images.poor_start_steps=null",  # a diffuse start is poor here: keep train.steps
    ]
    code, err = run_cli(train_args(example / "fit.yaml", run_dir, sets), capsys)
    assert code == 0, err
    assert config.load(example / "fit.yaml").model.grid.coords == given[1]  # as given
    assert model_of(config.load(run_dir / "config.yaml")) == trained
    assert model_of(config.load(run_dir / "init" / "config.yaml")) == trained
    ckpt = load_checkpoint(run_dir / "ckpt.pt")["config"]["model"]
    assert (ckpt["encoding"], ckpt["grid"]["coords"]) == trained
    start = json.loads((run_dir / "metrics.json").read_text())["training"]["init"]["start"]
    assert (start["encoding"], start["grid_coords"]) == trained
    assert start["encoding_moved"] is (trained[0] != given[0])
    out = tmp_path / "again.onnx"
    code, err = run_cli(["export", str(run_dir), "-o", str(out)], capsys)
    assert code == 0, err
    wi = physics.random_directions(2000, 3).astype(np.float32)
    wo = physics.random_directions(2000, 4).astype(np.float32)
    a = neural_brdf.load(run_dir / "model.onnx")(wi, wo)
    np.testing.assert_allclose(neural_brdf.load(out)(wi, wo), a, rtol=1e-6, atol=1e-7)
    more = train_args(example / "fit.yaml", run_dir, [*sets, "train.steps=6"])
    code, err = run_cli([*more, "--resume"], capsys)
    assert code == 0, err
    assert json.loads((run_dir / "metrics.json").read_text())["training"]["steps"] == 6
    assert model_of(config.load(run_dir / "config.yaml")) == trained


def test_the_albedo_penalty_estimates_a_sharp_lobe_without_bias_and_without_false_excesses():
    """The penalty's albedo estimate, mean(f * weight) over albedo_directions' wo per
    incidence, is unbiased (its mean over 20 steps against the lobe's own albedo at the
    same wi, from its own sampler: analytic.physics.albedo, 2^14 points, independent of
    the mixture) and reads a sharp anisotropic lobe of albedo <= 0.85 below 1 at every
    incidence in every one of 50 steps.  Cosine-distributed wo alone, the estimator
    before session 85, read such a lobe up to several times its albedo at grazing
    incidence, and the penalty's pull on those false excesses made a good start drift."""
    from analytic import physics
    from analytic.microfacet import Microfacet
    from neural_brdf.inverse import fit as inverse

    lobe = Microfacet(alpha_x=0.05, alpha_y=0.2, fresnel="schlick", f0=[0.85, 0.85, 0.85])
    images = config.Images()
    k = len(images.albedo_incidences)
    ratios, highest = [], 0.0
    for step in range(50):
        wi, wo, weight = inverse.albedo_directions(step, images)
        f = lobe.f(wi.double(), wo.double())[:, 0]
        a = (f * weight.double()).reshape(k, -1).mean(1)
        highest = max(highest, float(a.max()))
        if step < 20:
            incident = wi.reshape(k, -1, 3)[:, 0].double()
            ref = physics.albedo(lobe, incident, 1 << 14)
            ratios.append((a / ref[:, 0]).numpy())
    assert highest < 1.0, highest
    np.testing.assert_allclose(np.mean(ratios, 0), 1.0, atol=0.02)


def test_the_albedo_penalty_follows_the_images_section(mi):
    """images.albedo_incidences, albedo_side and albedo_weight set the penalty's
    directions and weight: K x side^2 pairs at those incidences, the penalty linear in
    the weight (0: off), and the penalty max(0, A - 1)^2 of a network whose albedo
    exceeds 1."""
    import drjit as dr

    from neural_brdf.inverse import bsdf as ib
    from neural_brdf.inverse import fit as inverse

    images = config.Images(albedo_incidences=[10.0, 60.0, 85.0], albedo_side=5)
    wi, wo, cos_over_pdf = inverse.albedo_directions(3, images)
    assert wi.shape == wo.shape == (3 * 25, 3) and cos_over_pdf.shape == (3 * 25,)
    cos = wi[:, 2].reshape(3, 25).numpy()
    np.testing.assert_allclose(cos[:, 0], np.cos(np.deg2rad([10.0, 60.0, 85.0])), rtol=1e-6)
    assert np.all(cos == cos[:, :1])  # one incidence per block
    bsdf = mi.load_dict({"type": ib.PLUGIN, "model": ib.COMPACT, "init_value": 0.3})
    raw = bsdf.torch_model()
    w = {k: ib._to_dr(v) for k, v in raw.state_dict().items()}
    args = (w, *(mi.TensorXf(x.numpy()) for x in (wi, wo, cos_over_pdf)))
    values = {}
    for weight in (0.0, 1.0, 2.5):
        pen, amax = inverse.albedo_penalty_fn(
            raw, images.model_copy(update={"albedo_weight": weight})
        )(*args)
        values[weight] = float(pen.array[0])
        dr.sync_thread()
    assert float(amax.array[0]) > 1.0  # init 0.3: an albedo near 12.6 x 0.3 at grazing
    assert values[0.0] == 0.0 and values[1.0] > 0.0
    np.testing.assert_allclose(values[2.5], 2.5 * values[1.0], rtol=1e-6)


# ------------------------------------------------------------------ a user's walkthrough
# A tiny fit: 16² views, a few steps, a named start fitted and distilled briefly, no
# poor-start verdict (which would distil and train for hundreds of steps).
TINY_FIT = [
    *FIT_OVERRIDES,
    "train.steps=4",
    "images.start=diffuse",
    "images.start_steps=3",
    "images.start_refine_steps=0",
    "images.start_train_steps=20",
    "images.poor_start_loss=null",
    "images.validation_every=2",
    "images.patience=null",
]


@pytest.mark.parametrize("start", ["diffuse", "ggx"])
def test_a_view_held_out_whole_is_scored_not_refused_by_the_starts_distillation(
    mi, example, tmp_path, capsys, start
):
    # images.validation_views broke every fit: the start's distillation (sample-based
    # training, in init/) took the images section with it, and its config, which has
    # no target.images, refused it ("only for target.images"), exit 2, after the start
    run_dir = tmp_path / "run"
    held = ["images.validation_views=[2]", "images.validation_pixels=0", f"images.start={start}"]
    code, err = run_cli(train_args(example / "fit.yaml", run_dir, TINY_FIT + held), capsys)
    assert code == 0, err
    training = json.loads((run_dir / "metrics.json").read_text())["training"]
    val = training["validation"]
    assert val["views"] == ["view3.exr"] and val["heldout_pixels"] == RES * RES, val
    assert math.isfinite(val["start_loss"]) and math.isfinite(val["best_loss"]), val
    assert "1 held out (view3.exr)" in training["target"], training["target"]
    # the distillation's own config: the images section at its defaults
    init = config.load(run_dir / "init" / "config.yaml")
    assert init.target.images is None and init.images.validation_views == []


@pytest.mark.parametrize(
    "camera, says",
    [
        ('origin="0, 0, 5" target="0, 0, 10"', "the camera looks away from the object"),
        ('origin="0, 0, 0.2" target="0, 0, 0"', "only the back of the surface"),
    ],
    ids=["turned away", "inside the sphere"],
)
@pytest.mark.parametrize("held_out", [False, True])
def test_a_view_that_sees_none_of_the_object_exits_2_before_anything_is_written(
    mi, copy_of, capsys, camera, says, held_out
):
    # it was fitted (exit 0), metrics.json saying pixels_lit: 0 for it, and its target fed
    # the noise estimate; a view held out whole would be scored on nothing
    text = (copy_of / "view2.xml").read_text()
    (copy_of / "blind.xml").write_text(
        re.sub(r'origin="[^"]*" target="[^"]*"', camera, text, count=1)
    )
    extra = "train: {steps: 1, progress: false}\nimages: {start: constant"
    extra += ", validation_views: [1]}\n" if held_out else "}\n"
    views = [("view1.xml", "view1.exr"), ("blind.xml", "view2.exr"), ("view3.xml", "view3.exr")]
    path = _config(copy_of, views, extra)
    needles = ("target.images[1].scene", "blind.xml", "sees no pixel of the fitted object", says)
    _expect_exit_2(path, copy_of / "run", capsys, *needles)
    assert not (copy_of / "run" / "config.yaml").exists()


def test_a_fit_nested_in_another_bsdf_is_named_when_no_pixel_is_found():
    # the object's pixels are those whose ray meets a shape whose own BSDF is the fit: a
    # <ref id="fit"/> inside a twosided is not found, and the message says why
    from neural_brdf.errors import InputError
    from neural_brdf.inverse import views as inverse

    root = ET.fromstring(
        '<scene version="3.0.0"><bsdf type="diffuse" id="fit"/><shape type="sphere">'
        '<bsdf type="twosided"><ref id="fit"/></bsdf></shape></scene>'
    )
    view = inverse.View(Path("s.xml"), Path("s.exr"), ET.ElementTree(root), None, "path")
    none = np.zeros((4, 4), bool)
    with pytest.raises(InputError, match=r'nested in a <bsdf type="twosided">') as e:
        inverse.check_sees_object(view, "target.images[0].scene", none, none)
    assert str(e.value).startswith("target.images[0].scene: s.xml: the view sees no pixel")
    inverse.check_sees_object(view, "k", none, ~none)  # a front-facing pixel: seen


def test_ctrl_c_during_the_distillation_says_the_start_is_chosen_again(
    mi, example, tmp_path, capsys, monkeypatch
):
    """Ctrl-C while the start was distilled said 'checkpoint saved to RUN/init/ckpt.pt;
    continue with --resume', but the resume chooses the start again (init/ is not
    resumed): the line says what --resume does."""
    import signal

    from neural_brdf.errors import Interrupted
    from neural_brdf.train import loop

    def stopped(*args, **kwargs):
        e = Interrupted("interrupted at step 7 (SIGTERM); checkpoint saved to x; continue")
        e.signum = signal.SIGTERM
        raise e

    monkeypatch.setattr(loop, "train", stopped)
    auto = ["images.start=auto", "images.start_families=[diffuse]", "images.validation_pixels=0.2"]
    code, err = run_cli(train_args(example / "fit.yaml", tmp_path / "run", TINY_FIT + auto), capsys)
    assert code == 143, err
    assert "during the start's distillation (SIGTERM)" in err, err
    assert "--resume chooses the start again" in err and "checkpoint saved" not in err, err


def test_resume_after_ctrl_c_during_the_starts_choice_fits_again_from_it(
    mi, example, tmp_path, capsys, monkeypatch
):
    # Ctrl-C while auto fitted its families (no init/ yet: the folder held config.yaml
    # and coverage.png alone), then --resume: "no checkpoint", exit 2
    import signal
    import time

    from neural_brdf.inverse import starts

    real = starts.fit_candidate

    def interrupted(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # a terminal's Ctrl-C, in this process
        time.sleep(5)  # (the handler raises KeyboardInterrupt at once)
        raise AssertionError("SIGINT did not interrupt")

    run_dir = tmp_path / "run"
    auto = ["images.start=auto", "images.start_families=[diffuse]", "images.validation_pixels=0.2"]
    args = train_args(example / "fit.yaml", run_dir, TINY_FIT + auto)
    monkeypatch.setattr(starts, "fit_candidate", interrupted)
    # as in a terminal: a job started in the background (CI's) inherits SIGINT ignored
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code, err = run_cli(args, capsys)
    finally:
        signal.signal(signal.SIGINT, old)
    assert code == 130 and "interrupted" in err, err
    left = sorted(p.name for p in run_dir.iterdir() if p.name != ".lock")
    assert left == [".neural-brdf-run", "config.yaml", "coverage.png"], left
    monkeypatch.setattr(starts, "fit_candidate", real)
    code, err = run_cli(args + ["--resume"], capsys)
    assert code == 0, err
    said = [line for line in err.splitlines() if "does not exist yet" in line]
    assert len(said) == 1 and "the fit starts again from the start's choice" in said[0], err
    assert (run_dir / "model.onnx").is_file() and (run_dir / "ckpt.pt").is_file()
    # a finished run's model without its checkpoint is not fitted again
    (run_dir / "ckpt.pt").unlink()
    code, err = run_cli(args + ["--resume", "--set", "train.steps=6"], capsys)
    assert code == 2 and "no checkpoint" in err, err


# a Python BSDF whose constructor Ctrl-C interrupts: Mitsuba turns what Python code it
# calls raises into a RuntimeError holding the traceback's text ("KeyboardInterrupt: ")
INTERRUPTING = "neural_brdf_test_interrupting"


@pytest.fixture
def interrupting_plugin(mi):
    class Interrupting(mi.BSDF):
        def __init__(self, props):
            super().__init__(props)
            raise KeyboardInterrupt

    mi.register_bsdf(INTERRUPTING, lambda props: Interrupting(props))
    return (
        f'<scene version="3.0.0"><shape type="sphere"><bsdf type="{INTERRUPTING}"/></shape></scene>'
    )


def test_ctrl_c_inside_a_scenes_load_is_the_interrupt_not_bad_input(
    mi, interrupting_plugin, tmp_path
):
    from neural_brdf.errors import InputError, Interrupted
    from neural_brdf.inverse import views as inverse

    with pytest.raises(KeyboardInterrupt):
        inverse.load_scene(tmp_path / "s.xml", interrupting_plugin)
    terminated = "Traceback ...\nneural_brdf.tooling.cli._Terminated: terminated (SIGTERM)"
    for text, kind in [
        ("[parser.cpp:1] failed to instantiate\nKeyboardInterrupt: ", KeyboardInterrupt),
        (terminated, KeyboardInterrupt),
        ("failed\nneural_brdf.errors.Interrupted: stopped", Interrupted),
        ("failed\nSystemExit: 3", SystemExit),
        ("[xml.cpp:12] Error while loading\nRuntimeError: no such plugin", None),
    ]:
        stop = inverse.interruption_in(text.splitlines()[-1])
        assert (type(stop) if stop is not None else None) is kind, text
    assert getattr(inverse.interruption_in(terminated.splitlines()[-1]), "signum", 0) == 15
    # a bad scene is still bad input
    with pytest.raises(InputError, match="Mitsuba cannot load it"):
        inverse.load_scene(
            tmp_path / "s.xml", '<scene version="3.0.0"><shape type="nothing"/></scene>'
        )


@pytest.mark.parametrize("raised", ["inside Mitsuba", "KeyboardInterrupt", "Interrupted"])
def test_ctrl_c_while_the_scenes_load_exits_130_not_2(
    mi, interrupting_plugin, copy_of, capsys, monkeypatch, raised
):
    # "error: v1.xml: Mitsuba cannot load it: KeyboardInterrupt:", exit 2, before
    from neural_brdf.errors import Interrupted

    real = mi.load_string

    def loading(text, *args, **kwargs):
        if raised == "KeyboardInterrupt":
            raise KeyboardInterrupt
        if raised == "Interrupted":
            raise Interrupted("interrupted (Ctrl-C)")
        return real(interrupting_plugin)

    monkeypatch.setattr(mi, "load_string", loading)
    path = _config(copy_of, [("view1.xml", "view1.exr")], "train: {progress: false}\n")
    code, err = run_cli(["train", str(path), "--out", str(copy_of / "run")], capsys)
    assert code == 130, err
    assert "interrupted (Ctrl-C)" in err and "cannot load" not in err, err


def test_resuming_a_run_stopped_early_says_to_raise_the_patience_not_the_steps(
    mi, example, tmp_path, capsys, monkeypatch
):
    # "already finished at step 4; nothing to do (raise train.steps to train on ...)",
    # which does nothing for a stage stopped by images.patience
    from neural_brdf.inverse import fit as fitmod

    scores = iter([1.0, 0.5, 0.9])  # the start, step 2 (the best), step 4: stop (patience 1)
    monkeypatch.setattr(fitmod, "heldout_loss", lambda views, *, spp, seed: next(scores))
    run_dir = tmp_path / "run"
    stop = TINY_FIT + ["train.steps=8", "images.patience=1", "images.validation_pixels=0.2"]
    code, err = run_cli(train_args(example / "fit.yaml", run_dir, stop), capsys)
    assert code == 0 and "the image stage stops at step 4" in err, err
    more = stop + ["train.steps=20"]
    code = cli.main(train_args(example / "fit.yaml", run_dir, more) + ["--resume"])
    out, err = capsys.readouterr()
    assert code == 0 and "already finished at step 4" in out, out + err
    assert "raise train.steps" not in out, out
    assert "its image stage stopped early at step 4 (images.patience 1)" in out, out
    assert "raise images.patience, or set it to null, to train on" in out, out


def test_a_clearcoat_start_is_named_as_such_in_the_determined_warning(mi):
    # "... of the principled start" when auto chose clearcoat (a principled with a coat)
    from types import SimpleNamespace

    from neural_brdf.inverse import determined, families
    from neural_brdf.inverse import fit as fitmod

    init = {"start": {"family": "clearcoat", "params": families.family("clearcoat").initial()}}
    element = fitmod._start_element(init)
    assert element is not None and element.get("type") == "principled"
    assert fitmod._start_family(init) == "clearcoat"
    assert fitmod._start_family({"roughconductor": {"alpha": 0.2}}) is None  # the ggx start
    det = SimpleNamespace(energy_figure=0.1, bins=8, tol=0.05, figure=0.2, reference="principled")
    line = determined.warning(det, label=fitmod._start_family(init))  # type: ignore[arg-type]
    assert line is not None and "of the clearcoat start" in line, line
    assert "of the principled start" in (determined.warning(det) or "")  # type: ignore[arg-type]


@pytest.mark.parametrize("capture, index", [("environment", 3), ("flash_pair", 4)])
def test_the_examples_held_out_view_is_in_fit_yaml_with_how_to_score_it(
    mi, tmp_path, capture, index
):
    # --heldout wrote view4, but fit.yaml neither listed it nor said how to use it
    import yaml

    from neural_brdf.inverse import scene as inverse_example

    folder = tmp_path / "ex"
    inverse_example.write(folder, resolution=8, spp=2, steps=3, capture=capture, heldout=True)
    text = (folder / "fit.yaml").read_text()
    entry = "    # - {scene: view4.xml, image: view4.exr}"
    assert entry in text and f"images: {{validation_views: [{index}]}}" in text, text
    # as it says: the entry uncommented, the section added; view4 is then held out whole
    done = text.replace(entry, entry.replace("# ", "", 1))
    done += f"images: {{validation_views: [{index}]}}\n"
    (folder / "scored.yaml").write_text(done)
    cfg = config.load(folder / "scored.yaml")
    assert cfg.target.images[index].scene.endswith("view4.xml")
    assert cfg.images.validation_views == [index]
    plain = yaml.safe_load(text)["target"]["images"]  # as written: view4 not fitted
    assert all("view4" not in e["scene"] for e in plain)
