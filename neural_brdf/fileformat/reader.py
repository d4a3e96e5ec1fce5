"""The one ONNX loader: a path, bytes or a ModelProto -> ModelProto, with a one-line
error for a file that is not ONNX, and the file's metadata as strings or typed.

    from neural_brdf.fileformat import reader
    proto = reader.load("model.onnx")        # InputError: "model.onnx: not a loadable ..."
    reader.props(proto)                      # {"max_albedo": "0.94", ...}
    reader.metadata(proto).max_albedo        # typed (fileformat.metadata.Metadata)
    reader.signature(proto)                  # ("wi", "wo") or ("wi", "wo", "uv")

The graph lowering (:mod:`neural_brdf.graph`), the Mitsuba plugin and the report read
models through it; the runtime opens files with onnxruntime itself and decodes their
metadata with :mod:`.metadata`.
"""

from __future__ import annotations

import os

import numpy as np
import onnx
from onnx import numpy_helper

from neural_brdf.errors import InputError
from neural_brdf.fileformat import (
    INPUT_WIDTHS,
    NORMAL,
    OUTPUT,
    OUTPUT_SIGNATURES,
    SIGNATURES,
    sizes,
)
from neural_brdf.fileformat.metadata import Metadata, check_props_versions


def load(model, *, external_data: bool = True) -> onnx.ModelProto:
    """A path, bytes or ModelProto -> ModelProto (a one-line InputError if unreadable).
    ``external_data`` False leaves tensors stored beside the file unread (the metadata
    and the graph's structure only)."""
    if isinstance(model, onnx.ModelProto):
        return model
    source = str(model) if not isinstance(model, (bytes, bytearray)) else "model bytes"
    try:
        if isinstance(model, (bytes, bytearray)):
            proto = onnx.load_from_string(bytes(model))
        elif isinstance(model, (str, os.PathLike)):
            proto = onnx.load(str(model), load_external_data=external_data)
        else:
            raise TypeError(
                f"expected a path, bytes or onnx.ModelProto, got {type(model).__name__}"
            )
    except TypeError:
        raise
    except Exception as e:  # onnx raises DecodeError, OSError and others on a bad file
        raise InputError(f"{source}: not a loadable ONNX model ({type(e).__name__})") from None
    if not proto.HasField("graph"):  # protobuf reads an empty file as an empty message
        raise InputError(f"{source}: not an ONNX model (it has no graph; an empty file?)")
    sizes.check(proto, source=source)  # declared sizes, before anything is allocated
    check_finite(proto, source=source)
    try:  # a later contract's file (format_version 99) may mean another thing
        check_props_versions({p.key: p.value for p in proto.metadata_props})
    except InputError as e:
        raise InputError(f"{source}: {e}") from None
    return proto


def check_finite(proto: onnx.ModelProto, *, source: str = "model") -> None:
    """A one-line InputError naming ``source`` and the initializer if a floating-point
    initializer holds a NaN or an infinity (a diverged training's weights): every
    consumer would give NaN, write NAN literals or fail later.  Tensors stored beside
    the file and not loaded are not checked."""
    for t in proto.graph.initializer:
        if t.data_location == onnx.TensorProto.EXTERNAL and not t.raw_data:
            continue
        if t.data_type not in _FLOATS:
            continue
        try:
            a = numpy_helper.to_array(t)
        except Exception:  # a malformed tensor: onnxruntime or the lowering names it
            continue
        if not np.isfinite(a).all():
            raise InputError(
                f"{source}: initializer {_names((t.name,))[1:-1]} holds non-finite values "
                f"(NaN or inf): the model's weights are broken"
            )


def props(proto: onnx.ModelProto) -> dict[str, str]:
    """The metadata_props as strings, in file order (a repeated key keeps its last value)."""
    return {p.key: p.value for p in proto.metadata_props}


def metadata(proto: onnx.ModelProto, *, source: str = "model") -> Metadata:
    """The metadata_props decoded and typed (a one-line InputError naming ``source`` and
    the key for a value that cannot be decoded)."""
    try:
        return Metadata.from_props(props(proto))
    except InputError as e:
        raise InputError(f"{source}: {e}") from None


def signature(proto: onnx.ModelProto, *, source: str = "model") -> tuple[str, ...]:
    """The graph's input names, checked against the contract: one of
    :data:`~neural_brdf.fileformat.SIGNATURES` ((wi, wo), or (wi, wo, uv) for a material
    that varies over the surface), in that order, each float32 [N, width] where its shape
    is declared, and the output ``f`` float32 [N, 3] (a declared width the fixed 3),
    followed in a textured graph by the optional normal field ``n`` [N, 3]
    (:func:`outputs`).  A one-line InputError naming ``source`` otherwise."""
    g = proto.graph
    inits = {t.name for t in g.initializer}  # IR < 4 lists initializers among the inputs
    values = [v for v in g.input if v.name not in inits]
    names = tuple(v.name for v in values)
    outs = tuple(v.name for v in g.output)
    allowed = OUTPUT_SIGNATURES if names == SIGNATURES[1] else OUTPUT_SIGNATURES[:1]
    if names not in SIGNATURES or outs not in allowed:
        expected = " or ".join(str(s) for s in SIGNATURES)
        raise InputError(
            f"{source}: expected inputs {expected} and output {OUTPUT!r} (and {NORMAL!r} "
            f"with uv), got {_names(names)} -> {_names(outs)}"
        )
    for v, width in [(v, INPUT_WIDTHS[v.name]) for v in values] + [(o, 3) for o in g.output]:
        t = v.type.tensor_type
        dims = [d.dim_value if d.HasField("dim_value") else None for d in t.shape.dim]
        # a width may be left symbolic (torch.onnx.export names the output's "Castf_dim_1":
        # the runtime checks what a run returns); a declared one must be the contract's:
        # an output [N, 1] or [N, 4] is no RGB the consumers can use
        if t.elem_type != onnx.TensorProto.FLOAT or (
            t.HasField("shape") and (len(dims) != 2 or dims[1] not in (None, width))
        ):
            raise InputError(
                f"{source}: {v.name!r}: expected float32 [N, {width}], got {_declared(v)}"
            )
    return names


def outputs(proto: onnx.ModelProto, *, source: str = "model") -> tuple[str, ...]:
    """The graph's output names, checked with its inputs by :func:`signature`: ("f",) or,
    for a textured graph that carries its teacher's normal field, ("f", "n")."""
    signature(proto, source=source)
    return tuple(v.name for v in proto.graph.output)


_FLOATS = frozenset(
    {
        onnx.TensorProto.FLOAT,
        onnx.TensorProto.DOUBLE,
        onnx.TensorProto.FLOAT16,
        onnx.TensorProto.BFLOAT16,
    }
)
_TYPES: dict[int, str] = {onnx.TensorProto.FLOAT: "float32", onnx.TensorProto.DOUBLE: "float64"}


def _declared(v: onnx.ValueInfoProto) -> str:
    """A value's declared type and shape for an error text: "float64 [N, 3]"."""
    t = v.type.tensor_type
    try:
        kind = _TYPES.get(t.elem_type) or onnx.TensorProto.DataType.Name(t.elem_type).lower()
    except ValueError:  # not a known element type
        kind = f"element type {t.elem_type}"
    if not t.HasField("shape"):
        return f"{kind} of undeclared shape"
    dims = [
        str(d.dim_value) if d.HasField("dim_value") else (d.dim_param[:20] or "?")
        for d in t.shape.dim[:6]
    ]
    return f"{kind} [{', '.join(dims)}{', ...' if len(t.shape.dim) > 6 else ''}]"


def _names(names: tuple[str, ...]) -> str:
    """``names`` for an error text: at most 4, each at most 40 characters."""
    shown = [n if len(n) <= 40 else n[:37] + "..." for n in names[:4]]
    return "(" + ", ".join(repr(n) for n in shown) + (", ..." if len(names) > 4 else "") + ")"
