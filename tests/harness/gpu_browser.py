"""Run generated shaders on the GPU of headless Chromium: GLSL in WebGL2, WGSL in WebGPU.

    from harness import gpu_browser
    f = gpu_browser.eval_glsl(glsl_source, wi, wo)     # (N, 3) float32, like runtime.eval
    f = gpu_browser.eval_wgsl(wgsl_source, wi, wo)
    with gpu_browser.Session() as s:                   # one browser for several calls
        s.open("viewer.html"); s.evaluate("1 + 1"); s.errors; s.screenshot("out.png")

``glsl_source`` is GLSL ES 3.00 defining ``vec3 neural_brdf_eval(vec3 wi, vec3 wo)``
(a ``#version`` line, if any, is dropped: the harness writes its own); ``wgsl_source``
is WGSL defining ``fn neural_brdf_eval(wi: vec3<f32>, wo: vec3<f32>) -> vec3<f32>``.
A textured GLSL file: ``eval_glsl(source, wi, wo, uv=uv, textures={name: (data,
width)})`` calls ``neural_brdf_eval(wi, wo, uv)`` and binds each float array ``data`` as
the R32F ``uniform sampler2D name``, ``width`` floats to a texel row (docs/codegen.md).

WebGL2: the directions go into two RGBA32F textures, one fragment per pair renders
``neural_brdf_eval`` into an RGBA32F framebuffer (EXT_color_buffer_float) and
``readPixels`` reads it back.  WebGPU: a compute shader reads storage buffers and writes
one.  Both run on SwiftShader (Chromium's CPU implementation of Vulkan, under ANGLE for
WebGL), so no GPU is needed; on a machine with one, the same code runs there.

Chromium is driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``:
NUL-terminated JSON on file descriptors 3 and 4), which lets Python await the page's
promises (WebGPU is asynchronous), collect console errors and uncaught exceptions, and
move float arrays both ways bit-exactly as base64.  The page is a self-contained HTML
file in a temporary folder; nothing touches the network.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from harness.browser import CHROMIUM, BrowserError
from neural_brdf.fileio import atomic_write

# Measured on Chromium 156 (Debian 12): WebGL2 runs on ANGLE's SwiftShader Vulkan
# backend with or without --disable-gpu (which only warns that the automatic software
# fallback is deprecated); WebGPU finds the SwiftShader adapter with
# --enable-unsafe-webgpu alone.  These flags ask for both explicitly.
GPU_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--enable-unsafe-webgpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--force-device-scale-factor=1",
    "--remote-debugging-pipe",
)
TIMEOUT = 120  # seconds for one protocol call (a page load, an evaluation)
TEXTURE_WIDTH = 1024  # pairs per texture row in the WebGL harness
WORKGROUP = 64  # invocations per WebGPU workgroup

RUNNER_JS = r"""
"use strict";
function nbDecode(b64) {
  const s = atob(b64), u = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
  return new Float32Array(u.buffer);
}
function nbEncode(f32) {
  const u = new Uint8Array(f32.buffer, f32.byteOffset, f32.byteLength);
  let s = "";
  for (let i = 0; i < u.length; i += 0x8000)
    s += String.fromCharCode.apply(null, u.subarray(i, i + 0x8000));
  return btoa(s);
}
function nbPad4(xyz, n, count, k = 3) {  // (n, k) -> (count, 4): vec4 rows, zero padding
  const out = new Float32Array(count * 4);
  for (let i = 0; i < n; i++) { out.set(xyz.subarray(k * i, k * i + k), 4 * i); }
  return out;
}
function nbEvalGLSL(source, wiB64, woB64, n, width, uvB64 = null, textures = []) {
  const h = Math.ceil(n / width), w = Math.min(n, width);
  const canvas = document.createElement("canvas");
  canvas.width = w; canvas.height = h;
  const gl = canvas.getContext("webgl2", {antialias: false});
  if (!gl) throw new Error("WebGL2 is not available");
  if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("no EXT_color_buffer_float");
  const body = source.replace(/^\s*#version[^\n]*\n/, "");
  const uv = uvB64 !== null;
  const fsrc = "#version 300 es\nprecision highp float;\nprecision highp int;\n" + body +
    "\nuniform highp sampler2D nb_wi;\nuniform highp sampler2D nb_wo;\n" +
    "uniform highp sampler2D nb_uv;\nout vec4 nb_out;\n" +
    "void main() {\n  ivec2 p = ivec2(gl_FragCoord.xy);\n" +
    "  vec3 wi = texelFetch(nb_wi, p, 0).xyz, wo = texelFetch(nb_wo, p, 0).xyz;\n" +
    (uv ? "  nb_out = vec4(neural_brdf_eval(wi, wo, texelFetch(nb_uv, p, 0).xy), 1.0);\n}\n"
        : "  nb_out = vec4(neural_brdf_eval(wi, wo), 1.0);\n}\n");
  const vsrc = "#version 300 es\nvoid main() {\n" +
    "  vec2 p = vec2(float((gl_VertexID & 1) << 2), float((gl_VertexID & 2) << 1)) - 1.0;\n" +
    "  gl_Position = vec4(p, 0.0, 1.0);\n}\n";
  const prog = nbProgram(gl, vsrc, fsrc);
  const tex = (b64, unit, k = 3) => {
    const t = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit); gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, w, h, 0, gl.RGBA, gl.FLOAT,
                  nbPad4(nbDecode(b64), n, w * h, k));
    return t;
  };
  tex(wiB64, 0); tex(woB64, 1);
  if (uv) tex(uvB64, 3, 2);
  textures.forEach((t, k) => {          // the bound data: R32F, t.width floats a row
    const data = nbDecode(t.data), th = Math.ceil(data.length / t.width);
    const padded = new Float32Array(t.width * th);
    padded.set(data);
    const tx = gl.createTexture();
    gl.activeTexture(gl.TEXTURE4 + k); gl.bindTexture(gl.TEXTURE_2D, tx);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, t.width, th, 0, gl.RED, gl.FLOAT, padded);
  });
  const target = gl.createTexture();
  gl.activeTexture(gl.TEXTURE2); gl.bindTexture(gl.TEXTURE_2D, target);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, w, h);
  const fb = gl.createFramebuffer();
  gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
  gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, target, 0);
  if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE)
    throw new Error("RGBA32F framebuffer incomplete");
  gl.useProgram(prog);
  gl.uniform1i(gl.getUniformLocation(prog, "nb_wi"), 0);
  gl.uniform1i(gl.getUniformLocation(prog, "nb_wo"), 1);
  if (uv) gl.uniform1i(gl.getUniformLocation(prog, "nb_uv"), 3);
  textures.forEach((t, k) => {
    const loc = gl.getUniformLocation(prog, t.name);
    if (loc === null) throw new Error("no uniform " + t.name + " in the shader");
    gl.uniform1i(loc, 4 + k);
  });
  gl.viewport(0, 0, w, h);
  gl.drawArrays(gl.TRIANGLES, 0, 3);
  const px = new Float32Array(w * h * 4);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.FLOAT, px);
  const err = gl.getError();
  if (err !== gl.NO_ERROR) throw new Error("WebGL error 0x" + err.toString(16));
  const out = new Float32Array(n * 3);
  for (let i = 0; i < n; i++) out.set(px.subarray(4 * i, 4 * i + 3), 3 * i);
  return {f: nbEncode(out), renderer: nbRenderer(gl)};
}
function nbRenderer(gl) {
  const d = gl.getExtension("WEBGL_debug_renderer_info");
  return d ? gl.getParameter(d.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
}
function nbProgram(gl, vsrc, fsrc) {
  const compile = (type, src) => {
    const s = gl.createShader(type);
    gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS))
      throw new Error("shader compile: " +
                      gl.getShaderInfoLog(s).trim().split("\n").slice(0, 3).join(" | "));
    return s;
  };
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl.VERTEX_SHADER, vsrc));
  gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fsrc));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS))
    throw new Error("link: " + gl.getProgramInfoLog(p));
  return p;
}
async function nbEvalWGSL(source, wiB64, woB64, n, workgroup) {
  if (!navigator.gpu) throw new Error("WebGPU is not available (navigator.gpu undefined)");
  const adapter = await navigator.gpu.requestAdapter();
  if (!adapter) throw new Error("WebGPU: no adapter");
  const dev = await adapter.requestDevice();
  const code = source + `
@group(0) @binding(0) var<storage, read> nb_wi: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> nb_wo: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> nb_f: array<vec4<f32>>;
@compute @workgroup_size(${workgroup})
fn nb_main(@builtin(global_invocation_id) id: vec3<u32>) {
  let i = id.x;
  if (i >= arrayLength(&nb_f)) { return; }
  nb_f[i] = vec4<f32>(neural_brdf_eval(nb_wi[i].xyz, nb_wo[i].xyz), 1.0);
}`;
  dev.pushErrorScope("validation");
  const module = dev.createShaderModule({code});
  const info = await module.getCompilationInfo();
  const errs = info.messages.filter(m => m.type === "error");
  if (errs.length)
    throw new Error("WGSL compile: " +
                    errs.slice(0, 3).map(m => `line ${m.lineNum}: ${m.message}`).join(" | "));
  const pipe = dev.createComputePipeline({layout: "auto",
                                          compute: {module, entryPoint: "nb_main"}});
  const S = GPUBufferUsage;
  const upload = (b64) => {
    const data = nbPad4(nbDecode(b64), n, n);
    const b = dev.createBuffer({size: data.byteLength, usage: S.STORAGE | S.COPY_DST});
    dev.queue.writeBuffer(b, 0, data); return b;
  };
  const bi = upload(wiB64), bo = upload(woB64);
  const bf = dev.createBuffer({size: n * 16, usage: S.STORAGE | S.COPY_SRC});
  const rb = dev.createBuffer({size: n * 16, usage: S.MAP_READ | S.COPY_DST});
  const bg = dev.createBindGroup({layout: pipe.getBindGroupLayout(0), entries: [
    {binding: 0, resource: {buffer: bi}}, {binding: 1, resource: {buffer: bo}},
    {binding: 2, resource: {buffer: bf}}]});
  const enc = dev.createCommandEncoder();
  const pass = enc.beginComputePass();
  pass.setPipeline(pipe); pass.setBindGroup(0, bg);
  pass.dispatchWorkgroups(Math.ceil(n / workgroup)); pass.end();
  enc.copyBufferToBuffer(bf, 0, rb, 0, n * 16);
  dev.queue.submit([enc.finish()]);
  const verr = await dev.popErrorScope();
  if (verr) throw new Error("WebGPU validation: " + verr.message.split("\n")[0]);
  await rb.mapAsync(GPUMapMode.READ);
  const px = new Float32Array(rb.getMappedRange().slice(0));
  const out = new Float32Array(n * 3);
  for (let i = 0; i < n; i++) out.set(px.subarray(4 * i, 4 * i + 3), 3 * i);
  const ai = adapter.info || {};
  return {f: nbEncode(out), renderer: `${ai.vendor || "?"} ${ai.architecture || "?"}`};
}
"""
RUNNER_PAGE = (
    "<!DOCTYPE html><html><head><meta charset='utf-8'><title>neural-brdf shader "
    f"harness</title></head><body><script>{RUNNER_JS}</script></body></html>"
)


class ShaderError(BrowserError):
    """The browser refused the shader or the evaluation failed (message from the page)."""


class Session:
    """One headless Chromium, driven over the DevTools protocol; use as a context manager.

    ``errors`` collects console errors and uncaught exceptions of the open page."""

    def __init__(self, *, width: int = 1200, height: int = 900):
        if not Path(CHROMIUM).is_file():
            raise BrowserError(
                f"{CHROMIUM}: not found; apt-get install chromium (or set $CHROMIUM)"
            )
        self._tmp = tempfile.TemporaryDirectory(prefix="nbrdf-gpu-")
        to_chrome_r, self._w = os.pipe()
        self._r, from_chrome_w = os.pipe()

        def _fds():  # the protocol pipe is fd 3 (commands) and fd 4 (replies)
            r, w = (fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_chrome_r, from_chrome_w))
            os.dup2(r, 3)
            os.dup2(w, 4)

        self._proc = subprocess.Popen(
            [
                CHROMIUM,
                *GPU_FLAGS,
                f"--user-data-dir={self._tmp.name}/profile",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            pass_fds=(3, 4),
            preexec_fn=_fds,
        )
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf = b""
        self._id = 0
        self._events: list[dict] = []
        self.errors: list[str] = []
        self.renderer = ""
        try:
            target = self._call("Target.createTarget", {"url": "about:blank"})["targetId"]
            self._session = self._call(
                "Target.attachToTarget", {"targetId": target, "flatten": True}
            )["sessionId"]
            self._call("Page.enable", session=True)
            self._call("Runtime.enable", session=True)
            self._call(
                "Emulation.setDeviceMetricsOverride",
                {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
                session=True,
            )
        except BaseException:  # no half-started browser left behind
            self.close()
            raise

    # ------------------------------------------------------------------ protocol
    def _send(self, method: str, params: dict | None, session: bool) -> int:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = self._session
        try:
            os.write(self._w, json.dumps(msg).encode() + b"\0")
        except BrokenPipeError:
            raise BrowserError(f"chromium exited (code {self._proc.poll()})") from None
        return self._id

    def _next(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._r], [], [], left)[0]:
                raise BrowserError(f"chromium did not answer within {TIMEOUT} s")
            chunk = os.read(self._r, 1 << 20)
            if not chunk:
                raise BrowserError(f"chromium exited (code {self._proc.poll()})")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        msg = json.loads(msg)
        if msg.get("method") == "Runtime.consoleAPICalled" and msg["params"]["type"] in (
            "error",
            "assert",
        ):
            args = msg["params"]["args"]
            self.errors.append(
                " ".join(str(a.get("value", a.get("description", ""))) for a in args)
            )
        elif msg.get("method") == "Runtime.exceptionThrown":
            d = msg["params"]["exceptionDetails"]
            self.errors.append(d.get("exception", {}).get("description", d.get("text", "")))
        return msg

    def _call(self, method: str, params: dict | None = None, *, session: bool = False) -> dict:
        i = self._send(method, params, session)
        deadline = time.monotonic() + TIMEOUT
        while True:
            msg = self._next(deadline)
            if msg.get("id") == i:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error'].get('message')}")
                return msg["result"]
            if "method" in msg:
                self._events.append(msg)

    def _wait_event(self, method: str) -> dict:
        deadline = time.monotonic() + TIMEOUT
        while True:
            for k, e in enumerate(self._events):
                if e["method"] == method:
                    return self._events.pop(k)
            msg = self._next(deadline)
            if "method" in msg:
                self._events.append(msg)

    # ------------------------------------------------------------------ public
    def open(self, page) -> None:
        """Load a local HTML file (or a URL) and wait for its load event; clears errors."""
        url = page if "://" in str(page) else Path(page).resolve().as_uri()
        self._events.clear()
        self.errors.clear()
        self._call("Page.navigate", {"url": url}, session=True)
        self._wait_event("Page.loadEventFired")

    def evaluate(self, expression: str):
        """The JSON value of a JS expression, awaited if it is a promise; a thrown
        exception raises :class:`ShaderError` with its message."""
        r = self._call(
            "Runtime.evaluate",
            {"expression": expression, "awaitPromise": True, "returnByValue": True},
            session=True,
        )
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            text = d.get("exception", {}).get("description", d.get("text", "error"))
            raise ShaderError(text.splitlines()[0])
        return r["result"].get("value")

    def screenshot(self, png_path) -> None:
        """The viewport as a PNG (the window size given to the constructor)."""
        data = self._call("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
        atomic_write(Path(png_path), base64.b64decode(data))

    def close(self) -> None:
        if self._proc.poll() is None:
            try:
                self._send("Browser.close", None, False)
                self._proc.wait(timeout=20)
            except (BrowserError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
        os.close(self._w)
        os.close(self._r)
        self._tmp.cleanup()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ shaders
    def _runner(self) -> None:
        if not self.evaluate("typeof nbEvalGLSL === 'function'"):
            page = Path(self._tmp.name) / "runner.html"
            page.write_text(RUNNER_PAGE, encoding="utf-8")
            self.open(page)

    def _eval(self, call: str, source: str, wi, wo, extra: int, *more: str) -> np.ndarray:
        wi = np.ascontiguousarray(wi, dtype=np.float32)
        wo = np.ascontiguousarray(wo, dtype=np.float32)
        wi, wo = np.broadcast_arrays(wi, wo)
        if wi.shape[-1:] != (3,):
            raise ValueError(f"wi, wo: expected shape (..., 3), got {wi.shape}")
        batch = wi.shape[:-1]
        n = int(np.prod(batch))
        if n == 0:
            return np.zeros(batch + (3,), np.float32)
        self._runner()
        b64 = [
            base64.b64encode(np.ascontiguousarray(a.reshape(-1, 3)).tobytes()).decode()
            for a in (wi, wo)
        ]
        r = self.evaluate(
            f"{call}({json.dumps(source)}, {json.dumps(b64[0])}, "
            f"{json.dumps(b64[1])}, {n}, {extra}{''.join(', ' + m for m in more)})"
        )
        self.renderer = r["renderer"]
        f = np.frombuffer(base64.b64decode(r["f"]), dtype=np.float32)
        return f.reshape(batch + (3,)).copy()

    def eval_glsl(self, source: str, wi, wo, *, uv=None, textures=None) -> np.ndarray:
        """``neural_brdf_eval`` of GLSL ES 3.00 ``source`` on each (wi, wo) pair, in WebGL2;
        with ``uv`` (N, 2) on each (wi, wo, uv) row, ``textures`` (uniform name ->
        (float array, floats per texel row)) bound as R32F textures."""
        if uv is None and not textures:
            return self._eval("nbEvalGLSL", source, wi, wo, TEXTURE_WIDTH)
        batch = np.broadcast_shapes(np.shape(wi), np.shape(wo))[:-1]
        uv = np.zeros(batch + (2,)) if uv is None else uv
        uv = np.ascontiguousarray(np.broadcast_to(uv, batch + (2,)), np.float32).reshape(-1, 2)
        bound = [
            {
                "name": name,
                "width": int(width),
                "data": base64.b64encode(np.asarray(data, "<f4").tobytes()).decode(),
            }
            for name, (data, width) in (textures or {}).items()
        ]
        return self._eval(
            "nbEvalGLSL",
            source,
            wi,
            wo,
            TEXTURE_WIDTH,
            json.dumps(base64.b64encode(uv.tobytes()).decode()),
            json.dumps(bound),
        )

    def eval_wgsl(self, source: str, wi, wo) -> np.ndarray:
        """``neural_brdf_eval`` of WGSL ``source`` on each (wi, wo) pair, in WebGPU."""
        return self._eval("nbEvalWGSL", source, wi, wo, WORKGROUP)


def eval_glsl(source: str, wi, wo) -> np.ndarray:
    """:meth:`Session.eval_glsl` in a browser of its own."""
    with Session() as s:
        return s.eval_glsl(source, wi, wo)


def eval_wgsl(source: str, wi, wo) -> np.ndarray:
    """:meth:`Session.eval_wgsl` in a browser of its own."""
    with Session() as s:
        return s.eval_wgsl(source, wi, wo)
