// Evaluate an exported model with onnxruntime-web (its wasm back end) under Node:
//
//   node tests/js/ort_web_eval.mjs MODEL.onnx DIR
//
// DIR/cases.json lists {"name", "n"}; DIR/NAME.wi.f32 and NAME.wo.f32 hold n x 3
// little-endian float32.  Writes DIR/NAME.f.f32 (n x 3) for every case that ran, and
// DIR/results.json: {"version", "cases": {NAME: {"dims"} or {"error"}}}.  A failing case
// is recorded, not fatal, so the test sees each; a file that does not load fails every case.  Used by tests/fileformat/test_portable.py
// (install: cd tests/js && ONNXRUNTIME_NODE_INSTALL=skip npm ci).
import {readFileSync, writeFileSync} from "node:fs";
import {join} from "node:path";
import * as ort from "onnxruntime-web";

const [model, dir] = process.argv.slice(2);
ort.env.wasm.numThreads = 1;               // no worker threads under Node
ort.env.logLevel = "error";
const message = (e) => String(e && e.message ? e.message : e).slice(0, 500);
const cases = JSON.parse(readFileSync(join(dir, "cases.json"), "utf8"));
let session;
try {
  session = await ort.InferenceSession.create(readFileSync(model), {
    executionProviders: ["wasm"],
  });
} catch (e) {                              // the file does not load: every case fails
  const failed = Object.fromEntries(cases.map(({name}) => [name, {error: message(e)}]));
  writeFileSync(join(dir, "results.json"), JSON.stringify({version: null, cases: failed}));
  process.exit(0);
}
const f32 = (path) => {
  const b = readFileSync(path);
  return new Float32Array(b.buffer.slice(b.byteOffset, b.byteOffset + b.byteLength));
};
const results = {version: ort.env.versions.web, cases: {}};
for (const {name, n} of cases) {
  try {
    const feeds = {
      wi: new ort.Tensor("float32", f32(join(dir, name + ".wi.f32")), [n, 3]),
      wo: new ort.Tensor("float32", f32(join(dir, name + ".wo.f32")), [n, 3]),
    };
    const f = (await session.run(feeds)).f;
    writeFileSync(join(dir, name + ".f.f32"), Buffer.from(f.data.buffer, f.data.byteOffset,
                                                            f.data.byteLength));
    results.cases[name] = {dims: f.dims};
  } catch (e) {
    results.cases[name] = {error: message(e)};
  }
}
writeFileSync(join(dir, "results.json"), JSON.stringify(results));
