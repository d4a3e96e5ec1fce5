"""Safe file writes: every file the package writes goes through here.

    atomic_write(path, b"...")             # bytes or str (UTF-8)
    with atomic_path(path) as tmp:         # for writers that want a file name
        torch.save(state, tmp)

What happens depends on what ``path`` is:

* a regular file, or nothing yet: the data go to a temporary file in the destination
  folder, are flushed and fsynced, and the temporary file is renamed over ``path`` with
  ``os.replace``, which is atomic on POSIX; the folder is then fsynced so that the rename
  itself survives a power cut.  A reader sees the old file or the new one, never a torn
  one, and an exception or Ctrl-C mid-write leaves no temporary file behind (a process
  killed outright, SIGKILL or OOM, leaves its ``.NAME.*.tmp``: the next run that holds a
  run folder removes those of the run's files, runfolder.remove_stale_temporaries).  A
  new file gets the permissions a plain ``open(path, "w")`` would give (0o666 less the
  umask; ``mkstemp`` alone leaves 0o600); a replaced file keeps its own.
* a symbolic link: it is followed, and the file it points to is replaced as above (or
  created, for a dangling link); the link stays a link.
* a device, a FIFO or a socket (``/dev/null``, ``/dev/stdout``, a named pipe): it cannot
  be replaced, so it is opened and written directly, as ``open(path, "wb")`` would.
  ``-o /dev/null`` leaves /dev/null a device, and ``/dev/full`` gives ENOSPC.
* a folder: IsADirectoryError.

Every OSError raised here names ``path`` (``e.filename``, ``e.strerror``): the command
line prints ``PATH: cannot write (No space left on device)`` and exits with code 2.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import stat
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

_UMASK_LOCK = threading.Lock()


def _umask() -> int:
    """The process umask (os.umask can only be read by setting it, hence the lock)."""
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # some file systems refuse to open folders: nothing to sync
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _destination(path: Path) -> tuple[Path, os.stat_result | None, bool]:
    """(the file to write, its stat or None when new, whether it is replaced by rename)."""
    try:
        st = os.stat(path)  # follows links, /dev/stdout's magic ones included
    except FileNotFoundError:  # a new file, or a dangling link: created where it points
        return Path(os.path.realpath(path)), None, True
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
    if not stat.S_ISREG(st.st_mode):
        return path, st, False  # a device, FIFO or socket: written in place
    return Path(os.path.realpath(path)), st, True


def written_in_place(path: str | os.PathLike) -> bool:
    """Whether a write to ``path`` goes in place, as :func:`atomic_path` writes it: a
    device, FIFO or socket (``/dev/null``, ``/dev/stdout``, a named pipe), not a regular
    file, a folder or a new path."""
    try:
        st = os.stat(path)  # follows links, as _destination does
    except OSError:
        return False
    return not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode))


def _renamed(e: OSError, path: Path) -> OSError:
    """``e`` naming ``path`` (OSError(errno, ...) picks the subclass from the errno)."""
    if e.errno is None:  # e.g. OSError("simulated"): nothing to name
        return e
    return OSError(e.errno, e.strerror or os.strerror(e.errno), str(path))


@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike, *, suffix: str = ".tmp", parents: bool = False
) -> Iterator[str]:
    """Yield a file name for the writer; on success its content is at ``path``.

    For a regular (or new) ``path`` the name is a temporary file beside it, renamed over
    it on success; for a device or FIFO it is the device itself (see the module doc).
    ``suffix`` is the temporary file's extension, for writers that choose the format
    from it (matplotlib, Chromium screenshots).  ``parents=True`` creates missing
    folders; otherwise a missing folder raises FileNotFoundError, so that a mistyped
    ``-o`` path is an error rather than a new folder.  On any exception,
    KeyboardInterrupt included, the temporary file is removed and ``path`` is left as
    it was.  An OSError of the writer about the file it was given (or about no file: a
    full disk) is raised again naming ``path``.  A ``path`` that ends with a separator
    names a folder (``-o out/``): NotADirectoryError, never the file ``out``.
    """
    raw = os.fspath(path)
    if names_a_folder(raw) and not os.path.isdir(raw):
        why = "a name that ends with / is a folder's; give a file name"
        raise NotADirectoryError(errno.ENOTDIR, why, raw)
    path = Path(path)
    name = None  # what the writer was given, once it has been
    try:
        if parents:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
            except (FileExistsError, NotADirectoryError):  # a file where a folder goes
                file = next(p for p in (path.parent, *path.parent.parents) if p.exists())
                why = f"{file} is a file, not a folder"
                raise NotADirectoryError(errno.ENOTDIR, why, str(path)) from None
        real, st, replace = _destination(path)
        if not replace:
            name = str(real)
            yield name
            return
        fd, tmp = tempfile.mkstemp(dir=real.parent, prefix=f".{real.name}.", suffix=suffix)
        os.close(fd)
        try:
            name = tmp
            yield tmp
            name = None
            fd = os.open(tmp, os.O_RDWR)  # the writer may have closed its handle
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            os.chmod(tmp, stat.S_IMODE(st.st_mode) if st else 0o666 & ~_umask())
            os.replace(tmp, real)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
        _fsync_dir(real.parent)
    except OSError as e:
        if name is not None and e.filename is not None and str(e.filename) != name:
            raise  # the writer's own trouble with some other file
        raise _renamed(e, path) from e


_SEPARATORS = tuple(s for s in (os.sep, os.altsep) if s)


def names_a_folder(path: str | os.PathLike) -> bool:
    """Whether the name ``path`` is spelled as a folder's: it ends with a separator, or
    its last part is "." or "..".  ``Path`` drops both, so ``-o out/`` wrote, or
    replaced, the file ``out``."""
    raw = os.fspath(path)
    return raw.endswith(_SEPARATORS) or os.path.basename(raw) in (".", "..")


def check_output_folder(out: str, flag: str = "-o") -> None:
    """Before any work, an output file's name: InputError naming ``flag`` when it is
    spelled as a folder's (:func:`names_a_folder`, and no folder is there) or its folder
    does not exist (or is a file)."""
    from neural_brdf.errors import InputError

    if names_a_folder(out) and not os.path.isdir(out):
        raise InputError(f"{flag} {out}: a folder's name; give a file name")
    parent = Path(out).parent
    if not parent.is_dir():
        why = f"{parent} is a file, not a folder" if parent.exists() else f"no folder {parent}"
        raise InputError(f"{flag} {out}: cannot write ({why})")


# the temporary file atomic_path writes beside NAME: .NAME.<mkstemp's 8 characters>.tmp
_TEMPORARY = re.compile(r"\.(.+)\.[a-z0-9_]{8}\.tmp")


def temporary_of(name: str) -> str | None:
    """The file name whose write through :func:`atomic_path` (default suffix) left the
    temporary file ``name`` behind (a process killed mid-write), or None if ``name`` is
    not such a file.  The naming rule lives here, beside the writer."""
    m = _TEMPORARY.fullmatch(name)
    return m.group(1) if m else None


def _write_all(name: str, payload: bytes) -> None:
    fd = os.open(name, os.O_WRONLY | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0))
    try:
        view = memoryview(payload)
        while view:
            view = view[os.write(fd, view) :]
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, data: bytes | str, *, parents: bool = False) -> None:
    """Write ``data`` (str is encoded as UTF-8) to ``path`` atomically (see atomic_path)."""
    payload = data.encode("utf-8") if isinstance(data, str) else data
    with atomic_path(path, parents=parents) as name:
        _write_all(name, payload)


def atomic_write_all(payloads: dict[str, bytes]) -> None:
    """Each file of ``payloads`` (path -> bytes) atomically (see atomic_path), and all of
    them or none: every one is written to its temporary file before the first is
    renamed, and a failed write removes them all (a textured model's code and textures)."""
    with contextlib.ExitStack() as stack:
        for path, payload in payloads.items():
            _write_all(stack.enter_context(atomic_path(path)), payload)


# ------------------------------------------------------------------ reading
class NotAFileError(OSError):
    """A file to read is a FIFO, a device or a socket: ``str()`` is the one-line
    message, ``PATH: is a FIFO, not a file``."""

    def __str__(self) -> str:
        return f"{self.filename}: {self.strerror}"


_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _not_a_file(path: str | os.PathLike, mode: int) -> NotAFileError | None:
    for test, kind in _KINDS:
        if test(mode):
            return NotAFileError(errno.EINVAL, f"is {kind}, not a file", os.fspath(path))
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        return NotAFileError(errno.EINVAL, "is not a regular file", os.fspath(path))
    return None


def open_for_reading(path: str | os.PathLike) -> BinaryIO:
    """``open(path, "rb")`` for a regular file (links followed), never blocking: a FIFO,
    a device (``/dev/zero``) or a socket raises :class:`NotAFileError` before anything
    is read (the file is opened non-blocking and checked with fstat), a folder
    IsADirectoryError, a missing file FileNotFoundError."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise _renamed(e, Path(path)) from None
    bad = _not_a_file(path, st.st_mode)  # a socket cannot even be opened
    if bad is not None:
        raise bad
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), os.fspath(path))
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(path, flags)
    try:
        st = os.fstat(fd)  # what was opened: the path may have changed since the stat
        bad = _not_a_file(path, st.st_mode)
        if bad is not None:
            raise bad
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), os.fspath(path))
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_capped(path: str | os.PathLike, limit: int) -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_for_reading`), at most
    ``limit + 1`` of them: a result longer than ``limit`` means the file is larger."""
    with open_for_reading(path) as fh:
        return fh.read(limit + 1)


# ------------------------------------------------------------------ JSON reports
def jsonable(value: object) -> object:
    """``value`` as JSON types: numpy scalars and arrays, tuples and paths converted, and
    a float that is not finite as the text Python writes for it ("nan", "inf", "-inf"),
    at any depth.  Strict JSON has no NaN or Infinity; a string keeps what a null would
    lose (which one it was).  The reports (metrics.json, ``validate --json``, a sweep's
    results) go through here; model.onnx's metadata keeps its own documented rule
    (fileformat.metadata.encode: null inside objects, docs/portable.md)."""
    if isinstance(value, float):
        return float(value) if math.isfinite(value) else repr(float(value))
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    tolist = getattr(value, "tolist", None)  # numpy arrays and scalars, torch tensors
    if callable(tolist):
        return jsonable(tolist())
    return value


def json_text(value: object, *, indent: int | None = 2) -> str:
    """Strict JSON text of ``value`` (:func:`jsonable`), with a final newline."""
    return json.dumps(jsonable(value), indent=indent, allow_nan=False) + "\n"
