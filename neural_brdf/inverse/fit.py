"""Neural BRDFs from images: inverse rendering with the physics kept (docs/inverse.md).

    python -m neural_brdf.inverse.scene runs/images          # an example: 3 views
    neural-brdf train runs/images/fit.yaml --out runs/images-fit

A config whose target is ``images`` (a list of ``{scene: view.xml, image: view.exr}``,
paths relative to the config file) is trained by differentiable rendering instead of
from BRDF samples (:func:`fit`):

1. each scene (a Mitsuba 3 XML file) is loaded with its ``<bsdf id="fit">`` replaced by
   the trainable ``neural_brdf_ad`` plugin (:mod:`neural_brdf.inverse.bsdf`): the same
   :class:`neural_brdf.train.model.RawBRDF` that ``neural-brdf train`` fits, evaluated by torch
   inside Mitsuba's AD graph (``dr.wrap``), its weights Dr.Jit tensors;
2. the start (``images.start: ggx``, the default): Mitsuba's ``roughconductor``
   (GGX; alpha, RGB eta and k) is fitted to the images (:func:`fit_roughconductor`), and
   the network is trained on BRDF samples of the matching analytic GGX
   (:func:`ggx_initial_state`, the sample-based training of :mod:`neural_brdf.train.loop`);
   the image fit then runs at ``images.start_lr_scale`` times the learning rate.  With
   ``images.start: constant`` the network starts as a dim constant;
3. every step renders every fitted view with the scene's own integrator (``prb`` runs as
   ``prb_basic``: see :data:`INTEGRATORS`), ``images.primal_spp`` samples per pixel in
   the primal pass and ``images.spp`` in the gradient pass (``mi.render`` draws them with
   decorrelated seeds), compares each render with its target by the relative MSE of HDR
   images, adds a penalty on a directional albedo above 1, back-propagates
   (``dr.backward``) and takes an ``mi.ad.Adam`` step on the learning-rate schedule of
   ``train`` (warm-up, cosine), the grids at their ``lr_scale``; the sampling lobe is
   refitted to the network every ``images.lobe_every`` steps;
   with a validation split (``images.validation_pixels``, ``images.validation_views``:
   :func:`split_views`), the held-out pixels and views take no part in the fit, the
   start's included; their loss (:func:`heldout_loss`) is scored before the first step
   and every ``images.validation_every`` steps, and the fit returns the weights of the
   best score, the start's when no step beats it;
4. the fitted network goes through the usual export (:func:`neural_brdf.export.
   normalized_model`: the exact albedo normalisation is baked into the graph when the
   raw albedo exceeds 1 anywhere) to ``model.onnx``, which is validated (reciprocity,
   minimum, white furnace: :func:`neural_brdf.validate.report` without a reference);
   ``metrics.json`` records it with the fit's figures.

Checkpoints (``ckpt.pt``: weights, Adam's moments, step, sampling lobe), ``log.csv``,
``--resume``, Ctrl-C and divergence behave as in :mod:`neural_brdf.train.loop`: the fit
runs in the same :class:`neural_brdf.train.session.Session`.  Before the start, the
part of the (wi, wo) domain the fitted views observe is computed
(:func:`neural_brdf.inverse.coverage.assess`): ``coverage.png`` in the run folder, the
figures in metrics.json's ``training.coverage``, and a warning on stderr when it is
thin.  Bad input raises :class:`neural_brdf.errors.InputError` (exit code 2) with one
line naming the file, before anything is written: a missing or unreadable image, an
image that is not RGB, an image whose size is not the film's, a scene without
``<bsdf id="fit">`` or with no ``<shape>`` that uses it (``<ref id="fit"/>``, or the
BSDF nested in the shape), a view that sees no pixel of the fitted object
(:func:`neural_brdf.inverse.views.check_sees_object`), an integrator that cannot be
differentiated here, samples per pixel (``images.*spp``) beyond the memory budget.  The
Mitsuba variant (``target.variant``, else ``train.device``: ``llvm_ad_rgb`` on the CPU,
``cuda_ad_rgb`` on CUDA) must be a JIT AD RGB one (config.py refuses others).

Loss.  With x the render, y the target and y_bar the target's channel mean at a pixel,

    L_img = mean over pixels and channels of (x - y)^2 / (y_bar^2 + REL_EPS)

the relative MSE that Lehtinen et al. 2018 ("Noise2Noise: Learning Image Restoration
without Clean Data", ICML) use for HDR Monte Carlo renders, with the denominator from the
clean target rather than from the estimate, so that a dark rim counts as much as a
highlight.  For a flash/no-flash pair (an entry's ``subtract``: y is the flash
photograph minus the other) y_bar is the flash photograph's, whose light sets the
difference's noise (:meth:`View.rel_weight`).  Energy: the fit adds

    L_albedo = images.albedo_weight * sum over K incidences and RGB of max(0, A(wi) - 1)^2,

the K incidences ``images.albedo_incidences``, A(wi) = (1 / N) sum_j f(wi, wo_j) cos / p,
wo_j from the validator's mixture of proposals, cosine, uniform and GGX half vectors
around the normal and around wi, by the balance heuristic (Veach 1997;
:func:`neural_brdf.physics.quadrature.mis_directions`, N = ``images.albedo_side``^2,
fresh every step), so the fit is steered away from a network the normalisation would
have to scale down; the exported bound itself comes from the normalisation, not the
penalty.  Cosine-distributed wo alone, as before session 85, rarely hit a sharp lobe: on
the development set's brushed copper (albedo 0.80 to 0.93) the estimate exceeded 1 at
some incidence in 81 % of steps (up to 7.9; 4 % and 1.03 with the mixture), and the
penalty's pull on those false excesses, not the images, made the network drift from a
good start (docs/inverse.md).
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from neural_brdf import config as cfgmod
from neural_brdf import runfolder
from neural_brdf.errors import InputError
from neural_brdf.fileformat import LOBE_KEY
from neural_brdf.fileformat import lobe as lobe_format
from neural_brdf.inverse.views import (  # noqa: F401  (the views' layer, handed on)
    INTEGRATORS,
    NOISE_KEEP,
    NOISE_SCALE,
    REL_EPS,
    TORCH_THREADS,
    View,
    bsdf_element,
    check_films,
    check_render_sizes,
    distillation_config,
    fit_bsdf,
    fit_element,
    fit_is_used,
    fitted_views,
    is_poor,
    jit_notes_off,
    load_scene,
    mitsuba_bsdf,
    mitsuba_f_cos,
    prepare_views,
    read_image,
    read_scene,
    read_views,
    rel_weight,
    relative_mse,
    render_view,
    scene_text,
    sphere_mask,
    split_views,
    start_training,
    target_noise,
    tiles,
    use_variant,
    variant_key,
    variant_name,
    xml_float,
)
from neural_brdf.train.model import RawBRDF, grid_lr_scales
from neural_brdf.train.model import lr_scale as scale_of
from neural_brdf.train.session import LOG_COLUMNS, MUST_MATCH, Session

# The network's start: a constant f = INIT_VALUE / ((cos_i + cos_o) / 2) (model.py), whose
# albedo, 12.6 INIT_VALUE at grazing incidence, stays below 1 everywhere.
INIT_VALUE = 0.05
KIND = "images"  # the checkpoint's kind (neural_brdf.train.session)
# The settings (config.Images) are in the config: docs/config.md.  After a "ggx" start
# the image fit runs at images.start_lr_scale x train.lr, its grids at
# images.start_grid_lr_scale x that (not model.grid.lr_scale): a noisy gradient makes
# the network drift from a good start, the more so the higher the rate (benchmark, 300
# steps from a start 0.5 % off: 7.3 % at 0.2 with the grids at 10, 5.3 % at 0.2 and 1,
# 5.0 % at 0.05 and 10, 3.8 % at 0.05 and 1; measured with the albedo penalty's
# cosine-sampled estimate, whose false excesses were much of that drift: module doc).
# A resumed images fit keeps its start and its validation split (with the seed, in MUST_MATCH).
RESUME_MUST_MATCH = (
    *MUST_MATCH,
    "images.start",
    "images.validation_pixels",
    "images.validation_block",
    "images.validation_views",
)
HELDOUT_COLUMN = "heldout_loss"  # log.csv's column of the held-out loss (with a split)
# A start not called poor (images.poor_start_loss, an excess of relative MSE) whose
# held-out loss is this many times the targets' noise or more gets a warning
# (far_above_noise): two orders of magnitude, where no start of the development set
# that fits its views stands (0.2 to 2.3 times; docs/inverse-design.md, "A poor start")
FAR_ABOVE_NOISE = 100.0
VALIDATION_STEP = 999_983  # the held-out renders' seeds: _rng_seed(train.seed, this, view)


# ---------------------------------------------- the start's verdict, the stage's losses
def poor_start(
    init_info: dict, limit: float | None, noise: float | None = None, steps: int | None = None
) -> bool:
    """Mark the chosen start poor (``init_info["start"]["poor"]``, kept in the
    checkpoint) when its held-out loss exceeds the targets' own noise (``noise``,
    :func:`target_noise`; 0 when None) by more than ``limit``
    (``images.poor_start_loss``): no family holds the material, and the image stage,
    which :func:`fit_neural` then runs at ``train.lr`` with the grids at
    ``images.poor_start_grid_lr_scale``, must do the work.  The noise estimate is recorded
    (``start["target_noise"]``) either way.  ``steps``: what the image stage then runs
    (:func:`poor_start_config`), recorded and said.  Says so on stderr.  True when
    marked."""
    start = init_info.get("start") or {}
    if noise is not None:
        start["target_noise"] = float(noise)
    loss = start.get("val_loss")
    if limit is None or loss is None:
        return False
    excess = float(loss) - (noise or 0.0)
    if not is_poor(loss, limit, noise):
        far_above_noise(start, float(loss), noise, excess, limit)
        return False
    start["poor"] = {
        "val_loss": float(loss),
        "target_noise": float(noise or 0.0),
        "excess": excess,
        "limit": float(limit),
        **({"steps": int(steps)} if steps is not None else {}),
    }
    print(
        f"start {start.get('family')}: held-out loss {loss:.4g}, {excess:.4g} above the "
        f"targets' noise ({noise or 0.0:.2g}) > images.poor_start_loss {limit:g}: no "
        "family fits the views; the image stage runs at train.lr"
        + (f" for up to {steps} steps" if steps is not None else ""),
        file=sys.stderr,
    )
    return True


def far_above_noise(
    start: dict, loss: float, noise: float | None, excess: float, limit: float
) -> None:
    """Warn (one line on stderr, ``start["far_above_noise"]`` in metrics.json) when a
    start that ``images.poor_start_loss`` does not call poor still has a held-out loss
    :data:`FAR_ABOVE_NOISE` times the targets' noise or more: the limit is an excess of
    relative MSE, and under point lights, whose renders are nearly noise-free and mostly
    dark, a start that fits its views badly can stay under it (docs/inverse-design.md, "A poor
    start").  Changes nothing."""
    if not noise or noise <= 0.0 or not loss >= FAR_ABOVE_NOISE * noise:  # NaN: no
        return
    ratio = loss / noise
    start["far_above_noise"] = {"ratio": ratio, "excess": excess, "limit": float(limit)}
    print(
        f"warning: start {start.get('family')}: held-out loss {loss:.4g}, {ratio:.0f} times "
        f"the targets' noise ({noise:.2g}), is not poor by images.poor_start_loss {limit:g} "
        f"(an excess of {excess:.2g} over the noise); if the fitted views stay far from "
        "their images (training.validation in metrics.json), set images.poor_start_loss "
        f"below {excess:.2g} so that the image stage learns the material at train.lr",
        file=sys.stderr,
    )


def poor_start_steps(cfg: cfgmod.Config) -> int:
    """The image stage's steps after a poor start: ``train.steps`` raised to
    ``images.poor_start_steps`` (never lowered; null: ``train.steps``)."""
    return max(cfg.train.steps, cfg.images.poor_start_steps or 0)


def poor_start_config(cfg: cfgmod.Config, init_info: dict | None) -> cfgmod.Config:
    """``cfg`` with ``train.steps`` raised to :func:`poor_start_steps` when the start of
    ``init_info`` was marked poor (:func:`poor_start`): the image stage then learns the
    material rather than refining a start, and the rate's cosine decay spans the longer
    run.  ``cfg`` itself otherwise (a good start, no limit, or ``train.steps`` already
    at least that)."""
    steps = poor_start_steps(cfg)
    if steps == cfg.train.steps or not (((init_info or {}).get("start") or {}).get("poor")):
        return cfg
    return cfg.model_copy(update={"train": cfg.train.model_copy(update={"steps": steps})})


def check_split_sees_object(views: list[View], images: cfgmod.Images) -> None:
    """InputError, before anything is written, when the object keeps no pixel once its
    outline is left out (``view.object``: the filter's reach), when the fitted views keep
    none of it outside the held-out tiles (the start and the network would fit no pixel),
    or when a validation split is asked for and its held-out pixels hold none of the
    object in any view: the held-out loss would have nothing to score (an assertion
    failed mid-run, exit 1, for a one-view split of 2 % of the tiles at two seeds of
    four, and for a small object).  The masks are the start's own
    (:func:`neural_brdf.inverse.starts.run_masks`)."""
    from neural_brdf.inverse import starts

    train, held = starts.run_masks(views)
    counts = ", ".join(
        f"{v.image_path.name} {int(t.sum() + h.sum())}" for v, t, h in zip(views, train, held)
    )
    if not any(t.any() or h.any() for t, h in zip(train, held)):
        raise InputError(
            f"target.images: {views[0].scene_path}: the fitted object covers no pixel "
            "inside its outline (as far in as the film's reconstruction filter reaches) "
            "in any view: frame it larger or render the views at a higher resolution"
        )
    # the key that held the object's pixels out: whole views, or tiles of the others
    key = "images.validation_pixels" if images.validation_pixels > 0 else "images.validation_views"
    if not any(t.any() for t in train):
        raise InputError(
            f"{key}: the fitted views keep no pixel of the object outside the held-out "
            f"tiles and views (its pixels: {counts}): fit a view that sees it"
        )
    if not images.split or any(h.any() for h in held):
        return
    said = (
        f"{images.validation_pixels:g} of the tiles are held out"
        if images.validation_pixels > 0
        else f"views {images.validation_views} are held out"
    )
    raise InputError(
        f"{key}: {said}, and they hold no pixel of the fitted object in any view (its "
        f"pixels: {counts}): raise images.validation_pixels, or hold out a whole view "
        "that sees the object (images.validation_views)"
    )


def heldout_loss(views: list[View], *, spp: int, seed: int) -> float | None:
    """The relative MSE (module doc) over the validation split, estimated without the
    render's own noise: the mean over the held-out pixels (:meth:`View.validation_mask`,
    within ``view.object`` when it is known) of every view and over RGB of
    (x1 - y)(x2 - y) w, x1 and x2 two renders of the view as its scene now stands, without
    gradients, of ``spp`` // 2 samples per pixel each (at least 1) and independent seeds
    set by ``seed`` and the view alone.  Its expectation is the loss of the noise-free
    render, so two weights (or a network and an analytic start:
    :func:`neural_brdf.inverse.starts.noise_free_loss`) compare by how well they fit, not
    by how noisy they render; scores of different weights share their samples (through
    the same sampling lobe: :func:`fit_neural` scores its best weights again after
    each refit of the lobe).  None
    when no pixel is held out."""
    import drjit as dr
    import mitsuba as mi

    total, count = 0.0, 0
    each = max(1, spp // 2)
    for i, v in enumerate(views):
        mask = v.validation_mask()
        if mask is None:
            continue
        if v.object is not None:
            mask = mask & v.object
        if not mask.any():
            continue
        renders = []
        for k in (0, 1):
            fixed = _rng_seed(seed, VALIDATION_STEP + k, i)
            with dr.suspend_grad():
                img = mi.render(v.scene, spp=each, seed=fixed)  # type: ignore[arg-type]  # stub: mi.UInt32
            renders.append(np.asarray(img, dtype=np.float64)[..., :3] - v.target)
        term = renders[0] * renders[1] * v.rel_weight()
        total += float(np.sum(term[mask]))
        count += 3 * int(mask.sum())
    return total / count if count else None


def albedo_directions(
    seed: int, images: cfgmod.Images | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """wi (K*N, 3) at ``images.albedo_incidences`` (degrees; a random azimuth each), wo
    (K*N, 3) and their weights cos(theta_o) / p(wo) (K*N,): N = ``images.albedo_side``^2
    per incidence (at least one per proposal, so 7 for a side of 1 or 2) from
    :func:`neural_brdf.physics.quadrature.mis_directions` (the cosine, the uniform
    hemisphere and GGX half vectors of several widths around the normal and around wi,
    by the balance heuristic), fresh for every ``seed``, so that
    mean(f * weight) per incidence estimates its albedo.  ``images``: the config's
    section (None: its defaults)."""
    from neural_brdf.physics import quadrature

    images = cfgmod.Images() if images is None else images
    g = torch.Generator().manual_seed(seed)
    k, n = len(images.albedo_incidences), images.albedo_side**2
    theta = torch.tensor([float(d) for d in images.albedo_incidences]).deg2rad()
    phi = 2 * math.pi * torch.rand(k, generator=g)
    wi = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()], -1)
    wo, weight = quadrature.mis_directions(wi.double(), n, seed)
    return (
        wi.repeat_interleave(wo.shape[1], 0).float(),
        wo.reshape(-1, 3).float(),
        weight.reshape(-1).float(),
    )


def albedo_penalty_fn(raw: RawBRDF, images: cfgmod.Images | None = None):
    """A dr.wrap'ed torch function: (weights, wi, wo, weight) -> ``images.albedo_weight``
    x the sum of max(0, A - 1)^2 (module doc) over :func:`albedo_directions`'
    incidences, and the largest A estimated.  ``images``: the config's section (None:
    its defaults)."""
    import drjit as dr

    images = cfgmod.Images() if images is None else images
    k, weight = len(images.albedo_incidences), images.albedo_weight

    @dr.wrap(source="drjit", target="torch")
    def penalty(weights, wi, wo, w):
        f = torch.func.functional_call(raw, weights, (wi, wo))  # (K*N, 3)
        # weight 0: below the horizon, where f is not looked at (as in quadrature.albedo)
        fw = torch.where(w[:, None] > 0, f * w[:, None], 0.0)
        a = fw.reshape(k, -1, 3).mean(1)  # (K, 3)
        return weight * torch.relu(a - 1.0).square().sum().reshape(1), a.max().reshape(1)

    return penalty


# ------------------------------------------------------------------ checkpoints
def _adam_state(opt) -> dict:
    """Adam's step counts and moments per weight, as CPU tensors (for ckpt.pt)."""
    out = {}
    for k, (_value, _promoted, _lr, extra) in opt.state.items():
        t, m, v = extra[0], extra[1], extra[2]
        out[k] = {
            "t": int(np.asarray(t.numpy()).reshape(-1)[0]),
            "m": torch.from_numpy(np.array(m.numpy(), dtype=np.float32, copy=True)),
            "v": torch.from_numpy(np.array(v.numpy(), dtype=np.float32, copy=True)),
        }
    return out


def _load_adam_state(opt, saved: dict) -> None:
    """Restore :func:`_adam_state` into ``opt`` (weights it does not hold are skipped)."""
    import drjit as dr

    for k, s in saved.items():
        if k not in opt.state:
            continue
        value, promoted, lr, extra = opt.state[k]
        flat = type(extra[1])
        t = dr.uint32_array_t(flat)(int(s["t"]))
        opt.state[k] = (
            value,
            promoted,
            lr,
            (t, flat(s["m"].numpy()), flat(s["v"].numpy()), extra[3]),
        )


# ------------------------------------------------------------------ the fit
def _rng_seed(seed: int, step: int, view: int) -> int:
    return (seed * 1_000_003 + step * 101 + view) % (2**31 - 1)


def fit_neural(
    cfg: cfgmod.Config,
    views: list[View],
    run_dir: Path,
    *,
    resume: bool = False,
    init_state: dict | None = None,
    init_value: float = INIT_VALUE,
    lr_factor: float = 1.0,
    grid_lr_scale: float | None = None,
    init_info: dict | None = None,
    session: Session | None = None,
) -> tuple[RawBRDF, dict[str, Any]]:
    """Fit the RawBRDF of ``cfg.model`` to ``views`` (those not held out: the
    validation split marked by :func:`split_views`) with ``cfg.images``'s settings;
    writes ckpt.pt and log.csv.  With a split, returns the weights of the best held-out
    loss (the start's when no step beats it, or when it scores no worse through the last
    sampling lobe: ``check_start``).  ``session``: the run's session when
    :func:`fit` has begun it (else one is opened here,
    :meth:`neural_brdf.train.session.Session.one`)."""
    import drjit as dr
    import mitsuba as mi

    from neural_brdf.inverse import bsdf as ib
    from neural_brdf.train import loop

    t, images = cfg.train, cfg.images
    fitted = fitted_views(views)
    split = any(v.validation_mask() is not None for v in views)
    # torch's ops here are small elementwise ones, called from inside the render: a
    # multiply of 92k floats took 0.025 ms on one thread and 0.14 ms on two
    # (OMP_WAIT_POLICY=PASSIVE, as the CLI sets; 7.8 ms without it) on the busy 2-core
    # reference machine, so the fit runs torch on one thread (Dr.Jit has its own pool)
    torch.set_num_threads(TORCH_THREADS)
    columns = (*LOG_COLUMNS, HELDOUT_COLUMN) if split else LOG_COLUMNS
    sess = session or Session.one(cfg, run_dir, resume=resume, kind=KIND, columns=columns)
    ckpt = sess.resumed(must_match=RESUME_MUST_MATCH)
    sess.begin()
    if ckpt is not None:
        init_info = ckpt.get("init")
    if ((init_info or {}).get("start") or {}).get("poor"):  # a poor start (poor_start)
        lr_factor, grid_lr_scale = 1.0, images.poor_start_grid_lr_scale

    model_text = json.dumps(cfg.model.model_dump())
    bsdf = bsdf_element(
        ib.PLUGIN,
        model=model_text,
        seed=int(t.seed),
        init_value=float(init_value),
        evaluator=cfg.images.evaluator,
    )
    prepare_views(views, bsdf)
    lead = views[0].bsdf
    if init_state is not None:
        lead.load_state_dict(init_state)
    if ckpt is not None:
        lead.load_state_dict(ckpt["model"])
    raw_template = lead.raw
    names = list(lead.weights)
    opt = mi.ad.Adam(lr=t.lr)
    for n in names:
        opt[n] = mi.TensorXf(lead.weights[n])
    scales = grid_lr_scales(cfg.model, grid_lr_scale)
    lr_scale = {n: scale_of(n, scales) for n in names}
    penalty = albedo_penalty_fn(raw_template, cfg.images)

    render_seconds = 0.0
    # where the rest of the stage's time goes (this process's part of a resumed run)
    parts = {"validation": 0.0, "albedo": 0.0, "lobe": 0.0}

    @contextlib.contextmanager
    def timed(part: str):
        """Add the block's wall-clock seconds to ``parts[part]``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            parts[part] += time.perf_counter() - t0

    lobe = None
    # the split's record: the start's held-out loss, the best one, its step and weights,
    # the last one scored and its step (kept in the checkpoint)
    val: dict[str, Any] | None = None
    if ckpt is not None:
        _load_adam_state(opt, ckpt["optimizer"])
        sess.restore(ckpt)
        lobe = ckpt.get("lobe")  # (init_info: read from it above)
        render_seconds = float(ckpt.get("render_seconds", 0.0))
        val = ckpt.get("validation")

    def weights_now() -> dict:
        return {n: torch.from_numpy(np.array(opt[n].numpy(), copy=True)) for n in names}

    def state() -> dict[str, Any]:
        return {
            "model": weights_now(),
            "optimizer": _adam_state(opt),
            "lobe": lobe,
            "init": init_info,
            "render_seconds": render_seconds,
            # the last step's figures: metrics.json's final_* after a resume with no step
            # left (a stop after the last step, before the export) were NaN
            "last": last,
            **({"validation": val} if split else {}),
        }

    def set_lobe(new):
        for v in views:
            v.bsdf.set_lobe(new, "fitted to the network")

    def held_out_loss(weights) -> float:
        """The held-out loss of ``weights`` (the optimiser's, or a saved state) through
        the sampling lobe in use."""
        for v in views:
            if v.validation_mask() is not None:
                for n in names:
                    w = weights[n]
                    v.params["raw." + n] = (
                        w if isinstance(w, mi.TensorXf) else mi.TensorXf(w.numpy())
                    )
                v.params.update()
        loss = heldout_loss(views, spp=images.validation_spp, seed=t.seed)
        assert loss is not None
        return loss

    def rescore_best(step: int) -> None:
        """After a refit of the sampling lobe, the best weights' held-out loss again,
        through the new lobe: the scores that follow are compared with it, never with
        one drawn through another lobe.  The loss's expectation does not depend on the
        lobe, but its samples do, and scores through two lobes share none of them (the
        development gold's fell by 24 % at a refit and rose back at the next, its
        weights all but unchanged, and the stage kept a step of the lucky lobe).  Not
        after a refit whose lobe samples as the one in use: the same samples."""
        assert val is not None and val.get("best") is not None
        with timed("validation"):
            val["best_loss"] = held_out_loss(val["best"])
            val.setdefault("best_rescored", []).append([step, val["best_loss"]])
        # the start's score is through the lobe in use only while it is the best
        val["start_current"] = int(val["best_step"]) == 0

    def check_start(step: int) -> bool:
        """At the end of the stage, the start against the kept weights through the lobe
        in use: once a step has beaten the start and the lobe was refitted, each later
        replacement of the best compared scores that share their samples, but the chain
        of them never compared the kept weights with the start.  Scored again through
        the last lobe, the start competes with every score drawn through it (the kept
        weights' included), as if it had been scored again at that refit, and it is
        kept when it scores no worse: the stage never ends worse than its start on the
        split through one set of samples (issue 29).  Whether it scored the start (not
        while its score is through the lobe in use, which it is while it is the best).
        Where the last lobe samples as the start's did (a refit back onto its grid
        point), the start's own score is through the same samples and is used again."""
        assert val is not None
        if val.get("start_current", True) or val.get("start") is None:
            return False  # (no "start": a checkpoint written before it was kept)
        same = (
            val.get("start_lobe") is not None
            and lobe is not None
            and lobe_format.same_density(val["start_lobe"], lobe)
        )
        if same:
            loss = val["start_loss"]
        else:
            with timed("validation"):
                loss = held_out_loss(val["start"])
        val["start_rescored"] = [step, loss]
        val["start_lobe_same"] = same
        val["start_current"] = True
        if loss <= val["best_loss"]:
            print(
                f"images: the start scores {loss:.4g} through the last sampling lobe against "
                f"{val['best_loss']:.4g} for step {val['best_step']}: the start is kept",
                file=sys.stderr,
            )
            val.update(best_loss=loss, best_step=0, best=val["start"])
            val["best_scored"] = val["start_loss"]  # (its score at its step, as log.csv's)
        return True

    def score(step: int) -> float:
        """The held-out loss of the weights now, recorded in ``val``."""
        nonlocal val
        with timed("validation"):
            loss = held_out_loss(opt)
            if val is None:  # the start's (its weights kept for check_start)
                val = {"start_loss": loss, "best_loss": math.inf, "best_step": 0, "best": None}
                val.update(start=weights_now(), start_current=True, start_lobe=lobe)
            if loss < val["best_loss"]:  # (best_loss: its score through the lobe in use)
                val.update(best_loss=loss, best_step=step, best=weights_now(), best_scored=loss)
            val.update(last_loss=loss, last_step=step)
        return loss

    def stalled() -> bool:
        """``images.patience`` scorings since the best one (the split only)."""
        return stalled_for(val, images, t.steps) is not None

    if lobe is None:
        lobe = lead.refit_lobe(seed=t.seed)
    set_lobe(lobe)
    last = {"loss": math.nan, "image": math.nan, "albedo": math.nan, "max_albedo": math.nan}
    if ckpt is not None and isinstance(ckpt.get("last"), dict):  # (older: not kept)
        last = {k: float(ckpt["last"].get(k, math.nan)) for k in last}
    with sess.run(state) as s, ib.evaluated_mode(), jit_notes_off(views):
        if split and val is None:
            score(s.step)  # the start's held-out loss, before the first step
        while s.step < t.steps and not stalled():
            s.stop_if_interrupted()
            step = s.step
            lr = loop.learning_rate(t, step) * lr_factor
            opt.set_learning_rate({n: lr * lr_scale[n] for n in names})
            if step > 0 and step % images.lobe_every == 0:
                before = lobe
                with timed("lobe"):
                    lobe = lead.refit_lobe(seed=t.seed + step, state=weights_now())
                    set_lobe(lobe)
                if split and val is not None and val.get("best") is not None:
                    if before is not None and lobe_format.same_density(before, lobe):
                        # the same samples: the best's score through the lobe stands
                        val.setdefault("lobe_unchanged", []).append(step)
                    else:
                        rescore_best(step)
            total = 0.0
            t_render = time.perf_counter()
            for i, v in enumerate(fitted):
                for n in names:
                    v.params["raw." + n] = opt[n]
                v.params.update()
                img = mi.render(
                    v.scene,
                    v.params,
                    spp=images.primal_spp,
                    spp_grad=images.spp,
                    seed=_rng_seed(t.seed, step, i),  # type: ignore[arg-type]  # stub: mi.UInt32
                )
                loss = relative_mse(img, v.target_tensor, v.weight_tensor) / len(fitted)
                dr.backward(loss)
                total += float(loss.array[0])
            render_seconds += time.perf_counter() - t_render
            with timed("albedo"):
                wi, wo, w = albedo_directions(t.seed * 7919 + step, cfg.images)
                pen, amax = penalty(
                    {n: opt[n] for n in names},
                    mi.TensorXf(wi.numpy()),
                    mi.TensorXf(wo.numpy()),
                    mi.TensorXf(w.numpy()),
                )
                dr.backward(pen)
                last = {
                    "image": total,
                    "albedo": float(pen.array[0]),  # (evaluates the penalty: timed with it)
                    "max_albedo": float(amax.array[0]),
                }
            last["loss"] = last["image"] + last["albedo"]
            if not math.isfinite(last["loss"]):
                raise s.diverged(last["loss"], step)
            opt.step()
            s.advance()
            held = score(s.step) if split and s.due(images.validation_every) else None
            if s.due(t.log_every) or held is not None:
                extra: dict[str, Any] = {HELDOUT_COLUMN: held} if split else {}
                s.log(loss=last["loss"], lr=lr, **extra)
                s.postfix(loss=f"{last['loss']:.4g}", albedo=f"{last['max_albedo']:.3f}")
            stop = held is not None and stalled()
            if s.due(t.checkpoint_every) or stop:
                s.check_weights(all(np.all(np.isfinite(opt[n].numpy())) for n in names))
                s.checkpoint()
            if stop:
                assert val is not None
                print(
                    f"images: no better held-out loss in {images.patience} scorings since step "
                    f"{val['best_step']}: the image stage stops at step {s.step} "
                    f"(images.patience; train.steps {t.steps})",
                    file=sys.stderr,
                )
        if split and val is not None and check_start(s.step):
            s.checkpoint()
    raw = copy.deepcopy(raw_template)
    raw.load_state_dict(val["best"] if val is not None else weights_now())
    training: dict[str, Any] = {
        "steps": sess.step,
        "device": variant_of(),
        "train_seconds": sess.seconds,
        **sess.record(),
        "render_seconds": render_seconds,
        # this process's scorings of the held-out pixels, albedo penalties and lobe refits
        **{f"{k}_seconds": v for k, v in parts.items()},
        "final_loss": last["loss"],
        "final_image_loss": last["image"],
        "final_albedo_penalty": last["albedo"],
        "final_max_albedo_estimate": last["max_albedo"],
        "spp_per_step": images.spp,
        "primal_spp_per_step": images.primal_spp,
        "lr_factor": lr_factor,
        "grid_lr_scales": {p: s for p, s in scales.items()},
        "views": len(fitted),
        LOBE_KEY: lobe,
        "init": init_info,
        "target": describe(views),
    }
    if val is not None:
        training["validation"] = validation_figures(views, images, val, t.steps)
    return raw.eval(), training


def stalled_for(val: dict | None, images: cfgmod.Images, steps: int) -> int | None:
    """The step at which the image stage stops early: the last scored one, when it is
    before ``steps`` (train.steps) and ``images.patience`` scorings (``patience *
    validation_every`` steps) have passed since the best; None while it runs on, when it
    ran to ``steps``, and without a split or a patience."""
    if images.patience is None or val is None or "last_step" not in val:
        return None
    last = int(val["last_step"])
    waited = last - int(val["best_step"])
    return last if last < steps and waited >= images.patience * images.validation_every else None


def validation_figures(
    views: list[View], images: cfgmod.Images, val: dict, steps: int
) -> dict[str, Any]:
    """metrics.json's ``training.validation``: the split and its held-out losses, and
    where the image stage stopped early (``steps``: train.steps)."""
    best = int(val["best_step"])
    return {
        "pixels": images.validation_pixels,
        "views": [v.name() for v in views if v.held_out],
        "heldout_pixels": sum(
            int(m.sum()) for v in views if (m := v.validation_mask()) is not None
        ),
        "spp": images.validation_spp,
        "every": images.validation_every,
        "loss_definition": "relative MSE (x - y)^2 / (y_bar^2 + 0.01), y_bar the target's "
        "channel mean (a flash/no-flash pair's: the flash photograph's), mean over the held-out "
        "pixels of the object and RGB, estimated without the render's noise as "
        "(x1 - y)(x2 - y) / (y_bar^2 + 0.01), x1 and x2 two renders of spp / 2 samples with "
        "fixed independent seeds (the same at every scoring); after a refit of the sampling "
        "lobe that samples otherwise the best weights are scored again through the new one, "
        "so that every comparison is of scores that share their samples",
        "start_loss": val["start_loss"],
        # the best's score at its step (log.csv's), comparable with the start's when no
        # refit of the sampling lobe came between them; best_rescored: its scores since
        "best_loss": val.get("best_scored", val["best_loss"]),
        "best_step": best,
        # [step, loss]: the best weights scored again through the lobe refitted at step
        "best_rescored": val.get("best_rescored", []),
        # [step, loss]: the start scored again through the last lobe at the stage's end
        # (step), where a step had beaten it before a refit; kept when no worse
        "start_rescored": val.get("start_rescored"),
        # whether that is the start's own score, the last lobe sampling as its lobe did
        "start_lobe_same": val.get("start_lobe_same"),
        # the steps whose refit returned a lobe that samples as the one in use: the best
        # weights' score through it stands (not scored again)
        "lobe_unchanged": val.get("lobe_unchanged", []),
        "last_loss": val.get("last_loss"),
        "last_step": val.get("last_step"),
        "kept": "the start" if best == 0 else f"step {best}",
        "patience": images.patience,
        "stopped_at": stalled_for(val, images, steps),
    }


def variant_of() -> str:
    import mitsuba as mi

    return str(mi.variant())


def describe(views: list[View]) -> str:
    names = ", ".join(v.name() for v in fitted_views(views))
    held = [v.name() for v in views if v.held_out]
    out = f"{len(views) - len(held)} images ({names}) by inverse rendering"
    return out + (f", {len(held)} held out ({', '.join(held)})" if held else "")


# ------------------------------------------------------------------ the run
def fit(
    cfg: cfgmod.Config,
    run_dir: Path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    folder: runfolder.Folder | None = None,
) -> tuple[RawBRDF, dict[str, Any], float, cfgmod.Config]:
    """The training stage of ``neural-brdf train`` for a config with ``target.images``:
    check the folder and the images, assess the coverage of the fitted views
    (``coverage.png``, ``training["coverage"]``, a warning when thin), fit (a GGX start
    first, by default; ``cfg.images``); returns (network, figures, the start time, the
    config it trained: ``cfg``, its grid and encoding as the start chose them,
    :func:`neural_brdf.inverse.starts.model_for_start`).
    :func:`neural_brdf.pipeline.run` then exports and validates it like any run (no
    reference: the physics checks only).  ``folder``: ``run_dir`` as the caller opened
    it (:func:`neural_brdf.runfolder.hold`)."""
    if folder is None:
        folder = runfolder.Folder.open(run_dir, resume=resume, overwrite=overwrite)
    t0 = time.perf_counter()
    use_variant(variant_name(cfg), key=variant_key(cfg))
    views = read_views(cfg)
    try:
        raw, training, cfg = _fit_views(cfg, run_dir, views, folder, resume=resume)
    finally:
        release(views)
    # what the views determine near the fitted network (the report's map; the warning
    # came after the start): its scenes loaded anew, the fit's plugins released
    training["determined"], warning = _determined(
        views,
        run_dir,
        _network_brdf(raw),
        cfg.train.seed,
        training["coverage"],
        picture=True,
        role="fit",
    )
    if warning and not training["determined_start"].get("warned"):
        print(f"warning: {warning}", file=sys.stderr)
    init = training.get("init")
    training["start_seconds"] = float(init["seconds"]) if isinstance(init, dict) else 0.0
    # the whole fit (start, image stage, the checks before them); a resumed run: this part
    training["fit_seconds"] = time.perf_counter() - t0
    return raw, training, t0, cfg


def _fit_views(
    cfg: cfgmod.Config,
    run_dir: Path,
    views: list[View],
    folder: runfolder.Folder,
    *,
    resume: bool,
) -> tuple[RawBRDF, dict[str, Any], cfgmod.Config]:
    from neural_brdf.inverse import coverage, starts

    images = cfg.images
    check_films(views)  # before anything is written
    check_render_sizes(views, images)
    split_views(views, images, cfg.train.seed)
    # the object's pixels (the held-out loss, the start's split, the noise estimate): a
    # view that sees none of the object is refused, before anything is written
    for k, v in enumerate(views):
        v.object = starts.seen_object_mask(v, f"target.images[{k}].scene")
    check_split_sees_object(views, images)
    columns = (*LOG_COLUMNS, HELDOUT_COLUMN) if images.split else LOG_COLUMNS
    if resume and stopped_before_image_stage(folder):
        again = " from the start's choice" if images.start not in ("ggx", "constant") else ""
        print(
            f"{cfg.name}: {folder.ckpt} does not exist yet (the run was stopped during its "
            f"start, before the image stage): the fit starts again{again}",
            file=sys.stderr,
        )
        resume = False
    if resume:  # its start's grid, encoding (starts.model_for_start) and steps, as trained
        cfg = _resumed_config(cfg, folder)
    sess = Session.one(cfg, folder, resume=resume, kind=KIND, columns=columns)
    # a checkpoint that cannot be resumed: refused before any write
    sess.resumed(must_match=RESUME_MUST_MATCH)
    sess.begin()  # the marker and config.yaml (an overwritten run removed), then init/
    covered, warning = coverage.assess(
        fitted_views(views), picture=run_dir / runfolder.COVERAGE, seed=cfg.train.seed
    )
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    init_state, init_info = None, None
    lr_factor, grid_lr_scale = 1.0, None
    if images.start not in ("ggx", "constant"):  # auto, or a family
        lr_factor, grid_lr_scale = images.start_lr_scale, images.start_grid_lr_scale
        if not resume:
            init_state, init_info, trained = starts.network_start(
                cfg, views, folder.init, report=_reporter(cfg)
            )
            if trained is not cfg:  # the start's grid: config.yaml says what is trained
                cfg = trained
                sess.reconfigure(cfg)
            noise, steps = target_noise(views), poor_start_steps(cfg)  # the steps, if poor
            if poor_start(init_info, images.poor_start_loss, noise, steps):
                cfg = poor_start_config(cfg, init_info)  # config.yaml: the steps it runs
                sess.reconfigure(cfg)
    elif images.start == "ggx":
        lr_factor, grid_lr_scale = images.start_lr_scale, images.start_grid_lr_scale
        if not resume:
            rough = fit_roughconductor(
                views,
                cfg.train,
                spp=images.spp,
                primal_spp=images.primal_spp,
                steps=images.start_steps,
                lr=images.ggx_lr,
                validation_spp=images.validation_spp,
                label=f"{cfg.name}: GGX start, ",
            )
            init_state, init_info = ggx_initial_state(
                cfg, rough, folder.init, images.start_train_steps
            )
            init_info["roughconductor"] = rough
            init_info["seconds"] += rough["seconds"]
    # what the views determine near the start (a resumed run: its checkpoint's start)
    start_info = init_info if init_info is not None else _saved_init(folder)
    element = _start_element(start_info)  # None: the constant start, measured by a stand-in
    determined_start, warning = _determined(
        views,
        run_dir,
        element,
        cfg.train.seed,
        covered,
        picture=False,
        role="start" if element is not None else "stand-in for the constant start",
        label=_start_family(start_info) if element is not None else None,
    )
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    determined_start["warned"] = warning is not None
    raw, training = fit_neural(
        cfg,
        views,
        run_dir,
        resume=resume,
        init_state=init_state,
        lr_factor=lr_factor,
        grid_lr_scale=grid_lr_scale,
        init_info=init_info,
        session=sess,
    )
    training["coverage"] = covered
    training["resumed"] = resume  # (fit_seconds: then this process's part alone)
    training["determined_start"] = {
        k: determined_start[k]
        for k in (
            "figure",
            "energy_figure",
            "by_bin_width_deg",
            "observed_figure",
            "reference",
            "warned",
        )
    }
    return raw, training, cfg


def stopped_before_image_stage(folder: runfolder.Folder) -> bool:
    """Was the images run in ``folder`` stopped (Ctrl-C, SIGTERM, kill) before its image
    stage wrote a checkpoint: while the coverage was assessed, the start chosen or
    distilled (``init/``)?  A run folder (its marker, or ``init/``) without ``ckpt.pt``
    and without a model (one that wrote its model and lost its checkpoint is not fitted
    again: the resume says it has no checkpoint)."""
    if folder.ckpt.exists() or folder.model.exists():
        return False
    return folder.init.exists() or os.path.lexists(folder.path / runfolder.MARKER)


def finished_report(cfg: cfgmod.Config, run_dir: Path, folder: runfolder.Folder) -> dict | None:
    """``--resume`` of an images run that has finished: its metrics.json (model.onnx
    written too) when the checkpoint, checked as a resume checks it, is at the steps the
    run trains (after a poor start, more: :func:`_resumed_config`) or where its image
    stage stopped early (``training.validation.stopped_at``: a resume would not step
    again); None otherwise, and always without a checkpoint."""
    if not folder.ckpt.exists():
        return None
    resumed = _resumed_config(cfg, folder)
    from neural_brdf.train import session

    ckpt = session.load_resumable(resumed, folder.ckpt, kind=KIND, must_match=RESUME_MUST_MATCH)
    step = int(ckpt["step"])
    done = session.finished_report(run_dir, step)
    if done is None:
        return None
    validation = done["training"].get("validation")
    v = validation if isinstance(validation, dict) else {}
    # stopped early under the same patience (another lets the stage train on)
    stopped = v.get("stopped_at") == step and v.get("patience") == resumed.images.patience
    if not (step >= resumed.train.steps or stopped):
        return None
    if stopped:  # train.steps, the CLI's usual advice, would not make it train on
        done = {**done, "resume_advice": early_stop_advice(step, resumed.images.patience)}
    return done


def early_stop_advice(step: int, patience: int | None) -> str:
    """What lets an images run whose image stage stopped early at ``step`` (under
    ``images.patience`` ``patience``: :func:`stalled_for`) train on when resumed: a
    larger patience, or none; a larger ``train.steps`` alone stops it again at once."""
    return (
        f"its image stage stopped early at step {step} (images.patience {patience}): raise "
        "images.patience, or set it to null, to train on (raising train.steps alone does not)"
    )


def _saved_init(folder: runfolder.Folder) -> dict[str, Any] | None:
    """The ``init`` record of the checkpoint a run resumes (its start), or None."""
    from neural_brdf.train.session import load_checkpoint

    if not folder.ckpt.is_file():
        return None
    try:
        init = load_checkpoint(folder.ckpt).get("init")
    except (InputError, AttributeError):
        return None
    return init if isinstance(init, dict) else None


def _start_element(init: Any) -> ET.Element | None:
    """The ``<bsdf>`` of a fit's start (its ``init`` record): the chosen family's, the
    ``ggx`` start's fitted ``roughconductor``; None for the constant start."""
    from neural_brdf.inverse import families

    if not isinstance(init, dict):
        return None
    start, rough = init.get("start"), init.get("roughconductor")
    if isinstance(start, dict) and start.get("family") and start.get("params"):
        return families.family(str(start["family"])).element(start["params"])
    if isinstance(rough, dict) and "alpha" in rough:
        return roughconductor_element(rough)
    return None


def _start_family(init: Any) -> str | None:
    """The family of a fit's start (its ``init`` record), as the choice named it
    (``clearcoat``, whose ``<bsdf>`` is a ``principled``); None for the ``ggx`` and
    the constant starts."""
    start = init.get("start") if isinstance(init, dict) else None
    family = start.get("family") if isinstance(start, dict) else None
    return str(family) if family else None


def _network_brdf(raw: RawBRDF):
    """f(wi, wo) of the trained network, numpy in and out (RGB, 1/sr)."""
    device = next(raw.parameters()).device

    def f(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        out = [np.zeros((0, 3), np.float32)]
        with torch.no_grad():
            for a in range(0, len(wi), 1 << 16):
                t = [
                    torch.as_tensor(np.asarray(x[a : a + (1 << 16)]), dtype=torch.float32)
                    for x in (wi, wo)
                ]
                out.append(raw(t[0].to(device), t[1].to(device))[:, :3].cpu().numpy())
        return np.concatenate(out)

    return f


def _determined(
    views: list[View],
    run_dir: Path,
    reference: Any,
    seed: int | None,
    covered: dict[str, Any],
    *,
    picture: bool,
    role: str = "start",
    label: str | None = None,
) -> tuple[dict[str, Any], str | None]:
    """How well the fitted views determine f near ``reference`` (the start's
    ``<bsdf>``, the network's f, or None: a grey diffuse;
    :mod:`neural_brdf.inverse.determined`) within the bins that their coverage
    (``covered``, its summary) observes: its summary and warning (``role`` and
    ``label``, the start's family, name the reference there), the map
    ``determined.png`` in the run folder when ``picture``."""
    from neural_brdf.inverse import determined

    return determined.assess(
        fitted_views(views),
        reference,
        target_noise(views),
        picture=run_dir / runfolder.DETERMINED if picture else None,
        role=role,
        label=label,
        seed=seed or 0,
        observed=np.asarray(covered["observed_bins"], bool),
    )


def _resumed_config(cfg: cfgmod.Config, folder: runfolder.Folder) -> cfgmod.Config:
    """``cfg`` as the checkpoint being resumed was trained: the grid and encoding of its
    start's family (:func:`neural_brdf.inverse.starts.model_for_start`) and, after a poor
    start, its steps (:func:`poor_start_config`); ``cfg`` itself when there is no readable
    checkpoint (the resume check then says why)."""
    from neural_brdf.inverse import starts

    init = _saved_init(folder)
    start = init.get("start") if init is not None else None
    if not isinstance(start, dict) or "family" not in start:  # unreadable; ggx, constant
        return cfg
    return poor_start_config(starts.model_for_start(cfg, str(start["family"])), init)


def _reporter(cfg: cfgmod.Config):
    """A line on stderr per stage of the start (with ``train.progress``), else None."""
    if not cfg.train.progress:
        return None
    return lambda line: print(f"{cfg.name}: {line}", file=sys.stderr, flush=True)


def release(views: list[View]) -> None:
    """Drop the views' Mitsuba scenes and their ``neural_brdf_ad`` plugins, now (not at
    some later garbage collection).  A live instance of a BSDF takes part in every later
    render of the process in Mitsuba's symbolic mode (a symbolic virtual call traces
    every registered instance), where the plugin cannot evaluate: the report's preview
    renders right after the fit."""
    import gc

    for v in views:
        v.scene = v.params = v.bsdf = v.target_tensor = v.weight_tensor = None
    gc.collect()


# ------------------------------------------------------------------ the analytic fit
# Mitsuba's own roughconductor (GGX), fitted to the same images: the comparison of the
# benchmark, and the first stage of the "ggx" initialisation.
ROUGH_START = {"alpha": 0.3, "eta": (1.0, 1.0, 1.0), "k": (3.0, 3.0, 3.0)}
ROUGH_BOUNDS = {"alpha.value": (0.01, 1.0), "eta.value": (0.02, 5.0), "k.value": (0.0, 10.0)}


def fit_roughconductor(
    views: list[View],
    train: cfgmod.Train,
    *,
    spp: int,
    primal_spp: int | None = None,
    steps: int | None = None,
    lr: float = 0.02,
    validation_spp: int = 64,
    label: str = "",
) -> dict[str, Any]:
    """Fit ``roughconductor`` (GGX; alpha, RGB eta and k) to ``views`` with the fit's loss,
    mi.ad.Adam and ``train``'s schedule (warm-up, decay) at ``lr``; returns the fitted
    parameters and the time.  No torch is involved, so Mitsuba's symbolic mode is used.
    With a validation split (:func:`split_views`) the held-out pixels and views take no
    part, and the result has their loss (``heldout_loss``, at ``validation_spp``).
    ``label``: a progress bar (when ``train.progress``) named after it."""
    import drjit as dr
    import mitsuba as mi

    from neural_brdf.train import loop

    steps = train.steps if steps is None else steps
    sched = train.model_copy(update={"steps": steps, "lr": lr})
    prepare_views(views, bsdf_element("roughconductor", distribution="ggx", **ROUGH_START))
    opt = mi.ad.Adam(lr=lr)
    for key in ROUGH_BOUNDS:
        opt[key] = views[0].params[key]
    start = time.perf_counter()
    loss_value = math.nan
    bar = tqdm(
        total=steps,
        desc=f"{label}roughconductor",
        disable=train.bar_disabled() if label else True,
        dynamic_ncols=True,
        mininterval=0.5,
        leave=False,
    )
    fitted = fitted_views(views)
    for step in range(steps):
        opt.set_learning_rate(loop.learning_rate(sched, step))
        loss_value = 0.0
        for i, v in enumerate(fitted):
            v.params.update(opt)
            img = mi.render(
                v.scene,
                v.params,
                spp=primal_spp or spp,
                spp_grad=spp,
                seed=_rng_seed(train.seed, step, i),  # type: ignore[arg-type]  # stub: mi.UInt32
            )
            loss = relative_mse(img, v.target_tensor, v.weight_tensor) / len(fitted)
            dr.backward(loss)
            loss_value += float(loss.array[0])
        opt.step()
        for key, (lo, hi) in ROUGH_BOUNDS.items():
            opt[key] = dr.clip(opt[key], lo, hi)
        bar.update(1)
    bar.close()
    seconds = time.perf_counter() - start

    def values(key):
        return [float(x) for x in np.asarray(opt[key].numpy()).reshape(-1)]

    out = {
        "alpha": values("alpha.value")[0],
        "eta": values("eta.value"),
        "k": values("k.value"),
        "steps": steps,
        "spp_per_step": spp,
        "primal_spp_per_step": primal_spp or spp,
        "final_image_loss": loss_value,
        "seconds": seconds,
    }
    if any(v.validation_mask() is not None for v in views):
        for v in views:
            v.params.update(opt)
        out["heldout_loss"] = heldout_loss(views, spp=validation_spp, seed=train.seed)
    return out


def roughconductor_element(fit: dict) -> ET.Element:
    """The ``<bsdf type="roughconductor">`` of :func:`fit_roughconductor`'s result."""
    return bsdf_element(
        "roughconductor",
        distribution="ggx",
        alpha=float(fit["alpha"]),
        eta=tuple(fit["eta"]),
        k=tuple(fit["k"]),
    )


def ggx_initial_state(
    cfg: cfgmod.Config, rough: dict, run_dir: Path, steps: int
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The "ggx" initialisation's second stage: the RawBRDF of ``cfg.model`` trained on
    BRDF samples (:func:`neural_brdf.train.loop.train`, into ``run_dir``) of the analytic
    microfacet model that matches Mitsuba's roughconductor: GGX, separable Smith
    masking, conductor Fresnel with the fitted eta and k."""
    from neural_brdf.train import loop

    target = {
        "model": "microfacet",
        "params": {
            "distribution": "ggx",
            "alpha": float(rough["alpha"]),
            "masking": "smith_separable",
            "fresnel": "conductor",
            "eta": [float(x) for x in rough["eta"]],
            "k": [float(x) for x in rough["k"]],
        },
    }
    icfg = distillation_config(
        cfg,
        target,
        f"{cfg.name}: GGX start, network",
        start_training(cfg, steps),
        source="ggx initialisation",
    )
    raw, info = loop.train(icfg, run_dir)
    return raw.state_dict(), {
        "target": info["target"],
        "steps": steps,
        "seconds": info["train_seconds"],
        "raw_val_rel_rmse": info["raw_val_rel_rmse"],
    }


# ------------------------------------------------------------------ measurements
def psnr_linear(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (dB) of linear RGB over ``mask``'s pixels: 10 log10(peak^2 / MSE), peak the
    reference's largest value there, MSE over the pixels and the 3 channels."""
    ref, img = reference[mask].astype(np.float64), image[mask].astype(np.float64)
    mse = float(np.mean((img - ref) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(float(ref.max()) ** 2 / mse)


def image_rel_rmse(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> float:
    """sqrt(sum (image - reference)^2 / sum reference^2) over ``mask``'s pixels."""
    ref, img = reference[mask].astype(np.float64), image[mask].astype(np.float64)
    return float(np.sqrt(np.sum((img - ref) ** 2) / np.sum(ref**2)))


def brdf_pairs(bsdf, n: int, seed: int, min_cos: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of the BRDF error: wi uniform (in solid angle) on the cap
    cos(theta) > ``min_cos``; wo half uniform on the same cap, half drawn by ``bsdf``'s own
    sampler (a Mitsuba BSDF, the true one) and kept where cos(theta_o) > ``min_cos``."""
    import drjit as dr
    import mitsuba as mi

    rng = np.random.default_rng(seed)

    def cap(m):
        c = rng.uniform(min_cos, 1.0, m)
        phi = rng.uniform(0.0, 2 * math.pi, m)
        s = np.sqrt(1.0 - c * c)
        return np.stack([s * np.cos(phi), s * np.sin(phi), c], -1)

    half = n // 2
    wi_u, wo_u = cap(half), cap(half)
    wi_s = cap(4 * (n - half))
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi_s))
    si.wi = mi.Vector3f(*(np.ascontiguousarray(wi_s[:, j], np.float32) for j in range(3)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    u = rng.random((len(wi_s), 3)).astype(np.float32)
    bs, _ = bsdf.sample(mi.BSDFContext(), si, mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
    wo_s = np.stack([np.asarray(bs.wo[j].numpy(), np.float64) for j in range(3)], -1)
    keep = np.flatnonzero(wo_s[:, 2] > min_cos)[: n - half]
    wi = np.concatenate([wi_u, wi_s[keep]])
    wo = np.concatenate([wo_u, wo_s[keep] / np.linalg.norm(wo_s[keep], axis=-1, keepdims=True)])
    return wi, wo


def brdf_rel_rmse(fc_fit: np.ndarray, fc_true: np.ndarray) -> float:
    """sqrt(sum (f^ cos - f cos)^2 / sum (f cos)^2) over pairs and RGB."""
    return float(np.sqrt(np.sum((fc_fit - fc_true) ** 2) / np.sum(fc_true**2)))
