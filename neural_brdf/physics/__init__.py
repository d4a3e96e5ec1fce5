"""Physics shared by training, validation and the back ends (issue 22's layout).

* :mod:`.quadrature`: hemispherical integrals (directional albedo by importance-sampled
  quadrature), used by the model's albedo table, the validator's furnace test and the plots.
* :mod:`.lobe`: the importance-sampling lobe fitted to a BRDF (GGX or Beckmann, with
  albedo-like weights), its JSON form in the exported file, its pdf and sampling.

Imports only :mod:`neural_brdf.errors` and :mod:`neural_brdf.fileformat` below it.
"""
