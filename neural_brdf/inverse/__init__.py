"""Fitting a BRDF to rendered images (``target.images``, docs/inverse.md).

* :mod:`.bsdf`: a differentiable Mitsuba BSDF that evaluates the network (``RawBRDF``).
* :mod:`.fit`: the training stage: read the scene and images, fit, checkpoint.
* :mod:`.scene`: the example scene and its reference images.
* :mod:`.coverage`: the part of the (wi, wo) domain the views observe, before fitting.
"""
