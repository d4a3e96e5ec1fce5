"""Export a trained run to one self-contained ONNX file (the contract other tools use).

    inputs   wi, wo   float32 [N, 3]   unit vectors in the local frame (analytic.frame)
    output   f        float32 [N, 3]   BRDF in 1/sr, RGB, without the cosine
    N is dynamic.  Encoding, horizon test and albedo normalisation are in the graph.
    The graph is total: it normalises wi and wo itself, and a row with a NaN, an
    infinity or a zero-length direction gives f = 0 (other rows are unaffected).

The ONNX model fields describe the file: ``producer_name`` "neural-brdf",
``producer_version`` the package version (neural_brdf.version), ``model_version`` the
integer ``config.FORMAT_VERSION`` (bumped when this contract changes) and ``doc_string``
one paragraph: the target, the encoding and the input/output contract above.

``metadata_props`` (read with ``neural_brdf.load(path).metadata``):

    format_version, producer, frame, units, encoding, normalization, target,
    max_albedo, hemispherical_albedo, reciprocity_error, min_value,
    parity_rel_error, float32_rel_precision, training_config (the resolved config, YAML),
    sampling_lobe (JSON: the importance-sampling lobe fitted to the network, neural_brdf.lobe)

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
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import torch

from analytic import physics

from . import config as cfgmod
from . import data, lobe, validate
from .encoding import is_anisotropic
from .errors import ParityError
from .fileio import atomic_write
from .model import NormalizedBRDF, RawBRDF, TotalBRDF, albedo_table
from .runtime import INPUTS, OUTPUT
from .version import __version__

PRODUCER_NAME = "neural-brdf"  # ONNX producer_name; producer_version: the package's
PRODUCER = f"{PRODUCER_NAME} {__version__}"  # the ``producer`` metadata entry
FRAME = (
    "local shading frame: z = normal, x = tangent (anisotropy axis), y = z cross x; "
    "wi and wo are unit vectors pointing away from the surface; f = 0 when "
    "wi_z <= 0 or wo_z <= 0"
)
UNITS = "f: BRDF value in 1/sr per RGB channel, without the cosine factor"
# Parity is relative to max(|f|, PARITY_FLOOR * mean |f|).  Below a tenth of the model's
# mean value the comparison is absolute: there the float32 network is itself no more
# accurate than ~1e-5 (softplus tails carry the absolute error of their argument).
# Measured on a smooth-Beckmann run: torch float32 vs the same network in float64
# differs by 4.7e-5 relative without the floor and 5.9e-6 with it; torch vs
# onnxruntime by 4.0e-5 and 7.7e-6.
PARITY_FLOOR = 0.1
ANALYTIC_OPSET = 17  # opset of analytic_onnx (as neural_brdf.mitsuba used)


class CheckpointError(cfgmod.InputError):
    """A run directory or checkpoint is missing or unusable."""


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


def load_checkpoint(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint (train first, or check the run directory)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several unrelated types on a corrupt file
        raise CheckpointError(f"{path}: unreadable checkpoint ({type(e).__name__})") from None


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
    applied = (
        "A+ <= 1 at every node, so the division is the identity and the graph omits it"
        if model.identity
        else "applied in the graph"
    )
    return (
        f"f = raw / max(1, A+(wi), A+(wo)) per channel ({applied}); "
        f"A+ = MIS quadrature albedo of "
        f"the raw network + {n.sigmas:g} standard errors, neighbour maximum, times "
        f"(1 + {n.margin:g}); table of {model.table.shape[0]} nodes per axis, "
        f"{n.samples} points per node"
    )


def to_onnx_bytes(model: torch.nn.Module, opset: int) -> bytes:
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
            buf,
            dynamo=False,
            opset_version=opset,
            input_names=list(INPUTS),
            output_names=[OUTPUT],
            dynamic_axes={"wi": {0: "N"}, "wo": {0: "N"}, "f": {0: "N"}},
        )
    return buf.getvalue()


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
    change another row (see :class:`neural_brdf.model.TotalBRDF`).
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
    meta = {
        "format_version": str(cfgmod.FORMAT_VERSION),
        "producer": PRODUCER,
        "frame": FRAME,
        "units": UNITS,
        "encoding": cfg.model.encoding,
        "normalization": normalization_note(model, cfg.normalization),
        "target": target_desc,
        "max_albedo": repr(checks["max_albedo"]["value"]),
        "hemispherical_albedo": json.dumps(phys["hemispherical_albedo"]),
        "reciprocity_error": repr(checks["reciprocity"]["value"]),
        "min_value": repr(checks["min_value"]["value"]),
        "parity_rel_error": repr(parity),
        "float32_rel_precision": repr(precision),
        "training_config": cfg.to_yaml(),
        lobe.KEY: lobe.to_json(lobe.fit(fn)),  # renderers' importance sampling
    }
    proto = onnx.load_from_string(payload)
    onnx.helper.set_model_props(proto, meta)
    proto.producer_name = PRODUCER_NAME
    proto.producer_version = __version__
    proto.model_version = cfgmod.FORMAT_VERSION  # the file format, an integer
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
