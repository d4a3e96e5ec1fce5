"""Training speed (issue 21): the project's loop against minimal loops of the same shapes,
and the phases of ``neural-brdf train`` (start, train, export, validate, report).

    python benchmarks/training_speed.py                 # quickstart, gold, mlp/gold
    python benchmarks/training_speed.py gold --repeats 5 --steps 1000
    python benchmarks/training_speed.py gold --device cuda   # every loop and CLI run on the GPU

Loops, all on the same thread count (``train.threads`` of the preset), timed in one run,
interleaved (project, model-only, plain MLP; again), the best of ``--repeats``:

* ``project``: :func:`neural_brdf.train.loop.train` for ``--steps`` steps: the pair pool and
  its refresh from the analytic target, the loss, fused Adam, the CSV log, held-out
  errors and checkpoints as configured (``train.seconds`` of the run: its loop, not the
  process start or the target's first pool);
* ``model_only``: the same RawBRDF, loss and fused Adam on batches sliced from one
  pre-drawn tensor of pairs: what the loop would cost with free data and no bookkeeping;
* ``plain_mlp``: ``nn.Sequential`` of the same layer widths (the encoding's and grids'
  feature count in, 3 out, the preset's activation) with an MSE loss and fused Adam on a
  fixed random batch: the minimal torch loop of the same shapes, without the encoding,
  the grids' gathers or the log loss.

Many materials (``--many K``): K variants of configs/gold.yaml (conductor and roughness
varied, seeds apart) trained for ``--steps`` steps one after the other with
``train.train`` and together with ``neural_brdf.train.many.train_many``, interleaved, best of
``--repeats``; materials per minute of each and the held-out errors of both.

Phases: ``neural-brdf train PRESET`` in a fresh process (``--phases`` times, the best
total), its ``metrics.json`` ``seconds`` and the process's wall time; "start" is the
wall time minus the run's own total (interpreter, imports, config).

Results: ``benchmarks/results/training_speed.json`` (a table in docs/results.md).
The machine's load is recorded at the start and the end: on the shared 2-core machine a
busy second core changes the figures.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))

from common import write_json  # noqa: E402

from neural_brdf import config, presets  # noqa: E402
from neural_brdf.train import (  # noqa: E402
    data,
    loop,  # noqa: E402
    many,
)
from neural_brdf.train import encoding as enc  # noqa: E402
from neural_brdf.train.model import ACTIVATIONS, RawBRDF  # noqa: E402

OUT = REPO / "benchmarks" / "results" / "training_speed.json"
PRESETS = ("quickstart", "gold", "mlp/gold")


def project_loop(cfg: config.Config, folder: Path) -> float:
    """Seconds per step of train.train (its own clock: the loop, not the first pool)."""
    run_dir = folder / "project"
    shutil.rmtree(run_dir, ignore_errors=True)
    _, fig = loop.train(cfg, run_dir)
    return fig["train_seconds"] / fig["steps"]


def _sync(device: torch.device | None) -> None:
    """Wait for the GPU's queued work (timers read host time); nothing on the CPU."""
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed_steps(step, steps: int, device: torch.device | None = None) -> float:
    for _ in range(min(20, steps)):  # warm-up: allocator, first-call dispatch
        step()
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    _sync(device)
    return (time.perf_counter() - t0) / steps


def model_only_loop(cfg: config.Config, steps: int) -> float:
    """Seconds per step of the same model, loss and optimizer on pre-drawn pairs."""
    t, d = cfg.train, cfg.data
    dev = loop.resolve_device(t.device)
    target = data.build_target(cfg.target)
    gen = torch.Generator().manual_seed(t.seed)
    wi, wo, f = (x.to(dev) for x in data.pair_source(target, d, gen).draw(d.pool_size))
    raw = RawBRDF.from_config(cfg.model).to(dev)
    opt = torch.optim.Adam(raw.parameters(), lr=t.lr, fused=True)
    order = torch.randperm(d.pool_size, generator=gen).to(dev)
    state = {"k": 0}

    def step():
        k = state["k"]
        if k + d.batch_size > d.pool_size:
            k = 0
        idx = order[k : k + d.batch_size]
        state["k"] = k + d.batch_size
        a, b, y = wi[idx], wo[idx], f[idx]
        loss = loop.loss_fn(t.loss, raw(a, b), y, b[:, 2:3], t.loss_eps, t.peak_weight, t.peak_cap)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return _timed_steps(step, steps, dev)


def plain_mlp_loop(cfg: config.Config, steps: int) -> float:
    """Seconds per step of nn.Sequential of the same widths, MSE, fused Adam."""
    m = cfg.model
    n_in = (
        enc.num_features(m.encoding)
        + (m.grid.channels if m.grid.size else 0)
        + (m.cosine_grid.channels if m.cosine_grid.size else 0)
    )
    layers, width = [], n_in
    for h in m.hidden:
        layers += [torch.nn.Linear(width, h), ACTIVATIONS[m.activation]()]
        width = h
    dev = loop.resolve_device(cfg.train.device)
    net = torch.nn.Sequential(*layers, torch.nn.Linear(width, 3)).to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.train.lr, fused=True)
    x = torch.rand(cfg.data.batch_size, n_in).to(dev)
    y = torch.rand(cfg.data.batch_size, 3).to(dev)

    def step():
        loss = torch.nn.functional.mse_loss(net(x), y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return _timed_steps(step, steps, dev)


def phases(preset: str, folder: Path, device: str = "cpu") -> dict:
    """``neural-brdf train PRESET`` in a fresh process: its seconds and wall time."""
    run_dir = folder / "phases"
    shutil.rmtree(run_dir, ignore_errors=True)
    cmd = [sys.executable, "-m", "neural_brdf", "train", preset, "--out", str(run_dir)]
    cmd += ["--set", "train.progress=false", "--set", f"train.device={device}"]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, cwd=folder)
    wall = time.perf_counter() - t0
    m = json.loads((run_dir / "metrics.json").read_text())
    s = m["seconds"]
    return {
        "wall": wall,
        "start": wall - s["total"],
        **{k: s[k] for k in ("train", "export", "validate", "report", "total")},
        "rel_rmse": m["accuracy"]["rel_rmse"],
        "peak_error": (m.get("peak") or {}).get("value"),
        "passed": m["passed"],
    }


def measure(preset: str, steps: int, repeats: int, n_phases: int, device: str = "cpu") -> dict:
    base = config.load(presets.resolve(preset), ["train.progress=false"])
    t = base.train
    cfg = config.load(
        presets.resolve(preset),
        [
            "train.progress=false",
            f"train.steps={steps}",
            # the preset's bookkeeping, scaled to the shorter run
            f"train.checkpoint_every={max(1, t.checkpoint_every * steps // t.steps)}",
            f"train.eval_every={max(1, t.eval_every * steps // t.steps)}",
            f"train.device={device}",
        ],
    )
    torch.set_num_threads(cfg.train.threads)
    best = {"project": math.inf, "model_only": math.inf, "plain_mlp": math.inf}
    with tempfile.TemporaryDirectory(prefix="nbrdf-speed-") as tmp:
        folder = Path(tmp)
        for _ in range(repeats):  # interleaved
            best["project"] = min(best["project"], project_loop(cfg, folder))
            best["model_only"] = min(best["model_only"], model_only_loop(cfg, steps))
            best["plain_mlp"] = min(best["plain_mlp"], plain_mlp_loop(cfg, steps))
        runs = [phases(preset, folder, device) for _ in range(n_phases)]
    ms = {k: 1e3 * v for k, v in best.items()}
    return {
        "preset": preset,
        "device": str(loop.resolve_device(cfg.train.device)),
        "threads": cfg.train.threads,
        "batch_size": cfg.data.batch_size,
        "hidden": cfg.model.hidden,
        "grid": cfg.model.grid.size,
        "preset_steps": base.train.steps,
        "timed_steps": steps,
        "ms_per_step": ms,
        "steps_per_s": {k: 1e3 / v for k, v in ms.items()},
        "project_vs_model_only": ms["project"] / ms["model_only"],
        "project_vs_plain_mlp": ms["project"] / ms["plain_mlp"],
        "phases_best": min(runs, key=lambda r: r["total"]),
        "phases_all_wall": [r["wall"] for r in runs],
    }


MANY_METALS = ("Au", "Cu", "Al", "Ag")
MANY_ALPHAS = (0.2, 0.4)


def measure_many(k: int, steps: int, repeats: int, device: str = "cpu") -> dict:
    """K gold-recipe materials: one after the other, and in one batch."""
    combos = [(m, a) for a in MANY_ALPHAS for m in MANY_METALS]
    cfgs = [
        config.load(
            presets.resolve("gold"),
            [
                "train.progress=false",
                f"train.steps={steps}",
                "train.eval_every=0",
                f"target.params.material={combos[i % len(combos)][0]}",
                f"target.params.alpha={combos[i % len(combos)][1]}",
                f"train.seed={i}",
                f"name=m{i}",
                f"train.device={device}",
            ],
        )
        for i in range(k)
    ]
    torch.set_num_threads(cfgs[0].train.threads)
    best = {"sequential": math.inf, "batched": math.inf}
    errors: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory(prefix="nbrdf-many-") as tmp:
        folder = Path(tmp)
        for r in range(repeats):
            t0 = time.perf_counter()
            alone = [loop.train(c, folder / f"s{r}" / c.name)[1] for c in cfgs]
            best["sequential"] = min(best["sequential"], time.perf_counter() - t0)
            t0 = time.perf_counter()
            together = many.train_many(cfgs, [folder / f"b{r}" / c.name for c in cfgs])
            best["batched"] = min(best["batched"], time.perf_counter() - t0)
            errors = {
                "sequential": [f["raw_val_rel_rmse"] for f in alone],
                "batched": [f["raw_val_rel_rmse"] for _, f in together],
            }
    return {
        "materials": k,
        "device": str(loop.resolve_device(cfgs[0].train.device)),
        "steps": steps,
        "batch_size": cfgs[0].data.batch_size,
        "seconds": best,
        "materials_per_minute": {key: 60.0 * k / v for key, v in best.items()},
        "speedup": best["sequential"] / best["batched"],
        "raw_val_rel_rmse": errors,
        "max_error_difference": max(
            abs(a - b) for a, b in zip(errors["sequential"], errors["batched"])
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("presets", nargs="*", default=list(PRESETS))
    ap.add_argument("--steps", type=int, default=1000, help="steps per timed loop")
    ap.add_argument("--repeats", type=int, default=3, help="interleaved rounds (best of)")
    ap.add_argument("--phases", type=int, default=2, help="CLI runs per preset (best of)")
    ap.add_argument("--many", type=int, default=8, help="materials of the batch (0: skip)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument(
        "--device", default="cpu", choices=("cpu", "cuda", "auto"), help="train.device of all"
    )
    args = ap.parse_args()
    load_start = os.getloadavg()
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    models = result.setdefault("presets", {})
    for name in args.presets:
        print(f"{name}:", flush=True)
        models[name] = measure(name, args.steps, args.repeats, args.phases, args.device)
        r = models[name]
        print(
            f"  project {r['ms_per_step']['project']:.2f} ms/step, model only "
            f"{r['ms_per_step']['model_only']:.2f}, plain MLP {r['ms_per_step']['plain_mlp']:.2f}"
            f"; CLI total {r['phases_best']['wall']:.1f} s",
            flush=True,
        )
    if args.many:
        print(f"many: {args.many} materials", flush=True)
        result["many"] = measure_many(args.many, args.steps, args.repeats, args.device)
        r = result["many"]
        print(
            f"  sequential {r['seconds']['sequential']:.1f} s, batched "
            f"{r['seconds']['batched']:.1f} s ({r['speedup']:.2f}x)",
            flush=True,
        )
    result.update(
        {
            "benchmark": "training_speed",
            "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "machine": (
                f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
                f"torch {torch.__version__}"
            ),
            "load": {"start": load_start[0], "end": os.getloadavg()[0]},
            "method": (
                "per preset: the project's loop, the model-only loop and the plain-MLP "
                "loop interleaved, best of the repeats; the CLI run best of --phases"
            ),
        }
    )
    write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
