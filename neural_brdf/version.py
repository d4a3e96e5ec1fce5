"""The package version: ONE number, from the installed package metadata.

    from neural_brdf.version import __version__      # the number in pyproject.toml
    neural-brdf --version

pyproject.toml holds the number; ``importlib.metadata`` reads it from an installed (or
editable) package.  A bare source tree without metadata (``PYTHONPATH=. python
train.py``) reads pyproject.toml next to the package instead, and anything else gets
``0+unknown``.  The CLI, the ONNX ``producer_version`` and the ``producer`` metadata use
this value.
"""

from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path

DISTRIBUTION = "neural-brdf"
UNKNOWN = "0+unknown"


def _from_source_tree() -> str | None:
    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    try:
        text = pyproject.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    if not re.search(r'^name\s*=\s*"neural-brdf"', text, re.M):
        return None
    found = re.search(r'^version\s*=\s*"([^"]+)"', text, re.M)
    return found.group(1) if found else None


def package_version() -> str:
    """The version of the installed distribution, else of the source tree, else 0+unknown."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return _from_source_tree() or UNKNOWN


__version__ = package_version()
