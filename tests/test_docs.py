"""The documentation cannot drift: generated tables, links, config keys, no outside paths.

PYTHONPATH=$PWD python -m pytest -q tests/test_docs.py      # about a second
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
DOCS = sorted(
    [REPO / "README.md", *(REPO / "docs").glob("*.md"), REPO / "benchmarks" / "README.md"]
)
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")  # [text](target)


def _tool():
    spec = importlib.util.spec_from_file_location(
        "results_tables", REPO / "tools" / "results_tables.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_results_page_is_generated_from_the_json():
    """docs/results.md is exactly what tools/results_tables.py makes of the JSON now."""
    committed = (REPO / "docs" / "results.md").read_text()
    assert _tool().render() == committed, (
        "docs/results.md differs from the benchmark JSON: run python tools/results_tables.py"
    )


def _study():
    spec = importlib.util.spec_from_file_location("study", REPO / "experiments" / "study.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_experiment_tables_are_generated_from_their_json():
    """docs/experiments.md's tables are what experiments/study.py makes of docs/results/."""
    study = _study()
    page = (REPO / "docs" / "experiments.md").read_text()
    assert len(study.MARKED.findall(page)) == 4  # size, ablation, loss, furnace
    assert study.tables_page(page) == page, "run python experiments/study.py --tables"
    # and the check can fail: a changed figure in a trial changes its table
    stale = page.replace("| 8x8 | 171 / 219 | 3.82 % |", "| 8x8 | 171 / 219 | 9.99 % |")
    assert stale != page and study.tables_page(stale) == page


def test_results_page_changes_with_the_json(tmp_path):
    """The check can fail: a changed figure in the JSON changes the page."""
    tool = _tool()
    src = REPO / "benchmarks" / "results" / "neural_presets.json"
    text = src.read_text()
    changed = tmp_path / "neural_presets.json"
    changed.write_text(text.replace('"rel_rmse": 0.', '"rel_rmse": 0.9', 1))
    sections = [(changed if p == src else p, f) for p, f in tool.SECTIONS]
    assert tool.render(sections) != tool.render()


def test_results_page_names_its_sources():
    page = (REPO / "docs" / "results.md").read_text()
    for path, _ in _tool().SECTIONS:
        rel = Path(path).relative_to(REPO).as_posix()
        assert f"Source: `{rel}`" in page
    assert page.count("Recorded in the file:") == len(_tool().SECTIONS)


def _links():
    for doc in DOCS:
        text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)  # not code blocks
        for target in LINK.findall(text):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # web links, in-page anchors
            yield doc, target


@pytest.mark.parametrize(
    "doc,target", list(_links()), ids=lambda x: x if isinstance(x, str) else x.name
)
def test_relative_links_point_at_files_in_the_repository(doc, target):
    file, _, anchor = target.partition("#")
    path = (doc.parent / file).resolve()
    assert path.exists(), f"{doc.relative_to(REPO)}: broken link {target}"
    assert REPO in path.parents, f"{doc.relative_to(REPO)}: {target} leaves the repository"
    if anchor and path.suffix == ".md":
        assert anchor in _anchors(path), f"{doc.relative_to(REPO)}: no heading #{anchor}"


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return {
        re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
        for h in re.findall(r"^#+ (.+)$", text, flags=re.M)
    }


def test_anchor_rule():
    assert "measured-materials-merl" in _anchors(REPO / "docs" / "results.md")


def test_link_check_finds_links():
    """The pattern really sees the README's links (an empty parametrisation passes)."""
    readme = [t for d, t in _links() if d.name == "README.md" and d.parent == REPO]
    assert "docs/cli.md" in readme and len(readme) >= 10


def _keys(tree: dict, prefix: str = "") -> list[str]:
    out = []
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v and k != "params":
            out += _keys(v, key + ".")
        else:
            out.append(key)
    return out


def test_every_default_config_key_is_documented():
    keys = _keys(yaml.safe_load((REPO / "configs" / "defaults.yaml").read_text()))
    assert len(keys) > 30 and "train.loss" in keys
    page = (REPO / "docs" / "config.md").read_text()
    missing = [k for k in keys if f"`{k}`" not in page]
    assert not missing, f"docs/config.md does not document {missing}"


def _row(page: str, start: str) -> str:
    """The first line of docs/``page`` that starts with ``start``."""
    text = (REPO / "docs" / page).read_text()
    rows = [line for line in text.splitlines() if line.startswith(start)]
    assert rows, f"docs/{page}: no line starts with {start!r}"
    return rows[0]


def test_the_hand_kept_lists_name_every_encoding_and_codegen_target():
    # a new encoding or back end is one file and its registry line (docs/architecture.md):
    # the pages that list the names by hand must follow, and this names the page to edit
    from neural_brdf import backends, encodings
    from neural_brdf.tooling import cli

    rows = {
        "config.md": _row("config.md", "| `model.encoding` |"),
        "model.md": _row("model.md", "| `encoding` |"),
        "portable.md": _row("portable.md", "| `encoding` |"),
    }
    lacking = {
        page: missing
        for page, row in rows.items()
        if (missing := [n for n in encodings.names() if f"`{n}`" not in row])
    }
    assert not lacking, "the encodings' lists lack names: " + "; ".join(
        f"docs/{page} lacks {missing}" for page, missing in lacking.items()
    )
    usage = "--target " + "|".join(backends.TARGETS)
    assert usage in (REPO / "docs" / "cli.md").read_text(), f"docs/cli.md: say {usage}"
    assert usage in (cli.__doc__ or ""), f"neural_brdf/tooling/cli.py's docstring: say {usage}"


def test_the_cli_page_names_every_measured_format():
    # bake's and validate's usage lines in docs/cli.md spell the suffixes (the command's
    # own help takes them from the registry, neural_brdf/measured/formats.py)
    from neural_brdf.measured import formats

    lines = {
        "bake": _row("cli.md", "neural-brdf bake "),
        "validate": _row("cli.md", "neural-brdf validate "),
    }
    lacking = {
        command: missing
        for command, line in lines.items()
        if (missing := [f.suffix for f in formats.all_formats() if f.suffix not in line])
    }
    assert not lacking, "docs/cli.md: " + "; ".join(
        f"the {command} line lacks {missing}" for command, missing in lacking.items()
    )


def test_the_images_guide_lists_every_images_key():
    # docs/inverse.md's "The config" says its images bullet holds every setting of the fit
    keys = _keys(yaml.safe_load((REPO / "configs" / "defaults.yaml").read_text()))
    images = [k.removeprefix("images.") for k in keys if k.startswith("images.")]
    assert len(images) > 30 and "start" in images
    page = (REPO / "docs" / "inverse.md").read_text()
    section = page[page.index("\n## The config\n") :]
    section = section[: section.index("\n## ", 1)]
    missing = [k for k in images if f"`{k}`" not in section]
    assert not missing, f"docs/inverse.md, The config, does not list images.{missing}"


def test_docs_do_not_point_outside_the_repository():
    for doc in DOCS:
        text = doc.read_text()
        for banned in ("NOTES.md", "../shared", "shared/data", "/work/"):
            assert banned not in text, f"{doc.relative_to(REPO)} mentions {banned}"


def test_every_test_file_and_benchmark_script_is_listed():
    listed = (REPO / "docs" / "testing.md").read_text() + (
        REPO / "docs" / "benchmarks.md"
    ).read_text()
    files = sorted((REPO / "tests").rglob("test_*.py")) + sorted(
        p for p in (REPO / "benchmarks").glob("*.py") if p.name != "__init__.py"
    )
    assert len(files) > 30
    missing = [p.name for p in files if p.name not in listed and "node_modules" not in p.parts]
    assert not missing, f"not listed in docs/testing.md or docs/benchmarks.md: {missing}"


# ------------------------------------------------------------------ README's layout
def _readme_layout() -> dict[str, list[str]]:
    """README's "Layout" block: top-level folder -> the names listed under it.  A line
    ``  name name/ ...   text`` (two spaces in, names separated by one space, then at
    least two spaces) lists parts of the folder above it."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    block = text.split("## Layout", 1)[1].split("```", 2)[1]
    out: dict[str, list[str]] = {}
    folder = None
    for line in block.splitlines():
        if re.match(r"^[a-z_.]+/?\s", line + " "):
            folder = line.split()[0]
            out[folder] = []
        elif line.startswith("  ") and not line.startswith("   ") and folder:
            names = re.split(r"\s{2,}", line.strip(), maxsplit=1)[0]
            out[folder] += names.split(" ")
    return out


def _package_parts() -> set[str]:
    """neural_brdf's parts: its subpackages (``name/``) and top-level modules (``name``)."""
    pkg = REPO / "neural_brdf"
    parts = {p.name + "/" for p in pkg.iterdir() if (p / "__init__.py").is_file()}
    parts |= {p.stem for p in pkg.glob("*.py") if p.stem not in ("__init__", "__main__")}
    return parts


def test_readme_layout_lists_every_part_of_the_package():
    layout = _readme_layout()
    assert "neural_brdf/" in layout, sorted(layout)
    listed = set(layout["neural_brdf/"])
    assert listed == _package_parts(), (
        f"README's Layout lists {sorted(listed - _package_parts())} that the package "
        f"lacks and lacks {sorted(_package_parts() - listed)}"
    )


def test_readme_layout_lists_the_top_level_folders():
    layout = _readme_layout()
    for folder in layout:
        name = folder.rstrip("/")
        assert (REPO / name).exists(), f"README's Layout names {folder}, which is not here"
    untracked = ("runs", "build", "data", "__pycache__")  # .gitignore's folders
    folders = {
        p.name
        for p in REPO.iterdir()
        if p.is_dir()
        and not p.name.startswith(".")
        and p.name not in untracked
        and not p.name.endswith(".egg-info")
    }
    listed = {f.rstrip("/") for f in layout}
    assert folders <= listed, f"README's Layout lacks {sorted(folders - listed)}"


# ------------------------------------------------ the Python examples name what exists
PYTHON_BLOCK = re.compile(r"```python\n(.*?)```", re.S)
OWN = ("neural_brdf", "analytic")  # the packages whose names the examples must get right


def _examples() -> list[tuple[str, str]]:
    return [
        (f"{doc.relative_to(REPO)}#{i}", block)
        for doc in DOCS
        for i, block in enumerate(PYTHON_BLOCK.findall(doc.read_text()))
    ]


def _names_used(block: str) -> list[tuple[str, str | None]]:
    """(module, attribute) of the project's own names an example uses: each ``from M
    import A``, and each ``alias.A`` where ``alias`` is an imported project module."""
    import ast

    tree = ast.parse(block)
    aliases: dict[str, str] = {}
    used: list[tuple[str, str | None]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in OWN:
                    # `import a.b` binds a; `import a.b as c` binds c to a.b
                    aliases[a.asname or a.name.split(".")[0]] = (
                        a.name if a.asname else a.name.split(".")[0]
                    )
                    used.append((a.name, None))
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in OWN:
            for a in node.names:
                used.append((node.module, a.name))
                aliases[a.asname or a.name] = f"{node.module}.{a.name}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if node.value.id in aliases:
                used.append((aliases[node.value.id], node.attr))
    return used


def test_the_python_examples_use_names_that_exist():
    import importlib

    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")  # the examples' variant; the plugins' modules need one
    examples = _examples()
    assert len(examples) >= 10  # the check finds the examples
    wrong = []
    for where, block in examples:
        for module, attr in _names_used(block):
            try:
                obj = importlib.import_module(module)
            except ModuleNotFoundError:  # `from package import submodule` as a module path
                parent, _, last = module.rpartition(".")
                obj = getattr(importlib.import_module(parent), last, None)
                if obj is None:
                    wrong.append(f"{where}: {module}")
                    continue
            if attr is not None and not hasattr(obj, attr):
                try:
                    importlib.import_module(f"{module}.{attr}")
                except ModuleNotFoundError:
                    wrong.append(f"{where}: {module}.{attr}")
    assert wrong == []


DOC_PATH = re.compile(r"\bdocs/[\w./-]+\.md\b")


def test_every_docs_page_named_in_the_repository_exists():
    # configs, code, benchmarks and docs name pages as docs/X.md; a renamed page leaves
    # them pointing nowhere (configs/merl.yaml named docs/merl_sweep.md)
    files = [
        *DOCS,
        *(REPO / "configs").rglob("*.yaml"),
        *(REPO / "neural_brdf").rglob("*.py"),
        *(REPO / "benchmarks").glob("*.py"),
        *(REPO / "tools").glob("*.py"),
    ]
    named = {(f.relative_to(REPO), m) for f in files for m in DOC_PATH.findall(f.read_text())}
    assert len({m for _, m in named}) >= 10  # the check finds them
    assert sorted((str(f), m) for f, m in named if not (REPO / m).is_file()) == []
