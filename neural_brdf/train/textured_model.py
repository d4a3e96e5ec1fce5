"""A spatially varying neural BRDF: a field of lobe weights over uv times K shared lobes.

    f(wi, wo, uv) = sum_k z_k(uv) g_k(wi, wo)                  per RGB channel, 1/sr

the design of docs/model.md, "Spatially varying models: the contract" (issue 30):

* :class:`WeightField`: per texel, K + 1 logits and their softmax; the last slot is
  "nothing" (it absorbs energy), so each texel's K weights are >= 0 with sum <= 1.  It
  is looked up as a renderer samples a texture: WRAP (repeat, u -> u - floor(u)) and
  BILINEAR filtering between texel centres, texel (i, j) (column i along u, row j along
  v) centred at ((i + 0.5) / R, (j + 0.5) / R), the convention of GPU textures and of
  Mitsuba 3's ``bitmap`` (Dr.Jit's texture.h: position = uv * resolution - 0.5; its
  default ``wrap_mode`` is repeat and ``filter_type`` bilinear).  The table is stored
  row-major as an image, [v row, u column]: flat index j * R + i.
* :class:`TexturedBRDF`: the K lobes g_k, each a :class:`~neural_brdf.train.model.RawBRDF`
  while training and a :class:`~neural_brdf.train.model.NormalizedBRDF` once
  :func:`normalized_textured` has tabulated its albedo bound.

Why this keeps the physics between texels (docs/model.md, same section): a bilinear blend
of texels is a convex combination of their weight vectors, and the set {z >= 0,
sum z <= 1} is convex, so z(uv) stays in it at every uv.  Then

* reciprocity is exact: each g_k is bit-exactly symmetric (its encoding), z depends on uv
  only, and the sum is formed in the same order for (wi, wo) and (wo, wi);
* albedo: int f cos dwo = sum_k z_k int g_k cos dwo <= sum_k z_k A+_k <= max_k A+_k,
  at most 1 + the tables' margin once each lobe is normalised ("Energy conservation that
  stays reciprocal").  With ``texture.lobe_bound: texel`` the lobes stay raw and each
  texel's z is scaled so that sum_k z_k A+_k <= 1 at every node of incidence
  (:func:`texel_bound`): linear constraints in z, which every convex blend keeps.

Export, ``neural_brdf.export.to_onnx_bytes(exportable(model), opset,
inputs=TEXTURED_INPUTS)``: the softmax is evaluated once and the [R*R, K] weight table
baked into the graph as a constant (no Softmax or Exp in it); the look-up
is Floor, Sub, Mul, Add, Less, Where, Clip, Cast and Gather, as for
:class:`~neural_brdf.train.model.FeatureGrid`.  The graph is total
(:class:`TotalTexturedBRDF`): any input row gives a finite f, and 0 where wi, wo or uv
holds a NaN or an infinity (or a direction has zero length).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import torch
import torch.nn as nn

from neural_brdf import config as cfgmod
from neural_brdf.fileformat import SIGNATURES
from neural_brdf.train.conditioned import ConditionedNormalizedBRDF, normalized_conditioned
from neural_brdf.train.encoding import is_anisotropic
from neural_brdf.train.ggx_heads import GGXLobes, analytic_count, with_head_envelope
from neural_brdf.train.model import NormalizedBRDF, RawBRDF, albedo_table, unit_or_invalid

TEXTURED_INPUTS = SIGNATURES[1]  # ("wi", "wo", "uv")


def bilinear_wrap(
    table: torch.Tensor,
    uv: torch.Tensor,
    resolution: int | tuple[int, int],
    scale: torch.Tensor | None = None,
) -> torch.Tensor:
    """The bilinear, wrapping look-up of ``table`` [Rv*Ru, C] (row-major [v, u]) at ``uv``
    [N, 2] (finite) -> [N, C].  ``resolution``: R (a square R x R table) or (Ru, Rv),
    the texels along u and along v; a rectangular table also needs ``scale``, the
    tensor [Ru, Rv] (a module's buffer, so that tracing records it as a constant).

    Per axis: x = (u - floor(u)) * R - 0.5, i0 = floor(x) in [-1, R - 1], a = x - i0; the
    two texels are i0 and i0 + 1, each wrapped into [0, R) (-1 -> R - 1, R -> 0).  A u
    just below an integer may round to u - floor(u) = 1.0: then x = R - 0.5, i0 = R - 1
    and a = 0.5, the same texels and weights as at u = 0.  The indices are clipped to
    [0, R - 1] as well (a no-op for finite uv) before the Cast, so no Gather index can
    leave the table.
    """
    ru, rv = (resolution, resolution) if isinstance(resolution, int) else resolution
    # a square table keeps scalar constants (the graph of every earlier file); a
    # rectangular one has a pair (Ru, Rv), the same ops broadcast
    if ru != rv and scale is None:
        raise ValueError(f"bilinear_wrap: a {ru} x {rv} table needs scale = [Ru, Rv]")
    r: float | torch.Tensor = float(ru) if ru == rv else scale.to(uv.dtype)  # type: ignore[union-attr]
    frac = uv - torch.floor(uv)  # wrap (repeat): in [0, 1]
    x = frac * r - 0.5
    i0 = torch.floor(x)
    a = x - i0  # (N, 2), in [0, 1)
    i1 = i0 + 1.0
    if isinstance(r, float):
        i0 = torch.where(i0 < 0.0, i0 + r, i0).clamp(0.0, r - 1.0)
        i1 = torch.where(i1 > r - 1.0, i1 - r, i1).clamp(0.0, r - 1.0)
    else:
        i0 = torch.where(i0 < 0.0, i0 + r, i0).clamp(min=0.0).minimum(r - 1.0)
        i1 = torch.where(i1 > r - 1.0, i1 - r, i1).clamp(min=0.0).minimum(r - 1.0)
    u0, v0 = i0[..., 0].long(), i0[..., 1].long()
    u1, v1 = i1[..., 0].long(), i1[..., 1].long()
    au, av = a[..., 0:1], a[..., 1:2]
    n = int(ru)
    return (
        table[v0 * n + u0] * (1 - au) * (1 - av)
        + table[v0 * n + u1] * au * (1 - av)
        + table[v1 * n + u0] * (1 - au) * av
        + table[v1 * n + u1] * au * av
    )


# The field's detail check (:func:`detail_warning`): f cos at normal
# incidence and at a 45-degree mirror pair, on a grid DETAIL_PROBE times finer than the
# field (twice above DETAIL_MAX / DETAIL_PROBE texels, not measured above DETAIL_MAX); a
# warning above DETAIL_WARN relative RMSE (chosen on a walkthrough's own teachers: the
# tour's procedural roughplastic 2.9 % at 32², a principled and a blend with bitmaps
# 23 and 19 %, a checkerboard 22 %; the three were 15, 9 and 28 % off after training).
_S = 0.5**0.5
DETAIL_PAIRS = (
    ((0.0, 0.0, 1.0), (0.0, 0.0, 1.0)),
    ((_S, 0.0, _S), (-_S, 0.0, _S)),
)
DETAIL_PROBE = 4
DETAIL_MAX = 1024
DETAIL_WARN = 0.1


def detail_error(target: Any, texels: int) -> float:
    """How far a field of ``texels`` x ``texels`` texels, looked up as the file does
    (:func:`bilinear_wrap`), can be from a spatially varying ``target``
    (``eval(wi, wo, uv)``): f cos at :data:`DETAIL_PAIRS`, sampled at the field's texel
    centres and interpolated to a grid :data:`DETAIL_PROBE` times finer (twice above
    :data:`DETAIL_MAX` / DETAIL_PROBE texels; 0, not measured, above DETAIL_MAX),
    against the teacher there; the relative RMSE over the grid, both pairs and RGB.
    What a field that samples the teacher loses; training fits the texels instead, and
    may lose less or more (a walkthrough's checkerboard: 22 % here, 28 % after
    training)."""
    if texels > DETAIL_MAX:
        return 0.0
    n = DETAIL_PROBE * texels if DETAIL_PROBE * texels <= DETAIL_MAX else 2 * texels
    fine, coarse = _uv_grid(n), _uv_grid(texels)
    err = ref = 0.0
    for wi, wo in DETAIL_PAIRS:
        at_fine = _f_cos_at(target, wi, wo, fine)
        table = torch.from_numpy(_f_cos_at(target, wi, wo, coarse))  # row-major [v, u]
        interp = bilinear_wrap(table, torch.from_numpy(fine), texels).numpy()
        err += float(np.sum((interp - at_fine) ** 2))
        ref += float(np.sum(at_fine**2))
    return float(np.sqrt(err / ref)) if ref > 0 else 0.0


def detail_warning(target: Any, texels: int) -> str | None:
    """One line when :func:`detail_error` of the file's field exceeds DETAIL_WARN."""
    error = detail_error(target, texels)
    if not error > DETAIL_WARN:
        return None
    return (
        f"{target.where}: the teacher varies over uv more finely than the field of "
        f"{texels}x{texels} texels: f cos, sampled at its texel centres and "
        f"interpolated, is {100 * error:.0f} % off the teacher between them; raise "
        "texture.resolution or set texture.project (docs/mitsuba.md)"
    )


def _uv_grid(n: int) -> np.ndarray:
    """The centres of n x n texels, (n * n, 2), row-major [v, u] as the field's table."""
    axis = (np.arange(n) + 0.5) / n
    return np.stack(np.meshgrid(axis, axis, indexing="xy"), -1).reshape(-1, 2)


def _f_cos_at(target: Any, wi: tuple, wo: tuple, uv: np.ndarray) -> np.ndarray:
    """The target's f cos at the one pair (wi, wo) at every uv: (len(uv), 3)."""
    k = len(uv)
    f = np.asarray(target.eval(np.tile(wi, (k, 1)), np.tile(wo, (k, 1)), uv), dtype=np.float64)
    return f * wo[2]


class WeightField(nn.Module):
    """Per-texel logits -> K non-negative weights with sum <= 1 at every uv, one set for
    all channels (``channels`` 1: logits [R*R, K + 1]) or one per RGB channel
    (``channels`` 3: logits [R*R, 3, K + 1]; docs/model.md: per-channel weights tint the
    shared lobes, the bound holds per channel).

    The softmax is taken per texel (and channel) over the K + 1 slots and the last
    ("nothing") dropped; :meth:`forward` looks the weights up at uv by
    :func:`bilinear_wrap` (module doc: WRAP, BILINEAR, texel centres at ((i + 0.5) / R,
    (j + 0.5) / R), flat index j * R + i).  The table is [R*R, C*K], column c * K + k.

    ``levels`` L > 1 (``texture.field_levels``) changes how the logits are learned, not
    what the field is: a texel's logits (and latent logit) are its own plus those of
    L - 1 coarser tables (R/2, R/4, ...) looked up bilinearly at its centre.  The
    function is still a table of R x R weight vectors blended bilinearly (export bakes
    it), but each coarse logit sees the pairs of many texels: a fine field's texels see
    few pairs of a batch each, and on the development principled R = 256 with one level
    trained worse than R = 64 although its block-averaged teacher is 3.5 times closer.  The
    coarsest table starts random (``init_std``), the finer ones at 0.
    """

    def __init__(
        self,
        resolution: int,
        lobes: int,
        *,
        channels: int = 1,
        init_std: float = 1.0,
        latent: int = 0,
        levels: int = 1,
    ):
        super().__init__()
        if resolution < 1 or lobes < 1:
            raise ValueError(f"WeightField: resolution and lobes >= 1, got {resolution}, {lobes}")
        if channels not in (1, 3):
            raise ValueError(f"WeightField: channels 1 or 3, got {channels}")
        if latent not in (0, 1, 2):  # the lobes' latent s and/or analytic heads' alpha
            raise ValueError(f"WeightField: latent 0, 1 or 2, got {latent}")
        if levels < 1 or resolution % (1 << (levels - 1)):
            raise ValueError(
                f"WeightField: levels >= 1 and resolution divisible by 2^(levels - 1), "
                f"got {levels} levels at {resolution}"
            )
        self.resolution = int(resolution)
        self.lobes = int(lobes)
        self.channels = int(channels)
        self.latent = int(latent)
        self.levels = int(levels)
        tail = (*(() if channels == 1 else (channels,)), self.lobes + 1)
        self.logits = nn.Parameter(torch.randn((self.resolution**2, *tail)) * init_std)
        # the lobes' latent s = sigmoid(logit) per texel (docs/model.md, "Conditioned
        # lobes"), started in the middle of [0, 1] with a little spread
        self.latent_logits = (
            nn.Parameter(torch.randn(self.resolution**2, self.latent) * 0.1) if latent else None
        )
        self.coarse = nn.ParameterList()  # level l = 1 .. L-1: (R / 2^l)^2 texels
        self.coarse_latent = nn.ParameterList()
        if self.levels > 1:
            sizes = [self.resolution >> level for level in range(1, self.levels)]
            with torch.no_grad():
                self.logits.zero_()
            for i, r in enumerate(sizes):
                last = i == len(sizes) - 1  # the coarsest starts random, the others at 0
                start = torch.randn((r * r, *tail)) if last else torch.zeros(r * r, *tail)
                start = start * init_std
                self.coarse.append(nn.Parameter(start))
                if latent:
                    self.coarse_latent.append(nn.Parameter(torch.zeros(r * r, self.latent)))
            n = self.resolution
            c = (torch.arange(n, dtype=torch.float32) + 0.5) / n
            centres = torch.stack(torch.meshgrid(c, c, indexing="xy"), -1).reshape(-1, 2)
            self.register_buffer("centres", centres, persistent=False)  # (u, v), j * R + i

    centres: torch.Tensor  # a buffer (register_buffer) when levels > 1

    def _summed(self, fine: torch.Tensor, coarse: nn.ParameterList) -> torch.Tensor:
        """``fine`` plus every coarse level looked up at the fine texel centres."""
        total = fine
        for table in coarse:
            r = int(round(table.shape[0] ** 0.5))
            flat = table.reshape(table.shape[0], -1)
            total = total + bilinear_wrap(flat, self.centres, r).reshape(fine.shape)
        return total

    def weights(self) -> torch.Tensor:
        """The field's table at the texel centres, [R*R, C*K + latent]: the weights
        (>= 0, sum over k <= 1 per texel and channel), then the latent columns (in [0, 1])."""
        w = torch.softmax(self._summed(self.logits, self.coarse), -1)[..., : self.lobes]
        w = w.reshape(w.shape[0], -1)
        if self.latent_logits is None:
            return w
        s = torch.sigmoid(self._summed(self.latent_logits, self.coarse_latent))
        return torch.cat([w, s], -1)

    def lookup(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(N, 2) -> (weights (N, K) or (N, 3, K), latent (N, latent) or None)."""
        return split_field(bilinear_wrap(self.weights(), uv, self.resolution), self)

    def forward(self, uv: torch.Tensor) -> torch.Tensor:  # (N, 2) -> (N, K) or (N, 3, K)
        return self.lookup(uv)[0]

    def frozen(self) -> FrozenWeightField:
        """The same look-up with the softmax evaluated once (for export)."""
        with torch.no_grad():
            return FrozenWeightField(
                self.weights(), self.resolution, channels=self.channels, latent=self.latent
            )


def split_field(
    values: torch.Tensor, field: WeightField | FrozenWeightField
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A looked-up row of a field's table [N, C*K + latent] -> (weights (N, K) or
    (N, 3, K), latent (N, latent) or None)."""
    ck = field.channels * field.lobes
    z = values[:, :ck] if field.latent else values
    z = z if field.channels == 1 else z.reshape(-1, field.channels, field.lobes)
    return z, (values[:, ck : ck + field.latent] if field.latent else None)


class FrozenWeightField(nn.Module):
    """A :class:`WeightField` whose weights [R*R, C*K] are a constant buffer: the same
    values bit for bit (one softmax of the same logits), no Softmax in the graph."""

    table: torch.Tensor  # a buffer (register_buffer)

    def __init__(
        self, weights: torch.Tensor, resolution: int, *, channels: int = 1, latent: int = 0
    ):
        super().__init__()
        self.resolution = int(resolution)
        self.channels = int(channels)
        self.latent = int(latent)
        self.lobes = (int(weights.shape[1]) - self.latent) // self.channels
        self.register_buffer("table", weights.detach().float().clone())

    def weights(self) -> torch.Tensor:
        return self.table

    def lookup(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        return split_field(bilinear_wrap(self.table, uv, self.resolution), self)

    def forward(self, uv: torch.Tensor) -> torch.Tensor:
        return self.lookup(uv)[0]


class NormalField(nn.Module):
    """The teacher's shading normal over uv (docs/model.md, "The normal field"): a table
    ``texels`` [Rv, Ru, 3] of unnormalised normals (a normal map's 2 t - 1), looked up
    as :class:`WeightField` is (:func:`bilinear_wrap`: repeat, bilinear, texel centres
    at ((i + 0.5) / Ru, (j + 0.5) / Rv)) and normalised:

        n(uv) = normalize(bilinear(texels, uv))     Mitsuba 3.9.1's normalmap.cpp frame()

    the order of Mitsuba's normalmap (interpolate the texture, then normalise), so a
    file whose texels are a bitmap's own reproduces Mitsuba's normal between texel
    centres too.  A texel sum of zero length gives (0, 0, 1).  Not trained: it is copied
    from the teacher at export.

    ``source`` ("normalmap" or "bumpmap") and the two flags of Mitsuba's wrappers
    (``flip_invalid_normals``, ``use_shadowing_function``) travel to the file's metadata:
    a renderer that wants the teacher's look applies them with the rotation."""

    texels: torch.Tensor  # buffers (register_buffer)
    scale: torch.Tensor
    up: torch.Tensor

    def __init__(
        self,
        texels: Any,
        *,
        source: str = "normalmap",
        flip_invalid_normals: bool = True,
        use_shadowing_function: bool = True,
    ):
        super().__init__()
        texels = torch.as_tensor(texels, dtype=torch.float32)
        if texels.dim() != 3 or texels.shape[-1] != 3 or min(texels.shape[:2]) < 1:
            raise ValueError(f"NormalField: texels [Rv, Ru, 3], got {tuple(texels.shape)}")
        self.register_buffer("texels", texels.detach().clone())
        self.resolution = (int(texels.shape[1]), int(texels.shape[0]))  # (Ru, Rv)
        self.register_buffer("scale", torch.tensor(self.resolution, dtype=torch.float32), False)
        self.register_buffer("up", torch.tensor([0.0, 0.0, 1.0]), persistent=False)
        self.source = str(source)
        self.flip_invalid_normals = bool(flip_invalid_normals)
        self.use_shadowing_function = bool(use_shadowing_function)

    def forward(self, uv: torch.Tensor) -> torch.Tensor:  # (N, 2) -> (N, 3), unit
        v = bilinear_wrap(self.texels.reshape(-1, 3), uv, self.resolution, self.scale)
        length = torch.sqrt((v * v).sum(-1, keepdim=True))
        up = torch.zeros_like(v) + self.up
        ok = length > 0.0
        return torch.where(ok, v / torch.where(ok, length, torch.ones_like(length)), up)


def texel_bound(
    table: torch.Tensor, envelope: torch.Tensor, field: WeightField | FrozenWeightField
) -> torch.Tensor:
    """``texture.lobe_bound: texel`` (docs/model.md, "The lobes' bound"): a field's table
    [R*R, C*K + latent] with each texel's weights divided, per RGB channel c, by
    max(1, max_j sum_k z_k,c E[j, 3k + c]), where ``envelope`` E [J, 3K] bounds lobe k's
    albedo in channel c on node j's cell of incidences (for conditioned lobes, at every
    latent value).  After it every texel satisfies the J x 3 linear constraints
    sum_k z_k,c E[j, 3k + c] <= 1, and so does every convex blend of texels: bilinear
    filtering cannot leave the set.  With one weight per lobe (``channels`` 1) the texel
    takes the largest of its three channels' factors.  The latent columns are unchanged."""
    k, ck = field.lobes, field.channels * field.lobes
    if envelope.dim() != 2 or envelope.shape[1] != 3 * k:
        raise ValueError(f"texel_bound: an envelope [J, {3 * k}], got {tuple(envelope.shape)}")
    env = envelope.reshape(-1, k, 3).permute(0, 2, 1)  # (J, 3, K): [j, c, k]
    z = table[:, :ck].reshape(table.shape[0], field.channels, k)
    if field.channels == 1:
        m = torch.einsum("tk,jck->tjc", z[:, 0], env).amax(1).amax(1, keepdim=True)
    else:
        m = torch.einsum("tck,jck->tjc", z, env).amax(1)  # (T, 3)
    z = (z / m.clamp_min(1.0)[..., None]).reshape(table.shape[0], ck)
    return torch.cat([z, table[:, ck:]], -1)


class TexturedBRDF(nn.Module):
    """f(wi, wo, uv) = sum_k z_k(uv) g_k(wi, wo), (N, 3); module doc for why it is
    reciprocal bit for bit and, with normalised lobes, energy conserving at every uv.

    ``lobes``: K separate networks, each (N, 3); or ONE network with K heads (a
    ``RawBRDF`` with ``heads`` = K, or its ``NormalizedBRDF``), (N, 3K), head k in
    columns 3k .. 3k + 2: the shared lobes (``texture.lobe_network: shared``), one set of
    features and hidden layers for all K, each head normalised by its own columns of
    the albedo table, so the bound's argument is unchanged and a renderer evaluates one
    network instead of K (docs/model.md, "Spatially varying models")."""

    def __init__(
        self,
        lobes: Iterable[nn.Module],
        field: WeightField | FrozenWeightField,
        normal: NormalField | None = None,
    ):
        super().__init__()
        self.lobes = nn.ModuleList(lobes)
        self.shared = len(self.lobes) == 1 and heads_of(self.lobes[0]) > 1
        count = heads_of(self.lobes[0]) if self.shared else len(self.lobes)
        if count != field.lobes:
            raise ValueError(f"TexturedBRDF: {count} lobes, the field has {field.lobes}")
        wants = {int(getattr(getattr(g, "raw", g), "latent", 0)) for g in self.lobes}
        if wants != {int(getattr(field, "latent", 0))}:
            has = int(getattr(field, "latent", 0))
            raise ValueError(f"TexturedBRDF: lobes with latent {wants}, the field has {has}")
        self.field = field
        # the teacher's normal field (docs/model.md, "The normal field"): carried to the
        # file as a second output, never part of f
        self.normal = normal
        self.anisotropic = any(bool(getattr(g, "anisotropic", False)) for g in self.lobes)
        # texture.lobe_bound: scale, while training: a constant per lobe and channel, (3K,),
        # 1 / max(1, the raw lobe's largest albedo), set by the loop (textured_loop.
        # bound_scale); not saved (the loop estimates it again on resume), never exported
        # (normalized_textured folds the export's own bound into ScaledBRDF)
        self.lobe_scale: torch.Tensor | None
        self.register_buffer("lobe_scale", None, persistent=False)
        # texture.lobe_bound: texel, while training: the envelope E [J, 3K] of
        # texel_bound, estimated by the loop (textured_loop.bound_envelope) and applied to
        # the field's table before the look-up; never saved, never exported (the export
        # bakes its own bound into the frozen table: normalized_textured)
        self.texel_envelope: torch.Tensor | None
        self.register_buffer("texel_envelope", None, persistent=False)
        # set by normalized_textured: the envelope a texel of its field is bounded by
        self.bound_envelope: torch.Tensor | None = None

    def _lobe(self, k: int, g: torch.Tensor) -> torch.Tensor:
        """Lobe k's (N, 3) values ``g`` times its training-time scale, if any."""
        if self.lobe_scale is None:
            return g
        return g * self.lobe_scale[3 * k : 3 * k + 3]

    def forward(self, wi: torch.Tensor, wo: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        # z: (N, K), or (N, 3, K) with per-channel weights; s: the lobes' latent or None
        if self.texel_envelope is None:
            z, s = self.field.lookup(uv)
        else:  # each texel's weights bounded first, then blended (texel_bound)
            table = texel_bound(self.field.weights(), self.texel_envelope, self.field)
            z, s = split_field(bilinear_wrap(table, uv, self.field.resolution), self.field)
        if z.dim() == 2:
            z = z[:, None, :]  # one weight for every channel
        extra = () if s is None else (s,)  # conditioned lobes: g(wi, wo; s(uv))
        if self.shared:  # one network, K heads side by side
            g = self.lobes[0](wi, wo, *extra)
            f = z[:, :, 0] * self._lobe(0, g[:, 0:3])
            for k in range(1, self.field.lobes):  # left to right, as below
                f = f + z[:, :, k] * self._lobe(k, g[:, 3 * k : 3 * k + 3])
            return f
        f = z[:, :, 0] * self._lobe(0, self.lobes[0](wi, wo, *extra))
        for k in range(1, len(self.lobes)):  # left to right: the same order for (wo, wi)
            f = f + z[:, :, k] * self._lobe(k, self.lobes[k](wi, wo, *extra))
        return f


# A lobe table whose largest node is at most this is replaced by a constant scale
# (ScaledBRDF): the head dimmed by at most 2 % everywhere instead of two table look-ups
# and a divide per evaluation, which cost about a third of a homogeneous compact file's
# render (development roughplastic, one head's raw albedo 1.018: 1.84x the compact file
# with the table, 1.47x without).
FOLD_LIMIT = 1.02


class ScaledBRDF(nn.Module):
    """raw(wi, wo[, s]) times a constant per output column, c = 1 / max(1, the column's
    largest A+ over the table's nodes): its albedo is at most A+ c <= 1 everywhere (A+
    bounds A on each cell as the table's does), reciprocal (a constant), and a renderer
    pays one multiply instead of the look-ups (:data:`FOLD_LIMIT`)."""

    scale: torch.Tensor  # a buffer (register_buffer): (3 * heads,)

    def __init__(self, raw: RawBRDF, table: torch.Tensor):
        super().__init__()
        self.raw = raw
        self.anisotropic = bool(getattr(raw, "anisotropic", False))
        peak = table.reshape(-1, table.shape[-1]).amax(0).clamp_min(1.0)
        self.register_buffer("scale", (1.0 / peak).float())
        self.identity = False

    def forward(self, wi: torch.Tensor, wo: torch.Tensor, *s: torch.Tensor) -> torch.Tensor:
        return self.raw(wi, wo, *s) * self.scale


NORMALIZED = (NormalizedBRDF, ConditionedNormalizedBRDF, ScaledBRDF)
BOUNDS = ("table", "scale", "texel")  # texture.lobe_bound (normalized_textured)


def heads_of(lobe: nn.Module) -> int:
    """How many lobes one network holds: its ``heads`` (a RawBRDF's, or the raw network
    of a NormalizedBRDF), 1 for any other module."""
    raw = lobe.raw if isinstance(lobe, NORMALIZED) else lobe
    return int(getattr(raw, "heads", 1))


def raw_of(lobe: nn.Module) -> RawBRDF:
    """A lobe's raw network (a normalised lobe's ``raw``, the network beside analytic
    heads (:class:`~neural_brdf.train.ggx_heads.GGXLobes`) its ``net``, a raw one itself)."""
    raw = lobe.raw if isinstance(lobe, NORMALIZED) else lobe
    raw = raw.net if isinstance(raw, GGXLobes) else raw
    if not isinstance(raw, RawBRDF):
        raise TypeError(f"a lobe must be a RawBRDF or a NormalizedBRDF, got {type(lobe)}")
    return raw


def normalized_textured(
    model: TexturedBRDF,
    normalization: cfgmod.Normalization | None = None,
    *,
    seed: int = 0,
    target: Any = None,
    bound: str = "table",
) -> tuple[TexturedBRDF, list[dict[str, Any]]]:
    """Each lobe wrapped in :class:`NormalizedBRDF` with its own A+ table
    (:func:`albedo_table`, settings ``normalization``, default :class:`config.Normalization`;
    seed ``seed + 17 + k`` for lobe k), and the field frozen (:meth:`WeightField.frozen`).
    Returns (model, per-lobe table figures).  A lobe that is already a NormalizedBRDF is
    tabulated again from its raw network.

    Bound (docs/model.md, "Spatially varying models: the contract"): every g_k has
    albedo <= A+_k / max(1, A+_k) <= 1 ("Energy conservation that stays reciprocal", with
    A+_k >= A_k to the table's tolerance), and z(uv) >= 0 with sum z <= 1 at every uv
    (a bilinear blend of convex weight vectors), so the albedo of f at uv is
    sum_k z_k(uv) A_k <= 1 + margin, between texel centres included.  ``target``: a
    sampler for the quadrature (an analytic BRDF), or None: a textured teacher's
    sampler depends on uv, so none is passed by default.

    ``bound`` (``texture.lobe_bound``): "table" keeps a lobe's table unless its largest
    node is at most :data:`FOLD_LIMIT`; "scale" always folds it into
    :class:`ScaledBRDF`, 1 / max(1, the largest A+ of each column): the same bound (A+
    bounds the albedo on every cell of the table, so its largest node bounds it
    everywhere), no table in the graph.  "texel" keeps every lobe raw and bounds the
    field instead (:func:`texel_bound`): the envelope E [J, 3K] is each lobe's A+ table
    (its largest node over the latent, for conditioned lobes) side by side, and the
    frozen table's texels are divided so that sum_k z_k,c A+_k,c <= 1 on every node's
    cell, for every channel c; a blend of texels keeps it (the constraints are linear in
    z), so the albedo at any uv is at most 1 + margin.  It is less strict than a
    constant per lobe where the lobes peak at different incidences (a diffuse lobe at
    the normal, a Fresnel-bright one at grazing), and the graph carries neither a table
    nor a multiply.
    """
    if bound not in BOUNDS:
        raise ValueError(f"normalized_textured: bound {' or '.join(BOUNDS)}, got {bound!r}")
    n = normalization if normalization is not None else cfgmod.Normalization()
    lobes: list[nn.Module] = []
    info: list[dict[str, Any]] = []
    envelopes: list[torch.Tensor] = []  # bound "texel": each lobe's nodes, side by side
    for k, lobe in enumerate(model.lobes):
        raw = raw_of(lobe).eval()
        analytic = analytic_count(lobe)  # GGX heads: albedo <= 1 in closed form
        if analytic and bound != "texel":
            raise ValueError(
                f"normalized_textured: analytic heads are bounded per texel, not by {bound!r}"
            )
        if not n.enabled:
            lobes.append(lobe.eval() if analytic else raw)
            info.append({"enabled": False})
            continue
        aniso = is_anisotropic(raw.encoding)
        norm: NormalizedBRDF | ConditionedNormalizedBRDF | ScaledBRDF
        if raw.latent:  # conditioned lobes: a table over (s, theta) (train/conditioned.py)
            norm, a, err = normalized_conditioned(raw, n, seed=seed + 17 + k)
        else:
            # a shared network's table has 3K columns: head k normalised by its own three
            table, a, err = albedo_table(
                raw,
                size=n.grid_size if aniso else n.table_size,
                anisotropic=aniso,
                samples=n.samples,
                seed=seed + 17 + k,
                sigmas=n.sigmas,
                margin=n.margin,
                target=target,
            )
            norm = NormalizedBRDF(raw, table).eval()
        if bound == "texel":  # the lobe stays raw; its nodes join the field's envelope
            env = lobe_envelope(norm.table, bool(raw.latent))
            if analytic:  # the analytic heads' envelope at the same nodes (ggx_heads)
                env = with_head_envelope(env, bool(getattr(raw, "anisotropic", False)))
            envelopes.append(env)
            lobes.append(lobe.eval() if analytic else raw)
        else:
            if not norm.identity and (bound == "scale" or float(norm.table.max()) <= FOLD_LIMIT):
                norm = ScaledBRDF(raw, norm.table).eval()  # a constant instead of the table
            lobes.append(norm)
        heads = heads_of(raw)  # one entry per lobe: a shared network's K heads each
        for h in range(heads):
            cols = slice(3 * h, 3 * h + 3)
            info.append(
                {
                    "enabled": True,
                    "raw_max_albedo": float(a[..., cols].max()),
                    "raw_max_stderr": float(err[..., cols].max()),
                    "in_graph": bound != "texel" and not norm.identity,
                    "form": (
                        "texel"
                        if bound == "texel"
                        else "scale"
                        if isinstance(norm, ScaledBRDF)
                        else "table"
                    ),
                }
            )
        for _ in range(analytic):
            info.append(
                {
                    "enabled": True,
                    "raw_max_albedo": 1.0,  # a closed-form bound (ggx_heads' module doc)
                    "raw_max_stderr": 0.0,
                    "in_graph": False,
                    "form": "analytic",
                }
            )
    field = model.field.frozen() if isinstance(model.field, WeightField) else model.field
    envelope = torch.cat(envelopes, -1) if envelopes else None
    if envelope is not None:
        bounded = texel_bound(field.weights(), envelope, field)
        field = FrozenWeightField(
            bounded, field.resolution, channels=field.channels, latent=field.latent
        )
    out = TexturedBRDF(lobes, field, model.normal).eval()
    # what bounds a texel of this model: with "texel" the envelope above; otherwise every
    # lobe's albedo is at most 1, so sum_k z_k <= 1 per channel (an envelope of ones).  A
    # new field for these lobes (train/textured_project.py) is bounded by it; never exported
    out.bound_envelope = envelope if envelope is not None else torch.ones(1, 3 * field.lobes)
    return out, info


def lobe_envelope(table: torch.Tensor, conditioned: bool) -> torch.Tensor:
    """A lobe's A+ table -> [J, C] (J nodes of incidence, C = 3 x heads columns): an
    isotropic table as it is, an anisotropic grid's nodes flattened, a conditioned
    table (S, K, C) its largest value over the latent axis, so that each node's bound
    holds at every latent value."""
    if conditioned:
        return table.amax(0)
    return table.reshape(-1, table.shape[-1])


# ------------------------------------------------------------------- total graph
def uv_or_invalid(uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2) -> (uv with invalid rows set to 0, valid (N, 1)): valid when both entries
    are finite.  Elementwise ops only (IsNaN, IsInf, Or, Not, Where)."""
    bad = torch.isnan(uv) | torch.isinf(uv)
    ok = ~(bad[..., 0:1] | bad[..., 1:2])
    return torch.where(ok, uv, torch.zeros_like(uv)), ok


class TotalTexturedBRDF(nn.Module):
    """The exported graph: ``model`` (forward(wi, wo, uv)) made total over every row.

    wi and wo go through :func:`~neural_brdf.train.model.unit_or_invalid` (as
    :class:`~neural_brdf.train.model.TotalBRDF`), uv through :func:`uv_or_invalid`; a
    row with an invalid wi, wo or uv gives exactly 0 without touching another row.  Both
    directions are cleaned by the same ops, so bit-exact symmetry survives.

    With a normal field (``model.normal``) the graph has a second output, n(uv) [N, 3]
    (``fileformat.NORMAL``): (0, 0, 1) where uv is invalid."""

    up: torch.Tensor  # a buffer (register_buffer)

    def __init__(self, model: TexturedBRDF):
        super().__init__()
        self.model = model
        self.anisotropic = model.anisotropic
        self.register_buffer("up", torch.tensor([0.0, 0.0, 1.0]), persistent=False)

    def forward(
        self, wi: torch.Tensor, wo: torch.Tensor, uv: torch.Tensor
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        ui, ok_i = unit_or_invalid(wi, self.up)
        uo, ok_o = unit_or_invalid(wo, self.up)
        c, ok_uv = uv_or_invalid(uv)
        f = self.model(ui, uo, c)
        f = torch.where(ok_i & ok_o & ok_uv, f, torch.zeros_like(f))
        if self.model.normal is None:
            return f
        n = self.model.normal(c)
        return f, torch.where(ok_uv, n, torch.zeros_like(n) + self.up)


def exportable(model: TexturedBRDF) -> TotalTexturedBRDF:
    """``model`` with its field frozen, made total: the module the ONNX graph is of."""
    field = model.field.frozen() if isinstance(model.field, WeightField) else model.field
    return TotalTexturedBRDF(TexturedBRDF(list(model.lobes), field, model.normal).eval()).eval()
