"""Training configuration: YAML in, a validated :class:`Config` out.

Every default lives here, one setting per line with a comment; a config file holds
only the keys it changes (``configs/defaults.yaml`` lists them all and is checked
against this schema by the tests).  Overrides come from the command line::

    python train.py configs/gold.yaml --set train.steps=500 --set model.hidden=[32,32]

A value given by ``--set`` is parsed as YAML, so numbers, booleans and lists work.
Unknown keys, wrong types and invalid values raise :class:`ConfigError` with a
one-line message that names the key and where it was given (``gold.yaml: train.stepz:
unknown key``, ``--set train.stepz=5: train.stepz: unknown key``); the CLI turns it
into exit code 2.  Types are strict: an integer setting does not accept ``2.5`` or
``"2"``, a float setting accepts an integer.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from neural_brdf import encodings, limits

# The same classes as neural_brdf.errors (kept light for runtime and the CLI).
from neural_brdf.errors import ConfigError
from neural_brdf.target import Kind

# Of the resolved config, the checkpoint and the exported model: neural_brdf.fileformat.


class _Section(BaseModel):
    # allow_inf_nan=False: every float setting (in lists too) must be finite; YAML's
    # .inf, -.inf, .nan and an overflowing 1e999 are refused naming the key
    model_config = ConfigDict(
        extra="forbid", strict=True, validate_default=True, allow_inf_nan=False
    )


class ImageView(_Section):
    # one entry of target.images (docs/inverse.md); paths relative to the config file
    scene: str  # a Mitsuba 3 XML scene whose <bsdf id="fit"> is the BSDF to fit
    image: str  # its target: a linear RGB EXR of the scene's film size
    # a flash/no-flash pair (docs/inverse.md): the photograph without the flash, of the
    # same size; the target is image - subtract, the scene lit by the flash alone
    subtract: str | None = None

    def label(self) -> str:
        """The target's file name, or the pair's difference ("a.exr - b.exr")."""
        name = Path(self.image).name
        return name if self.subtract is None else f"{name} - {Path(self.subtract).name}"


class Target(_Section):
    model: str = "lambertian"  # a name in analytic.available()
    params: dict[str, Any] = Field(default_factory=dict)  # passed to analytic.create
    data: str | None = None  # or: measured data, MERL .binary / RGL .bsdf
    images: list[ImageView] | None = None  # or: images, fitted by inverse rendering
    # or: a Mitsuba 3 XML file holding one <bsdf>, the teacher (measured/mitsuba.py);
    # relative to the config file
    mitsuba: str | None = None
    # Mitsuba variant of an images fit (null: from train.device) or of a mitsuba teacher
    # (null: llvm_ad_rgb)
    variant: str | None = None

    @property
    def kind(self) -> Kind:
        """Which kind of target this section gives (:data:`neural_brdf.target.KINDS`): the
        one of ``images``, ``data`` (measured) and ``mitsuba`` that is set (the
        validators allow one), else analytic (``model``, ``params``).  The built
        target's own ``kind`` is the same (:func:`neural_brdf.target.kind_of`)."""
        if self.images is not None:
            return "images"
        if self.data is not None:
            return "measured"
        if self.mitsuba is not None:
            return "mitsuba"
        return "analytic"

    @model_validator(mode="after")
    def _images(self):
        if self.images is not None:
            if not self.images:
                raise ValueError("images: empty; give at least one {scene, image} pair")
            if self.data is not None or self.params or self.model != "lambertian":
                raise ValueError("images: give target.images alone, not with data/model/params")
        if self.variant is not None:
            if self.images is None and self.mitsuba is None:
                raise ValueError("variant: only for target.images or target.mitsuba")
            if self.variant not in ("llvm_ad_rgb", "cuda_ad_rgb"):
                raise ValueError(
                    f"variant: {self.variant!r} is not a JIT AD RGB variant "
                    "(llvm_ad_rgb or cuda_ad_rgb)"
                )
        return self

    @model_validator(mode="after")
    def _one_kind(self):
        if self.mitsuba is not None:
            if not self.mitsuba.strip():
                raise ValueError("mitsuba: empty path")
            if (
                self.data is not None
                or self.images is not None
                or self.params
                or self.model != Target.model_fields["model"].default
            ):
                raise ValueError(
                    "mitsuba: give target.mitsuba alone, not with data/model/params/images"
                )
        if self.data is not None:
            if not self.data.strip():
                raise ValueError("data: empty path")
            # (a resolved config.yaml of an earlier version repeats the default model:
            # that is not a clash)
            if self.params or self.model != Target.model_fields["model"].default:
                raise ValueError(
                    "data: give either target.data (measured) or "
                    "target.model/params (analytic), not both"
                )
        return self


class CosineGrid(_Section):
    # a learned (u, v) feature grid (model.py); as model.cosine_grid, over the two
    # cosines, (cos_i + cos_o) / 2 and |cos_i - cos_o| / (cos_i + cos_o): it carries terms
    # set by the cosines, as a diffuse term of Ashikhmin-Shirley's form
    size: int = Field(0, ge=0, le=257)  # nodes per axis; 0: off
    channels: int = Field(4, ge=1, le=64)  # learned features per node
    init_std: float = Field(1e-2, ge=0.0, le=1.0)  # initial values ~ N(0, init_std^2)
    lr_scale: float = Field(10.0, gt=0.0)  # the grid's learning rate / train.lr

    @model_validator(mode="after")
    def _size(self):
        if self.size == 1:
            raise ValueError("size: must be 0 (off) or >= 2 nodes per axis")
        return self


class Grid(CosineGrid):
    # model.grid: over the reciprocal half/difference angles, or the half vector.
    # theta: (u_h, theta_d / (pi/2)), u_h the peak coordinate (encoding.py); half_disc
    # (anisotropic encoding): the half vector's polar map, sqrt(u_h) (cos phi_h, sin phi_h)
    coords: Literal["theta", "half_disc"] = "theta"
    size: int = Field(32, ge=0, le=257)  # nodes per axis; 0: off (on by default: compact)


class Model(_Section):
    # a name in neural_brdf/encodings/ (isotropic, anisotropic; "raw" feeds (wi, wo) as
    # they are: NOT reciprocal, for ablations only); checked by _encoding below
    encoding: str = "isotropic"
    peak_coordinate: Literal["u_h", "sqrt"] = "u_h"  # theta_h feature: u_h | sqrt (old, MERL)
    # The defaults are the compact recipe (issues 12 and 21): a 32 x 32 x 4 learned grid
    # and one ReLU layer of 32; the 3 x 64 SiLU networks are the configs/mlp/ presets.
    hidden: list[int] = Field(default_factory=lambda: [32])  # hidden layer widths
    activation: Literal["relu", "silu", "gelu", "tanh", "softplus"] = "relu"  # hidden layers
    grazing_power: float = Field(1.0, ge=0.0, le=4.0)  # output / ((cos_i + cos_o) / 2)^power
    # the cosine of grazing_power: mean (cos_i + cos_o) / 2, or max(cos_i, cos_o), the
    # denominator of Ashikhmin-Shirley's specular term (model.py)
    grazing_cos: Literal["mean", "max"] = "mean"
    # f = output_scale * softplus(y) (see model.py); 1e-3 to 1e3: the head's initial bias,
    # softplus^-1(0.3 / output_scale), and f stay within float32
    output_scale: float = Field(1.0, ge=1e-3, le=1e3)
    grid: Grid = Field(default_factory=Grid)  # learned feature grid (on by default)
    cosine_grid: CosineGrid = Field(default_factory=CosineGrid)  # a second one (off)

    @field_validator("encoding")
    @classmethod
    def _encoding(cls, name: str) -> str:
        # the registry, not a Literal: an encoding registered at run time is accepted too;
        # worded as pydantic words a Literal ("Input should be 'a', 'b' or 'c'")
        if name not in encodings.names():
            *first, last = [repr(n) for n in encodings.names()]
            expected = f"{', '.join(first)} or {last}" if first else last
            raise PydanticCustomError(
                "literal_error", "Input should be {expected}", {"expected": expected}
            )
        return name

    @model_validator(mode="after")
    def _widths(self):
        if not self.hidden or any(w < 1 for w in self.hidden):
            raise ValueError("hidden: needs at least one layer, each of width >= 1")
        spec = encodings.get(self.encoding)  # its grid axes (Encoding.grid_axes)
        if self.grid.coords not in spec.grid_axes and "grid" not in self.model_fields_set:
            self.grid.size = 0  # the default grid needs the encoding's angles: off for raw
        if self.grid.size and self.grid.coords not in spec.grid_axes:
            having = " or ".join(encodings.names(grid=self.grid.coords))
            key = f"grid.coords: {self.grid.coords}" if spec.grid_axes else "grid:"  # raw: none
            raise ValueError(f"{key} needs the {having} encoding, not {self.encoding}")
        if self.cosine_grid.size and not spec.reciprocal:
            having = " or ".join(encodings.names(reciprocal=True))
            raise ValueError(f"cosine_grid: needs the {having} encoding, not {self.encoding}")
        return self


class Normalization(_Section):
    enabled: bool = True  # albedo normalisation (off: ablations only)
    table_size: int = Field(65, ge=4, le=1025)  # isotropic albedo table: nodes in theta
    grid_size: int = Field(17, ge=4, le=257)  # anisotropic albedo table: nodes per axis
    samples: int = Field(8192, ge=256)  # quadrature points per table node
    sigmas: float = Field(3.0, ge=0.0)  # quadrature standard errors added to A
    margin: float = Field(1e-3, ge=0.0, le=0.5)  # relative headroom on the tabulated A
    # a node whose A +- sigmas x stderr straddles 1 while sigmas x stderr exceeds the
    # margin is estimated again with refine x samples (its noise, not A, may be what
    # passes 1: docs/model.md; 1: never)
    refine: int = Field(16, ge=1, le=256)


class Data(_Section):
    batch_size: int = Field(4096, ge=16)  # pairs per step
    pool_size: int = Field(262144, ge=16)  # pairs kept in the sample pool
    reuse: float = Field(4.0, ge=1.0)  # mean number of times a pair is used
    uniform: float = Field(0.1, ge=0.0)  # share of wo uniform on the hemisphere
    cosine: float = Field(0.1, ge=0.0)  # share of wo cosine-distributed
    importance: float = Field(0.7, ge=0.0)  # share of wo from the target's sampler
    peak: float = Field(0.1, ge=0.0)  # share of pairs uniform in (u_h, theta_d) (train/data.py)

    @model_validator(mode="after")
    def _shares(self):
        if self.uniform + self.cosine + self.importance + self.peak <= 0:
            raise ValueError("uniform/cosine/importance/peak: at least one share must be > 0")
        if self.pool_size < self.batch_size:
            raise ValueError("pool_size: must be >= batch_size")
        return self


# A seed is 0 <= seed < 2**31.  The code derives seeds from it by at most
# (seed + ~10**6) * 7919 + a few hundred (validate.py's REMEASURE_SEED, then
# quadrature.albedo's replicas; fit.py's seed * 7919 + step), about 2**44 here: far inside
# torch's and numpy's int64 (a larger seed ended in "Overflow when unpacking long long"
# after training); numpy refuses a negative seed.  Mitsuba's UInt32 seeds take
# seed + step, or reduce modulo 2**31 - 1.
SEED_LIMIT = 2**31
MAX_STEPS = 10**8  # far beyond any training (the recipes take 2000 to 20000)
MAX_THREADS = 1024  # torch's pool: 100000 threads crashed the process (SIGSEGV)


class Train(_Section):
    steps: int = Field(3000, ge=1, le=MAX_STEPS)  # optimizer steps
    seed: int = Field(0, ge=0, lt=SEED_LIMIT)  # seeds weights, data and quadrature
    lr: float = Field(3e-2, gt=0.0)  # Adam learning rate after warm-up
    lr_min: float = Field(0.01, ge=0.0, le=1.0)  # final lr as a fraction of lr (cosine)
    schedule: Literal["cosine", "constant"] = "cosine"  # lr decay after warm-up
    warmup: int = Field(100, ge=0)  # linear warm-up steps
    loss: Literal["log_l2", "log_l1", "nbrdf"] = "log_l2"  # see train.py
    loss_eps: float = Field(1e-3, gt=0.0)  # offset inside the log (1/sr)
    peak_weight: float = Field(10.0, ge=0.0)  # extra loss weight (f cos)^2 / mean (f cos)^2
    peak_cap: float = Field(100.0, gt=0.0)  # cap on (f cos)^2 / mean (f cos)^2 in the weight
    # torch CPU threads (fixed for determinism; docs/config.md); 100000 crashed torch
    threads: int = Field(1, ge=1, le=MAX_THREADS)
    device: Literal["cpu", "cuda", "auto"] = "cpu"  # auto: cuda when torch sees a GPU
    checkpoint_every: int = Field(500, ge=1)  # steps between checkpoints
    log_every: int = Field(25, ge=1)  # steps between CSV rows
    eval_every: int = Field(500, ge=0)  # steps between held-out errors (0: never)
    # tqdm progress bar on stderr: auto, only where stderr is a terminal (a log file gets
    # no carriage-return frames; the run's per-stage lines still print); true, always
    progress: bool | Literal["auto"] = "auto"

    @model_validator(mode="before")
    @classmethod
    def _progress(cls, raw: Any) -> Any:
        # one message naming the three choices, rather than one per member of the union
        got = raw.get("progress", "auto") if isinstance(raw, dict) else "auto"
        if not (isinstance(got, bool) or got == "auto"):
            shown = limits.bounded(repr(got), 80)
            raise ValueError(f"progress: expected true, false or auto (got {shown})")
        return raw

    def bar_disabled(self) -> bool | None:
        """tqdm's ``disable`` for :attr:`progress`: None (off where stderr is not a
        terminal, tqdm's own test) for ``auto``."""
        return None if self.progress == "auto" else not self.progress


class Validation(_Section):
    pairs: int = Field(20000, ge=100)  # random pairs for reciprocity / min value
    furnace_dirs: int = Field(91, ge=2)  # furnace polar angles (aniso: half, x16 azimuths)
    furnace_samples: int = Field(8192, ge=256)  # quadrature points per incoming direction
    # a direction over 1 + albedo_tol is measured again with furnace_refine x
    # furnace_samples points, which decide (1: never; docs/model.md)
    furnace_refine: int = Field(16, ge=1, le=256)
    accuracy_samples: int = Field(131072, ge=1024)  # importance-sampled pairs for the error
    reciprocity_tol: float = Field(1e-6, ge=0.0)  # max relative |f(a,b) - f(b,a)|
    albedo_tol: float = Field(1e-3, ge=0.0)  # max albedo allowed: 1 + albedo_tol
    peak_tol: float = Field(0.03, ge=0.0)  # max |f / f_ref - 1| at and near the mirror direction
    seed: int = Field(1234, ge=0, lt=SEED_LIMIT)  # independent of the training seeds


class Export(_Section):
    opset: int = Field(17, ge=13, le=20)  # ONNX opset of the legacy exporter
    parity_pairs: int = Field(4096, ge=16)  # pairs for the torch-vs-onnxruntime check
    parity_tol: float = Field(1e-5, gt=0.0)  # max relative difference


# The analytic families an images fit can start from (neural_brdf/inverse/starts.py,
# FAMILIES; tests/inverse/test_starts.py keeps the two equal), simplest first.
START_FAMILIES = (
    "diffuse",
    "roughplastic",
    "principled",
    "roughconductor",
    # after the conductor: a tie of their equal numbers of free scalars goes to the earlier
    "clearcoat",
    "roughconductor_aniso",
    "blend",
)
START_CHOICES = ("auto", "ggx", "constant", *START_FAMILIES)
ANISOTROPIC_FAMILIES = ("roughconductor_aniso",)  # need an anisotropic model.encoding


class Images(_Section):
    # an images fit (target.images; docs/inverse.md): its start, its renders and its
    # validation split; read by no other target
    # auto: every family of start_families fitted to the images, the one the validation
    # split prefers distilled into the network; a family name: that one; ggx: the
    # roughconductor fit of the first version; constant: a dim f
    start: str = "auto"
    start_families: list[str] = Field(default_factory=lambda: list(START_FAMILIES))
    start_steps: int | None = Field(None, ge=1)  # each family's fit (null: 80; ggx: train.steps)
    start_lr: float = Field(0.2, gt=0.0)  # ... Adam's rate on its free variables, decayed
    start_lr_end: float = Field(0.05, gt=0.0, le=1.0)  # ... (cosine) to this fraction of it
    start_spp: int = Field(4, ge=1)  # ... samples per pixel of its gradient pass
    start_primal_spp: int = Field(16, ge=1)  # ... and of its primal pass
    # ... its step recorded once per view and replayed (drjit.freeze; false: traced
    # anew every step; the same fit to float rounding: docs/inverse-design.md, "Frozen steps")
    start_freeze: bool = True
    # the chosen family's fit continued from its parameters, its second half's iterates
    # averaged; kept unless the validation split prefers the unrefined parameters
    # (0 steps: off; chosen on the development set: docs/inverse-design.md, "Refining the choice")
    start_refine_steps: int = Field(60, ge=0)
    start_refine_lr: float = Field(0.02, gt=0.0)  # its rate, decayed (cosine) ...
    start_refine_lr_end: float = Field(0.1, gt=0.0, le=1.0)  # ... to this fraction of it
    start_refine_spp: int = Field(16, ge=1)  # its gradient pass's samples (primal: twice)
    # a further refinement from the last while the split gains: the last round kept and
    # its held-out loss below (1 - start_refine_gain) x the one before, at most
    # start_refine_rounds rounds in all (docs/inverse-design.md, "Refining the choice")
    start_refine_rounds: int = Field(8, ge=1)
    start_refine_gain: float = Field(0.1, ge=0.0, lt=1.0)
    # auto's contenders: every family whose held-out loss is within this factor of the
    # least fits start_steps more steps from where it stopped, and the choice is made
    # again on the continued losses, unless the chosen one is already within
    # start_tie_max of the targets' noise (null: never; docs/inverse-design.md, "The contenders")
    start_continue_within: float | None = Field(2.0, ge=1.0)
    # auto's choice a family warm-started from others (clearcoat from principled,
    # roughconductor_aniso from roughconductor, blend from diffuse and roughconductor):
    # those are fitted further until they have had as many steps, and the choice made
    # again, so a family never wins over its source for its longer fit alone
    # (docs/inverse-design.md, "A warm start's head start")
    start_catch_up: bool = True
    # ... at most this many of them, the chosen one and the others of least held-out loss
    # (null: every one within the factor; docs/inverse-design.md, "The contenders")
    start_continue_max: int | None = Field(3, ge=2)
    # auto's choice tied by the split's standard error alone (a more complex family's
    # held-out loss the least, above the chosen one's by more than start_tie_tol): the
    # two are fitted again on this many folds of the training tiles, each held out in
    # turn, and chosen by the same rule over every tile the run fits (0: never;
    # docs/inverse-design.md, "An inconclusive split")
    start_cross_folds: int = Field(2, ge=0)
    start_train_steps: int = Field(12000, ge=1)  # training steps on the start (docs/inverse.md)
    # their learning rate (null: train.lr, the image stage's); sample-based training's own
    # default rate, chosen on the development set's brushed starts (docs/inverse.md)
    start_train_lr: float | None = Field(0.03, gt=0.0)
    start_lr_scale: float = Field(0.05, gt=0.0)  # after a fitted start: image stage lr / train.lr
    start_grid_lr_scale: float = Field(1.0, gt=0.0)  # ... its grids' lr / that (not grid.lr_scale)
    # after an anisotropic start (ANISOTROPIC_FAMILIES): half_disc puts the network's grid
    # over the half vector's disc (model.grid.coords: half_disc), where a brushed lobe
    # varies; model: model.grid.coords as set (docs/inverse-design.md, "The grid after an
    # anisotropic start"; chosen on the development set)
    anisotropic_grid: Literal["half_disc", "model"] = "half_disc"
    # after an isotropic start (any other family): isotropic trains the network with the
    # isotropic encoding (model.encoding: isotropic, when model.encoding is anisotropic),
    # so that no dependence on the half vector's azimuth the views cannot pin is learned;
    # model: model.encoding as set (docs/inverse-design.md, "The encoding after an isotropic
    # start"; chosen on the development set)
    isotropic_encoding: Literal["isotropic", "model"] = "isotropic"
    # auto's choice: a family with more free scalars is taken over a simpler one only when
    # its held-out loss is lower by more than max(start_tie_tol x the least,
    # min(start_tie_sigmas standard errors of the paired difference, start_tie_max x the
    # least)) (docs/inverse-design.md, "The start")
    start_tie_tol: float = Field(0.02, ge=0.0)
    start_tie_sigmas: float = Field(2.0, ge=0.0)
    start_tie_max: float = Field(0.25, ge=0.0)
    ggx_lr: float = Field(0.02, gt=0.0)  # the ggx start's roughconductor fit: Adam's rate
    # a chosen start whose held-out loss exceeds the targets' own noise (estimated from
    # the images, inverse.fit.target_noise) by more than this fits the views poorly (no
    # family holds the material): the image stage then runs at train.lr with the grids
    # at poor_start_grid_lr_scale (null: never; chosen on the development set under
    # both captures: docs/inverse-design.md, "A poor start")
    poor_start_loss: float | None = Field(0.0015, gt=0.0)
    # a first choice whose held-out loss exceeds the targets' noise by more than this is
    # poor at once: no family is near, so no contender is fitted further and the chosen
    # one is not refined (their time saved; at least poor_start_loss; null, here or
    # there: never; chosen on the development set: docs/inverse-design.md, "A poor start")
    poor_start_early_loss: float | None = Field(0.03, gt=0.0)
    # after a poor start the image stage learns the material rather than polishing a
    # start, and runs at least this many steps (train.steps raised to it; the rate's
    # cosine spans them; null: train.steps; chosen on the development set:
    # docs/inverse-design.md, "A poor start")
    poor_start_steps: int | None = Field(450, ge=1)
    # ... and its grids' learning rate / train.lr (null: model.grid.lr_scale, as from the
    # constant start; docs/inverse-design.md, "A poor start")
    poor_start_grid_lr_scale: float | None = Field(1.0, gt=0.0)
    # ... and the start's distillation into the network runs at this rate instead of
    # start_train_lr: the image stage reshapes such a start's network rather than
    # polishing it (null: train.lr; chosen on the development set: docs/inverse-design.md,
    # "A poor start")
    poor_start_train_lr: float | None = Field(None, gt=0.0)
    # ... for this many steps instead of start_train_steps (null: start_train_steps;
    # chosen on the development set: docs/inverse-design.md, "A poor start")
    poor_start_train_steps: int | None = Field(6000, ge=1)
    spp: int = Field(8, ge=1)  # samples per pixel of every view and step: the gradient pass
    primal_spp: int = Field(16, ge=1)  # ... the primal pass (its noise is in every gradient)
    lobe_every: int = Field(50, ge=1)  # steps between fits of the sampling lobe to the network
    # where the plugin evaluates the network without a tracked gradient (the primal
    # pass, the held-out scores): auto (per variant, measured), graph (the lowered ONNX
    # graph in Dr.Jit) or torch; the function is the same (docs/inverse.md)
    evaluator: Literal["auto", "graph", "torch"] = "auto"
    # the image stage's albedo penalty: albedo_weight x the sum over albedo_incidences
    # (degrees) and RGB of max(0, A - 1)^2, A estimated from albedo_side^2 wo per
    # incidence by multiple importance sampling, fresh every step (0: off; docs/inverse.md)
    albedo_weight: float = Field(1.0, ge=0.0)
    albedo_incidences: list[float] = Field(
        default_factory=lambda: [0.0, 30.0, 50.0, 65.0, 75.0, 82.0, 87.0]
    )
    albedo_side: int = Field(24, ge=1, le=256)
    # the validation split, held out of the fit (the start's too), choosing the start
    # (auto) and scored every validation_every steps; the best-scoring weights are kept
    # (the start's if none beat it)
    validation_pixels: float = Field(0.2, ge=0.0, lt=1.0)  # share of a fitted view's tiles
    validation_block: int = Field(4, ge=1, le=64)  # the split's tiles: block x block pixels
    validation_views: list[int] = Field(default_factory=list)  # target.images indices, whole
    validation_every: int = Field(10, ge=1)  # steps between held-out losses
    # held-out scorings in a row without a new best after which the image stage stops
    # (its best weights kept as ever; null: it runs train.steps; chosen on the development
    # set: docs/inverse-design.md, "When the image stage stops")
    patience: int | None = Field(5, ge=1)
    validation_spp: int = Field(64, ge=1)  # samples per pixel of the held-out renders

    @model_validator(mode="after")
    def _early_poor(self):
        # a start poor at once (its contenders and refinement skipped) must be poor
        early, limit = self.poor_start_early_loss, self.poor_start_loss
        if early is not None and limit is not None and early < limit:
            raise ValueError(
                f"poor_start_early_loss: {early:g} calls a start poor that "
                f"poor_start_loss ({limit:g}) does not; set it at least that, or null"
            )
        return self

    @property
    def early_poor_loss(self) -> float | None:
        """``poor_start_early_loss``, or None when ``poor_start_loss`` is null (no start
        is poor, so none is poor at once)."""
        return None if self.poor_start_loss is None else self.poor_start_early_loss

    @field_validator("start")
    @classmethod
    def _start(cls, name: str) -> str:
        if name not in START_CHOICES:
            *first, last = [repr(n) for n in START_CHOICES]
            raise PydanticCustomError(
                "literal_error",
                "Input should be {expected}",
                {"expected": f"{', '.join(first)} or {last}"},
            )
        return name

    @field_validator("start_families")
    @classmethod
    def _families(cls, names: list[str]) -> list[str]:
        bad = [n for n in names if n not in START_FAMILIES]
        if bad:
            why = f"{bad[0]!r} is not a family; expected some of {', '.join(START_FAMILIES)}"
        elif not names:
            why = "empty; name at least one family"
        elif len(set(names)) != len(names):
            why = f"{names} names a family twice"
        else:
            return names
        raise PydanticCustomError("start_families", why)

    @field_validator("albedo_incidences")
    @classmethod
    def _incidences(cls, degrees: list[float]) -> list[float]:
        bad = [d for d in degrees if not 0.0 <= d < 90.0]
        if not degrees:
            why = "empty; name at least one incidence (degrees)"
        elif bad:
            why = f"{bad[0]} is not an incidence in degrees from 0 to below 90"
        else:
            return degrees
        raise PydanticCustomError("albedo_incidences", why)

    @property
    def split(self) -> bool:
        """Is a validation split on?"""
        return self.validation_pixels > 0 or bool(self.validation_views)


class Texture(_Section):
    # a spatially varying teacher (target.mitsuba with textures, a normal or bump map;
    # docs/mitsuba.md, "Textured materials"): the model is a field of lobe weights over
    # uv times `lobes` shared neural lobes (docs/model.md, "Spatially varying models");
    # read by no other target.  Each lobe is the `model` section's network; the steps,
    # learning rate and loss are `train`'s, the batch and pool `data`'s.
    lobes: int = Field(4, ge=1, le=16)  # K shared lobes
    resolution: int = Field(32, ge=1, le=1024)  # the weight field's texels per side (R x R)
    field_lr_scale: float = Field(10.0, gt=0.0)  # the field's logits: lr x this
    # scalar: one weight per lobe and texel; rgb: one per lobe, texel and RGB channel (no
    # gain on the development teachers: docs/mitsuba.md, "Textured materials")
    weights: Literal["scalar", "rgb"] = "scalar"
    # shared: one network with K heads (one set of features and hidden layers; a
    # renderer evaluates one network); separate: K networks (the `model` section's
    # each).  Shared was both more accurate and cheaper to render on the development
    # teachers (benchmarks/textured_lobes.py, docs/mitsuba.md)
    lobe_network: Literal["separate", "shared"] = "shared"
    # 1: the lobes take a latent s(uv) in [0, 1] from the field as one more input
    # (conditioned lobes: a head can follow a roughness map; normalised by a table over
    # (s, theta): docs/model.md, "Conditioned lobes"); isotropic encodings only
    latent: int = Field(0, ge=0, le=1)
    # rgb: each lobe's network has an RGB output; grey: one output per lobe, its colour
    # the field's per-channel weights (needs weights: rgb).  The network's last layer and
    # its softplus are a third as wide, the largest part of a textured file's extra
    # render cost (docs/mitsuba.md, "Textured materials")
    lobe_color: Literal["rgb", "grey"] = "rgb"
    # how each lobe's albedo is bounded in the file (docs/model.md, "The lobes' bound"):
    # table, A+ looked up per evaluation (a constant instead when its largest node is at
    # most 1.02); scale, always one constant per head, 1 / max(1, its largest A+), and
    # training sees that constant too (re-estimated every 100 steps), so the lobes learn
    # within it and a renderer pays one multiply instead of the table's look-ups
    # texel, every lobe raw and the field's texels bounded instead: each texel's weights
    # divided so that sum_k z_k A+_k <= 1 at every incidence node and channel (linear in
    # z, so bilinear blends keep it); looser than one constant per lobe where lobes peak
    # at different incidences, and neither a table nor a multiply in the graph
    lobe_bound: Literal["table", "scale", "texel"] = "table"
    # ggx: two analytic heads beside the shared network, GGX with F = 1 and with
    # Schlick's grazing factor (1 - cos theta_d)^5, their alpha one more column of the
    # field (started from the teacher's eval); reciprocal, and each head's albedo <= 1 in
    # closed form for any alpha (docs/model.md, "Analytic GGX heads"). Needs
    # lobe_network: shared and lobe_bound: texel
    analytic_heads: Literal["none", "ggx"] = "none"
    # several starts (docs/mitsuba.md, "Several starts"): `starts` models from the seeds
    # train.seed, +1, ..., each trained `start_steps` steps (null: all of train.steps), the
    # one with the lowest error on pairs of its own (not the held-out ones) continued
    starts: int = Field(1, ge=1, le=16)
    start_steps: int | None = Field(None, ge=1)
    # the training pairs drawn from the teacher again every this many steps (fresh pairs;
    # null: one pool of data.pool_size for the run): a fine field sees a fixed pool's few
    # pairs per texel over and over (docs/mitsuba.md, "The pool and the field's resolution")
    fresh_every: int | None = Field(None, ge=1)
    # the pool holds at least this many pairs per texel of the field: max(data.pool_size,
    # pool_per_texel x R^2) pairs (null: data.pool_size alone); 2048 chosen on the
    # development teachers (docs/mitsuba.md, "The pool and the field's resolution")
    pool_per_texel: int | None = Field(2048, ge=1)
    # the field's logits learned as the sum of this many tables, R, R/2, R/4, ... (each
    # looked up at the R x R texel centres): the same R x R field in the file, but coarse
    # logits see many texels' pairs (docs/mitsuba.md, "The pool and the field's
    # resolution"); R must be divisible by 2^(field_levels - 1)
    field_levels: int = Field(1, ge=1, le=8)
    # after training, the field replaced by one of project x project texels fitted texel
    # by texel to the teacher on the frozen lobes (docs/mitsuba.md, "A finer field by
    # projection onto the lobes"): each texel's weights the exact non-negative least
    # squares of f cos on project_pairs pairs drawn at its centre, its latent the best of
    # project_latents values on [0, 1] and the trained one; then bounded as every field
    # is, so the physics holds as before.  null: the trained field (R x R) is the file's.
    # Shared lobe networks only; the export does it again from the checkpoint (seeded)
    project: int | None = Field(None, ge=1, le=2048)
    project_pairs: int = Field(512, ge=8)
    project_latents: int = Field(5, ge=2, le=64)
    # each projected texel shrunk toward the trained field's weights at its centre: a
    # ridge of project_ridge times the mean diagonal of its least squares' normal matrix
    # (0: none); chosen on the development teachers (docs/mitsuba.md)
    project_ridge: float = Field(0.01, ge=0.0, le=100.0)
    # with analytic_heads, the alphas each projected texel tries at its best latent:
    # geometric from half to twice its trained alpha (1: the trained alpha only)
    project_alphas: int = Field(1, ge=1, le=15)
    # with analytic_heads, where a projected texel's alpha comes from: the trained
    # field's, the teacher's own GGX fit at the texel (ggx_heads.alpha_from_teacher), or
    # both tried (the texel keeps the better)
    project_alpha: Literal["trained", "teacher", "both"] = "trained"
    # after the projection, the shared lobe network trained refit_steps more steps at
    # refit_lr with the projected field frozen, then normalised and the texels bounded
    # again (docs/mitsuba.md, "The lobes refitted on the projected field"); 0: none.
    # Needs project
    refit_steps: int = Field(0, ge=0, le=100_000)
    refit_lr: float = Field(0.001, gt=0.0, le=1.0)
    # random uv of the furnace (validate; a quadrature each, so bounded); pairs' uv: all
    # random
    validation_uv: int = Field(64, ge=1, le=4096)

    @model_validator(mode="after")
    def _projected_field(self):
        # the projection fits the K heads of one network (textured_project.project_field)
        if self.project is not None and self.lobe_network != "shared":
            raise ValueError(
                "project: the field is projected onto one shared lobe network; "
                f"set lobe_network: shared (got {self.lobe_network})"
            )
        if self.refit_steps and self.project is None:
            raise ValueError(
                "refit_steps: the lobes are refitted on a projected field; set project "
                "(or refit_steps: 0)"
            )
        return self

    @model_validator(mode="after")
    def _analytic_heads(self):
        # the heads sit beside one shared network and join the texels' bound (ggx_heads.py)
        if self.analytic_heads != "none" and (
            self.lobe_network != "shared" or self.lobe_bound != "texel"
        ):
            raise ValueError(
                "analytic_heads: the heads sit beside one shared lobe network and are "
                "bounded per texel; set lobe_network: shared and lobe_bound: texel (got "
                f"{self.lobe_network}, {self.lobe_bound})"
            )
        if self.project_alpha != "trained" and (
            self.analytic_heads == "none" or self.project is None
        ):
            raise ValueError(
                "project_alpha: a projected texel's GGX alpha; set analytic_heads: ggx and "
                f"project (or project_alpha: trained; got {self.analytic_heads}, "
                f"project {self.project})"
            )
        return self

    @model_validator(mode="after")
    def _grey_lobes(self):
        # a grey lobe's colour is the field's per-channel weights: with one weight per
        # lobe the whole model would be grey
        if self.lobe_color == "grey" and self.weights != "rgb":
            raise ValueError(
                "lobe_color: grey lobes take their colour from per-channel weights, "
                f"so they need weights: rgb, not {self.weights}"
            )
        return self

    def pool(self, pool_size: int) -> int:
        """The pairs of a textured fit's pool, given ``data.pool_size``."""
        per = 0 if self.pool_per_texel is None else self.pool_per_texel * self.resolution**2
        return max(pool_size, per)


# A run's name is one plain folder name: never a path (``../..``, ``/etc``), never empty,
# hidden or an option (``.x``, ``-x``), no control characters (issue 28).
MAX_NAME = 128
_NAME_FORBIDDEN = re.compile(r"[/\\\x00-\x1f\x7f]")


def check_name(name: str) -> str:
    """``name`` if it is a plain folder name (see above), else ValueError("name: ...")."""
    why = None
    if not name.strip():
        why = "empty"
    elif name != name.strip():
        why = "starts or ends with a space"
    elif name in (".", ".."):
        why = "a path, not a name"
    elif _NAME_FORBIDDEN.search(name):
        why = "holds a path separator or a control character"
    elif name[0] in ".-":
        why = "starts with '.' or '-'"
    elif len(name) > MAX_NAME:
        why = f"longer than {MAX_NAME} characters"
    if why is not None:
        shown = repr(name) if len(name) <= 60 else repr(name[:60]) + "..."
        raise ValueError(
            f"name: {shown}: {why}; a run's name is one plain folder name "
            "(letters, digits, '_', '-', '.'), e.g. gold_v2"
        )
    return name


class Config(_Section):
    name: str = "run"  # default run directory: runs/<name>/ (a plain name: check_name)
    target: Target = Field(default_factory=Target)
    model: Model = Field(default_factory=Model)
    normalization: Normalization = Field(default_factory=Normalization)
    data: Data = Field(default_factory=Data)
    train: Train = Field(default_factory=Train)
    validation: Validation = Field(default_factory=Validation)
    export: Export = Field(default_factory=Export)
    images: Images = Field(default_factory=Images)  # an images fit's settings
    texture: Texture = Field(default_factory=Texture)  # a spatially varying teacher's

    @model_validator(mode="after")
    def _plain_name(self):
        check_name(self.name)
        return self

    @model_validator(mode="after")
    def _held_out_views(self):
        held = self.images.validation_views
        if not held:
            return self
        key = "images.validation_views"
        if self.target.images is None:
            raise ValueError(f"{key}: only for target.images (an images fit)")
        n = len(self.target.images)
        bad = [k for k in held if not 0 <= k < n]
        if bad:
            raise ValueError(
                f"{key}: {bad[0]} is not an index of target.images (0 to {n - 1}: {n} views)"
            )
        if len(set(held)) != len(held):
            raise ValueError(f"{key}: {held} names a view twice")
        if len(held) >= n:
            raise ValueError(f"{key}: holds out all {n} views; at least one must be fitted")
        return self

    @model_validator(mode="after")
    def _conditioned_lobes(self):
        # the (s, theta) albedo table of conditioned lobes is isotropic (train/conditioned.py)
        if self.texture.latent and encodings.get(self.model.encoding).anisotropic:
            raise ValueError(
                f"texture.latent: conditioned lobes need an isotropic model.encoding, "
                f"not {self.model.encoding}"
            )
        return self

    @model_validator(mode="after")
    def _texture_starts(self):
        lv = self.texture.field_levels
        if self.texture.resolution % (1 << (lv - 1)):
            raise ValueError(
                f"texture.field_levels: {lv} levels need texture.resolution divisible by "
                f"{1 << (lv - 1)} (got {self.texture.resolution})"
            )
        n = self.texture.start_steps
        if n is not None and n > self.train.steps:
            raise ValueError(
                f"texture.start_steps: {n} is more than train.steps ({self.train.steps})"
            )
        return self

    @model_validator(mode="after")
    def _images_start(self):
        im = self.images
        if self.target.images is None:
            return self
        if im.start == "auto" and not im.split:
            raise ValueError(
                "images.start: auto chooses the start by the validation split, which is off; "
                "set images.validation_pixels > 0 or images.validation_views, or name the "
                "start (constant, ggx or a family)"
            )
        isotropic = not encodings.get(self.model.encoding).anisotropic
        if im.start in ANISOTROPIC_FAMILIES and isotropic:
            raise ValueError(
                f"images.start: {im.start} needs an anisotropic model.encoding "
                f"(anisotropic), not {self.model.encoding}"
            )
        if im.start == "auto" and isotropic and set(im.start_families) <= set(ANISOTROPIC_FAMILIES):
            raise ValueError(
                f"images.start_families: {', '.join(im.start_families)} alone: every family "
                f"is left out, as an isotropic model.encoding ({self.model.encoding}) cannot "
                "represent it; add an isotropic family or set model.encoding: anisotropic"
            )
        return self

    def to_yaml(self) -> str:
        """The resolved config (a run's config.yaml): every key, except the analytic
        ``target.model`` and ``target.params`` of a target that is not analytic (a
        Mitsuba teacher, measured data, an images fit).  Those can only hold their
        defaults there (Target's validators), which reading the file gives them again,
        and written out they read as if the run had a Lambertian target."""
        d = self.model_dump()
        t = self.target
        if t.mitsuba is not None or t.data is not None or t.images is not None:
            del d["target"]["model"], d["target"]["params"]
        return yaml.safe_dump(d, sort_keys=False)


# --------------------------------------------------------------------- sizes
# Bytes a setting makes the program hold at once, estimated from above so that the
# check (limits.check_bytes) fires before the allocation does.  Each is one tensor or a
# few of the same size: a pool pair is 9 float32 plus the target's work on it (~16 x).
PAIR_BYTES = 9 * 4 * 16
EVAL_CHUNK = 1 << 18  # pairs evaluated at once by validation and the runtime (runtime.CHUNK)


def sizes(cfg: Config) -> list[tuple[str, float]]:
    """(key, bytes) of every setting whose size the memory budget bounds."""
    m, d, v, n = cfg.model, cfg.data, cfg.validation, cfg.normalization
    widths = [*m.hidden, 3]
    # weights (an encoding's width is far below 64), with their gradients and Adam's two
    # moments; activations of a validation / runtime chunk (those of a training batch,
    # kept for the backward pass, count under data.batch_size)
    weights = 4.0 * (64 * widths[0] + sum(a * b for a, b in zip(widths, widths[1:])))
    out: list[tuple[str, float]] = [
        ("model.hidden", 4 * weights + 3.0 * 4 * EVAL_CHUNK * max(widths)),
        ("data.batch_size", float(d.batch_size) * (PAIR_BYTES + 3 * 4 * sum(widths))),
        ("data.pool_size", float(d.pool_size) * PAIR_BYTES),
        ("validation.accuracy_samples", float(v.accuracy_samples) * PAIR_BYTES),
        ("validation.pairs", float(v.pairs) * PAIR_BYTES),
        ("validation.furnace_samples", float(v.furnace_samples) * v.furnace_dirs * PAIR_BYTES),
        ("normalization.samples", float(n.samples) * max(n.table_size, n.grid_size**2) * 12),
        ("export.parity_pairs", float(cfg.export.parity_pairs) * PAIR_BYTES),
    ]
    if (
        cfg.target.mitsuba is not None
        and cfg.texture.pool_per_texel is not None
        and may_vary(cfg.target.mitsuba)
    ):
        # a textured teacher's pool (a homogeneous one reads data.pool_size alone)
        pool = cfg.texture.pool(d.pool_size)
        out.append(("texture.pool_per_texel", float(pool) * PAIR_BYTES))
        if cfg.texture.project is not None:  # the projected table: its float64 solutions,
            heads = 2 if cfg.texture.analytic_heads != "none" else 0  # and alpha's column
            width = 3 * (cfg.texture.lobes + heads) + 1 + bool(heads)  # float32, bounded copy
            out.append(("texture.project", (8.0 + 4.0 + 4.0) * cfg.texture.project**2 * width))
            # a texel's pairs are drawn and solved at once (at least one texel a chunk):
            # the pairs, and the float64 rows of its least squares
            pairs = float(cfg.texture.project_pairs)
            out.append(("texture.project_pairs", pairs * (PAIR_BYTES + 8.0 * width)))
    for key, grid in (("model.grid", m.grid), ("model.cosine_grid", m.cosine_grid)):
        out.append((key + ".size", 16.0 * grid.size**2 * grid.channels))
    return out


def may_vary(teacher: str) -> bool:
    """Whether the Mitsuba file ``teacher`` may vary over the surface, read as text before
    Mitsuba loads it: only a texture (a bitmap, a procedural one, the map of a
    ``normalmap`` or ``bumpmap``) or an included file can make it vary, so a readable
    file naming neither is homogeneous.  Unreadable: True (counted; the load refuses it)."""
    try:
        text = Path(teacher).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return True
    return "texture" in text or "include" in text


def check_sizes(cfg: Config, *, source: str = "config", overrides: Sequence[str] = ()) -> None:
    """limits.TooLarge naming the key whose size exceeds the budget, and where it was
    given (``source``, or the ``--set`` of ``overrides`` that set it)."""
    for key, nbytes in sizes(cfg):
        where = _blame(key.split("."), overrides) or source
        limits.check_bytes(f"{where}: {key}", nbytes, hint="give a smaller value")


# --------------------------------------------------------------------- YAML
class _Refused(yaml.constructor.ConstructorError):
    """A YAML text that parses but that a config must not be: its ``problem`` is the
    message, ``problem_mark`` where (parse_yaml: ``SOURCE: line N: problem``)."""


_NULL = "tag:yaml.org,2002:null"


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads ``1e-3`` as a float (YAML 1.2), not as a string,
    refuses a mapping that gives a key twice (at any depth; plain YAML keeps the last
    one silently), and a ``target.images:`` key with no value at all (every entry
    commented out: an explicit ``null`` is the documented "no images")."""

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: set = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue  # "<<: *base": keys given beside it override the merged ones
                key = self.construct_object(key_node, deep=True)
                try:
                    twice = key in seen
                    seen.add(key)
                except TypeError:  # unhashable: SafeLoader's own error follows
                    continue
                if twice:
                    shown = limits.bounded(repr(key), 80)
                    raise _Refused(None, None, f"duplicate key {shown}", key_node.start_mark)
        return super().construct_mapping(node, deep=deep)

    def construct_document(self, node: Any) -> Any:
        for key, value in _pairs(node):
            if key.value == "target":
                for k, v in _pairs(value):
                    # "images:" and nothing after it, not the explicit "images: null"
                    empty = isinstance(v, yaml.ScalarNode) and v.tag == _NULL and not v.value
                    if k.value == "images" and empty:
                        raise _Refused(
                            None,
                            None,
                            "target.images: holds no views (every entry commented out?); "
                            "list at least one {scene, image} pair, or delete the key",
                            k.start_mark,
                        )
        return super().construct_document(node)


def _pairs(node: Any) -> list:
    """A mapping node's (key, value) nodes whose key is a plain string scalar."""
    if not isinstance(node, yaml.MappingNode):
        return []
    return [
        (k, v) for k, v in node.value if isinstance(k, yaml.ScalarNode) and k.tag.endswith(":str")
    ]


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                    |\.[0-9_]+(?:[eE][-+][0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def parse_yaml(text: str, *, source: str) -> Any:
    """YAML text -> Python data; ConfigError (with line and column) on a syntax error,
    and on a text that expands to more than limits.MAX_CONFIG_NODES nodes (an alias
    bomb: a few hundred bytes that reference each other into billions of values)."""
    try:
        data = yaml.load(text, Loader=_Loader)
    except _Refused as e:
        line = e.problem_mark.line + 1 if e.problem_mark else "?"
        raise ConfigError(limits.bounded(f"{source}: line {line}: {e.problem}")) from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(limits.bounded(f"{source}: invalid YAML{where}: {problem}")) from None
    except RecursionError:
        raise ConfigError(f"{source}: YAML nested too deeply") from None
    if limits.count_nodes(data) > limits.MAX_CONFIG_NODES:
        raise ConfigError(
            f"{source}: expands to more than {limits.MAX_CONFIG_NODES:,} YAML values "
            "(aliases counted each time they are used): refused"
        )
    return data


def _names_a_brdf(target: Any) -> bool:
    """Whether a raw ``target`` section names what to train: a model, a measured file, a
    teacher or images (``target: {data: }``, a path left empty, names none)."""
    if not isinstance(target, dict):
        return True  # (the schema's error, not this warning)
    return any(target.get(k) is not None for k in ("model", "data", "mitsuba", "images"))


def apply_override(raw: dict, item: str) -> None:
    """Apply one ``a.b.c=value`` override to the raw (unvalidated) config dict."""
    key, sep, text = item.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. train.steps=500")
    path = key.strip().split(".")
    if not all(p.strip() for p in path):
        raise ConfigError(f"--set {item}: an empty part in the key {key.strip()!r}")
    if path in (["target", "data"], ["target", "mitsuba"]) and not text.strip():
        # (an unset shell variable: YAML reads it as null, the default analytic target,
        # which would then be trained without a word; null itself, written out, is that)
        raise ConfigError(f"--set {item}: an empty path; give the file (or null for none)")
    value = parse_yaml(text, source=f"--set {key}")
    node = raw
    for i, part in enumerate(path[:-1]):
        if node.get(part) is None:  # absent, or the file's empty section (`train:`)
            node[part] = {}
        child = node[part]
        if not isinstance(child, dict):
            raise ConfigError(f"--set {item}: {'.'.join(path[: i + 1])}: is a value, not a section")
        node = child
    node[path[-1]] = value


def _blame(
    key: Sequence,
    overrides: Sequence[str],
    *,
    within: Sequence = (),
    message: str = "",
    under: bool = True,
) -> str | None:
    """``--set ITEM`` of the last override that sets ``key`` (the failing key) or a section
    holding it, or (``under``: a schema error, where a key set under a value made it a
    section) a key under it; None when the key comes from the file.

    ``within`` and ``message``: ``key`` was found by a validator of section ``within``
    (its message names it).  Such a check may fail for a key that the message names
    beside it (``pool_size: must be >= batch_size``): the one override under ``within``
    whose key the message names is blamed; when none or several are, the file is.
    Another override in the same section is never blamed (it did not fail)."""
    key = tuple(str(p) for p in key)
    given = [(tuple(item.partition("=")[0].strip().split(".")), item) for item in overrides]
    for k, item in reversed(given):
        # the key itself, a section holding it, or a key under it (train.steps.x=5 made
        # the value train.steps a section)
        if key[: len(k)] == k or (under and k[: len(key)] == key):
            return f"--set {item}"
    within = tuple(str(p) for p in within)
    named = {}  # the overrides under `within` whose key the message names: the last of each
    for k, item in given:
        rest = ".".join(k[len(within) :])
        if message and rest and k[: len(within)] == within:
            if re.search(rf"(?<![\w.]){re.escape(rest)}(?![\w.])", message):
                named[k] = item
    return f"--set {next(iter(named.values()))}" if len(named) == 1 else None


def _is_key(path: Sequence[str]) -> bool:
    """Whether ``path`` names a section or key of the schema, down to its first leaf
    (``target.params``: the leaf; what lies under a mapping is not checked)."""
    model: Any = Config
    for part in path:
        fields = getattr(model, "model_fields", None)
        if fields is None:  # a leaf or a mapping: the rest lies under it
            return True
        if part not in fields:
            return False
        ann = fields[part].annotation
        subs = [a for a in getattr(ann, "__args__", ()) if isinstance(a, type)]
        model = (
            ann
            if isinstance(ann, type)
            else next((a for a in subs if issubclass(a, BaseModel)), None)
        )
    return True


def blamed(e: ConfigError, source: str, overrides: Sequence[str]) -> ConfigError:
    """``e``, raised after validation by a check of a config key (``target.params:
    alpha: ...``, from building the target), named as :func:`from_dict` names its own
    errors: by the ``--set`` that gave the key, else by the config file ``source``.  A
    message that does not start with a key of the config (a file's, a run's) is kept."""
    msg = str(e)
    m = re.match(r"([a-z_]+(?:\.[A-Za-z_]\w*)*):", msg)
    if not m or msg.startswith(f"{source}:") or not _is_key(m.group(1).split(".")):
        return e  # (a message naming a file: images.yaml: ... is no key of the config)
    key = m.group(1).split(".")
    by = _blame(key, overrides, under=False)  # the key's override, or its section's
    sub = re.match(r"\s*(?:\w+\.)?(\w+):", msg[m.end() :])  # "alpha:", "microfacet.alpha:"
    if by is None and sub:  # else the one just under it that the message names first
        for item in reversed(overrides):
            if item.partition("=")[0].strip().split(".") == [*key, sub.group(1)]:
                by = f"--set {item}"
                break
    return ConfigError(f"{by or source}: {msg}")


def _key_of(err: Any) -> tuple[str, ...]:
    """The key a top-level validator's message names first (``images.x: ...``), as a loc."""
    m = re.match(r"(?:Value error, )?([A-Za-z_][\w.]*):", str(err.get("msg", "")))
    return tuple(m.group(1).split(".")) if m else ()


def _describe(err: Any) -> str:
    loc = ".".join(str(p) for p in err["loc"])
    if err["type"] == "extra_forbidden":
        return f"{loc}: unknown key"
    if err["type"] == "value_error":
        # our section validators word their message as "field: what is wrong"
        msg = err["msg"].removeprefix("Value error, ")
        return f"{loc}.{msg}" if loc else msg
    got = err.get("input")
    shown = "" if isinstance(got, (dict, list)) else f" (got {limits.bounded(repr(got), 80)})"
    return f"{loc}: {err['msg']}{shown}"


def from_dict(raw: Any, *, source: str = "config", overrides: Sequence[str] = ()) -> Config:
    """Validate a raw config.  An error names ``source``, or the ``--set`` of
    ``overrides`` (already applied to ``raw``) that gave the offending key."""
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{source}: expected a mapping of keys at the top level")
    try:
        cfg = Config.model_validate(raw)
    except ValidationError as e:
        # a misspelt key first: it is also a missing one ("imgae" for "image"), and the
        # typo is what the user must see
        errs = sorted(e.errors(), key=lambda err: err["type"] != "extra_forbidden")
        more = f" (and {len(errs) - 1} more)" if len(errs) > 1 else ""
        loc = tuple(errs[0]["loc"])
        if errs[0]["type"] == "value_error" or not loc:
            # a validator's error: its loc is the section, its message names the key
            key, msg = loc + _key_of(errs[0]), str(errs[0].get("msg", ""))
            where = _blame(key, overrides, within=loc, message=msg) or source
        else:
            where = _blame(loc, overrides) or source
        raise ConfigError(limits.bounded(f"{where}: {_describe(errs[0])}{more}")) from None
    except RecursionError:
        raise ConfigError(f"{source}: nested too deeply") from None
    check_sizes(cfg, source=source, overrides=overrides)
    return cfg


def read_text(path: Path) -> str:
    """A config file's text; ConfigError naming the file if it is unreadable or not UTF-8,
    or is no regular file (a FIFO or a device: refused before it is read, never waited
    on).  At most ``limits.MAX_CONFIG_BYTES`` + 1 bytes are read.  (The command line
    names a measured file given as a config as such: ``cli._not_measured``.)"""
    from neural_brdf import fileio

    try:
        data = fileio.read_capped(path, limits.MAX_CONFIG_BYTES)
    except fileio.NotAFileError as e:
        raise ConfigError(f"{e} (give a config file)") from None
    except IsADirectoryError:  # a run folder, most likely ("Is a directory" before)
        inside, model = Path(path) / "config.yaml", Path(path) / "model.onnx"
        said = f"; its config is {inside}" if inside.is_file() else ""
        said += f", its model {model}" if said and model.is_file() else ""
        raise ConfigError(f"{path}: is a folder, not a config file{said}") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config ({e.strerror})") from None
    if len(data) > limits.MAX_CONFIG_BYTES:
        try:
            size = limits.human(path.stat().st_size)
        except OSError:
            size = "more than " + limits.human(limits.MAX_CONFIG_BYTES)
        raise ConfigError(
            f"{path}: {size}, more than a config may be "
            f"({limits.human(limits.MAX_CONFIG_BYTES)}); is it a config file?"
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a YAML text file (byte {e.start} is not UTF-8)") from None


def paths_relative_to(raw: dict, folder: Path) -> None:
    """target.images, target.mitsuba and target.data paths in a config file are relative
    to its folder: made absolute (so a run's config.yaml finds them from any folder).
    target.data was read against the current folder before: a file found there and not
    beside the config is still taken (a config written for that rule).  A path that
    starts with ``~`` is the user's home (as a shell would read it), not a folder "~"
    beside the config."""
    target = raw.get("target")
    if isinstance(target, dict):
        for key in ("data", "mitsuba"):
            if isinstance(target.get(key), str) and target[key].startswith("~"):
                target[key] = os.path.expanduser(target[key])
        data = target.get("data")
        if isinstance(data, str) and data.strip() and not Path(data).is_absolute():
            beside = folder / data
            old_rule = not beside.exists() and Path(data).exists()
            target["data"] = os.path.abspath(data if old_rule else beside)
        teacher = target.get("mitsuba")
        if isinstance(teacher, str) and teacher.strip() and not Path(teacher).is_absolute():
            target["mitsuba"] = os.path.abspath(folder / teacher)
    images = target.get("images") if isinstance(target, dict) else None
    for item in images if isinstance(images, list) else ():
        for key in ("scene", "image", "subtract") if isinstance(item, dict) else ():
            value = item.get(key)
            if isinstance(value, str) and value.startswith("~"):
                value = item[key] = os.path.expanduser(value)
            if isinstance(value, str) and value.strip() and not Path(value).is_absolute():
                item[key] = os.path.abspath(folder / value)


# Keys added after runs were written whose default is not what the earlier version did:
# the value that does it again.  A run's config.yaml is resolved (every key of its
# version written), so a key it lacks was added since, and ``load(..., run=True)``
# gives it this value, not the default: ``export RUN`` of an older run makes its file
# again.  A user's config without the key takes the default.
EARLIER: dict[tuple[str, str], Any] = {
    ("texture", "project_ridge"): 0.0,  # no ridge before texture.project_ridge
}


def _earlier_defaults(raw: dict) -> None:
    """A run's resolved config: each :data:`EARLIER` key it lacks (in a section it has)
    takes the earlier version's value."""
    for (section, key), value in EARLIER.items():
        part = raw.get(section)
        if isinstance(part, dict) and key not in part:
            part[key] = value


def load(
    path: str | Path | None,
    overrides: Sequence[str] = (),
    *,
    name: str | None = None,
    warn: Callable[[str], None] | None = None,
    run: bool = False,
) -> Config:
    """Read a YAML config (or start from the defaults when ``path`` is None), apply
    ``--set`` overrides and validate.  ``name`` defaults to the file's stem.

    ``warn`` is called with a one-line message when the file (with the overrides)
    gives no ``target``: an empty file, or one without a ``target:`` section, is valid,
    and trains the default target, but is more likely a mistake; when it sets
    ``images`` keys (to other than their defaults) for a target that is not an images
    fit, which reads none of them (:func:`ignored_images`); and when it sets
    ``texture`` keys for a target that is not a Mitsuba teacher (:func:`ignored_texture`).

    ``run``: ``path`` is a run's resolved config.yaml, written by an earlier version
    perhaps: a key it lacks that did otherwise before it existed takes that value
    (:data:`EARLIER`).
    """
    raw: dict = {}
    empty = False
    if path is not None:
        path = Path(path)
        text = read_text(path)
        raw = parse_yaml(text, source=str(path))
        if raw is None:
            raw, empty = {}, True
        if not isinstance(raw, dict):
            raise ConfigError(
                f"{path}: expected a mapping of keys at the top level, got {type(raw).__name__}"
            )
        if "name" not in raw:
            raw["name"] = name or path.stem
        paths_relative_to(raw, path.parent)
        if run:
            _earlier_defaults(raw)
    for item in overrides:
        apply_override(raw, item)
    if overrides:
        paths_relative_to(raw, Path.cwd())  # a path given by --set: the current folder's
    cfg = from_dict(raw, source=str(path) if path is not None else "config", overrides=overrides)
    given = raw.get("target")
    if warn is not None and path is not None and "target" not in raw:
        what = "empty config" if empty else "no target: section"
        warn(f"{path}: {what}: training the default target (a {cfg.target.model} BRDF)")
    elif warn is not None and path is not None and not _names_a_brdf(given):
        warn(
            f"{path}: target: names no BRDF (model, data, mitsuba and images empty): "
            f"training the default target (a {cfg.target.model} BRDF)"
        )
    if warn is not None:
        for section, keys, why in (
            ("images", ignored_images(cfg), "only an images fit (target.images) reads them"),
            ("texture", ignored_texture(cfg), _texture_unread(cfg)),
        ):
            if not keys:
                continue
            # the file, unless every one of them was given by --set (then the first's)
            blamed = [_blame((section, k), overrides) for k in keys]
            where = next((b for b in blamed if b), "config") if all(blamed) else str(path)
            listed = ", ".join(f"{section}.{k}" for k in keys)
            warn(f"{where}: {listed}: ignored: {why}")
    return cfg


def _changed(section: _Section, default: _Section) -> list[str]:
    """The keys of ``section`` set to other than their values in ``default``."""
    return [k for k in type(default).model_fields if getattr(section, k) != getattr(default, k)]


def ignored_images(cfg: Config) -> list[str]:
    """The ``images`` keys ``cfg`` sets to other than their defaults while its target is
    not an images fit (no other target reads them); [] for an images fit."""
    if cfg.target.images is not None:
        return []
    return _changed(cfg.images, Images())


def ignored_texture(cfg: Config) -> list[str]:
    """The ``texture`` keys ``cfg`` sets to other than their defaults while its target is
    not a Mitsuba teacher: only a teacher that varies over the surface reads them.  []
    for a Mitsuba teacher, whose file is read first: a homogeneous one's run says the
    section is ignored itself (``pipeline.teacher_warnings``, the same comparison)."""
    if cfg.target.mitsuba is not None:
        return []
    return _changed(cfg.texture, Texture())


def _texture_unread(cfg: Config) -> str:
    t = cfg.target
    what = (
        "an images fit (target.images)"
        if t.images is not None
        else "measured data (target.data)"
        if t.data is not None
        else f"an analytic target ({t.model})"
    )
    return (
        "only a Mitsuba teacher that varies over the surface (target.mitsuba) reads "
        f"them, not {what}; the model is homogeneous"
    )
