"""Many materials in one run: independent small models trained together (issue 21).

    from neural_brdf import config, pipeline
    cfgs = [config.load("configs/gold.yaml", [f"target.params.material={m}"]) for m in ...]
    pipeline.run_many(cfgs, "runs/metals")          # = neural-brdf train-many ... --out

Each material keeps its own model, target, pair pool, generator and seed, exactly as
:func:`neural_brdf.train.loop.train` would build them; the models' weights are stacked
(``torch.func.stack_module_state``) and one step evaluates them all at once with
``torch.func.vmap`` over the same network, so a step pays the framework's per-operation
cost once for all of them.  The loss is the sum of the models' own losses, so each model
gets the gradient it would get alone, and Adam works element by element: the models do
not interact.  They differ from single runs only by floating-point rounding in the
batched kernels (tests/train/test_many.py compares them).

The configs must share the network (``model``), the batch shape (``data.batch_size``,
``pool_size``, ``reuse``) and the optimisation (``train`` but for ``seed``); targets,
data shares and seeds may differ.  The batch runs in one
:class:`neural_brdf.train.session.Session` (progress, Ctrl-C and SIGTERM, divergence) with
one :class:`~neural_brdf.train.session.RunFiles` per material, written when the batch has
trained: each material's folder then becomes the new run at once (its marker, config.yaml,
a checkpoint that can be exported, ``neural-brdf export``, but not resumed, and log.csv's
final row; an old run there removed first), and until then an old run in it stays whole.
Ctrl-C stops the batch and nothing is kept.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import torch
from torch.func import functional_call, stack_module_state, vmap

from neural_brdf import config as cfgmod
from neural_brdf import runfolder
from neural_brdf.train import data, loop
from neural_brdf.train.model import RawBRDF, grid_lr_scales, parameter_groups
from neural_brdf.train.session import RunFiles, Session

# train settings that may differ between the batched materials (the rest must match)
FREE_TRAIN = ("seed", "progress")


def _flat(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _shared(key: str) -> bool:
    """Must the batched materials agree on this (dotted) config key?"""
    section, _, rest = key.partition(".")
    if section == "model":
        return True
    if section == "data":
        return rest in ("batch_size", "pool_size", "reuse")
    return section == "train" and rest not in FREE_TRAIN


def check_batchable(cfgs: list[cfgmod.Config], sources: list[str] | None = None) -> None:
    """One-line ConfigError naming the first setting that stops ``cfgs`` training as one
    batch (it must be the same for all of them), and the files (``sources``, one per
    config; else the configs' names) that disagree."""
    if not cfgs:
        raise cfgmod.ConfigError("train-many: no configs")
    label = sources if sources is not None else [c.name for c in cfgs]
    for src, c in zip(label, cfgs):
        if c.target.images is not None:
            raise cfgmod.ConfigError(
                f"{src}: target.images: an images fit cannot be trained in a batch"
            )
    first = _flat(cfgs[0].model_dump())
    for src, cfg in zip(label[1:], cfgs[1:]):
        now = _flat(cfg.model_dump())
        for key in (k for k in first if _shared(k)):
            if first[key] != now.get(key):
                raise cfgmod.ConfigError(
                    f"{src}: {key}: differs from {label[0]} ({now.get(key)!r} here, "
                    f"{first[key]!r} there); materials trained together share the network, "
                    "the batch and the optimisation"
                )


def train_many(
    cfgs: list[cfgmod.Config],
    run_dirs: list[Path],
    *,
    targets: list | None = None,
    folders: list[runfolder.Folder] | None = None,
) -> list[tuple[RawBRDF, dict[str, Any]]]:
    """Train one model per config, all in one loop; returns [(network, figures)] as
    :func:`neural_brdf.train.loop.train` does for one.  ``folders``: ``run_dirs`` as the
    caller opened them (:func:`neural_brdf.runfolder.hold`); else each is opened here as
    :func:`neural_brdf.train.loop.train` opens its own (a run in it is replaced)."""
    check_batchable(cfgs)
    t = cfgs[0].train
    torch.set_num_threads(t.threads)
    device = loop.resolve_device(t.device)
    targets = targets or [data.build_target(c.target) for c in cfgs]
    if folders is None:
        folders = [runfolder.Folder.open(d, resume=False, overwrite=True) for d in run_dirs]
    sess = Session(
        [RunFiles(c, f) for c, f in zip(cfgs, folders)],
        checkpoints=False,
        desc=f"{len(cfgs)} materials",
    )
    pools, raws, evals = [], [], []
    for cfg, target in zip(cfgs, targets):
        pool, raw = loop.seeded_start(cfg, target, device)  # as train.train starts
        raws.append(raw.to(device))
        pools.append(pool)
        evals.append(loop.eval_pairs(target, cfg, device))
    params, buffers = stack_module_state(raws)
    base = copy.deepcopy(raws[0]).to("meta")

    def forward(p, b, wi, wo):
        return functional_call(base, (p, b), (wi, wo))

    def loss_one(pred, f, cos):
        return loop.loss_fn(t.loss, pred, f, cos, t.loss_eps, t.peak_weight, t.peak_cap)

    batched, batched_loss = vmap(forward), vmap(loss_one)
    groups = parameter_groups(params.items(), grid_lr_scales(cfgs[0].model))
    opt = torch.optim.Adam(groups, lr=t.lr, fused=True)
    loss_sum = torch.zeros((), device=device)
    with sess.run() as s:
        while s.step < t.steps:
            s.stop_if_interrupted()
            lr = loop.learning_rate(t, s.step)
            for group in opt.param_groups:
                group["lr"] = lr * group["lr_scale"]
            wi, wo, f = (torch.stack(x) for x in zip(*(p.batch() for p in pools)))
            losses = batched_loss(batched(params, buffers, wi, wo), f, wo[..., 2:3])
            loss = losses.sum()
            loss_sum += loss.detach()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            s.advance()
            if s.step % t.log_every == 0 and not math.isfinite(float(loss_sum)):
                raise s.diverged(float(loss_sum), s.step, exact=False)
    seconds = sess.seconds
    final = losses.detach().cpu().tolist()
    last_lr = loop.learning_rate(t, t.steps - 1)
    out = []
    for k, (files, raw, target) in enumerate(zip(sess.runs, raws, targets)):
        weights = {n: p[k].detach() for n, p in params.items()}
        raw.load_state_dict(weights | {n: b[k] for n, b in buffers.items()})
        raw.eval()
        eval_wi, eval_wo, eval_f = evals[k]
        with torch.no_grad():
            err = loop.rel_rmse(raw(eval_wi, eval_wo), eval_f, eval_wo[:, 2:3])
        state = {
            "model": {n: v.cpu() for n, v in raw.state_dict().items()},
            "loss": final[k],
            "batched": len(cfgs),  # not resumable: no optimizer or pool state
        }
        row = {"step": t.steps, "loss": final[k], "lr": last_lr, "seconds": seconds}
        with runfolder.held_signals():  # the folder is the old run or the whole new one
            files.begin()
            files.save(files.state(t.steps, seconds, state))
            files.write_log([files.format_row(row | {"val_rel_rmse": err})])
        out.append(
            (
                raw.cpu(),
                {
                    "steps": t.steps,
                    "device": str(device),
                    "train_seconds": seconds,
                    "final_loss": final[k],
                    "raw_val_rel_rmse": err,
                    "target": target.describe(),
                    "batched_with": len(cfgs),
                },
            )
        )
    return out
