"""The files a run's target reads, fingerprinted: what ``--resume`` compares.

    from neural_brdf.train import target_files
    target_files.digest(cfg)     # {"/abs/teacher.xml": "<sha256 hex>", "/abs/diffuse.exr": ...}

A checkpoint records :func:`digest` (:class:`neural_brdf.train.session.RunFiles`), and a
resumed run compares it with the files as they are now
(:func:`neural_brdf.train.session.check_target_files`): a config compares paths, so a file
edited or replaced under the same path would otherwise be trained on without a word.

The files, by the target's kind (paths absolute, as the config names them; a file
found through a rule below, as that rule finds it):

* analytic (``target.model``): none;
* measured (``target.data``): the file;
* a Mitsuba teacher (``target.mitsuba``): the XML and what it reads (:func:`_xml_files`);
* an images fit (``target.images``): each entry's ``scene`` (and what it reads, as
  for a teacher), ``image`` and ``subtract``.

What an XML reads: the files of its ``<include filename>`` elements, found as
:func:`neural_brdf.inverse.views.expand` finds them
(:func:`neural_brdf.measured.mitsuba.include_candidates`), and
the files its ``<string name="filename">`` elements and ``filename`` attributes name
(bitmaps, an envmap, meshes, a ``measured`` table, a spectrum file), resolved by
Mitsuba's file resolver with the scene's folder first
(:func:`neural_brdf.measured.mitsuba.resolver_for`, as the teacher and the images fit
load them).  A name holding a ``$parameter`` and a name that resolves to no file are
left out: the fingerprint covers what can be found, never fails a run.
"""

from __future__ import annotations

import hashlib
import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from neural_brdf import config as cfgmod
from neural_brdf.measured.mitsuba import INCLUDE_DEPTH, include_candidates

CHUNK = 1 << 20  # bytes read at a time


def sha256(path: str | os.PathLike[str]) -> str:
    """The sha256 of the file's bytes (hex), read in chunks; OSError if unreadable."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(CHUNK):
            h.update(block)
    return h.hexdigest()


def where(cfg: cfgmod.Config, path: str) -> str:
    """The config key that reads ``path`` (a key of :func:`digest`), for a message:
    ``target.data``, ``target.mitsuba``, ``target.images[k].scene`` (or ``.image``,
    ``.subtract``) for an entry's own file, else ``target.images``."""
    t = cfg.target
    for k, item in enumerate(t.images or []):
        for field in ("scene", "image", "subtract"):
            value = getattr(item, field)
            if value is not None and os.path.abspath(value) == path:
                return f"target.images[{k}].{field}"
    if t.images is not None:
        return "target.images"
    return "target.mitsuba" if t.mitsuba is not None else "target.data"


def digest(cfg: cfgmod.Config) -> dict[str, str]:
    """Every file the target of ``cfg`` reads (absolute path) -> its sha256 (module doc);
    {} for an analytic target.  A file that cannot be read is left out (the run that
    reads it says why)."""
    out: dict[str, str] = {}
    for path in files(cfg):
        if path in out:
            continue
        try:
            out[path] = sha256(path)
        except OSError:
            continue
    return out


def files(cfg: cfgmod.Config) -> list[str]:
    """Every file the target of ``cfg`` reads, absolute, as found (module doc): what
    :func:`digest` hashes, and what a command that writes must not write over."""
    t = cfg.target
    if t.data is not None:
        return [os.path.abspath(t.data)]
    if t.mitsuba is not None:
        return _xml_files(Path(t.mitsuba))
    files: list[str] = []
    for item in t.images or []:
        files += _xml_files(Path(item.scene))
        files += [os.path.abspath(p) for p in (item.image, item.subtract) if p is not None]
    return files


def _xml_files(xml: Path) -> list[str]:
    """The XML at ``xml``, the files it includes and the files they name (module doc)."""
    files = [os.path.abspath(xml)]
    roots: list[ET.Element] = []
    _includes(xml, [xml.resolve().parent], 0, files, roots)
    names = [
        value
        for root in roots
        for el in root.iter()
        if el.tag != "include"
        for value in _filenames(el)
        if value.strip() and "$" not in value
    ]
    if names:
        resolver = _resolver(xml)
        for value in names:
            found = Path(value) if resolver is None else Path(str(resolver.resolve(value)))
            if resolver is None and not found.is_absolute():
                found = xml.resolve().parent / value
            if found.is_file():
                files.append(os.path.abspath(found))
    return list(dict.fromkeys(files))


def _filenames(el: ET.Element) -> list[str]:
    """The file names ``el`` gives: ``<string name="filename" value>``, or a ``filename``
    attribute (``<spectrum filename>``)."""
    if el.tag == "string" and el.get("name") == "filename":
        return [el.get("value", "")]
    value = el.get("filename")
    return [value] if value is not None else []


def _includes(
    path: Path, folders: list[Path], depth: int, files: list[str], roots: list[ET.Element]
) -> None:
    """Parse ``path`` into ``roots`` and add the files it includes to ``files``,
    recursively (module doc); an unreadable file is skipped."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError, UnicodeDecodeError):
        return
    roots.append(root)
    if depth >= INCLUDE_DEPTH:
        return
    for el in root.iter("include"):
        name = el.get("filename", "")
        if not name.strip() or "$" in name:
            continue
        found = next((c for c in include_candidates(name, folders) if c.is_file()), None)
        if found is None or os.path.abspath(found) in files:
            continue
        files.append(os.path.abspath(found))
        _includes(found, [found.parent, *folders], depth + 1, files, roots)


def _resolver(xml: Path) -> Any:
    """Mitsuba's file resolver for the XML at ``xml`` (its folder first), or None
    without Mitsuba (then a relative name is the XML folder's)."""
    try:
        import mitsuba as mi
    except ImportError:
        return None
    from neural_brdf.measured.mitsuba import resolver_for

    return resolver_for(mi, xml)
