"""Training loop: checkpoints, resume, Ctrl-C and divergence handling, CSV log.

    python train.py configs/gold.yaml --out runs/gold            # = neural-brdf train ...
    python train.py configs/gold.yaml --out runs/gold --resume   # continue a run
    python train.py configs/gold.yaml --set train.steps=200 --set train.seed=3

A run directory holds ``config.yaml`` (resolved), ``ckpt.pt``, ``log.csv``,
``model.onnx`` and ``metrics.json``.  Without ``--out`` a run goes to ``runs/<name>/``.

Loss.  With c = cos(theta_o), eps = ``train.loss_eps`` and d the per-channel error:

    log_l2  (default)  d = (log(eps + c f^) - log(eps + c f))^2
    log_l1             d = |log(eps + c f^) - log(eps + c f)|
    nbrdf              d = |log(1 + c f^) - log(1 + c f)|          (Sztrajman et al. 2021)

    loss = sum w d / sum w,   w = 1 + peak_weight min(cap, (c f)^2 / mean (c f)^2)
    (w is computed from the target alone and not differentiated)

The log makes a dim tail count by its relative error.  The weight aims the loss at the
accuracy target, the relative L2 error of f cos: for small errors
(f^ c - f c)^2 ~ (f c)^2 d, so a log loss weighted by (f c)^2 is that metric, and the 1
keeps every pair in play.  Measured with the preset recipes (relative RMSE of f cos):

    preset            nbrdf   log_l2 unweighted   log_l2 weighted (default)
    gold              0.57%   0.85%               0.47%
    beckmann_smooth   1.54%   -                   0.37%
    plastic           2.00%   -                   1.69%

The cap (``peak_cap``, 100) stops one pair from carrying a batch: Ward and
Ashikhmin-Shirley grow like 1/cos^2 at the grazing mirror configuration, and one such
pair in the pool made the loss spike 100-fold at the same step in every run.  On the
Ashikhmin-Shirley brushed-metal preset the cap took the error from 2.1% to 0.7%.

Determinism.  Weights are initialised from ``torch.manual_seed(seed)``; data come from
one ``torch.Generator`` seeded with ``seed``; the thread count is fixed by
``train.threads``.  The checkpoint holds weights, optimizer, pool and generator state,
so an interrupted and resumed run ends with the same weights as an uninterrupted one.
Resuming with a larger ``train.steps`` trains on; the cosine schedule then follows the
new length.  ``target``, ``model``, ``data`` and the loss must match the checkpoint.

A fresh run does not replace another run's files: :func:`neural_brdf.pipeline.run` (and
``neural-brdf train``) refuses a folder holding model.onnx, metrics.json or ckpt.pt unless
``--resume`` (or ``resume=True``) continues it or ``--overwrite`` (``overwrite=True``)
replaces it.
Resuming a finished run (its checkpoint at ``train.steps``, model.onnx and metrics.json
written) does nothing and touches no file; a ``train.steps`` below the checkpoint's step
is refused.  The run holds ``RUN_DIR/.lock`` (``fcntl.flock``, the holder's pid inside)
from start to end, so that a second run into the same folder stops at once (RunLocked).

Checkpoints are written to a temporary file and renamed (atomic), loaded with
``weights_only=True``.  Ctrl-C or SIGTERM (what docker, systemd, Slurm and Ray send)
finishes the current step, writes a checkpoint and raises :class:`Interrupted`, whose
``signum`` is the signal (the CLI exits with 128 + signum: 130, 143); a second one
aborts at once.  A non-finite loss or weight raises :class:`Diverged` and leaves the
last good checkpoint in place.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from neural_brdf import config as cfgmod
from neural_brdf.errors import Diverged, InputError, Interrupted
from neural_brdf.fileio import atomic_write
from neural_brdf.train import data
from neural_brdf.train.model import RawBRDF

fcntl: Any
try:
    import fcntl
except ImportError:  # Windows: runs are not locked
    fcntl = None

LOG_COLUMNS = ["step", "loss", "lr", "seconds", "val_rel_rmse"]
# Settings a resumed run must share with its checkpoint (the rest may change, e.g. steps).
MUST_MATCH = ("target", "model", "data", "train.seed", "train.loss", "train.loss_eps")
EVAL_PAIRS = 16384  # held-out importance-sampled pairs for the CSV's val_rel_rmse


# Finished-run outputs: their presence means a fresh run here would destroy a result.
FINISHED_FILES = ("model.onnx", "metrics.json")
# Removed by ``overwrite=True`` before a fresh run, so that an interrupted overwrite does
# not leave the old run's results beside the new checkpoint.
RUN_OUTPUTS = ("model.onnx", "metrics.json", "report.html", "report.md", "log.csv")


class RunExists(InputError):
    """A fresh run would replace a finished or unfinished one (exit code 2)."""


def check_fresh_run_dir(run_dir: Path, *, resume: bool, overwrite: bool) -> None:
    """Refuse to start a fresh run over another run's files unless ``overwrite``.

    A finished run (model.onnx or metrics.json) or an unfinished one (ckpt.pt) is kept
    unless the caller resumes it or asks to overwrite it; ``overwrite`` then deletes
    the old outputs (RUN_OUTPUTS and report-*.png).
    """
    if resume:
        return
    finished = [n for n in FINISHED_FILES if (run_dir / n).exists()]
    if not overwrite:
        if finished:
            raise RunExists(
                f"{run_dir}: holds a finished run ({finished[0]}); choose another "
                "--out, continue it with --resume, or replace it with --overwrite"
            )
        if (run_dir / "ckpt.pt").exists():
            raise RunExists(
                f"{run_dir}: holds an unfinished run (ckpt.pt); continue it with "
                "--resume or replace it with --overwrite"
            )
        return
    for path in [*(run_dir / n for n in RUN_OUTPUTS), *run_dir.glob("report-*.png")]:
        path.unlink(missing_ok=True)


class RunLocked(InputError):
    """Another process is running in the same run directory (exit code 2)."""


LOCK_FILE = ".lock"  # in the run directory while a run holds it: the holder's pid


@contextmanager
def run_lock(run_dir: Path):
    """Create ``run_dir`` if needed and hold ``run_dir/.lock`` (an exclusive
    ``fcntl.flock``, the holder's pid written inside) until the block ends.

    A second holder raises :class:`RunLocked` at once, naming the first one's pid.  The
    lock dies with its process (even by SIGKILL), so a stale ``.lock`` file is no
    obstacle.  The file is removed on release, and a folder this call created is
    removed again if the run left it empty (an error before anything was written).
    """
    created = not run_dir.exists()
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{run_dir}: is a file, not a run folder (choose another --out)") from None
    except OSError as e:
        raise InputError(f"{run_dir}: cannot create the run folder ({e.strerror})") from None
    path = run_dir / LOCK_FILE
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as e:
            raise InputError(f"{path}: cannot create the run's lock file ({e.strerror})") from None
        if fcntl is None:
            break
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise RunLocked(
                f"{run_dir}: in use by another run (pid {holder}); wait for it to end "
                "or choose another --out"
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


def default_run_dir(cfg: cfgmod.Config) -> Path:
    return Path("runs") / cfg.name


LOSSES = ("log_l2", "log_l1", "nbrdf")  # train.loss (config.Train lists the same names)


def loss_fn(
    kind: str,
    pred: torch.Tensor,
    ref: torch.Tensor,
    cos: torch.Tensor,
    eps: float,
    peak_weight: float = 0.0,
    peak_cap: float = math.inf,
):
    if kind not in LOSSES:
        raise ValueError(f"train.loss: one of {list(LOSSES)}, got {kind!r}")
    a, b = pred * cos, ref * cos
    if kind == "nbrdf":
        d = (torch.log1p(a) - torch.log1p(b)).abs()
    else:
        d = torch.log(a + eps) - torch.log(b + eps)
        d = d * d if kind == "log_l2" else d.abs()
    if peak_weight == 0.0:
        return d.mean()
    with torch.no_grad():
        b2 = b * b
        w = 1.0 + peak_weight * (b2 / b2.mean().clamp_min(1e-30)).clamp_max(peak_cap)
    return (w * d).mean() / w.mean()


def learning_rate(t: cfgmod.Train, step: int) -> float:
    if step < t.warmup:
        return t.lr * (step + 1) / t.warmup
    if t.schedule == "constant" or t.steps <= t.warmup:
        return t.lr
    x = (step - t.warmup) / max(1, t.steps - t.warmup)
    return t.lr * (t.lr_min + (1.0 - t.lr_min) * 0.5 * (1.0 + math.cos(math.pi * min(x, 1.0))))


def rel_rmse(pred: torch.Tensor, ref: torch.Tensor, cos: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm((pred - ref) * cos) / torch.linalg.vector_norm(ref * cos))


# ------------------------------------------------------------------ checkpoints
def save_checkpoint(path: Path, state: dict) -> None:
    """Write a checkpoint atomically.  It is serialised in memory first: torch.save's
    own file writer reports a full disk as a RuntimeError without the errno, and
    atomic_write raises an OSError naming ``path`` (ENOSPC: "No space left on device")."""
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write(path, bytes(buf.getbuffer()))


def _get(d: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        d = d.get(part) if isinstance(d, dict) else None
    return d


class CheckpointError(InputError):
    """A run directory or checkpoint is missing or unusable."""


def load_checkpoint(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint (train first, or check the run directory)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several unrelated types on a corrupt file
        raise CheckpointError(f"{path}: unreadable checkpoint ({type(e).__name__})") from None


def check_resumable(saved: dict, cfg: cfgmod.Config) -> None:
    now = cfg.model_dump()
    for key in MUST_MATCH:
        if _get(saved, key) != _get(now, key):
            raise cfgmod.ConfigError(
                f"{key}: differs from the checkpoint being resumed "
                f"({_get(saved, key)!r} there, {_get(now, key)!r} here)"
            )


def load_resumable(cfg: cfgmod.Config, ckpt_path: Path) -> dict:
    """The checkpoint that ``cfg`` resumes: same format version, same MUST_MATCH
    settings, and ``train.steps`` not below its step (a resumed run only trains on)."""
    ckpt = load_checkpoint(ckpt_path)
    if ckpt.get("format_version") != cfgmod.FORMAT_VERSION:  # e.g. another encoding
        raise cfgmod.ConfigError(
            f"{ckpt_path}: written by format version {ckpt.get('format_version')}, this "
            f"is {cfgmod.FORMAT_VERSION}; it cannot be resumed: train anew (--overwrite)"
        )
    if ckpt.get("batched"):
        raise cfgmod.ConfigError(
            f"{ckpt_path}: trained in a batch of {ckpt['batched']} materials "
            "(neural_brdf.train.many), which keeps no optimizer or pool: it cannot be resumed: "
            "train anew (--overwrite)"
        )
    check_resumable(ckpt["config"], cfg)
    step = int(ckpt["step"])
    if cfg.train.steps < step:
        raise cfgmod.ConfigError(
            f"train.steps: {cfg.train.steps} is below the step of the checkpoint being "
            f"resumed ({step}, {ckpt_path}); a resumed run only trains on: give "
            f"train.steps >= {step}"
        )
    return ckpt


def finished_report(run_dir: Path, step: int) -> dict | None:
    """The metrics.json of a run that finished at ``step`` (its model.onnx written
    too), or None: a run stopped before it finished exporting or validating."""
    if not (run_dir / "model.onnx").is_file():
        return None
    try:
        report = json.loads((run_dir / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    training = report.get("training") if isinstance(report, dict) else None
    return report if isinstance(training, dict) and training.get("steps") == step else None


INTERRUPT_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # Ctrl-C; docker, systemd, Slurm, Ray


def signal_name(signum: int | None) -> str:
    return "Ctrl-C" if signum in (None, signal.SIGINT) else signal.Signals(signum).name


def _abort(signum: int) -> KeyboardInterrupt:
    e = KeyboardInterrupt(f"{signal_name(signum)} again: aborted")
    e.signum = signum  # type: ignore[attr-defined]  # the CLI's exit code: 128 + signum
    return e


@contextmanager
def deferred_interrupt():
    """Turn the first Ctrl-C (SIGINT) or SIGTERM into a flag checked between steps
    (main thread only): ``flag["set"]``, and ``flag["signum"]`` the signal.  A second
    one raises KeyboardInterrupt at once.  An :class:`Interrupted` raised in the block
    leaves it with ``e.signum`` set to the signal (the CLI exits with 128 + signum)."""
    flag = {"set": False, "signum": None}
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


# ------------------------------------------------------------------ the run
def resolve_device(name: str) -> torch.device:
    """``train.device`` -> a torch device; "cuda" without a usable GPU is a config error."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise cfgmod.ConfigError(
            f"train.device: cuda, but this torch ({torch.__version__}) sees no CUDA GPU "
            "(use cpu or auto)"
        )
    return torch.device(name)


def train(
    cfg: cfgmod.Config,
    run_dir: Path,
    *,
    resume: bool = False,
    target: Any = None,
    checkpoint: dict | None = None,
) -> tuple[RawBRDF, dict[str, Any]]:
    """Optimise the raw network; writes ckpt.pt and log.csv.  Returns (network, figures).

    ``target`` is the model of ``cfg.target`` (``data.build_target``) when the caller
    has built it; ``checkpoint`` the run's checkpoint (:func:`load_resumable`) when the
    caller has loaded it to resume.
    """
    t = cfg.train
    torch.set_num_threads(t.threads)
    device = resolve_device(t.device)
    if target is None:
        target = data.build_target(cfg.target)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path, log_path = run_dir / "ckpt.pt", run_dir / "log.csv"
    ckpt = None
    if resume:
        ckpt = checkpoint if checkpoint is not None else load_resumable(cfg, ckpt_path)
    atomic_write(run_dir / "config.yaml", cfg.to_yaml())

    gen = torch.Generator().manual_seed(t.seed)
    torch.manual_seed(t.seed)
    pool = data.Pool(data.pair_source(target, cfg.data, gen), cfg.data, device)
    init = float(pool.f.median().clamp(1e-3, 10.0))
    raw = RawBRDF.from_config(cfg.model, init_value=init)
    if ckpt is not None:
        raw.load_state_dict(ckpt["model"])
    raw.to(device)  # the pool too; its generator and the checkpoints stay on the CPU
    # the learned grids (model.grid, model.cosine_grid): their own learning rates,
    # lr_scale x the schedule
    scales = {"grid.": cfg.model.grid.lr_scale, "cos_grid.": cfg.model.cosine_grid.lr_scale}
    by_prefix: dict[str, list[torch.nn.Parameter]] = {prefix: [] for prefix in ("", *scales)}
    for n, p in raw.named_parameters():
        by_prefix[next((k for k in scales if n.startswith(k)), "")].append(p)
    groups: list[dict[str, Any]] = [
        {"params": ps, "lr_scale": scales.get(k, 1.0)} for k, ps in by_prefix.items() if ps or not k
    ]
    # fused: one kernel for all parameters (CPU and CUDA); 0.04 ms a step against
    # 0.12 ms for the per-tensor loop on compact/gold (2 cores)
    opt = torch.optim.Adam(groups, lr=t.lr, fused=True)
    eval_wi, eval_wo, eval_f = (
        x.float().to(device) for x in data.accuracy_pairs(target, EVAL_PAIRS, t.seed + 101)
    )
    step, seconds, last_loss = 0, 0.0, math.nan
    if ckpt is not None:
        opt.load_state_dict(ckpt["optimizer"])  # moves Adam's moments to the weights' device
        pool.load_state_dict(ckpt["pool"])
        step, seconds = int(ckpt["step"]), float(ckpt["train_seconds"])
        last_loss = float(ckpt.get("loss", math.nan))  # older checkpoints: from log.csv
        print(f"{cfg.name}: resuming {ckpt_path} at step {step} of {t.steps}", file=sys.stderr)

    def state():
        return {
            "format_version": cfgmod.FORMAT_VERSION,
            "step": step,
            "config": cfg.model_dump(),
            "model": {k: v.cpu() for k, v in raw.state_dict().items()},
            "optimizer": opt.state_dict(),
            "pool": pool.state_dict(),
            "train_seconds": seconds,
            "loss": last_loss,  # of the last step: metrics' final_loss after a resume
        }

    def weights_finite() -> bool:
        return all(bool(torch.isfinite(p).all()) for p in raw.parameters())

    if ckpt is None:
        save_checkpoint(ckpt_path, state())
    rows = []
    if resume and log_path.is_file():
        with open(log_path, newline="") as fh:
            rows = [r for r in csv.DictReader(fh) if int(r["step"]) <= step]
        if rows and not math.isfinite(last_loss) and int(rows[-1]["step"]) == step:
            last_loss = float(rows[-1]["loss"])
    try:
        log_fh = open(log_path, "w", newline="")
        log = csv.DictWriter(log_fh, LOG_COLUMNS)
        log.writeheader()
        log.writerows(rows)
    except OSError as e:
        raise _cannot_write(log_path, e) from None

    bar = tqdm(
        total=t.steps,
        initial=min(step, t.steps),
        desc=cfg.name,
        disable=not t.progress,
        dynamic_ncols=True,
        mininterval=0.5,
        leave=False,
    )
    # The loss is read on the host only where it is logged or checkpointed (a read
    # waits for a GPU); ``loss_sum`` turns non-finite with the first bad step's loss.
    loss_sum = torch.zeros((), device=device)
    checked = step

    def check_loss() -> None:
        nonlocal last_loss, checked
        if step == checked:
            return
        last_loss = float(loss.detach())
        total = float(loss_sum)
        if not (math.isfinite(total) and math.isfinite(last_loss)):
            bad = last_loss if not math.isfinite(last_loss) else total
            where = f"at step {step - 1}" if step - 1 == checked else f"by step {step - 1}"
            raise Diverged(
                f"loss is {bad} {where}; the last good checkpoint is kept in "
                f"{ckpt_path} (try a lower train.lr)"
            )
        checked = step

    start = time.perf_counter() - seconds
    ok = False
    try:
        with deferred_interrupt() as sigint:
            while step < t.steps:
                if sigint["set"]:
                    check_loss()
                    seconds = time.perf_counter() - start
                    save_checkpoint(ckpt_path, state())
                    raise interrupted(sigint, step, ckpt_path)
                lr = learning_rate(t, step)
                for group in opt.param_groups:
                    group["lr"] = lr * group.get("lr_scale", 1.0)
                wi, wo, f = pool.batch()  # on the training device
                pred = raw(wi, wo)
                loss = loss_fn(t.loss, pred, f, wo[:, 2:3], t.loss_eps, t.peak_weight, t.peak_cap)
                loss_sum += loss.detach()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                step += 1
                bar.update(1)
                if step % t.log_every == 0 or step == t.steps:
                    check_loss()
                    row = {
                        "step": step,
                        "loss": f"{last_loss:.6g}",
                        "lr": f"{lr:.4g}",
                        "seconds": f"{time.perf_counter() - start:.2f}",
                        "val_rel_rmse": "",
                    }
                    if t.eval_every and (step % t.eval_every == 0 or step == t.steps):
                        with torch.no_grad():
                            err = rel_rmse(raw(eval_wi, eval_wo), eval_f, eval_wo[:, 2:3])
                        row["val_rel_rmse"] = f"{err:.5g}"
                        bar.set_postfix(loss=f"{last_loss:.4g}", err=f"{100 * err:.2f}%")
                    else:
                        bar.set_postfix(loss=f"{last_loss:.4g}")
                    try:
                        log.writerow(row)
                        log_fh.flush()
                    except OSError as e:
                        raise _cannot_write(log_path, e) from None
                if step % t.checkpoint_every == 0 or step == t.steps:
                    check_loss()
                    if not weights_finite():
                        raise Diverged(
                            f"weights became non-finite by step {step}; the last "
                            f"good checkpoint is kept in {ckpt_path}"
                        )
                    seconds = time.perf_counter() - start
                    save_checkpoint(ckpt_path, state())
        ok = True
    finally:
        bar.close()
        try:
            log_fh.close()
        except OSError as e:  # a full disk: the buffered rows cannot be written
            if ok:
                raise _cannot_write(log_path, e) from None
    seconds = time.perf_counter() - start
    with torch.no_grad():
        err = rel_rmse(raw(eval_wi, eval_wo), eval_f, eval_wo[:, 2:3])
    return raw.cpu().eval(), {
        "steps": step,
        "device": str(device),
        "train_seconds": seconds,
        "final_loss": last_loss,
        "raw_val_rel_rmse": err,
        "target": target.describe(),
    }


def _cannot_write(path: Path, e: OSError) -> InputError:
    return InputError(f"{path}: cannot write ({e.strerror or e})")
