"""Atomic file writes: every file the package writes goes through here.

    atomic_write(path, b"...")             # bytes or str (UTF-8)
    with atomic_path(path) as tmp:         # for writers that want a file name
        torch.save(state, tmp)

The data goes to a temporary file in the destination folder, is flushed and fsynced,
gets the permissions a plain ``open(path, "w")`` would give (0o666 less the umask;
``mkstemp`` alone leaves 0o600), and is renamed over ``path`` with ``os.replace``,
which is atomic on POSIX.  The folder is then fsynced so that the rename itself
survives a power cut.  A reader therefore sees the old file or the new one, never a
torn one, and a crash or Ctrl-C mid-write leaves no temporary file behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

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


@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike, *, suffix: str = ".tmp", parents: bool = False
) -> Iterator[str]:
    """Yield a temporary file name beside ``path``; on success it replaces ``path``.

    ``suffix`` is the temporary file's extension, for writers that choose the format
    from it (matplotlib, Chromium screenshots).  ``parents=True`` creates missing
    folders; otherwise a missing folder raises FileNotFoundError, so that a mistyped
    ``-o`` path is an error rather than a new folder.  On any exception,
    KeyboardInterrupt included, the temporary file is removed and ``path`` is left as
    it was.
    """
    path = Path(path)
    if parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:  # the writer may have closed its handle
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


def atomic_write(path: str | os.PathLike, data: bytes | str, *, parents: bool = False) -> None:
    """Write ``data`` (str is encoded as UTF-8) to ``path`` atomically (see atomic_path)."""
    payload = data.encode("utf-8") if isinstance(data, str) else data
    with atomic_path(path, parents=parents) as tmp, open(tmp, "wb") as fh:
        fh.write(payload)
