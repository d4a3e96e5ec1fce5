"""One training session: the frame every training loop runs in (issue 28).

    sess = Session.one(cfg, run_dir, resume=resume)        # or a runfolder.Folder
    ckpt = sess.resumed()                                    # the checkpoint, when resuming
    sess.begin()                                             # marker, config.yaml
    ... build the model; if ckpt: load it, sess.restore(ckpt) ...
    with sess.run(state) as s:                               # ckpt.pt, log.csv, progress
        while s.step < cfg.train.steps:
            s.stop_if_interrupted()                          # Ctrl-C / SIGTERM: saved, raised
            ... one optimisation step ...
            s.advance()
            if s.due(cfg.train.log_every):
                s.log(loss=..., lr=...)
            if s.due(cfg.train.checkpoint_every):
                s.checkpoint()

:func:`neural_brdf.train.loop.train` (BRDF samples), :func:`neural_brdf.train.many.train_many`
(many materials in one loop: one :class:`RunFiles` each, written once at the end) and
:func:`neural_brdf.inverse.fit.fit_neural` (images) all run in a :class:`Session`.  It
owns what they share and nothing of what they train:

* the run's files (:class:`RunFiles`, in a :class:`neural_brdf.runfolder.Folder`): the
  first writes (the folder's marker and config.yaml, an overwritten run removed first),
  the checkpoint (written atomically, read with ``weights_only=True``; ``kind`` tells an
  images fit's from a sample-based one), the resume checks (format version, the settings
  in ``MUST_MATCH``, the target's files unchanged, ``train.steps`` not below the
  checkpoint's step), log.csv (one ``LOG_COLUMNS``, plus the columns a loop adds:
  ``columns``; the rows of a resumed run kept up to its step);
* the loop's frame: the step and the training time (a resumed run's included), the
  progress bar, Ctrl-C and SIGTERM deferred to the end of the step (:func:`deferred_interrupt`:
  a checkpoint, then :class:`Interrupted`; a second signal aborts at once), and the
  divergence errors (:class:`Diverged`, naming the step and the last good checkpoint).

What a loop saves beyond the common keys (format_version, kind, step, config,
train_seconds, and ``target_files``: the sha256 of each file the target reads,
:mod:`neural_brdf.train.target_files`, compared on resume) is its ``state()``: weights,
optimizer, pool, lobe, and so on.
"""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import torch
from tqdm import tqdm

from neural_brdf import config as cfgmod
from neural_brdf import runfolder
from neural_brdf.errors import Diverged, InputError, Interrupted
from neural_brdf.fileformat import FORMAT_VERSION
from neural_brdf.fileio import atomic_write
from neural_brdf.train import target_files

# log.csv's columns; a loop may add its own after them (``columns``)
LOG_COLUMNS = ("step", "loss", "lr", "seconds", "val_rel_rmse")
# Settings a resumed run must share with its checkpoint (the rest may change, e.g. steps).
MUST_MATCH = ("target", "model", "data", "train.seed", "train.loss", "train.loss_eps")
# What trained a checkpoint (its "kind" key; none: BRDF samples), in the resume errors.
KINDS = {
    None: "a training from BRDF samples",
    "images": "an images fit",
    "textured": "a textured model's training (a spatially varying teacher)",
}
# ... and what a textured run's must share too (train.textured_loop)
TEXTURED_MUST_MATCH = (*MUST_MATCH, "texture")
# A checkpoint's key (and metrics.json's training key) of the run's resumes: for each,
# its step and the settings changed there, dotted key -> [before, after] (a resume may
# change what is not in MUST_MATCH: train.lr, say; config.yaml then holds the new value,
# so this is what tells the weights' own history)
RESUMES = "resumes"
# A checkpoint's key of the target's files, path -> sha256 (train.target_files.digest),
# compared on resume; absent from a checkpoint written before it (then not compared)
TARGET_FILES = "target_files"


# ------------------------------------------------------------------ checkpoints
class CheckpointError(InputError):
    """A run directory or checkpoint is missing or unusable."""


def save_checkpoint(path: Path, state: dict) -> None:
    """Write a checkpoint atomically.  It is serialised in memory first: torch.save's
    own file writer reports a full disk as a RuntimeError without the errno, and
    atomic_write raises an OSError naming ``path`` (ENOSPC: "No space left on device")."""
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write(path, bytes(buf.getbuffer()))


def load_checkpoint(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint (train first, or check the run directory)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several unrelated types on a corrupt file
        raise CheckpointError(f"{path}: unreadable checkpoint ({type(e).__name__})") from None


def _get(d: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        d = d.get(part) if isinstance(d, dict) else None
    return d


def _with_defaults(saved: dict) -> dict:
    """A checkpoint's config as this version reads it: a key added since it was saved
    (texture.lobe_color, say) takes its default, as loading that config would give it.
    The saved dict unchanged where it no longer validates (a key since removed, a target
    file since moved): then the comparison is of what was saved."""
    try:
        out = cfgmod.Config.model_validate(saved).model_dump()
    except Exception:  # pydantic's ValidationError and the validators' own errors
        return saved
    # a target.data saved relative, as it was read before paths were made absolute
    # (config.paths_relative_to): the current folder's, by the rule of its time (that
    # key alone: a relative target.mitsuba or target.images of a config built in Python
    # is compared as saved, with the one resumed)
    data = {"target": {"data": out["target"].get("data")}}
    cfgmod.paths_relative_to(data, Path.cwd())
    out["target"]["data"] = data["target"]["data"]
    return out


def check_resumable(
    saved: dict,
    cfg: cfgmod.Config,
    must_match: Sequence[str] = MUST_MATCH,
    *,
    what: str = "the checkpoint being resumed",
) -> None:
    """ConfigError naming the first key of ``must_match`` on which ``cfg`` differs from
    the ``saved`` config of a checkpoint (``what``, in the message)."""
    now = _with_defaults(cfg.model_dump())  # (a config built in Python may name it relative)
    saved = _with_defaults(saved)
    for key in must_match:
        there, here = _get(saved, key), _get(now, key)
        if there != here:
            path, there, here = _first_difference(there, here, key)
            raise cfgmod.ConfigError(
                f"{path}: differs from {what} ({there!r} there, {here!r} here)"
            )


def _first_difference(a: Any, b: Any, path: str) -> tuple[str, Any, Any]:
    """Where two different config values first differ, as deep as both go (the leaf,
    ``target.images[0].scene``, say, not the section): the path and the two values
    there.  A key one side lacks, or lists of two lengths, stop at their parent."""
    if isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys():
        k = next(k for k in a if a[k] != b[k])
        return _first_difference(a[k], b[k], f"{path}.{k}")
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        i = next(i for i, (x, y) in enumerate(zip(a, b)) if x != y)
        return _first_difference(a[i], b[i], f"{path}[{i}]")
    return path, a, b


def _leaves(d: Any, prefix: str = "") -> dict[str, Any]:
    """A nested dict's values by dotted key (a list is a leaf)."""
    if not isinstance(d, dict) or not d:
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def config_changes(saved: dict, cfg: cfgmod.Config) -> dict[str, list[Any]]:
    """The settings on which ``cfg`` differs from a checkpoint's ``saved`` config,
    dotted key -> [there, here], sorted (a key either lacks: None on that side)."""
    before, after = _leaves(_with_defaults(saved)), _leaves(_with_defaults(cfg.model_dump()))
    return {
        k: [before.get(k), after.get(k)]
        for k in sorted(before.keys() | after.keys())
        if before.get(k) != after.get(k)
    }


def _short(v: Any) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


def target_file_problems(saved: Any, cfg: cfgmod.Config) -> Iterator[str]:
    """One line for each file of ``saved`` (a checkpoint's :data:`TARGET_FILES`: path
    -> sha256) that is gone, unreadable or whose bytes differ now, naming its key; none
    for a checkpoint of an earlier version (``saved`` None)."""
    if not isinstance(saved, dict):
        return
    for path, sha in saved.items():
        key = target_files.where(cfg, path)
        try:
            now = target_files.sha256(path)
        except FileNotFoundError:
            yield f"{key}: {path} is gone since the checkpoint was written"
            continue
        except OSError as e:
            yield (
                f"{key}: {path}: cannot be read ({e.strerror or e}) to compare it with the "
                "checkpoint's"
            )
            continue
        if now != sha:
            yield f"{key}: {path} changed since the checkpoint was written (sha256 differs)"


def check_target_files(saved: Any, cfg: cfgmod.Config) -> None:
    """ConfigError naming the first file of ``saved`` (a checkpoint's
    :data:`TARGET_FILES`: path -> sha256) that is gone or whose bytes differ now
    (:func:`target_file_problems`); a checkpoint of an earlier version (``saved`` None)
    is not checked."""
    for problem in target_file_problems(saved, cfg):
        raise cfgmod.ConfigError(f"{problem}; train anew (--overwrite) or restore the file")


def load_resumable(
    cfg: cfgmod.Config,
    ckpt_path: Path,
    *,
    kind: str | None = None,
    must_match: Sequence[str] = MUST_MATCH,
) -> dict:
    """The checkpoint that ``cfg`` resumes: same format version, trained the same way
    (``kind``), not in a batch, the same ``must_match`` settings, the target's files
    as they were (:func:`check_target_files`), and ``train.steps`` not below its step
    (a resumed run only trains on)."""
    ckpt = load_checkpoint(ckpt_path)
    if ckpt.get("format_version") != FORMAT_VERSION:  # e.g. another encoding
        raise cfgmod.ConfigError(
            f"{ckpt_path}: written by format version {ckpt.get('format_version')}, this "
            f"is {FORMAT_VERSION}; it cannot be resumed: train anew (--overwrite)"
        )
    if ckpt.get("batched"):
        raise cfgmod.ConfigError(
            f"{ckpt_path}: trained in a batch of {ckpt['batched']} materials "
            "(neural_brdf.train.many), which keeps no optimizer or pool: it cannot be resumed: "
            "train anew (--overwrite)"
        )
    if ckpt.get("kind") != kind:
        were, now = (KINDS.get(k, f"a {k!r} run") for k in (ckpt.get("kind"), kind))
        raise cfgmod.ConfigError(
            f"{ckpt_path}: the checkpoint of {were}, and this run is {now}; it cannot "
            "be resumed: train anew (--overwrite)"
        )
    check_resumable(ckpt["config"], cfg, must_match)
    check_target_files(ckpt.get(TARGET_FILES), cfg)
    step = int(ckpt["step"])
    if cfg.train.steps < step:
        raise cfgmod.ConfigError(
            f"train.steps: {cfg.train.steps} is below the step of the checkpoint being "
            f"resumed ({step}, {ckpt_path}); a resumed run only trains on: give "
            f"train.steps >= {step}"
        )
    return ckpt


# metrics.json's key while its run writes its report (pipeline._record): such a run has
# not finished (a resume exports, validates and reports it again)
REPORT_PENDING = "report_pending"


def measured_another_model(metrics: dict, run_dir: Path) -> bool:
    """Whether ``metrics`` (a run's metrics.json) measured another model.onnx than the
    one in ``run_dir``: its ``model_sha256`` differs from the file's (``export RUN``
    after an edit of config.yaml, a file put there); False without the digest (a
    metrics.json written before it was kept).  OSError when the model cannot be read."""
    said = metrics.get(runfolder.MODEL_DIGEST)
    return said is not None and said != target_files.sha256(run_dir / runfolder.MODEL)


def remeasure_advice(run_dir: Path) -> str:
    """What measures and reports a run again whose metrics.json is of another model."""
    return (
        f"neural-brdf train {run_dir / runfolder.CONFIG} --out {run_dir} --resume exports, "
        "measures and reports the run again"
    )


def finished_report(run_dir: Path, step: int) -> dict | None:
    """The metrics.json of a run that finished at ``step`` (its model.onnx written
    too), or None: a run stopped before it finished exporting, validating or writing
    the report it was to write (:data:`REPORT_PENDING`), or one whose metrics.json
    measured another model.onnx (``export RUN`` after an edit of config.yaml: its
    ``--resume`` exports, measures and reports the run again)."""
    if not (run_dir / runfolder.MODEL).is_file():
        return None
    from neural_brdf.fileformat import reader

    try:  # an empty or truncated model.onnx (outside damage) is exported again
        reader.load(run_dir / runfolder.MODEL, external_data=False)
    except InputError:
        return None
    try:
        report = json.loads((run_dir / runfolder.METRICS).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    training = report.get("training") if isinstance(report, dict) else None
    if not isinstance(training, dict) or training.get("steps") != step:
        return None
    try:
        if measured_another_model(report, run_dir):
            return None
    except OSError:
        return None
    return None if report.get(REPORT_PENDING) else report


# ------------------------------------------------------------------ Ctrl-C and SIGTERM
INTERRUPT_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # Ctrl-C; docker, systemd, Slurm, Ray


def signal_name(signum: int | None) -> str:
    return "Ctrl-C" if signum in (None, signal.SIGINT) else signal.Signals(signum).name


def _abort(signum: int) -> KeyboardInterrupt:
    e = KeyboardInterrupt(f"{signal_name(signum)} again: aborted")
    e.signum = signum  # type: ignore[attr-defined]  # the CLI's exit code: 128 + signum
    return e


@contextmanager
def deferred_interrupt() -> Iterator[dict[str, Any]]:
    """Turn the first Ctrl-C (SIGINT) or SIGTERM into a flag checked between steps
    (main thread only): ``flag["set"]``, and ``flag["signum"]`` the signal.  A second
    one raises KeyboardInterrupt at once.  An :class:`Interrupted` raised in the block
    leaves it with ``e.signum`` set to the signal (the CLI exits with 128 + signum)."""
    flag: dict[str, Any] = {"set": False, "signum": None}
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        if flag["set"]:
            raise _abort(signum)
        flag["set"], flag["signum"] = True, signum

    previous = {s: signal.signal(s, handler) for s in INTERRUPT_SIGNALS}
    try:
        yield flag
    except Interrupted as e:
        if getattr(e, "signum", None) is None:
            e.signum = flag["signum"] or signal.SIGINT
        raise
    finally:
        for s, h in previous.items():
            signal.signal(s, signal.SIG_DFL if h is None else h)


deferred_sigint = deferred_interrupt  # the former name (SIGINT only)


def interrupted(flag: dict, step: int, ckpt_path: Path) -> Interrupted:
    """The Interrupted of a run stopped by ``flag`` (:func:`deferred_interrupt`) after
    ``step``, its checkpoint saved to ``ckpt_path``."""
    e = Interrupted(
        f"interrupted at step {step} ({signal_name(flag['signum'])}); checkpoint saved "
        f"to {ckpt_path}; continue with --resume"
    )
    e.signum = flag["signum"] or signal.SIGINT
    return e


def _cannot_write(path: Path, e: OSError) -> InputError:
    return InputError(f"{path}: cannot write ({e.strerror or e})")


# ------------------------------------------------------------------ one run's files
class RunFiles:
    """The files of one run in its folder: config.yaml, ckpt.pt, log.csv.

    ``kind``: what trains it (None: BRDF samples; "images": an images fit), saved in
    the checkpoint and checked on resume.  ``columns``: log.csv's columns (LOG_COLUMNS
    and any a loop adds after them; a resumed log's rows keep the columns they share)."""

    def __init__(
        self,
        cfg: cfgmod.Config,
        folder: runfolder.Folder,
        *,
        kind: str | None = None,
        columns: Sequence[str] = LOG_COLUMNS,
    ) -> None:
        self.cfg, self.folder, self.kind = cfg, folder, kind
        self.columns = list(columns)
        self._fh: IO[str] | None = None
        self._writer: csv.DictWriter | None = None
        self._digest: tuple[str, dict[str, str]] | None = None  # (target, its files')

    @property
    def ckpt_path(self) -> Path:
        return self.folder.ckpt

    @property
    def log_path(self) -> Path:
        return self.folder.log

    def begin(self) -> None:
        """The run's first writes: the folder's marker and config.yaml (an overwritten
        run's files removed first: :meth:`neural_brdf.runfolder.Folder.start`)."""
        self.folder.start(self.cfg.to_yaml())

    def target_digest(self) -> dict[str, str]:
        """The target's files and their sha256 (:func:`target_files.digest`), read
        once per target (at the first checkpoint: the files the run has just read)."""
        target = self.cfg.target.model_dump_json()
        if self._digest is None or self._digest[0] != target:
            self._digest = (target, target_files.digest(self.cfg))
        return self._digest[1]

    def state(self, step: int, seconds: float, extra: dict[str, Any]) -> dict[str, Any]:
        """A checkpoint: the common keys, then ``extra`` (the loop's own state)."""
        kind = {} if self.kind is None else {"kind": self.kind}
        return {
            "format_version": FORMAT_VERSION,
            **kind,
            "step": step,
            "config": self.cfg.model_dump(),
            "train_seconds": seconds,
            TARGET_FILES: self.target_digest(),
            **extra,
        }

    def save(self, state: dict[str, Any]) -> None:
        save_checkpoint(self.ckpt_path, state)

    def resumable(self, must_match: Sequence[str] = MUST_MATCH) -> dict:
        return load_resumable(self.cfg, self.ckpt_path, kind=self.kind, must_match=must_match)

    def format_row(self, values: dict[str, Any]) -> dict[str, str]:
        """A log.csv row: step as is, loss 6 digits, lr 4, seconds to 0.01 s, the
        held-out error 5 (empty when not measured); other columns 6 digits."""
        formats = {"step": "d", "loss": ".6g", "lr": ".4g", "seconds": ".2f", "val_rel_rmse": ".5g"}
        return {
            k: "" if v is None or v == "" else format(v, formats.get(k, ".6g"))
            for k, v in values.items()
        }

    def kept_rows(self, step: int, *, log_every: int | None = None) -> list[dict[str, str]]:
        """A resumed run's log.csv rows up to ``step``, its checkpoint's.  The log is
        appended to row by row, so a kill can cut its last line short: that line is
        dropped.  A log that is not one (no ``step`` column, a line before the
        checkpoint's step that is no row of it, steps out of order) is refused, naming
        it, rather than replaced by the rows it could read: the user moves it away.
        Rows missing before the checkpoint's step (a file cut short elsewhere, or empty)
        are said on stderr: more than ``log_every`` steps (the checkpoint's, which a
        resume may change; None: the config's) between the last row and that step."""
        path = self.log_path
        if not path.is_file():
            return []
        move = "move it away to resume (the checkpoint is kept)"
        try:
            with open(path, newline="", encoding="utf-8") as fh:
                text = fh.read()
            lines = list(csv.reader(io.StringIO(text, newline="")))
        except (OSError, UnicodeDecodeError, csv.Error) as e:
            raise InputError(f"{path}: cannot read it as the run's log ({e}); {move}") from None
        if len(lines) > 1 and not text.endswith(("\n", "\r")):
            lines = lines[:-1]  # a row is written with its newline: this one was cut short
        every = log_every if isinstance(log_every, int) else self.cfg.train.log_every
        if not lines:
            lines = [["step"]]  # an empty file: no rows (said below, when some are due)
        header = lines[0]
        if "step" not in header:
            raise InputError(
                f"{path}: not the run's log (no step column in its first line); {move}"
            )
        at = header.index("step")
        rows: list[dict[str, str]] = []
        for number, fields in enumerate(lines[1:], start=2):
            try:
                row_step = int(fields[at]) if len(fields) == len(header) else None
            except ValueError:
                row_step = None
            if row_step is not None and row_step > step:
                break  # rows after the checkpoint: written again
            if row_step is None or (rows and row_step <= int(rows[-1]["step"])):
                if number == len(lines):
                    break  # the last line cut short by a kill
                raise InputError(f"{path}: line {number} is not a row of the run's log; {move}")
            rows.append(dict(zip(header, fields, strict=True)))
        last = int(rows[-1]["step"]) if rows else 0
        if step - last > every:
            print(
                f"{path}: its rows end at step {last}, the checkpoint's is {step}: the rows "
                "between are missing from it (the file was cut short); the log goes on from there",
                file=sys.stderr,
            )
        return rows

    def open_log(self, rows: list[dict[str, str]]) -> None:
        """log.csv anew with ``rows`` (a resumed run's, up to its checkpoint), replaced
        whole (an interrupted resume keeps the old file), then appended to row by row."""
        try:
            head = io.StringIO(newline="")
            writer = csv.DictWriter(head, self.columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
            atomic_write(self.log_path, head.getvalue())
            self._fh = open(self.log_path, "a", newline="")
            self._writer = csv.DictWriter(self._fh, self.columns, extrasaction="ignore")
        except OSError as e:
            raise _cannot_write(self.log_path, e) from None

    def log(self, row: dict[str, str]) -> None:
        assert self._writer is not None and self._fh is not None, "log.csv is not open"
        try:
            self._writer.writerow(row)
            self._fh.flush()
        except OSError as e:
            raise _cannot_write(self.log_path, e) from None

    def close_log(self, *, ok: bool) -> None:
        fh, self._fh, self._writer = self._fh, None, None
        if fh is None:
            return
        try:
            fh.close()
        except OSError as e:  # a full disk: the buffered rows cannot be written
            if ok:
                raise _cannot_write(self.log_path, e) from None

    def write_log(self, rows: list[dict[str, str]]) -> None:
        """All of log.csv at once (atomically)."""
        buf = io.StringIO(newline="")
        w = csv.DictWriter(buf, self.columns, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        atomic_write(self.log_path, buf.getvalue())


# ------------------------------------------------------------------ the loop's frame
class Session:
    """The frame of one training loop over one run (:meth:`one`) or several trained
    together (``runs``: a batch, whose checkpoints the loop writes at the end:
    ``checkpoints=False``).  See the module doc."""

    def __init__(
        self,
        runs: Sequence[RunFiles],
        *,
        resume: bool = False,
        checkpoints: bool = True,
        desc: str | None = None,
    ) -> None:
        if not runs:
            raise ValueError("a session trains at least one run")
        self.runs = list(runs)
        self.resume = resume
        self.checkpoints = checkpoints
        self.train = runs[0].cfg.train
        self.desc = desc if desc is not None else runs[0].cfg.name
        self.step = 0
        self.seconds = 0.0  # training time: of the run so far, then of the whole run
        self.kept: list[list[dict[str, str]]] = [[] for _ in self.runs]
        self._logs_read = False  # a resumed run's rows read by begin(), before any write
        self._resumed: dict | None = None
        self.resumes: list[dict[str, Any]] = []  # RESUMES: the checkpoint's, then this one
        self._begun = False
        self._state: Callable[[], dict[str, Any]] | None = None
        self._flag: dict[str, Any] = {"set": False, "signum": None}
        self._bar: Any = None
        self._start = 0.0

    @classmethod
    def one(
        cls,
        cfg: cfgmod.Config,
        folder: runfolder.Folder | str | os.PathLike,
        *,
        resume: bool = False,
        kind: str | None = None,
        columns: Sequence[str] = LOG_COLUMNS,
        desc: str | None = None,
    ) -> Session:
        """The session of one run in ``folder``.  A path is opened here as a direct
        call's folder: a run in it is replaced (resumed with ``resume``), a folder of
        other files refused (:func:`neural_brdf.runfolder.check_writable`)."""
        if not isinstance(folder, runfolder.Folder):
            folder = runfolder.Folder.open(folder, resume=resume, overwrite=True)
        return cls([RunFiles(cfg, folder, kind=kind, columns=columns)], resume=resume, desc=desc)

    def reconfigure(self, cfg: cfgmod.Config) -> None:
        """The one run trains ``cfg`` from now on (an images fit's grid or encoding after its
        start: :func:`neural_brdf.inverse.starts.model_for_start`): its checkpoints record it and
        its config.yaml is written again (atomically), so that ``export``, ``report`` and
        ``--resume`` rebuild the network that was trained."""
        if len(self.runs) != 1:
            raise ValueError("reconfigure: a session of one run only")
        files = self.runs[0]
        files.cfg = cfg
        self.train = cfg.train
        files.folder.start(cfg.to_yaml())

    # the one run's files (a session of one run)
    @property
    def files(self) -> RunFiles:
        return self.runs[0]

    @property
    def ckpt_path(self) -> Path:
        return self.runs[0].ckpt_path

    @property
    def log_path(self) -> Path:
        return self.runs[0].log_path

    # ---------------------------------------------------------------- before the loop
    def resumed(self, checkpoint: dict | None = None, **kw: Any) -> dict | None:
        """The checkpoint this session resumes (``checkpoint`` when the caller has
        loaded it), checked (:func:`load_resumable`) once; None for a fresh run."""
        if not self.resume:
            return None
        if self._resumed is None:
            self._resumed = checkpoint if checkpoint is not None else self.files.resumable(**kw)
        return self._resumed

    def begin(self) -> None:
        """Every run's first writes (marker, config.yaml: :meth:`RunFiles.begin`), once.
        A resumed run's log.csv is read first (:meth:`RunFiles.kept_rows`): a log that
        cannot be resumed is refused before config.yaml takes the new settings."""
        if not self._begun:
            ckpt = self._resumed if self.resume else None
            if ckpt is not None:
                train = ckpt.get("config", {}).get("train", {})
                every = train.get("log_every") if isinstance(train, dict) else None
                for k, r in enumerate(self.runs):
                    self.kept[k] = r.kept_rows(int(ckpt["step"]), log_every=every)
                self._logs_read = True
            for r in self.runs:
                r.begin()
            self._begun = True

    def restore(self, ckpt: dict) -> None:
        """Take the step and the training time of the checkpoint being resumed, and say so,
        with the settings that changed since it was written (:func:`config_changes`):
        they are recorded with the step (:data:`RESUMES`, in every later checkpoint and
        in metrics.json's ``training.resumes``), since config.yaml keeps the new ones."""
        self.step, self.seconds = int(ckpt["step"]), float(ckpt["train_seconds"])
        earlier = ckpt.get(RESUMES)
        changed = config_changes(ckpt["config"], self.files.cfg)
        self.resumes = [*(earlier if isinstance(earlier, list) else [])]
        self.resumes.append({"step": self.step, "changed": changed})
        said = ""
        if changed:
            said = "; changed since it was written: " + ", ".join(
                f"{k} {_short(a)} -> {_short(b)}" for k, (a, b) in changed.items()
            )
            said += " (config.yaml holds the new values; metrics.json's training.resumes both)"
        print(
            f"{self.files.cfg.name}: resuming {self.ckpt_path} at step {self.step} of "
            f"{self.train.steps}{said}",
            file=sys.stderr,
        )

    def record(self) -> dict[str, Any]:
        """metrics.json's training keys of the session itself: its resumes, if any."""
        return {RESUMES: self.resumes} if self.resumes else {}

    # ---------------------------------------------------------------- the loop
    @contextmanager
    def run(self, state: Callable[[], dict[str, Any]] | None = None) -> Iterator[Session]:
        """The loop's frame.  ``state()``: the loop's part of a checkpoint (None: no
        checkpoints here).  On entry a fresh run's first checkpoint is written, log.csv
        opened (a resumed run's rows up to its step kept: :attr:`kept`), the progress bar
        shown and Ctrl-C / SIGTERM deferred; on exit the bar and the logs are closed
        and :attr:`seconds` is the run's training time."""
        self._state = state if self.checkpoints else None
        if self._state is not None and not self.resume:
            self.checkpoint(timed=False)
        if self.checkpoints:
            for k, r in enumerate(self.runs):
                if not self._logs_read:
                    self.kept[k] = r.kept_rows(self.step) if self.resume else []
                r.open_log(self.kept[k])
        self._bar = tqdm(
            total=self.train.steps,
            initial=min(self.step, self.train.steps),
            desc=self.desc,
            disable=self.train.bar_disabled(),
            dynamic_ncols=True,
            mininterval=0.5,
            leave=False,
        )
        self._start = time.perf_counter() - self.seconds
        ok = False
        try:
            with deferred_interrupt() as flag:
                self._flag = flag
                yield self
            ok = True
        finally:
            self._bar.close()
            for r in self.runs:
                r.close_log(ok=ok)
        self.seconds = self.elapsed()

    def elapsed(self) -> float:
        """Seconds of training, a resumed run's earlier ones included."""
        return time.perf_counter() - self._start

    def advance(self, n: int = 1) -> None:
        """``n`` steps done."""
        self.step += n
        self._bar.update(n)

    def due(self, every: int) -> bool:
        """Is this step one of every ``every``'s (or the last)?"""
        return self.step % every == 0 or self.step == self.train.steps

    def postfix(self, **values: str) -> None:
        self._bar.set_postfix(**values)

    def log(self, run: int = 0, **values: Any) -> None:
        """A log.csv row of run ``run`` at this step: ``loss``, ``lr``, ``val_rel_rmse``
        (None: not measured) and any column the loop added; ``seconds`` is the time."""
        row = {"step": self.step, "seconds": self.elapsed(), "val_rel_rmse": None, **values}
        self.runs[run].log(self.runs[run].format_row(row))

    def checkpoint(self, *, timed: bool = True) -> None:
        """Write the checkpoint(s) at this step (``timed``: the time so far saved)."""
        if self._state is None:
            return
        if timed:
            self.seconds = self.elapsed()
        extra = {**self._state(), **self.record()}
        self.files.save(self.files.state(self.step, self.seconds, extra))

    def stop_if_interrupted(self, before: Callable[[], None] | None = None) -> None:
        """After a Ctrl-C or SIGTERM: ``before()`` (a last check of the loss), a
        checkpoint, and :class:`Interrupted` (the CLI exits with 128 + the signal)."""
        if not self._flag["set"]:
            return
        if before is not None:
            before()
        if self._state is None:
            e = Interrupted(
                f"interrupted at step {self.step} ({signal_name(self._flag['signum'])}); "
                "a batched run keeps no checkpoint: run it again"
            )
            e.signum = self._flag["signum"] or signal.SIGINT
            raise e
        self.checkpoint()
        raise interrupted(self._flag, self.step, self.ckpt_path)

    # ---------------------------------------------------------------- divergence
    def _kept(self) -> str:
        if self._state is None:
            return f" in a batch of {len(self.runs)} materials (try a lower train.lr)"
        return f"; the last good checkpoint is kept in {self.ckpt_path} (try a lower train.lr)"

    def diverged(self, loss: float, step: int, *, exact: bool = True) -> Diverged:
        """A non-finite ``loss`` at ``step`` (``exact=False``: by then)."""
        return Diverged(f"loss is {loss} {'at' if exact else 'by'} step {step}{self._kept()}")

    def check_weights(self, finite: bool) -> None:
        """Diverged unless ``finite`` (the weights are, at a checkpoint)."""
        if not finite:
            raise Diverged(
                f"weights became non-finite by step {self.step}; the last good "
                f"checkpoint is kept in {self.ckpt_path}"
            )
