"""Physically plausible neural BRDFs: train on the CPU, export ONNX, validate physics.

    python train.py configs/quickstart.yaml              # train + export + validate
    neural-brdf train quickstart                         # the same preset, from any folder
    neural-brdf validate runs/quickstart/model.onnx

    import neural_brdf
    brdf = neural_brdf.load("runs/quickstart/model.onnx")   # onnxruntime only
    f = brdf.eval(wi, wo)                                    # (..., 3) -> (..., 3), 1/sr

The package's parts, in the order data flows (docs/architecture.md; each imports only
the parts before it, tests/test_packaging.py): errors, limits, fileio, version,
fileformat/ (the file's contract), config, presets, runtime (the consumer side),
physics/, measured/, train/, validate, graph/, export, backends/, renderers/, inverse/,
viewer/, pipeline, tooling/ (the command line).

``import neural_brdf`` is light: ``load`` and ``NeuralBRDF`` are imported on first use
(numpy and onnxruntime only), and neither torch nor pydantic is loaded by them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from neural_brdf.version import __version__

if TYPE_CHECKING:
    from neural_brdf.runtime import NeuralBRDF, load

__all__ = ["NeuralBRDF", "__version__", "load"]
_LAZY = {"NeuralBRDF", "load"}


def __getattr__(name: str) -> Any:
    # PEP 562: onnxruntime is imported when load/NeuralBRDF is first used, not by the CLI
    if name in _LAZY:
        from neural_brdf import runtime

        return getattr(runtime, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
