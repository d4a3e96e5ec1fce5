"""A differentiable neural BSDF for Mitsuba 3: the training-time path of inverse rendering.

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")                 # or cuda_ad_rgb
    from neural_brdf.inverse import bsdf as inverse_bsdf  # registers 'neural_brdf_ad'
    bsdf = mi.load_dict({"type": "neural_brdf_ad", "model": inverse_bsdf.COMPACT})
    params = mi.traverse(bsdf)                    # 'raw.mlp.head.weight', 'raw.grid.table', ...
    with inverse_bsdf.evaluated_mode():           # dr.wrap needs evaluated loops and calls
        img = mi.render(scene, params, spp=16)
        dr.backward(loss(img))                    # gradients reach every weight

Design.  The model is the very :class:`neural_brdf.train.model.RawBRDF` that ``neural-brdf
train`` trains, evaluated by torch; :func:`drjit.wrap` stitches it into Mitsuba's
Dr.Jit AD graph (Dr.Jit <-> torch interop).  Its trainable state (the MLP weights, the
learned feature grids) lives in Dr.Jit tensors (``mi.TensorXf``) that ``traverse``
exposes, so ``mi.traverse``, ``mi.ad`` optimisers and ``dr.backward`` work as with a
built-in plugin: each evaluation hands those tensors to torch, which runs
``torch.func.functional_call(raw, weights, (wi, wo))``, and reverse-mode AD runs
torch's backward for that call.  No part of the model is retyped here: when the fit is
done, :func:`state_dict` turns the tensors back into the RawBRDF's state and the usual
export (:func:`neural_brdf.export.normalized_model`, ONNX) applies unchanged.  Renderers
then use the exported graph (:mod:`neural_brdf.renderers.mitsuba`); this plugin is for fitting only.

Speed: two evaluations of one function.  Where no weight tracks a gradient (Mitsuba's
primal pass of ``mi.render``, held-out scores, plain renders), the ``graph`` evaluator
(the default, ``auto``, in ``llvm_ad_rgb``) does not call torch: it evaluates the
RawBRDF's own ONNX graph (the exporter every file goes through, without the
normalisation), lowered once per model section (every instance of it shares the
program) by :func:`neural_brdf.graph.lower` with every ``state_dict`` entry kept as a
trained parameter, and the Dr.Jit back end binds the live tensors at each evaluation
(:func:`neural_brdf.backends.drjit.run`, ``params``), so
the primal pass traces into Mitsuba's kernels like the ``neural_brdf`` plugin's, in
symbolic or evaluated mode.  Where a gradient is tracked (the gradient pass) torch
evaluates the network through ``dr.wrap`` as above: differentiating the lowered graph in
Dr.Jit turned every weight's adjoint into a scatter or a reduction over the lanes, slower
than torch's matrix products (module doc of :mod:`neural_brdf.backends.drjit`).  Torch
runs only the part the weights set, :meth:`RawBRDF.network` (the grids' look-ups and the
MLP); the parts free of weights, :meth:`RawBRDF.encode` (the features and the grids'
coordinates) and :meth:`RawBRDF.finish` (the grazing factor, zero below the horizon),
run in Dr.Jit from their own exported graphs, lowered like the whole one, fused into the
kernels around torch's call (where wi or wo track a gradient, torch runs all of it, so
that they get their adjoints).  All of these evaluate the same function to float32
rounding (tests/backends/test_trained_params.py, tests/inverse/test_inverse.py);
``'evaluator': 'torch'`` uses torch for both passes,
and is what ``auto`` picks in ``cuda_ad_rgb``, where torch's matrix products on the GPU
measured faster than the lowered graph's per-weight loads (:data:`AUTO`).
In a symbolic scope the graph is used whatever the evaluator: a symbolic virtual call
traces every BSDF instance alive, so a symbolic render of another scene (a
``roughconductor`` fit beside a live plugin) traces this one, and torch cannot.

Reciprocity is exact, as in training: it is a property of the encoding (bit-identical
features for (wi, wo) and (wo, wi)), which this plugin evaluates unchanged.  The albedo
bound is not enforced here (raw network, no table): :mod:`neural_brdf.inverse.fit` penalises
an albedo above 1 during the fit and the export bakes the exact normalisation.

Constraints of :func:`drjit.wrap`.  Torch needs evaluated arrays, so a render that
tracks gradients must run with symbolic loops and symbolic virtual calls switched off
(:func:`evaluated_mode`); ``eval`` raises a one-line error otherwise.  Sampling is the mixture of
:mod:`neural_brdf.physics.lobe_fit` (cosine hemisphere + a GGX/Beckmann visible-normal lobe), with
code shared with the ``neural_brdf`` plugin (:class:`neural_brdf.renderers.mitsuba._GraphBSDF`); the
lobe is fitted to the current network by :meth:`NeuralBSDFAD.refit_lobe`.  The sample
weight is eval / pdf, and the pdf does not depend on the weights (the lobe is fixed
between refits), so at fixed samples every path's contribution is linear in f: the
gradient of a render is that of its Monte Carlo estimate (tests/inverse/test_inverse.py checks
it against finite differences).

Importing this module needs an RGB JIT variant with AD (``llvm_ad_rgb``,
``cuda_ad_rgb``); others raise :class:`neural_brdf.errors.InputError`.
"""

from __future__ import annotations

import contextlib
import copy

import drjit as dr
import mitsuba as mi
import numpy as np
import torch
import yaml

from neural_brdf import config as cfgmod
from neural_brdf import graph
from neural_brdf.encodings.angles import columns
from neural_brdf.errors import InputError
from neural_brdf.fileformat import lobe as lobe_format
from neural_brdf.physics import lobe_fit

if mi.variant() is None or not (mi.is_rgb and dr.is_diff_v(mi.Float) and dr.is_jit_v(mi.Float)):
    raise InputError(
        f"neural_brdf.inverse.bsdf: Mitsuba variant {mi.variant()!r} is not a JIT AD RGB "
        "variant; set llvm_ad_rgb or cuda_ad_rgb first"
    )

from neural_brdf.backends import drjit as drjit_backend  # noqa: E402
from neural_brdf.export import to_onnx_bytes  # noqa: E402
from neural_brdf.renderers.mitsuba import _GraphBSDF  # noqa: E402  (needs the variant set, like this module)
from neural_brdf.train.model import RawBRDF  # noqa: E402

PLUGIN = "neural_brdf_ad"
# How the plugin evaluates the network (its 'evaluator' property; module doc, Speed):
# "graph": the RawBRDF's ONNX graph, lowered once with its weights kept as parameters,
# where no gradient is tracked (a primal render), torch where one is;
# "torch": the RawBRDF through dr.wrap wherever arrays are evaluated (the graph only
# where they are symbolic, which torch cannot take);
# "auto" (the default): whichever measured faster in the variant (primal_evaluator).
EVALUATORS = ("auto", "graph", "torch")  # images.evaluator's choices (config.Images)
# "auto" per variant, from benchmarks/image_step.py (the primal pass of three 96² views
# at 16 spp, results/image_step.json and results/cuda/image_step.json): llvm_ad_rgb on 2
# cores, graph 0.081 s against torch 0.146 s; cuda_ad_rgb on an H200, graph 0.054 s
# against torch 0.030 s (torch's GPU matrix products beat the per-weight loads that the
# lowered graph makes in every lane).
AUTO = {"llvm_ad_rgb": "graph", "cuda_ad_rgb": "torch"}
# The compact recipe (configs/gold.yaml): 32 x 32 x 4 grid + one ReLU layer of 32.
COMPACT = "{hidden: [32], activation: relu, grid: {size: 32, channels: 4, lr_scale: 10.0}}"
# A start for the sampling lobe before it is fitted to the network.
DEFAULT_LOBE = {"kind": lobe_format.KIND, "alpha": 0.3, "weight": 0.5}

__all__ = [
    "COMPACT",
    "PLUGIN",
    "NeuralBSDFAD",
    "evaluated_mode",
    "model_section",
]


@contextlib.contextmanager
def evaluated_mode():
    """Evaluated (not symbolic) loops and virtual calls, as :func:`drjit.wrap` needs."""
    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    old = [dr.flag(f) for f in flags]
    for f in flags:
        dr.set_flag(f, False)
    try:
        yield
    finally:
        for f, v in zip(flags, old):
            dr.set_flag(f, v)


def model_section(text_or_dict) -> cfgmod.Model:
    """The ``model`` config section from YAML text or a dict (validated as in a config)."""
    raw = yaml.safe_load(text_or_dict) if isinstance(text_or_dict, str) else text_or_dict
    try:
        return cfgmod.Model.model_validate(raw or {})
    except Exception as e:  # pydantic's ValidationError: one line
        first = str(e).splitlines()
        raise InputError(f"{PLUGIN}: 'model': {first[-1] if first else e}") from None


def _to_dr(t: torch.Tensor) -> mi.TensorXf:
    return mi.TensorXf(np.ascontiguousarray(t.detach().cpu().float().numpy()))


def _eval_torch(raw: RawBRDF):
    """The torch side where wi or wo track a gradient: (wi, wo components, weights) ->
    f cos(theta_o), RGB columns, the whole RawBRDF in torch (:func:`drjit.wrap` hands
    it every floating-point input with ``requires_grad`` set: the directions' adjoints
    flow back to Dr.Jit)."""

    @dr.wrap(source="drjit", target="torch")
    def f_cos(wx, wy, wz, ox, oy, oz, weights):
        wi = columns([wx, wy, wz])  # (N, 3), column-major as the encodings' features
        wo = columns([ox, oy, oz])
        f = torch.func.functional_call(raw, weights, (wi, wo))
        fc = f * oz.clamp_min(0.0)[:, None]
        return fc[:, 0], fc[:, 1], fc[:, 2]

    return f_cos


class _Part(torch.nn.Module):
    """One part of the RawBRDF's forward pass, ``part(raw, *inputs)``, as a module: what
    ``torch.onnx.export`` traces and ``torch.func.functional_call`` runs (the parameters
    are the RawBRDF's, under ``raw.``)."""

    def __init__(self, raw: RawBRDF, part):
        super().__init__()
        self.raw = raw
        self.part = part

    def forward(self, *inputs):
        return self.part(self.raw, *inputs)


def _encode_columns(raw: RawBRDF, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """:meth:`RawBRDF.encode` as one (N, K) output, its columns in the order of
    :meth:`RawBRDF.encoded_columns`."""
    return columns(raw.encoded_columns(raw.encode(wi, wo)))


def _network_of_columns(raw: RawBRDF, cols: list[torch.Tensor]) -> torch.Tensor:
    return raw.network(raw.encoded_from_columns(cols))


def _network_torch(raw: RawBRDF):
    """(encoded columns, weights) -> the network's output columns, in torch through
    :func:`drjit.wrap`: the weights' gradients are torch's; the columns, free of
    weights and computed in Dr.Jit from directions that track no gradient, are
    detached (torch would otherwise differentiate them too, adjoints Dr.Jit drops)."""
    net = _Part(raw, _network_of_columns)

    @dr.wrap(source="drjit", target="torch")
    def network(cols, weights):
        y = torch.func.functional_call(
            net, {"raw." + k: v for k, v in weights.items()}, ([c.detach() for c in cols],)
        )
        return tuple(y[:, k] for k in range(y.shape[-1]))

    return network


def primal_evaluator(evaluator: str, variant: str) -> str:
    """What evaluates the network where no gradient is tracked: "graph" or "torch"
    (``evaluator`` as the plugin's property; "auto" resolved by :data:`AUTO`)."""
    if evaluator not in EVALUATORS:
        raise InputError(
            f"{PLUGIN}: 'evaluator': {evaluator!r} is not one of {', '.join(EVALUATORS)}"
        )
    return AUTO.get(variant, "graph") if evaluator == "auto" else evaluator


# Lowered parts by (model section as JSON, part), each with its packet plan: every
# weight is a parameter bound at run time, so one program serves every plugin instance
# of a section (a fit makes 3 or 4; an export and lowering took about 0.06 s each)
_LOWERED: dict[tuple[str, str], tuple[graph.Program, drjit_backend.PacketPlan]] = {}


def _lowered(
    raw: RawBRDF, section: cfgmod.Model, part: str
) -> tuple[graph.Program, drjit_backend.PacketPlan]:
    """A part of the RawBRDF's graph (the exporter every file goes through, no
    normalisation), lowered once per section, and its packet plan: ``whole`` (wi, wo ->
    f, every ``state_dict`` entry kept as a trained parameter, which
    :func:`drjit_backend.run` binds to the plugin's live weights), and the weight-free
    parts the gradient pass runs around torch's network, ``encode`` (wi, wo -> e:
    :meth:`RawBRDF.encode`) and ``finish`` (y, wi, wo -> f: :meth:`RawBRDF.finish`).
    ``raw`` is built from ``section``."""
    key = (section.model_dump_json(), part)
    if key not in _LOWERED:
        opset = cfgmod.Export().opset
        if part == "whole":
            onnx_bytes = to_onnx_bytes(raw, opset)
            program = graph.lower(onnx_bytes, ("f",), params=tuple(raw.state_dict()))
        elif part == "encode":
            onnx_bytes = to_onnx_bytes(_Part(raw, _encode_columns), opset, outputs=("e",))
            program = graph.lower(onnx_bytes, ("e",))
        else:
            widths = {"y": raw.colors * raw.heads}
            finish = _Part(raw, RawBRDF.finish)
            onnx_bytes = to_onnx_bytes(finish, opset, inputs=("y", "wi", "wo"), widths=widths)
            program = graph.lower(onnx_bytes, ("f",))
        _LOWERED[key] = (program, drjit_backend.PacketPlan(program))
    return _LOWERED[key]


class NeuralBSDFAD(_GraphBSDF):
    """``{'type': 'neural_brdf_ad', 'model': '<YAML of a model section>', 'seed': 0,
    'init_value': 0.3}``: a trainable RawBRDF (see the module doc).

    ``raw.<name>`` parameters (``mi.traverse``) are the torch ``state_dict`` entries as
    ``mi.TensorXf`` of the same shapes, all differentiable.
    """

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        section = model_section(props["model"] if "model" in props else COMPACT)
        seed = int(props["seed"]) if "seed" in props else 0
        init_value = float(props["init_value"]) if "init_value" in props else 0.3
        self.model = section
        with torch.random.fork_rng():  # seeds the weights without touching torch's RNG
            torch.manual_seed(seed)
            self.raw = RawBRDF.from_config(section, init_value=init_value).eval()
        self.weights = {k: _to_dr(v) for k, v in self.raw.state_dict().items()}
        # torch runs the network alone (the weight-free parts in Dr.Jit) unless wi or wo
        # track a gradient: then all of it (_torch_f_cos)
        self._network_torch = _network_torch(self.raw)
        self._f_cos_torch_directions = _eval_torch(self.raw)
        self.encoder = _lowered(self.raw, section, "encode")
        self.finisher = _lowered(self.raw, section, "finish")
        self.evaluator = str(props["evaluator"]) if "evaluator" in props else EVALUATORS[0]
        self.primal = primal_evaluator(self.evaluator, mi.variant())
        self.program, self.plan = _lowered(self.raw, section, "whole")
        self.textured = False  # the parent's _f_cos: a homogeneous graph (wi, wo)
        self.label = "trainable RawBRDF"
        self.lobe_source = "default"
        self.set_lobe(DEFAULT_LOBE)
        flags = (
            mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        )
        self.m_components = [flags]
        self.m_flags = flags

    # -- state ------------------------------------------------------------------
    def set_lobe(self, lobe: dict, source: str = "set") -> None:
        """The sampling mixture (:mod:`neural_brdf.fileformat.lobe`); not differentiated."""
        self.lobe = lobe_format.complete(dict(lobe))
        self.lobe_table = self.lobe.get("table")
        self.lobe_weight = (
            max(self.lobe_table["weight"]) if self.lobe_table else float(self.lobe["weight"])
        )
        self.lobe_retro = self.lobe["retro"]
        self.lobe_source = source

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The current weights as a RawBRDF ``state_dict`` (CPU float32 copies)."""
        return {
            k: torch.from_numpy(np.array(v.numpy(), dtype=np.float32, copy=True)).reshape(
                tuple(v.shape)
            )
            for k, v in self.weights.items()
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Set the weights from a RawBRDF ``state_dict`` (shapes must match)."""
        params = mi.traverse(self)  # assigns in place: scenes keep seeing these tensors
        for k, v in state.items():
            if k not in self.weights or tuple(self.weights[k].shape) != tuple(v.shape):
                raise InputError(f"{PLUGIN}: weight {k!r} does not fit this model")
            params["raw." + k] = _to_dr(v)
        params.update()

    def torch_model(self, state: dict[str, torch.Tensor] | None = None) -> RawBRDF:
        """A RawBRDF holding the current weights, or ``state`` (a copy, for export or
        checks)."""
        raw = copy.deepcopy(self.raw)
        raw.load_state_dict(self.state_dict() if state is None else state)
        return raw.eval()

    def refit_lobe(self, seed: int = 0, state: dict[str, torch.Tensor] | None = None) -> dict:
        """Fit the sampling lobe to the network (its current weights, or ``state``) with
        :func:`neural_brdf.physics.lobe_fit.fit`, and use it."""
        raw = self.torch_model(state)

        def fn(wi, wo):
            with torch.no_grad():
                return raw(torch.as_tensor(wi).float(), torch.as_tensor(wo).float()).numpy()

        fitted = lobe_fit.fit(fn, seed=seed, anisotropic=raw.anisotropic)
        self.set_lobe(fitted, "fitted to the current weights")
        return fitted

    # -- evaluation: the lowered graph, or torch through dr.wrap ---------------------
    def _graph_uses_program(self) -> bool:
        """Whether this evaluation runs the lowered graph (else torch).  Always inside a
        symbolic scope: torch cannot take symbolic arrays, and a symbolic virtual call
        traces every BSDF instance alive, so a render of any other scene in symbolic
        mode traces this one too.  Otherwise where the primal evaluator is "graph" and
        no weight tracks a gradient (Mitsuba's primal pass suspends them)."""
        if dr.flag(dr.JitFlag.SymbolicScope):
            return True
        return self.primal == "graph" and not any(
            dr.grad_enabled(v.array) for v in self.weights.values()
        )

    def _graph_f_cos(self, wi, wo, cos_o=None):
        """The lowered graph with the live weights bound (parent's ``_f_cos`` calls it
        inside its conditional, symbolic or evaluated).  ``cos_o``, the parent's unit
        wo's cosine, is not used: the fit's directions are Mitsuba's, and the cosine is
        cos_theta(wo), as the gradient pass (:meth:`_torch_f_cos`) takes it."""
        cols = drjit_backend.run(
            self.program,
            {"wi": [wi.x, wi.y, wi.z], "wo": [wo.x, wo.y, wo.z]},
            self.plan,
            params={k: v.array for k, v in self.weights.items()},
        )
        cos_o = mi.Frame3f.cos_theta(wo)
        return mi.Color3f(cols["f"][0], cols["f"][1], cols["f"][2]) * cos_o

    def _torch_f_cos(self, wi, wo):
        if dr.flag(dr.JitFlag.SymbolicLoops) or dr.flag(dr.JitFlag.SymbolicCalls):
            raise InputError(
                f"{PLUGIN}: render inside neural_brdf.inverse.bsdf.evaluated_mode() "
                "(torch needs evaluated loops and calls)"
            )
        if dr.grad_enabled(wi) or dr.grad_enabled(wo):
            fc = self._f_cos_torch_directions(wi.x, wi.y, wi.z, wo.x, wo.y, wo.z, self.weights)
            return mi.Color3f(*fc)
        # the encoding and the finish (grazing factor, horizon) in Dr.Jit from their own
        # graphs, fused into the kernel that gathers the lanes; torch runs the grids and
        # the MLP, which the weights set (module doc, Speed)
        dirs = {"wi": [wi.x, wi.y, wi.z], "wo": [wo.x, wo.y, wo.z]}
        e = drjit_backend.run(self.encoder[0], dirs, self.encoder[1])["e"]
        y = self._network_torch(e, self.weights)
        f = drjit_backend.run(self.finisher[0], {"y": list(y), **dirs}, self.finisher[1])["f"]
        cos_o = dr.maximum(mi.Frame3f.cos_theta(wo), 0.0)
        return mi.Color3f(f[0], f[1], f[2]) * cos_o

    def _f_cos(self, si, wo, active):
        if self._graph_uses_program():  # the parent's conditional, symbolic or not
            return super()._f_cos(si, wo, active)
        wi = si.wi
        valid = active & (mi.Frame3f.cos_theta(wi) > 0.0) & (mi.Frame3f.cos_theta(wo) > 0.0)
        if dr.width(valid) == 0 or not dr.any(valid, axis=None):
            return mi.Color3f(0.0)
        # torch sees the valid lanes only (a quarter of a fit's are below a horizon:
        # emitter samples behind the surface), gathered and scattered back; the
        # scatter's adjoint is a gather, so each lane's gradient is where it was
        n = dr.width(valid)
        if dr.width(wi) != n or dr.width(wo) != n:  # a broadcast side: evaluate them all
            return dr.select(valid, self._torch_f_cos(wi, wo), mi.Color3f(0.0))
        lanes = dr.compress(valid)
        if dr.width(lanes) == n:
            return self._torch_f_cos(wi, wo)
        value = self._torch_f_cos(
            dr.gather(mi.Vector3f, wi, lanes), dr.gather(mi.Vector3f, wo, lanes)
        )
        out = dr.zeros(mi.Color3f, n)
        dr.scatter(out, value, lanes)
        return out

    def traverse(self, callback):
        for k, v in self.weights.items():
            callback.put(f"raw.{k}", v, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        pass  # the tensors are read at every evaluation

    def to_string(self):
        sizes = sum(int(np.prod(v.shape)) for v in self.weights.values())
        return (
            f"NeuralBSDFAD[{self.model.hidden} {self.model.activation}, grid "
            f"{self.model.grid.size}, {sizes} weights, lobe {self.lobe['distribution']} "
            f"alpha={self.lobe['alpha']:.3g} ({self.lobe_source})]"
        )


mi.register_bsdf(PLUGIN, lambda props: NeuralBSDFAD(props))
