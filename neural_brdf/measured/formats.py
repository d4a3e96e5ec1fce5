"""The measured formats, by file suffix: the one registry that training
(``target.data``), ``validate --reference`` and ``neural-brdf bake`` read.

    from neural_brdf.measured import formats
    brdf = formats.read("gold.binary")          # a MeasuredBRDF; InputError on a bad file
    formats.bake(fn, "gold.bsdf")               # the writer the suffix names
    formats.format_of("x.exr")                  # InputError: unknown extension, the known ones

A :class:`Format` is a name, a suffix, a reader ``read(path) -> MeasuredBRDF``, a writer
``bake(fn, path)`` (``fn``: a callable f(wi, wo) on (N, 3) float64 numpy, or an object
with ``.eval``) and the error type its reader raises on a bad file.  A new format is one
:func:`register` call (docs/architecture.md, "A measured format"); MERL and RGL are
registered below.  Their readers and writers import their package on first use, so this
module stays light (numpy only: ``rgl`` never loads torch, ``merl`` does).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neural_brdf.errors import InputError
from neural_brdf.measured.base import FormatError, MeasuredBRDF

PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class Format:
    """One measured file format."""

    name: str  # "MERL", as messages and ``bake`` print it
    suffix: str  # ".binary": lower case, with the dot; matched case-insensitively
    read: Callable[[PathLike], MeasuredBRDF]  # a bad file raises ``error``
    bake: Callable[[Any, PathLike], object]  # tabulate fn(wi, wo) and write it (atomically)
    error: type[Exception] = FormatError  # what ``read`` raises on a bad file

    def __post_init__(self) -> None:
        s = self.suffix
        if not (s.startswith(".") and len(s) > 1 and s == s.lower() and "/" not in s):
            raise ValueError(f"suffix: expected a lower-case '.ext', got {s!r}")


_FORMATS: dict[str, Format] = {}


def register(fmt: Format) -> Format:
    """Add ``fmt`` to the registry; a suffix already taken raises ValueError."""
    if fmt.suffix in _FORMATS:
        raise ValueError(f"{fmt.suffix}: already the suffix of {_FORMATS[fmt.suffix].name}")
    _FORMATS[fmt.suffix] = fmt
    return fmt


def unregister(suffix: str) -> None:
    """Remove the format of ``suffix`` (a test's toy format); unknown suffixes are ignored."""
    _FORMATS.pop(suffix.lower(), None)


def all_formats() -> list[Format]:
    """Every registered format, in registration order."""
    return list(_FORMATS.values())


def known() -> str:
    """The registered suffixes with their names: ``.binary (MERL), .bsdf (RGL)``."""
    return ", ".join(f"{f.suffix} ({f.name})" for f in _FORMATS.values())


# A file whose suffix names no format is still known by these opening bytes (Mitsuba's
# tensor file: an RGL material saved as ``.pbsdf``, say).
MAGICS: dict[bytes, str] = {b"tensor_file\0": ".bsdf"}


def _by_magic(path: PathLike) -> Format | None:
    """The format whose :data:`MAGICS` ``path`` starts with; None for any other file, or
    no regular file (a FIFO is not waited on; nothing is raised)."""
    from neural_brdf import fileio

    try:
        with fileio.open_for_reading(path) as fh:
            head = fh.read(max(map(len, MAGICS), default=0))
    except (OSError, ValueError):
        return None
    for magic, suffix in MAGICS.items():
        if head.startswith(magic) and suffix in _FORMATS:
            return _FORMATS[suffix]
    return None


def find(path: PathLike) -> Format | None:
    """The format of ``path`` by its suffix, or else by its first bytes (:data:`MAGICS`:
    an RGL tensor file of another suffix), or None."""
    return _FORMATS.get(Path(path).suffix.lower()) or _by_magic(path)


def format_of(path: PathLike) -> Format:
    """The format of ``path`` by its suffix (or first bytes, :func:`find`); an unknown
    one raises a one-line InputError naming the file and the known suffixes."""
    fmt = find(path)
    if fmt is None:
        suffix = Path(path).suffix.lower() or "(none)"
        raise InputError(
            f"{path}: unknown extension {suffix!r} for measured data; known: {known()}"
        )
    return fmt


def read(path: PathLike) -> MeasuredBRDF:
    """Read ``path`` with the reader its suffix names.  Any problem (an unknown suffix, a
    bad file: the format's ``error``) raises a one-line InputError naming the file."""
    fmt = format_of(path)
    try:
        return fmt.read(path)
    except InputError:
        raise
    except fmt.error as e:
        text = " ".join(str(e).split()) or type(e).__name__
        raise InputError(text if str(path) in text else f"{path}: {text}") from None


def bake(fn: Any, path: PathLike) -> Format:
    """Tabulate ``fn`` in the format the suffix of ``path`` names and write it there;
    returns that format.  An unknown suffix raises InputError (nothing is written)."""
    fmt = format_of(path)
    fmt.bake(fn, path)
    return fmt


# ------------------------------------------------------------------ the built-ins
def _read_merl(path: PathLike) -> MeasuredBRDF:
    from neural_brdf.measured import merl

    brdf = merl.read_merl(path)
    if len(brdf.support) == 0:
        raise merl.MerlFormatError(f"{Path(path)}: no measured bins above the horizon")
    return brdf


def _bake_merl(fn: Any, path: PathLike) -> object:
    from neural_brdf.measured import merl

    return merl.bake(fn, path)


def _read_rgl(path: PathLike) -> MeasuredBRDF:
    from neural_brdf.measured import rgl

    return rgl.read_rgl(path)


def _bake_rgl(fn: Any, path: PathLike) -> object:
    from neural_brdf.measured import rgl

    return rgl.bake(fn, path)


MERL = register(Format("MERL", ".binary", _read_merl, _bake_merl))
RGL = register(Format("RGL", ".bsdf", _read_rgl, _bake_rgl))
