"""A finer weight field by projection, texel by texel, onto frozen lobes.

A textured model's field is trained with its lobes by Adam, and a fine field trains
worse than a coarse one (docs/mitsuba.md, "The pool and the field's resolution": a
texel of a 256^2 field is in the footprint of about one pair in two batches).  Once the
lobes are trained, though, a texel's weights are a linear problem: at the texel centre
uv_t the model is f(wi, wo) = sum_k z_k g_k(wi, wo; s) per RGB channel, so for fixed
lobes and latent s the weights that minimise the squared error of f cos against the
teacher on M pairs drawn at uv_t are a non-negative least-squares problem of K unknowns
per channel, solved exactly here (:func:`nnls`, every active set: K is small).  The
latent, the lobes' one non-linear input, is searched over a grid of values and the
trained field's own value at the centre; the texel keeps the one of least error.

:func:`project_field` does this for every texel of an R x R field (R finer than the
trained one, or the same), and bounds each texel as ``texture.lobe_bound: texel`` does
(:func:`~neural_brdf.train.textured_model.texel_bound`): the weights stay >= 0 and
sum_k z_k,c A+_k,c <= 1 at every node, so the physics argument of docs/model.md holds
between texel centres unchanged (bilinear blends keep linear constraints), and
reciprocity is the lobes' own.  The error of f cos is the benchmark's measure
(relative RMSE over pairs, benchmarks/textured.py), so a least-squares fit per texel
lowers exactly the sum that figure is made of, at the texel centres.

A texel's pairs are few for a heavy-tailed teacher: on the development principled, with
128 pairs a texel, the fit's error on its own pairs was about half of what fresh pairs
at the same centres showed, and more pairs lowered the latter (docs/mitsuba.md, "The
pairs per texel and the ridge").  So besides more pairs (``texture.project_pairs``),
``ridge`` shrinks each texel toward the trained field's weights there (the trained field
fitted every pair near the texel): a ridge of the least squares toward z_0, as strong as
``ridge`` times the mean diagonal of the texel's normal matrix.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from itertools import combinations
from typing import Any

import numpy as np
import torch

from analytic import frame
from neural_brdf import config as cfgmod
from neural_brdf.train.ggx_heads import (
    ALPHA_MIN,
    GGXLobes,
    alpha_from_teacher,
    alpha_of,
    t_of,
)
from neural_brdf.train.textured_model import (
    FrozenWeightField,
    TexturedBRDF,
    WeightField,
    texel_bound,
)

MAX_LOBES = 8  # every active set: 2^K - 1 small solves per problem
# texture.project_alpha: where a projected texel's alpha comes from
ALPHA_SOURCES = ("trained", "teacher", "both")
# texture.project_alphas: the alphas an analytic head's texel tries, geometric from its
# trained alpha / ALPHA_SPAN to x ALPHA_SPAN
ALPHA_SPAN = 2.0


def nnls(
    gram: torch.Tensor, rhs: torch.Tensor, sq: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched exact non-negative least squares of K <= MAX_LOBES unknowns from the
    normal equations: min_z ||A z - y||^2 subject to z >= 0, given G = A^T A
    (..., K, K), b = A^T y (..., K) and ||y||^2 (...).  Returns (z (..., K), the least
    squared residual (...)).  Every non-empty active set S is solved (G_SS z_S = b_S,
    with a ridge of 1e-9 of G's mean diagonal); the best one with z_S >= 0 is the
    solution (the NNLS optimum is the unconstrained optimum on its support).  z = 0 when
    no set is feasible (a zero column).

    The full set is solved first: a problem whose solution there is >= 0 has its optimum
    (the problem is convex, and no subset's residual is below the full set's), so only
    the others go through the enumeration, the same solves on fewer rows (on a 64^2
    projection of the development principled, a third of the problems stop at the full
    set: 36 % with the trained alpha, 31 % with ``both``)."""
    k = rhs.shape[-1]
    if not 1 <= k <= MAX_LOBES:
        raise ValueError(f"nnls: 1 to {MAX_LOBES} unknowns, got {k}")
    batch = rhs.shape[:-1]
    if k > 1 and rhs.dim() > 1:
        full, r_full = _solve_set(gram, rhs, sq, _scale(gram))
        done = (full >= 0).all(-1)
        if bool(done.any()):
            z_out = torch.where(done[..., None], full, torch.zeros_like(full))
            r_out = torch.where(done, r_full, sq)
            rest = (~done).reshape(-1).nonzero().squeeze(-1)
            if len(rest):
                flat = (gram.reshape(-1, k, k), rhs.reshape(-1, k), sq.reshape(-1))
                z_rest, r_rest = _nnls_all_sets(*(x[rest] for x in flat))
                z_out = z_out.reshape(-1, k).index_copy(0, rest, z_rest).reshape(*batch, k)
                r_out = r_out.reshape(-1).index_copy(0, rest, r_rest).reshape(batch)
            return z_out, r_out
    return _nnls_all_sets(gram, rhs, sq)


def _scale(gram: torch.Tensor) -> torch.Tensor:
    """G's mean diagonal (..., 1, 1): the solves' ridge is 1e-9 of it."""
    return gram.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-300)[..., None, None]


def _solve_set(
    gram: torch.Tensor, rhs: torch.Tensor, sq: torch.Tensor, scale: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The unconstrained least squares on one active set, (G_SS, b_S): z_S and its
    squared residual ||y||^2 - 2 z.b + z^T G z."""
    size = rhs.shape[-1]
    z = torch.linalg.solve(gram + 1e-9 * scale * torch.eye(size, dtype=gram.dtype), rhs)
    return z, sq - 2.0 * (z * rhs).sum(-1) + (z * (gram @ z[..., None])[..., 0]).sum(-1)


def _nnls_all_sets(
    gram: torch.Tensor, rhs: torch.Tensor, sq: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`nnls` by every non-empty active set (its doc)."""
    k = rhs.shape[-1]
    best_r = sq.clone()  # z = 0
    best_z = torch.zeros_like(rhs)
    scale = _scale(gram)
    for size in range(1, k + 1):
        for subset in combinations(range(k), size):
            idx = torch.tensor(subset)
            zs, r = _solve_set(gram[..., idx[:, None], idx[None, :]], rhs[..., idx], sq, scale)
            better = (zs >= 0).all(-1) & (r < best_r)
            if bool(better.any()):
                z = torch.zeros_like(rhs).index_copy_(-1, idx, zs)
                best_r = torch.where(better, r, best_r)
                best_z = torch.where(better[..., None], z, best_z)
    return best_z, best_r


def texel_centres(resolution: int) -> np.ndarray:
    """(R*R, 2) uv of the texel centres, flat index j * R + i (the field's order)."""
    c = (np.arange(resolution) + 0.5) / resolution
    u, v = np.meshgrid(c, c, indexing="xy")
    return np.stack([u, v], -1).reshape(-1, 2)


def draw_pairs(
    teacher: Any, uv: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wi, wo, the teacher's f) at ``uv`` (N, 2), drawn as validation draws its pairs:
    wi uniform on the hemisphere, wo uniform for a random half and from the teacher's
    sampler for the other (a failed sample stays uniform)."""
    n = len(uv)
    wi = frame.square_to_uniform_hemisphere(torch.from_numpy(rng.random((n, 2)))).numpy()
    wo = frame.square_to_uniform_hemisphere(torch.from_numpy(rng.random((n, 2)))).numpy()
    rows = np.flatnonzero(rng.random(n) < 0.5)
    if len(rows):
        sampled = np.asarray(teacher.sample(wi[rows], uv[rows], rng.random((len(rows), 2))))
        good = sampled[:, 2] > 0
        wo[rows[good]] = sampled[good]
    f = np.nan_to_num(np.asarray(teacher.eval(wi, wo, uv), np.float64))
    return wi, wo, f


class _Parts:
    """The normal equations of one chunk's texels (t texels of M pairs each) at a
    candidate latent (one per texel, repeated over its pairs): A^T A and A^T y of
    g cos against the teacher's f cos, per channel.

    With analytic heads (:class:`GGXLobes`) the network's columns depend on the searched
    latent only and the heads' on alpha's column only, and the candidates repeat each
    (the trained latent with every alpha tried, every latent with the trained alpha):
    each part's values and its own block of A^T A and A^T y are computed once per
    distinct value and kept, and a candidate adds only the cross block between its two
    parts.  The values are ``lobe``'s own forward's (tests/train/test_ggx_heads.py)."""

    def __init__(
        self,
        lobe: torch.nn.Module,
        x: tuple[torch.Tensor, ...],
        pairs: int,
        cos: torch.Tensor,
        y: torch.Tensor,
    ):
        self.lobe, self.x, self.pairs = lobe, x, pairs
        self.cos, self.y = cos, y  # (t M, 1) and (t, 3, M), float64
        self.t = y.shape[0]
        self.split = isinstance(lobe, GGXLobes)
        self.cache: dict[tuple[str, bytes], tuple[torch.Tensor, ...]] = {}

    def _block(self, kind: str, s: torch.Tensor | None, fn: Callable) -> tuple[torch.Tensor, ...]:
        """(A (t, 3 or 1, M, C), its A^T A, its A^T y) of one part at ``s``, kept."""
        key = (kind, b"" if s is None else s.numpy().tobytes())
        if key not in self.cache:
            extra = () if s is None else (s.repeat_interleave(self.pairs, 0),)
            with torch.no_grad():
                v = fn(*self.x, *extra).double() * self.cos
            if kind == "heads":  # (t M, 2): one value for the three channels
                a = v.reshape(self.t, 1, self.pairs, v.shape[1])
            else:  # (t M, 3C), columns lobe-major: (t, 3, M, C)
                a = v.reshape(self.t, self.pairs, v.shape[1] // 3, 3).permute(0, 3, 1, 2)
                a = a.contiguous()
            a_t = a.transpose(-1, -2)
            self.cache[key] = (a, a_t @ a, (a_t @ self.y[..., None])[..., 0])
        return self.cache[key]

    def __call__(
        self, s: torch.Tensor | None
    ) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
        """(the parts' A blocks, A^T A (t, 3, K, K), A^T y (t, 3, K)) at ``s``."""
        if not self.split or s is None:
            a, gram, rhs = self._block("lobes", s, self.lobe)
            return [a], gram, rhs
        lobe = self.lobe
        assert isinstance(lobe, GGXLobes)
        lat = lobe.searched_latent
        a_n, g_nn, b_n = self._block("network", s[:, :lat].contiguous(), lobe.network_part)
        a_h, g_hh, b_h = self._block("heads", s[:, lat:].contiguous(), lobe.head_part)
        g_nh = a_n.transpose(-1, -2) @ a_h  # (t, 3, Kn, 2)
        g_hh = g_hh.expand(-1, g_nh.shape[1], -1, -1)
        gram = torch.cat(
            [torch.cat([g_nn, g_nh], -1), torch.cat([g_nh.transpose(-1, -2), g_hh], -1)], -2
        )
        return [a_n, a_h], gram, torch.cat([b_n, b_h], -1)


def project_field(
    lobe: torch.nn.Module,
    field: WeightField | FrozenWeightField,
    teacher: Any,
    envelope: torch.Tensor,
    *,
    resolution: int,
    pairs: int = 128,
    latents: int = 5,
    seed: int = 0,
    ridge: float = 0.0,
    chunk_pairs: int = 1 << 19,
    alphas: int = 1,
    alpha_source: str = "trained",
) -> tuple[FrozenWeightField, dict[str, Any]]:
    """The weights (and latent) of every texel of an R x R field (R = ``resolution``)
    fitted to ``teacher`` at its centre on ``pairs`` pairs (:func:`draw_pairs`), for the
    frozen shared lobe network ``lobe`` ((wi, wo[, s]) -> (N, 3K)), then bounded by
    ``envelope`` [J, 3K] (:func:`~neural_brdf.train.textured_model.texel_bound`).  With
    conditioned lobes (``field.latent``) the latent is chosen per texel among
    ``latents`` values evenly spaced on [0, 1] and ``field``'s own value at the centre.
    One weight per lobe (``field.channels`` 1) fits the three channels together.
    ``ridge`` > 0 shrinks each texel toward ``field``'s weights z_0 at its centre: the
    least squares gains ridge * mean(diag A^T A) * ||z - z_0||^2 (scale-free; every
    latent tried keeps the same z_0), and the texel keeps the candidate of least
    penalised error.  Returns the frozen field and figures (seconds, the share of texels
    the bound scaled down, the squared residual's sum over the texels' pairs, without
    the penalty, against that of ``field`` on the same pairs).  With analytic heads,
    ``alpha_source`` says where a texel's alpha (before the ``alphas`` search) comes
    from: "trained" (``field`` at its centre), "teacher" (the teacher's own GGX fit at
    its centre, :func:`~neural_brdf.train.ggx_heads.alpha_from_teacher`) or "both"
    (each tried, the texel keeps the better)."""
    t0 = time.perf_counter()
    k, channels, latent = field.lobes, field.channels, field.latent
    rng = np.random.default_rng(seed)
    centres = texel_centres(resolution)
    count = len(centres)
    table = torch.zeros(count, channels * k + latent)
    now = field.lookup(torch.from_numpy(centres).float())  # the trained field at the centres
    per = max(1, chunk_pairs // pairs)
    residual, residual_before, teacher_seconds = 0.0, 0.0, 0.0
    # the latent columns searched: the lobes' s; analytic heads' alpha column (the last,
    # after s) keeps the trained field's value (train/ggx_heads.py)
    searched = int(getattr(lobe, "searched_latent", latent))
    grid = [float(v) for v in np.linspace(0.0, 1.0, latents)] if searched else []
    factors: list[float] = []  # alpha's multipliers, the trained one's (1) left out
    fitted: torch.Tensor | None = None  # the teacher's alpha at the centres, as t
    if alpha_source not in ALPHA_SOURCES:
        raise ValueError(f"alpha_source: {alpha_source!r}: one of {', '.join(ALPHA_SOURCES)}")
    if alpha_source != "trained" and latent > searched and now[1] is not None:
        fitted = torch.sigmoid(alpha_from_teacher(teacher, resolution))
    if alphas > 1 and latent > searched:
        factors = [
            float(f)
            for f in np.geomspace(1.0 / ALPHA_SPAN, ALPHA_SPAN, alphas)
            if abs(f - 1) > 1e-9
        ]
    for a in range(0, count, per):
        t = min(per, count - a)
        uv = np.repeat(centres[a : a + t], pairs, 0)
        t1 = time.perf_counter()
        wi, wo, f = draw_pairs(teacher, uv, rng)
        teacher_seconds += time.perf_counter() - t1
        cos = torch.from_numpy(wo[:, 2:3])
        y = (torch.from_numpy(f) * cos).reshape(t, pairs, 3).permute(0, 2, 1)  # (t, 3, M)
        x = (torch.from_numpy(wi).float(), torch.from_numpy(wo).float())
        old_z = now[0][a : a + t].double()
        old_z = old_z[:, None, :].expand(t, 3, k) if channels == 1 else old_z
        candidates: list[torch.Tensor | None] = [None]
        if now[1] is not None:  # conditioned lobes: the trained latent, then the grid
            trained = now[1][a : a + t]
            candidates = [trained]
            bases = [trained]
            if fitted is not None:  # the teacher's alpha (only it, or beside the trained)
                teachers = trained.clone()
                teachers[:, searched:] = fitted[a : a + t]
                bases = [teachers] if alpha_source == "teacher" else [trained, teachers]
                candidates += [teachers]
            for base in bases:
                for v in grid:
                    s_v = base.clone()
                    s_v[:, :searched] = v
                    candidates.append(s_v)
        best_r = torch.full((t,), float("inf"), dtype=torch.float64)
        best_data = torch.zeros(t, dtype=torch.float64)  # its error without the penalty
        best_z = torch.zeros(t, channels, k, dtype=torch.float64)
        best_s = torch.zeros(t, latent)

        queue = list(candidates)
        parts = _Parts(lobe, x, pairs, cos, y)
        y_sq = (y * y).sum(-1)  # ||y||^2 per texel and channel, every candidate's
        c = 0
        while c < len(queue):
            s = queue[c]
            blocks, gram, rhs = parts(s)  # of g cos: A (t, 3, M, K) in blocks of columns
            if c == 0:  # the trained field's own weights and latent on these pairs
                d, at = -y, 0
                for block in blocks:
                    width = block.shape[-1]
                    d = d + (block @ old_z[:, :, at : at + width, None])[..., 0]
                    at += width
                residual_before += float((d * d).sum())
            sq = y_sq
            if channels == 1:  # one weight for all channels: their problems summed
                gram, rhs, sq = (
                    gram.sum(1, keepdim=True),
                    rhs.sum(1, keepdim=True),
                    sq.sum(1, keepdim=True),
                )
            # ||A z - y||^2 + lam ||z - z_0||^2 is the NNLS of (G + lam I, b + lam z_0)
            prior = old_z if channels == 3 else old_z[:, :1]  # z_0, (t, 3 or 1, K)
            lam = ridge * gram.diagonal(dim1=-2, dim2=-1).mean(-1, keepdim=True)  # (t, c, 1)
            gram = gram + lam[..., None] * torch.eye(k, dtype=gram.dtype)
            rhs = rhs + lam * prior
            sq = sq + lam[..., 0] * (prior * prior).sum(-1)
            z, r = nnls(gram, rhs, sq)  # r: the penalised error, which chooses
            data = r - lam[..., 0] * ((z - prior) ** 2).sum(-1)  # the error alone
            r, data = r.sum(-1), data.sum(-1)
            better = r < best_r
            if c == 0 and alpha_source == "teacher" and fitted is not None:
                better = torch.zeros_like(better)  # the trained alpha is not a candidate
            best_r = torch.where(better, r, best_r)
            best_data = torch.where(better, data, best_data)
            best_z = torch.where(better[:, None, None], z, best_z)
            if s is not None:
                best_s = torch.where(better[:, None], s, best_s)
            c += 1
            if c == len(candidates) and factors:
                # analytic heads' alpha (its column after s): alphas around the texel's
                # own at its best s (texture.project_alphas; 1: the trained alpha only)
                for factor in factors:
                    s_a = best_s.clone()
                    alpha = (alpha_of(best_s[:, searched:]) * factor).clamp(ALPHA_MIN, 1.0)
                    s_a[:, searched:] = t_of(alpha)
                    queue.append(s_a)

        residual += float(best_data.sum())
        table[a : a + t, : channels * k] = best_z.reshape(t, channels * k).float()
        if latent:
            table[a : a + t, channels * k :] = best_s
    free = FrozenWeightField(table, resolution, channels=channels, latent=latent)
    bounded = texel_bound(free.weights(), envelope, free)
    scaled = (bounded[:, : channels * k] < table[:, : channels * k]).any(-1)
    out = FrozenWeightField(bounded, resolution, channels=channels, latent=latent)
    return out, {
        "resolution": resolution,
        "pairs_per_texel": pairs,
        "latents": latents if searched else 0,
        "ridge": ridge,
        "alphas": 1 + len(factors),
        "alpha_source": alpha_source if fitted is not None else "trained",
        "seconds": time.perf_counter() - t0,
        "teacher_seconds": teacher_seconds,
        "bounded_texel_share": float(scaled.float().mean()),
        "residual": residual,
        "residual_trained_field": residual_before,
    }


def projected(
    model: TexturedBRDF,
    teacher: Any,
    *,
    resolution: int,
    pairs: int,
    latents: int,
    seed: int,
    ridge: float = 0.0,
    alphas: int = 1,
    alpha_source: str = "trained",
) -> tuple[TexturedBRDF, dict[str, Any]]:
    """A normalised textured model (``normalized_textured``'s: one shared lobe network,
    its ``bound_envelope`` set) with its field replaced by :func:`project_field`'s at
    ``resolution``; the lobes and the normal field are kept.  Returns (model, figures)."""
    if model.bound_envelope is None:
        raise ValueError("projected: a model from normalized_textured (bound_envelope set)")
    lobe = model.lobes[0]
    field, info = project_field(
        lobe,
        model.field,
        teacher,
        model.bound_envelope,
        resolution=resolution,
        pairs=pairs,
        latents=latents,
        seed=seed,
        ridge=ridge,
        alphas=alphas,
        alpha_source=alpha_source,
    )
    return TexturedBRDF([lobe], field, model.normal).eval(), info


REFIT_POOL = 1 << 21  # the refit's pairs, drawn once (about 2.5 s of the teacher's calls)
REFIT_WARMUP = 50
REFIT_CHECK_PAIRS = 200_000  # fresh pairs the refit's error is measured on
REFIT_CHECK_EVERY = 500  # steps between the measures


def refit_lobes(
    model: TexturedBRDF,
    teacher: Any,
    *,
    steps: int,
    lr: float,
    batch: int,
    seed: int,
    pool: int = REFIT_POOL,
    check_pairs: int = REFIT_CHECK_PAIRS,
    check_every: int = REFIT_CHECK_EVERY,
    bounded: Callable[[TexturedBRDF], TexturedBRDF] | None = None,
    peak: float = cfgmod.Data().peak,
) -> tuple[TexturedBRDF, dict[str, Any]]:
    """A projected model's shared lobe network trained ``steps`` more steps with its
    projected field frozen (``texture.refit_steps``): the lobes were trained beside a
    coarser field, and the projection fitted each texel to those lobes; some steps of
    the lobes on the finer field lower the error that is left.  The loss is the sum the
    projection minimises, the squared error of f cos (over the pool's mean square of the
    teacher's f cos), not training's log loss: on the development principled the log
    loss lowered one teacher's error and raised the other's (docs/mitsuba.md, "The lobes
    refitted on the projected field").  Adam at ``lr`` (every parameter alike; a warm-up
    of :data:`REFIT_WARMUP` steps, then a cosine decay, :class:`neural_brdf.config.Train`'s
    defaults) on batches of ``batch`` pairs from ``pool`` pairs drawn as training draws
    them (:class:`~neural_brdf.train.textured_loop.PairPool`), seeded by ``seed``.  The
    field's weights and latent do not change; the lobes' albedo does, so the caller
    normalises the result again (``normalized_textured``: new tables, each texel bounded
    again).

    The refit's lobes are bounded again before they are used, and the bound costs what
    their albedo gained (on the development principled, one refit's error went from 5.32
    to 5.04 % raw and back to 5.38 % bounded).  So ``bounded`` (model -> the model as it
    will be bounded: the caller's ``normalized_textured``, deterministic) is applied before
    the relative RMSE of f cos is measured on ``check_pairs`` fresh pairs of the
    teacher's (drawn as training draws them, seed ``seed + 1``: neither the refit's nor
    any benchmark's), at the start and every ``check_every`` steps; the lobes of the
    least error are kept, so the refit never ends worse than its start on those pairs
    (it returns the model as it came when no step beat it).  None: measured raw.
    Returns (the model, its lobes raw, figures: the errors measured and the step
    kept)."""
    import copy

    from neural_brdf.train.loop import learning_rate, rel_rmse
    from neural_brdf.train.textured_loop import PairPool, pairs

    if steps < 1:
        raise ValueError(f"refit_lobes: steps >= 1, got {steps}")
    sched = cfgmod.Train(steps=steps, lr=lr, warmup=min(REFIT_WARMUP, steps - 1), seed=seed)
    t0 = time.perf_counter()
    out = copy.deepcopy(model)
    params = list(out.lobes.parameters())
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr)
    drawn = PairPool(teacher, pool, seed, peak=peak)  # data.peak, as training
    wi_all, wo_all, uv_all, f_all = drawn.at(0)
    scale = float(((f_all * wo_all[:, 2:3]) ** 2).mean().clamp_min(1e-30))
    check = pairs(teacher, check_pairs, np.random.default_rng(seed + 1))

    def error() -> float:
        m = out if bounded is None else bounded(out)
        with torch.no_grad():
            return rel_rmse(m(check[0], check[1], check[2]), check[3], check[1][:, 2:3])

    out.eval()
    errors = [(0, error())]
    best: tuple[float, int, dict[str, Any] | None] = (
        errors[0][1],
        0,
        copy.deepcopy(out.lobes.state_dict()),
    )
    gen = torch.Generator().manual_seed(seed)
    out.train()
    loss = torch.zeros(())
    for step in range(steps):
        if step and step % check_every == 0:
            out.eval()
            errors.append((step, error()))
            if errors[-1][1] < best[0]:
                best = (errors[-1][1], step, copy.deepcopy(out.lobes.state_dict()))
            out.train()
        for group in opt.param_groups:
            group["lr"] = learning_rate(sched, step)
        idx = torch.randint(0, len(wi_all), (batch,), generator=gen)
        wi, wo, uv, f = wi_all[idx], wo_all[idx], uv_all[idx], f_all[idx]
        cos = wo[:, 2:3]
        loss = (((out(wi, wo, uv) - f) * cos) ** 2).mean() / scale
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    out.eval()
    last = float(loss.detach())
    if not math.isfinite(last):
        raise FloatingPointError(f"refit_lobes: loss {last} at the last step")
    errors.append((steps, error()))
    if errors[-1][1] < best[0]:
        best = (errors[-1][1], steps, None)
    if best[2] is not None:  # an earlier state (the start's included) was better
        out.lobes.load_state_dict(best[2])
    for p in params:
        p.requires_grad_(False)
    return out, {
        "steps": steps,
        "lr": lr,
        "batch": batch,
        "pool": pool,
        "loss": "squared error of f cos",
        "final_loss": last,
        "check_pairs": check_pairs,
        "check_errors": [[k, e] for k, e in errors],
        "kept_step": best[1],
        "seconds": time.perf_counter() - t0,
        "pool_seconds": drawn.seconds,
    }


def refitted(
    model: TexturedBRDF,
    teacher: Any,
    bound: Callable[[TexturedBRDF], tuple[TexturedBRDF, list[dict[str, Any]]]],
    *,
    steps: int,
    lr: float,
    batch: int,
    seed: int,
    pool: int = REFIT_POOL,
    peak: float = cfgmod.Data().peak,
) -> tuple[TexturedBRDF, list[dict[str, Any]], dict[str, Any]]:
    """:func:`refit_lobes` checked as ``bound`` bounds its lobes (model -> (the bounded
    model, its lobes' table figures): the caller's ``normalized_textured``), then bound.
    Returns (the bounded model, the table figures, the refit's figures)."""
    out, info = refit_lobes(
        model,
        teacher,
        steps=steps,
        lr=lr,
        batch=batch,
        seed=seed,
        pool=pool,
        bounded=lambda m: bound(m)[0],
        peak=peak,
    )
    out, tables = bound(out)
    return out, tables, info


PROJECT_SEED = 23  # the projection's seed: the run's train.seed plus this
REFIT_SEED = 29  # the refit's


def project_and_refit(
    model: TexturedBRDF,
    teacher: Any,
    bound: Callable[[TexturedBRDF], tuple[TexturedBRDF, list[dict[str, Any]]]],
    *,
    resolution: int,
    pairs: int,
    latents: int,
    ridge: float,
    refit_steps: int,
    refit_lr: float,
    batch: int,
    pool: int,
    seed: int,
    alphas: int = 1,
    alpha_source: str = "trained",
    peak: float = cfgmod.Data().peak,
) -> tuple[TexturedBRDF, list[dict[str, Any]] | None, dict[str, Any]]:
    """``texture.project`` and ``texture.refit_steps`` after training: a model normalised
    by ``bound`` (``normalized_textured``) with its field projected (:func:`projected`,
    seed ``seed`` + :data:`PROJECT_SEED`) and, with ``refit_steps``, its lobes refitted
    on that field (:func:`refitted`, seed ``seed`` + :data:`REFIT_SEED`, at most
    :data:`REFIT_POOL` of ``pool`` pairs) and bounded again.  Returns (model, the
    refitted lobes' table figures or None without a refit, the projection's figures with
    the refit's under ``refit``).  The export and ``benchmarks/textured.py`` both call it."""
    model, info = projected(
        model,
        teacher,
        resolution=resolution,
        pairs=pairs,
        latents=latents,
        ridge=ridge,
        seed=seed + PROJECT_SEED,
        alphas=alphas,
        alpha_source=alpha_source,
    )
    tables = None
    if refit_steps:
        model, tables, info["refit"] = refitted(
            model,
            teacher,
            bound,
            steps=refit_steps,
            lr=refit_lr,
            batch=batch,
            seed=seed + REFIT_SEED,
            pool=min(REFIT_POOL, pool),
            peak=peak,
        )
    return model, tables, info
