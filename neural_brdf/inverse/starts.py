"""Starts for an images fit: analytic families fitted to the views, one chosen by a
held-out split of the user's own pixels (issue 29, item 1; docs/inverse.md).

    from neural_brdf.inverse import starts
    choice = starts.choose_start(views)          # fit.View list: scenes + target images
    choice.family, choice.params, choice.summary()   # the chosen start, every candidate
    state, info = starts.distill(cfg, choice.element, run_dir, steps)   # the network's start

A *family* (:mod:`neural_brdf.inverse.families`: a Mitsuba 3 BSDF plugin, its
parameters kept in their ranges by construction, and the families its fit may start
from) is a candidate start.

The fit (:func:`fit_start`) minimises the relative MSE of :mod:`neural_brdf.inverse.fit`
(:func:`~neural_brdf.inverse.fit.relative_mse`, :func:`~neural_brdf.inverse.fit.rel_weight`:
the loss the network stage uses) over the *training* pixels of a seeded split of the
object's pixels (:func:`split_pixels`; the run's own validation split, when the views
carry one, is left out of both parts), with mi.ad.Adam on the free variables and a
cosine-decayed rate (:class:`Schedule`); it renders in Mitsuba's symbolic mode (no
torch).  Before the first step, one render scales the reflectances so that the mean
brightness of the training pixels matches (each channel; clamped inside its range).
:func:`choose_start` starts two families from simpler ones already fitted
(:func:`warm_start`): the anisotropic conductor from the isotropic one, the blend from
the diffuse and the conductor with the least-squares weight of their renders.

Frozen steps.  A step renders every view (``mi.render``, primal and gradient passes),
and Dr.Jit would trace Mitsuba's integrator and BSDF again each time, the same kernels
every step.  With ``images.start_freeze`` (:attr:`Schedule.freeze`, the default) the
step's render, loss and gradient (:func:`render_loss_backward`) run under
:func:`drjit.freeze`: recorded at a view's first steps, replayed after.  A recording
reads only its arguments' arrays, so the parameters enter it as arguments: the family's
map from the free variables and ``params.update()`` run outside (Mitsuba's
``roughplastic`` reads alpha on the host when it updates, which a recording refuses),
the parameters go in as fresh leaves, and their gradients are pulled back through the
map afterwards (``dr.backward`` of sum(value x its leaf's gradient)).  The leaves and
the seed are opaque arrays (a literal would key the recording by its value), so a view
records at its first two steps (the first render adds state to the scene, which Dr.Jit
counts as more inputs) and replays at every step after.  Where Dr.Jit cannot record a
step (Mitsuba's ``direct_projective`` refuses) the fit says so once per integrator
(:data:`UNFREEZABLE`) and traces its steps; :attr:`Candidate.frozen` records which.
The fit is the traced one to float rounding (tests/inverse/test_starts.py: 1e-4
relative after 6 steps, every family); on three 96 x 96 views the six families before
``clearcoat`` took 28.9 s against 50.8 s traced (benchmarks/start_fit.py).

The loss reported for a candidate, on the held-out pixels (and on the training pixels,
for comparison), is the same relative MSE estimated without the render's own noise: two
renders of ``val_spp`` samples with independent seeds, x1 and x2, give
mean((x1 - y)(x2 - y) w), whose expectation is the relative MSE of the noise-free render
(:func:`noise_free_loss`, :func:`pixel_losses`).  A plain (x - y)^2 adds the render's
variance, which depends on the BSDF and the lighting, not on how well the BSDF fits: on
the example's views at 96 x 96 it was two thirds of the plain figure of a good fit at
2 x 64 samples (0.0037 against 0.0012 noise-free), enough to hide the differences
between good candidates.

:func:`choose_start` fits every family and keeps the simplest (fewest free scalars) whose
held-out loss is within ``max(tie_tol x the least, sigmas x the standard error of the
paired difference)`` of the least one (:func:`pick`): the families are scored on the same
pixels with the same render seeds, the difference pixel by pixel, its standard error from
its sums over the split's tiles.  A family with more parameters must earn its place.  It
takes the views only: the scenes' own ``<bsdf id="fit">`` is never read (the object's
pixels are found with a stand-in diffuse), so no truth the user does not have enters the
choice.  :func:`network_start` then fits the *contenders* (:func:`contend`: the families
within ``images.start_continue_within`` of the least held-out loss, at most
``images.start_continue_max`` of them, unless the chosen one is already at the targets'
noise) as many steps again and chooses once more, checks a choice that the split
tied by its standard error alone on folds of the training tiles (:func:`inconclusive`,
:func:`cross_check`), and refines the chosen family (:func:`refine_rounds`); none of
the three when the first choice is so
far above the targets' noise (``images.poor_start_early_loss``, :func:`far_above_floor`)
that no family is near the material.

:func:`teacher_xml` writes the chosen BSDF as a standalone Mitsuba XML file, the teacher
of ``target: {mitsuba: FILE.xml}`` (:class:`neural_brdf.measured.mitsuba.MitsubaTarget`),
and :func:`distill` trains the network on it by sample-based training
(:func:`neural_brdf.train.loop.train`), as :func:`neural_brdf.inverse.fit.ggx_initial_state`
does from the analytic GGX.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from neural_brdf import config as cfgmod
from neural_brdf import runfolder
from neural_brdf.errors import InputError, Interrupted
from neural_brdf.inverse import views as inverse
from neural_brdf.inverse.families import DEFAULT, FAMILIES, family, warm_sources

TEACHER_XML = runfolder.TEACHER  # the file distill() writes into its run folder
# A stand-in for the scene's own <bsdf id="fit"> where only the geometry matters (the
# object's pixels): the scene's BSDF may be the truth of a synthetic view.
STAND_IN = inverse.bsdf_element("diffuse")


# ------------------------------------------------------------------ the split
def object_mask(view: inverse.View) -> np.ndarray:
    """(H, W) bool: the pixels of the object to fit (:func:`~neural_brdf.inverse.fit.
    sphere_mask`: every shape with ``<bsdf id="fit">``, eroded by the film's filter),
    found with :data:`STAND_IN` in place of the scene's own BSDF."""
    return inverse.sphere_mask(_stood_in(view))


def seen_object_mask(view: inverse.View, key: str) -> np.ndarray:
    """:func:`object_mask`, after checking that the view sees the object at all
    (:func:`~neural_brdf.inverse.views.check_sees_object`: InputError naming ``key``,
    ``target.images[k].scene``, otherwise); one load of the scene for both."""
    hit, front, reach = inverse.fit_hits(_stood_in(view))
    inverse.check_sees_object(view, key, hit, front)
    return inverse.eroded(hit, reach)


def _stood_in(view: inverse.View) -> inverse.View:
    """``view`` with :data:`STAND_IN` as its scene's ``<bsdf id="fit">``."""
    root = ET.fromstring(inverse.scene_text(view.tree, STAND_IN))
    return dataclasses.replace(view, tree=ET.ElementTree(root))


tiles = inverse.tiles  # (H, W) tile indices (the split's units)


def split_pixels(
    views: Sequence[inverse.View], share: float, seed: int, *, block: int = 4
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(train, held-out) masks, each a list of (H, W) bool per view: the object's pixels
    (:func:`object_mask`) cut into ``block`` x ``block`` tiles (:func:`tiles`),
    ``share`` of each view's tiles (rounded; at least one and at most all but one when
    ``share`` > 0) held out at random (seeded by ``seed`` and the view's index).  The two
    are disjoint and together the object's pixels.  Tiles rather than single pixels: a
    held-out pixel then mostly has held-out neighbours, which see nearly the same pairs
    (wi, wo) as it does, and the choice's standard error (:func:`pick`) treats tiles as
    independent.

    The run's own validation split (``images.validation_pixels`` and
    ``validation_views``: :func:`neural_brdf.inverse.fit.split_views`, marked on the
    views) is left out of both masks: the start is chosen within the pixels the fit may
    use, and the run's held-out pixels stay unseen by the start as by the network."""
    if not 0.0 <= share < 1.0:
        raise ValueError(f"share {share}: expected 0 <= share < 1")
    if block < 1:
        raise ValueError(f"block {block}: expected >= 1")
    train, held = [], []
    for i, v in enumerate(views):
        obj = object_mask(v)
        reserved = v.validation_mask()
        if reserved is not None:
            obj &= ~reserved
        tile = tiles(obj.shape, block)
        found = np.unique(tile[obj])
        n = len(found)
        k = int(round(share * n))
        if share > 0 and n > 1:
            k = min(max(k, 1), n - 1)
        rng = np.random.default_rng([seed, i])
        val = obj & np.isin(tile, rng.permutation(found)[:k])
        train.append(obj & ~val)
        held.append(val)
    return train, held


def units(masks: Sequence[np.ndarray], block: int) -> np.ndarray:
    """The tile (:func:`tiles`) of each pixel of ``masks``, numbered across the views,
    in the order of :func:`pixel_losses`: the independent units of :func:`pick`."""
    out, offset = [], 0
    for m in masks:
        t = tiles(m.shape, block)
        out.append(offset + t[m])
        offset += int(t.max()) + 1
    return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)


# ------------------------------------------------------------------ losses
def pixel_losses(
    view: inverse.View, mask: np.ndarray, x1: np.ndarray, x2: np.ndarray | None = None
) -> np.ndarray:
    """The relative MSE's terms (:func:`~neural_brdf.inverse.fit.relative_mse`) of
    render ``x1`` against ``view``'s target at ``mask``'s pixels (row-major), averaged
    over RGB: (x1 - y)^2 w; with a second render ``x2`` of independent samples,
    (x1 - y)(x2 - y) w, whose expectation is the term of the noise-free render (module
    doc)."""
    y = view.target[mask].astype(np.float64)
    w = view.rel_weight()[mask].astype(np.float64)
    d1 = x1[mask].astype(np.float64) - y
    d2 = d1 if x2 is None else x2[mask].astype(np.float64) - y
    return (d1 * d2 * w).mean(-1)


def masked_loss(
    view: inverse.View, mask: np.ndarray, x1: np.ndarray, x2: np.ndarray | None = None
) -> float:
    """The mean of :func:`pixel_losses`: the relative MSE over ``mask``'s pixels and
    RGB (without the render's noise when ``x2`` is given).  NaN for an empty mask."""
    return float(pixel_losses(view, mask, x1, x2).mean()) if mask.any() else math.nan


def _pooled(terms: Sequence[tuple[float, int]]) -> float:
    """The pixel-weighted mean of per-view losses (loss, pixel count)."""
    n = sum(c for _, c in terms if c)
    return math.nan if n == 0 else sum(x * c for x, c in terms if c) / n


def _render_np(view: inverse.View, params: Any, *, spp: int, seed: int) -> np.ndarray:
    import mitsuba as mi

    img = mi.render(view.scene, params, spp=spp, seed=seed)  # type: ignore[arg-type]  # stub: mi.UInt32
    return np.asarray(img, dtype=np.float32)[..., :3]


def noise_free_loss(
    views: Sequence[inverse.View],
    masks: Sequence[np.ndarray],
    *,
    spp: int,
    seed: int,
    plain: bool = False,
) -> float:
    """The relative MSE over ``masks`` (pixel-weighted over the views) of the views'
    scenes as they are loaded (:func:`~neural_brdf.inverse.fit.prepare_views`), without
    the render's noise: two renders of ``spp`` samples each (:func:`masked_loss`); with
    ``plain`` the MSE of their mean instead.  For the network, render inside
    :func:`neural_brdf.inverse.bsdf.evaluated_mode`."""
    terms = []
    for i, v in enumerate(views):
        m = masks[i]
        if not m.any():
            continue
        a = _render_np(v, v.params, spp=spp, seed=_seed(seed, 1, i))
        b = _render_np(v, v.params, spp=spp, seed=_seed(seed, 2, i))
        x = masked_loss(v, m, 0.5 * (a + b)) if plain else masked_loss(v, m, a, b)
        terms.append((x, int(m.sum())))
    return _pooled(terms)


def _seed(seed: int, stage: int, view: int) -> int:
    return (seed * 1_000_003 + stage * 7919 + view * 101 + 17) % (2**31 - 1)


# ------------------------------------------------------------------ one family
@dataclass
class Candidate:
    """One family fitted to the views: its parameters and figures."""

    family: str
    params: dict[str, Any]
    train_loss: float  # relative MSE, noise-free estimate, on the training pixels
    val_loss: float  # ... on the held-out pixels (the choice's figure)
    val_loss_plain: float  # the plain relative MSE of a 2 x val_spp render, held out
    seconds: float
    steps: int
    complexity: int
    element: ET.Element = field(repr=False)
    # the held-out pixels' terms (pixel_losses, noise-free), views in order: for pick()
    val_pixels: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    # the fitted family's render of each view (2 x val_spp samples; None: not rendered)
    images: list[np.ndarray | None] = field(default_factory=list, repr=False)
    frozen: bool = False  # whether its steps were recorded and replayed (Frozen steps)
    # the Adam steps behind its start: those of the fits its warm start came from
    # (warm_start), or of the fit it continues, and of a continuation of it not kept
    # (it had those steps, and they did not help); see fit_further and catch_up
    before: int = 0

    @property
    def total_steps(self) -> int:
        """Every step behind this fit, its own and those it started from."""
        return self.before + self.steps

    def summary(self) -> dict[str, Any]:
        """JSON-ready (metrics.json)."""
        return {
            "family": self.family,
            "plugin": FAMILIES[self.family].plugin,
            "params": self.params,
            "train_loss": self.train_loss,
            "val_loss": self.val_loss,
            "val_loss_plain": self.val_loss_plain,
            "free_scalars": self.complexity,
            "steps": self.steps,
            "steps_before": self.before,
            "seconds": self.seconds,
            "frozen_steps": self.frozen,
        }


@dataclass(frozen=True)
class Schedule:
    """How :func:`fit_start` steps: Adam's rate on the free variables, cosine-decayed to
    ``lr_end`` times it; the samples per pixel of the gradient pass (``spp``), of the
    primal pass, and of each of the two held-out renders."""

    steps: int = 80
    spp: int = 4
    primal_spp: int = 16
    val_spp: int = 64
    lr: float = 0.2
    lr_end: float = 0.05
    freeze: bool = True  # record a step once per view and replay it (module doc)

    def rate(self, step: int) -> float:
        c = 0.5 * (1.0 + math.cos(math.pi * step / max(1, self.steps)))
        return self.lr * (self.lr_end + (1.0 - self.lr_end) * c)

    @classmethod
    def of(cls, images: cfgmod.Images) -> Schedule:
        """Each family's fit as the config's ``images`` section sets it."""
        return cls(
            steps=cls.steps if images.start_steps is None else images.start_steps,
            spp=images.start_spp,
            primal_spp=images.start_primal_spp,
            val_spp=images.validation_spp,
            lr=images.start_lr,
            lr_end=images.start_lr_end,
            freeze=images.start_freeze,
        )

    @classmethod
    def refining(cls, images: cfgmod.Images) -> Schedule:
        """The chosen family's refinement (:func:`refine`) as ``images`` sets it: its
        primal pass at twice its gradient pass's samples."""
        return cls(
            steps=images.start_refine_steps,
            spp=images.start_refine_spp,
            primal_spp=2 * images.start_refine_spp,
            val_spp=images.validation_spp,
            lr=images.start_refine_lr,
            lr_end=images.start_refine_lr_end,
            freeze=images.start_freeze,
        )


def fit_start(
    views: Sequence[inverse.View],
    family_name: str,
    *,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    seed: int = 0,
    steps: int | None = None,
    spp: int | None = None,
    schedule: Schedule | None = None,
    init: Mapping[str, Any] | None = None,
) -> tuple[ET.Element, dict[str, Any], float, float]:
    """Fit the family ``family_name`` to ``views`` on the training pixels ``mask_train``
    (mi.ad.Adam, module doc); returns (its ``<bsdf>``, its parameters, the training and
    the held-out (``mask_val``) relative MSE).  ``steps`` and ``spp`` override
    ``schedule``'s; ``init``: the parameters to start from.  See :func:`fit_candidate`
    for every figure."""
    c = fit_candidate(
        views,
        family_name,
        mask_train=mask_train,
        mask_val=mask_val,
        seed=seed,
        steps=steps,
        spp=spp,
        schedule=schedule,
        init=init,
    )
    return c.element, c.params, c.train_loss, c.val_loss


class Fixed:
    """A value handed to a frozen function (:func:`drjit.freeze`) as it is: compared by
    identity, never traversed for Dr.Jit arrays, so it keys the recording."""

    __slots__ = ("value",)

    def __init__(self, value: Any) -> None:
        self.value = value


def render_loss_backward(scene, params, primal, grad, leaves, target, weight, seed) -> None:
    """One view's share of a family's step: ``mi.render`` of ``scene`` (``params``: a
    :class:`Fixed` of its ``mi.traverse``; ``primal``, ``grad``: the two passes' samples
    per pixel) at ``seed`` (``mi.UInt32``), the relative MSE against ``target`` and
    ``dr.backward``, which leaves the gradients on ``leaves`` (the parameters the scene
    holds, by key).  The unit :func:`fit_candidate` freezes (module doc, Frozen steps):
    every Dr.Jit array it reads is an argument, ``leaves`` included, so a replay reads
    the step's values."""
    import drjit as dr
    import mitsuba as mi

    img = mi.render(scene, params.value, spp=primal, spp_grad=grad, seed=seed)  # type: ignore[arg-type]  # stub: mi.UInt32
    dr.backward(inverse.relative_mse(img, target, weight))


def fit_candidate(
    views: Sequence[inverse.View],
    family_name: str,
    *,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    seed: int = 0,
    steps: int | None = None,
    spp: int | None = None,
    schedule: Schedule | None = None,
    init: Mapping[str, Any] | None = None,
    average_from: int | None = None,
) -> Candidate:
    """:func:`fit_start` with every figure (a :class:`Candidate`).  ``init``: the
    parameters to start from (by name, as :meth:`~neural_brdf.inverse.families.Family.numbers`
    gives them), else the
    family's start values scaled to the images' brightness (module doc).
    ``average_from``: the fit's result is the mean of the free variables after each step
    from this one on (Polyak averaging: the last steps' jitter averaged out), else the
    last step's.  Loads the
    views' scenes with the family's BSDF (:func:`~neural_brdf.inverse.fit.prepare_views`:
    the views' ``scene``, ``params`` and tensors are replaced); views without training
    pixels are not rendered during the fit."""
    import drjit as dr
    import mitsuba as mi

    fam = family(family_name)
    sched = schedule or Schedule()
    if steps is not None:
        sched = dataclasses.replace(sched, steps=steps)
    if spp is not None:
        sched = dataclasses.replace(sched, spp=spp)
    if len(mask_train) != len(views) or len(mask_val) != len(views):
        raise ValueError("mask_train and mask_val need one mask per view")
    n_train = sum(int(m.sum()) for m in mask_train)
    if n_train == 0:
        raise ValueError("no training pixels")
    start = time.perf_counter()
    views = list(views)
    fitted = [i for i, m in enumerate(mask_train) if m.any()]
    if init is not None:
        free0 = fam.free_of(init)
        inverse.prepare_views(views, fam.element(fam.numbers(free0)))
    else:
        inverse.prepare_views(views, fam.element(fam.numbers(fam.free_of(fam.initial()))))
        # the brightness of the training pixels, matched by the reflectances (module doc)
        ys, xs = np.zeros(3), np.zeros(3)
        for i in fitted:
            v = views[i]
            img = _render_np(v, v.params, spp=sched.primal_spp, seed=_seed(seed, 3, i))
            ys += v.target[mask_train[i]].sum(0)
            xs += img[mask_train[i]].sum(0)
        scale = np.where(xs > 0, ys / np.maximum(xs, 1e-12), 1.0)
        free0 = fam.free_of(fam.initial(scale))

    def set_free(free: Mapping[str, Any], xp: Any) -> None:
        keys = fam.to_mitsuba(fam.values(free, xp), xp)
        for v in views:
            for k, x in keys.items():
                v.params[k] = x
            v.params.update()

    def typed(z: np.ndarray) -> Any:
        return mi.Float(float(z[0])) if z.size == 1 else mi.Color3f(*(float(x) for x in z))

    opt = mi.ad.Adam(lr=sched.lr)
    for n, z in free0.items():
        opt[n] = typed(z)
    # the loss over all training pixels: relative_mse's mean over the film, rescaled to
    # a mean over the training pixels of every view
    weights = {}
    for i in fitted:
        v = views[i]
        h, w = v.target.shape[:2]
        m = mask_train[i][..., None].astype(np.float32)
        weights[i] = mi.TensorXf(v.rel_weight() * m * (h * w / n_train))
    sums: dict[str, np.ndarray] = {}
    n_sum = 0
    # a step's render, loss and gradient, recorded at each view's first steps and
    # replayed after (module doc, Frozen steps); the family's map and the parameters'
    # update run outside; traced where Dr.Jit could not record a scene's integrator
    frozen = sched.freeze and not any(views[i].integrator in UNFREEZABLE for i in fitted)
    step_fn = dr.freeze(render_loss_backward) if frozen else render_loss_backward
    fixed_params = {i: Fixed(views[i].params) for i in fitted}
    for step in range(sched.steps):
        opt.set_learning_rate(sched.rate(step))
        for i in fitted:
            v = views[i]
            # the parameters from the free variables, per view: dr.backward frees the graph
            values = fam.to_mitsuba(fam.values({n: opt[n] for n in fam.params}, dr), dr)
            leaves = {k: dr.detach(x) for k, x in values.items()}
            dr.make_opaque(leaves)
            for k, x in leaves.items():
                dr.enable_grad(x)
                v.params[k] = x
            v.params.update()
            args = (
                v.scene,
                fixed_params[i],
                sched.primal_spp,
                sched.spp,
                leaves,
                v.target_tensor,
                weights[i],
                dr.opaque(mi.UInt32, _seed(seed, 100 + step, i)),
            )
            try:
                step_fn(*args)
            except RuntimeError as e:
                if not frozen:
                    raise
                stop = _interruption(e)
                if stop is not None:  # Ctrl-C or SIGTERM inside the recording: stop
                    raise stop from None
                _cannot_record(v, e)
                frozen, step_fn = False, render_loss_backward
                for x in leaves.values():  # what the failed recording may have left
                    dr.clear_grad(x)
                step_fn(*args)
            # the chain rule through the family's map: the leaves' gradients pulled back
            dr.backward(sum(dr.sum(values[k] * dr.grad(x), axis=None) for k, x in leaves.items()))
        opt.step()
        if average_from is not None and step >= average_from:
            for n in fam.params:
                z = np.asarray(opt[n].numpy(), np.float64).reshape(-1)
                sums[n] = sums[n] + z if n in sums else z
            n_sum += 1
    if n_sum:
        free = {n: sums[n] / n_sum for n in fam.params}
    else:
        free = {n: np.asarray(opt[n].numpy(), np.float64).reshape(-1) for n in fam.params}
    set_free({n: typed(z) for n, z in free.items()}, dr)
    train_terms, val_px, plain_terms = [], [], []
    images: list[np.ndarray | None] = []
    for i, v in enumerate(views):
        if not (mask_train[i].any() or mask_val[i].any()):
            images.append(None)
            continue
        a = _render_np(v, v.params, spp=sched.val_spp, seed=_seed(seed, 1, i))
        b = _render_np(v, v.params, spp=sched.val_spp, seed=_seed(seed, 2, i))
        images.append(0.5 * (a + b))
        if mask_train[i].any():
            train_terms.append((masked_loss(v, mask_train[i], a, b), int(mask_train[i].sum())))
        if mask_val[i].any():
            val_px.append(pixel_losses(v, mask_val[i], a, b))
            plain_terms.append((masked_loss(v, mask_val[i], 0.5 * (a + b)), int(mask_val[i].sum())))
    held = np.concatenate(val_px) if val_px else np.zeros(0)
    params = fam.numbers(free)
    return Candidate(
        family=fam.name,
        params=params,
        train_loss=_pooled(train_terms),
        val_loss=float(held.mean()) if held.size else math.nan,
        val_loss_plain=_pooled(plain_terms),
        seconds=time.perf_counter() - start,
        steps=sched.steps,
        complexity=fam.complexity,
        element=fam.element(params),
        val_pixels=held,
        images=images,
        frozen=frozen,
    )


# Integrator types (a view's ``integrator``) whose step Dr.Jit could not record in this
# process (Mitsuba 3.9's direct_projective refuses: "Projective Integrators are not yet
# supported inside of frozen functions"): their fits trace every step (fit_candidate),
# said once per type on stderr.
UNFREEZABLE: set[str] = set()


def _interruption(error: BaseException) -> BaseException | None:
    """The Ctrl-C or SIGTERM (a KeyboardInterrupt, or any exception that is not an
    Exception) that Dr.Jit wrapped in ``error`` when it struck inside a recording, else
    None: a recording that fails for its own reasons is traced instead, an interrupted
    one is not."""
    seen: BaseException | None = error
    while seen is not None:
        if not isinstance(seen, Exception):
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


def _cannot_record(view: inverse.View, error: BaseException) -> None:
    if view.integrator in UNFREEZABLE:
        return
    UNFREEZABLE.add(view.integrator)
    while error.__cause__ is not None:  # Dr.Jit chains the reason under its summary
        error = error.__cause__
    first = str(error).splitlines()[0] if str(error) else type(error).__name__
    print(
        f"images.start_freeze: Dr.Jit cannot record a step of integrator "
        f"{view.integrator!r} ({view.scene_path.name}: {first[:160]}); the start's fits "
        "trace every step instead (slower, the same fit)",
        file=sys.stderr,
    )


# ------------------------------------------------------------------ the choice
# A family with more free scalars is chosen over a simpler one only when its held-out
# loss is lower by more than TIE_TOL (relative) and by more than TIE_SIGMAS standard
# errors of the paired difference (tiles as the independent units), the latter capped
# at TIE_MAX (relative): pick().  The config's defaults (images.start_tie_tol,
# start_tie_sigmas, start_tie_max), which network_start passes.
_IMAGES = cfgmod.Images()
TIE_TOL, TIE_SIGMAS, TIE_MAX = (
    _IMAGES.start_tie_tol,
    _IMAGES.start_tie_sigmas,
    _IMAGES.start_tie_max,
)


def compare(a: Candidate, b: Candidate, unit: np.ndarray | None) -> tuple[float, float]:
    """(a's held-out loss minus b's, the standard error of that difference), the
    difference taken pixel by pixel (the same pixels, the same render seeds) and its
    error from the spread of its sums over ``unit`` (each held-out pixel's tile:
    :func:`units`); None: pixels as the units."""
    d = a.val_pixels - b.val_pixels
    n = d.size
    if n == 0:
        return math.nan, math.nan
    ids = np.arange(n) if unit is None else np.unique(unit, return_inverse=True)[1]
    sums = np.bincount(ids, weights=d)
    k = len(sums)
    se = float(np.std(sums, ddof=1) * math.sqrt(k) / n) if k > 1 else math.inf
    return float(d.mean()), se


def pick(
    candidates: Sequence[Candidate],
    unit: np.ndarray | None = None,
    *,
    tie_tol: float = TIE_TOL,
    sigmas: float = TIE_SIGMAS,
    tie_max: float = TIE_MAX,
) -> tuple[Candidate, dict[str, dict[str, Any]]]:
    """The simplest candidate (fewest free scalars; then the earlier) whose held-out loss
    exceeds the least one's by no more than ``tie_tol`` times it or ``sigmas`` standard
    errors of the paired difference (:func:`compare`, over ``unit``), whichever is
    larger, the latter capped at ``tie_max`` times the least: a more complex family must
    earn its place, and a much worse simple one is never taken.  Returns it and, per family, the
    margin over the best (``above_best``, ``standard_error``, ``tied``)."""
    ok = [c for c in candidates if math.isfinite(c.val_loss)]
    if not ok:
        raise ValueError("no candidate has a finite held-out loss")
    best = min(ok, key=lambda c: c.val_loss)
    margins: dict[str, dict[str, Any]] = {}
    tied = []
    for c in ok:
        diff, se = compare(c, best, unit) if c is not best else (0.0, 0.0)
        within = diff <= max(
            tie_tol * abs(best.val_loss), min(sigmas * se, tie_max * abs(best.val_loss))
        )
        margins[c.family] = {"above_best": diff, "standard_error": se, "tied": bool(within)}
        if within:
            tied.append(c)
    chosen = min(tied, key=lambda c: (c.complexity, list(candidates).index(c)))
    return chosen, margins


@dataclass
class Choice:
    """The chosen start and every candidate (in the order fitted)."""

    family: str
    element: ET.Element
    params: dict[str, Any]
    candidates: list[Candidate]
    margins: dict[str, dict[str, Any]]  # pick()'s, per family
    val_share: float  # the share of the pixels scored (train and held out) held out
    block: int
    tie_tol: float
    sigmas: float
    tie_max: float
    seconds: float
    # catch_up's: per family fitted further its record, and the family picked before
    caught_up: dict[str, dict[str, Any]] = field(default_factory=dict)
    first_pick: str | None = None
    held_pixels: int | None = None  # the held-out pixels the choice scored
    pixels: int | None = None  # ... and those it fitted with them

    @property
    def chosen(self) -> Candidate:
        return next(c for c in self.candidates if c.family == self.family)

    def summary(self) -> dict[str, Any]:
        """JSON-ready (metrics.json, the report): the choice, the rule, every candidate."""
        return {
            "family": self.family,
            "params": self.params,
            "val_loss": self.chosen.val_loss,
            "rule": (
                "the simplest family (fewest free scalars) whose held-out relative MSE "
                "(noise-free estimate) is within max(tie_tol x the least, min(sigmas x the "
                "standard error of the paired difference over tiles, tie_max x the least)) "
                "of the least"
            ),
            "tie_tol": self.tie_tol,
            "sigmas": self.sigmas,
            "tie_max": self.tie_max,
            "split": {
                "val_share": self.val_share,
                "held_out_pixels": self.held_pixels,
                "pixels": self.pixels,
                "block_pixels": self.block,
            },
            "candidates": [
                {**c.summary(), **self.margins.get(c.family, {})} for c in self.candidates
            ],
            "caught_up": self.caught_up,
            **({"first_pick": self.first_pick} if self.first_pick != self.family else {}),
            "seconds": self.seconds,
        }


def warm_start(
    name: str,
    fitted: Mapping[str, Candidate],
    views: Sequence[inverse.View],
    mask_train: Sequence[np.ndarray],
) -> dict[str, Any] | None:
    """The start of family ``name`` from the families already ``fitted`` (its
    :attr:`~neural_brdf.inverse.families.Family.warm` rule over its ``warm_from``:
    ``clearcoat`` from ``principled``, ``roughconductor_aniso`` from ``roughconductor``,
    ``blend`` from ``diffuse`` and ``roughconductor``), so that it starts about as well
    as its simpler families end; None (its own start) for a family without one, or where
    a family it needs is not fitted."""
    fam = family(name)
    if fam.warm is None or any(n not in fitted for n in fam.warm_from):
        return None
    return fam.warm(fitted, views, mask_train)


def fit_warm(
    views: Sequence[inverse.View],
    name: str,
    fitted: Mapping[str, Candidate],
    *,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    **kw: Any,
) -> Candidate:
    """:func:`fit_candidate` of family ``name`` from its warm start (:func:`warm_start`
    from the families ``fitted``; its own start where there is none), with the steps
    behind that start counted (:attr:`Candidate.before`: the most of its sources')."""
    init = warm_start(name, fitted, views, mask_train)
    c = fit_candidate(views, name, mask_train=mask_train, mask_val=mask_val, init=init, **kw)
    if init is None:
        return c
    return dataclasses.replace(c, before=max(fitted[n].total_steps for n in warm_sources(name)))


def fit_further(
    views: Sequence[inverse.View],
    c: Candidate,
    *,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    seed: int,
    schedule: Schedule,
) -> tuple[Candidate, dict[str, Any]]:
    """``c`` fitted ``schedule.steps`` more steps from its parameters
    (:func:`fit_candidate` with ``init``, the same render seeds, so that the held-out
    losses stay paired).  Returns (the continued fit, or ``c`` where that one's held-out
    loss is higher (:func:`no_worse`), with those steps counted behind it; a record:
    ``steps``, ``val_loss_before``, ``val_loss_after``, ``kept``, ``seconds``)."""
    r = fit_candidate(
        views,
        c.family,
        mask_train=mask_train,
        mask_val=mask_val,
        seed=seed,
        schedule=schedule,
        init=c.params,
    )
    r = dataclasses.replace(r, before=c.total_steps)
    ok = no_worse(r.val_loss, c.val_loss)
    kept = r if ok else dataclasses.replace(c, before=c.before + r.steps)
    record = {
        "steps": r.steps,
        "val_loss_before": c.val_loss,
        "val_loss_after": r.val_loss,
        "kept": ok,
        "seconds": r.seconds,
    }
    return kept, record


def behind(c: Candidate, current: Mapping[str, Candidate]) -> list[str]:
    """The families ``c``'s warm start comes from (:func:`warm_sources`) among
    ``current`` that have had fewer steps than ``c`` (:attr:`Candidate.total_steps`): compared with
    ``c`` as they stand, they would be judged on a shorter fit."""
    return [
        n for n in warm_sources(c.family) if n in current and current[n].total_steps < c.total_steps
    ]


def _merged(a: dict[str, Any] | None, b: dict[str, Any]) -> dict[str, Any]:
    """Two :func:`fit_further` records of one family, one after the other, as one."""
    if a is None:
        return b
    return {
        "steps": a["steps"] + b["steps"],
        "val_loss_before": a["val_loss_before"],
        "val_loss_after": b["val_loss_after"] if b["kept"] else a["val_loss_after"],
        "kept": a["kept"] or b["kept"],
        "seconds": a["seconds"] + b["seconds"],
    }


def catch_up(
    views: Sequence[inverse.View],
    cands: Sequence[Candidate],
    *,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    seed: int,
    schedule: Schedule,
    unit: np.ndarray | None = None,
    tie_tol: float = TIE_TOL,
    sigmas: float = TIE_SIGMAS,
    tie_max: float = TIE_MAX,
    progress: Callable[[str, str, dict[str, Any]], None] | None = None,
) -> tuple[Candidate, list[Candidate], dict[str, dict[str, Any]], dict[str, dict[str, Any]], str]:
    """:func:`pick`, and while the family chosen was warm-started from families that had
    fewer steps (:func:`behind`: a ``clearcoat`` from a ``principled`` has had the
    principled's steps and its own), fit those further (:func:`fit_further`, by
    ``schedule``) until they have had as many, and pick again: a family never wins over
    the one it starts from by its longer fit alone.  Returns
    (the candidate chosen, every candidate as it now stands (in ``cands``' order), per
    family fitted further its record, :func:`pick`'s margins, the family picked first).
    ``progress``: called with each family fitted further, the family it caught up
    with, and its record."""
    current = {c.family: c for c in cands}
    done: dict[str, dict[str, Any]] = {}
    first: str | None = None
    while True:
        pool = [current[c.family] for c in cands]
        chosen, margins = pick(pool, unit, tie_tol=tie_tol, sigmas=sigmas, tie_max=tie_max)
        first = first or chosen.family
        # the chosen family's sources alone: catching up the sources of another (the
        # best) would give them steps the chosen one never had, the same bias the other
        # way (a CI copper's principled, caught up with the clearcoat, displaced its
        # roughconductor); a source that ties is simpler than the chosen one, so none does
        todo = behind(chosen, current)
        if not todo or schedule.steps <= 0:
            return chosen, pool, done, margins, first
        for n in todo:
            current[n], r = fit_further(
                views,
                current[n],
                mask_train=mask_train,
                mask_val=mask_val,
                seed=seed,
                schedule=schedule,
            )
            done[n] = _merged(done.get(n), r)
            if progress is not None:
                progress(n, chosen.family, r)


def choose_start(
    views: Sequence[inverse.View],
    families: Sequence[str] = DEFAULT,
    *,
    steps: int | None = None,
    spp: int | None = None,
    seed: int = 0,
    val_share: float = 0.25,
    block: int = 4,
    masks: tuple[Sequence[np.ndarray], Sequence[np.ndarray]] | None = None,
    schedule: Schedule | None = None,
    tie_tol: float = TIE_TOL,
    sigmas: float = TIE_SIGMAS,
    tie_max: float = TIE_MAX,
    catch_up_sources: bool = True,
    progress: Callable[[Candidate], None] | None = None,
    caught: Callable[[str, str, dict[str, Any]], None] | None = None,
) -> Choice:
    """Fit every family of ``families`` (:func:`fit_warm`, in the order of
    :data:`~neural_brdf.inverse.families.FAMILIES`, whatever the order given) to the training
    pixels of a seeded split (:func:`split_pixels` with ``val_share``, ``block``,
    ``seed``; or ``masks`` = (train, held-out) given) and choose by the held-out loss
    (:func:`pick`; with ``catch_up_sources``, :func:`catch_up`: a warm-started family
    chosen is judged against its sources after as many steps).  The
    views are all it looks at: the scenes' own ``<bsdf id="fit">`` plays no part.
    ``progress`` is called with each candidate when it is fitted, ``caught`` as
    :func:`catch_up`'s ``progress``."""
    start = time.perf_counter()
    sched = schedule or Schedule()
    if steps is not None:
        sched = dataclasses.replace(sched, steps=steps)
    if spp is not None:
        sched = dataclasses.replace(sched, spp=spp)
    for name in families:
        family(name)
    if not families:
        raise ValueError("no families to choose from")
    # in the registry's order, whatever the order given: a warm start's sources first
    given = set(families)
    families = [n for n in FAMILIES if n in given]
    if masks is None:
        train, held = split_pixels(views, val_share, seed, block=block)
    else:
        train, held = list(masks[0]), list(masks[1])
    if not any(m.any() for m in held):
        raise ValueError("no held-out pixels: the choice needs a validation split")
    # the split as it is (the run's own, when ``masks`` are given: not ``val_share``)
    n_held = sum(int(m.sum()) for m in held)
    n_all = n_held + sum(int(m.sum()) for m in train)
    out: list[Candidate] = []
    for name in families:
        c = fit_warm(
            views,
            name,
            {c.family: c for c in out},
            mask_train=train,
            mask_val=held,
            seed=seed,
            schedule=sched,
        )
        out.append(c)
        if progress is not None:
            progress(c)
    rule = dict(tie_tol=tie_tol, sigmas=sigmas, tie_max=tie_max)
    done: dict[str, dict[str, Any]] = {}
    if catch_up_sources:
        best, out, done, margins, first = catch_up(
            views,
            out,
            mask_train=train,
            mask_val=held,
            seed=seed,
            schedule=sched,
            unit=units(held, block),
            progress=caught,
            **rule,
        )
    else:
        best, margins = pick(out, units(held, block), **rule)
        first = best.family
    return Choice(
        family=best.family,
        element=best.element,
        params=best.params,
        candidates=out,
        margins=margins,
        val_share=n_held / n_all,
        block=block,
        tie_tol=tie_tol,
        sigmas=sigmas,
        tie_max=tie_max,
        seconds=time.perf_counter() - start,
        held_pixels=n_held,
        pixels=n_all,
        caught_up=done,
        first_pick=first,
    )


# ------------------------------------------------------------------ refining the choice
# The candidates' fits end at images.start_lr_end (0.05) x their rate, about 1-2 % of a
# roughness or a reflectance per Adam step in the logistic's free variable: the jitter the
# family's final parameters keep.  The chosen family's fit continues at a tenth of the
# rate with more samples per pixel, its iterates averaged over the second half of the
# steps (refine(); Schedule.refining).


def no_worse(after: float, before: float) -> bool:
    """Is a continued fit's held-out loss ``after`` to be kept over ``before``: not
    higher, and not NaN or infinite (a fit that diverged) where ``before`` is finite.
    Without held-out pixels both are NaN and nothing prefers the earlier fit."""
    if not math.isfinite(before):
        return math.isnan(before) or math.isfinite(after)
    return math.isfinite(after) and after <= before


def refine(
    views: Sequence[inverse.View],
    chosen: Candidate,
    *,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    seed: int,
    schedule: Schedule,
) -> tuple[Candidate, dict[str, Any]]:
    """Continue ``chosen``'s fit from its parameters by ``schedule``
    (:meth:`Schedule.refining`), the result the mean of the second half's iterates.
    ``chosen``'s held-out loss must come from renders of ``schedule.val_spp`` samples
    and the same ``seed``.  Returns (the candidate kept: the refined one unless its
    held-out loss, scored on the same pixels with the same render seeds, is higher than
    ``chosen``'s, or there is no held-out pixel; a summary for metrics.json)."""
    r = fit_candidate(
        views,
        chosen.family,
        mask_train=mask_train,
        mask_val=mask_val,
        seed=seed,  # the choice's held-out render seeds: the two losses are paired
        schedule=schedule,
        init=chosen.params,
        average_from=schedule.steps // 2,
    )
    before = chosen.val_loss
    # without a split (a family named alone, no held-out pixels: NaN) nothing prefers it
    kept = r if no_worse(r.val_loss, before) else chosen
    summary = {
        "steps": schedule.steps,
        "spp": schedule.spp,
        "lr": schedule.lr,
        "val_loss_before": before,
        "val_loss_after": r.val_loss,
        "kept": kept is r,
        "params_before": chosen.params,
        "params_after": r.params,
        "seconds": r.seconds,
    }
    return kept, summary


def refine_rounds(
    views: Sequence[inverse.View],
    chosen: Candidate,
    *,
    rounds: int,
    gain: float,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    seed: int,
    schedule: Schedule,
) -> tuple[Candidate, dict[str, Any]]:
    """:func:`refine` again from its result while the split says it still gains: a
    further round runs when the last one was kept and cut the held-out loss by more than
    the fraction ``gain`` (``images.start_refine_gain``), at most ``rounds`` in all
    (``images.start_refine_rounds``; 1: :func:`refine` alone).  Every round is scored on
    the same held-out pixels with the same render seeds.  Returns (the candidate kept,
    the summary of :func:`refine` over all rounds: the loss and parameters before the
    first and after the last kept, ``steps`` a round's, the seconds summed, and
    ``rounds``, the held-out loss after each)."""
    current, summaries = chosen, []
    for _ in range(rounds):
        current, r = refine(
            views,
            current,
            mask_train=mask_train,
            mask_val=mask_val,
            seed=seed,
            schedule=schedule,
        )
        summaries.append(r)
        if not (r["kept"] and r["val_loss_after"] < (1.0 - gain) * r["val_loss_before"]):
            break
    first, last = summaries[0], summaries[-1]
    summary = {
        **first,
        "val_loss_after": current.val_loss if current is not chosen else last["val_loss_after"],
        "kept": current is not chosen,
        "params_after": current.params if current is not chosen else last["params_after"],
        "seconds": sum(float(r["seconds"]) for r in summaries),
        "rounds": [float(r["val_loss_after"]) for r in summaries],
    }
    return current, summary


# ------------------------------------------------------------------ the contenders
# A family whose 80 steps stop short of its best can lose the choice to a simpler one
# that has converged on a worse fit (the development set's blue principled under point
# lights: its own family at 1.3 x the roughplastic's held-out loss after 80 steps, at the
# targets' noise after 80 more).  So with images.start_continue_within every family
# within that factor of the least held-out loss fits as many steps again from where it
# stopped, and the choice is made again on the continued losses (contend(); then the
# chosen one is refined as before), unless the chosen start is already at the targets'
# noise (uncontested(); docs/inverse-design.md, "The contenders").


def at_floor(chosen: Candidate, noise: float | None, tie_max: float = TIE_MAX) -> bool:
    """Is ``chosen``'s held-out loss within ``tie_max`` of the targets' own noise
    (``noise``, :func:`~neural_brdf.inverse.fit.target_noise`; None: unknown, so no)?
    That noise is the floor no loss goes below: a start at its floor could not be beaten
    by more than the choice's cap forgives."""
    return noise is not None and chosen.val_loss <= (1.0 + tie_max) * noise


def far_above_floor(chosen: Candidate, noise: float | None, early: float | None) -> bool:
    """Does ``chosen``'s held-out loss exceed the targets' own noise (``noise``; None:
    unknown, taken as 0) by more than ``early`` (``images.poor_start_early_loss``;
    None: never)?  Such a start is poor at once: no family is near the material, and
    fitting the contenders further or refining the chosen one would not bring it near
    (the most the contenders and the refinement took off a first choice on the
    development set was 0.003, the brushed copper under lights; docs/inverse-design.md,
    "A poor start")."""
    return early is not None and chosen.val_loss - (noise or 0.0) > early


def uncontested(
    chosen: Candidate,
    noise: float | None,
    tie_max: float = TIE_MAX,
    early: float | None = None,
) -> str | None:
    """Why no contender is fitted further (:func:`contenders`), or None: ``"at its
    floor"`` (:func:`at_floor`) or ``"far above its floor"``
    (:func:`far_above_floor`, with ``early``)."""
    if at_floor(chosen, noise, tie_max):
        return "at its floor"
    return "far above its floor" if far_above_floor(chosen, noise, early) else None


def contenders(
    cands: Sequence[Candidate],
    chosen: Candidate,
    within: float | None,
    *,
    most: int | None = None,
    noise: float | None = None,
    tie_max: float = TIE_MAX,
    early: float | None = None,
) -> list[Candidate]:
    """The candidates fitted further before the choice is made again (in the order
    fitted): with ``within``, every one whose held-out loss is at most ``within`` times
    the least, ``chosen`` among them; with ``most``, ``chosen`` and the others of least
    held-out loss, ``most`` in all; none when ``within`` is None, when there is a single
    candidate, or when ``chosen`` is :func:`uncontested` (``early``: its limit above the
    floor)."""
    finite = [c.val_loss for c in cands if math.isfinite(c.val_loss)]
    if within is None or len(cands) < 2 or not finite:
        return []
    if uncontested(chosen, noise, tie_max, early):
        return []
    limit = within * min(finite)
    near = [
        c for c in cands if c is not chosen and math.isfinite(c.val_loss) and c.val_loss <= limit
    ]
    if most is not None:  # stable: of equal losses, the one fitted first
        near = sorted(near, key=lambda c: c.val_loss)[: most - 1]
    return [c for c in cands if c is chosen or any(c is n for n in near)]


def contend(
    views: Sequence[inverse.View],
    cands: Sequence[Candidate],
    chosen: Candidate,
    *,
    within: float | None,
    most: int | None = None,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    seed: int,
    schedule: Schedule,
    unit: np.ndarray | None = None,
    tie_tol: float = TIE_TOL,
    sigmas: float = TIE_SIGMAS,
    tie_max: float = TIE_MAX,
    noise: float | None = None,
    early: float | None = None,
    progress: Callable[[str, dict[str, Any]], None] | None = None,
) -> tuple[Candidate, list[Candidate], dict[str, dict[str, Any]], dict[str, dict[str, Any]]]:
    """Fit each of the :func:`contenders` ``schedule.steps`` more steps from its
    parameters (:func:`fit_further`: the candidates' own schedule and render seeds, the
    continued fit kept unless its held-out loss is higher), and choose again among every
    candidate (:func:`pick`, the same rule).  Returns (the candidate chosen, every
    candidate as it now stands, per family continued its summary, :func:`pick`'s margins
    of the new choice; with no contender: ``chosen``, ``cands``, none, none).
    ``progress``: called with each family and its summary when it is continued."""
    todo = contenders(cands, chosen, within, most=most, noise=noise, tie_max=tie_max, early=early)
    if not todo:
        return chosen, list(cands), {}, {}
    current = {c.family: c for c in cands}
    done: dict[str, dict[str, Any]] = {}
    for c in todo:
        current[c.family], done[c.family] = fit_further(
            views, c, mask_train=mask_train, mask_val=mask_val, seed=seed, schedule=schedule
        )
        if progress is not None:
            progress(c.family, done[c.family])
    pool = [current[c.family] for c in cands]
    picked, margins = pick(pool, unit, tie_tol=tie_tol, sigmas=sigmas, tie_max=tie_max)
    return picked, pool, done, margins


# ------------------------------------------------------------------ an inconclusive split
# The run's split holds a fifth of the tiles out.  A lobe whose highlights fall on a few
# tiles may have one or two of them there, and the split then ties the family that has
# the lobe with a simpler one by its standard error alone: a development torus under a
# grey clear coat scored clearcoat's gain over principled at 0.000059 on the split, a tie,
# and at 0.000073 +- 0.000026 over every tile once each was held out in turn.  So
# a choice tied that way (inconclusive()) is checked: the two families are fitted again
# on images.start_cross_folds folds of the training tiles, each held out in turn
# (fold_masks()), and chosen by pick() over the split's tiles and every fold's together
# (cross_check(); docs/inverse-design.md, "An inconclusive split").  The folds leave the run's
# held-out pixels out, as the start's fits do.


def inconclusive(
    cands: Sequence[Candidate], chosen: Candidate, *, tie_tol: float = TIE_TOL
) -> Candidate | None:
    """The candidate of least held-out loss, when it has more free scalars than
    ``chosen`` and its loss is lower than ``chosen``'s by more than ``tie_tol`` times
    it, so that :func:`pick` tied the two by the standard error of their difference
    alone; else None."""
    ok = [c for c in cands if math.isfinite(c.val_loss)]
    if not ok or not math.isfinite(chosen.val_loss):
        return None
    best = min(ok, key=lambda c: c.val_loss)
    if best is chosen or best.complexity <= chosen.complexity:
        return None
    diff, _ = compare(chosen, best, None)
    return best if diff > tie_tol * abs(best.val_loss) else None


def fold_masks(
    train: Sequence[np.ndarray], block: int, seed: int, folds: int
) -> list[list[np.ndarray]]:
    """``folds`` held-out masks (each a list of (H, W) bool per view) that cut the tiles
    (:func:`tiles`) of the training pixels ``train`` into parts as equal as they can be,
    dealt at random (seeded by ``seed`` and the view's index): disjoint, and together
    ``train``."""
    out = [[np.zeros_like(m) for m in train] for _ in range(folds)]
    for i, m in enumerate(train):
        t = tiles(m.shape, block)
        ids = np.random.default_rng([seed, 29, i, 2]).permutation(np.unique(t[m]))
        for k, part in enumerate(np.array_split(ids, folds)):
            out[k][i] = m & np.isin(t, part)
    return out


def cross_check(
    views: Sequence[inverse.View],
    simple: Candidate,
    rival: Candidate,
    *,
    mask_train: Sequence[np.ndarray],
    mask_val: Sequence[np.ndarray],
    folds: int,
    block: int,
    seed: int,
    schedule: Schedule,
    tie_tol: float = TIE_TOL,
    sigmas: float = TIE_SIGMAS,
    tie_max: float = TIE_MAX,
) -> tuple[str, dict[str, Any]]:
    """Choose between ``simple`` and ``rival`` (fitted on ``mask_train``, scored on
    ``mask_val`` with ``seed``'s render seeds) over more held-out tiles: each of
    ``folds`` folds of the training tiles (:func:`fold_masks`) is held out in turn, the
    two families (with the families their warm starts come from, :func:`warm_sources`)
    are fitted on the rest by ``schedule`` as :func:`choose_start` fits them, and
    :func:`pick` (the same rule) chooses over the ``mask_val`` tiles and every fold's
    together.  Where one of the two is the other's warm start (``simple`` the
    ``principled`` of a ``clearcoat``) and has had fewer steps (:func:`behind`), it is
    fitted further (:func:`fit_further`), on the split and in each fold, until it has had
    as many.  Returns (the family chosen, a summary for metrics.json)."""
    start = time.perf_counter()
    pair = (simple, rival)
    names = [c.family for c in pair]
    needed = {n for c in names for n in (*warm_sources(c), c)}
    order = [n for n in FAMILIES if n in needed]  # a warm start's families before it

    def level(
        cur: dict[str, Candidate], train: Sequence[np.ndarray], held: Sequence[np.ndarray]
    ) -> list[str]:
        # a family the other one's warm start comes from is fitted further until it has
        # had as many steps: the check does not credit the later family with the longer
        # fit (the test set's isotropic chrome took the anisotropic conductor for it)
        out: list[str] = []
        for b in names:
            while schedule.steps > 0 and (todo := behind(cur[b], cur)):
                for a in todo:
                    cur[a], _ = fit_further(
                        views, cur[a], mask_train=train, mask_val=held, seed=seed, schedule=schedule
                    )
                    out.append(a)
        return out

    split = {c.family: c for c in pair}  # on the split: as fitted, or fitted further
    continued = level(split, mask_train, mask_val)
    pixels = {n: [split[n].val_pixels] for n in names}
    unit = [units(mask_val, block)]
    fitted_folds = 0
    for held in fold_masks(mask_train, block, seed, folds):
        train = [a & ~b for a, b in zip(mask_train, held, strict=True)]
        if not any(m.any() for m in held) or not any(m.any() for m in train):
            continue
        fitted: dict[str, Candidate] = {}
        for name in order:
            fitted[name] = fit_warm(
                views, name, fitted, mask_train=train, mask_val=held, seed=seed, schedule=schedule
            )
        cur = {n: fitted[n] for n in names}
        level(cur, train, held)
        for n in names:
            pixels[n].append(cur[n].val_pixels)
        unit.append(units(held, block))
        fitted_folds += 1
    terms = {n: np.concatenate(pixels[n]) for n in names}
    pooled = [
        dataclasses.replace(c, val_pixels=terms[c.family], val_loss=float(terms[c.family].mean()))
        for c in pair
    ]
    every = np.concatenate(unit)
    won, margins = pick(pooled, every, tie_tol=tie_tol, sigmas=sigmas, tie_max=tie_max)
    gain, se = compare(pooled[0], pooled[1], every)  # simple's loss minus the rival's
    summary = {
        "folds": folds,
        "folds_fitted": fitted_folds,
        "families": names,
        "continued": sorted(set(continued), key=names.index),
        "tiles": int(np.unique(every).size),
        "val_loss": {c.family: c.val_loss for c in pooled},
        "rival_gain": gain,
        "standard_error": se,
        "margins": margins,
        "chosen": won.family,
        "seconds": time.perf_counter() - start,
    }
    return won.family, summary


# ------------------------------------------------------------------ the run's start
def candidates(cfg: cfgmod.Config) -> tuple[list[str], dict[str, str]]:
    """The families an images fit of ``cfg`` fits (``images.start``: every one of
    ``images.start_families`` for ``auto``, else that family), and those left out, with
    why: an anisotropic family when ``model.encoding`` is isotropic (the network could
    not represent it; config.py refuses one named alone)."""
    from neural_brdf import encodings

    images = cfg.images
    names = list(images.start_families) if images.start == "auto" else [images.start]
    left: dict[str, str] = {}
    if not encodings.get(cfg.model.encoding).anisotropic:
        for n in names:
            if family(n).anisotropic:
                left[n] = (
                    f"model.encoding {cfg.model.encoding!r} is isotropic and cannot represent "
                    "it (model.encoding: anisotropic can)"
                )
    return [n for n in names if n not in left], left


def model_for_start(cfg: cfgmod.Config, family: str) -> cfgmod.Config:
    """``cfg`` as the network of a start of ``family`` is trained; ``cfg`` itself when
    nothing changes.

    - After an anisotropic family (:attr:`~neural_brdf.inverse.families.Family.anisotropic`) with
      ``images.anisotropic_grid: half_disc``: the grid over the half vector's disc
      (``model.grid.coords: half_disc``, where a brushed lobe varies; the grid over
      (theta_h, theta_d) cannot follow it), when the model has a grid and its encoding
      offers that grid (docs/inverse-design.md, "The grid after an anisotropic start").
    - After any other family with ``images.isotropic_encoding: isotropic``: the
      isotropic encoding, when ``model.encoding`` is an anisotropic reciprocal one and the
      isotropic encoding offers the model's grid.  The validation split preferred a
      family without the half vector's azimuth, so the network is not given one to learn
      from views that see few of its values (docs/inverse-design.md, "The encoding after an
      isotropic start")."""
    from neural_brdf import encodings

    model = cfg.model
    spec = encodings.get(model.encoding)
    d: dict[str, Any] | None = None
    known = FAMILIES.get(family)  # (a resumed run's family may since have gone)
    if known is not None and known.anisotropic:
        if (
            cfg.images.anisotropic_grid == "half_disc"
            and model.grid.size
            and model.grid.coords != "half_disc"
            and "half_disc" in spec.grid_axes
        ):
            d = cfg.model_dump()
            d["model"]["grid"]["coords"] = "half_disc"
            source = "images.anisotropic_grid"
    elif (
        cfg.images.isotropic_encoding == "isotropic"
        and spec.anisotropic
        and spec.reciprocal
        and (not model.grid.size or model.grid.coords in encodings.ISOTROPIC.grid_axes)
    ):
        d = cfg.model_dump()
        d["model"]["encoding"] = encodings.ISOTROPIC.name
        source = "images.isotropic_encoding"
    return cfg if d is None else cfgmod.from_dict(d, source=source)


def run_masks(views: Sequence[inverse.View]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(train, held-out) masks of the run's own validation split (:func:`~neural_brdf.
    inverse.fit.split_views`) within the object's pixels (``view.object``, else
    :func:`object_mask`): the start is fitted on the pixels the network stage fits and
    chosen on those it is scored on."""
    train, held = [], []
    for v in views:
        obj = v.object if v.object is not None else object_mask(v)
        val = v.validation_mask()
        val = np.zeros_like(obj) if val is None else val
        train.append(obj & ~val)
        held.append(obj & val)
    return train, held


def network_start(
    cfg: cfgmod.Config,
    views: Sequence[inverse.View],
    init_dir: Path,
    *,
    report: Callable[[str], None] | None = None,
) -> tuple[dict[str, Any], dict[str, Any], cfgmod.Config]:
    """The start of an images fit whose ``images.start`` is ``auto`` or a family: the
    candidates (:func:`candidates`) fitted on the run's training pixels, the one the
    validation split prefers (:func:`choose_start`; a family named alone is taken as
    it is), distilled into the network (:func:`distill`, ``images.start_train_steps``
    steps in ``init_dir``; a poor start's: ``images.poor_start_train_steps``).  Returns
    (the network's state_dict, figures: the distillation's, with ``start``, every
    candidate and the choice, the config the network is trained with: ``cfg`` after
    :func:`model_for_start`).  ``report``: called with a line per candidate fitted and
    one for the choice."""
    images = cfg.images
    names, left = candidates(cfg)
    if not names:
        raise InputError(
            "images.start_families: every family is left out: "
            + "; ".join(f"{k}: {why}" for k, why in left.items())
        )
    train, held = run_masks(views)
    sched = Schedule.of(images)
    early = False  # poor at once (far_above_floor): no contenders, no refinement

    def said(c: Candidate) -> None:
        if report is not None:
            held = (
                f"held-out loss {c.val_loss:.4g}"
                if math.isfinite(c.val_loss)
                else "no held-out pixels to score it on"
            )
            report(
                f"start {c.family}: {held} (training pixels {c.train_loss:.4g}), {c.seconds:.1f} s"
            )

    def caught(name: str, by: str, r: dict[str, Any]) -> None:
        if report is not None:
            report(
                f"caught up {name} with {by}, which started from it: {r['steps']} steps "
                f"more, held-out loss {r['val_loss_after']:.4g} against "
                f"{r['val_loss_before']:.4g} ({'kept' if r['kept'] else 'not kept'}), "
                f"{r['seconds']:.1f} s"
            )

    if images.start == "auto":
        if not any(m.any() for m in held):
            raise InputError(
                "images.start: auto chooses by the validation split, and it holds no pixel "
                "of the object; set images.validation_pixels or images.validation_views"
            )
        choice = choose_start(
            views,
            names,
            seed=cfg.train.seed,
            block=images.validation_block,
            masks=(train, held),
            schedule=sched,
            tie_tol=images.start_tie_tol,
            sigmas=images.start_tie_sigmas,
            tie_max=images.start_tie_max,
            catch_up_sources=images.start_catch_up,
            progress=said,
            caught=caught,
        )
        element, summary = choice.element, choice.summary()
        chosen, cands = choice.chosen, choice.candidates
    else:
        c = fit_candidate(
            views,
            names[0],
            mask_train=train,
            mask_val=held,
            seed=cfg.train.seed,
            schedule=sched,
        )
        said(c)
        element, chosen, cands = c.element, c, [c]
        summary = {
            "family": c.family,
            "params": c.params,
            "val_loss": c.val_loss,
            "rule": "images.start names the family",
            "candidates": [c.summary()],
            "seconds": c.seconds,
        }
    noise = inverse.target_noise(list(views))  # the floor (images.poor_start_loss's too)
    if images.start == "auto":

        def continued(name: str, r: dict[str, Any]) -> None:
            if report is not None:
                report(
                    f"continued {name}: held-out loss {r['val_loss_after']:.4g} against "
                    f"{r['val_loss_before']:.4g} ({'kept' if r['kept'] else 'not kept'}), "
                    f"{r['seconds']:.1f} s"
                )

        first = chosen
        chosen, pool, done, margins = contend(
            views,
            cands,
            chosen,
            within=images.start_continue_within,
            most=images.start_continue_max,
            mask_train=train,
            mask_val=held,
            seed=cfg.train.seed,
            schedule=sched,
            unit=units(held, images.validation_block),
            tie_tol=images.start_tie_tol,
            sigmas=images.start_tie_sigmas,
            tie_max=images.start_tie_max,
            noise=noise,
            early=images.early_poor_loss,
            progress=continued,
        )
        summary["continue_within"] = images.start_continue_within
        summary["continue_max"] = images.start_continue_max
        summary["early_loss"] = images.early_poor_loss
        # why no contender was fitted further: the chosen start at its floor, or so far
        # above it that it is poor at once (nor is it refined)
        summary["uncontested"] = uncontested(
            first, noise, images.start_tie_max, images.early_poor_loss
        )
        # (a noise estimate so high that the start is also at its floor: not poor at once)
        early = summary["uncontested"] == "far above its floor"
        if early and report is not None:
            report(
                f"start {first.family}: held-out loss {first.val_loss - (noise or 0.0):.2g} "
                f"above the targets' noise > images.poor_start_early_loss "
                f"{images.poor_start_early_loss:g}: poor at once, no contender fitted "
                "further, not refined"
            )
        rival = (
            inconclusive(pool, chosen, tie_tol=images.start_tie_tol)
            if images.start_cross_folds and not early
            else None
        )
        if rival is not None:  # the split tied them by its standard error alone
            fitted = {c.family: c for c in cands}  # before the contenders: as the folds fit them
            won, check = cross_check(
                views,
                fitted[chosen.family],
                fitted[rival.family],
                mask_train=train,
                mask_val=held,
                folds=images.start_cross_folds,
                block=images.validation_block,
                seed=cfg.train.seed,
                schedule=sched,
                tie_tol=images.start_tie_tol,
                sigmas=images.start_tie_sigmas,
                tie_max=images.start_tie_max,
            )
            summary["cross_check"] = check
            summary["seconds"] = float(summary["seconds"]) + float(check["seconds"])
            if report is not None:
                report(
                    f"cross-check {rival.family} against {chosen.family}, the split's tiles "
                    f"and {check['folds']} folds of the training tiles held out in turn: "
                    f"held-out loss lower by {check['rival_gain']:.2g} +- "
                    f"{check['standard_error']:.2g}; {won} chosen, {check['seconds']:.1f} s"
                )
            if won == rival.family:
                chosen = rival
        for c in summary["candidates"]:  # each contender's continued loss beside its first
            r = done.get(c["family"])
            if r is not None:
                c["continued_val_loss"] = r["val_loss_after"] if r["kept"] else c["val_loss"]
                c["continue_seconds"] = r["seconds"]
            if c["family"] in margins:
                c["continued_margin"] = margins[c["family"]]
        if chosen.family != first.family:
            summary["first_choice"] = first.family
        element = chosen.element
        summary["family"] = chosen.family
        summary["params"] = chosen.params
        summary["val_loss"] = chosen.val_loss
        summary["seconds"] = float(summary["seconds"]) + sum(
            float(r["seconds"]) for r in done.values()
        )
    if images.start_refine_steps > 0 and not early:
        kept, summary["refine"] = refine_rounds(
            views,
            chosen,
            rounds=images.start_refine_rounds,
            gain=images.start_refine_gain,
            mask_train=train,
            mask_val=held,
            seed=cfg.train.seed,
            schedule=Schedule.refining(images),
        )
        r = summary["refine"]
        if report is not None:
            report(
                f"refined {chosen.family}: held-out loss {r['val_loss_after']:.4g} against "
                f"{r['val_loss_before']:.4g} ({'kept' if r['kept'] else 'not kept'}), "
                f"{r['seconds']:.1f} s"
            )
        element = kept.element
        summary["params"] = kept.params
        summary["val_loss"] = kept.val_loss
        summary["seconds"] = float(summary["seconds"]) + float(r["seconds"])
    summary["left_out"] = left
    if report is not None:
        shown = ", ".join(f"{k} {_short(v)}" for k, v in summary["params"].items())
        report(f"start: {summary['family']} ({shown})")
    moved = model_for_start(cfg, str(summary["family"]))
    summary["grid_coords"] = moved.model.grid.coords  # the network's, as distilled
    summary["encoding"] = moved.model.encoding
    summary["encoding_moved"] = moved.model.encoding != cfg.model.encoding
    if report is not None and moved.model.grid.coords != cfg.model.grid.coords:
        report(
            "grid: over the half vector's disc after an anisotropic start (images.anisotropic_grid)"
        )
    if report is not None and summary["encoding_moved"]:
        report(
            f"encoding: {moved.model.encoding} after an isotropic start (images.isotropic_encoding)"
        )
    cfg = moved
    # the verdict the image stage takes (inverse.fit.poor_start), made before distilling
    poor = inverse.is_poor(summary.get("val_loss"), images.poor_start_loss, noise)
    steps = images.start_train_steps
    if poor and images.poor_start_train_steps is not None:
        steps = images.poor_start_train_steps
    state, info = distill(cfg, element, init_dir, steps, poor=poor)
    info["start"] = summary
    info["seconds"] = float(info["seconds"]) + float(summary["seconds"])
    return state, info, cfg


def _short(v: Any) -> str:
    if isinstance(v, (list, tuple)):
        return "(" + ", ".join(f"{float(x):.3g}" for x in v) + ")"
    return f"{float(v):.3g}" if isinstance(v, (int, float)) else str(v)


# ------------------------------------------------------------------ the teacher
def teacher_xml(element: ET.Element) -> str:
    """``element`` as a standalone Mitsuba 3 XML file (``<bsdf version="3.0.0">``, no
    id): the ``target: {mitsuba: FILE.xml}`` teacher (:class:`neural_brdf.measured.
    mitsuba.MitsubaTarget`)."""
    el = copy.deepcopy(element)
    el.attrib.pop("id", None)
    root = ET.Element("bsdf", {"version": "3.0.0", **el.attrib})
    root.extend(list(el))
    ET.indent(root, space="    ")
    return (
        '<?xml version="1.0" encoding="utf-8"?>\n'
        "<!-- an images fit's start (neural_brdf.inverse.starts) -->\n"
        + ET.tostring(root, encoding="unicode")
        + "\n"
    )


def distill(
    cfg: cfgmod.Config, element: ET.Element, run_dir: Path, steps: int, *, poor: bool = False
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The network of ``cfg.model`` trained on BRDF samples of ``element`` (sample-based
    training, :func:`neural_brdf.train.loop.train`, ``steps`` steps, on one torch
    thread, at a ``poor`` start's rate when it is one: :func:`neural_brdf.inverse.views.
    start_training`) in the run folder ``run_dir`` (an images fit's ``init/``), whose
    :data:`TEACHER_XML` holds the teacher (:func:`teacher_xml`) and whose config's
    target is ``{mitsuba: that file}``.  Returns (the network's state_dict, figures),
    as :func:`neural_brdf.inverse.fit.ggx_initial_state` does."""
    from neural_brdf import runfolder
    from neural_brdf.fileio import atomic_write
    from neural_brdf.measured.mitsuba import MitsubaTarget
    from neural_brdf.train import loop
    from neural_brdf.train.session import signal_name

    run_dir = Path(run_dir)
    xml = (run_dir / TEACHER_XML).absolute()
    variant = inverse.variant_name(cfg)
    icfg = inverse.distillation_config(
        cfg,
        {"mitsuba": str(xml), "variant": variant},
        f"{cfg.name}: {element.get('type')} start, network",
        inverse.start_training(cfg, steps, poor=poor),
        source="images start",
    )
    # the folder becomes a run (its marker) before the teacher is written into it: a
    # folder holding a file no run wrote is refused (neural_brdf.runfolder)
    folder = runfolder.Folder.open(run_dir, resume=False, overwrite=True)
    folder.start(icfg.to_yaml())
    atomic_write(xml, teacher_xml(element))
    teacher = MitsubaTarget(xml, variant=variant, key="images start")
    try:
        raw, info = loop.train(icfg, run_dir, target=teacher, folder=folder)
    except Interrupted as e:  # init/ckpt.pt is not resumed: the fit's --resume starts again
        stopped = Interrupted(
            f"interrupted during the start's distillation ({signal_name(e.signum)}); "
            "--resume chooses the start again (the image stage has no checkpoint yet)"
        )
        stopped.signum = e.signum
        raise stopped from None
    return raw.state_dict(), {
        "target": info["target"],
        "teacher": str(xml),
        "steps": steps,
        "lr": icfg.train.lr,
        "seconds": info["train_seconds"],
        "raw_val_rel_rmse": info["raw_val_rel_rmse"],
    }
