"""BSDF evaluation in Dr.Jit (Mitsuba 3, llvm_ad_rgb) on batches of directions.

One timed call is what a Python caller of the plugin pays:

    out = bsdf.eval(BSDFContext(), si, wo)      # traces the evaluation
    dr.eval(out); dr.sync_thread()              # compiles (first call) and runs it

``si.wi`` and ``wo`` are evaluated before timing, and the same arrays are reused, so
that every call traces the same kernel and finds it in Dr.Jit's kernel cache.  The
first call, which compiles with LLVM, is reported separately (``first_call_s``; a
kernel already in the on-disk cache ~/.drjit loads instead, so it depends on history).
``dr.sync_thread`` is needed: the LLVM backend launches kernels asynchronously.

The steady-state cost of a call is the tracing (for the neural plugin, a Python walk
over the ONNX graph), the kernel's assembly and its run.  A renderer traces once per
megakernel or wavefront, so the large-batch rate is its cost per sample, and the
small-batch rate is the fixed cost per call.  ``BSDF.eval`` returns f * cos(theta_o):
the cosine costs one multiply more than ``f``.
"""

from __future__ import annotations

import json
import time

import drjit as dr
import mitsuba as mi
import numpy as np

if mi.variant() is None:
    mi.set_variant("llvm_ad_rgb")

import neural_brdf.renderers.mitsuba  # noqa: E402,F401  (registers neural_brdf and analytic_brdf)

_PLUGINS: dict[str, object] = {}


def load(bsdf: dict):
    """``mi.load_dict(bsdf)``, once per dict (the neural plugin fits its sampling lobe
    when it loads a file without one: not part of evaluation)."""
    key = json.dumps(bsdf, sort_keys=True)
    if key not in _PLUGINS:
        _PLUGINS[key] = mi.load_dict(bsdf)
    return _PLUGINS[key]


def evaluator(bsdf: dict, wi: np.ndarray, wo: np.ndarray):
    """A no-argument callable that evaluates ``bsdf`` (a load_dict dict) on the pairs."""
    plugin = load(bsdf)
    ctx = mi.BSDFContext()
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
    v = mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])
    dr.eval(si, v)
    dr.sync_thread()

    def call():
        out = plugin.eval(ctx, si, v)
        dr.eval(out)
        dr.sync_thread()

    return call


def first_call_seconds(call) -> float:
    t0 = time.perf_counter()
    call()
    return time.perf_counter() - t0


def reference_bsdfs(target: dict) -> dict[str, dict]:
    """What the neural plugin is compared with: Mitsuba's built-in roughconductor (GGX,
    alpha and material of ``target`` when it is a conductor microfacet, else its own
    defaults) and the ``analytic_brdf`` plugin running ``target``'s exported graph."""
    p = target.get("params") or {}
    rough = {"type": "roughconductor", "distribution": "ggx", "alpha": float(p.get("alpha", 0.3))}
    if p.get("material"):
        rough["material"] = p["material"]
    return {
        "roughconductor": rough,
        "analytic_brdf": {
            "type": "analytic_brdf",
            "model": target["model"],
            "params": json.dumps(p),
        },
    }


def info() -> dict:
    return {
        "variant": mi.variant(),
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "drjit_threads": dr.thread_count(),
    }
