"""Physics and accuracy checks of an exported model (or of any BRDF-like callable).

Physics (all must pass: ``report["passed"]``, :func:`physics_passed`; training and
``neural-brdf export`` exit 1 otherwise):

* reciprocity: max |f(a,b) - f(b,a)| / max(|f(a,b)|, |f(b,a)|) over random pairs,
  10% of them within 1 degree of grazing (``analytic.reciprocity_error``);
* non-negativity: the smallest value over the same pairs (``analytic.min_value``; a
  NaN counts as -inf);
* white furnace: rho(wi) = int f cos dwo by MIS quadrature (:mod:`neural_brdf.physics.quadrature`)
  on a dense grid of incoming directions down to 0.01 degree above the horizon (91 polar
  angles; for an anisotropic model 46 polar angles x 16 azimuths); the maximum must be
  <= 1 + albedo_tol.
  The seeds and the grid differ from those that built the normalisation table.
  The hemispherical albedo (1/pi) int rho(wi) cos dwi is reported as well.

Accuracy, with a reference (``--reference CONFIG``, ``--reference material.binary`` or
``material.bsdf``, or during training):

* ``rel_rmse``: relative RMSE of f cos(theta_o),
  sqrt(sum (f^ cos - f cos)^2) / sqrt(sum (f cos)^2) over all channels of pairs with
  wi uniform on the hemisphere and wo drawn from the reference's importance sampler
  (analytic reference), or over every measured bin centre of a MERL file (measured
  reference: the data themselves, uninterpolated, each bin counted once as in the
  NBRDF paper's grid errors);
* ``nbrdf_log_error``: the NBRDF loss, mean |log(1 + f cos) - log(1 + f^ cos)|;
* ``rel_rmse_by_incidence``: the same error within bands of cos(theta_i);
* ``worst``: the pairs with the largest |f^ cos - f cos|.

Peak, with an analytic reference (:func:`peak`): the error right at the highlight,
which a mean over random pairs cannot see (a notch 0.3 degrees wide at the mirror
direction moved the relative RMSE by less than 0.1 %).  For incidences ``PEAK_THETAS``
(0, 10, 45, 70 degrees; at 0, wi = wo = the normal, the three ways are alike by
symmetry) wo is put at the exact mirror direction and at ``PEAK_OFFSETS`` (0.01, 0.1,
0.3, 1 degree) from it, towards the normal, towards the horizon and out of
the plane of incidence; for a model that may be anisotropic, in the two planes of
incidence phi = 0 and phi = 90 degrees (both tangent axes).  The error at a pair is the
largest over RGB of |f^ / f - 1|, with f floored at 1e-3 of the largest target value
of the probe (so a channel with next to nothing in it cannot dominate).  The check passes
when the largest error is <= ``validation.peak_tol`` (3 %).

``neural-brdf validate`` exits 1 when any check of its report fails, the peak included
(:func:`passed`); training's verdict is the physics alone.

The model is compared with a ``target`` (:mod:`neural_brdf.target`): an analytic model
or measured data; an images fit has none (physics only).  ``export`` writes into the file
the figures :func:`physics` measured on its graph; they are this module's.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

import analytic
from neural_brdf import config as cfgmod
from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write, json_text
from neural_brdf.physics import quadrature
from neural_brdf.runtime import load
from neural_brdf.target import Described, Target, kind_of, spatially_varying
from neural_brdf.train import data
from neural_brdf.train.encoding import is_anisotropic

# Directions of the furnace grid stop this far above the horizon (radians, 0.01 degree).
HORIZON_GAP = math.radians(0.01)
AZIMUTHS = 16  # per polar angle, for an anisotropic model
N_WORST = 5
# cos(theta_i) bands of the per-band errors: for a model whose f cos grows without bound
# at grazing angles (Ward, Ashikhmin-Shirley) the overall error is set by the first band.
INCIDENCE_BANDS = ((0.0, 0.05), (0.05, 0.2), (0.2, 0.5), (0.5, 1.01))
# The peak probe: incidences and offsets from the mirror direction, in degrees.
PEAK_THETAS = (0.0, 10.0, 45.0, 70.0)  # 0: wi = wo = the normal, a flash's view
PEAK_OFFSETS = (0.0, 0.01, 0.1, 0.3, 1.0)
# offset directions: towards the normal, towards the horizon, out of the plane of incidence
PEAK_DIRECTIONS = ("normal", "horizon", "across")
# The furnace's second measurement of a direction over the limit draws other scramblings.
REMEASURE_SEED = 1_000_003
PEAK_FLOOR = 1e-3  # relative floor of the target in the ratio (of the probe's largest value)


def furnace_directions(n_theta: int, anisotropic: bool, seed: int) -> torch.Tensor:
    """(M, 3) incoming directions: ``n_theta`` polar angles on [0, 90 deg - gap] with a
    random azimuth each (isotropic), or ``ceil(n_theta / 2)`` polar angles times
    ``AZIMUTHS`` azimuths (anisotropic)."""
    g = torch.Generator().manual_seed(seed)
    if anisotropic:
        n_theta = (n_theta + 1) // 2
    theta = torch.linspace(0.0, 0.5 * math.pi - HORIZON_GAP, n_theta, dtype=torch.float64)
    if anisotropic:
        n_phi = AZIMUTHS
        offset = torch.rand(n_theta, 1, generator=g, dtype=torch.float64)
        phi = (torch.arange(n_phi, dtype=torch.float64)[None] + offset) * (2 * math.pi / n_phi)
        theta = theta[:, None].expand_as(phi)
    else:
        phi = 2 * math.pi * torch.rand(n_theta, generator=g, dtype=torch.float64)
    return analytic.frame.spherical(theta, phi).reshape(-1, 3)


def physics(
    fn: Callable,
    *,
    anisotropic: bool,
    settings: cfgmod.Validation,
    target: Described | None = None,
) -> dict[str, Any]:
    """Physics checks of ``fn(wi, wo)`` on numpy (N, 3) arrays -> a report dict
    (``checks``, ``hemispherical_albedo``, ``furnace``).  ``target``: the model's target,
    whose own sampler (if it has one) helps the furnace quadrature."""
    s = settings
    recip = analytic.reciprocity_error(fn, n=s.pairs, seed=s.seed)
    min_val = analytic.min_value(fn, n=s.pairs, seed=s.seed + 1)
    dirs = furnace_directions(s.furnace_dirs, anisotropic, s.seed + 2)
    rho, err, again = furnace(quadrature.from_numpy(fn), dirs, s, s.seed + 3, target=target)
    out = _physics_report(rho.numpy(), err.numpy(), dirs, anisotropic, recip, min_val, s)
    return remeasured(out, again, s)


def furnace(
    fn: Callable, dirs: torch.Tensor, s: cfgmod.Validation, seed: int, target=None
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The white furnace of a torch ``fn`` at ``dirs`` (M, 3) -> (rho, stderr (M, C),
    how many directions were measured again).

    A direction whose first estimate is over 1 + ``albedo_tol`` is measured again with
    ``furnace_refine`` x ``furnace_samples`` points of other scramblings, and that
    estimate decides: at grazing incidence the fixed proposals fit a lobe worst, and
    their standard error from a few replicas understates the spread.  A 600-step
    network whose albedo at 89.99 deg was 0.992 (2^20 points, two seeds) read
    1.031 +- 0.006 from 4,096 points and 0.986 to 0.994 from 2^16 (docs/model.md).  A
    model truly over the limit stays over it, measured four times more precisely."""
    rho, err = quadrature.albedo(fn, dirs, s.furnace_samples, seed=seed, target=target)
    over = ~(rho <= 1.0 + s.albedo_tol).all(-1)  # NaN counts as over
    if s.furnace_refine == 1 or not bool(over.any()):
        return rho, err, 0
    r2, e2 = quadrature.albedo(
        fn,
        dirs[over],
        s.furnace_refine * s.furnace_samples,
        seed=seed + REMEASURE_SEED,
        target=target,
    )
    rho, err = rho.clone(), err.clone()
    rho[over], err[over] = r2, e2
    return rho, err, int(over.sum())


def remeasured(report: dict[str, Any], count: int, s: cfgmod.Validation) -> dict[str, Any]:
    """``report`` with :func:`furnace`'s count of directions measured again."""
    report["checks"]["max_albedo"]["remeasured"] = count
    report["furnace"]["remeasured"] = count
    report["furnace"]["refine"] = s.furnace_refine
    return report


def _physics_report(
    rho: np.ndarray,
    err: np.ndarray,
    dirs: torch.Tensor,
    anisotropic: bool,
    recip: float,
    min_val: float,
    s: cfgmod.Validation,
) -> dict[str, Any]:
    """:func:`physics`'s report from its figures: ``rho``, ``err`` (M, C) the albedo and
    its standard error at the furnace directions ``dirs`` (M, 3)."""
    # hemispherical albedo: 2 int_0^1 rho(mu) mu dmu, rows averaged over azimuth
    n_theta = len(dirs) // AZIMUTHS if anisotropic else len(dirs)
    mu = dirs[:, 2].numpy().reshape(n_theta, -1)[:, 0]
    rho_theta = rho.reshape(n_theta, -1, rho.shape[-1]).mean(1)
    order = np.argsort(mu)
    y = rho_theta[order] * mu[order, None]
    hemi = 2.0 * np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(mu[order])[:, None], 0)
    imax = np.unravel_index(np.argmax(rho), rho.shape)
    max_albedo = float(rho.max()) if np.all(np.isfinite(rho)) else math.inf
    checks = {
        "reciprocity": {
            "value": recip,
            "limit": s.reciprocity_tol,
            "passed": bool(recip <= s.reciprocity_tol),
        },
        "min_value": {"value": min_val, "limit": 0.0, "passed": bool(min_val >= 0.0)},
        "max_albedo": {
            "value": max_albedo,
            "limit": 1.0 + s.albedo_tol,
            "passed": bool(max_albedo <= 1.0 + s.albedo_tol),
            "at_theta_deg": float(np.degrees(np.arccos(dirs[imax[0], 2].item()))),
            "quadrature_stderr": float(err[imax]),
        },
    }
    theta = np.degrees(np.arccos(np.clip(mu[order], -1.0, 1.0)))
    return {
        "checks": checks,
        "hemispherical_albedo": hemi.tolist(),
        "furnace": {
            "directions": len(dirs),
            "samples": s.furnace_samples,
            # rho(theta_i) as measured (azimuth-averaged when anisotropic): the report
            # plots it instead of a second quadrature
            "curve": {
                "theta_deg": [round(float(t), 4) for t in theta[::-1]],
                "rho": [[float(v) for v in row] for row in rho_theta[order][::-1]],
            },
        },
    }


def physics_passed(report: dict[str, Any]) -> bool:
    """Every physics check of ``report`` (of :func:`physics` or :func:`report`) passed:
    training's and ``neural-brdf export``'s verdict."""
    return all(c["passed"] for c in report["checks"].values())


def passed(report: dict[str, Any]) -> bool:
    """Every check of ``report`` (:func:`report`) passed: the physics and, with an
    analytic target, the peak.  ``neural-brdf validate``'s verdict."""
    return physics_passed(report) and bool(report.get("peak", {}).get("passed", True))


# a relative RMSE of f cos above this: the model does not reproduce its target at all (a
# teacher's lobe sharper than the network holds: principled at roughness ~0 read 99.9 %)
POOR_ACCURACY = 0.5


def accuracy_notes(report: dict[str, Any], *, peak: bool = True) -> list[str]:
    """One line for each figure of ``report`` that fails although training's verdict,
    the physics (:func:`physics_passed`), does not see it: the highlight's peak beyond
    its limit (``neural-brdf validate`` exits 1 on it; ``peak=False`` leaves it out), a
    relative RMSE above :data:`POOR_ACCURACY`, which no exit code sees (a measured
    reference has no peak check).  ``train`` and ``validate`` print them, so that a
    model that is physical but not its target is not read as a success from the exit
    code alone.  The peak as the table prints it (two decimals: 3.006 % is not "3.0 %")."""
    notes = []
    pk = report.get("peak")
    if peak and pk is not None and not pk["passed"]:
        notes.append(
            f"the highlight's peak is {100 * pk['value']:.2f} % off its target (limit "
            f"{100 * pk['limit']:g} %): physical, but not accurate there; train's exit "
            "code is the physics', `neural-brdf validate` exits 1 on this"
        )
    acc = report.get("accuracy", {}).get("rel_rmse")
    if acc is not None and acc > POOR_ACCURACY:
        notes.append(
            f"relative RMSE of f cos {100 * acc:.1f} %: the model does not reproduce its "
            "target (a lobe sharper than the network holds, or too few train.steps?)"
        )
    return notes


def accuracy(fn: Callable, target: Target, *, n: int, seed: int) -> dict[str, Any]:
    """Error of ``fn`` (numpy in/out) against ``target`` (an analytic BRDF or measured
    data) on :func:`data.accuracy_pairs`; ``n`` applies to analytic targets (measured
    data are compared on all their bins)."""
    measured = kind_of(target) == "measured"
    wi, wo, ref = data.accuracy_pairs(target, None if measured else n, seed)
    wi, wo, ref = wi.numpy(), wo.numpy(), ref.numpy()
    report = _accuracy_report(wi, wo, ref, np.asarray(fn(wi, wo), dtype=np.float64))
    # measured data: the bins training draws from, so none is held out (the report says so)
    report["pairs_from"] = "measured bins" if measured else "sampled"
    return report


def _accuracy_report(
    wi: np.ndarray,
    wo: np.ndarray,
    ref: np.ndarray,
    pred: np.ndarray,
    uv: np.ndarray | None = None,
) -> dict[str, Any]:
    """:func:`accuracy`'s figures from the pairs, the reference and the model's values
    (``uv``: the texture coordinates of a textured model's pairs, named in ``worst``)."""
    n = len(wi)
    cos = np.clip(wo[:, 2:3], 0.0, None)
    a, b = pred * cos, ref * cos
    log_err = float(np.mean(np.abs(np.log1p(np.clip(a, 0, None)) - np.log1p(b))))
    # the ratio of two sums of squares, each scaled by the reference's largest value
    # first: a reference of 1e-300 (a valid, if odd, MERL file) squared to 0 and read a
    # 157-digit percentage
    scale = float(np.max(np.abs(b))) if b.size else 0.0
    if 0.0 < scale < np.inf:
        a, b = a / scale, b / scale
    rel = float(np.sqrt(np.sum((a - b) ** 2) / max(np.sum(b**2), 1e-300)))
    bands = {}
    for lo, hi in INCIDENCE_BANDS:
        k = (wi[:, 2] >= lo) & (wi[:, 2] < hi)
        den = np.sum(b[k] ** 2)
        bands[f"cos_i {lo:g}-{min(hi, 1.0):g}"] = (
            float(np.sqrt(np.sum((a[k] - b[k]) ** 2) / den)) if den > 0 else None
        )
    per = np.abs(a - b).sum(-1)
    worst = []
    for i in np.argsort(-per)[:N_WORST]:
        worst.append(
            {
                "wi": wi[i].round(5).tolist(),
                "wo": wo[i].round(5).tolist(),
                "f": ref[i].tolist(),
                "f_model": pred[i].tolist(),
                **({"uv": uv[i].round(5).tolist()} if uv is not None else {}),
            }
        )
    return {
        "rel_rmse": rel,
        "nbrdf_log_error": log_err,
        "pairs": n,
        "rel_rmse_by_incidence": bands,
        "worst": worst,
    }


# ------------------------------------------------------------------ textured files
def uv_points(n: int, seed: int) -> np.ndarray:
    """``n`` random texture coordinates, uniform in [-1, 2)^2: between texel centres
    (almost surely), and outside [0, 1) as often as inside, since a renderer's uv wrap."""
    return np.random.default_rng(seed).uniform(-1.0, 2.0, (n, 2))


def physics_textured(
    fn: Callable,
    *,
    anisotropic: bool,
    settings: cfgmod.Validation,
    uv_count: int,
) -> dict[str, Any]:
    """:func:`physics` of a textured ``fn(wi, wo, uv)`` (numpy, (N, 3), (N, 3), (N, 2)):
    reciprocity and the smallest value over ``settings.pairs`` random pairs, each at its
    own random uv (:func:`uv_points`); the furnace at ``uv_count`` random uv, each by
    the quadrature of :func:`physics` over a grid of ``max(4, furnace_dirs // 8)``
    polar angles (the largest albedo over every uv and direction is the check; the
    curve and the hemispherical albedo are those of the uv where it was found).  The
    report adds ``furnace.uv`` (the points) and ``furnace.uv_max_albedo`` (each one's)."""
    s = settings
    uv = uv_points(s.pairs, s.seed + 40)

    def at_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return fn(a, b, uv)

    recip = analytic.reciprocity_error(at_pairs, n=s.pairs, seed=s.seed)
    min_val = analytic.min_value(at_pairs, n=s.pairs, seed=s.seed + 1)
    dirs = furnace_directions(max(4, s.furnace_dirs // 8), anisotropic, s.seed + 2)
    points = uv_points(uv_count, s.seed + 41)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    per_uv = []
    again = 0  # directions measured again, over every uv
    for k, p in enumerate(points):

        def at_point(a: np.ndarray, b: np.ndarray, p: np.ndarray = p) -> np.ndarray:
            return fn(a, b, np.broadcast_to(p, a.shape[:-1] + (2,)))

        rho, err, n = furnace(quadrature.from_numpy(at_point), dirs, s, s.seed + 3 + k)
        again += n
        r = rho.numpy()
        top = float(r.max()) if np.all(np.isfinite(r)) else math.inf
        per_uv.append(top)
        if best is None or not top <= best[0]:
            best = (top, r, err.numpy())
    assert best is not None  # uv_count >= 1
    out = _physics_report(best[1], best[2], dirs, anisotropic, recip, min_val, s)
    worst = int(np.argmax(per_uv))
    out["checks"]["max_albedo"]["at_uv"] = points[worst].round(6).tolist()
    out["furnace"]["uv"] = points.round(6).tolist()
    out["furnace"]["uv_max_albedo"] = per_uv
    return remeasured(out, again, s)


def accuracy_textured(fn: Callable, target: Any, *, n: int, seed: int) -> dict[str, Any]:
    """:func:`accuracy` of a textured ``fn(wi, wo, uv)`` against a spatially varying
    ``target`` (``eval(wi, wo, uv)``, ``sample(wi, uv, u)``) on ``n`` pairs at random uv
    in [0, 1)^2, drawn as its training's held-out pairs are (wi uniform, wo half uniform
    and half from the teacher's sampler: ``train.textured_loop.pairs``)."""
    from neural_brdf.train.textured_loop import pairs

    wi, wo, uv, ref = (x.double().numpy() for x in pairs(target, n, np.random.default_rng(seed)))
    pred = np.asarray(fn(wi, wo, uv), dtype=np.float64)
    return _accuracy_report(wi, wo, ref, pred, uv)


def normal_field_error(
    normal: Callable | None, target: Any, *, n: int, seed: int
) -> dict[str, Any] | None:
    """How far a textured file's normal field (``normal(uv)``, (N, 3); None: a file
    without one, whose normal is (0, 0, 1)) is from its teacher's (``target.normal_field``)
    at ``n`` random uv (:func:`uv_points`): the angle between them in degrees, max and
    mean, beside the teacher's largest tilt.  None when neither has a field."""
    if normal is None and getattr(target, "normal_map", None) is None:
        return None
    uv = uv_points(n, seed)
    ref = np.asarray(target.normal_field(uv), dtype=np.float64)
    got = np.tile([0.0, 0.0, 1.0], (n, 1)) if normal is None else np.asarray(normal(uv), float)

    def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # atan2: exact at small angles
        return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))

    err = angle(got, ref)
    return {
        "in_file": normal is not None,
        "uv": n,
        "max_deg": float(err.max()),
        "mean_deg": float(err.mean()),
        "teacher_max_tilt_deg": float(angle(ref, np.array([0.0, 0.0, 1.0])).max()),
    }


def peak_pairs(anisotropic: bool) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
    """The peak probe (module doc): wi, wo (float64, (N, 3)) and one label per pair."""
    wis, wos, labels = [], [], []
    planes = (0.0, 90.0) if anisotropic else (0.0,)
    for phi_deg in planes:
        phi = math.radians(phi_deg)
        ex = np.array([math.cos(phi), math.sin(phi), 0.0])  # in the plane, along the tangent
        ey = np.array([-math.sin(phi), math.cos(phi), 0.0])  # across it
        for th_deg in PEAK_THETAS:
            th = math.radians(th_deg)
            wi = math.sin(th) * ex + np.array([0.0, 0.0, math.cos(th)])
            for way in PEAK_DIRECTIONS:
                for off_deg in PEAK_OFFSETS:
                    if off_deg == 0.0 and way != "normal":
                        continue  # one pair at the mirror direction itself
                    o = math.radians(off_deg)
                    if way == "across":  # rotate the mirror direction about (its) ex x z
                        wo = (
                            -math.sin(th) * math.cos(o) * ex
                            + math.sin(o) * ey
                            + np.array([0.0, 0.0, math.cos(th) * math.cos(o)])
                        )
                    else:  # in the plane: the reflected polar angle th -/+ offset
                        t = th - o if way == "normal" else th + o
                        wo = -math.sin(t) * ex + np.array([0.0, 0.0, math.cos(t)])
                    wis.append(wi)
                    wos.append(wo / np.linalg.norm(wo))
                    labels.append(
                        {"phi_deg": phi_deg, "theta_deg": th_deg, "offset_deg": off_deg, "way": way}
                    )
    return np.array(wis), np.array(wos), labels


def peak(fn: Callable, target: Target, *, anisotropic: bool, tol: float) -> dict[str, Any]:
    """Model / target at and around the mirror direction (module doc) -> a report dict:
    the largest error, where it is, pass/fail against ``tol``, and every probed pair."""
    wi, wo, labels = peak_pairs(anisotropic)
    ref = np.asarray(target.eval(wi, wo), dtype=np.float64)
    pred = np.asarray(fn(wi, wo), dtype=np.float64)
    floor = PEAK_FLOOR * max(float(np.max(ref)), 1e-300)
    ratio = pred / np.maximum(ref, floor)
    err = np.where(np.isfinite(ratio), np.abs(ratio - 1.0), np.inf).max(-1)
    worst = int(np.argmax(err))
    rows = [
        dict(lab, ratio=[round(float(r), 5) for r in ratio[k]], error=float(err[k]))
        for k, lab in enumerate(labels)
    ]
    value = float(err[worst]) if np.isfinite(err[worst]) else math.inf
    return {
        "value": value,
        "limit": tol,
        "passed": bool(value <= tol),
        "at": labels[worst],
        "pairs": rows,
    }


def reference_from(path: str | Path, *, warn: Callable[[str], None] | None = None) -> Any:
    """``--reference``: a measured file (a MERL ``.binary``, an RGL ``.bsdf``: any suffix
    of :mod:`neural_brdf.measured.formats`), or else a YAML config (its target, read with
    train's warnings given ``warn``; a bad one's error names the file; an images fit's is
    refused: :func:`neural_brdf.train.data.refuse_images`)."""
    from neural_brdf.measured import formats

    if formats.find(path) is not None:
        return data.MeasuredTarget.from_file(path, key="--reference")
    if Path(path).suffix.lower() == ".xml":  # else read as YAML: "expected a mapping"
        raise InputError(
            f"--reference {path}: a Mitsuba teacher is named by a config "
            f"(target: {{mitsuba: {Path(path).name}}}); give that config"
        )
    if Path(path).suffix.lower() == ".onnx":  # else "not a YAML text file", or an empty one
        raise InputError(  # read as a config of the default target
            f"--reference {path}: a model, not a target: give the config or the measured "
            "file it was trained from (two models: neural-brdf view A.onnx --compare B.onnx)"
        )
    cfg = cfgmod.load(path, warn=warn)
    # a bad model or parameter: train's message, after the file's name
    return data.build_target(cfg.target, source=str(path))


def report(
    model_path: str | Path,
    *,
    target: cfgmod.Config | Target | None = None,
    settings: cfgmod.Validation | None = None,
    physics_report: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Full report of an exported model; ``["passed"]`` is the physics verdict
    (:func:`passed` adds the peak).

    ``target``: a :class:`Config` (its target is built), or a target already built (an
    analytic BRDF, measured data), or None (physics only).  ``settings`` default to the
    ``validation`` section of the model's embedded config.  ``physics_report``:
    :func:`physics` of this very file, when it was measured already (the pipeline
    measures the graph before writing it, for its metadata).
    """
    model = load(model_path)
    if settings is None:
        try:
            settings = cfgmod.from_dict(model.config).validation
        except cfgmod.ConfigError:
            settings = cfgmod.Validation()
    built = data.build_target(target.target) if isinstance(target, cfgmod.Config) else target
    out = {
        "model": str(model_path),
        "encoding": model.encoding,
        "target": model.target.get("description", ""),  # text, as metadata_version 1 had
    }
    if model.textured:  # f(wi, wo, uv): checked at random uv, against a textured teacher
        if physics_report is None:
            physics_report = physics_textured(
                model.eval,
                anisotropic=is_anisotropic(model.encoding),
                settings=settings,
                uv_count=_uv_count(model),
            )
        out.update(physics_report)
        if built is not None:
            if not spatially_varying(built):
                raise InputError(
                    f"{model_path}: a textured model, and the reference "
                    f"({built.describe()}) does not vary over the surface"
                )
            out["reference"] = built.describe()
            out["accuracy"] = accuracy_textured(
                model.eval, built, n=settings.accuracy_samples, seed=settings.seed + 4
            )
            normal = model.normal if model.has_normal_field else None
            field = normal_field_error(
                normal, built, n=settings.accuracy_samples, seed=settings.seed + 6
            )
            if field is not None:
                out["normal_field"] = field
        out["passed"] = physics_passed(out)
        return out
    if physics_report is None:
        physics_report = physics(
            model.eval, anisotropic=is_anisotropic(model.encoding), settings=settings, target=built
        )
    out.update(physics_report)
    if built is not None:
        if spatially_varying(built):
            raise InputError(
                f"{model_path}: the reference ({built.describe()}) varies over the surface "
                "and this model does not (it has no uv input)"
            )
        out["reference"] = built.describe()
        out["accuracy"] = accuracy(
            model.eval, built, n=settings.accuracy_samples, seed=settings.seed + 4
        )
        if kind_of(built) != "measured":
            out["peak"] = peak(
                model.eval,
                built,
                anisotropic=is_anisotropic(model.encoding) or bool(built.anisotropic),
                tol=settings.peak_tol,
            )
    out["passed"] = physics_passed(out)
    return out


def _uv_count(model: Any) -> int:
    """The furnace's uv points for a textured file: its config's ``texture.validation_uv``."""
    try:
        return cfgmod.from_dict(model.config).texture.validation_uv
    except cfgmod.ConfigError:
        return cfgmod.Texture().validation_uv


def uv_text(uv) -> str:
    """A furnace point's uv as the tables print it: in [0, 1), where it names a texel
    (textures repeat, and the furnace also probes uv outside [0, 1)); 3 decimals."""
    return f"{float(uv[0]) % 1.0:.3f}, {float(uv[1]) % 1.0:.3f}"


def format_table(report: dict[str, Any]) -> str:
    rows = [("check", "value", "limit", "result")]
    for name, c in report["checks"].items():
        op = "<=" if name != "min_value" else ">="
        value = f"{c['value']:.6f}" if name == "max_albedo" else f"{c['value']:.3g}"
        rows.append((name, value, f"{op} {c['limit']:.6g}", "ok" if c["passed"] else "FAIL"))
    hemi = ", ".join(f"{v:.4f}" for v in report["hemispherical_albedo"])
    # a textured file's: that of the uv where the furnace found its largest albedo
    at_uv = report["checks"].get("max_albedo", {}).get("at_uv")
    if at_uv is not None:
        hemi += f" (at uv {uv_text(at_uv)}, the max_albedo's)"
    rows.append(("hemispherical_albedo", hemi, "", ""))
    if "accuracy" in report:
        acc = report["accuracy"]
        # against a file: at its own nodes (a model baked from the file reads 0 there)
        nodes = " at the file's nodes" if acc.get("pairs_from") == "measured bins" else ""
        rows.append(("rel_rmse (f cos)", f"{100 * acc['rel_rmse']:.3f} %{nodes}", "", ""))
        for band, v in acc["rel_rmse_by_incidence"].items():
            rows.append((f"  {band}", "-" if v is None else f"{100 * v:.3f} %", "", ""))
        rows.append(("nbrdf_log_error", f"{acc['nbrdf_log_error']:.3g}", "", ""))
    if "peak" in report:
        pk = report["peak"]
        at = pk["at"]
        where = f"theta_i {at['theta_deg']:g}, {at['offset_deg']:g} deg {at['way']}"
        rows.append(
            (
                "peak (max |f/f_ref - 1|)",
                f"{100 * pk['value']:.2f} % at {where}",
                f"<= {100 * pk['limit']:g} %",
                "ok" if pk["passed"] else "FAIL",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    verdict = "PASSED" if report["passed"] else "FAILED"
    return "\n".join([f"{report['model']}: physics {verdict}"] + lines)


def write_json(report: dict[str, Any], path: str | Path) -> None:
    """Write ``report`` as strict JSON (fileio.json_text: a NaN or an infinity as the
    string "nan", "inf"), atomically (a temporary file, then a rename)."""
    atomic_write(Path(path), json_text(report))
