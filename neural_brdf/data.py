"""Training pairs (wi, wo, f) drawn on the fly from a target model.

wi is uniform on the upper hemisphere.  wo is a mixture, by configured shares, of
uniform-hemisphere, cosine-weighted and the target's own importance sampling (so that
specular peaks are seen often).  A sampled wo below the horizon (possible with
visible-normal or Phong lobes) is replaced by a cosine-distributed one, since the
network is 0 there by construction and the pair would teach nothing.

Evaluating an analytic target costs more than a training step of the small MLP, so
pairs live in a ring-buffer pool: each step replaces ``batch_size / reuse`` of the
oldest pairs with fresh ones and draws the batch from the whole pool.  With
``reuse = 1`` every pair is fresh.  All randomness comes from one seeded
``torch.Generator`` whose state is checkpointed with the pool, so a resumed run
continues exactly where it stopped.
"""

from __future__ import annotations

import math

import torch

import analytic
from analytic import frame

from . import config as cfgmod


def build_target(target: cfgmod.Target) -> analytic.BRDF:
    """The analytic model of ``target``; bad names or parameters raise ConfigError."""
    if target.data is not None:
        raise cfgmod.ConfigError("target.data: measured-data targets are not supported yet; "
                                 "use target.model and target.params")
    if target.model not in analytic.available():
        raise cfgmod.ConfigError(f"target.model: unknown model {target.model!r}; "
                                 f"available: {analytic.available()}")
    try:
        analytic.model_class(target.model)
    except ImportError:
        raise cfgmod.ConfigError(f"target.model: {target.model!r} is registered but its module "
                                 "is not importable in this installation") from None
    try:
        return analytic.create(target.model, **target.params)
    except (analytic.ParameterError, TypeError) as e:
        raise cfgmod.ConfigError(f"target.params: {e}") from None


def uniform_wi(n: int, gen: torch.Generator) -> torch.Tensor:
    return frame.square_to_uniform_hemisphere(torch.rand(n, 2, generator=gen))


class PairSource:
    """Fresh (wi, wo, f) batches from a target, float32."""

    def __init__(self, target: analytic.BRDF, data: cfgmod.Data, gen: torch.Generator):
        self.target, self.gen = target, gen
        total = data.uniform + data.cosine + data.importance
        self.shares = (data.uniform / total, data.cosine / total, data.importance / total)

    @torch.no_grad()
    def draw(self, n: int):
        g = self.gen
        n_uni = int(round(n * self.shares[0]))
        n_imp = int(round(n * self.shares[2]))
        n_cos = n - n_uni - n_imp
        wi = uniform_wi(n, g)
        wo_uni = frame.square_to_uniform_hemisphere(torch.rand(n_uni, 2, generator=g))
        wo_cos = frame.square_to_cosine_hemisphere(torch.rand(n_cos, 2, generator=g))
        wo_imp, _ = self.target.sample_t(wi[n_uni + n_cos:], torch.rand(n_imp, 2, generator=g))
        wo = torch.cat([wo_uni, wo_cos, wo_imp.float()], 0)
        backup = frame.square_to_cosine_hemisphere(torch.rand(n, 2, generator=g))
        wo = torch.where(wo[:, 2:3] > 0, wo, backup)
        wo = frame.normalize(wo)
        f = self.target.f(wi, wo).float()
        return wi, wo, f


class Pool:
    """Ring buffer of pairs, refreshed by ``batch_size / reuse`` pairs per batch."""

    def __init__(self, source: PairSource, data: cfgmod.Data):
        self.source, self.gen = source, source.gen
        self.batch_size = data.batch_size
        self.refresh = max(1, int(math.ceil(data.batch_size / data.reuse)))
        self.wi, self.wo, self.f = source.draw(data.pool_size)
        self.head = 0

    def batch(self):
        size = len(self.wi)
        idx = (self.head + torch.arange(self.refresh)) % size
        self.wi[idx], self.wo[idx], self.f[idx] = self.source.draw(self.refresh)
        self.head = int((self.head + self.refresh) % size)
        pick = torch.randint(0, size, (self.batch_size,), generator=self.gen)
        return self.wi[pick], self.wo[pick], self.f[pick]

    def state_dict(self) -> dict:
        return {"wi": self.wi, "wo": self.wo, "f": self.f, "head": self.head,
                "rng": self.gen.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.wi, self.wo, self.f = state["wi"], state["wo"], state["f"]
        self.head = int(state["head"])
        self.gen.set_state(state["rng"])


@torch.no_grad()
def importance_pairs(target: analytic.BRDF, n: int, seed: int):
    """Pairs for the accuracy metric: wi uniform, wo from the target's sampler (float64).

    Pairs whose wo falls below the horizon are kept: f = 0 there for both models.
    """
    g = torch.Generator().manual_seed(seed)
    wi = frame.square_to_uniform_hemisphere(torch.rand(n, 2, generator=g, dtype=torch.float64))
    wo, _ = target.sample_t(wi, torch.rand(n, 2, generator=g, dtype=torch.float64))
    wo = frame.normalize(wo)
    return wi, wo, target.f(wi, wo)
