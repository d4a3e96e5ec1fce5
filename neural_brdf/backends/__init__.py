"""Back ends of the lowered graph (:mod:`neural_brdf.graph`): target name -> renderer.

    from neural_brdf import backends
    source = backends.generate("model.onnx", "glsl")       # text of a GLSL ES 3.00 file
    backends.TARGETS                                       # ("c", "glsl", "wgsl")

``drjit`` executes the instructions with Dr.Jit arrays (the Mitsuba plugin's evaluation
path, :mod:`neural_brdf.backends.drjit`); the others render source code
(:mod:`neural_brdf.backends.cstyle`).  A back end is registered here by module and class
name and imported only when it is asked for, so the code generators need neither
Dr.Jit nor Mitsuba.
"""

from __future__ import annotations

import importlib

from neural_brdf.errors import InputError

# target -> (module, class)
REGISTRY: dict[str, tuple[str, str]] = {
    "c": ("neural_brdf.backends.c", "CRenderer"),
    "glsl": ("neural_brdf.backends.glsl", "GLSLRenderer"),
    "wgsl": ("neural_brdf.backends.wgsl", "WGSLRenderer"),
    "drjit": ("neural_brdf.backends.drjit", "DrJitBackend"),
}
# The targets that generate source code (``neural-brdf codegen --target``).
TARGETS = ("c", "glsl", "wgsl")


def get(target: str):
    """The back-end class of ``target``; an unknown name raises a one-line InputError."""
    if target not in REGISTRY:
        raise InputError(f"target: unknown back end {target!r} (known: {', '.join(REGISTRY)})")
    module, cls = REGISTRY[target]
    return getattr(importlib.import_module(module), cls)


def generate(model, target: str, *, lobe: dict | None = None) -> str:
    """Source code of ``target`` (one of TARGETS) for an ONNX model: f, pdf and sample.

    ``lobe`` overrides the sampling lobe stored in the model's metadata (a dict with
    ``alpha`` and ``weight``); a model without one must be given it."""
    if target not in TARGETS:
        raise InputError(f"target: expected one of {', '.join(TARGETS)}, got {target!r}")
    return get(target)().generate(model, lobe=lobe)
