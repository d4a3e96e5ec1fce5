"""The exported model's metadata (ONNX ``metadata_props``): its encoding, its decoding
and a typed object.

    from neural_brdf.fileformat.metadata import Metadata
    info = Metadata.from_props({p.key: p.value for p in proto.metadata_props})
    info.max_albedo, info.target["kind"], info.sampling_lobe   # typed, JSON values only
    info.to_json()                          # one JSON object: what JavaScript decodes
    info.to_props()                         # the strings the exporter writes, in its order

The keys and their kinds are :data:`neural_brdf.fileformat.KEYS` (docs/portable.md,
"Metadata").  A value is written as strict JSON (:func:`encode`); ``onnx_metadata.js``
decodes it in a browser or in Node the way :func:`read_metadata` does in Python, and
tests/fileformat/test_portable.py checks that the two agree on every key.  Files of
metadata_version 1 (the target as a description, the config as YAML) are read too.
This module needs numpy and yaml only (and neural_brdf.errors).
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from neural_brdf.errors import InputError
from neural_brdf.fileformat import (
    FORMAT_VERSION,
    JSON_KEYS,
    KEYS,
    LOBE_KEY,
    METADATA_VERSION,
    METADATA_VERSION_KEY,
)


def encode(value: Any) -> str:
    """A metadata value as strict JSON: a non-finite number in an object or array becomes
    null (JSON has no NaN or Infinity, and JSON.parse refuses them); a non-finite number
    alone is written as Python writes it ("inf", "nan"), as files of version 1 did."""
    value = plain(value)
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    return json.dumps(_finite(value), sort_keys=True, allow_nan=False)


def plain(value: Any) -> Any:
    """``value`` with numpy scalars and arrays, tuples and paths as JSON types."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, Path):
        return str(value)
    return value


def _finite(value: Any) -> Any:
    """JSON-ready ``value`` (see :func:`plain`) with non-finite floats as None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def check_versions(values: Mapping[str, Any]) -> int:
    """The ``metadata_version`` of decoded metadata ``values`` (1 when absent), after
    checking it and ``format_version`` (when present): whole numbers, and no later than
    this reader's (a later contract's keys and graph may mean other things through the
    same names).  A one-line InputError naming the key otherwise (the caller adds the
    file)."""
    for key, known in (
        (METADATA_VERSION_KEY, METADATA_VERSION),
        ("format_version", FORMAT_VERSION),
    ):
        # absent: metadata_version 1; a format_version is refused where it matters
        # (cli._project_model)
        if key not in values:
            continue
        v = values[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise InputError(f"metadata {key}: expected a whole number >= 1, got {_shown(v)}")
        if v > known:
            raise InputError(
                f"metadata {key}: {v}, and this reader knows up to {known}: the file was "
                "written by a later neural-brdf (upgrade it)"
            )
    return values.get(METADATA_VERSION_KEY, 1)


def check_props_versions(props: Mapping[str, str]) -> None:
    """:func:`check_versions` of a file's metadata_props (strings): what a consumer of
    the graph alone (``graph.lower``: codegen, the plugins) checks on load."""
    values: dict[str, Any] = {}
    for key in (METADATA_VERSION_KEY, "format_version"):
        if key in props:
            try:
                values[key] = json.loads(props[key])
            except ValueError:
                values[key] = props[key]
    check_versions(values)


def read_metadata(props: Mapping[str, str]) -> dict[str, Any]:
    """metadata_props (strings) -> values, for files of every metadata_version.

    JSON values are parsed; ``target`` is always an object (:func:`parse_target` for
    version 1's description) and ``training_config`` a dict (version 1's YAML is read);
    ``metadata_version`` is an int, 1 when absent.  Other keys stay text, and so does a
    number a version-1 file wrote as ``inf`` or ``nan``.  A ``metadata_version`` that is
    not a whole number, or a ``training_config`` that is neither JSON nor YAML, raises a
    one-line InputError naming the key (the caller adds the file)."""
    out: dict[str, Any] = dict(props)
    for key in JSON_KEYS:
        if key in props:
            try:
                out[key] = json.loads(props[key])
            except ValueError:
                pass  # version 1 text (the target, the YAML config) or "inf"/"nan"
    out[METADATA_VERSION_KEY] = check_versions(out)
    if "target" in props and not isinstance(out["target"], dict):
        out["target"] = parse_target(props["target"])
    if "training_config" in props and not isinstance(out["training_config"], dict):
        try:
            out["training_config"] = yaml.safe_load(props["training_config"]) or {}
        except yaml.YAMLError as e:  # neither JSON (version 2) nor YAML (version 1)
            problem = str(getattr(e, "problem", "") or type(e).__name__).splitlines()[0]
            raise InputError(
                f"metadata training_config: neither JSON nor YAML ({problem[:80]}): "
                f"{_shown(props['training_config'])}"
            ) from None
    if "training_config" in props and not isinstance(out["training_config"], dict):
        raise InputError(
            f"metadata training_config: expected a mapping of config keys, got "
            f"{_shown(out['training_config'])}"
        )
    if LOBE_KEY in props:  # the samplers' contract, checked for every consumer alike
        from neural_brdf.fileformat import lobe

        lobe.parse(props[LOBE_KEY])
    return out


def _shown(value: Any) -> str:
    """A metadata value for a one-line error: its repr, at most 40 characters."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


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


def _figure(value: Any) -> float | None:
    """A figure (max_albedo, ...) as a float: JSON numbers, and version 1's "inf" text."""
    if isinstance(value, bool) or value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


@dataclasses.dataclass(frozen=True)
class Metadata:
    """An exported model's metadata, typed.  Every value is a JSON value (str, int, float,
    bool, None, list, dict), so :meth:`to_json` is one JSON object, the one JavaScript's
    ``decodeMetadata`` gives for a file of this metadata_version.  The fields are in the
    order the exporter writes them; ``other`` keeps keys this version does not know."""

    metadata_version: int = METADATA_VERSION
    format_version: int | None = None
    producer: str | None = None
    frame: str | None = None
    units: str | None = None
    encoding: str | None = None
    normalization: str | None = None
    target: dict[str, Any] | None = None
    max_albedo: float | None = None
    hemispherical_albedo: list[float] | None = None
    reciprocity_error: float | None = None
    min_value: float | None = None
    parity_rel_error: float | None = None
    float32_rel_precision: float | None = None
    training_config: dict[str, Any] | None = None
    sampling_lobe: dict[str, Any] | None = None
    texture: dict[str, Any] | None = None  # a spatially varying file's weight field
    other: dict[str, str] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_props(cls, props: Mapping[str, str]) -> Metadata:
        """The metadata_props of a file (strings), of any metadata_version."""
        d = read_metadata(props)
        lobe = d.get("sampling_lobe")
        albedo = d.get("hemispherical_albedo")
        version = d.get("format_version")
        return cls(
            metadata_version=int(d[METADATA_VERSION_KEY]),
            format_version=int(version) if isinstance(version, (int, float)) else None,
            producer=d.get("producer"),
            frame=d.get("frame"),
            units=d.get("units"),
            encoding=d.get("encoding"),
            normalization=d.get("normalization"),
            target=d.get("target"),
            max_albedo=_figure(d.get("max_albedo")),
            hemispherical_albedo=[float(v) for v in albedo] if isinstance(albedo, list) else None,
            reciprocity_error=_figure(d.get("reciprocity_error")),
            min_value=_figure(d.get("min_value")),
            parity_rel_error=_figure(d.get("parity_rel_error")),
            float32_rel_precision=_figure(d.get("float32_rel_precision")),
            training_config=d.get("training_config"),
            sampling_lobe=lobe if isinstance(lobe, dict) else None,
            texture=d.get("texture") if isinstance(d.get("texture"), dict) else None,
            other={k: v for k, v in props.items() if k not in KEYS},
        )

    def to_props(self) -> dict[str, str]:
        """The metadata_props strings, in the exporter's order: JSON keys encoded by
        :func:`encode`, text keys as they are; None fields are left out."""
        out: dict[str, str] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "other" or value is None:
                continue
            out[f.name] = encode(value) if f.name in JSON_KEYS else str(value)
        out.update(self.other)
        return out

    def to_json(self) -> dict[str, Any]:
        """One JSON object (strict: non-finite figures are null), None fields left out."""
        out = {
            f.name: _finite(plain(getattr(self, f.name)))
            for f in dataclasses.fields(self)
            if f.name != "other" and getattr(self, f.name) is not None
        }
        return {**out, **self.other}
