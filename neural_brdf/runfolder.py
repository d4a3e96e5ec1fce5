"""A run folder: its file names, its lock, and when a run may write into it.

    with runfolder.hold(run_dir, resume=False, overwrite=False) as folder:  # lock + rules
        folder.start(cfg.to_yaml())     # marker, config.yaml (an old run removed first)
        ... write folder.ckpt, folder.log, folder.model, ...

Every name a run writes is here (``CONFIG``, ``CKPT``, ``LOG``, ``MODEL``, ``METRICS``,
``REPORT_HTML``, ``REPORT_MD``, ``REPORT_PNGS``, ``VIEWER``, a projected textured run's
``TEXTURED``, an images fit's ``COVERAGE``, ``DETERMINED`` and ``INIT`` folder, ``LOCK``
and ``MARKER``);
:func:`own_files` lists those a folder holds.

Which folders a run writes into.  A run writes only into a folder that is new, empty,
or recognised as a run, and never over a file it did not write:

* a run folder is one holding ``MARKER`` (``.neural-brdf-run``), which a run writes
  before anything else, or, as earlier versions left them, ``config.yaml`` and
  ``ckpt.pt`` together.  Such old folders are resumed and overwritten as before, and
  get the marker when a run writes into them again;
* any other folder that is not empty is refused (:class:`NotARunFolder`), even with
  ``overwrite`` or ``resume``: ``--out .`` in a project folder, or a folder of the
  user's own ``config.yaml``, ``log.csv`` or ``report.*``, is left as it is.  The
  lock file and a sweep's ``trial.json`` (which a run never writes) do not count;
* in a run folder, a fresh run (no ``resume``) is refused (:class:`RunExists`) when it
  holds results (``model.onnx``, ``metrics.json``: finished) or a checkpoint
  (unfinished), unless ``overwrite``.  ``overwrite`` removes every file the old run
  wrote, the checkpoint and viewer.html included, in one step that Ctrl-C and SIGTERM
  do not split, just before the new run's marker and config.yaml are written
  (:meth:`Folder.start`): an interrupted replacement leaves the folder the new run,
  never an old checkpoint beside a new config.  Nothing is removed before that, so an
  error in the input (a config, an image) leaves the old run whole.

The lock: a run holds ``RUN_DIR/.lock`` (an ``fcntl.flock``, its pid inside) from
start to end, so a second run into the same folder stops at once (:class:`RunLocked`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import stat
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neural_brdf import config as cfgmod
from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write, temporary_of

fcntl: Any
try:
    import fcntl
except ImportError:  # Windows: runs are not locked
    fcntl = None

# ------------------------------------------------------------------ the names
MARKER = ".neural-brdf-run"  # written first: "this folder is a run"
CONFIG = "config.yaml"  # the resolved config
CKPT = "ckpt.pt"  # the checkpoint
# metrics.json's key for the sha256 of the model.onnx it describes: a report of a run
# whose model.onnx was re-exported or replaced since is refused (viewer/report/run.py)
MODEL_DIGEST = "model_sha256"
TEXTURED = "textured.pt"  # a projected textured run's final model (train/textured_store.py)
LOG = "log.csv"  # the training log
MODEL = "model.onnx"  # the exported model
METRICS = "metrics.json"  # the validation report
COVERAGE = "coverage.png"  # an images fit's map of the observed (wi, wo) domain
DETERMINED = "determined.png"  # ... and of where they determine f near the fitted network
REPORT_HTML = "report.html"
REPORT_MD = "report.md"
# the markdown report's images, report-<key>.png: every key the report has ever written
# (a key the report adds is registered here, or the report refuses it), so --overwrite
# removes these and no other file of the user's that starts with report-
REPORT_IMAGES = (
    "albedo",
    "loss",
    "slices",
    "lobes",
    "rusinkiewicz",
    "render",
    "images-loss",
    "coverage",
    "determined",
)
REPORT_PNGS = tuple(f"report-{key}.png" for key in REPORT_IMAGES)
VIEWER = "viewer.html"  # the interactive viewer, beside the report
INIT = "init"  # an images fit's start: a run folder of its own, inside this one
TEACHER = "teacher.xml"  # in INIT: the fitted Mitsuba BSDF a start is distilled from
LOCK = ".lock"  # while a run holds the folder: its pid

# the files of a run (INIT aside), the order in which --overwrite removes them: the
# checkpoint first, the marker last
FILES = (
    CKPT,
    TEXTURED,
    MODEL,
    METRICS,
    LOG,
    COVERAGE,
    DETERMINED,
    REPORT_HTML,
    REPORT_MD,
    VIEWER,
    TEACHER,
    CONFIG,
    MARKER,
)
FINISHED = (MODEL, METRICS)  # a run that has written these has finished
# Present in a folder without making it someone else's: the lock, and a sweep's record
# of its trial (tooling/sweep/spec.py's MARKER), written before its run starts.  A run
# writes neither over a file of the user's.
COMPANIONS = (LOCK, "trial.json")


def _temporary_of_own(name: str) -> bool:
    """A temporary file of fileio.atomic_write for one of a run's files, left by a
    process killed mid-write (``.config.yaml.k7x2a9q1.tmp``)."""
    of = temporary_of(name)
    return of is not None and _own_name(of)


def _own_name(name: str) -> bool:
    return name in FILES or name in REPORT_PNGS


def default_run_dir(cfg: cfgmod.Config) -> Path:
    """Where a run goes without ``--out``: ``runs/<name>/``."""
    return Path("runs") / cfg.name


# ------------------------------------------------------------------ what a folder is
class RunExists(InputError):
    """A fresh run would replace a finished or unfinished one (exit code 2)."""


class NotARunFolder(InputError):
    """The folder holds files no run wrote: a run does not write there (exit code 2)."""


def is_run(run_dir: Path) -> bool:
    """Is ``run_dir`` a run folder: its marker, or an earlier version's config.yaml
    and ckpt.pt?"""
    return os.path.lexists(run_dir / MARKER) or (
        os.path.lexists(run_dir / CONFIG) and os.path.lexists(run_dir / CKPT)
    )


def _our_lock(path: Path) -> bool:
    """A lock file as :func:`run_lock` leaves it: small, a pid or nothing inside."""
    try:
        if not stat.S_ISREG(os.lstat(path).st_mode) or path.stat().st_size > 32:
            return False
        text = path.read_bytes().strip()
    except OSError:
        return False
    return text.isdigit() or not text


def foreign_entries(run_dir: Path) -> list[str]:
    """The names in ``run_dir`` that keep it from being a new run's folder: [] for a
    missing or empty folder (companions aside) or a run folder."""
    if not run_dir.is_dir() or is_run(run_dir):
        return []
    return [n for n in sorted(os.listdir(run_dir)) if not _companion(run_dir, n)]


def _companion(run_dir: Path, name: str) -> bool:
    """Does ``name`` leave ``run_dir`` a folder a new run may use?"""
    if name == LOCK:
        return _our_lock(run_dir / name)
    return name in COMPANIONS or _temporary_of_own(name)


def check_writable(run_dir: Path) -> None:
    """Raise :class:`NotARunFolder` (one line naming the folder and a file in it) when
    ``run_dir`` is a folder that is neither empty nor a run."""
    if os.path.lexists(run_dir) and not run_dir.is_dir():
        raise InputError(f"{run_dir}: is a file, not a run folder (choose another --out)")
    foreign = foreign_entries(run_dir)
    if not foreign:
        return
    own = [n for n in foreign if _own_name(n)]
    shown = (own or foreign)[0]
    what = "which no run wrote here" if own else "and no run"
    raise NotARunFolder(
        f"{run_dir}: not a run folder (it holds {shown}, {what}); a run writes only into "
        "a new or empty folder or its own run folder: choose another --out"
    )


def check_fresh_run_dir(run_dir: Path, *, resume: bool, overwrite: bool) -> None:
    """Refuse a folder a run may not write into (:func:`check_writable`), and a fresh
    run (no ``resume``) over a finished or unfinished run unless ``overwrite``.  Changes
    nothing: ``overwrite`` removes the old run later, in :meth:`Folder.start`."""
    check_writable(run_dir)
    if resume or overwrite or not is_run(run_dir):
        return
    finished = [n for n in FINISHED if os.path.lexists(run_dir / n)]
    if finished:
        raise RunExists(
            f"{run_dir}: holds a finished run ({finished[0]}); choose another "
            "--out, continue it with --resume, or replace it with --overwrite"
        )
    if os.path.lexists(run_dir / CKPT):
        raise RunExists(
            f"{run_dir}: holds an unfinished run ({CKPT}); continue it with "
            "--resume or replace it with --overwrite"
        )


def own_files(run_dir: str | os.PathLike) -> list[Path]:
    """The files of the run in ``run_dir`` that exist: config.yaml, ckpt.pt, log.csv,
    model.onnx, metrics.json, the report and its PNGs, viewer.html, the marker, and the
    files of an images fit's ``init/`` run; [] when ``run_dir`` is not a run folder.
    The lock and files the run did not write (a user's notes) are not listed."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir() or not is_run(run_dir):
        return []
    out = [run_dir / n for n in FILES if os.path.lexists(run_dir / n)]
    out += [run_dir / n for n in REPORT_PNGS if os.path.lexists(run_dir / n)]
    if (run_dir / INIT).is_dir() and not (run_dir / INIT).is_symlink():
        out += own_files(run_dir / INIT)
    return out


def is_own_file(path: str | os.PathLike) -> bool:
    """Is ``path`` one of a run's files in a run folder (existing or not): the check
    for an output that would replace a run's own file (``export RUN -o RUN/ckpt.pt``)."""
    path = Path(path)
    parent = path.parent
    # its companions too: a lock replaced by rename is no lock (the run holds the old one)
    own = _own_name(path.name) or path.name in COMPANIONS
    if parent.name == INIT and is_run(parent.parent):
        return own
    return parent.is_dir() and is_run(parent) and own


# ------------------------------------------------------------------ signals
@contextmanager
def held_signals() -> Iterator[None]:
    """Ctrl-C (SIGINT) and SIGTERM wait until the block ends (main thread only), then
    act as they would have: a few file operations that must not be split."""
    signals = (signal.SIGINT, signal.SIGTERM)
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in signals}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, signal.SIG_DFL if h is None else h)
        for signum in dict.fromkeys(caught):  # each once, in order
            signal.raise_signal(signum)


# ------------------------------------------------------------------ a folder in use
@dataclass
class Folder:
    """A run folder a run writes into: its paths, and :meth:`start`, which makes it
    this run's (``replace``: removing the old run's files first)."""

    path: Path
    replace: bool = False  # remove an old run's files at start (overwrite)

    @property
    def config(self) -> Path:
        return self.path / CONFIG

    @property
    def ckpt(self) -> Path:
        return self.path / CKPT

    @property
    def log(self) -> Path:
        return self.path / LOG

    @property
    def model(self) -> Path:
        return self.path / MODEL

    @property
    def metrics(self) -> Path:
        return self.path / METRICS

    @property
    def init(self) -> Path:
        return self.path / INIT

    @classmethod
    def open(cls, run_dir: str | os.PathLike, *, resume: bool, overwrite: bool) -> Folder:
        """The folder ``run_dir`` for a run, after :func:`check_fresh_run_dir`.  A fresh
        run in a run folder replaces what is there (an overwritten run, or one that
        left no checkpoint and no results)."""
        path = Path(run_dir)
        check_fresh_run_dir(path, resume=resume, overwrite=overwrite)
        return cls(path, replace=not resume and path.is_dir() and is_run(path))

    def start(self, config_text: str) -> None:
        """The run's first writes: with ``replace``, remove the old run's files (its
        checkpoint first, its ``init/`` run too); then the marker and config.yaml.  All
        in one step for Ctrl-C and SIGTERM (:func:`held_signals`)."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise InputError(
                f"{self.path}: is a file, not a run folder (choose another --out)"
            ) from None
        except OSError as e:
            raise InputError(f"{self.path}: cannot create the run folder ({e.strerror})") from None
        check_writable(self.path)  # the folder may have changed since open
        with held_signals():
            if self.replace:
                remove_run(self.path)  # its temporaries too
                self.replace = False
            else:
                remove_stale_temporaries(self.path)  # a resumed run's: a killed write's
            if not os.path.lexists(self.path / MARKER):
                atomic_write(self.path / MARKER, marker_text())
            atomic_write(self.config, config_text)


def marker_text() -> str:
    from neural_brdf.version import __version__

    return (
        f"This folder is a run of neural-brdf {__version__} (docs/cli.md, 'The run "
        "directory'): --resume and --overwrite work here.\n"
    )


def remove_run(run_dir: Path) -> None:
    """Remove the files a run wrote in ``run_dir`` (:func:`own_files`, the marker
    last) and its leftover temporary files; keep everything else.  A device or FIFO
    in a run file's place (directly or through a link) is kept: a run writes into it
    in place, and it holds no old state."""
    for path in own_files(run_dir):
        if path.name == MARKER and path.parent == run_dir:
            continue
        _remove(path)
    init = run_dir / INIT
    if init.is_dir() and not init.is_symlink():
        with contextlib.suppress(OSError):
            init.rmdir()  # only if the init run left nothing of the user's there
    remove_stale_temporaries(run_dir)
    _remove(run_dir / MARKER)


def _remove(path: Path) -> None:
    """Unlink a run's file (or the link in its place); keep a device, a FIFO, a socket
    or a folder that has a run file's name."""
    try:
        mode = os.stat(path).st_mode  # links followed: a link to /dev/full is kept
    except FileNotFoundError:
        mode = stat.S_IFREG  # a dangling link: removed
    if stat.S_ISREG(mode):
        path.unlink(missing_ok=True)


# ------------------------------------------------------------------ the lock
class RunLocked(InputError):
    """Another process is running in the same run directory (exit code 2)."""


@contextmanager
def run_lock(
    run_dir: Path, *, elsewhere: str = "choose another --out", holder: str = "run"
) -> Iterator[None]:
    """Create ``run_dir`` if needed and hold ``run_dir/.lock`` (an exclusive
    ``fcntl.flock``, the holder's pid written inside) until the block ends.

    A second holder raises :class:`RunLocked` at once, naming the first one's pid and
    ending with ``elsewhere`` (the command's own way out: its flag).  The lock dies with
    its process (even by SIGKILL), so a stale ``.lock`` file is no obstacle.  The file
    is removed on release, and a folder this call created is removed again if the run
    left it empty (an error before anything was written).  A folder this process cannot
    write (a read-only mount, another user's run) is not locked: nothing here can be
    written by it, so there is nothing to guard, and a command that only reads (a
    finished run's ``--resume``) runs; a write fails later naming its own file.
    """
    created = not run_dir.exists()
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{run_dir}: is a file, not a run folder (choose another --out)") from None
    except OSError as e:
        raise InputError(f"{run_dir}: cannot create the run folder ({e.strerror})") from None
    path = run_dir / LOCK
    fd = _lock_fd(run_dir, path, elsewhere, holder)
    if fd is None:  # a folder this process cannot write: unlocked
        yield
        return
    with contextlib.suppress(OSError):  # the pid only names the holder to a second run
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # before the unlock (above: a waiter then locks anew)
        os.close(fd)
        if created:
            with contextlib.suppress(OSError):
                run_dir.rmdir()  # only if empty


def _lock_fd(run_dir: Path, path: Path, elsewhere: str, holder: str = "run") -> int | None:
    """The open, locked lock file of :func:`run_lock`, or None where ``run_dir`` cannot
    be written by this process (:func:`_unwritable`)."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as e:
            if _unwritable(run_dir, e):
                return None
            raise InputError(f"{path}: cannot create the run's lock file ({e.strerror})") from None
        if fcntl is None:
            break
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = os.read(fd, 32).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise RunLocked(
                f"{run_dir}: in use by another {holder} (pid {pid}); wait for it to end "
                f"or {elsewhere}"
            ) from None
        except OSError:  # a file system without flock (some network mounts): unlocked
            break
        # The holder before us may have removed the file between our open and our lock:
        # then we hold a lock on a deleted file, and must lock the path's new file.
        try:
            if os.path.samestat(os.fstat(fd), os.stat(path)):
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    return fd


def _unwritable(folder: Path, e: OSError) -> bool:
    """Whether a failure ``e`` to create a file in ``folder`` means that this process
    can write nothing there: a read-only file system, or a folder it may not write
    (not a lock file of another user's in a folder it may write: that one is a run)."""
    if e.errno == errno.EROFS:
        return True
    return e.errno in (errno.EACCES, errno.EPERM) and not os.access(folder, os.W_OK | os.X_OK)


@contextmanager
def hold(run_dir: str | os.PathLike, *, resume: bool, overwrite: bool) -> Iterator[Folder]:
    """Lock ``run_dir`` (:func:`run_lock`) and open it for a run (:meth:`Folder.open`).
    A folder that is not a run's is refused before the lock file is created in it."""
    path = Path(run_dir)
    check_writable(path)
    with run_lock(path):
        yield Folder.open(path, resume=resume, overwrite=overwrite)


def remove_stale_temporaries(run_dir: Path) -> None:
    """Remove the temporary files of a run's own files (:func:`_temporary_of_own`) that a
    process killed mid-write left in ``run_dir`` (SIGKILL, OOM, a power cut: a checkpoint's
    is as large as the checkpoint); by :func:`remove_run` (an overwrite) and by
    :meth:`Folder.start` when a resumed run begins to train (not a refused run, nor the
    resume of a finished one, which touch nothing), with the folder's lock held.  A
    folder that is not a run's is left alone."""
    if not is_run(run_dir):
        return
    for name in os.listdir(run_dir):
        if _temporary_of_own(name):
            with contextlib.suppress(OSError):  # garbage: a folder read-only since keeps it
                _remove(run_dir / name)
