"""Renderers that evaluate the exported graph.

* :mod:`.mitsuba`: the Mitsuba 3 plugins ``neural_brdf`` (a model.onnx) and
  ``analytic_brdf`` (an analytic model exported to the same kind of graph).
* :mod:`.render`: preview and comparison renders with those plugins.
* :mod:`.spheres`: a small numpy sphere renderer and image metrics (no Mitsuba).
"""
