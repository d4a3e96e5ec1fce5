// neural-brdf viewer: draws generated GLSL (neural_brdf_eval) in WebGL2.  Inlined into
// one HTML file by neural_brdf/viewer/page.py together with the JSON in #nb-data.
"use strict";
const DATA = JSON.parse(document.getElementById("nb-data").textContent);
const S = DATA.sphere;                     // sphere view size in pixels
const NM = DATA.models.length;
const PI = Math.PI;
const LUMA = [0.2126, 0.7152, 0.0722];     // Rec. 709 luminance weights
const SLICE_N = 181;                       // theta_o samples of a slice, 1 degree apart
const status = document.getElementById("nb-status");
// a failure anywhere (no WebGL2, a shader the driver refuses) is shown on the page
window.addEventListener("error", (e) => { status.textContent = "error: " + e.message; });
const $ = (id) => document.getElementById(id);
// A textured model (DATA.textured) is drawn on a textured sphere and its plots are at one
// of DATA.probes (points uv); a teacher (a model with "tabulated") was evaluated by
// Mitsuba when the page was written, at DATA.lights ([theta, phi] in degrees) only.
const PROBES = DATA.probes;
const LIGHTS = DATA.lights;
const TEX_WIDTH = 2048;                    // texels per row of a bound texture (R32F)

// ---------------------------------------------------------------- metadata
// A model read from an ONNX file carries the file itself (base64, DATA.models[k].onnx);
// its metadata_props are read from those bytes by readOnnxMetadata and decodeMetadata
// (neural_brdf/fileformat/onnx_metadata.js, inlined before this script).  Shown before WebGL starts,
// so they are there even where WebGL2 is not.
function b64ToBytes(s) {
  const bin = atob(s), u = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) u[i] = bin.charCodeAt(i);
  return u;
}
function b64ToF32(s) {
  const u = b64ToBytes(s);
  return new Float32Array(u.buffer, 0, u.length >> 2);
}
// float16 (little-endian) with a scale, as neural_brdf/viewer/page.py (pack_half) writes it
function unpackHalf(p) {
  const u = b64ToBytes(p.data), h = new Uint16Array(u.buffer, 0, u.length >> 1);
  const out = new Float32Array(h.length);
  for (let i = 0; i < h.length; i++) {
    const x = h[i], e = (x >> 10) & 31, f = x & 1023, sign = x & 0x8000 ? -1 : 1;
    const v = e === 0 ? f * Math.pow(2, -24) : e === 31 ? (f ? NaN : Infinity) :
      (1 + f / 1024) * Math.pow(2, e - 15);
    out[i] = sign * v * p.scale;
  }
  return out;
}
// a textured file's metadata_props come as they are (its bytes would repeat its textures)
const METADATA = DATA.models.map((m) => m.onnx ? decodeMetadata(readOnnxMetadata(b64ToBytes(m.onnx))) :
  m.metadata ? decodeMetadata(m.metadata) : null);
function metadataLine(name, meta, note) {
  if (!meta) return note || name + ": no ONNX metadata (an analytic target)";
  const t = meta.target;
  const target = t && typeof t === "object" ? (t.kind === "analytic" ?
    t.model + " " + JSON.stringify(t.params) : t.description || t.kind) : String(t || "?");
  const num = (k) => typeof meta[k] === "number" ? meta[k].toPrecision(4) : String(meta[k] ?? "?");
  const sl = meta.sampling_lobe;
  const lobe = sl && typeof sl === "object" ? `, sampling lobe ${sl.distribution || "ggx"} ` +
    `α ${Number(sl.alpha).toPrecision(3)}, share ${Number(sl.weight).toPrecision(3)}` : "";
  return `${name}: fitted to ${target}; encoding ${meta.encoding || "?"}, max albedo ` +
    `${num("max_albedo")}, reciprocity error ${num("reciprocity_error")}${lobe} ` +
    `(metadata version ${meta.metadata_version}, ${meta.producer || "?"})`;
}
$("nb-meta").textContent = DATA.models.map((m, k) => metadataLine(m.name, METADATA[k], m.note)).join("\n");

const canvas = $("nb-gl");
canvas.width = S * (NM > 1 ? 3 : 1);
canvas.height = S;
const gl = canvas.getContext("webgl2", {antialias: false, preserveDrawingBuffer: true});
if (!gl) throw new Error("this viewer needs WebGL2");
if (!gl.getExtension("EXT_color_buffer_float"))
  throw new Error("this viewer needs EXT_color_buffer_float (float render targets)");

const HEADER = "#version 300 es\nprecision highp float;\nprecision highp int;\n";
const VERT = "#version 300 es\nvoid main() {\n" +
  "  vec2 p = vec2(float((gl_VertexID & 1) << 2), float((gl_VertexID & 2) << 1)) - 1.0;\n" +
  "  gl_Position = vec4(p, 0.0, 1.0);\n}\n";
// Sphere: orthographic view along -z, unit sphere filling the square; at each pixel the
// local frame is z = n, x = t = normalize((n.z, 0, -n.x)) (tangent along the equator's
// direction), y = n x t.  Directional light of irradiance pi at normal incidence, so a
// white Lambertian surface facing the light has radiance 1.  neural_brdf/viewer/page.py
// (sphere_directions) repeats this geometry for the tests.
const SPHERE_FRAME = `
uniform vec3 uLight;
uniform float uSize;
out vec4 nb_out;
// the pixel's normal n and the light wi and view wo in its frame; false off the sphere
bool sphereFrame(out vec3 n, out vec3 wi, out vec3 wo) {
  vec2 p = gl_FragCoord.xy / uSize * 2.0 - 1.0;
  float r2 = dot(p, p);
  if (r2 >= 1.0) return false;
  n = vec3(p, sqrt(1.0 - r2));
  vec3 t = vec3(n.z, 0.0, -n.x);
  float tl = length(t);
  t = tl > 1e-6 ? t / tl : vec3(1.0, 0.0, 0.0);
  vec3 b = cross(n, t);
  wi = vec3(dot(uLight, t), dot(uLight, b), dot(uLight, n));
  wo = vec3(t.z, b.z, n.z);
  return true;
}`;
const SPHERE_MAIN = SPHERE_FRAME + `
void main() {
  vec3 n, wi, wo;
  if (!sphereFrame(n, wi, wo)) { nb_out = vec4(0.0); return; }
  nb_out = vec4(neural_brdf_eval(wi, wo) * max(wi.z, 0.0) * 3.14159265358979, 1.0);
}`;
const PAIRS_MAIN = `
uniform highp sampler2D uWi;
uniform highp sampler2D uWo;
out vec4 nb_out;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  nb_out = vec4(neural_brdf_eval(texelFetch(uWi, p, 0).xyz, texelFetch(uWo, p, 0).xyz), 1.0);
}`;
// The textured sphere: the same geometry, uv = uRepeat (phi / pi + 1/2, 1 - theta / pi)
// with phi = atan(n.x, n.z) and theta = acos(n.y), so the tangent t above is dp/du; a
// normal field m = neural_brdf_normal(uv) turns the frame as Mitsuba's normalmap does:
// s = normalize(x - m m.x), t' = m x s (docs/codegen.md, "The normal field").
// neural_brdf/viewer/page.py (sphere_frames, textured_radiance) repeats it for the tests.
const sphereTexturedMain = (normal) => SPHERE_FRAME + `
uniform float uRepeat;
void main() {
  vec3 n, wi, wo;
  if (!sphereFrame(n, wi, wo)) { nb_out = vec4(0.0); return; }
  if (wi.z <= 0.0) { nb_out = vec4(0.0, 0.0, 0.0, 1.0); return; }
  vec2 uv = uRepeat * vec2(atan(n.x, n.z) / 3.14159265358979 + 0.5,
                           1.0 - acos(clamp(n.y, -1.0, 1.0)) / 3.14159265358979);
${normal ? `  vec3 m = neural_brdf_normal(uv);
  vec3 s = normalize(vec3(1.0, 0.0, 0.0) - m * m.x);
  vec3 q = cross(m, s);
  wi = vec3(dot(wi, s), dot(wi, q), dot(wi, m));
  wo = vec3(dot(wo, s), dot(wo, q), dot(wo, m));
` : ""}  nb_out = vec4(neural_brdf_eval(wi, wo, uv) * max(wi.z, 0.0) * 3.14159265358979, 1.0);
}`;
const PAIRS_TEXTURED_MAIN = `
uniform highp sampler2D uWi;
uniform highp sampler2D uWo;
uniform vec2 uUv;
out vec4 nb_out;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  nb_out = vec4(neural_brdf_eval(texelFetch(uWi, p, 0).xyz, texelFetch(uWo, p, 0).xyz, uUv), 1.0);
}`;
// Display: radiance x 2^EV, clamped, sRGB-encoded; or the relative difference of two
// radiance images, max over RGB of |A - B| / max(A, B, floor), as a false colour on a
// log scale from 1e-3 (dark blue) to 1 (yellow).
const DISPLAY = HEADER + `
uniform highp sampler2D uA;
uniform highp sampler2D uB;
uniform int uMode;
uniform float uGain;
uniform float uFloor;
uniform vec2 uOrigin;
out vec4 nb_out;
vec3 srgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}
vec3 ramp(float x) {
  x = clamp(x, 0.0, 1.0);
  return vec3(smoothstep(0.3, 0.9, x), smoothstep(0.0, 0.6, x) * (1.0 - 0.2 * x),
              0.35 + 0.6 * sin(3.14159 * min(x * 1.2, 1.0)) * (1.0 - x));
}
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy - uOrigin);
  vec4 a = texelFetch(uA, p, 0);
  if (a.a == 0.0) { nb_out = vec4(0.13, 0.13, 0.15, 1.0); return; }
  if (uMode == 0) { nb_out = vec4(srgb(a.rgb * uGain), 1.0); return; }
  vec3 b = texelFetch(uB, p, 0).rgb;
  vec3 d = abs(a.rgb - b) / max(max(a.rgb, b), vec3(uFloor));
  float e = max(d.r, max(d.g, d.b));
  nb_out = vec4(ramp((log(max(e, 1e-3)) / log(10.0) + 3.0) / 3.0), 1.0);
}`;

function compile(type, src, what) {
  const s = gl.createShader(type);
  gl.shaderSource(s, src);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS))
    throw new Error(what + ": shader compile: " +
                    gl.getShaderInfoLog(s).trim().split("\n").slice(0, 3).join(" | "));
  return s;
}
function program(fsrc, what) {
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl.VERTEX_SHADER, VERT, what));
  gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fsrc, what));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS))
    throw new Error(what + ": link: " + gl.getProgramInfoLog(p));
  return p;
}
function floatTarget(w, h) {
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, w, h);
  for (const k of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER])
    gl.texParameteri(gl.TEXTURE_2D, k, gl.NEAREST);
  const fb = gl.createFramebuffer();
  gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
  gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
  if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE)
    throw new Error("RGBA32F framebuffer incomplete");
  return {tex, fb, w, h};
}
function floatInput(data, w, h) {          // data: Float32Array w*h*4
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  for (const k of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER])
    gl.texParameteri(gl.TEXTURE_2D, k, gl.NEAREST);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, w, h, 0, gl.RGBA, gl.FLOAT, data);
  return tex;
}

// a textured model's bound textures: texture j of model k on unit 4 + 2 k + j, an R32F
// texture TEX_WIDTH texels wide holding the floats in order (docs/codegen.md)
function boundTexture(t, unit) {
  const n = t.rows * t.channels, h = Math.max(1, Math.ceil(n / TEX_WIDTH));
  if (h > gl.getParameter(gl.MAX_TEXTURE_SIZE))
    throw new Error(`a bound texture of ${t.rows} x ${t.channels} floats needs ${h} rows of ` +
                    `${TEX_WIDTH}: more than this WebGL2's MAX_TEXTURE_SIZE`);
  const data = new Float32Array(TEX_WIDTH * h);
  data.set(b64ToF32(t.data).subarray(0, n));
  gl.activeTexture(gl.TEXTURE0 + unit);
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  for (const k of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER])
    gl.texParameteri(gl.TEXTURE_2D, k, gl.NEAREST);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, TEX_WIDTH, h, 0, gl.RED, gl.FLOAT, data);
  gl.activeTexture(gl.TEXTURE0);
  return tex;
}
const models = DATA.models.map((m, k) => {
  const base = {name: m.name, albedo: m.albedo, textured: m.textured, target: floatTarget(S, S)};
  if (m.tabulated) {                       // a teacher: images and slices, no shader
    const cache = {};
    return Object.assign(base, {tabulated: m.tabulated, cache,
      image: (i) => cache[i] || (cache[i] = teacherPixels(unpackHalf(m.tabulated.images[i]))),
      slice: (p) => cache["s" + p] || (cache["s" + p] = unpackHalf(m.tabulated.slices[p]))});
  }
  const defines = m.textured ? `#define NEURAL_BRDF_TEXTURE_WIDTH ${TEX_WIDTH}\n` : "";
  const body = defines + m.glsl.replace(/^\s*#version[^\n]*\n/, "");
  const what = `model ${k} (${m.name})`;
  const out = Object.assign(base, {
    sphere: program(HEADER + body + (m.textured ? sphereTexturedMain(m.normal) : SPHERE_MAIN), what),
    pairs: program(HEADER + body + (m.textured ? PAIRS_TEXTURED_MAIN : PAIRS_MAIN), what)});
  m.textures.forEach((t, j) => {
    const unit = 4 + 2 * k + j;
    boundTexture(t, unit);
    for (const p of [out.sphere, out.pairs]) {
      gl.useProgram(p);
      gl.uniform1i(gl.getUniformLocation(p, "neural_brdf_texture" + j), unit);
    }
  });
  return out;
});
const display = program(DISPLAY, "display");

// ---------------------------------------------------------------- evaluation
// the index of the teacher's light nearest to a direction
function nearestLight(light) {
  let best = 0, bestDot = -2;
  LIGHTS.forEach(([t, p], i) => {
    const d = lightOf(t, p), c = d[0] * light[0] + d[1] * light[1] + d[2] * light[2];
    if (c > bestDot) { bestDot = c; best = i; }
  });
  return best;
}
function lightOf(thetaDeg, phiDeg) {
  const t = thetaDeg * PI / 180, p = phiDeg * PI / 180;
  return [Math.sin(t) * Math.cos(p), Math.sin(t) * Math.sin(p), Math.cos(t)];
}
// a teacher's image as RGBA pixels from its values inside the sphere in row order
// (bottom-up), as page.py stored them
function teacherPixels(vals) {
  const px = new Float32Array(S * S * 4);
  let q = 0;
  for (let j = 0; j < S; j++) {
    const y = (j + 0.5) / S * 2 - 1;
    for (let i = 0; i < S; i++) {
      const x = (i + 0.5) / S * 2 - 1;
      if (x * x + y * y >= 1) continue;
      px.set([vals[3 * q], vals[3 * q + 1], vals[3 * q + 2], 1], 4 * (j * S + i));
      q++;
    }
  }
  return px;
}
// the teacher's image at its light nearest to ``light``
function uploadTeacher(m, light) {
  gl.bindTexture(gl.TEXTURE_2D, m.target.tex);
  gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, S, S, gl.RGBA, gl.FLOAT,
                   m.image(nearestLight(light)));
}
function renderSphere(k, light) {
  const m = models[k];
  if (m.tabulated) { uploadTeacher(m, light); return; }
  gl.bindFramebuffer(gl.FRAMEBUFFER, m.target.fb);
  gl.viewport(0, 0, S, S);
  gl.useProgram(m.sphere);
  gl.uniform3fv(gl.getUniformLocation(m.sphere, "uLight"), light);
  gl.uniform1f(gl.getUniformLocation(m.sphere, "uSize"), S);
  if (m.textured) gl.uniform1f(gl.getUniformLocation(m.sphere, "uRepeat"), DATA.repeat);
  gl.drawArrays(gl.TRIANGLES, 0, 3);
}
function readTarget(t) {
  gl.bindFramebuffer(gl.FRAMEBUFFER, t.fb);
  const px = new Float32Array(t.w * t.h * 4);
  gl.readPixels(0, 0, t.w, t.h, gl.RGBA, gl.FLOAT, px);
  return px;
}
const PAIR_WIDTH = 1024;
function evalPairs(k, wi, wo, n, uv) {      // Float32Array n*3 each -> Float32Array n*3
  const w = Math.min(n, PAIR_WIDTH), h = Math.ceil(n / PAIR_WIDTH);
  const pad = (a) => {
    const out = new Float32Array(w * h * 4);
    for (let i = 0; i < n; i++) out.set(a.subarray(3 * i, 3 * i + 3), 4 * i);
    return out;
  };
  const m = models[k];
  if (m.tabulated) throw new Error(`model ${k} (${m.name}) is tabulated: it has no shader`);
  const t = floatTarget(w, h);
  gl.useProgram(m.pairs);
  if (m.textured) gl.uniform2fv(gl.getUniformLocation(m.pairs, "uUv"), uv || PROBES[state.probe]);
  const inputs = [floatInput(pad(wi), w, h), floatInput(pad(wo), w, h)];
  inputs.forEach((tex, unit) => {
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, tex);
  });
  gl.uniform1i(gl.getUniformLocation(m.pairs, "uWi"), 0);
  gl.uniform1i(gl.getUniformLocation(m.pairs, "uWo"), 1);
  gl.bindFramebuffer(gl.FRAMEBUFFER, t.fb);
  gl.viewport(0, 0, w, h);
  gl.drawArrays(gl.TRIANGLES, 0, 3);
  const px = readTarget(t);
  inputs.forEach((tex) => gl.deleteTexture(tex));
  gl.deleteTexture(t.tex);
  gl.deleteFramebuffer(t.fb);
  gl.activeTexture(gl.TEXTURE0);
  const out = new Float32Array(n * 3);
  for (let i = 0; i < n; i++) out.set(px.subarray(4 * i, 4 * i + 3), 3 * i);
  return out;
}

// ---------------------------------------------------------------- state and drawing
const state = {thetaL: 35, phiL: 30, ev: 0, thetaI: 45, log: false, probe: 0};
function lightDir() {
  return lightOf(state.thetaL, state.phiL);
}
// with a teacher the light is one of its lights: the nearest to the one asked for
function snapLight() {
  if (!LIGHTS) return;
  [state.thetaL, state.phiL] = LIGHTS[nearestLight(lightDir())];
}
function drawSpheres() {
  const L = lightDir();
  for (let k = 0; k < NM; k++) renderSphere(k, L);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.useProgram(display);
  const loc = (n) => gl.getUniformLocation(display, n);
  gl.uniform1i(loc("uA"), 0);
  gl.uniform1i(loc("uB"), 1);
  gl.uniform1f(loc("uGain"), Math.pow(2, state.ev));
  gl.uniform1f(loc("uFloor"), 1e-3 * Math.pow(2, -state.ev));
  const panels = NM > 1 ? [[0, 0, 0], [1, 1, 0], [2, 0, 1]] : [[0, 0, 0]];
  for (const [slot, a, mode] of panels) {
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, models[a].target.tex);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, models[NM > 1 ? 1 : 0].target.tex);
    gl.uniform1i(loc("uMode"), mode);
    gl.uniform2f(loc("uOrigin"), slot * S, 0);
    gl.viewport(slot * S, 0, S, S);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }
  gl.activeTexture(gl.TEXTURE0);
  if (NM > 1) {
    const a = readTarget(models[0].target), b = readTarget(models[1].target);
    let num = 0, den = 0, worst = 0;
    for (let i = 0; i < a.length; i += 4) {
      if (a[i + 3] === 0) continue;
      for (let c = 0; c < 3; c++) {
        const d = Math.abs(a[i + c] - b[i + c]);
        num += d * d; den += b[i + c] * b[i + c]; worst = Math.max(worst, d);
      }
    }
    let peak = 0;
    for (let i = 0; i < b.length; i += 4) peak = Math.max(peak, b[i], b[i + 1], b[i + 2]);
    $("nb-diff").textContent = `sphere: relative RMS difference ${(Math.sqrt(num / Math.max(den, 1e-30)) * 100).toFixed(2)} %, ` +
      `max |A − B| ${(100 * worst / Math.max(peak, 1e-30)).toFixed(2)} % of the peak radiance`;
  }
}

function slices() {                        // [model] -> {theta: deg[], fc: [n][3]}
  const ti = state.thetaI * PI / 180;
  const wi = new Float32Array(SLICE_N * 3), wo = new Float32Array(SLICE_N * 3), th = [];
  for (let j = 0; j < SLICE_N; j++) {
    const to = (-90 + 180 * j / (SLICE_N - 1)) * PI / 180;
    th.push(to * 180 / PI);
    wi.set([-Math.sin(ti), 0, Math.cos(ti)], 3 * j);
    wo.set([Math.sin(to), 0, Math.cos(to)], 3 * j);
  }
  return models.map((m, k) => {
    const f = m.tabulated ? m.slice(m.textured ? state.probe : 0).subarray(
      state.thetaI * SLICE_N * 3, (state.thetaI + 1) * SLICE_N * 3) : evalPairs(k, wi, wo, SLICE_N);
    const fc = [];
    for (let j = 0; j < SLICE_N; j++) {
      const c = Math.max(wo[3 * j + 2], 0);
      fc.push([f[3 * j] * c, f[3 * j + 1] * c, f[3 * j + 2] * c]);
    }
    return {theta: th, fc};
  });
}

// ---------------------------------------------------------------- ticks
// Pure functions (no DOM): tests/viewer/test_viewer.py runs this block in Node.
// A "nice" tick step: 1, 2 or 5 x 10^k, about (hi - lo) / n.
function niceStep(lo, hi, n) {
  const raw = (hi - lo) / Math.max(n, 1);
  if (!(raw > 0) || !isFinite(raw)) return 1;
  const p = Math.pow(10, Math.floor(Math.log10(raw)));
  const m = raw / p;
  return (m < 1.5 ? 1 : m < 3.5 ? 2 : m < 7.5 ? 5 : 10) * p;
}
// the multiples of niceStep(lo, hi, n) within [lo, hi] (about n + 1 of them)
function niceTicks(lo, hi, n) {
  const step = niceStep(lo, hi, n), out = [];
  const digits = Math.max(0, -Math.floor(Math.log10(step)) + 1);
  for (let i = Math.ceil(lo / step - 1e-9); i * step <= hi + 1e-9 * step; i++)
    out.push(Number((i * step).toFixed(digits)));
  return out;
}
// a tick's text: as many decimals as its step needs
function tickText(y, step) {
  return y.toFixed(Math.max(0, -Math.floor(Math.log10(step) + 1e-9)));
}
// the integer exponents within [lo, hi] (log10 units), every one or every few
function logTicks(lo, hi) {
  const every = Math.max(1, Math.ceil((hi - lo) / 6)), out = [];
  for (let e = Math.ceil(lo - 1e-9); e <= hi + 1e-9; e++) if (e % every === 0) out.push(e);
  return out;
}
// 10 to the integer power e, as text: "10⁻³", "1" for 10⁰
const SUPERSCRIPT = {"-": "⁻", 0: "⁰", 1: "¹", 2: "²", 3: "³", 4: "⁴", 5: "⁵", 6: "⁶", 7: "⁷", 8: "⁸", 9: "⁹"};
function pow10Text(e) {
  return e === 0 ? "1" : e === 1 ? "10" : "10" + [...String(e)].map((c) => SUPERSCRIPT[c]).join("");
}
// ---------------------------------------------------------------- end of ticks

const CH = ["#d62728", "#2ca02c", "#1f77b4"];
const DASH = [[], [6, 4]];
function axes(ctx, W, H, box, xr, yr, opts) {
  ctx.clearRect(0, 0, W, H);
  ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, W, H);
  ctx.strokeStyle = "#999"; ctx.lineWidth = 1; ctx.setLineDash([]);
  ctx.strokeRect(box.x, box.y, box.w, box.h);
  ctx.fillStyle = "#333"; ctx.font = "11px sans-serif"; ctx.textAlign = "center";
  for (const x of opts.xticks) {
    const px = box.x + (x - xr[0]) / (xr[1] - xr[0]) * box.w;
    ctx.fillText(String(x), px, box.y + box.h + 13);
    ctx.strokeStyle = "#eee"; ctx.beginPath(); ctx.moveTo(px, box.y); ctx.lineTo(px, box.y + box.h); ctx.stroke();
  }
  ctx.textAlign = "right";
  for (const y of opts.yticks) {
    const py = box.y + box.h - (y - yr[0]) / (yr[1] - yr[0]) * box.h;
    ctx.fillText(opts.ylabelOf(y), box.x - 4, py + 4);
    ctx.strokeStyle = "#eee"; ctx.beginPath(); ctx.moveTo(box.x, py); ctx.lineTo(box.x + box.w, py); ctx.stroke();
  }
  ctx.textAlign = "center"; ctx.font = "12px sans-serif";
  ctx.fillText(opts.title, box.x + box.w / 2, 14);
  ctx.fillText(opts.xlabel, box.x + box.w / 2, H - 4);
  ctx.save(); ctx.translate(11, box.y + box.h / 2); ctx.rotate(-PI / 2);
  ctx.fillText(opts.ylabel, 0, 0); ctx.restore();
}
function line(ctx, box, xr, yr, xs, ys, colour, dash) {
  ctx.strokeStyle = colour; ctx.setLineDash(dash); ctx.lineWidth = dash.length ? 1.2 : 2;
  ctx.beginPath();
  let pen = false;
  xs.forEach((x, i) => {
    const y = ys[i];
    if (!isFinite(y)) { pen = false; return; }
    const px = box.x + (x - xr[0]) / (xr[1] - xr[0]) * box.w;
    const py = box.y + box.h - (Math.min(Math.max(y, yr[0]), yr[1]) - yr[0]) / (yr[1] - yr[0]) * box.h;
    if (pen) ctx.lineTo(px, py); else ctx.moveTo(px, py);
    pen = true;
  });
  ctx.stroke();
  ctx.setLineDash([]);
}
function drawSlices(sl) {
  const cv = $("nb-slice"), ctx = cv.getContext("2d"), W = cv.width, H = cv.height;
  const box = {x: 58, y: 22, w: W - 70, h: H - 58};
  let hi = 0;
  for (const s of sl) for (const v of s.fc) hi = Math.max(hi, v[0], v[1], v[2]);
  hi = hi > 0 ? hi : 1;
  // log: the axis in log10 units, ticked at integer exponents (10⁻³, 10⁻², ...)
  const tr = state.log ? (v) => Math.log10(Math.max(v, 1e-30)) : (v) => v;
  const yr = state.log ? [Math.log10(hi) - 4, Math.log10(hi) + 0.2] : [0, hi * 1.05];
  const step = niceStep(yr[0], yr[1], 4);
  axes(ctx, W, H, box, [-90, 90], yr, {
    xticks: [-90, -60, -30, 0, 30, 60, 90],
    yticks: state.log ? logTicks(yr[0], yr[1]) : niceTicks(yr[0], yr[1], 4),
    xlabel: "θo [deg] (mirror at +θi)", ylabel: "f cos θo [1/sr]" + (state.log ? ", log scale" : ""),
    title: `f cos θo in the incidence plane, θi = ${state.thetaI}°` + probeText(),
    ylabelOf: (y) => state.log ? pow10Text(y) : tickText(y, step)});
  sl.forEach((s, k) => {
    for (let c = 0; c < 3; c++)
      line(ctx, box, [-90, 90], yr, s.theta, s.fc.map((v) => tr(v[c])), CH[c], DASH[k]);
  });
}
function drawPolar(sl) {
  const cv = $("nb-polar"), ctx = cv.getContext("2d"), W = cv.width, H = cv.height;
  ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, W, H);
  const cx = W / 2, cy = H - 24, R = Math.min(W / 2 - 16, H - 48);
  const lum = sl.map((s) => s.fc.map((v) => LUMA[0] * v[0] + LUMA[1] * v[1] + LUMA[2] * v[2]));
  let hi = 0;
  for (const l of lum) for (const v of l) hi = Math.max(hi, v);
  hi = hi > 0 ? hi : 1;
  // rings at nice values of f cos θo (luminance, 1/sr), labelled on the horizon
  ctx.strokeStyle = "#ddd"; ctx.lineWidth = 1;
  const rings = niceTicks(0, hi, 3).filter((v) => v > 0), ringStep = niceStep(0, hi, 3);
  ctx.fillStyle = "#666"; ctx.font = "10px sans-serif"; ctx.textAlign = "center";
  rings.forEach((v, i) => {
    ctx.beginPath(); ctx.arc(cx, cy, R * v / hi, PI, 2 * PI); ctx.stroke();
    const last = i === rings.length - 1, x = cx + R * v / hi;  // the last one with the unit
    ctx.textAlign = last ? "left" : "center";
    ctx.fillText(tickText(v, ringStep) + (last ? " 1/sr" : ""), last ? Math.min(x - 6, W - 44) : x, cy + 12);
  });
  for (const a of [-60, -30, 0, 30, 60]) {
    const t = a * PI / 180;
    ctx.beginPath(); ctx.moveTo(cx, cy); ctx.lineTo(cx + R * Math.sin(t), cy - R * Math.cos(t)); ctx.stroke();
  }
  ctx.strokeStyle = "#888"; ctx.beginPath(); ctx.moveTo(cx - R - 8, cy); ctx.lineTo(cx + R + 8, cy); ctx.stroke();
  const ti = state.thetaI * PI / 180;                // the incident direction, at -theta_i
  ctx.strokeStyle = "#e08000"; ctx.lineWidth = 2; ctx.beginPath(); ctx.moveTo(cx, cy);
  ctx.lineTo(cx - R * Math.sin(ti), cy - R * Math.cos(ti)); ctx.stroke();
  const colours = ["#222", "#c2185b"];
  lum.forEach((l, k) => {
    ctx.strokeStyle = colours[k]; ctx.setLineDash(DASH[k]); ctx.lineWidth = 2;
    ctx.beginPath();
    sl[k].theta.forEach((deg, j) => {
      const t = deg * PI / 180, r = R * l[j] / hi;
      const x = cx + r * Math.sin(t), y = cy - r * Math.cos(t);
      if (j) ctx.lineTo(x, y); else ctx.moveTo(x, y);
    });
    ctx.stroke(); ctx.setLineDash([]);
  });
  ctx.fillStyle = "#333"; ctx.font = "12px sans-serif"; ctx.textAlign = "center";
  ctx.fillText(`lobe: luminance of f cos θo, θi = ${state.thetaI}° (orange: light)`, W / 2, 14);
}
// a textured model's albedo curve is at the plots' point uv
const curveOf = (m) => Array.isArray(m.albedo) ? m.albedo[state.probe] : m.albedo;
function drawAlbedo() {
  const cv = $("nb-albedo"), ctx = cv.getContext("2d"), W = cv.width, H = cv.height;
  const box = {x: 50, y: 22, w: W - 62, h: H - 58};
  let hi = 1.05;
  for (const m of models) for (const v of curveOf(m).rho) hi = Math.max(hi, v[0] * 1.05, v[1] * 1.05, v[2] * 1.05);
  const yr = [0, hi], step = niceStep(0, hi, 4);
  axes(ctx, W, H, box, [0, 90], yr, {
    xticks: [0, 15, 30, 45, 60, 75, 90], yticks: niceTicks(0, hi, 4),
    xlabel: "θi [deg]", ylabel: "ρ(θi) = ∫ f cos θo dωo", title: (DATA.textured ? "albedo ρ(θi) (precomputed)" :
      "directional albedo ρ(θi) (precomputed)") + probeText(),
    ylabelOf: (y) => tickText(y, step)});
  models.forEach((m, k) => {
    const a = curveOf(m);
    for (let c = 0; c < 3; c++)
      line(ctx, box, [0, 90], yr, a.theta, a.rho.map((v) => v[c]), CH[c], DASH[k]);
  });
  const px = box.x + state.thetaI / 90 * box.w;
  ctx.strokeStyle = "#e08000"; ctx.beginPath(); ctx.moveTo(px, box.y); ctx.lineTo(px, box.y + box.h); ctx.stroke();
  const py = box.y + box.h - 1 / hi * box.h;
  ctx.strokeStyle = "#000"; ctx.setLineDash([2, 3]); ctx.beginPath(); ctx.moveTo(box.x, py);
  ctx.lineTo(box.x + box.w, py); ctx.stroke(); ctx.setLineDash([]);
}

function probeText() {
  if (!DATA.textured) return "";
  const [u, v] = PROBES[state.probe];
  return `, uv (${u.toPrecision(3)}, ${v.toPrecision(3)})`;
}
function redraw(what) {
  try {
    snapLight();
    if (what !== "plots") drawSpheres();
    if (what !== "spheres") { const sl = slices(); drawSlices(sl); drawPolar(sl); drawAlbedo(); }
    for (const [id, v] of [["nb-thetaL", state.thetaL], ["nb-phiL", state.phiL], ["nb-ev", state.ev],
                           ["nb-thetaI", state.thetaI]]) {
      $(id).value = v;
      $(id + "-v").textContent = String(v);
    }
    $("nb-log").checked = state.log;
    if (DATA.textured) $("nb-probe").value = String(state.probe);
  } catch (e) {
    status.textContent = String(e);
    throw e;
  }
}
let pending = null;
function schedule(what) {
  const w = pending && pending !== what ? "all" : what;
  if (pending === null) requestAnimationFrame(() => { const x = pending; pending = null; redraw(x); });
  pending = w;
}
for (const [id, key, what] of [["nb-thetaL", "thetaL", "spheres"], ["nb-phiL", "phiL", "spheres"],
                               ["nb-ev", "ev", "spheres"], ["nb-thetaI", "thetaI", "plots"]]) {
  const el = $(id);
  el.value = state[key];
  el.addEventListener("input", () => { state[key] = Number(el.value); schedule(what); });
}
$("nb-log").addEventListener("change", (e) => { state.log = e.target.checked; schedule("plots"); });
if (DATA.textured)
  $("nb-probe").addEventListener("change", (e) => { state.probe = Number(e.target.value); schedule("plots"); });
// drag on a sphere: the light comes from the direction of the point under the pointer
function dragLight(ev) {
  if (!(ev.buttons & 1)) return;
  const r = canvas.getBoundingClientRect();
  const scale = canvas.width / r.width;
  const px = ((ev.clientX - r.left) * scale) % S, py = (ev.clientY - r.top) * scale;
  let x = px / S * 2 - 1, y = 1 - py / S * 2;
  const r2 = x * x + y * y;
  if (r2 > 1) { x /= Math.sqrt(r2); y /= Math.sqrt(r2); }
  const z = Math.sqrt(Math.max(0, 1 - x * x - y * y));
  state.thetaL = Math.round(Math.acos(z) * 180 / PI);
  state.phiL = Math.round((Math.atan2(y, x) * 180 / PI + 360) % 360);
  $("nb-thetaL").value = state.thetaL; $("nb-phiL").value = state.phiL;
  schedule("spheres");
}
canvas.addEventListener("pointerdown", dragLight);
canvas.addEventListener("pointermove", dragLight);

// ---------------------------------------------------------------- test mode
function f32ToB64(f) {
  const u = new Uint8Array(f.buffer, f.byteOffset, f.byteLength);
  let s = "";
  for (let i = 0; i < u.length; i += 0x8000) s += String.fromCharCode.apply(null, u.subarray(i, i + 0x8000));
  return btoa(s);
}
window.nbViewer = {
  size: S, models: models.map((m) => m.name),
  probes: PROBES, lights: LIGHTS,
  // f of model k at n (wi, wo) pairs (base64 float32 (n, 3) each) -> base64 float32 (n, 3);
  // a textured model at uv [u, v] (default: the plots' point)
  evalPairs: (k, wi, wo, n, uv) => f32ToB64(evalPairs(k, b64ToF32(wi), b64ToF32(wo), n, uv)),
  // f cos(theta_o) of every model along the current slice (SLICE_N x 3 each, base64)
  sliceValues: () => slices().map((s) => f32ToB64(new Float32Array(s.fc.flat()))),
  // the float radiance image (S, S, 4), rows bottom-up, of model k lit from light (vec3)
  sphereRadiance: (k, light) => { renderSphere(k, light); return f32ToB64(readTarget(models[k].target)); },
  // the radiance image model k shows now (as last drawn), rows bottom-up
  shownRadiance: (k) => f32ToB64(readTarget(models[k].target)),
  setState: (s) => { Object.assign(state, s); redraw("all"); return state; },
  // model k's metadata, read from its ONNX bytes (null for an analytic target)
  metadata: (k) => METADATA[k],
};
redraw("all");
status.textContent = "ready";
