"""Lobes conditioned on a latent: g(wi, wo; s), s in [0, 1], normalised by a table over (s, theta).

A textured model's lobes (:mod:`neural_brdf.train.textured_model`) may take, besides
(wi, wo), a latent s(uv) in [0, 1] looked up from the weight field (``texture.latent``:
one more column of the field's table, a sigmoid per texel, blended bilinearly: a convex
combination of values in [0, 1] stays in [0, 1]).  s lets one head change its shape over
the surface, for instance a GGX lobe whose roughness follows a roughness map, which a
convex mix of K fixed lobes can only approximate (docs/model.md, "Conditioned lobes").

Reciprocity: s depends on uv only, and the raw network's features are bit-exactly
symmetric in (wi, wo) (:mod:`neural_brdf.train.encoding`), so [features, s] is too.

Energy (docs/model.md, "Energy conservation that stays reciprocal", extended by one axis):

    g(wi, wo; s) = raw(wi, wo; s) / max(1, A+(s, wi), A+(s, wo))      per head and channel

with A+ a table over (s, theta) built as the isotropic table is, one axis more: A is
estimated by MIS quadrature (:func:`neural_brdf.physics.quadrature.albedo`) at S x K
nodes (S = ``normalization.grid_size`` in s, K = ``normalization.table_size`` in theta),
``sigmas`` standard errors are added, each node takes the maximum over its 3 x 3
neighbours (as the anisotropic table does over its two axes), the result is scaled by
1 + ``margin``, and the look-up interpolates bilinearly.  So A+ >= A on every cell where A
is monotone in each coordinate between the nodes: the standard of the project's other
tables.  Then int g cos dwo <= A(s, wi) / max(1, A+(s, wi)) <= 1 for every s the field
can produce, between texel centres included, and validate's furnace measures it at
random uv.  Isotropic encodings only (an anisotropic lobe's table is already 2-D).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn as nn

from neural_brdf.physics import quadrature
from neural_brdf.train.model import (
    RawBRDF,
    bilinear_corners,
    neighbour_max_2d,
    node_directions,
    table_coords,
)


class _AtLatent(nn.Module):
    """raw(wi, wo; s) with s fixed: the function the quadrature integrates."""

    def __init__(self, raw: RawBRDF, s: float):
        super().__init__()
        self.raw = raw
        self.s = float(s)

    def forward(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        s = torch.full((wi.shape[0], self.raw.latent), self.s, dtype=wi.dtype)
        return self.raw(wi, wo, s)


def conditioned_albedo_table(
    raw: RawBRDF,
    *,
    latent_nodes: int,
    size: int,
    samples: int,
    seed: int,
    sigmas: float,
    margin: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A+ at the (s, theta) nodes, (S, K, C) float32 (module doc), plus the raw estimate
    and its standard error, (S, K, C) float64.  s on S nodes j / (S - 1), theta on K
    nodes as the isotropic table's (:func:`~neural_brdf.train.model.node_directions`)."""
    if raw.latent != 1:
        raise ValueError(f"conditioned_albedo_table: one latent input, got {raw.latent}")
    if raw.anisotropic:
        raise ValueError("conditioned lobes: an isotropic encoding only")
    dirs = node_directions(size, False)
    est, errs = [], []
    with torch.no_grad():
        for j in range(latent_nodes):
            fn = _AtLatent(raw, j / (latent_nodes - 1)).eval()
            a, err = quadrature.albedo(fn, dirs, samples, seed=seed + 31 * j)
            est.append(a)
            errs.append(err)
    a, err = torch.stack(est), torch.stack(errs)  # (S, K, C)
    upper = neighbour_max_2d(a + sigmas * err)
    return (upper * (1.0 + margin)).float(), a, err


class ConditionedNormalizedBRDF(nn.Module):
    """raw(wi, wo; s) / max(1, A+(s, wi), A+(s, wo)) (module doc); ``identity`` when no
    node exceeds 1 (the bilinear look-up is then <= 1 everywhere, as for
    :class:`~neural_brdf.train.model.NormalizedBRDF`), and the graph carries no table.

    One table per head, not per channel: the graph's table holds, for each head, the
    largest of its three channels' A+ (``head_table``), so a look-up gathers H values
    instead of 3H (the gathers are what a renderer pays for).  Each channel is then
    divided by at least its own bound, so the argument above holds channel by channel;
    a head whose channels exceed 1 unequally is dimmed a little more in the lesser ones.
    ``table`` keeps the per-channel bounds (for the file's figures and the fold of
    :class:`~neural_brdf.train.textured_model.ScaledBRDF`)."""

    table: torch.Tensor  # buffers (register_buffer): (S, K, C) and (S * K, H)
    head_table: torch.Tensor

    def __init__(self, raw: RawBRDF, table: torch.Tensor):
        super().__init__()
        if table.dim() != 3:
            shape = tuple(table.shape)
            raise ValueError(f"ConditionedNormalizedBRDF: table (S, K, C), got {shape}")
        self.raw = raw
        self.anisotropic = False
        self.register_buffer("table", table.detach().float().clone())
        self.nodes = (int(table.shape[0]), int(table.shape[1]))  # (S, K): Python ints
        self.heads = max(1, int(table.shape[-1]) // 3)
        per_head = self.table.reshape(self.nodes[0] * self.nodes[1], self.heads, -1).amax(-1)
        self.register_buffer("head_table", per_head.contiguous())
        self.identity = bool((self.table <= 1.0).all())

    def _load_from_state_dict(self, *args: Any, **kwargs: Any) -> None:
        # a loaded table (a kept textured export, textured_store.load) decides whether the
        # division is the identity, not the table this module was built with
        super()._load_from_state_dict(*args, **kwargs)
        self.identity = bool((self.table <= 1.0).all())

    def lookup(self, w: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """(N, 3), (N, 1) -> (N, H): bilinear in (s, x), x = theta / (pi / 2)."""
        ns, k = self.nodes
        ts = s[..., 0] * (ns - 1)
        tx = table_coords(w, False) * (k - 1)
        i0 = torch.floor(ts).clamp(0, ns - 2)
        j0 = torch.floor(tx).clamp(0, k - 2)
        a, b = (ts - i0)[..., None], (tx - j0)[..., None]
        j = i0.long() * k + j0.long()  # flat index of the (s0, x0) corner
        return bilinear_corners(self.head_table, j, k, a, b)

    def forward(self, wi: torch.Tensor, wo: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        f = self.raw(wi, wo, s)
        if self.identity:
            return f
        denom = torch.maximum(self.lookup(wi, s), self.lookup(wo, s)).clamp_min(1.0)  # (N, H)
        if self.heads == 1:
            return f / denom
        return torch.cat(
            [f[:, 3 * h : 3 * h + 3] / denom[:, h : h + 1] for h in range(self.heads)], -1
        )


def normalized_conditioned(
    raw: RawBRDF, n: Any, *, seed: int
) -> tuple[ConditionedNormalizedBRDF, torch.Tensor, torch.Tensor]:
    """``raw`` wrapped with its (s, theta) table under the ``normalization`` settings
    ``n`` (:class:`neural_brdf.config.Normalization`: ``grid_size`` nodes in s,
    ``table_size`` in theta); returns (module, raw albedo, its standard error)."""
    table, a, err = conditioned_albedo_table(
        raw,
        latent_nodes=n.grid_size,
        size=n.table_size,
        samples=n.samples,
        seed=seed,
        sigmas=n.sigmas,
        margin=n.margin,
    )
    return ConditionedNormalizedBRDF(raw, table).eval(), a, err
