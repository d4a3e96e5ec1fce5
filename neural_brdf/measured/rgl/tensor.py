"""Mitsuba's tensor file (the container of an RGL ``.bsdf``): read, parse, write."""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from neural_brdf import fileio, limits
from neural_brdf.fileio import atomic_write
from neural_brdf.measured.base import FormatError

# ------------------------------------------------------------------ tensor file
MAGIC = b"tensor_file\0"
VERSION = (1, 0)
ALIGN = 8  # data offsets are multiples of this (as Mitsuba's writer)
DTYPES = {
    1: np.uint8,
    2: np.int8,
    3: np.uint16,
    4: np.int16,
    5: np.uint32,
    6: np.int32,
    7: np.uint64,
    8: np.int64,
    9: np.float16,
    10: np.float32,
    11: np.float64,
}
DTYPE_CODES = {np.dtype(v): k for k, v in DTYPES.items()}
MAX_NDIM = 16  # a sanity bound on a field's rank (RGL files use <= 5)


class RGLFormatError(FormatError):
    """An RGL / tensor file that cannot be read.  The one-line message names the file."""


def read_tensor_file(path) -> dict[str, np.ndarray]:
    """Every field of a TensorFile, in file order, as native numpy arrays (copies)."""
    p = Path(path)
    try:
        with fileio.open_for_reading(p) as fh:
            size = os.fstat(fh.fileno()).st_size
            try:  # before reading: a huge file is refused by name, not by the allocator
                limits.check_bytes(str(p), size, hint="too large for a tensor file")
            except limits.TooLarge as e:
                raise RGLFormatError(str(e)) from None
            buf = fh.read()
    except fileio.NotAFileError as e:
        raise RGLFormatError(str(e)) from None
    except FileNotFoundError:
        raise RGLFormatError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise RGLFormatError(f"{p}: is a directory, not a tensor file") from None
    except OSError as e:
        raise RGLFormatError(f"{p}: cannot read ({e.strerror or e})") from None
    return parse_tensor_file(buf, source=str(p))


def parse_tensor_file(buf: bytes, *, source: str = "<bytes>") -> dict[str, np.ndarray]:
    """:func:`read_tensor_file` on bytes in memory."""
    pos = 0

    def take(n: int, what: str) -> bytes:
        nonlocal pos
        if pos + n > len(buf):
            raise RGLFormatError(f"{source}: truncated ({len(buf)} bytes) while reading {what}")
        out = buf[pos : pos + n]
        pos += n
        return out

    if take(len(MAGIC), "the header") != MAGIC:
        raise RGLFormatError(f"{source}: not a tensor file (header is not 'tensor_file')")
    version = tuple(take(2, "the version"))
    if version != VERSION:
        raise RGLFormatError(f"{source}: tensor file version {version}, expected {VERSION}")
    (count,) = struct.unpack("<I", take(4, "the field count"))
    specs = []
    for k in range(count):
        (n,) = struct.unpack("<H", take(2, f"field {k}"))
        try:
            name = take(n, f"field {k}'s name").decode("utf-8")
        except UnicodeDecodeError:
            raise RGLFormatError(f"{source}: field {k}: name is not UTF-8") from None
        ndim, code, offset = struct.unpack("<HBQ", take(11, f"field {name!r}"))
        if code not in DTYPES:
            raise RGLFormatError(f"{source}: field {name!r}: unknown dtype code {code}")
        if ndim > MAX_NDIM:
            raise RGLFormatError(f"{source}: field {name!r}: rank {ndim} > {MAX_NDIM}")
        shape = struct.unpack(f"<{ndim}Q", take(8 * ndim, f"field {name!r}'s shape"))
        specs.append((name, np.dtype(DTYPES[code]).newbyteorder("<"), shape, offset))
    out = {}
    for name, dtype, shape, offset in specs:
        size = math.prod(shape) * dtype.itemsize
        if offset + size > len(buf):
            raise RGLFormatError(
                f"{source}: field {name!r}: data ends at byte "
                f"{offset + size}, file has {len(buf)} (truncated)"
            )
        arr = np.frombuffer(buf, dtype=dtype, count=math.prod(shape), offset=offset)
        out[name] = arr.reshape(shape).astype(dtype.newbyteorder("="))
    return out


def tensor_file_bytes(fields: Mapping[str, object]) -> bytes:
    """The TensorFile encoding of ``fields`` (name -> array, or str stored as uint8)."""
    arrays = {}
    for name, v in fields.items():
        a = (
            np.frombuffer(v.encode("utf-8"), np.uint8)
            if isinstance(v, str)
            else np.ascontiguousarray(v)
        )
        if a.dtype.newbyteorder("=") not in DTYPE_CODES:
            raise ValueError(f"{name}: unsupported dtype {a.dtype}")
        arrays[name] = a
    header = bytearray(MAGIC + bytes(VERSION) + struct.pack("<I", len(arrays)))
    header_size = len(header) + sum(
        2 + len(n.encode("utf-8")) + 11 + 8 * a.ndim for n, a in arrays.items()
    )
    body, offset = bytearray(), header_size
    for name, a in arrays.items():
        start = -(-offset // ALIGN) * ALIGN
        label = name.encode("utf-8")
        header += struct.pack("<H", len(label)) + label
        header += struct.pack("<HBQ", a.ndim, DTYPE_CODES[a.dtype.newbyteorder("=")], start)
        header += struct.pack(f"<{a.ndim}Q", *a.shape)
        body += bytes(start - offset) + a.astype(a.dtype.newbyteorder("<")).tobytes()
        offset = start + a.nbytes
    return bytes(header) + bytes(body)


def write_tensor_file(path, fields: Mapping[str, object]) -> None:
    """Write ``fields`` as a TensorFile, atomically."""
    atomic_write(path, tensor_file_bytes(fields))
