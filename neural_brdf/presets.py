"""The shipped configs ("presets"): ``neural-brdf train gold`` from any folder.

    neural-brdf presets                       # name and one-line description of each
    neural-brdf train gold --out runs/gold    # = python train.py configs/gold.yaml ...
    neural-brdf sweep furnace                 # = neural-brdf sweep configs/sweeps/furnace.yaml

    from neural_brdf import presets
    presets.names()                           # ['bank', 'beckmann_rough', ...]
    presets.resolve("gold")                   # Path of the YAML file
    presets.resolve("my/own.yaml")            # a file that exists is used as it is
    presets.resolve("furnace", folder="sweeps")   # neural-brdf sweep furnace

There is one copy of the presets: the repository's top-level ``configs/`` folder.
pyproject.toml maps it into the package as ``neural_brdf.configs`` (package-data), so a
wheel installs it as ``site-packages/neural_brdf/configs/`` and this module reads it with
:mod:`importlib.resources`.  From a source checkout (``python train.py``, an editable
install) the checkout's own ``configs/`` is used, so an edit there is seen at once.
Files keep their relative layout (``sweeps/*.yaml`` name ``../gold.yaml``).

No heavy imports: listing presets does not load torch or pydantic.
"""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path

from neural_brdf.errors import InputError

PACKAGE = "neural_brdf.configs"  # the installed name of the top-level configs/
DESCRIPTION_CHARS = 100  # a description is cut to this length


def _source_tree() -> Path | None:
    """The checkout's configs/ when this package is imported from a source checkout."""
    root = Path(__file__).resolve().parents[1]
    pyproject = root / "pyproject.toml"
    if not (root / "configs" / "defaults.yaml").is_file() or not pyproject.is_file():
        return None
    try:
        text = pyproject.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    return root / "configs" if re.search(r'^name\s*=\s*"neural-brdf"', text, re.M) else None


def directory() -> Path:
    """The folder that holds the presets (a real directory: relative references work)."""
    source = _source_tree()
    if source is not None:
        return source
    try:
        # configs/ has no __init__.py: files() of a namespace package is a MultiplexedPath;
        # a file inside it is a plain Path, whose parent is the folder itself
        anchor = resources.files(PACKAGE).joinpath("defaults.yaml")
    except ModuleNotFoundError:
        raise InputError(
            "presets: not installed with this copy of neural_brdf (reinstall the package)"
        ) from None
    if not isinstance(anchor, Path) or not anchor.is_file():
        raise InputError(f"presets: {anchor} is not a file on disk (install unzipped)")
    return anchor.parent


SUBFOLDERS = ("mlp", "mitsuba")  # preset families named "mlp/gold", listed with the rest
# Former names still accepted: the compact presets were "compact/gold" until they became
# the top-level presets (issue 21); the 3 x 64 networks are now "mlp/gold".
ALIASES = {"compact/": ""}


def names(*, folder: str = "") -> list[str]:
    """The preset names: every ``*.yaml`` of the presets folder (or its ``folder``), and
    for the presets folder itself those of :data:`SUBFOLDERS` as ``mlp/gold``."""
    root = directory() / folder
    found = [p.stem for p in root.glob("*.yaml")]
    if not folder:
        found += [f"{sub}/{p.stem}" for sub in SUBFOLDERS for p in (root / sub).glob("*.yaml")]
    return sorted(found)


def description(path: Path) -> str:
    """The first sentence of a file's leading comment block, on one line."""
    words: list[str] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        text = line.lstrip("#").strip()
        if not text:
            if words:
                break
            continue
        words.append(text)
    joined = " ".join(words)
    end = re.search(r"\.(?=\s+[A-Z]|$)", joined)  # not "et al. 2003"
    sentence = joined[: end.start() + 1] if end else joined
    if len(sentence) > DESCRIPTION_CHARS:
        sentence = sentence[: DESCRIPTION_CHARS - 3].rsplit(" ", 1)[0] + "..."
    return sentence


def listing(*, folder: str = "") -> list[tuple[str, str]]:
    """(name, description) of every preset (of ``folder``: "sweeps" for the sweeps)."""
    where = directory() / folder
    return [(name, description(where / f"{name}.yaml")) for name in names(folder=folder)]


def resolve(name_or_path: str | Path, *, folder: str = "") -> Path:
    """A config file: an existing path wins; else a preset name (``gold``, ``gold.yaml``,
    ``mlp/gold``; the former ``compact/gold`` is ``gold``), looked up in the presets
    folder or, with ``folder="sweeps"``, among the sweeps.

    A bare name that is neither raises InputError naming it and listing the presets; a
    path with a folder in it is returned as it is (reading it reports a missing file).
    """
    path = Path(name_or_path)
    if path.is_file():
        return path
    text = str(name_or_path)
    stem = text.removesuffix(".yaml").removesuffix(".yml")
    known = names(folder=folder)
    if not folder and stem not in known:
        for old, new in ALIASES.items():
            if stem.startswith(old) and new + stem[len(old) :] in known:
                stem = new + stem[len(old) :]
    if ("/" in text or "\\" in text) and stem not in known:
        return path
    if stem and stem in known:
        return directory() / folder / f"{stem}.yaml"
    kind = "sweep" if folder else "config"
    if path.is_dir():  # a run folder given for its config, most likely
        inside = path / "config.yaml"
        hint = f"; its config is {inside}" if inside.is_file() else ""
        raise InputError(f"{text}: is a folder, not a {kind} file{hint}")
    raise InputError(f"{text}: neither a {kind} file nor a preset (presets: {', '.join(known)})")
