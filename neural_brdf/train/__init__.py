"""Training: from a target to a checkpoint.

* :mod:`.encoding`: the reciprocal input features of a direction pair.
* :mod:`.model`: the network (``RawBRDF``), its energy normalisation (``NormalizedBRDF``)
  and the exported whole (``TotalBRDF``).
* :mod:`.data`: targets (analytic, measured) and the training pairs drawn from them.
* :mod:`.loop`: the training loop, its checkpoints and ``log.csv``.
* :mod:`.many`: many materials trained as one batched model.

Knows nothing of export, validation or the report (:mod:`neural_brdf.pipeline` runs them).
"""
