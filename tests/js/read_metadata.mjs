// Print the metadata of ONNX files as JSON, read by the viewer's reader
// (neural_brdf/fileformat/onnx_metadata.js): node tests/js/read_metadata.mjs MODEL.onnx...
// -> [{"props": {key: "value"}, "decoded": {...}}, ...].  Used by tests/fileformat/test_portable.py.
import {readFileSync} from "node:fs";
import {createRequire} from "node:module";

const require = createRequire(import.meta.url);
const {readOnnxMetadata, decodeMetadata} = require("../../neural_brdf/fileformat/onnx_metadata.js");

const out = process.argv.slice(2).map((path) => {
  const props = readOnnxMetadata(readFileSync(path));
  return {props, decoded: decodeMetadata(props)};
});
process.stdout.write(JSON.stringify(out));
