"""Evaluate an exported neural BRDF with onnxruntime alone.

    import neural_brdf
    brdf = neural_brdf.load("runs/quickstart/model.onnx")
    f = brdf.eval(wi, wo)          # numpy (..., 3) in, (..., 3) float32 out, 1/sr, no cosine
    f = brdf.eval(wi, wo, uv)      # a textured file (brdf.textured): uv (..., 2) too
    n = brdf.normal(uv)            # its normal field (brdf.has_normal_field), (..., 3)
    brdf.metadata["max_albedo"]    # every metadata_props entry, as strings
    brdf.meta["max_albedo"]        # the same, decoded: JSON values parsed (read_metadata)
    brdf.info.max_albedo           # the same, typed (neural_brdf.fileformat.metadata.Metadata)
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

from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
from numpy.typing import ArrayLike

from neural_brdf.errors import InputError, not_a_file

# the file's contract (names, versions, metadata keys, their decoding): neural_brdf.fileformat
from neural_brdf.fileformat import (  # noqa: F401
    INPUTS,
    JSON_KEYS,
    METADATA_VERSION_KEY,
    NORMAL,
    OUTPUT,
    OUTPUT_SIGNATURES,
    SIGNATURES,
    UV,
)
from neural_brdf.fileformat.metadata import Metadata, parse_target, read_metadata  # noqa: F401

CHUNK = 1 << 18  # pairs per onnxruntime call: bounds the memory of a large eval
# onnxruntime's threads: it takes a C int (2**40 gave pybind11's 4-line TypeError), and
# a pool far beyond any host's cores only costs memory
MAX_THREADS = 1024


def _rows(name: str, x: ArrayLike, width: int, *, direction: bool = False) -> np.ndarray:
    """``x`` as float32 (..., ``width``), or a one-line InputError naming ``name``.

    A direction in a wider float whose rounding to float32 would lose it, such as
    (1e-50, 0, 1e-50) (the zero vector: f = 0) or (1e300, 0, 1e300) (infinite), is first
    scaled by its largest absolute component, the graph's own first step, so f is that
    of the direction; every other row is rounded as it is."""
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as e:  # a ragged list
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"{name}: expected an array of shape (..., {width}) ({first})") from None
    if a.dtype.kind not in "biuf":  # strings, objects, complex numbers
        raise InputError(f"{name}: expected real numbers, got an array of {a.dtype}")
    if a.shape[-1:] != (width,):
        raise InputError(f"{name}: expected shape (..., {width}), got {a.shape}")
    if direction and a.dtype.kind == "f" and a.dtype.itemsize > 4 and a.size:
        with np.errstate(all="ignore"):
            m = np.max(np.abs(a), axis=-1, keepdims=True)
            # only rows whose rounding to float32 would lose them: others are rounded
            # as they are, bit for bit as onnxruntime fed float32 would see them
            ok = np.isfinite(m) & (m > 0) & ((m < 2.0**-100) | (m > 2.0**100))
            if ok.any():
                a = np.where(ok, a / np.where(ok, m, 1.0), a)
    with np.errstate(over="ignore"):  # a larger float beyond float32: inf, f = 0
        return a.astype(np.float32)


class NeuralBRDF:
    """An exported model: ``eval(wi, wo)`` on numpy arrays, plus its metadata."""

    def __init__(self, path: str | Path, *, threads: int = 1):
        path = Path(path)
        if (
            isinstance(threads, bool)
            or not isinstance(threads, (int, np.integer))
            or not 1 <= threads <= MAX_THREADS
        ):
            raise InputError(
                f"threads: expected a whole number from 1 to {MAX_THREADS}, got {threads!r}"
            )
        if not path.is_file():
            raise InputError(not_a_file(path, "model"))
        # the file's declared sizes, checked before onnxruntime allocates from them
        from neural_brdf.fileformat import reader

        # and its contract: inputs float32 [N, width], the output f float32 [N, 3], and
        # finite weights (reader.load), each refused with one line naming the file
        reader.signature(reader.load(path, external_data=False), source=str(path))
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)  # 1 thread was fastest here (docs/results.md)
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own untyped errors on bad files
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise InputError(f"{path}: not a loadable ONNX model ({first[:200]})") from None
        names = tuple(i.name for i in self.session.get_inputs())
        outs = tuple(o.name for o in self.session.get_outputs())
        allowed = OUTPUT_SIGNATURES if names == SIGNATURES[1] else OUTPUT_SIGNATURES[:1]
        if names not in SIGNATURES or outs not in allowed:
            raise InputError(
                f"{path}: expected inputs {INPUTS} (or {SIGNATURES[1]}) and output "
                f"{OUTPUT!r} (and {NORMAL!r} with uv), got {names} -> {outs}"
            )
        self.inputs = names
        self.outputs = outs
        self.path = path
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        try:
            self.meta: dict[str, Any] = read_metadata(self.metadata)
            self.info: Metadata = Metadata.from_props(self.metadata)  # the same, typed
        except InputError as e:  # a value that cannot be decoded: name the file
            raise InputError(f"{path}: {e}") from None

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

    @property
    def textured(self) -> bool:
        """Does f vary over the surface (the graph's inputs are wi, wo and uv)?"""
        return UV in self.inputs

    @property
    def has_normal_field(self) -> bool:
        """Does the file carry its teacher's normal field (the output n, docs/portable.md,
        "Textured files")?  A renderer then rotates its shading frame to n(uv) and
        evaluates f in the rotated frame."""
        return NORMAL in self.outputs

    def normal(self, uv: ArrayLike) -> np.ndarray:
        """The shading normal n(uv): (..., 2) -> (..., 3) float32 unit vectors in the
        unperturbed shading frame; (0, 0, 1) everywhere for a file without a normal
        field, and where uv is not finite."""
        c = _rows("uv", uv, 2)
        rows = np.ascontiguousarray(c.reshape(-1, 2))
        out = np.zeros((len(rows), 3), dtype=np.float32)
        out[:, 2] = 1.0
        if not self.has_normal_field:
            return out.reshape(c.shape[:-1] + (3,))
        for s in range(0, len(rows), CHUNK):
            part = rows[s : s + CHUNK]
            zeros = np.zeros((len(part), 3), np.float32)  # onnxruntime wants every input
            out[s : s + CHUNK] = self._run(NORMAL, {INPUTS[0]: zeros, INPUTS[1]: zeros, UV: part})
        return out.reshape(c.shape[:-1] + (3,))

    def _run(self, output: str, feeds: dict[str, np.ndarray]) -> np.ndarray:
        try:
            res = self.session.run([output], feeds)[0]
        except Exception as e:  # onnxruntime raises its own untyped errors (Fail, ...)
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise InputError(f"{self.path}: onnxruntime failed ({first[:200]})") from None
        rows = len(next(iter(feeds.values())))
        if getattr(res, "shape", None) != (rows, 3):  # an output of undeclared shape
            shape = getattr(res, "shape", type(res).__name__)
            raise InputError(
                f"{self.path}: output {output!r}: expected float32 [N, 3], got shape {shape}"
            )
        return res

    def eval(self, wi: ArrayLike, wo: ArrayLike, uv: ArrayLike | None = None) -> np.ndarray:
        """f(wi, wo) in 1/sr: (..., 3) unit vectors (broadcast) -> (..., 3) float32 RGB.

        A textured file (:attr:`textured`) needs ``uv``, (..., 2) texture coordinates
        broadcast with the directions; a homogeneous one is the same at every uv, so a
        ``uv`` given to it is checked for its shape and otherwise unused."""
        wi = _rows("wi", wi, 3, direction=True)
        wo = _rows("wo", wo, 3, direction=True)
        if uv is None and self.textured:
            raise InputError(
                f"{self.path}: a textured material: give uv, (..., 2) texture coordinates"
            )
        c = np.zeros((2,), np.float32) if uv is None else _rows("uv", uv, 2)
        try:
            batch = np.broadcast_shapes(wi.shape[:-1], wo.shape[:-1], c.shape[:-1])
        except ValueError:
            raise InputError(
                f"wi, wo, uv: shapes {wi.shape}, {wo.shape}, {c.shape} do not broadcast"
            ) from None
        a = np.ascontiguousarray(np.broadcast_to(wi, batch + (3,)).reshape(-1, 3))
        b = np.ascontiguousarray(np.broadcast_to(wo, batch + (3,)).reshape(-1, 3))
        rows = np.ascontiguousarray(np.broadcast_to(c, batch + (2,)).reshape(-1, 2))
        out = np.empty((len(a), 3), dtype=np.float32)
        for s in range(0, len(a), CHUNK):
            feeds = {INPUTS[0]: a[s : s + CHUNK], INPUTS[1]: b[s : s + CHUNK]}
            if self.textured:
                feeds[UV] = rows[s : s + CHUNK]
            out[s : s + CHUNK] = self._run(OUTPUT, feeds)
        return out.reshape(batch + (3,))

    __call__ = eval

    def __repr__(self) -> str:
        return f"neural_brdf.load({str(self.path)!r})  # {self.target.get('description') or '?'}"


def load(path: str | Path, *, threads: int = 1) -> NeuralBRDF:
    """Open an exported ``model.onnx``; raises InputError on a missing or invalid file."""
    return NeuralBRDF(path, threads=threads)
