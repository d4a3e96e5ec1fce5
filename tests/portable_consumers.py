"""Every consumer of an exported file, driven from here (issue 23, docs/portable.md).

Each consumer runs in its own process through one protocol (tests/portable_eval.py,
tests/js/ort_web_eval.mjs): the same input cases, written as float32 files, go to

    onnxruntime       the newest, this interpreter's (the reference of every figure)
    onnxruntime-1.18  the oldest release pyproject allows, in the venv .venv-ort-old
    onnxruntime-web   its wasm back end under Node, installed in tests/js
    onnx2torch        the file converted to a torch module
    reference         onnx's ReferenceEvaluator

and :func:`measure` reduces what came back to the figures of benchmarks/results/
portable.json: per consumer its version, the largest relative difference from the newest
onnxruntime (neural_brdf.export.relative_difference), and whether the empty batch, the
hostile rows and bit-exact reciprocity held.  A consumer that is not installed raises
:class:`ConsumerMissing` with the command that installs it (bash .ci/run runs them all);
nothing is skipped.  Used by tests/fileformat/test_portable.py and benchmarks/portable.py.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from neural_brdf import export
from neural_brdf.fileformat import portable

REPO = Path(__file__).resolve().parents[1]
EVAL = REPO / "tests" / "portable_eval.py"
JS = REPO / "tests" / "js"
OLD_VENV = REPO / ".venv-ort-old"
OLD_PYTHON = OLD_VENV / "bin" / "python"
OLD_ORT = "1.18.1"  # the oldest onnxruntime pyproject.toml allows (onnxruntime>=1.18)
ONNX2TORCH = "1.5.15"

INSTALL = {
    "onnxruntime-1.18": (
        f"python3 -m venv .venv-ort-old && .venv-ort-old/bin/pip install "
        f"onnxruntime=={OLD_ORT} 'numpy<2'"
    ),
    "onnxruntime-web": "cd tests/js && ONNXRUNTIME_NODE_INSTALL=skip npm ci",
    "onnx2torch": f"pip install --no-deps onnx2torch=={ONNX2TORCH}",
}
CONSUMERS = ("onnxruntime-1.18", "onnxruntime-web", "onnx2torch", "reference")

HOSTILE = {
    "nan": [np.nan, 0.2, 0.9],
    "inf": [np.inf, 0.0, 1.0],
    "-inf": [0.1, -np.inf, 0.5],
    "inf_z": [0.0, 0.0, np.inf],
    "zero": [0.0, 0.0, 0.0],
    "all_nan": [np.nan, np.nan, np.nan],
}


GRAPHS = ("isotropic", "anisotropic", "grids")  # random_model's kinds


def random_raw(kind: str):
    """A network with random weights, bright (so that the albedo table is in the graph):
    ``isotropic`` or ``anisotropic`` 16-16 SiLU, or ``grids``, the compact recipe's look-ups
    (a 9 x 9 feature grid and a 5 x 5 cosine grid before a 16-wide layer)."""
    import torch

    from neural_brdf.train.model import RawBRDF

    torch.manual_seed(3)
    if kind == "grids":
        raw = RawBRDF("isotropic", [16], "silu", init_value=3.0, grid_size=9, cosine_grid_size=5)
        with torch.no_grad():
            raw.grid.table.normal_(0.0, 1.0)
            raw.cos_grid.table.normal_(0.0, 1.0)
    else:
        raw = RawBRDF(kind, [16, 16], "silu", init_value=3.0)
    with torch.no_grad():
        for p in raw.mlp.body.parameters():
            p.mul_(3.0)
    return raw.eval()


def random_model(kind: str):
    """:func:`random_raw` normalised by its albedo table (active: some node exceeds 1) and
    made total: the graph ``neural_brdf.export`` writes."""
    from neural_brdf.train.model import NormalizedBRDF, TotalBRDF, albedo_table

    raw = random_raw(kind)
    aniso = raw.anisotropic
    table, _, _ = albedo_table(
        raw,
        size=9 if aniso else 16,
        anisotropic=aniso,
        samples=256,
        seed=0,
        sigmas=3.0,
        margin=1e-3,
    )
    if not float(table.max()) > 1.0:
        raise AssertionError("the albedo table should divide (a bright network)")
    return TotalBRDF(NormalizedBRDF(raw, table).eval())


class ConsumerMissing(RuntimeError):
    """A consumer is not installed; the message says how to install it."""


def check_installed(consumer: str) -> None:
    """Raise :class:`ConsumerMissing` (with the install command) unless ``consumer`` runs."""
    how = f"install it with: {INSTALL.get(consumer, '')} (bash .ci/run does)"
    if consumer == "onnxruntime-1.18":
        if not OLD_PYTHON.is_file():
            raise ConsumerMissing(f"no {OLD_VENV.name} venv for onnxruntime {OLD_ORT}: {how}")
        got = subprocess.run(
            [str(OLD_PYTHON), "-c", "import onnxruntime; print(onnxruntime.__version__)"],
            capture_output=True,
            text=True,
        )
        if got.returncode or got.stdout.strip() != OLD_ORT:
            raise ConsumerMissing(
                f"{OLD_VENV.name} has no onnxruntime {OLD_ORT} "
                f"({(got.stdout + got.stderr).strip()[-200:]}): {how}"
            )
    elif consumer == "onnxruntime-web":
        if shutil.which("node") is None:
            raise ConsumerMissing("node is not installed (apt-get install nodejs)")
        if not (JS / "node_modules" / "onnxruntime-web" / "package.json").is_file():
            raise ConsumerMissing(f"onnxruntime-web is not installed in tests/js: {how}")
    elif consumer == "onnx2torch":
        import importlib.util

        if importlib.util.find_spec("onnx2torch") is None:
            raise ConsumerMissing(f"onnx2torch is not installed: {how}")


def cases(n: int = 20_000, seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The inputs every consumer gets: ``random`` (directions anywhere on the sphere at
    random lengths, so below-horizon and unnormalised rows are in), ``hostile`` (the same
    with every HOSTILE row on wi, on wo and on both, at known rows), ``swapped`` (random
    with wi and wo exchanged), ``one`` (its first row) and ``empty`` (0 rows)."""
    rng = np.random.default_rng(seed)
    wi = rng.normal(size=(n, 3)) * rng.uniform(0.1, 10.0, size=(n, 1))
    wo = rng.normal(size=(n, 3)) * rng.uniform(0.1, 10.0, size=(n, 1))
    wi[: n // 2, 2] = np.abs(wi[: n // 2, 2])  # half the rows above the horizon on both
    wo[: n // 2, 2] = np.abs(wo[: n // 2, 2])
    wi, wo = wi.astype(np.float32), wo.astype(np.float32)
    hi, ho = wi.copy(), wo.copy()
    for k, v in enumerate(HOSTILE.values()):
        for side, row in enumerate(hostile_rows(k, n)):
            if side in (0, 2):
                hi[row] = v
            if side in (1, 2):
                ho[row] = v
    empty = np.zeros((0, 3), np.float32)
    return {
        "random": (wi, wo),
        "hostile": (hi, ho),
        "swapped": (wo, wi),
        "one": (wi[:1], wo[:1]),
        "empty": (empty, empty),
    }


def hostile_rows(k: int, n: int) -> tuple[int, int, int]:
    """The rows of an ``n``-row ``hostile`` case that get HOSTILE value k on wi, on wo and
    on both: spread over the batch (first rows, middle, last rows)."""
    return (1 + 7 * k, n // 2 + 7 * k, n - 50 + 7 * k)


def all_hostile_rows(n: int) -> list[int]:
    return sorted(r for k in range(len(HOSTILE)) for r in hostile_rows(k, n))


def run(consumer: str, model: str | Path, inputs: dict) -> dict:
    """{"version", "cases": {name: float32 (n, 3) array, or the error message}} of one
    consumer on ``inputs`` (as :func:`cases` gives)."""
    if consumer != "onnxruntime":
        check_installed(consumer)
    with tempfile.TemporaryDirectory(prefix="nbrdf-portable-") as tmp:
        folder = Path(tmp)
        for name, (wi, wo) in inputs.items():
            np.ascontiguousarray(wi, "<f4").tofile(folder / f"{name}.wi.f32")
            np.ascontiguousarray(wo, "<f4").tofile(folder / f"{name}.wo.f32")
        listing = [{"name": k, "n": int(len(v[0]))} for k, v in inputs.items()]
        (folder / "cases.json").write_text(json.dumps(listing))
        if consumer == "onnxruntime-web":
            cmd = ["node", str(JS / "ort_web_eval.mjs"), str(model), str(folder)]
        else:
            python = OLD_PYTHON if consumer == "onnxruntime-1.18" else Path(sys.executable)
            kind = "onnxruntime" if consumer.startswith("onnxruntime") else consumer
            cmd = [str(python), str(EVAL), kind, str(model), str(folder)]
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=600)
        if done.returncode or not (folder / "results.json").is_file():
            raise RuntimeError(
                f"{consumer} on {model}: exit {done.returncode}: "
                f"{(done.stdout + done.stderr).strip()[-1500:]}"
            )
        results = json.loads((folder / "results.json").read_text())
        out = {}
        for name, r in results["cases"].items():
            if "error" in r:
                out[name] = r["error"]
            else:
                out[name] = np.fromfile(folder / f"{name}.f.f32", dtype="<f4").reshape(r["dims"])
        return {"version": results["version"], "cases": out}


def figures(got: dict, ref: dict) -> dict:
    """The figures of one consumer's results ``got`` against the newest onnxruntime's."""
    c, r = got["cases"], ref["cases"]
    errors = {k: v for k, v in c.items() if isinstance(v, str)}
    out: dict = {"version": got["version"], "errors": errors}
    if "random" in errors:
        return out
    out["max_rel_diff"] = export.relative_difference(
        c["random"].astype(np.float64), r["random"].astype(np.float64)
    )
    out["empty_batch"] = not isinstance(c["empty"], str) and c["empty"].shape == (0, 3)
    out["one_row"] = not isinstance(c["one"], str) and c["one"].shape == (1, 3)
    if not isinstance(c["hostile"], str):
        bad = all_hostile_rows(len(c["hostile"]))
        keep = np.ones(len(c["hostile"]), bool)
        keep[bad] = False
        out["hostile_rows_zero"] = bool(np.array_equal(c["hostile"][bad], np.zeros((len(bad), 3))))
        out["other_rows_unchanged"] = bool(np.array_equal(c["hostile"][keep], c["random"][keep]))
    out["finite"] = bool(np.isfinite(c["random"]).all())
    if not isinstance(c["swapped"], str):
        out["reciprocity_bit_exact"] = bool(np.array_equal(c["swapped"], c["random"]))
        out["reciprocity_max_rel"] = export.relative_difference(
            c["swapped"].astype(np.float64), c["random"].astype(np.float64)
        )
    return out


def passed(fig: dict) -> bool:
    """Every case ran and held: empty batch, hostile rows, the other rows, finiteness."""
    return not fig["errors"] and all(
        fig.get(k) is True
        for k in ("empty_batch", "one_row", "hostile_rows_zero", "other_rows_unchanged", "finite")
    )


def measure(model: str | Path, consumers=CONSUMERS, n: int = 20_000) -> dict:
    """{"onnxruntime": {version, ...}, consumer: figures, ...} for one file."""
    inputs = cases(n)
    ref = run("onnxruntime", model, inputs)
    out = {"onnxruntime": figures(ref, ref)}
    for consumer in consumers:
        out[consumer] = figures(run(consumer, model, inputs), ref)
    return out


def opset_figures(model: str | Path, opsets=(13, 14, 15, 18, 21), n: int = 4096) -> dict:
    """{opset: {"check_model": True, "onnxruntime": max rel diff, "onnxruntime-1.18": ...}}
    of :func:`neural_brdf.fileformat.portable.convert_opset` of ``model`` to each opset
    (1.18 runs opsets up to 21)."""
    import onnx

    inputs = {k: v for k, v in cases(n).items() if k in ("random", "empty")}
    ref = run("onnxruntime", model, inputs)["cases"]["random"].astype(np.float64)
    out = {}
    with tempfile.TemporaryDirectory(prefix="nbrdf-opset-") as tmp:
        for opset in opsets:
            path = Path(tmp) / f"opset{opset}.onnx"
            onnx.save(portable.convert_opset(model, opset), path)
            row: dict = {"check_model": True}
            for consumer in ("onnxruntime", "onnxruntime-1.18"):
                if consumer == "onnxruntime-1.18" and opset > 21:
                    continue
                got = run(consumer, path, inputs)["cases"]
                row[consumer] = (
                    got["random"]
                    if isinstance(got["random"], str)
                    else export.relative_difference(got["random"].astype(np.float64), ref)
                )
                row[f"{consumer} empty batch"] = not isinstance(got["empty"], str)
            out[str(opset)] = row
    return out


def read_metadata_js(*paths) -> list[dict]:
    """[{"props", "decoded"}] of each file, read in Node by
    neural_brdf/fileformat/onnx_metadata.js."""
    if shutil.which("node") is None:
        raise ConsumerMissing("node is not installed (apt-get install nodejs)")
    done = subprocess.run(
        ["node", str(JS / "read_metadata.mjs"), *map(str, paths)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    if done.returncode:
        raise RuntimeError(f"read_metadata.mjs: {(done.stdout + done.stderr).strip()[-1500:]}")
    return json.loads(done.stdout)
