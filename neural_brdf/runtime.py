"""Evaluate an exported neural BRDF with onnxruntime alone.

    import neural_brdf
    brdf = neural_brdf.load("runs/quickstart/model.onnx")
    f = brdf.eval(wi, wo)          # numpy (..., 3) in, (..., 3) float32 out, 1/sr, no cosine
    brdf.metadata["max_albedo"]    # every metadata_props entry, as strings
    brdf.meta["max_albedo"]        # the same, decoded: JSON values parsed (read_metadata)
    brdf.config                    # the training config (dict)
    brdf.target                    # what it was fitted to (dict: kind, model, params, ...)

The metadata schema has a version (``metadata_version``, docs/portable.md): files of
version 1, written before the key existed, hold the target as a description (for an
analytic target the ``analytic.create(...)`` call) and the training config as YAML;
version 2 holds both as JSON.  :func:`read_metadata` reads either into the same form.

This module needs numpy, onnxruntime and yaml only; it never imports torch or pydantic
(tests/test_packaging.py checks it in a fresh interpreter).
"""

from __future__ import annotations

import ast
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
import yaml
from numpy.typing import ArrayLike

from neural_brdf.errors import InputError

# the file's contract (names, versions, metadata keys): neural_brdf.fileformat
from neural_brdf.fileformat import INPUTS, JSON_KEYS, METADATA_VERSION_KEY, OUTPUT  # noqa: F401

CHUNK = 1 << 18  # pairs per onnxruntime call: bounds the memory of a large eval


def read_metadata(props: Mapping[str, str]) -> dict[str, Any]:
    """metadata_props (strings) -> values, for files of every metadata_version.

    JSON values are parsed; ``target`` is always an object (:func:`parse_target` for
    version 1's description) and ``training_config`` a dict (version 1's YAML is read);
    ``metadata_version`` is an int, 1 when absent.  Other keys stay text, and so does a
    number a version-1 file wrote as ``inf`` or ``nan``."""
    out: dict[str, Any] = dict(props)
    for key in JSON_KEYS:
        if key in props:
            try:
                out[key] = json.loads(props[key])
            except ValueError:
                pass  # version 1 text (the target, the YAML config) or "inf"/"nan"
    out[METADATA_VERSION_KEY] = int(out.get(METADATA_VERSION_KEY, 1))
    if "target" in props and not isinstance(out["target"], dict):
        out["target"] = parse_target(props["target"])
    if "training_config" in props and not isinstance(out["training_config"], dict):
        out["training_config"] = yaml.safe_load(props["training_config"]) or {}
    return out


def parse_target(text: str) -> dict[str, Any]:
    """A version-1 ``target`` description as the version-2 object.

    ``analytic.create('NAME', k=v, ...)`` (an analytic target's repr) gives
    ``{"kind": "analytic", "model": NAME, "resolved": {k: v}, "description": text}``; it
    is read with :mod:`ast` (literals only, nothing is evaluated).  Version 1 did not keep
    the parameters as given, so there is no ``params``: ``resolved`` holds every value,
    derived ones included.  ``MERL ...`` and ``RGL ...`` give kind ``measured``; anything
    else kind ``unspecified``."""
    try:
        call = ast.parse(text.strip(), mode="eval").body
        if not (
            isinstance(call, ast.Call)
            and ast.unparse(call.func) == "analytic.create"
            and len(call.args) == 1
        ):
            raise ValueError
        name = ast.literal_eval(call.args[0])
        params = {k.arg: _lists(ast.literal_eval(k.value)) for k in call.keywords if k.arg}
        if not isinstance(name, str):
            raise ValueError
        return {"kind": "analytic", "model": name, "resolved": params, "description": text}
    except (SyntaxError, ValueError, TypeError, RecursionError):
        pass
    if text.startswith(("MERL ", "RGL ")):
        return {"kind": "measured", "description": text}
    return {"kind": "unspecified", "description": text}


def _lists(value):
    """Tuples as lists, as JSON gives them (eta=(0.1, 0.2, 0.3) in a repr)."""
    if isinstance(value, (tuple, list)):
        return [_lists(v) for v in value]
    if isinstance(value, dict):
        return {k: _lists(v) for k, v in value.items()}
    return value


class NeuralBRDF:
    """An exported model: ``eval(wi, wo)`` on numpy arrays, plus its metadata."""

    def __init__(self, path: str | Path, *, threads: int = 1):
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no such model file")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads  # 1 thread was fastest here (docs/results.md)
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own untyped errors on bad files
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise InputError(f"{path}: not a loadable ONNX model ({first[:200]})") from None
        names = tuple(i.name for i in self.session.get_inputs())
        outs = tuple(o.name for o in self.session.get_outputs())
        if names != INPUTS or outs != (OUTPUT,):
            raise InputError(
                f"{path}: expected inputs {INPUTS} and output {OUTPUT!r}, got {names} -> {outs}"
            )
        self.path = path
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        self.meta: dict[str, Any] = read_metadata(self.metadata)

    @property
    def metadata_version(self) -> int:
        return self.meta[METADATA_VERSION_KEY]

    @property
    def config(self) -> dict[str, Any]:
        """The training config (JSON in metadata_version 2, YAML in 1), or {}."""
        return self.meta.get("training_config") or {}

    @property
    def target(self) -> dict[str, Any]:
        """What the model was fitted to: {"kind", "description", ...} (read_metadata)."""
        return self.meta.get("target") or {"kind": "unspecified", "description": ""}

    @property
    def encoding(self) -> str:
        return self.metadata.get("encoding", "isotropic")

    def eval(self, wi: ArrayLike, wo: ArrayLike) -> np.ndarray:
        """f(wi, wo) in 1/sr: (..., 3) unit vectors (broadcast) -> (..., 3) float32 RGB."""
        wi = np.asarray(wi, dtype=np.float32)
        wo = np.asarray(wo, dtype=np.float32)
        wi, wo = np.broadcast_arrays(wi, wo)
        if wi.shape[-1:] != (3,):
            raise InputError(f"wi, wo: expected shape (..., 3), got {wi.shape}")
        batch = wi.shape[:-1]
        a = np.ascontiguousarray(wi.reshape(-1, 3))
        b = np.ascontiguousarray(wo.reshape(-1, 3))
        out = np.empty((len(a), 3), dtype=np.float32)
        for s in range(0, len(a), CHUNK):
            out[s : s + CHUNK] = self.session.run(
                [OUTPUT], {"wi": a[s : s + CHUNK], "wo": b[s : s + CHUNK]}
            )[0]
        return out.reshape(batch + (3,))

    __call__ = eval

    def __repr__(self) -> str:
        return f"neural_brdf.load({str(self.path)!r})  # {self.target.get('description') or '?'}"


def load(path: str | Path, *, threads: int = 1) -> NeuralBRDF:
    """Open an exported ``model.onnx``; raises InputError on a missing or invalid file."""
    return NeuralBRDF(path, threads=threads)
