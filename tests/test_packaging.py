"""Packaging: presets shipped in the package, one version, light imports, the wheel's files.

The installed-wheel round trip (fresh venv, `neural-brdf train quickstart` from an empty
folder) is .ci/wheel_check.sh; these tests check the same contracts from the source tree.
"""

from __future__ import annotations

import functools
import inspect
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest

import neural_brdf
from neural_brdf import export, presets
from neural_brdf.errors import InputError
from neural_brdf.tooling.cli import main
from neural_brdf.train.model import RawBRDF

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "pydantic", "matplotlib", "scipy")


def python(code: str, *, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter that sees this source tree."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


def pyproject_version() -> str:
    text = (ROOT / "pyproject.toml").read_text()
    return re.search(r'^version\s*=\s*"([^"]+)"', text, re.M).group(1)


# ------------------------------------------------------------------ light consumers
def test_load_and_eval_do_not_import_torch(tmp_path):
    raw = RawBRDF("isotropic", [8], "silu", init_value=0.2).eval()
    path = tmp_path / "m.onnx"
    path.write_bytes(export.to_onnx_bytes(raw, 17))
    proc = python(
        f"""
import sys, json
import neural_brdf
f = neural_brdf.load({str(path)!r}).eval([[0, 0, 1.0]], [[0, 0.6, 0.8]])
print(json.dumps({{"f": f.tolist(), "heavy": [m for m in {HEAVY!r} if m in sys.modules]}}))
""",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["heavy"] == [], out
    assert len(out["f"][0]) == 3 and min(out["f"][0]) > 0


def test_help_version_and_presets_do_not_import_torch(tmp_path):
    proc = python(
        f"""
import sys, json
from neural_brdf.tooling.cli import main
codes = []
for argv in (["--help"], ["--version"], ["train", "--help"]):
    try:
        main(argv)
    except SystemExit as e:
        codes.append(e.code)
codes.append(main(["presets"]))
codes.append(main(["train", "no_such_preset"]))
print(json.dumps({{"codes": codes, "heavy": [m for m in {HEAVY!r} if m in sys.modules]}}))
""",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["codes"] == [0, 0, 0, 0, 2], out
    assert out["heavy"] == [], out


def test_input_error_is_one_class():
    from neural_brdf import config
    from neural_brdf.train import loop

    assert config.ConfigError.__mro__[1] is InputError
    # one home each: errors.InputError, fileformat.FORMAT_VERSION (config re-exports neither)
    assert not hasattr(config, "InputError") and not hasattr(config, "FORMAT_VERSION")
    assert issubclass(export.CheckpointError, InputError)
    assert issubclass(loop.RunExists, InputError)
    assert loop.Interrupted is neural_brdf.errors.Interrupted
    assert export.ParityError is neural_brdf.errors.ParityError


# ------------------------------------------------------------------ version
def test_one_version_everywhere(capsys):
    version = pyproject_version()
    try:
        installed = metadata.version("neural-brdf")
    except metadata.PackageNotFoundError:
        installed = version
    assert neural_brdf.__version__ == installed == version
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"neural-brdf {version}"
    assert export.PRODUCER == f"neural-brdf {version}"
    hard_coded = [
        p
        for d in ("neural_brdf", "analytic")
        for p in (ROOT / d).rglob("*.py")
        if f'"{version}"' in p.read_text()
    ]
    assert hard_coded == []


# ------------------------------------------------------------------ presets
def test_presets_are_the_configs_folder():
    assert presets.directory().resolve() == (ROOT / "configs").resolve()
    assert presets.names() == sorted(
        [p.stem for p in (ROOT / "configs").glob("*.yaml")]
        + [f"mlp/{p.stem}" for p in (ROOT / "configs" / "mlp").glob("*.yaml")]
        + [f"mitsuba/{p.stem}" for p in (ROOT / "configs" / "mitsuba").glob("*.yaml")]
    )
    assert "mitsuba/roughplastic" in presets.names()
    assert "mlp/gold" in presets.names()
    assert {"gold", "quickstart", "merl", "defaults"} <= set(presets.names())
    for name, text in presets.listing():
        assert text and "\n" not in text and len(text) <= presets.DESCRIPTION_CHARS, name
    assert (
        presets.description(ROOT / "configs" / "lambert.yaml")
        == "Lambertian diffuse, a constant 1/pi times the albedo."
    )


def test_a_path_wins_over_a_preset_and_unknown_names_list_presets(tmp_path, monkeypatch):
    assert presets.resolve("gold") == presets.directory() / "gold.yaml"
    assert presets.resolve("gold.yaml") == presets.directory() / "gold.yaml"
    monkeypatch.chdir(tmp_path)
    Path("gold").write_text("target: {model: lambertian}\n")
    assert presets.resolve("gold") == Path("gold")
    assert presets.resolve("sub/none.yaml") == Path("sub/none.yaml")  # read later: no file
    # a family preset by name, from any folder
    assert presets.resolve("mlp/gold") == presets.directory() / "mlp" / "gold.yaml"
    assert presets.resolve("mlp/gold.yaml").is_file()
    # the former names of the compact presets, now the top-level ones (issue 21)
    assert presets.resolve("compact/gold") == presets.directory() / "gold.yaml"
    assert presets.resolve("compact/gold.yaml") == presets.directory() / "gold.yaml"
    with pytest.raises(InputError, match=r"^velvet: neither .*gold, lambert"):
        presets.resolve("velvet")


def test_cli_presets_lists_every_name_and_sweep(capsys):
    assert main(["presets"]) == 0
    configs, _, rest = capsys.readouterr().out.partition("\n\n")
    assert [line.split()[0] for line in configs.splitlines()] == presets.names()
    sweeps = [line.split()[0] for line in rest.splitlines() if line.startswith("  ")]
    assert (
        sweeps
        == presets.names(folder="sweeps")
        == sorted(p.stem for p in (ROOT / "configs" / "sweeps").glob("*.yaml"))
    )
    assert (
        presets.resolve("furnace", folder="sweeps")
        == presets.directory() / "sweeps" / "furnace.yaml"
    )
    assert main(["sweep", "gold"]) == 2  # a config preset is not a sweep
    assert "gold: neither a sweep file nor a preset" in capsys.readouterr().err


def test_train_a_preset_by_name_from_another_folder(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "neural_brdf",
            "train",
            "lambert",
            "--out",
            "r",
            "--set",
            "train.steps=3",
            "--set",
            "train.progress=false",
            "--set",
            "model.hidden=[8]",
            "--set",
            "data.batch_size=64",
            "--set",
            "data.pool_size=256",
            "--set",
            "normalization.table_size=9",
            "--set",
            "normalization.samples=512",
            "--set",
            "validation.furnace_dirs=4",
            "--set",
            "validation.furnace_samples=512",
            "--set",
            "validation.pairs=200",
            "--set",
            "validation.accuracy_samples=2048",
            "--set",
            "export.parity_pairs=64",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "r" / "model.onnx").is_file()
    assert "name: lambert" in (tmp_path / "r" / "config.yaml").read_text()


# ------------------------------------------------------------------ the wheel's contents
def test_wheel_ships_presets_typing_and_license(tmp_path):
    """Build from a copy of the tree (the build writes build/ and *.egg-info beside it)."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    junk = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("analytic", "neural_brdf", "configs"):
        shutil.copytree(ROOT / name, src / name, ignore=junk)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--wheel-dir",
            str(tmp_path / "dist"),
            str(src),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("neural_brdf-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    configs = sorted(
        p.relative_to(ROOT / "configs").as_posix() for p in (ROOT / "configs").rglob("*.yaml")
    )
    assert any(c.startswith("sweeps/") for c in configs)
    missing = [c for c in configs if f"neural_brdf/configs/{c}" not in names]
    assert missing == []
    assert {"neural_brdf/py.typed", "analytic/py.typed"} <= names
    # every source file of the two packages (subpackages, the viewer's script, data)
    shipped = sorted(
        p.relative_to(ROOT).as_posix()
        for name in ("analytic", "neural_brdf")
        for p in (ROOT / name).rglob("*")
        if p.is_file() and p.suffix in (".py", ".js", ".json", ".typed")
    )
    assert [f for f in shipped if f not in names] == []
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    assert not [n for n in names if n.split("/")[0] in ("configs", "tests", "benchmarks")]
    meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(wheel).read(meta).decode()
    requires = [line for line in text.splitlines() if line.startswith("Requires-Dist:")]
    base = [r for r in requires if "extra ==" not in r]
    assert not [r for r in base if "scipy" in r or "pytest" in r], base
    torch_req = next(r for r in base if r.startswith("Requires-Dist: torch"))
    assert ">=2.5" in torch_req, torch_req  # torch.onnx.export(dynamo=False): 2.5+


# ------------------------------------------------------------------ typing
def test_public_api_is_annotated():
    import typing

    import analytic
    from neural_brdf import config, pipeline, validate
    from neural_brdf.runtime import NeuralBRDF
    from neural_brdf.train import loop

    public = [
        neural_brdf.load,
        NeuralBRDF.eval,
        analytic.create,
        analytic.albedo,
        config.load,
        presets.resolve,
        pipeline.run,
        loop.train,
        export.export,
        export.export_run,
        validate.report,
        validate.physics,
    ]
    for fn in public:
        hints = typing.get_type_hints(fn)  # resolvable, not only present
        sig = inspect.signature(fn)
        missing = [p for p in sig.parameters if p != "self" and p not in hints]
        assert missing == [] and "return" in hints, (fn.__qualname__, missing)
    for package in ("neural_brdf", "analytic"):
        assert (ROOT / package / "py.typed").is_file()


def test_presets_into_a_closed_pipe_exit_quietly():
    # `neural-brdf presets | head -0`: the reader is gone before the first line is written
    from cli_helpers import into_closed_pipe

    code, err = into_closed_pipe("presets")
    assert code == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err


# ------------------------------------------------------------------ the flow of a run
# docs/architecture.md: the package's parts in the order data flows through them.  A part
# (a subpackage, or a top-level module) imports only the parts before it, at the top of a
# module or inside a function; pipeline runs the stages, tooling is the command line.
LAYERS = [
    "errors",
    "limits",
    "fileio",
    "version",
    "fileformat",
    "encodings",
    "target",  # the kinds of target (light: errors only), which config names
    "config",
    "runfolder",
    "presets",
    "runtime",
    "physics",
    "measured",
    "train",
    "validate",
    "graph",
    "export",
    "backends",
    "renderers",
    "inverse",
    "viewer",
    "pipeline",
    "tooling",
]
PACKAGE = ROOT / "neural_brdf"


def _part(path: Path) -> str:
    rel = path.relative_to(PACKAGE).parts
    return rel[0] if len(rel) > 1 else path.stem


def _imported_parts(path: Path, text: str | None = None) -> set[str]:
    """The parts of neural_brdf a module imports (absolute or relative, anywhere in it)."""
    return {m.split(".")[1] for m in _module_imports(path, _module_set(), text) if "." in m}


@functools.cache
def _module_set() -> frozenset[str]:
    return frozenset(_module_name(p) for p in _modules())


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "configs" not in p.relative_to(PACKAGE).parts)


def test_every_part_of_the_package_has_its_place_in_the_flow():
    parts = {_part(p) for p in _modules()} - {"__init__", "__main__"}
    assert parts == set(LAYERS), (parts - set(LAYERS), set(LAYERS) - parts)


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_a_part_imports_only_the_parts_before_it(path):
    part = _part(path)
    if part in ("__init__", "__main__"):  # the package's front door: load, the CLI
        return
    later = set(LAYERS[LAYERS.index(part) + 1 :])
    imported = _imported_parts(path)
    assert not imported & later, f"{path.relative_to(ROOT)} imports {sorted(imported & later)}"


@pytest.mark.parametrize(
    "text",
    [
        "def f():\n    from ..viewer import report\n",
        "from neural_brdf.viewer.report import write_report\n",
        "from neural_brdf import pipeline\n",
        "import neural_brdf.tooling.cli\n",
    ],
)
def test_the_layer_test_sees_a_climb_back(text):
    # a module of train/ that reaches a later part, in each way an import can be written
    fake = PACKAGE / "train" / "x.py"
    assert _imported_parts(fake, text) & set(LAYERS[LAYERS.index("train") + 1 :])


def _module_name(path: Path) -> str:
    parts = ("neural_brdf",) + path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_imports(path: Path, modules: frozenset[str], text: str | None = None) -> set[str]:
    """The modules of the package that ``path`` imports, anywhere in it: ``from a.b
    import c`` is a.b.c where that is a module, else a.b (its package's face)."""
    import ast

    me = _module_name(path)
    package = me.split(".") if path.name == "__init__.py" else me.split(".")[:-1]
    out: set[str] = set()
    source = path.read_text(encoding="utf-8") if text is None else text
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package[: len(package) - (node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            for a in node.names:
                name = f"{base}.{a.name}"
                out.add(name if name in modules else base)
        elif isinstance(node, ast.Import):
            for a in node.names:
                name = a.name
                while name and name not in modules:
                    name = name.rpartition(".")[0]
                out.add(name)
    return (out & modules) - {me}


def _circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import graph's strongly connected parts of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                found.append(sorted(part))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_no_two_modules_import_each_other_even_within_a_part():
    """The layers keep parts in order; within a part (inverse/, train/, ...) no module
    reaches back to one that imports it, directly or round a longer loop, at the top
    or inside a function (docs/architecture.md)."""
    edges = {_module_name(p): _module_imports(p, _module_set()) for p in _modules()}
    assert sum(len(e) for e in edges.values()) > 100  # the graph was read
    assert _circles(edges) == []


def test_the_circle_test_sees_a_loop_through_a_function_level_import():
    # inverse/fit.py, starts.py and coverage.py before session 74: a loop of three
    modules = frozenset(f"neural_brdf.inverse.{m}" for m in ("fit", "starts", "coverage", "views"))
    texts = {
        "fit": "from neural_brdf.inverse.views import View\n"
        "def f():\n    from neural_brdf.inverse import coverage, starts\n",
        "starts": "from neural_brdf.inverse import fit as inverse\n",
        "coverage": "from . import views\ndef g():\n    from .fit import fit_bsdf\n",
        "views": "import numpy\n",
    }
    edges = {
        f"neural_brdf.inverse.{m}": _module_imports(PACKAGE / "inverse" / f"{m}.py", modules, t)
        for m, t in texts.items()
    }
    assert edges["neural_brdf.inverse.coverage"] == {
        "neural_brdf.inverse.views",
        "neural_brdf.inverse.fit",
    }
    assert _circles(edges) == [
        ["neural_brdf.inverse.coverage", "neural_brdf.inverse.fit", "neural_brdf.inverse.starts"]
    ]


def test_the_pipeline_runs_every_stage_and_the_cli_calls_it():
    assert {"train", "export", "validate", "viewer", "inverse"} <= _imported_parts(
        PACKAGE / "pipeline.py"
    )
    assert "pipeline" in _imported_parts(PACKAGE / "tooling" / "cli.py")


def test_the_file_format_module_is_the_bottom_and_its_readers_import_it():
    assert _imported_parts(PACKAGE / "fileformat" / "__init__.py") == set()
    for module in ("runtime.py", "export.py", "physics/lobe_fit.py", "train/session.py"):
        assert "fileformat" in _imported_parts(PACKAGE / module), module
    from neural_brdf import export, fileformat, runtime
    from neural_brdf.fileformat import lobe as lobe_format

    assert runtime.JSON_KEYS is fileformat.JSON_KEYS and runtime.OUTPUT == fileformat.OUTPUT
    assert fileformat.FORMAT_VERSION == export.FORMAT_VERSION
    assert lobe_format.KEY == fileformat.LOBE_KEY and lobe_format.KEY in fileformat.JSON_KEYS
