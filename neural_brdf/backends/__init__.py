"""Back ends of the lowered graph (:mod:`neural_brdf.graph`): target name -> renderer.

    from neural_brdf import backends
    source = backends.generate("model.onnx", "glsl")       # text of a GLSL ES 3.00 file
    backends.TARGETS                                       # ("c", "glsl", "wgsl")

``drjit`` executes the instructions with Dr.Jit arrays (the Mitsuba plugin's evaluation
path, :mod:`neural_brdf.backends.drjit`); the others render source code
(:mod:`neural_brdf.backends.cstyle`).  A back end is registered here by module and class
name and imported only when it is asked for, so the code generators need neither
Dr.Jit nor Mitsuba.  A new source generator is one file and its line in
:data:`REGISTRY`: :data:`TARGETS` follows from it (docs/architecture.md, "Adding
something").
"""

from __future__ import annotations

import importlib

import numpy as np

from neural_brdf.errors import InputError

# target -> (module, class); the key is the class's ``name``
REGISTRY: dict[str, tuple[str, str]] = {
    "c": ("neural_brdf.backends.c", "CRenderer"),
    "glsl": ("neural_brdf.backends.glsl", "GLSLRenderer"),
    "wgsl": ("neural_brdf.backends.wgsl", "WGSLRenderer"),
    "drjit": ("neural_brdf.backends.drjit", "DrJitBackend"),
}
# The back ends that execute the graph rather than write source code.
EXECUTORS = frozenset({"drjit"})
# The targets that generate source code (``neural-brdf codegen --target``): every other
# registered back end, in the registry's order.
TARGETS: tuple[str, ...] = tuple(t for t in REGISTRY if t not in EXECUTORS)


def get(target: str):
    """The back-end class of ``target``.  An unknown name, or a registry line whose
    module cannot be imported or lacks the class, raises a one-line InputError naming
    ``target`` and the cause."""
    if target not in REGISTRY:
        raise InputError(f"target: unknown back end {target!r} (known: {', '.join(REGISTRY)})")
    module, cls = REGISTRY[target]
    try:
        mod = importlib.import_module(module)
    except ImportError as e:  # a misspelt module, or a dependency it needs (drjit)
        cause = " ".join(str(e).split()) or type(e).__name__
        raise InputError(f"target {target!r}: cannot load its back end: {module}: {cause}") from e
    try:
        return getattr(mod, cls)
    except AttributeError:
        raise InputError(
            f"target {target!r}: cannot load its back end: {module}: has no class {cls!r} "
            "(its backends.REGISTRY line)"
        ) from None


def generate(
    model,
    target: str,
    *,
    lobe: dict | None = None,
    group: int | None = None,
    prefix: str | None = None,
    source: str | None = None,
) -> str:
    """Source code of ``target`` (one of TARGETS) for an ONNX model: f, pdf and sample.

    ``lobe`` overrides the sampling lobe stored in the model's metadata (a dict with
    ``alpha`` and ``weight``); a model without one must be given it.  ``group``: the
    WGSL bind group of a textured file's textures, an int from 0 to 2^31 - 1 (default
    1; anything else is a one-line InputError naming ``group``,
    :func:`neural_brdf.backends.wgsl.check_group`; texture k is at binding k; GLSL's
    bindings are #defines, C's are parameters).  ``prefix``: the prefix of every name
    the file defines (default ``neural_brdf``: ``neural_brdf_eval``, C's guard
    ``NEURAL_BRDF_H``), so that the files of several models can be used in one program
    (:func:`neural_brdf.backends.cstyle.check_prefix`).  ``source``: how the header
    comment and errors name the model (default: its path as given; errors of bytes or
    a ModelProto say ``codegen``)."""
    if target not in TARGETS:
        raise InputError(f"target: expected one of {', '.join(TARGETS)}, got {target!r}")
    options: dict = {} if prefix is None else {"prefix": prefix}
    if group is not None:
        if target != "wgsl":
            raise InputError(f"group: a WGSL bind group, not for target {target!r}")
        options["group"] = group
    # source only when given: a back end written to the registry's first contract,
    # generate(model, *, lobe), keeps working (tests/test_recipes.py adds one so)
    named: dict = {} if source is None else {"source": source}
    return get(target)(**options).generate(model, lobe=lobe, **named)


def textures(model, *, source: str | None = None) -> list[np.ndarray]:
    """The data the generated code of a textured file reads from its bound textures, in
    order (``neural_brdf_texture0``, ...): float32 [rows, channels] each, row-major, as
    the ONNX initializer holds them (for the weight field [R * R, K], row j * R + i for
    texel column i along u and row j along v).  A file with the normal field (output n)
    lists after neural_brdf_eval's the one neural_brdf_normal reads, its texels [Rv * Ru,
    3] (row j * Ru + i).  A two-input file has none: [].  ``source``: how errors name
    the model (default: its path as given)."""
    from neural_brdf.backends.cstyle import lower_file

    return [t.data.copy() for t in lower_file(model, source=source)[2]]
