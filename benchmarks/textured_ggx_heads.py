"""A prototype for issue 30's last gap: analytic GGX heads beside the textured recipe's
neural lobes, at one texel (development teachers; nothing is chosen, the model is
unchanged).

    python benchmarks/textured_ggx_heads.py            # about 22 minutes on 2 cores
    python benchmarks/textured_ggx_heads.py --quick    # tiny budgets: the machinery only

The textured principled misses its 3 % goal at the grazing highlights of its smoothest
texels (docs/mitsuba.md, "Where the error that is left lives"), where a GGX lobe of
alpha about 0.06 grows like 1 / (cos theta_i cos theta_o).  This fits one texel of the
``textured_ceiling.py`` teachers (homogeneous ``principled``, a development base colour)
with the textured recipe's K = 4 shared grey lobes (hidden [32], ``model.grazing_power``
1, RGB weights per lobe; no latent and no bound: one texel, and the bound's cost is
measured elsewhere), alone and with two analytic heads added, each weighted per RGB
channel like a lobe:

    g_a = D(h) G(wi, wo) / (4 cos theta_i cos theta_o),    g_b = g_a (1 - (wi . h))^5

GGX's D with one alpha, learned, and Smith's masking, either height-correlated,
G = 1 / (1 + L(wi) + L(wo)), or separable, G = G1(wi) G1(wo) with G1 = 1 / (1 + L)
(L: Smith's Lambda for GGX; Walter et al. 2007 eq. 33-34; Heitz 2014 eq. 99 for the
height-correlated form; Mitsuba 3's ``MicrofacetDistribution::G`` is the separable
one).  Both heads are symmetric in (wi, wo), so reciprocal, and with F <= 1 each one's
albedo is at most 1 for every alpha (single scattering loses energy): a bound in closed
form, which the issue allows, and which holds between texels for any blended alpha.
``g_b`` gives the Schlick rise of the Fresnel term toward grazing (Schlick 1994).

Arms per teacher: ``lobes``; ``ggx_corr`` and ``ggx_sep`` with alpha started at the
teacher's own (roughness^2: in a textured model the latent would start from the
teacher's maps, as ``texture.latent`` does today); ``ggx_sep_free`` with alpha started
at 0.28, to see whether the fit finds it; ``ggx_sep_est`` with alpha started from the
teacher's ``eval`` alone (:func:`alpha_from_eval`), as a textured model could start it.
Scored as ``textured_ceiling.py`` scores: the relative RMSE of f cos on its 200,000
pairs (seed 900), by bands of cos theta_i.
Nothing asserts; the JSON goes to results/textured_ggx_heads_dev.json and
``tools/results_tables.py`` makes the table of docs/results.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch, as the CLI does
REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import torch  # noqa: E402
from common import machine, write_json  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
TEACHERS = ("r0.25_m0", "r0.25_m1", "r0.4_m0.5", "r0.8_m0.5")  # textured_ceiling.TEACHERS
ARMS = {  # name -> (GGX heads, Smith's masking, alpha's start: None = the teacher's)
    "lobes": (False, None, None),
    "ggx_corr": (True, "correlated", None),
    "ggx_sep": (True, "separable", None),
    "ggx_sep_free": (True, "separable", 0.28),
    "ggx_sep_est": (True, "separable", "eval"),  # alpha_from_eval: the teacher's eval only
}
K, HIDDEN, LR, BATCH = 4, [32], 0.01, 8192  # textured.SETTINGS' lobes, lr and batch
STEPS, POOL = 4000, 1 << 21
ALPHA_MIN = 0.01


def ggx_heads(wi, wo, alpha, masking: str):
    """(N, 1) each: the GGX lobe with F = 1 and with the Schlick grazing factor, from the
    analytic library's microfacet distribution (its D and Smith terms) and Schlick's
    Fresnel with F0 = 0 (the factor (1 - wi.h)^5)."""
    from analytic import frame
    from analytic.fresnel import schlick
    from analytic.microfacet import Distribution

    dist = Distribution("ggx", alpha, alpha)  # alpha: a tensor, so the heads learn it
    h = frame.normalize(wi + wo)
    if masking == "separable":
        g = dist.G1(wi) * dist.G1(wo)
    else:
        g = 1.0 / (1.0 + dist.Lambda(wi) + dist.Lambda(wo))
    ci, co = wi[:, 2:3], wo[:, 2:3]
    f = (dist.D(h) * g)[:, None] / (4.0 * ci.clamp_min(frame.EPS_COS) * co.clamp_min(frame.EPS_COS))
    rise = schlick(0.0, frame.dot(wi, h))[:, :1]  # grey: (1 - wi.h)^5
    ok = (ci > 0) & (co > 0)
    return torch.where(ok, f, 0.0), torch.where(ok, f * rise, 0.0)


def alpha_from_eval(teacher, uv=(0.5, 0.5)) -> float:
    """A start for alpha from the teacher's ``eval`` alone, as the latent's start is
    made (textured_loop.latent_from_teacher): f(n, w) with wi at the normal and wo tilted
    by 0 to 80 degrees, fitted by k_d + k_s D(h) G1(w) / (4 cos theta) (the analytic
    library's GGX D and separable masking; G1 at the normal is 1) with k_d, k_s >= 0 by
    least squares relative to f, for each of 60 alphas from 0.01 to 1 (log-spaced): the
    alpha of the least relative error."""
    import numpy as np

    from analytic import frame
    from analytic.microfacet import Distribution

    t = np.radians(np.arange(0.0, 81.0, 2.0))
    wo = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], -1)
    wi = np.tile([0.0, 0.0, 1.0], (len(t), 1))
    f = np.nan_to_num(np.asarray(teacher.eval(wi, wo, np.tile(uv, (len(t), 1))), np.float64))
    f = f.mean(-1)
    wo_t = torch.from_numpy(wo)
    h = frame.normalize(torch.from_numpy(wi) + wo_t)
    w = 1.0 / np.maximum(f, 1e-9)  # relative
    best, best_err = 1.0, np.inf
    for a in np.geomspace(0.01, 1.0, 60):
        dist = Distribution("ggx", float(a), float(a))
        spec = (dist.D(h) * dist.G1(wo_t)).numpy() / (4.0 * wo[:, 2])
        x = np.stack([np.ones_like(spec), spec], -1) * w[:, None]
        k, *_ = np.linalg.lstsq(x, f * w, rcond=None)
        k = np.maximum(k, 0.0)
        err = float(np.sum((x @ k - f * w) ** 2))
        if err < best_err:
            best, best_err = float(a), err
    return best


class WithGGX(torch.nn.Module):
    """``base`` (the lobes) plus the two GGX heads of :func:`ggx_heads`, RGB weights
    (softplus, started at 0.13) and one alpha in [ALPHA_MIN, 1] (a logistic map)."""

    def __init__(self, base: torch.nn.Module, masking: str, alpha_start: float):
        super().__init__()
        self.base = base
        self.masking = masking
        a = (alpha_start - ALPHA_MIN) / (1.0 - ALPHA_MIN)
        self.a = torch.nn.Parameter(torch.logit(torch.tensor(a)))
        self.w = torch.nn.Parameter(torch.full((2, 3), -2.0))

    def alpha(self) -> torch.Tensor:
        return ALPHA_MIN + (1.0 - ALPHA_MIN) * torch.sigmoid(self.a)

    def forward(self, wi, wo, uv):
        g_a, g_b = ggx_heads(wi, wo, self.alpha(), self.masking)
        w = torch.nn.functional.softplus(self.w)
        return self.base(wi, wo, uv) + g_a * w[0] + g_b * w[1]


def make_model(pool_f, arm: str, alpha_start: float):
    """The recipe's lobes at one texel, with the arm's GGX heads; (model, Adam)."""
    from neural_brdf import config as cfgmod
    from neural_brdf.train.textured_loop import FIELD_LR_SCALE, lobe_networks, parameter_groups
    from neural_brdf.train.textured_model import TexturedBRDF, WeightField

    heads, masking, _ = ARMS[arm]
    init = float(pool_f.median().clamp(1e-3, 10.0)) * (K + 1) / K
    nets = lobe_networks(cfgmod.Model(hidden=HIDDEN), K, True, init_value=init, colors=1)
    base = TexturedBRDF(nets, WeightField(1, K, channels=3))
    # the learning-rate groups of textured_loop (its module doc); the heads' at 1
    groups = parameter_groups(base, cfgmod.Model(hidden=HIDDEN), FIELD_LR_SCALE)
    if not heads:
        return base, torch.optim.Adam(groups, lr=LR)
    model = WithGGX(base, masking, alpha_start)
    groups.append({"params": [model.a, model.w], "lr_scale": 1.0})
    return model, torch.optim.Adam(groups, lr=LR)


def fit(model, opt, pool, steps: int, seed: int) -> float:
    from neural_brdf import config as cfgmod
    from neural_brdf.train.loop import learning_rate, loss_fn

    wi, wo, uv, f = pool
    tr = cfgmod.Train(steps=steps, lr=LR)
    gen = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    for step in range(steps):
        lr = learning_rate(tr, step)
        for g in opt.param_groups:
            g["lr"] = lr * g["lr_scale"]
        i = torch.randint(0, len(wi), (BATCH,), generator=gen)
        loss = loss_fn(
            tr.loss, model(wi[i], wo[i], uv[i]), f[i], wo[i, 2:3], tr.loss_eps, tr.peak_weight,
            tr.peak_cap,
        )  # fmt: skip
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", action="append", default=[], help="a teacher (repeat)")
    ap.add_argument("--quick", action="store_true", help="tiny budgets: the machinery only")
    ap.add_argument("--out", type=Path, default=RESULTS / "textured_ggx_heads_dev.json")
    args = ap.parse_args(argv)
    load_before = [round(x, 2) for x in os.getloadavg()]

    import numpy as np
    import textured as bench
    import textured_ceiling as tc

    from neural_brdf.measured.textured import TexturedMitsubaTarget
    from neural_brdf.train.textured_loop import pairs

    steps, pool_n, n_pairs = (200, 1 << 15, 20_000) if args.quick else (STEPS, POOL, tc.PAIRS)
    out: dict = {
        "benchmark": "textured_ggx_heads",
        "set": "dev",
        "quick": args.quick,
        "recipe": {
            "lobes": K,
            "hidden": HIDDEN,
            "lr": LR,
            "batch": BATCH,
            "steps": steps,
            "pool": pool_n,
            "lobe_color": "grey",
            "weights": "rgb",
            "grazing_power": 1.0,
        },  # fmt: skip
        "arms": {k: {"ggx": v[0], "masking": v[1], "alpha_start": v[2]} for k, v in ARMS.items()},
        "pairs": n_pairs,
        "seed": tc.SEED,
        "base_color": tc.BASE,
        "rows": [],
        "machine": machine(load_before, torch=torch.__version__),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "torch_threads": torch.get_num_threads(),
    }
    work = Path(tempfile.mkdtemp(prefix="nbrdf-ggx-heads-"))
    for name in args.only or TEACHERS:
        rough, metal = tc.TEACHERS[name]
        xml = work / f"{name}.xml"
        xml.write_text(tc.teacher_xml(rough, metal))
        teacher = TexturedMitsubaTarget(xml)
        pool = pairs(teacher, pool_n, np.random.default_rng(0))
        scored = bench.validation_pairs(teacher, n_pairs, tc.SEED)
        estimated = alpha_from_eval(teacher)
        for arm in ARMS:
            torch.manual_seed(0)
            how = ARMS[arm][2]
            start = rough * rough if how is None else estimated if how == "eval" else how
            model, opt = make_model(pool[3], arm, float(start))
            secs = fit(model, opt, pool, steps, 0)

            def f(wi, wo, uv, model=model):
                with torch.no_grad():
                    t = [torch.from_numpy(np.ascontiguousarray(x)).float() for x in (wi, wo, uv)]
                    return model(*t).numpy()

            row = {"teacher": name, "roughness": rough, "metallic": metal, "arm": arm}
            row.update(tc.score(f, scored))
            row["train_seconds"] = secs
            if ARMS[arm][0]:
                row["alpha"] = float(model.alpha().detach())
                row["alpha_teacher"] = rough * rough
                row["alpha_start"] = float(start)
                row["head_weights"] = torch.nn.functional.softplus(model.w).tolist()
            out["rows"].append(row)
            write_json(args.out, out)
            print(
                f"{name} {arm}: {100 * row['rel_rmse']:.2f} %"
                + (f", alpha {row['alpha']:.3f}" if "alpha" in row else "")
                + f" ({secs:.0f} s)",
                flush=True,
            )
    out["machine"] = machine(load_before, torch=torch.__version__)
    write_json(args.out, out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
