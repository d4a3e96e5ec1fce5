"""Planning trials: the grid's points, their names and overrides, one job per trial."""

from __future__ import annotations

import hashlib
import itertools
import json
import re
from pathlib import Path

from neural_brdf import config as cfgmod
from neural_brdf.measured import formats
from neural_brdf.tooling.sweep.spec import (
    MAX_SLUG,
    TRIAL_DEFAULTS,
    SweepError,
    SweepFile,
    _entries,
    _material_names,
)


# ------------------------------------------------------------------ planning trials
def _fmt(value) -> str:
    if isinstance(value, list):
        return "x".join(_fmt(v) for v in value)
    if isinstance(value, dict):
        return "_".join(f"{k}-{_fmt(v)}" for k, v in value.items())
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def _slug(overrides: dict) -> str:
    parts = []
    for key, value in overrides.items():
        if key == "config":
            parts.append(Path(value).stem)
        elif key == "material":
            parts.append(value)
        else:
            parts.append(f"{key.split('.')[-1]}-{_fmt(value)}")
    return re.sub(r"[^A-Za-z0-9._+=-]+", "-", "_".join(parts)) or "trial"


def _digest(overrides: dict) -> str:
    return hashlib.sha1(json.dumps(overrides, sort_keys=True).encode()).hexdigest()[:6]


def _names(points: list[dict]) -> list[str]:
    """Readable, stable run-directory names; a short hash only where needed."""
    slugs = [_slug(p) for p in points]
    taken = {s: slugs.count(s) for s in slugs}
    return [
        s if len(s) <= MAX_SLUG and taken[s] == 1 else f"{s[:MAX_SLUG]}-{_digest(p)}"
        for s, p in zip(slugs, points)
    ]


def _points(spec: SweepFile, source: Path) -> list[dict]:
    grid = dict(spec.grid)
    if spec.materials is not None:
        grid = {"material": _material_names(spec.materials, source.parent, source), **grid}
    crossed = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
    points = [{**e, **g} for e in (_entries(spec, source) or [{}]) for g in crossed]
    first = ("config", "material")  # these lead the names
    return [
        {**{k: p[k] for k in first if k in p}, **{k: v for k, v in p.items() if k not in first}}
        for p in points
    ]


def _override(raw: dict, key: str, value) -> None:
    cfgmod.apply_override(raw, f"{key}={json.dumps(value)}")  # JSON is YAML


def plan(spec: SweepFile, source: Path, out_dir: Path) -> list[dict]:
    """One job per trial: name, run_dir, overrides, and its resolved config (or the
    ConfigError that its values raise)."""
    here = source.parent
    points = _points(spec, source)
    keys = [json.dumps(p, sort_keys=True) for p in points]
    for point, key in zip(points, keys):
        if keys.count(key) > 1:
            raise SweepError(
                f"{source}: the trial {_slug(point)!r} appears {keys.count(key)} times"
            )
    jobs = []
    for name, point in zip(_names(points), points):
        base = point.get("config", spec.base)
        raw = (cfgmod.parse_yaml((here / base).read_text(), source=base) if base else None) or {}
        if not isinstance(raw, dict):
            raise SweepError(f"{source}: {base}: expected a mapping of config keys")
        if base:  # its paths are relative to its own folder
            cfgmod.paths_relative_to(raw, (here / base).parent)
        raw["name"] = name
        job = {
            "name": name,
            "run_dir": str((out_dir / "trials" / name).resolve()),
            "overrides": point,
            "config": None,
            "error": None,
            "materialise": None,
        }
        for key, value in {**TRIAL_DEFAULTS, **spec.set}.items():
            _override(raw, key, value)
        for key, value in point.items():
            if key == "material" and spec.materials is not None:  # a "materials" sweep
                # the NBRDF network baked to a MERL file (trial._materialise)
                data = (out_dir / "data" / f"{value}{formats.MERL.suffix}").resolve()
                job["materialise"] = {
                    "npz": str((here / spec.materials.nbrdf).resolve()),
                    "name": value,
                    "path": str(data),
                }
                raw["target"] = {"data": str(data)}  # replaces an analytic target
            elif key != "config":
                _override(raw, key, value)
        cfgmod.paths_relative_to(raw, here)  # a path set by the sweep: the sweep file's folder
        try:
            job["config"] = cfgmod.from_dict(raw, source=f"trial {name}").model_dump()
        except cfgmod.ConfigError as e:
            job["error"] = f"ConfigError: {e}"
        jobs.append(job)
    return jobs
