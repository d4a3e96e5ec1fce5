"""Fit a :class:`~neural_brdf.train.textured_model.TexturedBRDF` to a textured teacher.

    from neural_brdf.measured.textured import TexturedMitsubaTarget
    from neural_brdf.train.textured_loop import train_textured
    from neural_brdf.train.textured_model import normalized_textured, to_onnx_bytes_textured

    model, figures = train_textured(TexturedMitsubaTarget(xml), lobes=4, resolution=32)
    model, tables = normalized_textured(model)   # each lobe's albedo bounded: f's too
    onnx_bytes = to_onnx_bytes_textured(model)

Data.  A teacher's calls (Mitsuba) are slow next to a step, so a pool of ``pool`` pairs
is drawn (once, or every ``fresh_every`` steps: :class:`PairPool`) and batches are drawn
from it with replacement: uv uniform in [0, 1)^2,
wi uniform on the hemisphere (as validation draws it: on the development principled the
grazing pairs carried 98 % of the squared error, and a cosine-distributed wi, used before,
left them rare in training: 16 % held-out error against 9.4 % with uniform wi), wo uniform
on the hemisphere for half the pool and from the teacher's own sampler
``teacher.sample(wi, uv, u)`` for the other half (a failed sample is replaced by a
uniform one), and the target ``teacher.eval(wi, wo, uv)``.  A ``data.peak`` share (0.1)
of the pool's pairs, taken from the uniform half, is drawn uniform in the encoding's
(u_h, theta_d) instead (:func:`pairs`), as homogeneous training draws its peak pairs.

Loss and schedule are the project's (:mod:`neural_brdf.train.loop`): ``log_l2`` with the
peak weight and cap (:func:`~neural_brdf.train.loop.loss_fn`), Adam with linear warm-up
then cosine decay (:func:`~neural_brdf.train.loop.learning_rate`).  Learning rates:
``lr`` for the lobes' MLPs, ``lr`` x the lobes' ``model.grid.lr_scale`` (10) for their
learned feature grids (as the project's loop), and ``lr`` x ``field_lr_scale`` (10) for
the weight field's logits.  The field is a table like the grids: each texel's logits see
only the pairs in its footprint, about 4/R^2 of a batch, so they get a grid's rate.

Accuracy: the relative RMSE of f cos(theta_o) against the teacher
(:func:`~neural_brdf.train.loop.rel_rmse`) on ``val_pairs`` held-out pairs at random uv,
wi uniform on the hemisphere, wo half uniform and half from the teacher's sampler (the
project's validation draws wo from the target's sampler: :func:`neural_brdf.train.data.
importance_pairs`).  It is measured before training (``init_val_rel_rmse``) and after.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from analytic import frame
from neural_brdf import config as cfgmod
from neural_brdf.runfolder import Folder
from neural_brdf.train.data import peak_pairs
from neural_brdf.train.ggx_heads import (
    alpha_from_teacher,
    analytic_count,
    with_head_envelope,
    with_heads,
)
from neural_brdf.train.loop import learning_rate, loss_fn, rel_rmse
from neural_brdf.train.model import RawBRDF, grid_lr_scales, lr_scale
from neural_brdf.train.session import TEXTURED_MUST_MATCH, Session
from neural_brdf.train.textured_model import TexturedBRDF, WeightField, lobe_envelope, raw_of

PEAK_SHARE = cfgmod.Data().peak  # the training pools' share of peak pairs (pairs())
FIELD_LR_SCALE = 10.0  # the weight field's logits: lr x this (module doc)
# pairs drawn from the teacher once: on a 16 x 16 roughplastic (K = 4, R = 16, 600
# steps of 2048) 131072 gave a held-out error of 7.1 %, 32768 stalled at 24 % (overfitted)
POOL = 131072
VAL_PAIRS = 16384  # held-out pairs
CHOOSE_SEED = 202  # several starts: the choice's own VAL_PAIRS pairs draw from seed + this
CHANNELS = {"scalar": 1, "rgb": 3}  # texture.weights: one weight per lobe, or per RGB channel
COLORS = {"rgb": 3, "grey": 1}  # texture.lobe_color: a lobe's outputs (RawBRDF.colors)


def pairs(
    teacher: Any,
    n: int,
    rng: np.random.Generator,
    *,
    cosine_wi: bool = False,
    peak: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """n pairs (wi, wo, uv, f) as float32 tensors: uv uniform, wi cosine-distributed
    (``cosine_wi``) or uniform, wo uniform for the first half and from the teacher's
    sampler for the second (failed samples: uniform).  ``peak``: the share of the first
    half replaced by pairs uniform in the encoding's (u_h, theta_d)
    (:func:`neural_brdf.train.data.peak_pairs`, ``data.peak`` for training; those below
    the horizon are kept as drawn): without them the corner wi = wo = the normal went
    untrained, and a textured roughplastic read 26 times its teacher there."""
    uv = rng.random((n, 2))
    u_wi = torch.from_numpy(rng.random((n, 2)))
    wi = (
        frame.square_to_cosine_hemisphere(u_wi)
        if cosine_wi
        else frame.square_to_uniform_hemisphere(u_wi)
    ).numpy()
    wo = frame.square_to_uniform_hemisphere(torch.from_numpy(rng.random((n, 2)))).numpy()
    half = n // 2
    n_peak = min(int(round(n * peak)), half)
    if n_peak:
        p_wi, p_wo = (x.numpy() for x in peak_pairs(torch.from_numpy(rng.random((n_peak, 4)))))
        above = ((p_wi[:, 2] > 0) & (p_wo[:, 2] > 0))[:, None]
        wi[:n_peak] = np.where(
            above, p_wi / np.linalg.norm(p_wi, axis=1, keepdims=True), wi[:n_peak]
        )
        wo[:n_peak] = np.where(
            above, p_wo / np.linalg.norm(p_wo, axis=1, keepdims=True), wo[:n_peak]
        )
    sampled = np.asarray(teacher.sample(wi[half:], uv[half:], rng.random((n - half, 2))))
    good = sampled[:, 2] > 0
    wo[half:][good] = sampled[good]
    f = np.asarray(teacher.eval(wi, wo, uv), dtype=np.float64)
    f = np.where(np.isfinite(f), f, 0.0)
    a, b, c, t = (torch.from_numpy(np.ascontiguousarray(x)).float() for x in (wi, wo, uv, f))
    return a, b, c, t


class PairPool:
    """The training pairs: ``size`` pairs drawn by :func:`pairs`, and with ``fresh_every``
    steps drawn again (``texture.fresh_every``; None: one pool for the whole run).

    Draw c (steps c x fresh_every onwards) comes from ``numpy.random.default_rng([seed,
    c])``, draw 0 from ``default_rng(seed)`` (the pool a run without fresh pairs draws), so
    a resumed run, and each of several starts, sees the same pairs at the same step.
    Why: a field of R x R texels sees a fixed pool's pairs over and over, and a finer
    field fewer of them per texel; on the development principled (R = 64 and 128, a
    pool of 2M pairs) the held-out error fell when the pool grew, and the teacher's calls
    cost about 0.6 s per million pairs against about 14 ms per step of 8192."""

    def __init__(
        self,
        teacher: Any,
        size: int,
        seed: int,
        fresh_every: int | None = None,
        peak: float = PEAK_SHARE,
    ):
        if fresh_every is not None and fresh_every < 1:
            raise ValueError(f"PairPool: fresh_every >= 1 or None, got {fresh_every}")
        self.teacher, self.size, self.seed, self.fresh_every = teacher, size, seed, fresh_every
        self.peak = peak
        self.draw = -1
        self.draws = 0  # how many times the teacher was asked (figures)
        self.seconds = 0.0
        self.pairs: tuple[torch.Tensor, ...] = ()
        self.at(0)

    def at(self, step: int) -> tuple[torch.Tensor, ...]:
        """The pool in use at ``step`` (drawn now if it is a new one)."""
        draw = 0 if self.fresh_every is None else step // self.fresh_every
        if draw != self.draw:
            t0 = time.perf_counter()
            rng = np.random.default_rng(self.seed if draw == 0 else [self.seed, draw])
            self.pairs = ()  # free the old pool before the new one is drawn
            self.pairs = pairs(self.teacher, self.size, rng, peak=self.peak)
            self.draw = draw
            self.draws += 1
            self.seconds += time.perf_counter() - t0
        return self.pairs


def _model_and_optimizer(
    m: cfgmod.Model,
    lobes: int,
    resolution: int,
    pool_f: torch.Tensor,
    lr: float,
    field_lr_scale: float,
    channels: int = 1,
    shared: bool = False,
    latent: int = 0,
    latent_init: torch.Tensor | None = None,
    levels: int = 1,
    colors: int = 3,
    analytic: str = "none",
) -> tuple[TexturedBRDF, torch.optim.Adam]:
    """K lobes ``RawBRDF.from_config(m)`` and an R x R weight field of ``channels`` (1:
    one weight per lobe, 3: one per lobe and RGB channel) sets of weights (from torch's
    global generator: the caller seeds it), and Adam with the learning-rate groups of
    the module doc (each group's ``lr_scale``).  ``shared``: one network with K heads
    instead of K networks (``texture.lobe_network``), its heads' weights drawn small and
    random so that they start apart.  ``latent`` 1: the lobes take the field's latent s(uv)
    as one more input (``texture.latent``, docs/model.md "Conditioned lobes"), its
    logits started at ``latent_init``.  ``colors`` 1: grey lobes (``texture.lobe_color``),
    coloured by the field's per-channel weights.  ``analytic`` "ggx": two analytic GGX
    heads beside the shared network (``texture.analytic_heads``, train/ggx_heads.py), their
    alpha one more latent column of the field, started with ``latent_init``'s last column
    (``latent_init`` then holds the lobes' latent and alpha's start side by side)."""
    # the initial f is sum_k z_k init, and the weights sum to about K / (K + 1) at the start
    init = float(pool_f.median().clamp(1e-3, 10.0)) * (lobes + 1) / lobes
    nets: list[torch.nn.Module] = list(
        lobe_networks(m, lobes, shared, init_value=init, latent=latent, colors=colors)
    )
    if analytic != "none":
        if len(nets) != 1:
            raise ValueError("analytic heads sit beside one shared lobe network")
        nets = [with_heads(nets[0], analytic)]
    extra = analytic_count(nets[0])
    field = WeightField(
        resolution, lobes + extra, channels=channels, latent=latent + bool(extra), levels=levels
    )
    if field.latent_logits is not None and latent_init is not None:
        with torch.no_grad():
            field.latent_logits.copy_(latent_init)
    model = TexturedBRDF(nets, field)
    opt = torch.optim.Adam(parameter_groups(model, m, field_lr_scale), lr=lr, fused=True)
    return model, opt


def parameter_groups(
    model: TexturedBRDF, m: cfgmod.Model, field_lr_scale: float = FIELD_LR_SCALE
) -> list[dict[str, Any]]:
    """Adam's parameter groups of a textured model (module doc), each with its
    ``lr_scale``: the field's logits at ``field_lr_scale``, the lobes' learned feature
    grids at the model section's grid ``lr_scale``, every other weight at 1."""
    scales = grid_lr_scales(m)
    groups: dict[float, list[torch.nn.Parameter]] = {}
    for name, p in model.named_parameters():
        if name.startswith("field."):
            scale = field_lr_scale
        else:
            local = name.split(".", 2)[2]  # lobes.<k>.<name in the RawBRDF>
            local = local[4:] if local.startswith("net.") else local  # beside GGX heads
            scale = lr_scale(local, scales)
        groups.setdefault(scale, []).append(p)
    return [{"params": ps, "lr_scale": s} for s, ps in groups.items()]


# texture.lobe_bound: scale (bound_scale): the training-time estimate of each raw lobe's
# largest albedo, every BOUND_EVERY steps, on a coarse grid of incidences (and latent
# values), BOUND_SAMPLES quadrature points each; the export tabulates the bound itself at
# the normalization section's full settings (textured_model.normalized_textured)
BOUND_EVERY = 100
BOUND_THETA = 17  # incidence nodes
BOUND_LATENT = 9  # latent nodes (conditioned lobes)
BOUND_SAMPLES = 1024


def _coarse_tables(
    model: TexturedBRDF,
    seed: int,
    size: int = BOUND_THETA,
    samples: int = BOUND_SAMPLES,
    upper: bool = False,
) -> list[tuple[torch.Tensor, bool]]:
    """Each raw lobe's albedo estimate at the coarse training settings (``size`` nodes of
    incidence, ``samples`` points each, no sigmas, no margin), or with ``upper`` its
    neighbour maximum over the nodes, as the export's tables take it: (table,
    conditioned) per lobe, a conditioned table (S, K, C), an isotropic one (K, C), an
    anisotropic one (K, K, C); C = 3 x the lobe's heads."""
    from neural_brdf.train.conditioned import conditioned_albedo_table
    from neural_brdf.train.model import albedo_table

    out = []
    with torch.no_grad():
        for k, lobe in enumerate(model.lobes):
            raw = raw_of(lobe)
            was = raw.training
            raw.eval()
            if getattr(raw, "latent", 0):
                up, a, _ = conditioned_albedo_table(
                    raw,
                    latent_nodes=BOUND_LATENT,
                    size=size,
                    samples=samples,
                    seed=seed + 7 * k,
                    sigmas=0.0,
                    margin=0.0,
                )
            else:
                up, a, _ = albedo_table(
                    raw,
                    size=size,
                    anisotropic=bool(raw.anisotropic),
                    samples=samples,
                    seed=seed + 7 * k,
                    sigmas=0.0,
                    margin=0.0,
                )
            raw.train(was)
            out.append((up if upper else a, bool(getattr(raw, "latent", 0))))
    return out


def bound_scale(model: TexturedBRDF, seed: int = 0) -> torch.Tensor:
    """(3K,) per lobe and channel: 1 / max(1, the raw lobe's largest albedo), estimated
    by the same quadrature as the export's tables at coarse settings (above, no added
    sigmas or margin: an estimate, not a bound).  Training divides each lobe by it
    (``texture.lobe_bound: scale``), so the lobes learn within albedo 1 and the
    export's constant (:class:`~neural_brdf.train.textured_model.ScaledBRDF`) dims them
    only by the two estimates' difference."""
    cols = [a.reshape(-1, a.shape[-1]).amax(0) for a, _ in _coarse_tables(model, seed)]
    cols += [torch.ones(3 * analytic_count(g)) for g in model.lobes]  # analytic: <= 1
    peak = torch.cat(cols).float().clamp_min(1.0)
    return 1.0 / peak


# texture.lobe_bound: texel (bound_envelope): the export's nodes of incidence (config.
# Normalization's table_size) and their neighbour maximum, so that training bounds the
# texels as the export will, with fewer points per node (no sigmas or margin)
ENVELOPE_THETA = 65
ENVELOPE_SAMPLES = 256


def bound_envelope(model: TexturedBRDF, seed: int = 0) -> torch.Tensor:
    """[J, 3K]: each raw lobe's albedo estimate per node of incidence, the neighbour
    maximum over the nodes (and its largest over the latent, for conditioned lobes), the
    lobes side by side, at :data:`ENVELOPE_THETA` nodes of :data:`ENVELOPE_SAMPLES`
    points.  Training bounds the field's texels by it
    (``texture.lobe_bound: texel``, :func:`~neural_brdf.train.textured_model.
    texel_bound`) as the export does by its own tables."""
    tables = _coarse_tables(model, seed, ENVELOPE_THETA, ENVELOPE_SAMPLES, upper=True)
    parts = []
    for (a, cond), lobe in zip(tables, model.lobes):
        env = lobe_envelope(a, cond).float()
        if analytic_count(lobe):  # the analytic heads' envelope at the same nodes
            env = with_head_envelope(env, bool(getattr(raw_of(lobe), "anisotropic", False)))
        parts.append(env)
    return torch.cat(parts, -1).float()


def _rebound(model: TexturedBRDF, bound: str, step: int, seed: int) -> None:
    """``texture.lobe_bound`` scale (the lobes' scale) or texel (the field's envelope):
    estimated when the model has none (the start, a resumed run's restored lobes) and
    again every BOUND_EVERY steps after the first."""
    due = bool(step and step % BOUND_EVERY == 0)
    if bound == "scale" and (model.lobe_scale is None or due):
        model.lobe_scale = bound_scale(model, seed + step)
    if bound == "texel" and (model.texel_envelope is None or due):
        model.texel_envelope = bound_envelope(model, seed + step)


# the latent's start (latent_from_teacher): the lobe's fall-off from the mirror
# direction at normal incidence, between wo = n and wo tilted by LATENT_TILT_DEG, above
# the value at LATENT_FLOOR_DEG (a floor that removes a broad diffuse part, so that the
# start follows the glossy lobe's width, not its share: on the development principled
# 9.6 % and 12.9 % held-out error for two seeds, against 10.6 % and 13.4 % without it)
LATENT_TILT_DEG = 15.0
LATENT_FLOOR_DEG = 60.0


def latent_from_teacher(teacher: Any, resolution: int) -> torch.Tensor:
    """A start for the field's latent logits, [R*R, 1] (docs/model.md, "Conditioned
    lobes"): at each texel centre, how sharply the teacher's lobe falls off,
    log((f(n, n) - f(n, w') + e) / (f(n, w) - f(n, w') + e)) (channel means, w tilted by
    :data:`LATENT_TILT_DEG` from the normal n, w' by :data:`LATENT_FLOOR_DEG`: a
    diffuse floor removed), ranked over the texels and mapped to
    s = (rank + 0.5) / R^2, so that s spans [0, 1] and orders the texels from the
    broadest lobe (s near 0) to the sharpest (s near 1).  Any teacher works: it asks
    only ``eval``.  Without this start every texel's s sits at 0.5, the lobes' slices
    along s see the same data, and s gets no gradient to spread with."""
    r = int(resolution)
    i = (np.arange(r * r) % r + 0.5) / r
    j = (np.arange(r * r) // r + 0.5) / r
    uv = np.stack([i, j], -1)  # row-major [v, u]: texel j * R + i
    n = np.tile([0.0, 0.0, 1.0], (r * r, 1))

    def at(deg: float) -> np.ndarray:  # f(n, wo tilted by deg) at every texel, channel mean
        t = math.radians(deg)
        wo = np.tile([math.sin(t), 0.0, math.cos(t)], (r * r, 1))
        return np.nan_to_num(np.asarray(teacher.eval(n, wo, uv), dtype=np.float64)).mean(-1)

    f0, f1, f2 = at(0.0), at(LATENT_TILT_DEG), at(LATENT_FLOOR_DEG)
    e = 1e-3 * max(float(np.abs(f0).mean()), 1e-6)
    sharp = np.log((np.maximum(f0 - f2, 0.0) + e) / (np.maximum(f1 - f2, 0.0) + e))
    rank = np.argsort(np.argsort(sharp, kind="stable"), kind="stable")
    s = (rank + 0.5) / (r * r)
    return torch.from_numpy(np.log(s / (1.0 - s))).float()[:, None]


def latent_start(teacher: Any, resolution: int, latent: int, analytic: str) -> torch.Tensor | None:
    """The field's latent logits at the start, [R*R, columns]: the lobes' latent
    (:func:`latent_from_teacher`, with ``latent``) then alpha's column
    (:func:`~neural_brdf.train.ggx_heads.alpha_from_teacher`, with analytic heads);
    None when the field has neither."""
    parts = []
    if latent:
        parts.append(latent_from_teacher(teacher, resolution))
    if analytic != "none":
        parts.append(alpha_from_teacher(teacher, resolution))
    return torch.cat(parts, -1) if parts else None


def lobe_networks(
    m: cfgmod.Model,
    lobes: int,
    shared: bool,
    *,
    init_value: float = 0.3,
    latent: int = 0,
    colors: int = 3,
) -> list[RawBRDF]:
    """K raw networks of the ``model`` section, or one with K heads (``shared``), each
    with ``latent`` more inputs (conditioned lobes) and ``colors`` outputs per lobe (3:
    RGB; 1: grey, ``texture.lobe_color``)."""
    if not shared:
        return [
            RawBRDF.from_config(m, init_value=init_value, latent=latent, colors=colors)
            for _ in range(lobes)
        ]
    net = RawBRDF.from_config(m, init_value=init_value, heads=lobes, latent=latent, colors=colors)
    if lobes > 1:
        with torch.no_grad():  # K zero heads would stay equal but for the field's weights
            torch.nn.init.normal_(net.mlp.head.weight, std=1e-2)
    return [net]


def _step(
    model: TexturedBRDF,
    opt: torch.optim.Adam,
    sched: cfgmod.Train,
    step: int,
    pool: tuple[torch.Tensor, ...],
    batch: int,
    gen: torch.Generator,
) -> tuple[torch.Tensor, float]:
    """One optimisation step at ``step`` of ``sched``'s schedule (each group's rate times
    its ``lr_scale``) on ``batch`` rows drawn from ``pool`` (wi, wo, uv, f) with ``gen``.
    Returns the loss (a tensor: read it only when needed) and the learning rate."""
    rate = learning_rate(sched, step)
    for group in opt.param_groups:
        group["lr"] = rate * group["lr_scale"]
    idx = torch.randint(0, len(pool[0]), (batch,), generator=gen)
    wi, wo, uv, f = (x[idx] for x in pool)
    loss = loss_fn(
        sched.loss,
        model(wi, wo, uv),
        f,
        wo[:, 2:3],
        sched.loss_eps,
        sched.peak_weight,
        sched.peak_cap,
    )
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss, rate


def _train_span(
    model: TexturedBRDF,
    opt: torch.optim.Adam,
    sched: cfgmod.Train,
    pool: PairPool,
    batch: int,
    gen: torch.Generator,
    *,
    lobe_bound: str,
    seed: int,
    start: int,
    stop: int,
) -> float:
    """Steps ``start`` to ``stop`` of ``sched``'s schedule (no checkpoints); the last
    loss read (every 100 steps and the last), which must be finite."""
    last = math.nan
    model.train()
    for step in range(start, stop):
        _rebound(model, lobe_bound, step, seed)
        loss, _ = _step(model, opt, sched, step, pool.at(step), batch, gen)
        if step == stop - 1 or step % 100 == 0:
            last = float(loss.detach())
            if not math.isfinite(last):
                raise FloatingPointError(f"train_textured: loss {last} at step {step}")
    model.eval()
    return last


def pick_start(
    make: Any,
    starts: int,
    steps: int,
    seed: int,
    train_span: Any,
    choose: tuple[torch.Tensor, ...],
) -> tuple[TexturedBRDF, torch.optim.Adam, torch.Generator, dict[str, Any]]:
    """Several starts (``texture.starts``, docs/mitsuba.md): for i < ``starts``, the model
    and optimiser ``make()`` builds after ``torch.manual_seed(seed + i)``, trained
    ``steps`` steps by ``train_span(model, opt, gen, seed + i)`` with a batch generator
    seeded ``seed + i``; the one with the lowest relative RMSE of f cos on the pairs
    ``choose`` (wi, wo, uv, f: drawn apart from the held-out pairs) is returned with its
    optimiser and generator, to continue from step ``steps``.  Start 0 is the run a single
    start would make.  The others are dropped as soon as one is better."""
    c_wi, c_wo, c_uv, c_f = choose
    best: tuple | None = None
    errors = []
    t0 = time.perf_counter()
    for i in range(starts):
        torch.manual_seed(seed + i)
        model, opt = make()
        gen = torch.Generator().manual_seed(seed + i)
        loss = train_span(model, opt, gen, seed + i)
        with torch.no_grad():
            err = rel_rmse(model(c_wi, c_wo, c_uv), c_f, c_wo[:, 2:3])
        errors.append(err)
        if best is None or err < best[0]:
            best = (err, model, opt, gen, i, loss)
    assert best is not None
    return (
        best[1],
        best[2],
        best[3],
        {
            "starts": starts,
            "start_steps": steps,
            "start_errors": errors,
            "chosen_start": best[4],
            "chosen_seed": seed + best[4],
            "chosen_loss": best[5],
            "starts_seconds": time.perf_counter() - t0,
        },
    )


def train_textured(
    teacher: Any,
    *,
    lobes: int = 4,
    resolution: int = 32,
    hidden: Sequence[int] = (32,),
    steps: int = 1500,
    batch: int = 4096,
    lr: float = 3e-2,
    field_lr_scale: float = FIELD_LR_SCALE,
    warmup: int = 100,
    pool: int = POOL,
    val_pairs: int = VAL_PAIRS,
    seed: int = 0,
    model_section: cfgmod.Model | None = None,
    weights: str = "scalar",
    lobe_network: str = "separate",
    latent: int = 0,
    lobe_color: str = "rgb",
    lobe_bound: str = "table",
    peak_weight: float | None = None,
    peak_cap: float | None = None,
    starts: int = 1,
    start_steps: int | None = None,
    fresh_every: int | None = None,
    field_levels: int = 1,
    analytic_heads: str = "none",
) -> tuple[TexturedBRDF, dict[str, Any]]:
    """Fit K = ``lobes`` shared raw lobes and an R x R weight field (R = ``resolution``)
    to ``teacher`` (``eval(wi, wo, uv)``, ``sample(wi, uv, u)``: a
    :class:`~neural_brdf.measured.textured.TexturedMitsubaTarget`).  Returns the model
    (raw lobes, not yet normalised: :func:`~neural_brdf.train.textured_model.
    normalized_textured`) and its figures: ``init_val_rel_rmse`` and ``val_rel_rmse``
    (module doc), ``final_loss``, ``train_seconds``, ``pool_seconds``.

    Each lobe is ``RawBRDF.from_config(model_section)``; by default the project's
    compact recipe (:class:`neural_brdf.config.Model`) with hidden widths ``hidden``.
    Weights from ``torch.manual_seed(seed)``, data from ``numpy`` and torch generators
    seeded with ``seed``; the thread count is the caller's (``torch.set_num_threads``).
    """
    m = model_section if model_section is not None else cfgmod.Model(hidden=list(hidden))
    sched = cfgmod.Train(steps=steps, lr=lr, warmup=min(warmup, max(steps - 1, 0)), seed=seed)
    peak = {
        k: v for k, v in (("peak_weight", peak_weight), ("peak_cap", peak_cap)) if v is not None
    }
    if peak:  # the loss's peak weight (train.peak_weight, train.peak_cap; None: defaults)
        sched = sched.model_copy(update=peak)
    t0 = time.perf_counter()
    pool_t = PairPool(teacher, pool, seed, fresh_every)
    p_f = pool_t.at(0)[3]
    v_wi, v_wo, v_uv, v_f = pairs(
        teacher, val_pairs, np.random.default_rng(seed + 101), cosine_wi=False
    )
    pool_seconds = time.perf_counter() - t0

    latent_init = latent_start(teacher, resolution, latent, analytic_heads)

    def make() -> tuple[TexturedBRDF, torch.optim.Adam]:  # from torch's seeded generator
        return _model_and_optimizer(
            m,
            lobes,
            resolution,
            p_f,
            lr,
            field_lr_scale,
            CHANNELS[weights],
            shared=lobe_network == "shared",
            latent=latent,
            latent_init=latent_init,
            levels=field_levels,
            colors=COLORS[lobe_color],
            analytic=analytic_heads,
        )

    def span(model, opt, gen, run_seed: int, start: int, stop: int) -> float:
        return _train_span(
            model, opt, sched, pool_t, batch, gen,
            lobe_bound=lobe_bound, seed=run_seed, start=start, stop=stop,
        )  # fmt: skip

    torch.manual_seed(seed)
    model, opt = make()

    def validate() -> float:
        with torch.no_grad():
            return rel_rmse(model(v_wi, v_wo, v_uv), v_f, v_wo[:, 2:3])

    _rebound(model, lobe_bound, 0, seed)
    init_err = validate()
    t1 = time.perf_counter()
    first, chosen = 0, dict[str, Any]()
    if starts > 1:
        first = steps if start_steps is None else min(start_steps, steps)
        choose = pairs(teacher, val_pairs, np.random.default_rng(seed + CHOOSE_SEED))
        model, opt, gen, chosen = pick_start(
            make, starts, first, seed, lambda mo, op, g, s: span(mo, op, g, s, 0, first), choose
        )
    else:
        gen = torch.Generator().manual_seed(seed)
    last = span(model, opt, gen, seed, first, steps) if first < steps else chosen["chosen_loss"]
    return model, {
        "steps": steps,
        "lobes": lobes,
        "resolution": resolution,
        "pool": pool,
        "pool_seconds": pool_seconds,
        "fresh_every": fresh_every,
        "field_levels": field_levels,
        "pool_draws": pool_t.draws,
        "pool_draw_seconds": pool_t.seconds,
        "train_seconds": time.perf_counter() - t1,
        "final_loss": last,
        "init_val_rel_rmse": init_err,
        "val_rel_rmse": validate(),
        "field_lr_scale": field_lr_scale,
        "weights": weights,
        "lobe_network": lobe_network,
        "latent": latent,
        "lobe_color": lobe_color,
        "lobe_bound": lobe_bound,
        "analytic_heads": analytic_heads,
        **chosen,
    }


def train(
    cfg: cfgmod.Config,
    run_dir: Path,
    *,
    target: Any,
    resume: bool = False,
    checkpoint: dict | None = None,
    folder: Folder | None = None,
) -> tuple[TexturedBRDF, dict[str, Any]]:
    """``neural-brdf train`` of a spatially varying teacher (``target``: a
    :class:`~neural_brdf.measured.textured.TexturedMitsubaTarget`): the loop of
    :func:`train_textured` with the config's settings (``texture``: K, R and the field's
    learning rate; ``train``: steps, learning rate, schedule, loss, seed; ``data``: the
    batch and the pool; ``model``: each lobe's network), run in a
    :class:`~neural_brdf.train.session.Session`: ckpt.pt written atomically every
    ``train.checkpoint_every`` steps (and at Ctrl-C / SIGTERM), log.csv, ``--resume``.

    A resumed run draws the same pool again (the same teacher, the same seed) and
    restores the weights, Adam's moments and the batch generator, so it continues the
    run it resumes.  Returns the raw model (lobes not yet normalised) and its figures:
    ``steps``, ``train_seconds``, ``pool_seconds``, ``final_loss``,
    ``init_val_rel_rmse``, ``raw_val_rel_rmse`` (module doc), ``target``."""
    t, tx = cfg.train, cfg.texture
    torch.set_num_threads(t.threads)
    sess = Session.one(
        cfg,
        folder if folder is not None else run_dir,
        resume=resume,
        kind="textured",
    )
    ckpt = sess.resumed(checkpoint, must_match=TEXTURED_MUST_MATCH)
    sess.begin()
    t0 = time.perf_counter()
    pool = PairPool(target, tx.pool(cfg.data.pool_size), t.seed, tx.fresh_every, cfg.data.peak)
    p_f = pool.at(0)[3]
    v_wi, v_wo, v_uv, v_f = pairs(
        target, VAL_PAIRS, np.random.default_rng(t.seed + 101), cosine_wi=False
    )
    pool_seconds = time.perf_counter() - t0
    latent_init = latent_start(target, tx.resolution, tx.latent, tx.analytic_heads)

    def make() -> tuple[TexturedBRDF, torch.optim.Adam]:  # from torch's seeded generator
        return _model_and_optimizer(
            cfg.model,
            tx.lobes,
            tx.resolution,
            p_f,
            t.lr,
            tx.field_lr_scale,
            CHANNELS[tx.weights],
            shared=tx.lobe_network == "shared",
            latent=tx.latent,
            latent_init=latent_init,
            levels=tx.field_levels,
            colors=COLORS[tx.lobe_color],
            analytic=tx.analytic_heads,
        )

    torch.manual_seed(t.seed)
    model, opt = make()

    def validate() -> float:
        with torch.no_grad():
            return rel_rmse(model(v_wi, v_wo, v_uv), v_f, v_wo[:, 2:3])

    _rebound(model, tx.lobe_bound, 0, t.seed)  # the lobes' training-time scale
    init_err = validate()
    gen = torch.Generator().manual_seed(t.seed)
    last = math.nan
    chosen: dict[str, Any] = {}
    if ckpt is not None:
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        gen.set_state(ckpt["generator"])
        init_err = float(ckpt.get("init_val_rel_rmse", init_err))
        last = float(ckpt.get("loss", math.nan))
        chosen = dict(ckpt.get("starts") or {})
        sess.restore(ckpt)
        model.lobe_scale = None  # estimated again for the restored lobes (_rebound)
        model.texel_envelope = None
    elif tx.starts > 1:  # several starts, before the checkpointed loop (pick_start)
        first = t.steps if tx.start_steps is None else tx.start_steps
        print(
            f"{cfg.name}: {tx.starts} starts of {first} steps each, then the best",
            file=sys.stderr,
        )
        choose = pairs(target, VAL_PAIRS, np.random.default_rng(t.seed + CHOOSE_SEED))

        def span(mo: TexturedBRDF, op: torch.optim.Adam, g: torch.Generator, sd: int) -> float:
            return _train_span(
                mo, op, t, pool, cfg.data.batch_size, g,
                lobe_bound=tx.lobe_bound, seed=sd, start=0, stop=first,
            )  # fmt: skip

        model, opt, gen, chosen = pick_start(make, tx.starts, first, t.seed, span, choose)
        sess.step, sess.seconds = first, chosen["starts_seconds"]
        last = chosen["chosen_loss"]

    def state() -> dict[str, Any]:
        return {
            "model": {k: v.detach().clone() for k, v in model.state_dict().items()},
            "optimizer": opt.state_dict(),
            "generator": gen.get_state(),
            "loss": last,
            "init_val_rel_rmse": init_err,
            "starts": chosen,
        }

    model.train()
    with sess.run(state) as s:
        if ckpt is None and chosen:  # log.csv's first row: the chosen start
            model.eval()
            s.log(
                loss=chosen["chosen_loss"],
                lr=learning_rate(t, s.step - 1),
                val_rel_rmse=validate(),
            )
            model.train()
        while s.step < t.steps:
            s.stop_if_interrupted()
            _rebound(model, tx.lobe_bound, s.step, t.seed)
            loss, rate = _step(model, opt, t, s.step, pool.at(s.step), cfg.data.batch_size, gen)
            s.advance()
            if s.due(t.log_every):
                last = float(loss.detach())
                if not math.isfinite(last):
                    raise sess.diverged(last, s.step - 1)
                err = None
                if t.eval_every and s.due(t.eval_every):
                    model.eval()
                    err = validate()
                    model.train()
                    s.postfix(loss=f"{last:.4g}", err=f"{100 * err:.2f}%")
                else:
                    s.postfix(loss=f"{last:.4g}")
                s.log(loss=last, lr=rate, val_rel_rmse=err)
            if s.due(t.checkpoint_every):
                s.check_weights(all(bool(torch.isfinite(p).all()) for p in model.parameters()))
                s.checkpoint()
    model.eval()
    return model, {
        "steps": sess.step,
        "device": "cpu",
        "lobes": tx.lobes,
        "resolution": tx.resolution,
        "weights": tx.weights,
        "latent": tx.latent,
        "lobe_color": tx.lobe_color,
        "analytic_heads": tx.analytic_heads,
        "pool": len(p_f),
        "pool_seconds": pool_seconds,
        "fresh_every": tx.fresh_every,
        "field_levels": tx.field_levels,
        "pool_draws": pool.draws,
        "pool_draw_seconds": pool.seconds,
        "train_seconds": sess.seconds,
        **sess.record(),
        "final_loss": last,
        "init_val_rel_rmse": init_err,
        "raw_val_rel_rmse": validate(),
        "target": target.describe(),
        **chosen,
    }
