"""The command line and experiment tooling.

* :mod:`.cli`: ``neural-brdf`` (train, export, validate, codegen, bake, render, view, ...).
* :mod:`.sweep`: hyper-parameter and material sweeps over :func:`neural_brdf.pipeline.run`.
"""
