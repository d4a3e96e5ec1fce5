"""Measured BRDF files: readers and writers.

* :mod:`.merl`: the MERL binary format (90 x 90 x 180 half/difference-angle table).
* :mod:`.rgl`: the RGL material database's ``.bsdf`` tensor file (read, bake, write).

A target of training (``target.file``) and of ``neural-brdf bake``.  A new measured format
is one new module here and its suffix in :data:`neural_brdf.train.data.MEASURED_SUFFIXES`
(docs/architecture.md).
"""
