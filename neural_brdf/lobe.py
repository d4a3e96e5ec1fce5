"""The analytic sampling lobe of a neural BRDF: fitted at export, stored in the ONNX file.

A renderer cannot invert a network, so it importance-samples a mixture that is cheap to
sample and whose density is known exactly:

    pdf(wo) = (1 - w) cos(theta_o) / pi  [wo_z > 0]  +  w D_wi(m) / (4 |wo . m|),
    m = normalize(wi + wo),

a cosine-weighted hemisphere plus a GGX visible-normal lobe of roughness ``alpha``
reflected about the sampled normal m (D_wi is the GGX distribution of visible normals,
Heitz 2018).  The second term is Mitsuba's ``MicrofacetDistribution(GGX, alpha,
sample_visible=True)``, so the plugin in :mod:`neural_brdf.mitsuba` samples it with
Mitsuba's own code.

:func:`fit` picks ``(alpha, w)`` on a grid, minimising the relative second moment of
the sample weight f cos / pdf (1 + the relative variance of a one-sample albedo
estimate), averaged over incident directions.  Every grid point is scored on one pooled
set of samples, so the network is evaluated once per sample, not once per candidate;
the fit takes about half a second.  :mod:`neural_brdf.export` stores the result in the
metadata key ``sampling_lobe``:

    {"kind": "cosine+ggx_vndf", "alpha": 0.26, "weight": 0.9,
     "second_moment": 1.31, "second_moment_cosine": 3.9}

``weight`` is the GGX share w; the two second moments (the fitted lobe's and cosine
sampling's alone) say how much the lobe helps.  This module needs numpy, torch and
onnxruntime only: no renderer.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import torch

from analytic import frame
from analytic.microfacet import Distribution

from .errors import InputError
from .runtime import OUTPUT

KEY = "sampling_lobe"  # ONNX metadata key
KIND = "cosine+ggx_vndf"

# The GGX alpha is never below this: Mitsuba's float32 GGX sampling loses accuracy for
# much sharper lobes.  The cosine share is never below 1 - MAX_WEIGHT, which bounds the
# sample weight where the network has a diffuse tail that the GGX lobe misses.
MIN_ALPHA = 0.01
MAX_WEIGHT = 0.9

# The grid, and the incident directions it is scored at: theta from near-normal to
# near-grazing (degrees), each at its own azimuth so anisotropic models are probed
# off-axis too.
ALPHAS = np.geomspace(MIN_ALPHA, 1.0, 25)
WEIGHTS = np.arange(10) / 10.0  # 0, 0.1, ..., MAX_WEIGHT
THETA_DEG = (5.0, 20.0, 35.0, 50.0, 65.0, 80.0)
SAMPLES = 1024  # per candidate lobe (and the cosine lobe) per direction


def fit(fn, *, seed: int = 0) -> dict:
    """Fit the lobe to ``fn(wi, wo) -> f`` (numpy float32 (N, 3) in, (N, 3) out, 1/sr).

    Returns the metadata dict (see the module docstring), with JSON-ready floats."""
    rng = np.random.default_rng(seed)
    dists = [Distribution("ggx", float(a), float(a)) for a in ALPHAS]
    score = np.zeros((len(ALPHAS), len(WEIGHTS)))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # these small ops ran 5x slower on 2 threads than on 1
    try:
        for k, theta in enumerate(THETA_DEG):
            score += _second_moments(fn, dists, _incident(theta, 0.9 * k), rng) / len(THETA_DEG)
    finally:
        torch.set_num_threads(threads)
    i, j = np.unravel_index(np.argmin(score), score.shape)
    return {
        "kind": KIND,
        "alpha": float(ALPHAS[i]),
        "weight": float(WEIGHTS[j]),
        "second_moment": float(score[i, j]),
        "second_moment_cosine": float(score[0, 0]),
    }


def _incident(theta_deg: float, phi: float) -> torch.Tensor:
    t = math.radians(theta_deg)
    return torch.tensor(
        [math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t)], dtype=torch.float64
    )


def _second_moments(fn, dists, wi1: torch.Tensor, rng) -> np.ndarray:
    """E_p[(f cos / p)^2] / A^2 for every (alpha, w) of the grid at one incident
    direction, from samples pooled over every candidate lobe and the cosine lobe
    (defensive mixture q); A = the albedo (RGB mean)."""
    n = SAMPLES
    u = torch.from_numpy(rng.random((len(dists) + 1, n, 2)))
    wi = wi1.expand(n, 3)
    wos = [frame.square_to_cosine_hemisphere(u[0])]
    wos += [frame.reflect(wi, d.sample_visible(wi, uu)) for d, uu in zip(dists, u[1:])]
    wo = torch.cat(wos, 0)  # (L n, 3)
    wi = wi1.expand(len(wo), 3)
    with torch.no_grad():
        p_cos = torch.where(wo[:, 2] > 0, frame.cosine_hemisphere_pdf(wo), 0.0)
        h = frame.normalize(wi + wo)
        jac = 1.0 / (4.0 * frame.dot(wo, h).clamp_min(1e-12))
        p_ggx = torch.stack([d.pdf_visible(wi, h) * jac for d in dists], 0)  # (A, L n)
    # The pooled samples' density over the whole sphere: a visible normal may reflect
    # wi below the horizon; such samples count, with f cos = 0.
    q = ((p_cos + p_ggx.sum(0)) / (len(dists) + 1)).numpy()
    f = np.asarray(fn(wi.numpy().astype(np.float32), wo.numpy().astype(np.float32)))
    fc = f.astype(np.float64).mean(-1) * np.clip(wo[:, 2].numpy(), 0.0, None)
    live = (fc > 0) & (q > 0)
    albedo = np.sum(fc[live] / q[live]) / len(wo)
    if not albedo > 0:  # black at this angle: no preference
        return np.zeros((len(dists), len(WEIGHTS)))
    # (f cos)^2 / q per sample, then / p for every candidate; float32 suffices to rank
    c = (fc[live] ** 2 / q[live]).astype(np.float32)
    p_cos = p_cos.numpy()[live].astype(np.float32)
    p_ggx = p_ggx.numpy()[:, live].astype(np.float32)  # (A, M)
    m2 = np.empty((len(dists), len(WEIGHTS)))
    with np.errstate(divide="ignore"):
        for j, w in enumerate(WEIGHTS.astype(np.float32)):
            m2[:, j] = np.sum(c / ((1 - w) * p_cos + w * p_ggx), axis=-1, dtype=np.float64)
    return m2 / (len(wo) * albedo * albedo)


def fit_onnx(model, *, seed: int = 0) -> dict:
    """:func:`fit` on an ONNX model (a path or the bytes of one), through onnxruntime."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    src = str(model) if isinstance(model, (str, os.PathLike)) else bytes(model)
    session = ort.InferenceSession(src, opts, providers=["CPUExecutionProvider"])
    return fit(lambda wi, wo: session.run([OUTPUT], {"wi": wi, "wo": wo})[0], seed=seed)


def to_json(lobe: dict) -> str:
    return json.dumps(lobe, sort_keys=True)


def parse(text: str) -> dict:
    """The metadata value -> the lobe dict; a one-line InputError if it is malformed."""
    try:
        lobe = json.loads(text)
        kind, alpha, weight = lobe["kind"], float(lobe["alpha"]), float(lobe["weight"])
    except (ValueError, KeyError, TypeError):
        raise InputError(
            f'metadata {KEY!r}: expected JSON {{"kind": "{KIND}", '
            f'"alpha": a, "weight": w}}, got {text!r}'
        ) from None
    if kind != KIND:
        raise InputError(f"metadata {KEY!r}: unknown lobe kind {kind!r} (known: {KIND!r})")
    if not (alpha > 0 and 0.0 <= weight <= 1.0):
        raise InputError(f"metadata {KEY!r}: alpha must be > 0 and weight in [0, 1], got {text!r}")
    return {**lobe, "alpha": max(alpha, MIN_ALPHA), "weight": weight}


def from_metadata(meta: dict) -> dict | None:
    """The stored lobe of a model's metadata (a dict of strings), or None (older files)."""
    text = meta.get(KEY)
    return None if text is None else parse(text)
