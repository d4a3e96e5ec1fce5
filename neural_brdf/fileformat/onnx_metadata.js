// neural-brdf: read an exported model's metadata (ONNX metadata_props) from the file's
// bytes, in a browser or in Node, with no dependency.  onnxruntime-web and -node have no
// metadata API, so this walks the protobuf itself (docs/portable.md, "Metadata").
//
//   const props = readOnnxMetadata(bytes);   // Uint8Array | ArrayBuffer -> {key: "value"}
//   const meta = decodeMetadata(props);      // the same, structured values parsed
//
// The walk knows three messages of onnx.proto and skips every other field by its wire
// type: ModelProto field 14 is metadata_props (repeated StringStringEntryProto), whose
// field 1 is the key and field 2 the value (both UTF-8 strings).  It reads nothing else,
// so it needs no schema, and the graph (a large field 7) is skipped in one step.
// neural_brdf/viewer/page.py inlines this file into the viewer page;
// tests/fileformat/test_portable.py runs it under Node (tests/js/read_metadata.mjs)
// against Python's onnx.
"use strict";

// Wire types of the protobuf encoding: 0 varint, 1 fixed64, 2 length-delimited,
// 5 fixed32 (3 and 4, the deprecated groups, never occur in ONNX files).
function onnxVarint(buf, pos) {            // -> [value, next position]; up to 2^53
  let value = 0, scale = 1, b;
  do {
    if (pos >= buf.length) throw new Error("ONNX metadata: truncated varint");
    b = buf[pos++];
    value += (b & 0x7f) * scale;
    scale *= 128;
  } while (b & 0x80);
  return [value, pos];
}

function onnxFields(buf, start, end, visit) {  // visit(field, wireType, valueStart, valueEnd)
  let pos = start;
  while (pos < end) {
    let tag, len;
    [tag, pos] = onnxVarint(buf, pos);
    const field = Math.floor(tag / 8), wire = tag % 8;
    if (wire === 0) {
      [, pos] = onnxVarint(buf, pos);
    } else if (wire === 1) {
      pos += 8;
    } else if (wire === 5) {
      pos += 4;
    } else if (wire === 2) {
      [len, pos] = onnxVarint(buf, pos);
      if (pos + len > end) throw new Error("ONNX metadata: truncated field " + field);
      visit(field, wire, pos, pos + len);
      pos += len;
    } else {
      throw new Error("ONNX metadata: unsupported wire type " + wire + " (not an ONNX file?)");
    }
    if (pos > end) throw new Error("ONNX metadata: truncated field " + field);
  }
}

const ONNX_METADATA_PROPS = 14;            // ModelProto.metadata_props
const ONNX_ENTRY_KEY = 1, ONNX_ENTRY_VALUE = 2;  // StringStringEntryProto.key / .value

// The metadata_props of an ONNX file: {key: value} with string values, in file order (a
// repeated key keeps its last value, as onnxruntime's custom_metadata_map does).
function readOnnxMetadata(bytes) {
  const buf = bytes instanceof Uint8Array ? bytes : new Uint8Array(bytes);
  const utf8 = new TextDecoder("utf-8");
  const out = {};
  onnxFields(buf, 0, buf.length, (field, wire, a, b) => {
    if (field !== ONNX_METADATA_PROPS) return;
    let key = "", value = "";
    onnxFields(buf, a, b, (f, w, s, e) => {
      if (f === ONNX_ENTRY_KEY) key = utf8.decode(buf.subarray(s, e));
      else if (f === ONNX_ENTRY_VALUE) value = utf8.decode(buf.subarray(s, e));
    });
    out[key] = value;
  });
  return out;
}

// Keys whose value is JSON (an object, an array or a number) in metadata_version 2; the
// others are text.  Files written before metadata_version existed (version 1) hold the
// target as a description and training_config as YAML: those stay text here (Python's
// neural_brdf.runtime reads both forms).
const ONNX_JSON_KEYS = ["metadata_version", "format_version", "target", "training_config",
  "hemispherical_albedo", "sampling_lobe", "max_albedo", "reciprocity_error", "min_value",
  "parity_rel_error", "float32_rel_precision", "texture"];

// readOnnxMetadata's strings with the JSON values parsed; metadata_version is 1 when the
// file has none.  A value that is not valid JSON (an older file's text) is kept as text.
function decodeMetadata(props) {
  const out = {};
  for (const [k, v] of Object.entries(props)) {
    out[k] = v;
    if (!ONNX_JSON_KEYS.includes(k)) continue;
    try { out[k] = JSON.parse(v); } catch (e) { /* version 1 text: kept as it is */ }
  }
  if (!("metadata_version" in out)) out.metadata_version = 1;
  return out;
}

if (typeof module !== "undefined" && module.exports)
  module.exports = {readOnnxMetadata, decodeMetadata, ONNX_JSON_KEYS};
