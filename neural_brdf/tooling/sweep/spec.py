"""The sweep file: its schema (pydantic), checks and the materials it names; the
constants every part of a sweep shares."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from neural_brdf import config as cfgmod

TRIAL_DEFAULTS = {"train.threads": 1, "train.progress": False}
MARKER = "trial.json"
METRICS = (
    "rel_rmse",
    "nbrdf_log_error",
    "max_albedo",
    "reciprocity",
    "min_value",
    "passed",
    "params",
    "train_seconds",
    "total_seconds",
)
MAX_SLUG = 80


class SweepError(cfgmod.ConfigError):
    """The sweep file is invalid (one line, naming the key); nothing was run."""


# ------------------------------------------------------------------ the sweep file
class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, populate_by_name=True)


class Materials(_Section):
    nbrdf: str  # NBRDF weights (.npz), relative to the file
    names: list[str] | Literal["all"] = "all"  # networks in it to train on


class SweepFile(_Section):
    name: str | None = None  # default: the file's stem
    base: str | None = None  # base config, relative to the file
    set: dict[str, Any] = Field(default_factory=dict)  # overrides for every trial
    grid: dict[str, list[Any]] = Field(default_factory=dict)  # crossed axes
    entries: list[dict[str, Any]] | dict[str, list[Any]] = Field(default_factory=list, alias="list")
    materials: Materials | None = None


def _is_config_key(key: str) -> bool:
    """Whether ``key`` (dotted) names a setting of :class:`config.Config`; anything under
    a free-form dict (``target.params.alpha``) counts."""
    node: Any = cfgmod.Config
    for part in key.split("."):
        fields = getattr(node, "model_fields", None)
        if fields is None or part not in fields:
            return False
        node = fields[part].annotation
        if getattr(node, "__origin__", None) is dict:
            return True
    return not hasattr(node, "model_fields")


def _error(source: str, err: Any) -> str:
    loc = ".".join(str(p) for p in err["loc"])
    if err["type"] == "extra_forbidden":
        return f"{source}: {loc}: unknown key"
    return f"{source}: {loc}: {err['msg']}"


def load_sweep(path: str | Path) -> SweepFile:
    """Read and check a sweep file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise SweepError(f"{path}: cannot read sweep file ({e.strerror})") from None
    raw = cfgmod.parse_yaml(text, source=str(path))
    if not isinstance(raw, dict):
        raise SweepError(f"{path}: expected a mapping of keys at the top level")
    try:
        spec = SweepFile.model_validate(raw)
    except ValidationError as e:
        raise SweepError(_error(str(path), e.errors()[0])) from None
    _check(spec, path)
    return spec


def _entries(spec: SweepFile, source: Path) -> list[dict]:
    if isinstance(spec.entries, list):
        return spec.entries
    lengths = {k: len(v) for k, v in spec.entries.items()}
    if len(set(lengths.values())) > 1:
        raise SweepError(f"{source}: list: zipped axes need equal lengths, got {lengths}")
    return [dict(zip(spec.entries, values)) for values in zip(*spec.entries.values())]


def _check(spec: SweepFile, source: Path) -> None:
    here = source.parent
    if spec.name is not None:  # the folder runs/sweeps/<name>/: one plain name, as a run's
        try:
            cfgmod.check_name(spec.name)
        except ValueError as e:
            why = str(e).replace("a run's name", "a sweep's name")
            raise SweepError(f"{source}: {why}") from None
    axes = (
        [("grid", k) for k in spec.grid]
        + [("list", k) for e in _entries(spec, source) for k in e]
        + [("set", k) for k in spec.set]
    )
    for section, key in axes:
        if key == "config" and section != "set":
            continue
        if key == "material" or not _is_config_key(key):
            raise SweepError(f"{source}: {section}.{key}: unknown config key")
    for key, values in spec.grid.items():  # crossed, an empty axis empties the sweep
        if not values:
            raise SweepError(f"{source}: grid.{key}: an empty list (no value to try)")
    if isinstance(spec.entries, dict):
        for key, values in spec.entries.items():
            if not values:
                raise SweepError(f"{source}: list.{key}: an empty list (no value to try)")
    both = set(spec.grid) & {k for e in _entries(spec, source) for k in e}
    if both:
        raise SweepError(f"{source}: {sorted(both)[0]}: in both grid and list")
    files = [("base", spec.base)] + [("config", c) for c in _axis_values(spec, source, "config")]
    for key, name in files:
        if name is not None and not (isinstance(name, str) and (here / name).is_file()):
            raise SweepError(f"{source}: {key}: no such config file {name!r}")
    if spec.materials is not None:
        _material_names(spec.materials, here, source)


def _axis_values(spec: SweepFile, source: Path, key: str) -> list:
    return spec.grid.get(key, []) + [e[key] for e in _entries(spec, source) if key in e]


def _material_names(m: Materials, here: Path, source: Path) -> list[str]:
    from neural_brdf.measured import merl

    npz = here / m.nbrdf
    if not npz.is_file():
        raise SweepError(f"{source}: materials.nbrdf: no such file {m.nbrdf!r}")
    try:
        available = merl.nbrdf_names(npz)
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise SweepError(f"{source}: materials.nbrdf: cannot read {m.nbrdf!r} ({e})") from None
    if m.names == "all":
        return available
    unknown = [n for n in m.names if n not in available]
    if unknown:
        raise SweepError(f"{source}: materials.names: {unknown[0]!r} is not in {m.nbrdf}")
    return list(m.names)
