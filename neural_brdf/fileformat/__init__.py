"""The exported file's contract, in one place: the bottom of the package.

This module holds the graph's input and output names, the format and metadata versions,
the metadata keys with their kinds and the fixed texts; it imports nothing (not even
numpy).  Its modules hold the rest of what a reader of model.onnx needs:

* :mod:`.metadata`: the values' encoding, their decoding for every metadata version and
  the typed :class:`~neural_brdf.fileformat.metadata.Metadata` the exporter writes;
* :mod:`.lobe`: the sampling lobe's schema, pdf and reference sampler;
* :mod:`.reader`: the one ONNX loader (one-line errors) and the graph's signature;
* :mod:`.portable`: the rewrite that makes torch's graph portable, and opset conversion;
* ``onnx_metadata.js``: the metadata read in a browser or in Node.  It lists
  :data:`JSON_KEYS` again, in its own language; tests/fileformat/test_portable.py checks
  that the two lists agree.

The exporter, the runtime, the config, the graph lowering, the Mitsuba plugin and the
code generators import these names.  docs/portable.md and docs/model.md describe the
keys; docs/architecture.md the package's layering.
"""

from __future__ import annotations

# The graph: inputs wi, wo float32 [N, 3] (unit vectors in the local shading frame),
# output f float32 [N, 3] (1/sr, no cosine).
INPUTS = ("wi", "wo")
OUTPUT = "f"
# An optional third input, for a material that varies over the surface (a textured
# material): uv float32 [N, 2], the surface point's texture coordinates (u, v) as the
# host's mesh gives them (docs/model.md, "The ONNX contract").
# Its graph is exported by neural_brdf.train.textured_model (issue 30: `neural-brdf
# train` of a textured Mitsuba teacher; its metadata has a "texture" entry); a reader
# accepts a graph whose inputs are one of SIGNATURES, in that order (reader.signature),
# and a consumer that gives no uv may evaluate only a graph without it.
UV = "uv"
OPTIONAL_INPUTS = (UV,)
SIGNATURES = (INPUTS, INPUTS + OPTIONAL_INPUTS)
# An optional second output of a textured graph: n float32 [N, 3], the shading normal
# that the teacher's normal (or bump) map gives at uv, a unit vector in the unperturbed
# shading frame.  It depends on uv alone.  The host rotates its frame to it (as
# Mitsuba's normalmap does) and evaluates f in the rotated frame: f stays reciprocal
# there, and the normal map is never baked into f (docs/model.md, "The normal field").
NORMAL = "n"
OUTPUT_SIGNATURES = ((OUTPUT,), (OUTPUT, NORMAL))  # the second only with the uv input
INPUT_WIDTHS = {INPUTS[0]: 3, INPUTS[1]: 3, UV: 2}  # each input is float32 [N, width]

# Of the resolved config, the checkpoint and the exported model (its ONNX model_version).
# 2: the encoding's peak coordinate u_h replaced sqrt(theta_h / (pi/2)) (issue 19), so a
# version-1 checkpoint's weights mean something else: it is not resumed.
FORMAT_VERSION = 2

# metadata_props: the version of their schema (docs/portable.md, "Metadata").  1: the files
# written before the key existed (target a description, training_config YAML); 2: every
# value that carries structure is JSON.  neural_brdf.runtime reads both.
METADATA_VERSION_KEY = "metadata_version"  # absent: version 1
METADATA_VERSION = 2

LOBE_KEY = "sampling_lobe"  # the importance-sampling lobe (fileformat/lobe.py), JSON

# metadata_props whose values are JSON (objects, arrays, numbers) in metadata_version 2;
# the others (TEXT_KEYS) are text.
JSON_KEYS = (
    METADATA_VERSION_KEY,
    "format_version",
    "target",
    "training_config",
    "hemispherical_albedo",
    LOBE_KEY,
    "max_albedo",
    "reciprocity_error",
    "min_value",
    "parity_rel_error",
    "float32_rel_precision",
    "texture",  # a spatially varying file only: its weight field (docs/portable.md)
)
TEXT_KEYS = ("producer", "frame", "units", "encoding", "normalization")
KEYS = JSON_KEYS + TEXT_KEYS  # every key an exported model carries

PRODUCER_NAME = "neural-brdf"  # ONNX producer_name (producer_version: the package's)
FRAME = (
    "local shading frame: z = normal, x = tangent (anisotropy axis), y = z cross x; "
    "wi and wo are unit vectors pointing away from the surface; f = 0 when "
    "wi_z <= 0 or wo_z <= 0"
)
UNITS = "f: BRDF value in 1/sr per RGB channel, without the cosine factor"
