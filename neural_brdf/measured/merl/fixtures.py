"""Real materials as functions, for tests and benchmarks: the NBRDF networks of the
100 MERL materials and their analytic ABC fits."""

from __future__ import annotations

import csv
import difflib
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from analytic import frame, fresnel
from neural_brdf.measured.merl.format import _canonical


# ------------------------------------------------------------ real-material fixtures
def _edge_in(wi, wo):
    """Numpy or torch in -> (was it torch, wi, wo) as broadcast tensors of one dtype."""

    def tensor(x):
        if isinstance(x, torch.Tensor):
            return x
        return torch.from_numpy(np.array(x, dtype=np.float64))  # a copy: never read-only

    is_torch = isinstance(wi, torch.Tensor) or isinstance(wo, torch.Tensor)
    wi_t, wo_t = tensor(wi), tensor(wo)
    dtype = torch.promote_types(wi_t.dtype, wo_t.dtype)
    wi_t, wo_t = torch.broadcast_tensors(wi_t.to(dtype), wo_t.to(dtype))
    return is_torch, wi_t, wo_t


def _edge_out(f: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, is_torch: bool):
    f = torch.where(((wi[..., 2] > 0) & (wo[..., 2] > 0))[..., None], f, torch.zeros_like(f))
    return f if is_torch else f.detach().cpu().numpy()


def _closest(name: str, names) -> str:
    near = difflib.get_close_matches(name, list(names), n=3)
    return f"; closest: {near}" if near else ""


def nbrdf_names(npz_path) -> list[str]:
    with np.load(npz_path) as z:
        return sorted({k.split("/")[0] for k in z.files})


def nbrdf_fixture(npz_path, name: str, *, reciprocal: bool = False) -> Callable:
    """One pretrained NBRDF network (Sztrajman et al. 2021) as f(wi, wo) -> (..., 3).

    The published architecture: a 6-21-21-3 ReLU MLP on
    x = [sin th_h, 0, cos th_h, sin th_d cos ph_d, sin th_d sin ph_d, cos th_d]
    (Rusinkiewicz angles with phi_h = 0), y = relu(relu(x W0 + b0) W1 + b1) W2 + b2,
    f = exp(y) - 1 in 1/sr with the MERL colour scales applied.  The raw output is
    returned (it can dip slightly below 0; :func:`bake` clamps), and 0 below the horizon.
    Numpy in -> numpy out, torch in -> torch out (float64 for numpy); the angles are
    computed in the input's precision, the MLP runs in float32.

    The networks are not reciprocal: f(wi, wo) and f(wo, wi) (phi_d and phi_d + pi)
    differ by a few percent typically and by over 50% in places, while a MERL grid
    folds phi_d and holds one value for both.  ``reciprocal=True`` returns
    (g(phi_d) + g(phi_d + pi)) / 2 = (g(wi, wo) + g(wo, wi)) / 2, on the canonically
    ordered pair: exactly symmetric, smooth across the fold, and what a MERL grid can
    represent.
    """
    with np.load(npz_path) as z:
        keys = [f"{name}/{k}" for k in ("W0", "b0", "W1", "b1", "W2", "b2")]
        if keys[0] not in z.files:
            names = {k.split("/")[0] for k in z.files}
            raise ValueError(f"{npz_path}: no NBRDF network named {name!r}{_closest(name, names)}")
        # float32, as the networks were trained and shipped (and twice as fast as float64)
        params = [torch.from_numpy(np.asarray(z[k], dtype=np.float32)) for k in keys]
    w0, b0, w1, b1, w2, b2 = params
    if w0.shape != (6, 21) or w2.shape[1] != 3:
        raise ValueError(
            f"{npz_path}: {name}: unexpected weight shapes {tuple(w0.shape)}, {tuple(w2.shape)}"
        )

    def net(th, td, dx, dy):
        x = torch.stack(
            [torch.sin(th), torch.zeros_like(th), torch.cos(th), dx, dy, torch.cos(td)], -1
        ).to(w0.dtype)  # (..., 6)
        y = torch.relu(x @ w0 + b0)  # (..., 21)
        y = torch.relu(y @ w1 + b1)  # (..., 21)
        return torch.expm1(y @ w2 + b2).to(th.dtype)  # exp(y) - 1, (..., 3)

    def f(wi, wo):
        is_torch, wi_t, wo_t = _edge_in(wi, wo)
        if reciprocal:
            wi_t, wo_t = _canonical(wi_t, wo_t)
        th, _, td, pd = frame.rusinkiewicz(wi_t, wo_t)
        dx, dy = torch.sin(td) * torch.cos(pd), torch.sin(td) * torch.sin(pd)
        val = net(th, td, dx, dy)
        if reciprocal:  # phi_d + pi: the difference vector's x, y negated
            val = 0.5 * (val + net(th, td, -dx, -dy))
        return _edge_out(val, wi_t, wo_t, is_torch)

    f.__name__ = f"nbrdf[{name}]"
    return f


@dataclass(frozen=True)
class ABCParams:
    """One row of merl_abc_low2012_params.csv: kD and A per channel, B, C and ior shared."""

    name: str
    kd: tuple[float, float, float]
    a: tuple[float, float, float]
    b: float
    c: float
    ior: float


def read_abc_params(csv_path) -> dict[str, ABCParams]:
    """name -> :class:`ABCParams`, from the columns name,kD_r,kD_g,kD_b,A_r,A_g,A_b,B,C,ior."""
    cols = ["name", "kD_r", "kD_g", "kD_b", "A_r", "A_g", "A_b", "B", "C", "ior"]
    out = {}
    with open(csv_path, newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames != cols:
            raise ValueError(f"{csv_path}: expected columns {cols}, got {reader.fieldnames}")
        for row in reader:
            v = {k: float(row[k]) for k in cols[1:]}
            out[row["name"]] = ABCParams(
                row["name"],
                (v["kD_r"], v["kD_g"], v["kD_b"]),
                (v["A_r"], v["A_g"], v["A_b"]),
                v["B"],
                v["C"],
                v["ior"],
            )
    return out


def abc_fixture(csv_path, name: str) -> Callable:
    """The ABC-model fit (Low et al. 2012) of one MERL material as f(wi, wo) -> (..., 3).

    Formula source: jdupuy/dj_brdf, ``dj_brdf.h`` (``abc::eval``, ``abc__ndf``,
    ``abc::gaf``, ``fresnel::unpolarized``), the code the parameter table comes from and
    pairs with, written out here from its equations:

        f = (kD + F(wi.h) D(h) G / (cos_i cos_o)) / pi
        D = A / (1 + B (1 - cos th_h))^C          (A per channel; B, C shared)
        G = min(1, 2 cos th_h cos_i / (wi.h), 2 cos th_h cos_o / (wo.h))   (V-cavity)
        F = exact unpolarised dielectric Fresnel with the fitted scalar ior

    D has the ABC profile A / (1 + B x)^C of Low et al. 2012 ("BRDF models for accurate
    and efficient rendering of glossy surfaces"), here in x = 1 - cos th_h as dj_brdf
    codes it; the paper itself was not at hand, so dj_brdf is the reference.  The 1/pi
    placement is checked in the tests against the NBRDF fit of the same materials.  F is
    :func:`analytic.fresnel.dielectric`, the same function as dj_brdf's
    ``unpolarized__eval`` in another algebraic form.  0 below the horizon.
    """
    table = read_abc_params(csv_path)
    if name not in table:
        raise ValueError(f"{csv_path}: no ABC fit for {name!r}{_closest(name, table)}")
    p = table[name]

    def f(wi, wo):
        is_torch, wi_t, wo_t = _edge_in(wi, wo)
        kd = torch.tensor(p.kd, dtype=wi_t.dtype)
        a = torch.tensor(p.a, dtype=wi_t.dtype)
        h = frame.half_vector(wi_t, wo_t)
        ci = wi_t[..., 2].clamp_min(frame.EPS_COS)
        co = wo_t[..., 2].clamp_min(frame.EPS_COS)
        ch = h[..., 2].clamp(0.0, 1.0)
        di = frame.dot(wi_t, h).clamp_min(frame.EPS_COS)
        do = frame.dot(wo_t, h).clamp_min(frame.EPS_COS)
        g = torch.minimum(2.0 * ch * ci / di, 2.0 * ch * co / do).clamp(max=1.0)
        d = a / (1.0 + p.b * (1.0 - ch))[..., None] ** p.c
        fr = fresnel.dielectric(p.ior, di)
        val = (kd + fr * d * (g / (ci * co))[..., None]) / math.pi
        return _edge_out(val, wi_t, wo_t, is_torch)

    f.__name__ = f"abc[{name}]"
    return f
