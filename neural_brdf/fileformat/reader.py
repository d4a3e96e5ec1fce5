"""The one ONNX loader: a path, bytes or a ModelProto -> ModelProto, with a one-line
error for a file that is not ONNX, and the file's metadata as strings or typed.

    from neural_brdf.fileformat import reader
    proto = reader.load("model.onnx")        # InputError: "model.onnx: not a loadable ..."
    reader.props(proto)                      # {"max_albedo": "0.94", ...}
    reader.metadata(proto).max_albedo        # typed (fileformat.metadata.Metadata)

The graph lowering (:mod:`neural_brdf.graph`), the Mitsuba plugin and the report read
models through it; the runtime opens files with onnxruntime itself and decodes their
metadata with :mod:`.metadata`.
"""

from __future__ import annotations

import os

import onnx

from neural_brdf.errors import InputError
from neural_brdf.fileformat.metadata import Metadata


def load(model, *, external_data: bool = True) -> onnx.ModelProto:
    """A path, bytes or ModelProto -> ModelProto (a one-line InputError if unreadable).
    ``external_data`` False leaves tensors stored beside the file unread (the metadata
    and the graph's structure only)."""
    if isinstance(model, onnx.ModelProto):
        return model
    try:
        if isinstance(model, (bytes, bytearray)):
            return onnx.load_from_string(bytes(model))
        if isinstance(model, (str, os.PathLike)):
            return onnx.load(str(model), load_external_data=external_data)
    except Exception as e:  # onnx raises DecodeError, OSError and others on a bad file
        raise InputError(
            f"{model if not isinstance(model, bytes) else 'model bytes'}: not a "
            f"loadable ONNX model ({type(e).__name__})"
        ) from None
    raise TypeError(f"expected a path, bytes or onnx.ModelProto, got {type(model).__name__}")


def props(proto: onnx.ModelProto) -> dict[str, str]:
    """The metadata_props as strings, in file order (a repeated key keeps its last value)."""
    return {p.key: p.value for p in proto.metadata_props}


def metadata(proto: onnx.ModelProto) -> Metadata:
    """The metadata_props decoded and typed."""
    return Metadata.from_props(props(proto))
