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
data shares and seeds may differ.  A batched run writes each material's config.yaml,
log.csv (the final row) and a checkpoint that can be exported (``neural-brdf export``)
but not resumed: Ctrl-C stops the batch and nothing is kept.
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path
from typing import Any

import torch
from torch.func import functional_call, stack_module_state, vmap

from neural_brdf import config as cfgmod
from neural_brdf.fileio import atomic_write
from neural_brdf.train import data
from neural_brdf.train import loop as trainmod
from neural_brdf.train.model import RawBRDF

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


def check_batchable(cfgs: list[cfgmod.Config]) -> None:
    """One-line ConfigError naming the first setting that stops ``cfgs`` training as one
    batch (it must be the same for all of them)."""
    if not cfgs:
        raise cfgmod.ConfigError("train-many: no configs")
    if any(c.target.images is not None for c in cfgs):
        raise cfgmod.ConfigError("target.images: an images fit cannot be trained in a batch")
    first = _flat(cfgs[0].model_dump())
    for cfg in cfgs[1:]:
        now = _flat(cfg.model_dump())
        for key in (k for k in first if _shared(k)):
            if first[key] != now.get(key):
                raise cfgmod.ConfigError(
                    f"{key}: differs between {cfgs[0].name} and {cfg.name} ({first[key]!r} "
                    f"and {now.get(key)!r}); materials trained together share the network, "
                    "the batch and the optimisation"
                )


def train_many(
    cfgs: list[cfgmod.Config], run_dirs: list[Path], *, targets: list | None = None
) -> list[tuple[RawBRDF, dict[str, Any]]]:
    """Train one model per config, all in one loop; returns [(network, figures)] as
    :func:`neural_brdf.train.loop.train` does for one."""
    check_batchable(cfgs)
    t = cfgs[0].train
    torch.set_num_threads(t.threads)
    device = trainmod.resolve_device(t.device)
    targets = targets or [data.build_target(c.target) for c in cfgs]
    pools, raws, evals = [], [], []
    for cfg, target, run_dir in zip(cfgs, targets, run_dirs):
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write(run_dir / "config.yaml", cfg.to_yaml())
        # the order of train.train: its generator, the global seed, the pool, the weights
        gen = torch.Generator().manual_seed(cfg.train.seed)
        torch.manual_seed(cfg.train.seed)
        pool = data.Pool(data.pair_source(target, cfg.data, gen), cfg.data, device)
        init = float(pool.f.median().clamp(1e-3, 10.0))
        raws.append(RawBRDF.from_config(cfg.model, init_value=init).to(device))
        pools.append(pool)
        evals.append(
            tuple(
                x.float().to(device)
                for x in data.accuracy_pairs(target, trainmod.EVAL_PAIRS, cfg.train.seed + 101)
            )
        )
    params, buffers = stack_module_state(raws)
    base = copy.deepcopy(raws[0]).to("meta")

    def forward(p, b, wi, wo):
        return functional_call(base, (p, b), (wi, wo))

    def loss_one(pred, f, cos):
        return trainmod.loss_fn(t.loss, pred, f, cos, t.loss_eps, t.peak_weight, t.peak_cap)

    batched, batched_loss = vmap(forward), vmap(loss_one)
    m = cfgs[0].model
    scales = {"grid.": m.grid.lr_scale, "cos_grid.": m.cosine_grid.lr_scale}
    groups: dict[str, list] = {prefix: [] for prefix in ("", *scales)}
    for name, p in params.items():
        groups[next((k for k in scales if name.startswith(k)), "")].append(p)
    opt = torch.optim.Adam(
        [{"params": ps, "lr_scale": scales.get(k, 1.0)} for k, ps in groups.items() if ps],
        lr=t.lr,
        fused=True,
    )
    loss_sum = torch.zeros((), device=device)
    start = time.perf_counter()
    with trainmod.deferred_interrupt() as sigint:
        for step in range(t.steps):
            if sigint["set"]:
                raise trainmod.Interrupted(
                    f"interrupted at step {step} ({trainmod.signal_name(sigint['signum'])}); "
                    "a batched run keeps no checkpoint: run it again"
                )
            lr = trainmod.learning_rate(t, step)
            for group in opt.param_groups:
                group["lr"] = lr * group["lr_scale"]
            wi, wo, f = (torch.stack(x) for x in zip(*(p.batch() for p in pools)))
            losses = batched_loss(batched(params, buffers, wi, wo), f, wo[..., 2:3])
            loss = losses.sum()
            loss_sum += loss.detach()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if (step + 1) % t.log_every == 0 and not math.isfinite(float(loss_sum)):
                raise trainmod.Diverged(
                    f"loss is {float(loss_sum)} by step {step + 1} in a batch of "
                    f"{len(cfgs)} materials (try a lower train.lr)"
                )
    seconds = time.perf_counter() - start
    final = losses.detach().cpu().tolist()
    out = []
    for k, (cfg, raw, target, run_dir) in enumerate(zip(cfgs, raws, targets, run_dirs)):
        weights = {n: p[k].detach() for n, p in params.items()}
        raw.load_state_dict(weights | {n: b[k] for n, b in buffers.items()})
        raw.eval()
        eval_wi, eval_wo, eval_f = evals[k]
        with torch.no_grad():
            err = trainmod.rel_rmse(raw(eval_wi, eval_wo), eval_f, eval_wo[:, 2:3])
        state = {
            "format_version": cfgmod.FORMAT_VERSION,
            "step": t.steps,
            "config": cfg.model_dump(),
            "model": {n: v.cpu() for n, v in raw.state_dict().items()},
            "train_seconds": seconds,
            "loss": final[k],
            "batched": len(cfgs),  # not resumable: no optimizer or pool state
        }
        trainmod.save_checkpoint(run_dir / "ckpt.pt", state)
        atomic_write(
            run_dir / "log.csv",
            ",".join(trainmod.LOG_COLUMNS)
            + f"\n{t.steps},{final[k]:.6g},{trainmod.learning_rate(t, t.steps - 1):.4g},"
            + f"{seconds:.2f},{err:.5g}\n",
        )
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
