"""Export a trained run to one self-contained ONNX file (the contract other tools use).

    built = export.build(model, cfg)                 # the graph, checked against torch
    phys = validate.physics(built.eval, anisotropic=built.anisotropic,
                            settings=cfg.validation, target=target)   # validate measures
    export.write(built, cfg, "model.onnx", physics=phys, target=target)  # export writes

or in one call, ``export.export(model, cfg, "model.onnx", measure=validate.physics,
target=target)``.  Export writes and checks parity; the physics figures the file
records are measured by :mod:`neural_brdf.validate` on the very graph written, and the
verdict on them is validate's too.

    inputs   wi, wo   float32 [N, 3]   unit vectors in the local frame (analytic.frame)
    output   f        float32 [N, 3]   BRDF in 1/sr, RGB, without the cosine
    N is dynamic.  Encoding, horizon test and albedo normalisation are in the graph.
    The graph is total: it normalises wi and wo itself, and a row with a NaN, an
    infinity or a zero-length direction gives f = 0 (other rows are unaffected).

The ONNX model fields describe the file: ``producer_name`` "neural-brdf",
``producer_version`` the package version (neural_brdf.version), ``model_version`` the
integer ``fileformat.FORMAT_VERSION`` (bumped when this contract changes) and ``doc_string``
one paragraph: the target, the encoding and the input/output contract above.

``metadata_props`` (read with ``neural_brdf.load(path).meta``; schema in docs/portable.md):

    metadata_version (2), format_version, producer, frame, units, encoding, normalization,
    target (JSON object: kind, model, params, description; :func:`target_json`),
    max_albedo, hemispherical_albedo, reciprocity_error, min_value,
    parity_rel_error, float32_rel_precision (JSON numbers and arrays),
    training_config (the resolved config, JSON),
    sampling_lobe (JSON: the importance-sampling lobe fitted to the network,
    neural_brdf.physics.lobe_fit)

The graph torch writes is rewritten by :func:`neural_brdf.fileformat.portable.portable_graph`
so that onnxruntime from 1.18 on, onnxruntime-web, onnx2torch, the ONNX reference
evaluator and the version converter all read it (docs/portable.md);
:func:`neural_brdf.fileformat.portable.convert_opset` gives it at opsets 13 up.

The physics values are measured on the exported graph itself, through onnxruntime.
Torch and onnxruntime are checked to agree to ``export.parity_tol`` (1e-5) relative,
with values below a tenth of the mean compared in absolute terms (see PARITY_FLOOR).
A network can be worse conditioned than that: its own float32 evaluation then differs
from the same weights in float64 by more than 1e-5 (seen at 1e-5 to 2e-5 on sharp
lobes).  Two float32 evaluations, each rounding in its own order, cannot be expected to
agree better than a few times that precision, so the check allows max(parity_tol, 4 x
precision) (:data:`PRECISION_FACTOR`, :func:`parity_allowed`,
which the report's parity row uses too), and both figures go to the metadata
(``parity_rel_error``, ``float32_rel_precision``).
"""

from __future__ import annotations

import copy
import io
import json
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import onnx
import onnxruntime as ort
import torch

from analytic import physics
from neural_brdf import config as cfgmod
from neural_brdf.errors import ParityError
from neural_brdf.fileformat import (
    FORMAT_VERSION,
    FRAME,
    INPUT_WIDTHS,
    INPUTS,
    METADATA_VERSION,
    NORMAL,
    OUTPUT,
    OUTPUT_SIGNATURES,
    PRODUCER_NAME,
    SIGNATURES,
    UNITS,
    UV,
)
from neural_brdf.fileformat.metadata import Metadata, plain
from neural_brdf.fileformat.portable import portable_graph
from neural_brdf.fileio import atomic_write
from neural_brdf.physics import lobe_fit
from neural_brdf.target import Described, check_textured, spatially_varying
from neural_brdf.train import data
from neural_brdf.train.encoding import is_anisotropic
from neural_brdf.train.loop import CheckpointError, load_checkpoint  # noqa: F401  (export.load_checkpoint)
from neural_brdf.train.model import NormalizedBRDF, RawBRDF, TotalBRDF, albedo_table
from neural_brdf.train.session import TARGET_FILES, check_resumable, target_file_problems
from neural_brdf.train.textured_model import (
    FOLD_LIMIT,
    NORMALIZED,
    ScaledBRDF,
    TexturedBRDF,
    exportable,
    raw_of,
)
from neural_brdf.version import __version__

PRODUCER = f"{PRODUCER_NAME} {__version__}"  # the ``producer`` metadata entry
# Parity is relative to max(|f|, PARITY_FLOOR * mean |f|).  Below a tenth of the model's
# mean value the comparison is absolute: there the float32 network is itself no more
# accurate than ~1e-5 (softplus tails carry the absolute error of their argument).
# Measured on a smooth-Beckmann run: torch float32 vs the same network in float64
# differs by 4.7e-5 relative without the floor and 5.9e-6 with it; torch vs
# onnxruntime by 4.0e-5 and 7.7e-6.
PARITY_FLOOR = 0.1
ANALYTIC_OPSET = 17  # opset of analytic_onnx (as neural_brdf.renderers.mitsuba used)


def target_json(
    cfg: cfgmod.Config, description: str, target: Described | None = None
) -> dict[str, Any]:
    """The ``target`` metadata entry: what the model was fitted to, as an object.

    ``{"kind": "analytic", "model": NAME, "params": {...}, "resolved": {...},
    "description": TEXT}`` for an analytic target: ``params`` as the config gave them
    (``analytic.create(NAME, **params)`` builds the target again), ``resolved`` every
    parameter's value, defaults and derived values included (a conductor's material and
    its eta and k: not arguments for create); ``{"kind": "measured", "data": PATH,
    "description": TEXT}`` for measured data; ``{"kind": "mitsuba", "file": XML, "variant":
    NAME, "excess": {...} or null, "description": TEXT}`` for a Mitsuba BSDF as the teacher
    (``excess``: where and by how much its albedo exceeded 1, before it was bounded);
    ``{"kind": "images", "views": N,
    "description": TEXT}`` for an inverse-rendering fit; ``{"kind": "unspecified",
    "description": TEXT}`` when the exporter was given a description only.  ``description``
    is the text files of metadata_version 1 held (for an analytic target, the
    ``analytic.create(...)`` call)."""
    import analytic

    t = cfg.target
    if isinstance(target, analytic.BRDF):
        given = t.params if t.model == target.name and t.data is None else target.params
        return {
            "kind": "analytic",
            "model": target.name,
            "params": plain(given),
            "resolved": plain(target.params),
            "description": description,
        }
    if target is not None and t.data is not None:
        return {"kind": "measured", "data": t.data, "description": description}
    if target is not None and t.mitsuba is not None:
        return {
            "kind": "mitsuba",
            "file": t.mitsuba,
            "variant": getattr(target, "variant", t.variant),
            "excess": plain(getattr(target, "excess", None)),  # where the albedo passed 1
            "description": description,
            **({"spatially_varying": True} if spatially_varying(target) else {}),
        }
    if t.images is not None:
        return {"kind": "images", "views": len(t.images), "description": description}
    return {"kind": "unspecified", "description": description}


def doc_string(
    cfg: cfgmod.Config, target_desc: str, normalized: bool, *, textured: bool = False
) -> str:
    """The ONNX ``doc_string``: what the model is and its input/output contract."""
    norm = (
        "albedo-normalised (max albedo <= 1 by construction)"
        if normalized
        else "without albedo normalisation (an ablation)"
    )
    return (
        f"Neural BRDF ({PRODUCER_NAME} {__version__}) fitted to {target_desc}. "
        f"Encoding: {cfg.model.encoding}; MLP hidden widths {cfg.model.hidden}; "
        f"{norm}. Inputs wi, wo: float32 [N, 3] unit vectors in the local shading "
        "frame (z = normal, x = tangent), both pointing away from the surface; output "
        "f: float32 [N, 3], the RGB BRDF in 1/sr without the cosine factor, 0 when "
        "either direction is at or below the horizon. The graph normalises wi and wo "
        "itself and gives f = 0 for a row with a NaN, an infinity or a zero-length "
        "direction, without affecting other rows. N is dynamic. Metadata "
        "(metadata_props) hold the physics figures and the training config."
        + (
            " Input uv: float32 [N, 2], the texture coordinates (wrapping by repeat, "
            "bilinear filtering of the weight field; metadata 'texture'); a row with a "
            "non-finite uv gives f = 0."
            if textured
            else ""
        )
    )


def raw_from_checkpoint(ckpt: dict, cfg: cfgmod.Config) -> RawBRDF:
    """The network a run exported: an images fit with held-out views keeps the weights of
    its best held-out scoring (``validation.best``, what the run's own model.onnx holds,
    :func:`neural_brdf.inverse.fit.fit_neural`), while ``model`` holds the last step's
    (with the optimiser's state, for ``--resume``); any other run, ``model``."""
    kept = (ckpt.get("validation") or {}).get("best")
    raw = RawBRDF.from_config(cfg.model)
    raw.load_state_dict(kept if isinstance(kept, dict) else ckpt["model"])
    return raw.eval()


def normalized_model(
    raw: RawBRDF, cfg: cfgmod.Config, target: Described | None = None
) -> tuple[NormalizedBRDF | RawBRDF, dict[str, Any]]:
    """Tabulate A+ for ``raw`` and wrap it; returns (model, table info).  ``target``'s
    own sampler, if it has one, helps the quadrature.

    With ``normalization.enabled: false`` (ablations) no table is built and the raw
    network itself is the model: nothing then bounds its albedo.
    """
    n = cfg.normalization
    if not n.enabled:
        return raw.eval(), {"enabled": False}
    aniso = is_anisotropic(cfg.model.encoding)
    stats: dict[str, int] = {}
    table, a, err = albedo_table(
        raw,
        size=n.grid_size if aniso else n.table_size,
        anisotropic=aniso,
        samples=n.samples,
        seed=cfg.train.seed + 17,
        sigmas=n.sigmas,
        margin=n.margin,
        target=target,
        refine=n.refine,
        stats=stats,
    )
    info = {
        "enabled": True,
        "raw_max_albedo": float(a.max()),
        "raw_max_stderr": float(err.max()),
        "nodes": int(a.shape[0]),
        "refined_nodes": stats["refined"],
        "nodes_above_1": int((table.reshape(-1, 3) > 1).any(-1).sum()),
    }
    model = NormalizedBRDF(raw, table).eval()
    info["in_graph"] = not model.identity  # False: A+ <= 1 everywhere, the division is 1
    return model, info


def normalization_note(model: torch.nn.Module, n: cfgmod.Normalization) -> str:
    """The ``normalization`` metadata entry: the construction, or that there is none."""
    if not isinstance(model, NormalizedBRDF):
        return "none: f = raw network (normalization.enabled: false, an ablation)"
    nodes = int(model.table.shape[0])  # type: ignore[index]  # a tensor buffer
    applied = (
        "A+ <= 1 at every node, so the division is the identity and the graph omits it"
        if model.identity
        else "applied in the graph"
    )
    return (
        f"f = raw / max(1, A+(wi), A+(wo)) per channel ({applied}); "
        f"A+ = MIS quadrature albedo of "
        f"the raw network + {n.sigmas:g} standard errors, neighbour maximum, times "
        f"(1 + {n.margin:g}); table of {nodes} nodes per axis, "
        f"{n.samples} points per node"
    )


def textured_normalization_note(
    model: TexturedBRDF, n: cfgmod.Normalization, bound: str = "table"
) -> str:
    """The ``normalization`` entry of a textured file (docs/model.md, "Spatially varying
    models: the contract"); ``bound``: ``texture.lobe_bound``."""
    lobes = [lobe for lobe in model.lobes if isinstance(lobe, NORMALIZED)]
    if bound == "texel" and n.enabled:
        latent = bool(getattr(model.field, "latent", 0))
        return (
            f"f = sum_k z_k(uv) g_k, each of the {model.field.lobes} lobes g_k its raw "
            "network, and each texel's weights divided so that sum_k z_k,c A+_k,c(node) "
            "<= 1 at every node of incidence and channel c (texture.lobe_bound: texel), "
            f"A+_k the lobe's table{' at its largest over s' if latent else ''} "
            f"(MIS quadrature + {n.sigmas:g} standard errors, neighbour maximum, times "
            f"(1 + {n.margin:g})); the constraints are linear in z, so every bilinear "
            "blend of texels keeps them: the albedo is <= 1 + margin at every uv"
            + (
                "; the last two lobes are analytic GGX heads (texture.analytic_heads), "
                "A+ = 1 at every node in closed form"
                if analytic_json(model) is not None
                else ""
            )
        )
    if not lobes:
        return "none: each lobe is its raw network (normalization.enabled: false, an ablation)"
    count = model.field.lobes
    shared = f" (the {count} heads of one network)" if model.shared else ""
    latent = bool(getattr(model.field, "latent", 0))
    lat = "s, " if latent else ""
    # conditioned lobes: one column per head, the largest of its channels' (conditioned.py)
    per = "per head (the largest of its channels' bounds)" if latent else "per channel"
    table = f"A+_k its own table over {'(s, theta)' if latent else 'the direction'}"
    form = (
        f" (a table whose largest node is <= {FOLD_LIMIT:g} is folded into a constant: "
        "raw_k / max(1, max A+_k))"
        if any(isinstance(lobe, ScaledBRDF) for lobe in lobes)
        else ""
    )
    return (
        f"f = sum_k z_k(uv) g_k with z_k >= 0, sum z_k <= 1 at every uv (bilinear blends "
        f"of texels included), and each of the {count} lobes{shared} "
        f"g_k = raw_k / max(1, A+_k({lat}wi), A+_k({lat}wo)) {per}, {table} "
        f"(MIS quadrature + {n.sigmas:g} standard errors, neighbour maximum, times "
        f"(1 + {n.margin:g})){form}: the albedo is <= max_k A+_k / max(1, A+_k) <= 1 + margin"
    )


def to_onnx_bytes(
    model: torch.nn.Module,
    opset: int,
    *,
    portable: bool = True,
    inputs: tuple[str, ...] = INPUTS,
    outputs: tuple[str, ...] = (OUTPUT,),
    widths: dict[str, int] | None = None,
) -> bytes:
    """``model`` (forward(wi, wo) -> f, or forward(wi, wo, uv) -> f with ``inputs`` =
    ``fileformat.SIGNATURES[1]``: a textured model; -> (f, n) with ``outputs`` =
    ``fileformat.OUTPUT_SIGNATURES[1]``: one with its normal field) as ONNX bytes:
    torch's legacy exporter, then :func:`portable_graph` (``portable=False``: torch's
    graph as it is, for comparison).  Each input is float32 [N, its width], N dynamic;
    the widths are the file format's (``INPUT_WIDTHS``) unless ``widths`` names them."""
    buf = io.BytesIO()
    width = {**INPUT_WIDTHS, **(widths or {})}
    example = tuple(torch.zeros(4, width[name]) for name in inputs)
    with warnings.catch_warnings():
        # The TorchScript exporter (dynamo=False) warns that it is deprecated.  It is
        # used on purpose: it writes one self-contained file and needs no onnxscript,
        # which is not a dependency of this project (docs/model.md, "Export and parity").
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        torch.onnx.export(
            model,
            example,
            buf,  # type: ignore[arg-type]  # a file object is accepted
            dynamo=False,
            opset_version=opset,
            input_names=list(inputs),
            output_names=list(outputs),
            dynamic_axes={name: {0: "N"} for name in (*inputs, *outputs)},
        )
    if not portable:
        return buf.getvalue()
    return portable_graph(onnx.load_from_string(buf.getvalue())).SerializeToString()


def parity_pairs(n: int, seed: int) -> torch.Tensor:
    """Random pairs: half above the horizon (10% near grazing), half anywhere on the sphere."""
    rng = np.random.default_rng(seed)
    up = np.concatenate(
        [physics.random_directions(n // 2, seed), physics.random_directions(n // 2, seed + 1)], -1
    )
    anywhere = rng.normal(size=(n - n // 2, 6))
    anywhere[:, :3] /= np.linalg.norm(anywhere[:, :3], axis=-1, keepdims=True)
    anywhere[:, 3:] /= np.linalg.norm(anywhere[:, 3:], axis=-1, keepdims=True)
    return torch.from_numpy(np.concatenate([up, anywhere], 0)).float()


def parity_error(
    model: torch.nn.Module,
    session: ort.InferenceSession,
    n: int,
    seed: int,
    *,
    textured: bool = False,
) -> tuple[float, float, float]:
    """(onnxruntime vs torch, torch float32 vs the same network in float64, onnxruntime
    vs float64), relative.  ``textured``: the model takes uv too, drawn uniformly in
    [-1, 2)^2 (wrapping included) with every pair; a model that also returns its normal
    field n (two outputs) is compared on f and n together (each relative to its own
    scale, the larger difference counts)."""
    pairs = parity_pairs(n, seed)
    wi, wo = pairs[:, :3].contiguous(), pairs[:, 3:].contiguous()
    args: tuple[torch.Tensor, ...] = (wi, wo)
    if textured:
        uv = np.random.default_rng(seed + 1).uniform(-1.0, 2.0, (len(wi), 2))
        args = (wi, wo, torch.from_numpy(uv).float())
    with torch.no_grad():
        refs = _outputs(model(*args))
        exacts = _outputs(copy.deepcopy(model).double()(*(a.double() for a in args)))
    feeds = dict(zip(SIGNATURES[1], (a.numpy() for a in args)))
    names = [OUTPUT, NORMAL][: len(refs)]
    gots = [g.astype(np.float64) for g in session.run(names, feeds)]
    return (
        max(relative_difference(g, r) for g, r in zip(gots, refs)),
        max(relative_difference(r, e) for r, e in zip(refs, exacts)),
        max(relative_difference(g, e) for g, e in zip(gots, exacts)),
    )


def _outputs(out: Any) -> list[np.ndarray]:
    """A model's output(s) as float64 arrays: [f] or [f, n]."""
    outs = out if isinstance(out, tuple) else (out,)
    return [o.numpy().astype(np.float64) for o in outs]


def relative_difference(got: np.ndarray, ref: np.ndarray) -> float:
    """max |got - ref| / max(|ref|, PARITY_FLOOR * mean of the nonzero |ref|)."""
    nonzero = np.abs(ref[ref != 0])
    floor = PARITY_FLOOR * nonzero.mean() if nonzero.size else 1.0
    return float(np.max(np.abs(got - ref) / np.maximum(np.abs(ref), floor)))


# how far two float32 evaluations of one network may be apart, in units of torch's own
# float32 error (its largest over the parity pairs): each rounds in its own order, and the
# largest of some thousands of rounding errors is not the same for both.  2 was too tight:
# a textured Al roughconductor under a normal map (seed 0) had torch 7.66e-6 from float64,
# onnxruntime 1.76e-5, at a pair 0.5 degrees above the horizon, and its export failed.  An
# export defect (a wrong op, a missing clamp) is orders of magnitude beyond this.
PRECISION_FACTOR = 4.0


def parity_allowed(parity_tol: float, precision: float) -> float:
    """The largest torch-vs-onnxruntime difference an export accepts: ``parity_tol``
    (``export.parity_tol``), or :data:`PRECISION_FACTOR` times the network's own float32
    ``precision`` where that is larger (module doc).  The report's parity row judges by
    it too."""
    return max(parity_tol, PRECISION_FACTOR * precision)


@dataclass(frozen=True)
class Built:
    """A model's graph as :func:`write` writes it (the ONNX bytes, no metadata yet), an
    onnxruntime session of it, and how closely it agrees with torch (:func:`build`)."""

    model: NormalizedBRDF | RawBRDF | TexturedBRDF
    payload: bytes
    session: ort.InferenceSession
    parity_rel_error: float
    float32_rel_precision: float

    @property
    def anisotropic(self) -> bool:
        return bool(self.model.anisotropic)

    @property
    def textured(self) -> bool:
        """A graph of (wi, wo, uv): :func:`build_textured`'s."""
        return isinstance(self.model, TexturedBRDF)

    def eval(self, wi: Any, wo: Any, uv: Any = None) -> np.ndarray:
        """f of the graph through onnxruntime: (N, 3) arrays in (and uv (N, 2) for a
        textured graph), (N, 3) float32 out."""
        feeds = {name: np.asarray(x, np.float32) for name, x in zip(INPUTS, (wi, wo))}
        if self.textured:
            feeds[UV] = np.ascontiguousarray(np.asarray(uv, np.float32))
        return self.session.run([OUTPUT], feeds)[0]

    @property
    def has_normal(self) -> bool:
        """A textured graph that carries its teacher's normal field (output ``n``)."""
        return isinstance(self.model, TexturedBRDF) and self.model.normal is not None

    def normal(self, uv: Any) -> np.ndarray:
        """The graph's normal field n(uv) (N, 3) through onnxruntime (needs
        :attr:`has_normal`)."""
        uv = np.ascontiguousarray(np.asarray(uv, np.float32))
        zeros = np.zeros((len(uv), 3), np.float32)
        return self.session.run([NORMAL], {INPUTS[0]: zeros, INPUTS[1]: zeros, UV: uv})[0]


class Measure(Protocol):
    """What measures a graph's physics for its metadata: :func:`neural_brdf.validate.physics`."""

    def __call__(
        self,
        fn: Callable[[Any, Any], np.ndarray],
        *,
        anisotropic: bool,
        settings: cfgmod.Validation,
        target: Described | None = None,
    ) -> dict[str, Any]: ...


def build(model: NormalizedBRDF | RawBRDF, cfg: cfgmod.Config) -> Built:
    """``TotalBRDF(model)`` as ONNX, checked against torch (ParityError when they differ
    by more than :func:`parity_allowed`; nothing is written).

    The graph normalises its inputs and gives 0 for rows with a non-finite or zero-length
    direction, so no input row can crash a host or change another row (see
    :class:`neural_brdf.train.model.TotalBRDF`).
    """
    graph = TotalBRDF(model)
    return _checked(model, graph, to_onnx_bytes(graph, cfg.export.opset), cfg)


def _checked(
    model: NormalizedBRDF | RawBRDF | TexturedBRDF,
    graph: torch.nn.Module,
    payload: bytes,
    cfg: cfgmod.Config,
    *,
    textured: bool = False,
) -> Built:
    """``payload`` (the ONNX of ``graph``) in an onnxruntime session, checked against torch
    by :func:`parity_error` (``textured``: at random uv too); ParityError when they differ
    by more than :func:`parity_allowed`."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    session = ort.InferenceSession(payload, opts, providers=["CPUExecutionProvider"])
    args = (graph, session, cfg.export.parity_pairs, cfg.train.seed + 29)
    if textured:
        parity, precision, ort_exact = parity_error(*args, textured=True)
    else:
        parity, precision, ort_exact = parity_error(*args)
    allowed = parity_allowed(cfg.export.parity_tol, precision)
    # torch and onnxruntime each round in float32, in their own order: where both errors
    # are near torch's largest (a grazing pair on a steep grid cell) their difference can
    # reach twice it, so onnxruntime also passes when it is as close to the exact float64
    # network as allowed (compact/bank: 7.3e-5 apart, 4.0e-5 from float64, allowed 7.2e-5)
    if not (parity <= allowed or ort_exact <= allowed):
        raise ParityError(
            f"torch and onnxruntime differ by {parity:.3g} relative (allowed "
            f"{allowed:.3g}: export.parity_tol, or {PRECISION_FACTOR:g} x the float32 precision "
            f"of the network, {precision:.3g}); nothing written"
        )
    return Built(model, payload, session, parity, precision)


def build_textured(model: TexturedBRDF, cfg: cfgmod.Config) -> Built:
    """A textured model (:mod:`neural_brdf.train.textured_model`, lobes normalised by
    ``normalized_textured``) as the graph of (wi, wo, uv): ``exportable(model)`` (the
    weight field frozen, total over every row), checked against torch at random uv as
    :func:`build` checks a homogeneous one."""
    graph = exportable(model)
    outputs = OUTPUT_SIGNATURES[1] if model.normal is not None else OUTPUT_SIGNATURES[0]
    payload = to_onnx_bytes(graph, cfg.export.opset, inputs=SIGNATURES[1], outputs=outputs)
    return _checked(model, graph, payload, cfg, textured=True)


def with_normal_field(model: TexturedBRDF, target: Any) -> TexturedBRDF:
    """``model`` carrying ``target``'s normal field (a textured Mitsuba teacher's normal or
    bump map, ``TexturedMitsubaTarget.normal_texels``) when it has one: the file then has
    the second output n (docs/model.md, "The normal field")."""
    from neural_brdf.train.textured_model import NormalField

    texels = target.normal_texels() if hasattr(target, "normal_texels") else None
    if texels is None:
        return model
    flags = dict(target.normal_map or {})
    model.normal = NormalField(
        texels,
        source=str(flags.get("plugin", "normalmap")),
        flip_invalid_normals=bool(flags.get("flip_invalid_normals", True)),
        use_shadowing_function=bool(flags.get("use_shadowing_function", True)),
    )
    return model


def _weights_text(field: Any) -> str:
    """What bounds the field's weights, as the file holds them: sum <= 1 (a softmax with
    an empty slot, or a projected field of normalised lobes) or, for a projected field of
    raw lobes (texture.project with lobe_bound texel), the lobes' envelope alone
    (docs/model.md)."""
    with torch.no_grad():
        k, c = int(field.lobes), int(getattr(field, "channels", 1))
        z = field.weights()[:, : c * k].reshape(-1, c, k)
        if float(z.sum(-1).max()) <= 1.0 + 1e-6:
            return "z_k >= 0, sum_k z_k <= 1 at every uv"
    return (
        "z_k >= 0 and, per texel and channel, sum_k z_k A+_k <= 1 at every node of "
        "incidence (the lobes' albedo bounds; bilinear blends keep it)"
    )


def texture_json(model: TexturedBRDF, info: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The ``texture`` metadata entry of a textured file: what its uv input means
    (docs/portable.md, "Textured files")."""
    field = model.field
    return {
        "inputs": list(SIGNATURES[1]),
        "model": "sum_k z_k(uv) g_k(wi, wo): K shared lobes, a field of K weights",
        "lobes": int(field.lobes),
        "resolution": [int(field.resolution), int(field.resolution)],
        "wrap": "repeat",
        "filter": "bilinear",
        "texel_centres": "((i + 0.5) / R, (j + 0.5) / R), i along u, j along v",
        "layout": "row-major [v, u]: flat index j * R + i; column c * K + k, the latent at C * K",
        "weights": _weights_text(field),
        "channels": int(getattr(field, "channels", 1)),  # 3: a set of weights per RGB channel
        # 1: one more column of the table, s(uv) in [0, 1], an input of every lobe
        # (conditioned lobes, docs/model.md), its albedo table over (s, theta)
        "latent": int(getattr(field, "latent", 0)),
        # grey: each lobe has one output, repeated to RGB (texture.lobe_color); rgb: three
        "lobe_color": "grey" if _grey_lobes(model) else "rgb",
        # analytic GGX heads: the last two of the lobes, alpha the table's last column
        "analytic_heads": analytic_json(model),
        "normal_field": normal_json(model),
        "lobe_tables": plain(info) if info is not None else None,
    }


def analytic_json(model: TexturedBRDF) -> dict[str, Any] | None:
    """The ``texture.analytic_heads`` entry: None, or what the analytic heads are
    (train/ggx_heads.py, docs/model.md "Analytic GGX heads")."""
    from neural_brdf.train.ggx_heads import ALPHA_MIN, HEADS, analytic_count

    if not any(analytic_count(g) for g in model.lobes):
        return None
    k = int(model.field.lobes)
    return {
        "kind": "ggx",
        "lobes": [k - HEADS, k - 1],
        "alpha": f"{ALPHA_MIN:g} + {1 - ALPHA_MIN:g} t, t the table's last column",
        "heads": [
            "D(h) G1(wi) G1(wo) / (4 cos_i cos_o): GGX, Smith's separable masking, F = 1",
            "the same times (1 - cos_d)^5 (Schlick's grazing factor)",
        ],
        "albedo": "each head's <= 1 for every alpha (closed form); in the texels' bound the "
        "first's envelope is 1, the second's measured per node of incidence",
    }


def _grey_lobes(model: TexturedBRDF) -> bool:
    """Whether the lobes' networks have one grey output per lobe (RawBRDF.colors 1)."""
    return all(int(getattr(raw_of(g), "colors", 3)) == 1 for g in model.lobes)


def normal_json(model: TexturedBRDF) -> dict[str, Any] | None:
    """The ``texture.normal_field`` entry: None, or how the output ``n`` is made and how a
    renderer applies it (docs/portable.md, "Textured files")."""
    nf = model.normal
    if nf is None:
        return None
    ru, rv = nf.resolution
    return {
        "output": NORMAL,
        "source": nf.source,
        "resolution": [ru, rv],
        "wrap": "repeat",
        "filter": "bilinear, then normalised",
        "texel_centres": "((i + 0.5) / Ru, (j + 0.5) / Rv), i along u, j along v",
        "frame": "n in the unperturbed shading frame; the rotated frame is n, "
        "s = normalize(x - n n_x), t = n x s (Mitsuba 3's normalmap); f is evaluated "
        "with wi, wo in it",
        "flip_invalid_normals": nf.flip_invalid_normals,
        "use_shadowing_function": nf.use_shadowing_function,
    }


def write(
    built: Built,
    cfg: cfgmod.Config,
    out: str | Path,
    *,
    physics: dict[str, Any],
    target: Described | None = None,
    target_desc: str | None = None,
    texture_info: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Write ``built`` to ``out`` with its metadata; returns the parity figures and the
    path.  A textured graph (:func:`build_textured`) gets the ``texture`` entry
    (:func:`texture_json`, ``texture_info``: each lobe's table figures).

    ``physics``: :func:`neural_brdf.validate.physics` of ``built.eval`` (the file records
    its figures); ``target``: what the model was fitted to, described by ``target_desc``
    (default ``target.describe()``; an images fit has no target, only a description).
    """
    if target_desc is None:
        if target is None:
            raise TypeError("write: give target or target_desc (what the model was fitted to)")
        target_desc = target.describe()
    checks = physics["checks"]
    meta = Metadata(
        metadata_version=METADATA_VERSION,
        format_version=FORMAT_VERSION,
        producer=PRODUCER,
        frame=FRAME,
        units=UNITS,
        encoding=cfg.model.encoding,
        normalization=(
            textured_normalization_note(built.model, cfg.normalization, cfg.texture.lobe_bound)
            if isinstance(built.model, TexturedBRDF)
            else normalization_note(built.model, cfg.normalization)
        ),
        target=target_json(cfg, target_desc, target),
        max_albedo=checks["max_albedo"]["value"],
        hemispherical_albedo=plain(physics["hemispherical_albedo"]),
        reciprocity_error=checks["reciprocity"]["value"],
        min_value=checks["min_value"]["value"],
        parity_rel_error=built.parity_rel_error,
        float32_rel_precision=built.float32_rel_precision,
        training_config=cfg.model_dump(mode="json"),
        # renderers' importance sampling (a textured graph: one lobe for the surface)
        sampling_lobe=lobe_fit.fit_onnx(built.payload)
        if built.textured
        else lobe_fit.fit(built.eval),
        texture=texture_json(built.model, texture_info)
        if isinstance(built.model, TexturedBRDF)
        else None,
    ).to_props()
    proto = onnx.load_from_string(built.payload)
    onnx.helper.set_model_props(proto, meta)
    proto.producer_name = PRODUCER_NAME
    proto.producer_version = __version__
    proto.model_version = FORMAT_VERSION  # the file format, an integer
    proto.doc_string = doc_string(
        cfg,
        target_desc,
        isinstance(built.model, (NormalizedBRDF, TexturedBRDF)),
        textured=built.textured,
    )
    onnx.checker.check_model(proto)
    atomic_write(Path(out), proto.SerializeToString(), parents=True)
    return {
        "parity_rel_error": built.parity_rel_error,
        "float32_rel_precision": built.float32_rel_precision,
        "path": str(out),
    }


def export(
    model: NormalizedBRDF | RawBRDF,
    cfg: cfgmod.Config,
    out: str | Path,
    *,
    measure: Measure,
    target: Described | None = None,
    target_desc: str | None = None,
) -> dict[str, Any]:
    """:func:`build`, ``measure`` the graph (pass :func:`neural_brdf.validate.physics`),
    :func:`write`: ``model`` to ``out``.  Returns the parity figures, the path and
    ``physics``, what ``measure`` returned (its verdict is validate's:
    ``validate.physics_passed``)."""
    built = build(model, cfg)
    phys = measure(
        built.eval, anisotropic=built.anisotropic, settings=cfg.validation, target=target
    )
    info = write(built, cfg, out, physics=phys, target=target, target_desc=target_desc)
    return {**info, "physics": phys}


def textured_from_checkpoint(ckpt: dict, cfg: cfgmod.Config) -> TexturedBRDF:
    """The raw textured model of a textured run's checkpoint (``train.textured_loop``)."""
    from neural_brdf.train.ggx_heads import HEADS, with_heads
    from neural_brdf.train.textured_loop import lobe_networks
    from neural_brdf.train.textured_model import WeightField

    tx = cfg.texture
    # the checkpoint's own layout decides (a run of separate lobes has lobes.1.*)
    state = ckpt["model"]
    separate = any(k.startswith("lobes.1.") for k in state)
    # analytic heads wrap the shared network (its weights under lobes.0.net.*)
    analytic = "ggx" if "lobes.0.net.mlp.head.weight" in state else "none"
    extra = HEADS if analytic != "none" else 0
    shared = not separate and (tx.lobes > 1 or bool(extra))
    # and its lobes' colour: a grey lobe's last layer has one row per head, not three
    head = state["lobes.0.net.mlp.head.weight" if extra else "lobes.0.mlp.head.weight"]
    colors = int(head.shape[0]) // (tx.lobes if shared else 1)
    # and so does its latent (conditioned lobes have field.latent_logits; alpha's column
    # follows the lobes' latent with analytic heads)
    columns = int(state["field.latent_logits"].shape[1]) if "field.latent_logits" in state else 0
    latent = columns - bool(extra)
    # and its field's levels (field.coarse.<l - 1> for each coarser level)
    levels = 1 + len({k.split(".")[2] for k in state if k.startswith("field.coarse.")})
    nets = lobe_networks(cfg.model, tx.lobes, shared, latent=latent, colors=colors)
    model = TexturedBRDF(
        [with_heads(nets[0], analytic)] if extra else nets,
        WeightField(
            tx.resolution,
            tx.lobes + extra,
            channels=3 if tx.weights == "rgb" else 1,
            latent=columns,
            levels=levels,
        ),
    )
    model.load_state_dict(ckpt["model"])
    return model.eval()


def textured_for_export(
    model: Any, cfg: cfgmod.Config, target: Any
) -> tuple[Any, list[dict[str, Any]], dict[str, Any] | None]:
    """A trained textured model as the file holds it: its lobes normalised
    (``normalized_textured`` under ``cfg``) and, with ``texture.project``, its field
    replaced by one fitted texel by texel to ``target`` on those lobes
    (:func:`neural_brdf.train.textured_project.project_field`, seeded by
    ``train.seed``, bounded by the lobes' envelope) and, with ``texture.refit_steps``,
    its lobes trained on against that field (``refit_lobes``) and normalised again.
    Returns (model, the lobes' table figures, the projection's figures, the refit's
    under ``refit``, or None).  The run and ``export RUN`` both call
    it, so a re-export gives the run's file."""
    from neural_brdf.train.textured_model import normalized_textured

    model, tables = normalized_textured(
        model, cfg.normalization, seed=cfg.train.seed, bound=cfg.texture.lobe_bound
    )
    tx = cfg.texture
    if tx.project is None:
        return model, tables, None
    from neural_brdf.train.textured_project import project_and_refit

    model, refit_tables, info = project_and_refit(
        model,
        target,
        lambda m: normalized_textured(
            m, cfg.normalization, seed=cfg.train.seed, bound=tx.lobe_bound
        ),
        resolution=tx.project,
        pairs=tx.project_pairs,
        latents=tx.project_latents,
        ridge=tx.project_ridge,
        refit_steps=tx.refit_steps,
        refit_lr=tx.refit_lr,
        batch=cfg.data.batch_size,
        pool=tx.pool(cfg.data.pool_size),
        seed=cfg.train.seed,
        peak=cfg.data.peak,
        alphas=tx.project_alphas,
        alpha_source=tx.project_alpha,
    )
    return model, refit_tables if refit_tables is not None else tables, info


def _export_textured(
    ckpt: dict,
    cfg: cfgmod.Config,
    run_dir: Path,
    out: str | Path | None,
    measure: Callable[..., dict[str, Any]] | None,
    target: Any,
) -> dict[str, Any]:
    """:func:`export_run` of a textured run: its lobes normalised, the (wi, wo, uv)
    graph built, ``measure`` (``validate.physics_textured``) on it, written."""
    if measure is None:
        raise TypeError("export_run: a textured run needs measure_textured")
    trained = textured_from_checkpoint(ckpt, cfg)
    kept: tuple[Any, list[dict[str, Any]], dict[str, Any]] | None = None
    if cfg.texture.project is not None:  # the run's own projection, when it kept it
        from neural_brdf import runfolder
        from neural_brdf.train import textured_store
        from neural_brdf.train.textured_model import normalized_textured

        kept, why = textured_store.load(
            run_dir / runfolder.TEXTURED,
            cfg,
            ckpt["model"],
            # a model of its own: the state loaded into it must not reach ``trained``,
            # whose raw lobes normalized_textured shares, in case it is projected again
            lambda: normalized_textured(
                textured_from_checkpoint(ckpt, cfg),
                cfg.normalization,
                seed=cfg.train.seed,
                bound=cfg.texture.lobe_bound,
            )[0],
        )
        if kept is None:
            print(f"{run_dir}: projecting the field again: {why}", file=sys.stderr)
    model, tables, projection = (
        kept if kept is not None else textured_for_export(trained, cfg, target)
    )
    if projection is not None:
        projection = {**projection, "kept_by_the_run": kept is not None}
    built = build_textured(with_normal_field(model, target), cfg)
    phys = measure(
        built.eval,
        anisotropic=built.anisotropic,
        settings=cfg.validation,
        uv_count=cfg.texture.validation_uv,
    )
    path = Path(out) if out is not None else run_dir / "model.onnx"
    info = write(built, cfg, path, physics=phys, target=target, texture_info=tables)
    info["physics"] = phys
    info["normalization"] = tables
    if projection is not None:
        info["projection"] = projection
    info["target"] = target_json(cfg, target.describe(), target)
    return info


# What ``export RUN`` reads from config.yaml that the checkpoint's weights were trained
# with: the network (model, key by key), and a textured run's field and lobes (texture)
EXPORT_MUST_MATCH = tuple(f"model.{k}" for k in cfgmod.Model.model_fields)
TEXTURED_EXPORT_MUST_MATCH = tuple(
    f"texture.{k}"
    for k in (
        "lobes",
        "resolution",
        "weights",
        "lobe_network",
        "latent",
        "lobe_color",
        "lobe_bound",
        "analytic_heads",
        "field_levels",
    )
)


def export_run(
    run_dir: str | Path,
    out: str | Path | None = None,
    *,
    measure: Measure,
    measure_textured: Callable[..., dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """``neural-brdf export RUN_DIR [-o OUT]``: checkpoint -> normalised model -> ONNX
    (:func:`export`, ``measure``: :func:`neural_brdf.validate.physics`; a textured
    run's: ``measure_textured``, :func:`neural_brdf.validate.physics_textured`).  Returns
    :func:`export`'s figures, ``normalization`` and ``target`` (the metadata's entry:
    ``kind`` "images" and ``views`` for an images fit, which has no reference)."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.is_file():
        raise CheckpointError(f"{run_dir}: not a run directory (no config.yaml)")
    cfg = cfgmod.load(cfg_path, run=True)
    ckpt = load_checkpoint(run_dir / "ckpt.pt")
    # an images fit has no target to build (not the default target.model, a Lambertian):
    # the metadata says {"kind": "images", "views": N} and physics is measured alone
    images = cfg.target.images is not None
    textured = ckpt.get("kind") == "textured"
    if not images and isinstance(ckpt.get("config"), dict):
        # the network the weights were trained as: an edited config.yaml would load them
        # into another network (a traceback) or compute another function (no word)
        check_resumable(
            ckpt["config"],
            cfg,
            EXPORT_MUST_MATCH + (TEXTURED_EXPORT_MUST_MATCH if textured else ()),
            what=f"the checkpoint that {cfg_path} goes with",
        )
    target = None if images else data.build_target(cfg.target)
    check_textured(target, textured=textured, where=str(run_dir / "ckpt.pt"))
    # the export goes ahead: the weights stand whatever became of the target's files
    # since, but the accuracy below is measured against the files as they are now,
    # which a changed one makes another target's: said, not refused
    for problem in [] if images else target_file_problems(ckpt.get(TARGET_FILES), cfg):
        print(
            f"warning: {problem}: the accuracy of this export is against the file as it "
            "is now, not the one the run trained on",
            file=sys.stderr,
        )
    if textured:
        return _export_textured(ckpt, cfg, run_dir, out, measure_textured, target)
    raw = raw_from_checkpoint(ckpt, cfg)
    model, table_info = normalized_model(raw, cfg, target)
    out = Path(out) if out is not None else run_dir / "model.onnx"
    desc = _images_description(cfg, run_dir) if images else None
    info = export(model, cfg, out, measure=measure, target=target, target_desc=desc)
    info["normalization"] = table_info
    said = desc if target is None else target.describe()
    info["target"] = target_json(cfg, said or "", target)
    return info


def _images_description(cfg: cfgmod.Config, run_dir: Path) -> str:
    """What an images fit was fitted to: the run's own words (metrics.json's
    ``training.target``, as the fit wrote them) or, without them, the views' images."""
    try:
        said = json.loads((run_dir / "metrics.json").read_text())["training"]["target"]
    except (OSError, ValueError, KeyError, TypeError):
        said = None
    if isinstance(said, str) and said:
        return said
    views = cfg.target.images or []
    names = ", ".join(v.label() for v in views)
    return f"{len(views)} images ({names}) by inverse rendering"


def analytic_onnx(model: str, params: dict | None = None) -> bytes:
    """An :mod:`analytic` model's own torch ``f(wi, wo)`` exported to ONNX bytes, with the
    contract of this module (inputs wi, wo [N, 3], output f [N, 3], no cosine) but no
    metadata: a reference for generated code and the viewer (no Mitsuba needed)."""
    import analytic

    brdf = analytic.create(model, **(params or {}))

    class _F(torch.nn.Module):
        def forward(self, wi, wo):
            return brdf.f(wi, wo).float()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # also the tracer's warnings on Python values
        return to_onnx_bytes(_F(), ANALYTIC_OPSET)
