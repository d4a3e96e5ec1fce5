"""The preset study of docs/experiments.md: three sweeps, then tables, figures and JSON.

    python experiments/study.py                  # run (or resume) the sweeps, then analyse
    python experiments/study.py --analyse-only   # only rebuild docs/ from sweeps/*
    python experiments/study.py --executor ray   # the same trials on Ray
    python experiments/study.py --tables         # the page's tables from docs/results/*.json

Sweeps (configs/sweeps/): ``size`` (accuracy against parameter count), ``ablation``
(symmetric vs raw encoding, albedo normalisation on vs off) and ``loss`` (log_l2,
log_l1, nbrdf), each over gold, clay, phong and brushed_ggx, and ``furnace`` (the
normalisation on two targets of albedo 1), all at 1500 steps.  Writes
docs/results/<sweep>.json (one row per trial), docs/figures/<sweep>.png and the tables of
docs/experiments.md (between its ``<!-- table: NAME -->`` markers).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from neural_brdf.fileio import atomic_write  # noqa: E402
from neural_brdf.tooling import sweep  # noqa: E402

SWEEPS = ("size", "ablation", "loss", "furnace")
FIGURES = True  # False: the analyses return their tables and write no figure (--tables)
PAGE = REPO / "docs" / "experiments.md"
# a table of the page: between "<!-- table: NAME -->" and "<!-- /table -->", generated
# from docs/results/NAME.json by the analysis of that name
MARKED = re.compile(r"(<!-- table: (\w+) -->\n)(.*?)(<!-- /table -->)", re.S)
PRESETS = ("gold", "clay", "phong", "brushed_ggx")
DOCS = REPO / "docs"


def rows(name: str, out: Path) -> list[dict]:
    """One flat row per trial: preset, settings, metrics, and from the trial's own
    metrics.json the raw network's albedo before normalisation."""
    results = json.loads((out / name / "results.json").read_text())
    flat = []
    for r in results["trials"]:
        o = dict(r["overrides"])
        preset = Path(o.pop("config")).stem if "config" in o else None
        row = {
            "trial": r["trial"],
            "status": r["status"],
            "error": r["error"],
            "preset": preset,
            **o,
            **r["metrics"],
        }
        metrics = out / name / r["run_dir"] / "metrics.json"
        if r["status"] == "ok":
            m = json.loads(metrics.read_text())
            row["raw_max_albedo"] = m["export"]["normalization"].get("raw_max_albedo")
            row["nodes_above_1"] = m["export"]["normalization"].get("nodes_above_1")
            row["encoding"] = m["encoding"]
        flat.append(row)
    return flat


def write_json(name: str, data: list[dict], settings: dict) -> None:
    path = DOCS / "results" / f"{name}.json"
    text = json.dumps(
        {"sweep": f"configs/sweeps/{name}.yaml", **settings, "trials": data}, indent=2
    )
    atomic_write(path, text + "\n", parents=True)


def _save(fig, name: str) -> None:
    if FIGURES:
        fig.savefig(DOCS / "figures" / f"{name}.png", dpi=120)


def figure(ncols: int, width: float = 4.2, height: float = 3.4):
    fig = Figure(figsize=(width * ncols, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(1, ncols, squeeze=False)[0]


def pct(x) -> str:
    return "-" if x is None else f"{100 * x:.2f} %"


def table(header: list[str], body: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in body])


# ------------------------------------------------------------------ size
def size(data: list[dict]) -> str:
    fig, (ax, bx) = figure(2)
    for preset in PRESETS:
        pts = sorted(
            (r["params"], r["rel_rmse"], r["train_seconds"])
            for r in data
            if r["preset"] == preset and r["status"] == "ok"
        )
        ax.plot([p[0] for p in pts], [100 * p[1] for p in pts], "o-", label=preset)
        bx.plot([p[0] for p in pts], [p[2] for p in pts], "o-", label=preset)
    ax.axhline(2.0, color="k", ls="--", lw=0.8, label="2 % target")
    for a, label in ((ax, "rel. RMSE of f cos (%)"), (bx, "training time, 1 thread (s)")):
        a.set_xscale("log")
        a.set_yscale("log")
        a.set_xlabel("parameters")
        a.set_ylabel(label)
        a.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    _save(fig, "size")
    widths = sorted({tuple(r["model.hidden"]) for r in data}, key=lambda w: (len(w), w))
    body = []
    for w in widths:
        cells = {r["preset"]: r for r in data if tuple(r["model.hidden"]) == w}
        params = f"{cells['gold'].get('params')} / {cells['brushed_ggx'].get('params')}"
        body.append(
            ["x".join(map(str, w)), params] + [pct(cells[p].get("rel_rmse")) for p in PRESETS]
        )
    return table(["hidden", "params (isotropic / anisotropic)"] + list(PRESETS), body)


# ------------------------------------------------------------------ ablation
def _variant(r: dict) -> str:
    enc = "raw" if r.get("model.encoding") == "raw" else "symmetric"
    return f"{enc}, norm {'on' if r['normalization.enabled'] else 'off'}"


VARIANTS = ("symmetric, norm on", "symmetric, norm off", "raw, norm on", "raw, norm off")


def ablation(data: list[dict]) -> str:
    fig, axes = figure(3, width=4.6)
    panels = [
        ("reciprocity", "reciprocity error (0 = exact)", 1.0),
        ("rel_rmse", "rel. RMSE of f cos (%)", 100.0),
        ("max_albedo", "max directional albedo", 1.0),
    ]
    step = 0.8 / len(VARIANTS)
    for ax, (key, label, scale) in zip(axes, panels):
        for k, v in enumerate(VARIANTS):
            vals = [
                next(
                    (
                        scale * r[key]
                        for r in data
                        if r["preset"] == p and _variant(r) == v and r["status"] == "ok"
                    ),
                    math.nan,
                )
                for p in PRESETS
            ]
            ax.bar([i + (k - 1.5) * step for i in range(len(PRESETS))], vals, step, label=v)
        ax.set_xticks(range(len(PRESETS)), PRESETS, fontsize=8)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_yscale("symlog", linthresh=1e-6)
    axes[2].axhline(1.0, color="k", ls="--", lw=0.8)
    axes[2].set_ylim(0.4, None)
    axes[0].legend(fontsize=7)
    _save(fig, "ablation")
    body = []
    for p in PRESETS:
        for v in VARIANTS:
            r = next(r for r in data if r["preset"] == p and _variant(r) == v)
            if r["status"] != "ok":
                body.append([p, v, "failed: " + r["error"], "", "", "", ""])
                continue
            body.append(
                [
                    p,
                    v,
                    f"{r['reciprocity']:.2g}",
                    pct(r["rel_rmse"]),
                    f"{r['max_albedo']:.4f}",
                    *_table_cells(r),
                    "yes" if r["passed"] else "**no**",
                ]
            )
    return table(
        [
            "preset",
            "variant",
            "reciprocity",
            "rel. RMSE",
            "max albedo",
            "raw max albedo (table)",
            "table nodes > 1",
            "physics passed",
        ],
        body,
    )


def _table_cells(r: dict) -> list[str]:
    """The normalisation table: the raw network's quadrature albedo, nodes rescaled."""
    raw, nodes = r.get("raw_max_albedo"), r.get("nodes_above_1")
    return ["-" if raw is None else f"{raw:.4f}", "-" if nodes is None else str(nodes)]


# ------------------------------------------------------------------ loss
LOSSES = ("log_l2", "log_l1", "nbrdf")


def loss(data: list[dict]) -> str:
    """Bars: the mean over seeds; dots: each seed."""
    fig, axes = figure(2)
    step = 0.8 / len(LOSSES)
    seeds = sorted({r.get("train.seed", 0) for r in data})

    def values(p, name, key):
        return [
            r[key]
            for s in seeds
            for r in data
            if r["preset"] == p and r["train.loss"] == name and r.get("train.seed", 0) == s
        ]

    for ax, (key, label, scale) in zip(
        axes,
        [
            ("rel_rmse", "rel. RMSE of f cos (%)", 100.0),
            ("nbrdf_log_error", "NBRDF log error", 1.0),
        ],
    ):
        for k, name in enumerate(LOSSES):
            x = [i + (k - 1) * step for i in range(len(PRESETS))]
            v = [[scale * y for y in values(p, name, key)] for p in PRESETS]
            ax.bar(x, [sum(y) / len(y) for y in v], step, label=name)
            for xi, y in zip(x, v):
                ax.plot([xi] * len(y), y, "k.", ms=4)
        ax.set_xticks(range(len(PRESETS)), PRESETS, fontsize=8)
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.grid(axis="y", alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    _save(fig, "loss")
    body = []
    for p in PRESETS:
        cells = []
        for n in LOSSES:
            rel, log = values(p, n, "rel_rmse"), values(p, n, "nbrdf_log_error")
            cells.append(" / ".join(pct(v) for v in rel) + f" ({sum(log) / len(log):.2g})")
        body.append([p] + cells)
    head = [f"{n}: rel. RMSE, seed {' / '.join(map(str, seeds))} (mean log err)" for n in LOSSES]
    return table(["preset"] + head, body)


# ------------------------------------------------------------------ furnace
def _furnace_target(r: dict) -> str:
    return (
        "GGX, F = 1, multiple scattering"
        if r.get("target.model") == "microfacet"
        else "white Lambertian"
    )


def furnace(data: list[dict]) -> str:
    fig, (ax,) = figure(1, width=6.0)
    labels = sorted({(_furnace_target(r), r["train.seed"]) for r in data})
    for k, on in enumerate((True, False)):
        vals = [
            next(
                r["max_albedo"]
                for r in data
                if (_furnace_target(r), r["train.seed"]) == lab and r["normalization.enabled"] == on
            )
            for lab in labels
        ]
        ax.bar(
            [i + (k - 0.5) * 0.4 for i in range(len(labels))],
            vals,
            0.4,
            label=f"normalisation {'on' if on else 'off'}",
        )
    ax.axhline(1.001, color="k", ls="--", lw=0.8, label="limit 1 + 1e-3")
    ax.set_xticks(
        range(len(labels)),
        ["\n".join(t.split(", ") + [f"seed {s}"]) for t, s in labels],
        fontsize=7,
    )
    ax.set_ylim(0.98, 1.015)
    ax.set_ylabel("max directional albedo (validator)")
    ax.legend(fontsize=8)
    _save(fig, "furnace")
    body = []
    for r in sorted(
        data, key=lambda r: (_furnace_target(r), r["train.seed"], not r["normalization.enabled"])
    ):
        body.append(
            [
                _furnace_target(r),
                str(r["train.seed"]),
                "on" if r["normalization.enabled"] else "off",
                pct(r["rel_rmse"]),
                f"{r['max_albedo']:.4f}",
                *_table_cells(r),
                "yes" if r["passed"] else "**no**",
            ]
        )
    return table(
        [
            "target",
            "seed",
            "normalisation",
            "rel. RMSE",
            "max albedo",
            "raw max albedo (table)",
            "table nodes > 1",
            "physics passed",
        ],
        body,
    )


def tables_page(text: str) -> str:
    """docs/experiments.md with every marked table regenerated from docs/results/*.json."""
    global FIGURES
    analyses = {"size": size, "ablation": ablation, "loss": loss, "furnace": furnace}
    FIGURES, saved = False, FIGURES
    try:

        def fill(m: re.Match) -> str:
            data = json.loads((DOCS / "results" / f"{m.group(2)}.json").read_text())["trials"]
            return f"{m.group(1)}{analyses[m.group(2)](data)}\n{m.group(4)}"

        return MARKED.sub(fill, text)
    finally:
        FIGURES = saved


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--analyse-only", action="store_true")
    ap.add_argument("--executor", default="local", choices=["local", "ray"])
    ap.add_argument("--workers", type=int)
    ap.add_argument(
        "--out", default=str(REPO / "runs" / "sweeps"), help="sweep folders (default runs/sweeps/)"
    )
    ap.add_argument(
        "--tables", action="store_true", help="only rewrite the page's tables from the JSON"
    )
    ap.add_argument("--check", action="store_true", help="exit 1 if the page's tables are stale")
    args = ap.parse_args()
    if args.tables or args.check:
        text = PAGE.read_text(encoding="utf-8")
        page = tables_page(text)
        if args.check:
            if page != text:
                print("docs/experiments.md: tables are stale: python experiments/study.py --tables")
                return 1
            return 0
        PAGE.write_text(page, encoding="utf-8")
        print(f"wrote {PAGE}")
        return 0
    out = Path(args.out)
    (DOCS / "figures").mkdir(parents=True, exist_ok=True)
    for name in SWEEPS:
        if not args.analyse_only:
            sweep.run_sweep(
                REPO / "configs" / "sweeps" / f"{name}.yaml",
                executor=args.executor,
                workers=args.workers,
                out=out / name,
                progress=sweep.print_progress,
            )
    settings = {
        "train.steps": 1500,
        "train.threads": 1,
        "train.seed": "0 unless stated",
        "machine": "shared 2-core CPU, 2 trials in parallel",
    }
    for name, analyse in (
        ("size", size),
        ("ablation", ablation),
        ("loss", loss),
        ("furnace", furnace),
    ):
        data = rows(name, out)
        write_json(name, data, settings)
        print(f"\n### {name}\n\n{analyse(data)}")
    PAGE.write_text(tables_page(PAGE.read_text(encoding="utf-8")), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
