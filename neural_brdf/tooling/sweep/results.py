"""A sweep's results: results.csv, results.md and the summary figure."""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

from neural_brdf.fileio import atomic_write
from neural_brdf.tooling.sweep.spec import METRICS
from neural_brdf.tooling.sweep.trial import _write_json


# ------------------------------------------------------------------ results
def _cell(value) -> str:
    if value is None:
        return ""
    return value if isinstance(value, str) else json.dumps(value)


def write_results(
    out_dir: Path, name: str, jobs: list[dict], records: dict, *, figure: bool = False
) -> dict:
    """results.json, results.csv (and summary.png) from the records, in plan order."""
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for job in jobs:
        r = records.get(job["name"]) or {
            "trial": job["name"],
            "run_dir": job["run_dir"],
            "overrides": job["overrides"],
            "status": "pending",
            "error": None,
            "metrics": {},
        }
        rows.append({**r, "run_dir": os.path.relpath(r["run_dir"], out_dir)})
    results = {"sweep": name, "folder": str(out_dir), "trials": rows}
    _write_json(out_dir / "results.json", results)
    keys = list(dict.fromkeys(k for r in rows for k in r["overrides"]))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["trial", "status", *keys, *METRICS, "error", "run_dir"])
    for r in rows:
        w.writerow(
            [
                r["trial"],
                r["status"],
                *(_cell(r["overrides"].get(k)) for k in keys),
                *(_cell(r["metrics"].get(m)) for m in METRICS),
                r["error"] or "",
                r["run_dir"],
            ]
        )
    _write_text(out_dir / "results.csv", buf.getvalue())
    if figure:
        summary_figure(rows, out_dir / "summary.png")
    return results


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, text)


def summary_figure(rows: list[dict], path: Path) -> None:
    """Per trial: accuracy, max albedo (furnace line at 1) and reciprocity error."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = [r["trial"] for r in rows]
    fig = Figure(figsize=(13, 1.2 + 0.28 * len(rows)), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3, sharey=True)
    panels = [
        ("rel_rmse", "rel. RMSE of f cos (%)", 100.0, "linear"),
        ("max_albedo", "max directional albedo", 1.0, "linear"),
        ("reciprocity", "reciprocity error", 1.0, "symlog"),
    ]
    y = range(len(rows))
    for ax, (key, label, scale, xscale) in zip(axes, panels):
        values = [r["metrics"].get(key) for r in rows]
        ok = [isinstance(v, (int, float)) for v in values]
        ax.barh(
            [i for i, k in zip(y, ok) if k],
            [scale * v for v, k in zip(values, ok) if k],
            color="tab:blue",
        )
        for i, (r, k) in enumerate(zip(rows, ok)):
            if not k:
                ax.text(
                    0.01,
                    i,
                    r["status"],
                    va="center",
                    color="tab:red",
                    transform=ax.get_yaxis_transform(),
                )
        if key == "max_albedo":
            ax.axvline(1.0, color="k", lw=0.8, ls="--")
        if key == "reciprocity":  # mostly exact zeros: write the values
            for i, (v, k) in enumerate(zip(values, ok)):
                if k:
                    ax.text(
                        0.02,
                        i,
                        f"{v:.2g}",
                        va="center",
                        fontsize=7,
                        transform=ax.get_yaxis_transform(),
                    )
            top = max([v for v, k in zip(values, ok) if k] + [0.0])
            ax.set_xlim(0.0, max(1e-6, 10 * top))
        ax.set_xscale(xscale, **({"linthresh": 1e-7} if xscale == "symlog" else {}))
        ax.set_xlabel(label)
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(list(y), names, fontsize=7)
    axes[0].invert_yaxis()
    buf = io.BytesIO()  # written whole or not at all, as every file of a sweep
    fig.savefig(buf, format=path.suffix[1:] or "png", dpi=110)
    atomic_write(path, buf.getvalue())
