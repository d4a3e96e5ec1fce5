"""Export a trained run to one self-contained ONNX file (the contract other tools use).

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
    neural_brdf.physics.lobe)

The graph torch writes is rewritten by :func:`portable_graph` so that onnxruntime from
1.18 on, onnxruntime-web, onnx2torch, the ONNX reference evaluator and the version
converter all read it (docs/portable.md); :func:`convert_opset` gives it at opsets 13 up.

The physics values are measured on the exported graph itself, through onnxruntime.
Torch and onnxruntime are checked to agree to ``export.parity_tol`` (1e-5) relative,
with values below a tenth of the mean compared in absolute terms (see PARITY_FLOOR).
A network can be worse conditioned than that: its own float32 evaluation then differs
from the same weights in float64 by more than 1e-5 (seen at 1e-5 to 2e-5 on sharp
lobes).  Two float32 evaluations cannot be expected to agree better than twice that
precision, so the check allows max(parity_tol, 2 x precision), and both figures go to
the metadata (``parity_rel_error``, ``float32_rel_precision``).
"""

from __future__ import annotations

import copy
import io
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper

from analytic import physics
from neural_brdf import config as cfgmod
from neural_brdf import validate
from neural_brdf.errors import ParityError
from neural_brdf.fileformat import (
    FORMAT_VERSION,
    FRAME,
    INPUTS,
    METADATA_VERSION,
    OUTPUT,
    PRODUCER_NAME,
    UNITS,
)
from neural_brdf.fileformat.metadata import Metadata, plain
from neural_brdf.fileio import atomic_write
from neural_brdf.physics import lobe
from neural_brdf.train import data
from neural_brdf.train.encoding import is_anisotropic
from neural_brdf.train.loop import CheckpointError, load_checkpoint  # noqa: F401  (export.load_checkpoint)
from neural_brdf.train.model import NormalizedBRDF, RawBRDF, TotalBRDF, albedo_table
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


def target_json(cfg: cfgmod.Config, description: str, target: Any = None) -> dict[str, Any]:
    """The ``target`` metadata entry: what the model was fitted to, as an object.

    ``{"kind": "analytic", "model": NAME, "params": {...}, "resolved": {...},
    "description": TEXT}`` for an analytic target: ``params`` as the config gave them
    (``analytic.create(NAME, **params)`` builds the target again), ``resolved`` every
    parameter's value, defaults and derived values included (a conductor's material and
    its eta and k: not arguments for create); ``{"kind": "measured", "data": PATH,
    "description": TEXT}`` for measured data; ``{"kind": "images", "views": N,
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
    if t.images is not None:
        return {"kind": "images", "views": len(t.images), "description": description}
    return {"kind": "unspecified", "description": description}


def doc_string(cfg: cfgmod.Config, target_desc: str, normalized: bool) -> str:
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
    )


def raw_from_checkpoint(ckpt: dict, cfg: cfgmod.Config) -> RawBRDF:
    raw = RawBRDF.from_config(cfg.model)
    raw.load_state_dict(ckpt["model"])
    return raw.eval()


def normalized_model(
    raw: RawBRDF, cfg: cfgmod.Config, target: Any = None
) -> tuple[NormalizedBRDF | RawBRDF, dict[str, Any]]:
    """Tabulate A+ for ``raw`` and wrap it; returns (model, table info).

    With ``normalization.enabled: false`` (ablations) no table is built and the raw
    network itself is the model: nothing then bounds its albedo.
    """
    n = cfg.normalization
    if not n.enabled:
        return raw.eval(), {"enabled": False}
    aniso = is_anisotropic(cfg.model.encoding)
    table, a, err = albedo_table(
        raw,
        size=n.grid_size if aniso else n.table_size,
        anisotropic=aniso,
        samples=n.samples,
        seed=cfg.train.seed + 17,
        sigmas=n.sigmas,
        margin=n.margin,
        extra=target,
    )
    info = {
        "enabled": True,
        "raw_max_albedo": float(a.max()),
        "raw_max_stderr": float(err.max()),
        "nodes": int(a.shape[0]),
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


# ------------------------------------------------------------------ a portable graph
# The graph torch writes is rewritten so that every consumer reads it: onnxruntime from the
# oldest release pyproject allows (1.18) to the newest, onnxruntime-web, onnx2torch, the
# ONNX reference evaluator, onnx's version converter (opset 13 and up) and
# neural_brdf.graph (the C/GLSL/WGSL and Dr.Jit back ends).  docs/portable.md lists what
# each rewrite fixed; every one computes the same float32 operations as before.
PORTABLE_PREFIX = "portable/"  # names of the nodes and constants the rewrites add
REDUCE_UNROLL = 8  # ReduceSum over a static axis of at most this many entries is unrolled


def portable_graph(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Rewrite ``proto`` (in place, and returned) into the portable form:

    * ``ReduceSum`` over a short static axis becomes the sum of its entries, left to
      right (Gather + Add): onnxruntime before 1.32 returns a [0, 3] tensor for the sum
      over the last axis of a [0, 3] one, and the next Div then fails on a batch of 0
      rows.  neural_brdf.graph lowers ReduceSum to the same left-to-right sum, so
      generated code does not change.
    * ``Clip`` with an omitted bound (torch's clamp_min / clamp_max write the empty
      input name "") becomes ``Max(x, min)`` / ``Min(x, max)``: onnx2torch takes a
      Clip's bounds as constants and refuses the empty name.
    * ``ConstantOfShape(Shape(x))`` (torch's zeros_like / ones_like) feeding a ``Where``
      that also takes ``x`` becomes a scalar constant, which Where broadcasts to the same
      shape: onnx's version converter has no adapter for Shape below opset 15.

    Nodes and initializers that nothing uses any more are dropped.  The graph's inputs,
    outputs and metadata are untouched."""
    g = proto.graph
    inferred = onnx.shape_inference.infer_shapes(proto)
    shapes = {
        v.name: [
            d.dim_value if d.HasField("dim_value") else None for d in v.type.tensor_type.shape.dim
        ]
        for v in list(inferred.graph.value_info) + list(inferred.graph.input)
        if v.type.tensor_type.HasField("shape")
    }
    consts = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    for n in g.node:
        if n.op_type == "Constant" and n.attribute and n.attribute[0].name == "value":
            consts[n.output[0]] = numpy_helper.to_array(n.attribute[0].t)
    producer = {o: n for n in g.node for o in n.output}
    added: list[onnx.TensorProto] = []

    def const(value, dtype) -> str:
        name = f"{PORTABLE_PREFIX}c{len(added)}"
        added.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    nodes = []
    for n in g.node:
        nodes.extend(_portable_node(n, shapes, consts, producer, const))
    del g.node[:]
    g.node.extend(nodes)
    g.initializer.extend(added)
    _drop_unused(g)
    return proto


def _portable_node(n, shapes, consts, producer, const) -> list:
    """The node(s) that replace ``n`` in :func:`portable_graph` (``[n]`` when none do)."""
    make = onnx.helper.make_node
    name = n.name or n.output[0]
    if n.op_type == "Clip" and not n.attribute and (len(n.input) < 3 or not all(n.input[1:3])):
        bounds = [(op, n.input[i]) for op, i in (("Max", 1), ("Min", 2)) if len(n.input) > i]
        bounds = [(op, b) for op, b in bounds if b]
        if not bounds:
            return [make("Identity", [n.input[0]], list(n.output), name=name)]
        out, x = [], n.input[0]
        for k, (op, b) in enumerate(bounds):
            y = n.output[0] if k == len(bounds) - 1 else f"{PORTABLE_PREFIX}{name}/{op}"
            out.append(make(op, [x, b], [y], name=f"{name}/{op}"))
            x = y
        return out
    if n.op_type == "ReduceSum":
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
        axes = consts.get(n.input[1]) if len(n.input) > 1 and n.input[1] else None
        if axes is None and attrs.get("axes") is not None:  # opset < 13: an attribute
            axes = np.asarray(attrs["axes"])
        shape = shapes.get(n.input[0])
        if axes is None or axes.size != 1 or shape is None or attrs.get("noop_with_empty_axes"):
            return [n]
        axis = int(axes.reshape(-1)[0]) % len(shape)
        size = shape[axis]
        if size is None or not 1 <= size <= REDUCE_UNROLL:
            return [n]
        keep = bool(attrs.get("keepdims", 1))
        out, acc = [], None
        for k in range(size):
            idx = const([k] if keep else k, np.int64)
            part = f"{PORTABLE_PREFIX}{name}/{k}"
            out.append(
                make("Gather", [n.input[0], idx], [part], name=f"{name}/Gather{k}", axis=axis)
            )
            if acc is not None:
                y = n.output[0] if k == size - 1 else f"{PORTABLE_PREFIX}{name}/sum{k}"
                out.append(make("Add", [acc, part], [y], name=f"{name}/Add{k}"))
                part = y
            acc = part
        if size == 1:
            out.append(make("Identity", [str(acc)], [n.output[0]], name=f"{name}/Identity"))
        return out
    if n.op_type == "Where":
        inputs = list(n.input)
        changed = False
        for i in (1, 2):
            src = producer.get(inputs[i])
            if src is None or src.op_type != "ConstantOfShape":
                continue
            shape_node = producer.get(src.input[0])
            if shape_node is None or shape_node.op_type != "Shape" or shape_node.attribute:
                continue
            if shape_node.input[0] != inputs[3 - i]:  # where(c, x, zeros_like(x)) only
                continue
            fill = next((a.t for a in src.attribute if a.name == "value"), None)
            value = numpy_helper.to_array(fill).reshape(-1)[0] if fill is not None else 0.0
            dtype = numpy_helper.to_array(fill).dtype if fill is not None else np.float32
            inputs[i] = const(value, dtype)
            changed = True
        if changed:
            return [make("Where", inputs, list(n.output), name=name)]
    return [n]


def _drop_unused(g) -> None:
    """Remove nodes none of whose outputs is used, and unused initializers (not in a graph
    with subgraphs, whose uses this does not see)."""
    if any(
        a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
        for n in g.node
        for a in n.attribute
    ):
        return
    while True:
        used = {i for n in g.node for i in n.input} | {o.name for o in g.output}
        keep = [n for n in g.node if any(o in used for o in n.output)]
        if len(keep) == len(g.node):
            break
        del g.node[:]
        g.node.extend(keep)
    inits = [t for t in g.initializer if t.name in used]
    del g.initializer[:]
    g.initializer.extend(inits)


# Opset conversion (docs/portable.md, "Opsets").  onnx's version converter has no adapter
# down from opset 14 for even Add, Sub, Mul and Div (14 only admitted more types), so it
# cannot take any graph with arithmetic below 14.  Every op these graphs hold kept its
# meaning for float32 from opset 13 to the newest: the schema versions below only widened
# the types (bfloat16, float8, integers, optional and sequence types) or added an
# attribute whose default keeps the old behaviour (Reshape allowzero, Shape start/end,
# Cast saturate, which acts on float8 only).  Between two opsets that only such versions
# separate, conversion is a relabelling of the opset, checked by onnx's full check.
MIN_OPSET = 13  # below it ReduceSum, Unsqueeze, Squeeze, Split, Clip changed form
TYPES_ONLY_VERSIONS = {
    *{(op, 14) for op in ("Add", "Sub", "Mul", "Div", "Relu", "Identity", "Reshape")},
    *{(op, 15) for op in ("Pow", "Shape")},
    *{(op, 16) for op in ("Where", "Identity", "LessOrEqual", "GreaterOrEqual")},
    *{(op, 19) for op in ("Cast", "Constant", "Equal", "Identity", "Reshape", "Shape")},
    *{(op, 20) for op in ("IsNaN", "IsInf", "ConstantOfShape")},
    *{
        (op, v)
        for v in (21, 23, 24)
        for op in (
            "Cast",
            "Constant",
            "ConstantOfShape",
            "Identity",
            "Reshape",
            "Shape",
            "Squeeze",
            "Transpose",
            "Unsqueeze",
        )
    },
    *{
        (op, 22)
        for op in ("Softplus", "Atan", "Asin", "Acos", "Cos", "Sin", "Tan", "Softsign", "Elu")
    },
}


def _version_steps(op: str, lo: int, hi: int) -> list[int]:
    """The schema versions of ``op`` that took effect in the opsets (lo, hi]."""
    steps = []
    for v in range(lo + 1, hi + 1):
        try:
            since = onnx.defs.get_schema(op, v).since_version
        except onnx.defs.SchemaError:
            return [-1]  # the op does not exist at one end
        if since > lo and since not in steps:
            steps.append(since)
    return steps


def convert_opset(model, opset: int) -> onnx.ModelProto:
    """An exported model (a path, bytes or ModelProto) at ONNX opset ``opset``.

    Between opset 13 and the newest that onnx knows, a graph whose ops changed only in
    their types in between (:data:`TYPES_ONLY_VERSIONS`; an attribute that would change
    the meaning, such as Reshape's allowzero = 1, disqualifies) is relabelled; any other is
    left to onnx's version converter, which converts upwards.  The result passes
    ``onnx.checker.check_model(full_check=True)``; ``onnx.checker.ValidationError`` or a
    ValueError when it cannot be converted."""
    from neural_brdf import graph as graphmod

    proto = copy.deepcopy(graphmod.load(model))
    current = next(o.version for o in proto.opset_import if o.domain in ("", "ai.onnx"))
    newest = onnx.defs.onnx_opset_version()
    if not MIN_OPSET <= opset <= newest:
        raise ValueError(f"opset {opset}: supported are {MIN_OPSET} to {newest}")
    lo, hi = sorted((current, opset))
    blocking = set()
    for n in proto.graph.node:
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
        changed = [(n.op_type, v) for v in _version_steps(n.op_type, lo, hi)]
        if any(c not in TYPES_ONLY_VERSIONS for c in changed) or (
            changed
            and (
                attrs.get("allowzero", 0)
                or "start" in attrs
                or "end" in attrs
                or "saturate" in attrs
            )
        ):
            blocking.add(n.op_type)
    if not blocking:
        for o in proto.opset_import:
            if o.domain in ("", "ai.onnx"):
                o.version = opset
        need = onnx.helper.find_min_ir_version_for(list(proto.opset_import))
        proto.ir_version = max(proto.ir_version, need)
    elif opset > current:
        proto = onnx.version_converter.convert_version(proto, opset)
    else:
        raise ValueError(
            f"opset {current} -> {opset}: ops {sorted(blocking)} changed meaning in between; "
            f"export at opset {opset} instead (export.opset)"
        )
    onnx.checker.check_model(proto, full_check=True)
    return proto


def to_onnx_bytes(model: torch.nn.Module, opset: int, *, portable: bool = True) -> bytes:
    """``model`` (forward(wi, wo) -> f) as ONNX bytes: torch's legacy exporter, then
    :func:`portable_graph` (``portable=False``: torch's graph as it is, for comparison)."""
    buf = io.BytesIO()
    example = (torch.zeros(4, 3), torch.zeros(4, 3))
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
            input_names=list(INPUTS),
            output_names=[OUTPUT],
            dynamic_axes={"wi": {0: "N"}, "wo": {0: "N"}, "f": {0: "N"}},
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
    model: torch.nn.Module, session: ort.InferenceSession, n: int, seed: int
) -> tuple[float, float, float]:
    """(onnxruntime vs torch, torch float32 vs the same network in float64, onnxruntime
    vs float64), relative."""
    pairs = parity_pairs(n, seed)
    wi, wo = pairs[:, :3].contiguous(), pairs[:, 3:].contiguous()
    with torch.no_grad():
        ref = model(wi, wo).numpy().astype(np.float64)
        exact = copy.deepcopy(model).double()(wi.double(), wo.double()).numpy()
    got = session.run([OUTPUT], {"wi": wi.numpy(), "wo": wo.numpy()})[0].astype(np.float64)
    return (
        relative_difference(got, ref),
        relative_difference(ref, exact),
        relative_difference(got, exact),
    )


def relative_difference(got: np.ndarray, ref: np.ndarray) -> float:
    """max |got - ref| / max(|ref|, PARITY_FLOOR * mean of the nonzero |ref|)."""
    nonzero = np.abs(ref[ref != 0])
    floor = PARITY_FLOOR * nonzero.mean() if nonzero.size else 1.0
    return float(np.max(np.abs(got - ref) / np.maximum(np.abs(ref), floor)))


def export(
    model: NormalizedBRDF | RawBRDF,
    cfg: cfgmod.Config,
    out: str | Path,
    *,
    target_desc: str,
    extra: Any = None,
) -> dict[str, Any]:
    """Write ``model`` to ``out`` with metadata; returns the measured figures.

    The graph written is ``TotalBRDF(model)``: it normalises its inputs and gives 0 for
    rows with a non-finite or zero-length direction, so no input row can crash a host or
    change another row (see :class:`neural_brdf.train.model.TotalBRDF`).
    """
    graph = TotalBRDF(model)
    payload = to_onnx_bytes(graph, cfg.export.opset)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    session = ort.InferenceSession(payload, opts, providers=["CPUExecutionProvider"])
    parity, precision, ort_exact = parity_error(
        graph, session, cfg.export.parity_pairs, cfg.train.seed + 29
    )
    allowed = max(cfg.export.parity_tol, 2.0 * precision)
    # torch and onnxruntime each round in float32, in their own order: where both errors
    # are near torch's largest (a grazing pair on a steep grid cell) their difference can
    # reach twice it, so onnxruntime also passes when it is as close to the exact float64
    # network as allowed (compact/bank: 7.3e-5 apart, 4.0e-5 from float64, allowed 7.2e-5)
    if not (parity <= allowed or ort_exact <= allowed):
        raise ParityError(
            f"torch and onnxruntime differ by {parity:.3g} relative (allowed "
            f"{allowed:.3g}: export.parity_tol, or twice the float32 precision "
            f"of the network, {precision:.3g}); nothing written"
        )

    def fn(a, b):
        return session.run(
            [OUTPUT], {"wi": np.asarray(a, np.float32), "wo": np.asarray(b, np.float32)}
        )[0]

    phys = validate.physics(fn, anisotropic=model.anisotropic, settings=cfg.validation, extra=extra)
    checks = phys["checks"]
    meta = Metadata(
        metadata_version=METADATA_VERSION,
        format_version=FORMAT_VERSION,
        producer=PRODUCER,
        frame=FRAME,
        units=UNITS,
        encoding=cfg.model.encoding,
        normalization=normalization_note(model, cfg.normalization),
        target=target_json(cfg, target_desc, extra),
        max_albedo=checks["max_albedo"]["value"],
        hemispherical_albedo=plain(phys["hemispherical_albedo"]),
        reciprocity_error=checks["reciprocity"]["value"],
        min_value=checks["min_value"]["value"],
        parity_rel_error=parity,
        float32_rel_precision=precision,
        training_config=cfg.model_dump(mode="json"),
        sampling_lobe=lobe.fit(fn),  # renderers' importance sampling
    ).to_props()
    proto = onnx.load_from_string(payload)
    onnx.helper.set_model_props(proto, meta)
    proto.producer_name = PRODUCER_NAME
    proto.producer_version = __version__
    proto.model_version = FORMAT_VERSION  # the file format, an integer
    proto.doc_string = doc_string(cfg, target_desc, isinstance(model, NormalizedBRDF))
    onnx.checker.check_model(proto)
    atomic_write(Path(out), proto.SerializeToString(), parents=True)
    return {"parity_rel_error": parity, "float32_rel_precision": precision, "physics": phys}


def export_run(run_dir: str | Path, out: str | Path | None = None) -> dict[str, Any]:
    """``neural-brdf export RUN_DIR [-o OUT]``: checkpoint -> normalised model -> ONNX."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.yaml"
    if not cfg_path.is_file():
        raise CheckpointError(f"{run_dir}: not a run directory (no config.yaml)")
    cfg = cfgmod.load(cfg_path)
    ckpt = load_checkpoint(run_dir / "ckpt.pt")
    target = data.build_target(cfg.target)
    raw = raw_from_checkpoint(ckpt, cfg)
    model, table_info = normalized_model(raw, cfg, target)
    out = Path(out) if out is not None else run_dir / "model.onnx"
    info = export(model, cfg, out, target_desc=target.describe(), extra=target)
    info["normalization"] = table_info
    info["path"] = str(out)
    return info


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
