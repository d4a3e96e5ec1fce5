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

The loop runs in a :class:`neural_brdf.train.session.Session`, which owns its frame:
config.yaml, ckpt.pt (written atomically, loaded with ``weights_only=True``), log.csv,
the progress bar, Ctrl-C and SIGTERM (what docker, systemd, Slurm and Ray send: the
current step finishes, a checkpoint is written and :class:`Interrupted` raised, whose
``signum`` is the signal; the CLI exits with 128 + signum: 130, 143; a second one aborts
at once) and divergence (a non-finite loss or weight raises :class:`Diverged` and leaves
the last good checkpoint in place).  Which folders a run may write into, and its lock,
are :mod:`neural_brdf.runfolder`'s: :func:`neural_brdf.pipeline.run` (and ``neural-brdf
train``) refuses a folder that is not a run's, and one holding a finished or unfinished
run unless ``--resume`` (``resume=True``) continues it or ``--overwrite``
(``overwrite=True``) replaces it.  Resuming a finished run (its checkpoint at
``train.steps``, model.onnx and metrics.json written) does nothing and touches no file; a
``train.steps`` below the checkpoint's step is refused.  Called directly, :func:`train`
replaces a run already in ``run_dir`` (or continues it with ``resume``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from neural_brdf import config as cfgmod
from neural_brdf import runfolder
from neural_brdf.errors import Diverged, InputError, Interrupted  # noqa: F401  (re-exported)
from neural_brdf.runfolder import (  # noqa: F401  (re-exported: their former home)
    Folder,
    NotARunFolder,
    RunExists,
    RunLocked,
    check_fresh_run_dir,
    default_run_dir,
    run_lock,
)
from neural_brdf.train import data
from neural_brdf.train.model import RawBRDF, grid_lr_scales, parameter_groups
from neural_brdf.train.session import (  # noqa: F401  (re-exported: their former home)
    INTERRUPT_SIGNALS,
    LOG_COLUMNS,
    MUST_MATCH,
    CheckpointError,
    Session,
    check_resumable,
    deferred_interrupt,
    deferred_sigint,
    finished_report,
    interrupted,
    load_checkpoint,
    load_resumable,
    save_checkpoint,
    signal_name,
)

LOCK_FILE = runfolder.LOCK  # the former names
FINISHED_FILES = runfolder.FINISHED
EVAL_PAIRS = 16384  # held-out importance-sampled pairs for the CSV's val_rel_rmse


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


def seeded_start(cfg: cfgmod.Config, target, device) -> tuple[data.Pool, RawBRDF]:
    """A run's pool of training pairs and its initial weights, in the order that makes
    ``train.seed`` give the same run in every loop (this one and
    :func:`neural_brdf.train.many.train_many`): the pool's generator, the global seed,
    the pool, the weights (the output initialised at the pool's median value)."""
    gen = torch.Generator().manual_seed(cfg.train.seed)
    torch.manual_seed(cfg.train.seed)
    pool = data.Pool(data.pair_source(target, cfg.data, gen), cfg.data, device)
    init = float(pool.f.median().clamp(1e-3, 10.0))
    return pool, RawBRDF.from_config(cfg.model, init_value=init)


def eval_pairs(target, cfg: cfgmod.Config, device) -> tuple[torch.Tensor, ...]:
    """(wi, wo, f) of the run's held-out accuracy pairs (EVAL_PAIRS, seeded by
    ``train.seed``), on ``device``."""
    pairs = data.accuracy_pairs(target, EVAL_PAIRS, cfg.train.seed + 101)
    return tuple(x.float().to(device) for x in pairs)


def train(
    cfg: cfgmod.Config,
    run_dir: Path,
    *,
    resume: bool = False,
    target: Any = None,
    checkpoint: dict | None = None,
    folder: Folder | None = None,
) -> tuple[RawBRDF, dict[str, Any]]:
    """Optimise the raw network; writes ckpt.pt and log.csv.  Returns (network, figures).

    ``target`` is the model of ``cfg.target`` (``data.build_target``) when the caller
    has built it; ``checkpoint`` the run's checkpoint (:func:`load_resumable`) when the
    caller has loaded it to resume; ``folder`` ``run_dir`` as the caller opened it
    (:func:`neural_brdf.runfolder.hold`), else it is opened here
    (:meth:`neural_brdf.train.session.Session.one`).
    """
    t = cfg.train
    torch.set_num_threads(t.threads)
    device = resolve_device(t.device)
    if target is None:
        target = data.build_target(cfg.target)
    sess = Session.one(cfg, folder if folder is not None else run_dir, resume=resume)
    ckpt = sess.resumed(checkpoint)
    sess.begin()

    pool, raw = seeded_start(cfg, target, device)
    if ckpt is not None:
        raw.load_state_dict(ckpt["model"])
    raw.to(device)  # the pool too; its generator and the checkpoints stay on the CPU
    # the learned grids (model.grid, model.cosine_grid): their own learning rates,
    # lr_scale x the schedule
    groups = parameter_groups(raw.named_parameters(), grid_lr_scales(cfg.model))
    # fused: one kernel for all parameters (CPU and CUDA); 0.04 ms a step against
    # 0.12 ms for the per-tensor loop on compact/gold (2 cores)
    opt = torch.optim.Adam(groups, lr=t.lr, fused=True)
    eval_wi, eval_wo, eval_f = eval_pairs(target, cfg, device)
    last_loss = math.nan
    if ckpt is not None:
        opt.load_state_dict(ckpt["optimizer"])  # moves Adam's moments to the weights' device
        pool.load_state_dict(ckpt["pool"])
        sess.restore(ckpt)
        last_loss = float(ckpt.get("loss", math.nan))  # older checkpoints: from log.csv

    def state() -> dict[str, Any]:
        return {
            "model": {k: v.cpu() for k, v in raw.state_dict().items()},
            "optimizer": opt.state_dict(),
            "pool": pool.state_dict(),
            "loss": last_loss,  # of the last step: metrics' final_loss after a resume
        }

    def weights_finite() -> bool:
        return all(bool(torch.isfinite(p).all()) for p in raw.parameters())

    # The loss is read on the host only where it is logged or checkpointed (a read
    # waits for a GPU); ``loss_sum`` turns non-finite with the first bad step's loss.
    loss_sum = torch.zeros((), device=device)
    checked = sess.step

    def check_loss() -> None:
        nonlocal last_loss, checked
        if sess.step == checked:
            return
        last_loss = float(loss.detach())
        total = float(loss_sum)
        if not (math.isfinite(total) and math.isfinite(last_loss)):
            bad = last_loss if not math.isfinite(last_loss) else total
            raise sess.diverged(bad, sess.step - 1, exact=sess.step - 1 == checked)
        checked = sess.step

    with sess.run(state) as s:
        rows = s.kept[0]
        if rows and not math.isfinite(last_loss) and int(rows[-1]["step"]) == s.step:
            last_loss = float(rows[-1]["loss"])
        while s.step < t.steps:
            s.stop_if_interrupted(check_loss)
            lr = learning_rate(t, s.step)
            for group in opt.param_groups:
                group["lr"] = lr * group.get("lr_scale", 1.0)
            wi, wo, f = pool.batch()  # on the training device
            pred = raw(wi, wo)
            loss = loss_fn(t.loss, pred, f, wo[:, 2:3], t.loss_eps, t.peak_weight, t.peak_cap)
            loss_sum += loss.detach()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            s.advance()
            if s.due(t.log_every):
                check_loss()
                err = None
                if t.eval_every and s.due(t.eval_every):
                    with torch.no_grad():
                        err = rel_rmse(raw(eval_wi, eval_wo), eval_f, eval_wo[:, 2:3])
                    s.postfix(loss=f"{last_loss:.4g}", err=f"{100 * err:.2f}%")
                else:
                    s.postfix(loss=f"{last_loss:.4g}")
                s.log(loss=last_loss, lr=lr, val_rel_rmse=err)
            if s.due(t.checkpoint_every):
                check_loss()
                s.check_weights(weights_finite())
                s.checkpoint()
    with torch.no_grad():
        err = rel_rmse(raw(eval_wi, eval_wo), eval_f, eval_wo[:, 2:3])
    return raw.cpu().eval(), {
        "steps": sess.step,
        "device": str(device),
        "train_seconds": sess.seconds,
        **sess.record(),
        "final_loss": last_loss,
        "raw_val_rel_rmse": err,
        "target": target.describe(),
    }
