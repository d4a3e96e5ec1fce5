"""The benchmark suite: one command, one JSON file (benchmarks/results/suite.json).

    python benchmarks/run_all.py                        # everything
    python benchmarks/run_all.py --quick                # smaller batch, 3 presets, small render
    python benchmarks/run_all.py --presets gold,lambert # a subset of configs/ for training
    python benchmarks/run_all.py --skip render,training # leave sections out
    python benchmarks/run_all.py --train-threads 1      # train on one core (shared machine)
    python benchmarks/run_all.py --table                # print the README table of suite.json

Sections, in the order they run (benchmarks/README.md says how each is measured):

    peak          fp32 matmul FLOP/s (torch.mm 2048^2) on 1 thread and on every core,
                  at the start and again at the end; the better of the two is the
                  reference of every "bound" (load only ever lowers it)
    analytic      evaluations/s of every analytic model, numpy (.eval) and torch (.f)
    neural        the default neural model in torch, onnxruntime (1 thread, all cores)
                  and Dr.Jit (the Mitsuba plugin), as a fraction of the matmul bound
    drjit         Mitsuba's built-in roughconductor and the analytic_brdf plugin,
                  evaluated in Dr.Jit like the neural plugin (its comparison)
    curves        evaluations/s against batch size, 1 to 4^10 = 1048576
    training      time (steps and seconds) to reach 2% relative RMSE of f cos per preset
    render        benchmarks/mitsuba_render.py (neural over built-in render time), run
                  as a subprocess on the quickstart model of ``training`` (ROOT/quickstart,
                  also from an earlier run; without one the script trains its own)

``summary`` holds the headline ratios, all computed from figures of this same run.
The file is written once, atomically, at the end; a section that fails is recorded as
``{"error": ...}`` and the exit code is 1.  Nothing here asserts a speed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does (neural_brdf/cli.py)

REPO = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
for p in (str(REPO), str(HERE)):  # run from a checkout without `pip install -e .`
    if p not in sys.path:
        sys.path.insert(0, p)

import analytic_throughput  # noqa: E402
import neural_presets  # noqa: E402
import neural_throughput as nt  # noqa: E402
import torch  # noqa: E402
from common import MATMUL_N, evals_per_second, write_json  # noqa: E402

from neural_brdf import config  # noqa: E402

OUT = HERE / "results" / "suite.json"
SECTIONS = ("analytic", "neural", "drjit", "curves", "training", "render")
QUICK_PRESETS = ("quickstart", "lambert", "brushed_ggx")
QUICKSTART = "quickstart"  # its model is the one rendered
PACKAGES = ("torch", "numpy", "onnx", "onnxruntime", "mitsuba", "drjit")


# ------------------------------------------------------------------ machine
def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cores_available": nt.cores(),
        "python": platform.python_version(),
        "torch_threads": torch.get_num_threads(),
        "versions": versions,
        "load_average_at_start": list(os.getloadavg()),
    }


# ------------------------------------------------------------------ sections
def section_drjit(n: int, repeats: int) -> dict:
    """The built-in and analytic BSDFs in Dr.Jit, as the neural plugin is measured."""
    import drjit_eval

    target = config.load(REPO / "configs" / f"{QUICKSTART}.yaml").target.model_dump()
    wi, wo = nt.random_pairs(n)
    rows = {}
    for name, bsdf in drjit_eval.reference_bsdfs(target).items():
        call = drjit_eval.evaluator(bsdf, wi, wo)
        first = drjit_eval.first_call_seconds(call)
        rate = evals_per_second(call, n, repeats)
        rows[name] = {"bsdf": bsdf, "first_call_s": first, "evals_per_s": rate}
        print(f"  drjit {name:15s} {rate / 1e6:8.3f} M evals/s", flush=True)
    return {"batch": n, "repeats": repeats, "target": target, **drjit_eval.info(), "bsdfs": rows}


def normalise(suite: dict, peaks: dict[int, float]) -> None:
    """Every peak-relative figure, against ``peaks`` (in place).  Contention only ever
    lowers a matmul timing, so the suite uses the best of its start and end peaks."""
    if "models" in suite.get("analytic", {}):
        an = suite["analytic"]
        analytic_throughput.normalise(an, peaks[an["torch_threads"]])
    if "rows" in suite.get("neural", {}):
        nt.normalise(suite["neural"], peaks)
    if "bsdfs" in suite.get("drjit", {}):
        peak = peaks.get(suite["drjit"]["drjit_threads"], max(peaks.values()))
        for d in suite["drjit"]["bsdfs"].values():
            d["matmul_flops_per_eval"] = peak / d["evals_per_s"]


def section_curves(repeats: int, folder: Path, drjit: bool) -> dict:
    curves = {}
    for backend, threads in nt.backends():
        if backend == "drjit" and not drjit:
            continue
        key = f"{backend}_{threads}"
        curves[key] = nt.batch_curve(backend, threads, folder, repeats=repeats)
        best = max(c["evals_per_s"] for c in curves[key])
        print(
            f"  curve {key:14s} batch 1: {curves[key][0]['evals_per_s'] / 1e3:9.2f} k/s, "
            f"max {best / 1e6:7.3f} M/s",
            flush=True,
        )
    return {
        "model": "isotropic default architecture",
        "batches": list(nt.BATCHES),
        "repeats": repeats,
        "curves": curves,
    }


def section_training(presets: list[str], root: Path, threads: int | None) -> dict:
    """Every preset in turn; one that fails is recorded (``failed``) and the rest run."""
    overrides = [] if threads is None else [f"train.threads={threads}"]
    rows, failed = {}, {}
    for name in presets:
        try:
            rows[name] = neural_presets.run_preset(name, root, overrides)
        except Exception as e:
            traceback.print_exc()
            failed[name] = f"{type(e).__name__}: {e}"
            continue
        print("  " + neural_presets.summary_line(rows[name]), flush=True)
    return {
        "target_rel_rmse": neural_presets.TARGET,
        "eval_every": neural_presets.EVAL_EVERY,
        "train_threads": threads or "preset",
        "root": str(root),
        "presets": rows,
        "failed": failed,
    }


def rendered_model(root: Path) -> Path | None:
    """The quickstart model the training section wrote (or an earlier run did); None
    lets mitsuba_render.py train its own."""
    path = root / QUICKSTART / "model.onnx"
    return path if path.is_file() else None


def section_render(model: Path | None, quick: bool) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "render.json"
        cmd = [sys.executable, str(HERE / "mitsuba_render.py"), "--out", str(out)]
        if model is not None:
            cmd += ["--model", str(model)]
        if quick:
            cmd += ["--resolution", "128", "--spp", "16", "--repeats", "3"]
        subprocess.run(cmd, check=True, cwd=REPO)
        result = json.loads(out.read_text())
    result["command"] = " ".join(Path(c).name if c == sys.executable else c for c in cmd[1:])
    return result


# ------------------------------------------------------------------ summary
def _row(neural: dict, backend: str, threads: int, encoding: str = "isotropic") -> dict | None:
    for r in neural.get("rows", []):
        if (r["backend"], r["threads"], r["encoding"]) == (backend, threads, encoding):
            return r
    return None


def summarize(suite: dict) -> dict:
    """The headline ratios, from figures of this run only."""
    out = {}
    an = suite.get("analytic", {}).get("models", {})
    neural = suite.get("neural", {})
    dj = suite.get("drjit", {}).get("bsdfs", {})
    cores = suite["machine"]["cores_available"]
    ratios = {}
    if an and neural.get("rows"):
        mf, lam = an["microfacet"], an["lambertian"]
        for backend, threads, ref, key in (
            ("torch", cores, mf, "torch"),
            ("onnxruntime", 1, mf, "numpy"),
            ("onnxruntime", cores, mf, "numpy"),
        ):
            r = _row(neural, backend, threads)
            if r:
                ratios[f"{backend}_{threads}_over_microfacet_{key}"] = (
                    r["evals_per_s"] / ref[f"{key}_evals_per_s"]
                )
                ratios[f"{backend}_{threads}_over_lambertian_{key}"] = (
                    r["evals_per_s"] / lam[f"{key}_evals_per_s"]
                )
    r = _row(neural, "drjit", cores)
    if r and dj:
        for name, ref in dj.items():
            ratios[f"drjit_over_{name}_drjit"] = r["evals_per_s"] / ref["evals_per_s"]
    out["neural_over_analytic"] = ratios
    out["fraction_of_bound"] = {
        f"{r['encoding']}_{r['backend']}_{r['threads']}": r["fraction_of_bound"]
        for r in neural.get("rows", [])
    }
    curves = {}
    for key, c in suite.get("curves", {}).get("curves", {}).items():
        rates = [p["evals_per_s"] for p in c]
        best = max(rates)
        half = next(p["batch"] for p in c if p["evals_per_s"] >= 0.5 * best)
        curves[key] = {
            "evals_per_s_at_batch_1": rates[0],
            "max_evals_per_s": best,
            "batch_at_max": c[rates.index(best)]["batch"],
            "batch_1_over_max": rates[0] / best,
            "first_batch_at_half_max": half,
        }
    out["batch_curves"] = curves
    out["time_to_target"] = {
        name: {
            k: r[k]
            for k in ("steps_to_target", "seconds_to_target", "steps", "train_s", "rel_rmse")
        }
        for name, r in suite.get("training", {}).get("presets", {}).items()
    }
    render = suite.get("render", {})
    if "ratio" in render:
        mode = render.get("ratio_mode")
        by_time = render.get("modes", {}).get(mode, {}).get("ratio", {})
        out["render_neural_over_roughconductor"] = {
            "wall_best_over_best": render["ratio"],
            "mode": mode,
            "wall_per_round": render.get("ratio_per_round"),
            **{
                f"{k}_best_over_best": v["best_over_best"]
                for k, v in by_time.items()
                if k != "wall"
            },
        }
    return out


# ------------------------------------------------------------------ table
def _m(x: float | None) -> str:
    if x is None:
        return "-"
    return f"{x / 1e6:.3g} M" if x >= 1e5 else f"{x / 1e3:.3g} k"


def table(suite: dict) -> str:
    """The README's benchmark tables (markdown) from a suite.json."""
    m = suite["machine"]
    peak = suite["peak"].get("gflops") or suite["peak"]["start_gflops"]  # older files: start
    cores = m["cores_available"]
    lines = [
        f"Measured {suite['created'][:10]} on {m['cpu']} ({cores} cores), "
        f"{'quick' if suite['quick'] else 'full'} mode; fp32 matmul peak "
        f"{peak[str(cores)]:.0f} GFLOP/s on {cores} threads, "
        f"{peak['1']:.0f} on 1; load average "
        f"{m['load_average_at_start'][0]:.1f} at the start, "
        f"{suite['load_average_at_end'][0]:.1f} at the end.",
        "",
    ]
    neural = suite.get("neural")
    if neural and "rows" in neural:
        an = suite.get("analytic", {}).get("models", {})
        lines += [
            f"**Throughput** (batch {neural['batch']:,}, evaluations/s; bound = matmul "
            f"peak / {neural['models']['isotropic']['linear_flops_per_eval']:,} FLOPs "
            "per evaluation):",
            "",
            "| model | backend | threads | evals/s | fraction of bound |",
            "|---|---|---|---|---|",
        ]
        for r in neural["rows"]:
            lines.append(
                f"| neural {r['encoding']} | {r['backend']} | {r['threads']} | "
                f"{_m(r['evals_per_s'])} | {r['fraction_of_bound']:.3f} |"
            )
        for name, d in suite.get("drjit", {}).get("bsdfs", {}).items():
            lines.append(
                f"| {name} (Mitsuba) | drjit | {suite['drjit']['drjit_threads']} | "
                f"{_m(d['evals_per_s'])} | - |"
            )
        for name in ("lambertian", "microfacet", "ashikhmin_shirley"):
            if name in an:
                for api in ("numpy", "torch"):
                    lines.append(
                        f"| analytic {name} | {api} | "
                        f"{suite['analytic']['torch_threads']} | "
                        f"{_m(an[name][f'{api}_evals_per_s'])} | - |"
                    )
        lines.append("")
    curves = suite.get("curves", {}).get("curves")
    if curves:
        keys = list(curves)
        lines += [
            "**Throughput against batch size** (evaluations/s, isotropic model):",
            "",
            "| batch | " + " | ".join(k.replace("_", ", ") + " thr" for k in keys) + " |",
            "|---" * (len(keys) + 1) + "|",
        ]
        for i, b in enumerate(suite["curves"]["batches"]):
            if i % 2 == 0:  # powers of 16 keep the table short
                lines.append(
                    f"| {b:,} | " + " | ".join(_m(curves[k][i]["evals_per_s"]) for k in keys) + " |"
                )
        lines.append("")
    train = suite.get("training", {}).get("presets")
    if train:
        lines += [
            "**Training time to 2 %** (relative RMSE of f cos on held-out pairs, "
            f"checked every {suite['training']['eval_every']} steps):",
            "",
            "| preset | steps to 2 % | seconds to 2 % | steps | train s | final rel. RMSE |",
            "|---|---|---|---|---|---|",
        ]
        for name, r in train.items():
            s = "-" if r["steps_to_target"] is None else str(r["steps_to_target"])
            t = "-" if r["seconds_to_target"] is None else f"{r['seconds_to_target']:.1f}"
            lines.append(
                f"| {name} | {s} | {t} | {r['steps']} | {r['train_s']:.0f} | "
                f"{100 * r['rel_rmse']:.2f} % |"
            )
        lines.append("")
    ren = suite.get("summary", {}).get("render_neural_over_roughconductor")
    if ren:
        spread = ren.get("wall_per_round") or {}
        lines.append(
            f"**Render time**, neural over Mitsuba's roughconductor (preview scene, "
            f"{suite['render']['resolution']}^2, {suite['render']['spp']} spp, "
            f"{ren['mode']} mode): {ren['wall_best_over_best']:.2f}x wall time, best "
            f"over best (per round {spread.get('min', 0):.2f}x to "
            f"{spread.get('max', 0):.2f}x); kernel time "
            f"{ren.get('kernel_best_over_best', float('nan')):.2f}x."
        )
    return "\n".join(lines).rstrip() + "\n"


# ------------------------------------------------------------------ main
def run(args, presets: list[str], skip: set[str]) -> tuple[dict, bool]:
    cores = nt.cores()
    batch = 1 << (18 if args.quick else 20)
    repeats = 2 if args.quick else 3
    suite = {
        "benchmark": "suite",
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(["benchmarks/run_all.py"] + sys.argv[1:]),
        "quick": args.quick,
        "batch": batch,
        "repeats": repeats,
        "statistic": "best of repeats after a warm-up call; small batches timed in "
        "blocks of >= 20 ms",
        "machine": machine_info(),
    }
    threads = sorted({1, cores})
    peaks = nt.measure_peaks(threads, repeats + 2)
    suite["peak"] = {
        "matmul": f"torch.mm {MATMUL_N}x{MATMUL_N} float32",
        "start_gflops": {str(t): p / 1e9 for t, p in peaks.items()},
    }
    print(f"matmul peak: {suite['peak']['start_gflops']} GFLOP/s", flush=True)
    ok = True
    root = Path(args.root)
    with tempfile.TemporaryDirectory() as tmp:
        steps = {
            "analytic": lambda: analytic_throughput.measure(batch, repeats, peaks[cores]),
            "neural": lambda: nt.measure(
                batch, repeats, peaks, Path(tmp), drjit="drjit" not in skip
            ),
            "drjit": lambda: section_drjit(batch, repeats),
            "curves": lambda: section_curves(repeats, Path(tmp), "drjit" not in skip),
            "training": lambda: section_training(presets, root, args.train_threads),
            "render": lambda: section_render(rendered_model(root), args.quick),
        }
        for name in SECTIONS:
            if name in skip:
                continue
            print(f"[{name}]", flush=True)
            t0 = time.perf_counter()
            try:
                suite[name] = steps[name]()
                ok = ok and not suite[name].get("failed")
            except Exception as e:  # record, and go on with the other sections
                traceback.print_exc()
                suite[name] = {"error": f"{type(e).__name__}: {e}"}
                ok = False
            suite.setdefault("section_seconds", {})[name] = time.perf_counter() - t0
    end = nt.measure_peaks(threads, repeats + 2)
    suite["peak"]["end_gflops"] = {str(t): p / 1e9 for t, p in end.items()}
    best = {t: max(peaks[t], end[t]) for t in threads}
    suite["peak"]["gflops"] = {str(t): p / 1e9 for t, p in best.items()}
    normalise(suite, best)
    suite["skipped"] = sorted(skip)
    suite["load_average_at_end"] = list(os.getloadavg())
    suite["summary"] = summarize(suite)
    return suite, ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"batch 2^18, 2 repeats, presets {','.join(QUICK_PRESETS)}, a "
        "128^2 16 spp render (3 rounds)",
    )
    ap.add_argument("--presets", help="comma-separated names in configs/ (default: all)")
    ap.add_argument("--skip", default="", help=f"comma-separated sections: {','.join(SECTIONS)}")
    ap.add_argument(
        "--train-threads",
        type=int,
        metavar="N",
        help="train.threads for every preset (default: each preset's own, 1)",
    )
    ap.add_argument(
        "--root",
        default=str(REPO / "runs" / "bench"),
        help="where the presets are trained (default: runs/bench)",
    )
    ap.add_argument("--out", type=Path, default=OUT, help="the JSON file (default: %(default)s)")
    ap.add_argument(
        "--table",
        action="store_true",
        help="print the markdown tables of an existing --out file and exit",
    )
    args = ap.parse_args(argv)
    if args.table:
        if not args.out.is_file():
            print(f"error: {args.out}: no such file (run the suite first)", file=sys.stderr)
            return 2
        print(table(json.loads(args.out.read_text())), end="")
        return 0
    presets = (
        args.presets.split(",")
        if args.presets
        else list(QUICK_PRESETS)
        if args.quick
        else neural_presets.preset_names()
    )
    skip = set(filter(None, args.skip.split(",")))
    unknown = sorted(set(presets) - set(neural_presets.preset_names()))
    bad = (
        f"--presets: unknown {unknown} (see configs/)"
        if unknown
        else f"--skip: unknown {sorted(skip - set(SECTIONS))} (sections: {','.join(SECTIONS)})"
        if skip - set(SECTIONS)
        else "--train-threads: must be >= 1"
        if args.train_threads is not None and args.train_threads < 1
        else None
    )
    if bad:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    suite, ok = run(args, presets, skip)
    write_json(args.out, suite)
    print(table(suite), end="")
    print(f"wrote {args.out}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
