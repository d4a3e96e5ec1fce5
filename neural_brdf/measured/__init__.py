"""Measured BRDF files: readers and writers, one registry by file suffix.

* :mod:`.formats`: the registry (suffix -> :class:`~.formats.Format`: name, reader,
  writer, error type) that ``target.data``, ``validate --reference`` and
  ``neural-brdf bake`` go through; :func:`.formats.read`, :func:`.formats.bake`.
* :mod:`.base`: what the formats share: the :class:`~.base.MeasuredBRDF` protocol a
  reader returns, :class:`~.base.FormatError`, and :func:`~.base.eval_pairs` (the edges
  of ``eval``: below the horizon, non-finite or zero-length directions give 0).
* :mod:`.merl`: the MERL binary format (90 x 90 x 180 half/difference-angle table).
* :mod:`.rgl`: the RGL material database's ``.bsdf`` tensor file (read, bake, write).
* :mod:`.mitsuba`: a BSDF of a Mitsuba 3 XML file as the teacher (``target.mitsuba``),
  evaluated and sampled by Mitsuba itself; it alone imports Mitsuba.

A new measured format is a reader returning a ``MeasuredBRDF`` and a writer, registered
with :func:`.formats.register` (docs/architecture.md, "A measured format").
"""
