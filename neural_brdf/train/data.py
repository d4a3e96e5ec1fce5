"""Training pairs (wi, wo, f) drawn on the fly from a target: an analytic model, or
measured data (``target: {data: path}``: a MERL ``.binary``, an RGL ``.bsdf``, any format
of :mod:`neural_brdf.measured.formats`, by the file's suffix).

Analytic targets.  wi is uniform on the upper hemisphere.  wo is a mixture, by configured shares, of
uniform-hemisphere, cosine-weighted and the target's own importance sampling (so that
specular peaks are seen often), and of ``peak`` pairs (:func:`peak_pairs`): uniform in
the peak coordinate u_h (:func:`neural_brdf.train.encoding.peak_coordinate`) and in
theta_d, so that the region about the mirror direction, which the encoding stretches
over half of u_h, is trained for any target, down to normal incidence.  Without them a
diffuse target (Oren-Nayar) left the grid rows near u_h = 0 under-trained: compact clay
read 8 % off its target within a degree of the mirror direction at 70 degrees.  With wi
uniform and wo reflected about a half vector uniform in u_h (the peak pairs until
2026-12-07) the corner u_h, theta_d -> 0 (wi = wo = the normal) was not: the quickstart
gold read 1.9 times its target there, the clay 7 % off (docs/model.md).  A sampled wo below
the horizon (possible with visible-normal or Phong lobes) is replaced by a
cosine-distributed one, since the network is 0 there by construction and the pair would
teach nothing.

Evaluating an analytic target costs more than a training step of the small MLP, so
pairs live in a ring-buffer pool: each step replaces ``batch_size / reuse`` of the
oldest pairs with fresh ones and draws the batch from the whole pool.  With
``reuse = 1`` every pair is fresh.  All randomness comes from one seeded
``torch.Generator`` whose state is checkpointed with the pool, so a resumed run
continues exactly where it stopped.
"""

from __future__ import annotations

import math

import numpy as np
import torch

import analytic
from analytic import frame
from neural_brdf import config as cfgmod
from neural_brdf.errors import InputError
from neural_brdf.measured import formats
from neural_brdf.measured.base import MeasuredBRDF
from neural_brdf.train import encoding as enc


class MeasuredTarget:
    """Measured data as a training target: a file of any format of
    :mod:`neural_brdf.measured.formats` (by its suffix), wrapped.  ``f`` (torch) and
    ``eval`` (numpy) are the format's lookup, ``draw`` gives training pairs on the
    measured support, ``grid_pairs`` the pairs where the file is exact (MERL: measured
    bin centres; RGL: value nodes).  No sampler: the quadratures that take a target's
    proposal (``target=``) skip it."""

    def __init__(self, brdf: MeasuredBRDF):
        self.brdf = brdf
        self.source = brdf.source
        self.anisotropic = bool(brdf.anisotropic)

    @classmethod
    def from_file(cls, path, *, key: str = "target.data") -> MeasuredTarget:
        """A measured file (its format by its suffix, :func:`formats.read`) as a target;
        an unknown suffix or a bad file raises a one-line ConfigError naming ``key``."""
        try:
            return cls(formats.read(path))
        except InputError as e:
            raise cfgmod.ConfigError(f"{key}: {e}") from None

    def describe(self) -> str:
        return self.brdf.describe()

    def eval(self, wi, wo) -> np.ndarray:
        return self.brdf.eval(wi, wo)

    def f(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        out = self.brdf.eval(wi.detach().cpu().double().numpy(), wo.detach().cpu().double().numpy())
        return torch.from_numpy(out).to(wi.dtype)

    def draw(self, n: int, gen: torch.Generator):
        """``n`` training pairs (float32) on the measured support; seeded by ``gen``."""
        seed = int(torch.randint(0, 2**62, (1,), generator=gen))
        wi, wo, f = self.brdf.sample_pairs(n, rng=seed)
        return tuple(torch.from_numpy(x).float() for x in (wi, wo, f))

    def grid_pairs(self, n: int | None = None, seed: int = 0):
        """(wi, wo, f) float64 tensors where the file is exact (``brdf.grid_pairs``): all
        of them, or ``n`` drawn without replacement."""
        pairs = self.brdf.grid_pairs(n, seed)
        return tuple(torch.from_numpy(np.ascontiguousarray(x)) for x in pairs)


def refuse_images(target: cfgmod.Target, source: str | None = None) -> None:
    """ConfigError (one line, naming ``source``, the config file, when given) when
    ``target`` is ``target.images``: an images fit has no target BRDF, and its
    ``target.model`` is the unused default (a Lambertian), which a reference (``validate
    --reference``, ``render --reference``) or a bake would silently stand for it."""
    if target.kind == "images":
        where = f"{source}: " if source else ""
        raise cfgmod.ConfigError(
            f"{where}target.images: an images fit has no target BRDF (it is fitted to "
            "photographs; the fitted BRDF is its run's model.onnx); give a config whose "
            "target is a BRDF"
        )


def build_target(target: cfgmod.Target, *, source: str | None = None):
    """The model of ``target``: an analytic BRDF, a :class:`MeasuredTarget` for
    ``target.data``, or a :class:`neural_brdf.measured.mitsuba.MitsubaTarget` for
    ``target.mitsuba`` (a :class:`neural_brdf.measured.textured.TexturedMitsubaTarget`
    when it varies over the surface); bad names, parameters or files raise ConfigError
    (InputError), and so does ``target.images`` (:func:`refuse_images`).  ``source``:
    the config file, which each ConfigError then names first (once: callers add
    nothing)."""
    try:
        return _build_target(target)
    except cfgmod.ConfigError as e:
        if source is None:
            raise
        raise cfgmod.ConfigError(f"{source}: {e}") from None


def _build_target(target: cfgmod.Target):
    refuse_images(target)
    if target.data is not None:
        return MeasuredTarget.from_file(target.data)
    if target.mitsuba is not None:  # Mitsuba is imported by this target only
        from neural_brdf.measured.mitsuba import MitsubaTarget, VariesOverSurface

        try:
            return MitsubaTarget(target.mitsuba, variant=target.variant)
        except VariesOverSurface:  # textures, a normal or bump map: f(wi, wo, uv)
            from neural_brdf.measured.textured import TexturedMitsubaTarget

            return TexturedMitsubaTarget(target.mitsuba, variant=target.variant or "llvm_ad_rgb")
    if target.model not in analytic.available():
        raise cfgmod.ConfigError(
            f"target.model: unknown model {target.model!r}; available: {analytic.available()}"
        )
    try:
        analytic.model_class(target.model)
    except ImportError as e:  # the cause on the same line: a missing dependency or a typo
        raise cfgmod.ConfigError(
            f"target.model: {target.model!r} is registered but its module is not "
            f"importable: {type(e).__name__}: {e}"
        ) from None
    try:
        brdf = analytic.create(target.model, **target.params)
    except (analytic.ParameterError, TypeError) as e:
        raise cfgmod.ConfigError(f"target.params: {e}") from None
    if not reflects(brdf):  # else a relative error of 1e143 % and "physics PASSED"
        raise cfgmod.ConfigError(
            f"target.params: {target.model} with these parameters reflects no light (f = 0 "
            "at every probed pair): there is nothing to learn or to compare with"
        )
    return brdf


def reflects(brdf: analytic.BRDF, pairs: int = 4096) -> bool:
    """Whether ``brdf`` is above 0 somewhere: ``pairs`` fixed pairs, wi uniform and wo
    cosine-distributed and near the mirror direction (a sharp lobe is seen too)."""
    g = torch.Generator().manual_seed(12345)
    wi = uniform_wi(pairs, g)
    wo = frame.square_to_cosine_hemisphere(torch.rand(pairs, 2, generator=g))
    mirror = wi * torch.tensor([-1.0, -1.0, 1.0])
    both = (torch.cat([wi, wi]), torch.cat([wo, mirror]))
    with torch.no_grad():
        return bool((brdf.eval(*both) > 0).any())


def uniform_wi(n: int, gen: torch.Generator) -> torch.Tensor:
    return frame.square_to_uniform_hemisphere(torch.rand(n, 2, generator=gen))


def peak_tan2(u_h: torch.Tensor) -> torch.Tensor:
    """tan^2(theta_h / 2) of the encoding's peak coordinate u_h: the inverse of its
    log-stretched map (:mod:`neural_brdf.encodings.angles`), so that uniform u_h gives
    half vectors uniform in u_h."""
    return enc.PEAK_EPS * torch.expm1(u_h / enc.PEAK_LOG_SCALE)


def about_mirror(wi: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """wi reflected about a half vector h with u_h(h) = u[:, 0] (the encoding's peak
    coordinate, so uniform u gives pairs uniform in u_h) and azimuth 2 pi u[:, 1]."""
    t2 = peak_tan2(u[:, 0])
    cos_h = (1.0 - t2) / (1.0 + t2)
    sin_h = 2.0 * torch.sqrt(t2) / (1.0 + t2)
    phi = 2.0 * math.pi * u[:, 1]
    h = torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h], -1)
    return 2.0 * (wi * h).sum(-1, keepdim=True) * h - wi


def peak_pairs(u: torch.Tensor, dtype: torch.dtype = torch.float32):
    """(wi, wo) uniform in the encoding's (u_h, theta_d) square: the Rusinkiewicz (1998)
    angles theta_h with peak coordinate u_h = u[:, 0] (:func:`about_mirror`'s mapping),
    phi_h = 2 pi u[:, 1], theta_d = pi/2 u[:, 2], phi_d = 2 pi u[:, 3]
    (:func:`analytic.frame.from_rusinkiewicz`).  Unlike wi uniform on the hemisphere,
    which puts one pair in 1,700 within 2 degrees of the normal, this trains the corner
    u_h, theta_d -> 0 (wi = wo = the normal) that the encoding stretches over half of
    u_h.  Either direction may be below the horizon."""
    u = u.double()
    theta_h = 2.0 * torch.atan(torch.sqrt(peak_tan2(u[:, 0])))
    wi, wo = frame.from_rusinkiewicz(
        theta_h, 2.0 * math.pi * u[:, 1], 0.5 * math.pi * u[:, 2], 2.0 * math.pi * u[:, 3]
    )
    return wi.to(dtype), wo.to(dtype)


def peak_share(wi_alt: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The peak share's (wi, wo), as many as ``wi_alt``: pairs uniform in (u_h, theta_d)
    (:func:`peak_pairs`); one with a direction below the horizon is replaced by
    ``wi_alt``'s own pair about the mirror direction (:func:`about_mirror`)."""
    n = len(wi_alt)
    wi_peak, wo_peak = peak_pairs(torch.rand(n, 4, generator=g))
    mirror = about_mirror(wi_alt, torch.rand(n, 2, generator=g))
    above = ((wi_peak[:, 2] > 0) & (wo_peak[:, 2] > 0))[:, None]
    return torch.where(above, wi_peak, wi_alt), torch.where(above, wo_peak, mirror)


class PairSource:
    """Fresh (wi, wo, f) batches from a target, float32."""

    def __init__(self, target: analytic.BRDF, data: cfgmod.Data, gen: torch.Generator):
        self.target, self.gen = target, gen
        total = data.uniform + data.cosine + data.importance + data.peak
        self.shares = tuple(
            x / total for x in (data.uniform, data.cosine, data.importance, data.peak)
        )

    @torch.no_grad()
    def draw(self, n: int):
        g = self.gen
        n_uni = int(round(n * self.shares[0]))
        n_imp = int(round(n * self.shares[2]))
        n_peak = int(round(n * self.shares[3]))
        n_cos = n - n_uni - n_imp - n_peak
        wi = uniform_wi(n, g)
        wo_uni = frame.square_to_uniform_hemisphere(torch.rand(n_uni, 2, generator=g))
        wo_cos = frame.square_to_cosine_hemisphere(torch.rand(n_cos, 2, generator=g))
        k = n_uni + n_cos
        wo_imp = self.target.sample_dir_t(wi[k : k + n_imp], torch.rand(n_imp, 2, generator=g))
        wi_peak, wo_peak = peak_share(wi[k + n_imp :], g)
        wi = torch.cat([wi[: k + n_imp], wi_peak], 0)
        wo = torch.cat([wo_uni, wo_cos, wo_imp.float(), wo_peak], 0)
        backup = frame.square_to_cosine_hemisphere(torch.rand(n, 2, generator=g))
        wo = torch.where(wo[:, 2:3] > 0, wo, backup)
        wi, wo = frame.normalize(wi), frame.normalize(wo)
        f = self.target.f(wi, wo).float()
        return wi, wo, f


class MeasuredPairSource:
    """Fresh (wi, wo, f) batches from measured data: the format's own draw on its
    support (``MeasuredBRDF.sample_pairs``), and for a format whose draw is not dense
    at the mirror direction (``dense_at_peak`` False: RGL's, wo from the file's sampler
    and the cosine) the ``data.peak`` share of peak pairs (:func:`peak_pairs`) as for an
    analytic target, evaluated by the file.  The other shares do not apply.  MERL's
    draw, uniform over its bins in index space, puts 1/90 of its pairs in its first
    theta_h bin (within 0.011 degrees); a gold GGX baked to ``.bsdf`` put 1.5e-5 of
    them in the grid's first column (u_h < 1/31) and trained to 93 % off its analytic
    peak at 3000 steps (exit 0: no peak check against a file), where its MERL bake read
    0.96 %."""

    def __init__(self, target: MeasuredTarget, data: cfgmod.Data, gen: torch.Generator):
        self.target, self.gen = target, gen
        total = data.uniform + data.cosine + data.importance + data.peak
        dense = bool(getattr(target.brdf, "dense_at_peak", False))
        self.peak = 0.0 if dense or total <= 0 else data.peak / total

    def draw(self, n: int):
        n_peak = int(round(n * self.peak))
        if n_peak == 0:
            return self.target.draw(n, self.gen)
        g = self.gen
        wi_p, wo_p = peak_share(uniform_wi(n_peak, g), g)
        backup = frame.square_to_cosine_hemisphere(torch.rand(n_peak, 2, generator=g))
        wo_p = torch.where(wo_p[:, 2:3] > 0, wo_p, backup)
        wi_p, wo_p = frame.normalize(wi_p), frame.normalize(wo_p)
        f_p = self.target.f(wi_p.double(), wo_p.double()).float()
        if n_peak == n:  # data.peak the only share (the file's draw of 0 pairs fails)
            return wi_p, wo_p, f_p
        wi, wo, f = self.target.draw(n - n_peak, g)
        return torch.cat([wi, wi_p]), torch.cat([wo, wo_p]), torch.cat([f, f_p])


def pair_source(target, data: cfgmod.Data, gen: torch.Generator):
    if isinstance(target, MeasuredTarget):
        return MeasuredPairSource(target, data, gen)
    return PairSource(target, data, gen)


class Pool:
    """Ring buffer of pairs, refreshed by ``batch_size / reuse`` pairs per batch.

    The pairs live in one (size, 9) tensor, rows (wi, wo, f), so that a batch is one
    gather.  Fresh pairs are drawn ``FRESH_CHUNK`` at a time (a whole number of
    refreshes) and handed out a refresh per batch: evaluating the target 1,024 pairs at
    a time cost 2.2 us a pair, 16,384 at a time 0.44 us (issue 21).  With ``device`` a
    GPU, the pool lives there and the batch indices are drawn there (their generator
    seeded from ``source.gen``), so a step copies nothing from the host; fresh chunks
    are drawn on the host and copied once per chunk.
    """

    FRESH_CHUNK = 16384

    def __init__(self, source, data: cfgmod.Data, device: torch.device | str = "cpu"):
        self.source, self.gen = source, source.gen
        self.device = torch.device(device)
        self.batch_size = data.batch_size
        self.refresh = max(1, int(math.ceil(data.batch_size / data.reuse)))
        self.chunk = self.refresh * max(1, self.FRESH_CHUNK // self.refresh)
        self.pairs = torch.cat(source.draw(data.pool_size), -1).to(self.device)
        self.head = 0
        self.fresh = self.pairs[:0]  # drawn, not yet in the pool
        self.fresh_head = 0
        if self.device.type == "cpu":
            self.pick_gen = self.gen
        else:  # one seed from the host's stream: the picks then stay on the device
            seed = int(torch.randint(0, 2**62, (1,), generator=self.gen))
            self.pick_gen = torch.Generator(self.device).manual_seed(seed)

    @property
    def f(self) -> torch.Tensor:
        return self.pairs[:, 6:9]

    def _next_fresh(self) -> torch.Tensor:
        if self.fresh_head >= len(self.fresh):
            self.fresh = torch.cat(self.source.draw(self.chunk), -1).to(self.device)
            self.fresh_head = 0
        out = self.fresh[self.fresh_head : self.fresh_head + self.refresh]
        self.fresh_head += self.refresh
        return out

    def batch(self):
        size = len(self.pairs)
        fresh = self._next_fresh()
        if self.head + self.refresh <= size:
            self.pairs[self.head : self.head + self.refresh] = fresh
        else:
            idx = (self.head + torch.arange(self.refresh, device=self.device)) % size
            self.pairs[idx] = fresh
        self.head = int((self.head + self.refresh) % size)
        pick = torch.randint(
            0, size, (self.batch_size,), generator=self.pick_gen, device=self.device
        )
        b = self.pairs[pick]
        return b[:, 0:3], b[:, 3:6], b[:, 6:9]

    def state_dict(self) -> dict:
        state = {
            "pairs": self.pairs.cpu(),
            "head": self.head,
            "fresh": self.fresh[self.fresh_head :].cpu(),
            "rng": self.gen.get_state(),
        }
        if self.pick_gen is not self.gen:
            state["pick_rng"] = self.pick_gen.get_state()
        return state

    def load_state_dict(self, state: dict) -> None:
        if "pairs" in state:
            self.pairs = state["pairs"].to(self.device)
        else:  # the first layout: wi, wo, f apart
            self.pairs = torch.cat([state["wi"], state["wo"], state["f"]], -1).to(self.device)
        self.head = int(state["head"])
        self.fresh = state.get("fresh", self.pairs[:0]).to(self.device)
        self.fresh_head = 0
        self.gen.set_state(state["rng"])
        if "pick_rng" in state and self.pick_gen is not self.gen:
            self.pick_gen.set_state(state["pick_rng"])


def accuracy_pairs(target, n: int | None, seed: int):
    """Pairs (float64) on which a model is compared with ``target``: importance-sampled
    for an analytic target (``n`` of them), measured bin centres for measured data (all
    of them when ``n`` is None)."""
    if isinstance(target, MeasuredTarget):
        return target.grid_pairs(n, seed)
    if n is None:
        raise ValueError("n: an analytic target needs a number of pairs")
    return importance_pairs(target, n, seed)


@torch.no_grad()
def importance_pairs(target: analytic.BRDF, n: int, seed: int):
    """Pairs for the accuracy metric: wi uniform, wo from the target's sampler (float64).

    Pairs whose wo falls below the horizon are kept: f = 0 there for both models.
    """
    g = torch.Generator().manual_seed(seed)
    wi = frame.square_to_uniform_hemisphere(torch.rand(n, 2, generator=g, dtype=torch.float64))
    wo = target.sample_dir_t(wi, torch.rand(n, 2, generator=g, dtype=torch.float64))
    wo = frame.normalize(wo)
    return wi, wo, target.f(wi, wo)
