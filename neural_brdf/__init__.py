"""Physically plausible neural BRDFs: train on the CPU, export ONNX, validate physics.

    python train.py configs/quickstart.yaml              # train + export + validate
    neural-brdf validate runs/quickstart/model.onnx

    import neural_brdf
    brdf = neural_brdf.load("runs/quickstart/model.onnx")   # onnxruntime only
    f = brdf.eval(wi, wo)                                    # (..., 3) -> (..., 3), 1/sr

Modules, in the order data flows: config, encoding, model, quadrature, data, train,
export, validate, runtime (the consumer side), cli.
"""

from .runtime import NeuralBRDF, load

__all__ = ["NeuralBRDF", "load"]
