"""Physics shared by training, validation and the back ends.

* :mod:`.quadrature`: hemispherical integrals (directional albedo by importance-sampled
  quadrature), used by the model's albedo table, the validator's furnace test and the plots.
* :mod:`.lobe_fit`: the importance-sampling lobe fitted to a BRDF (GGX or Beckmann, with
  albedo-like weights).  The lobe's schema, its JSON form in the exported file, its pdf and
  its reference sampler are the file format's: :mod:`neural_brdf.fileformat.lobe`.

Imports only :mod:`neural_brdf.errors`, :mod:`neural_brdf.fileformat` and
:mod:`neural_brdf.target` below it.
"""
