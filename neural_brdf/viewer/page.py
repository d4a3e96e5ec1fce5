"""An interactive BRDF viewer: one self-contained HTML file that draws generated GLSL in WebGL2.

    neural-brdf view runs/quickstart/model.onnx -o viewer.html
    neural-brdf view runs/a/model.onnx --compare runs/b/model.onnx -o ab.html
    neural-brdf view runs/quickstart/model.onnx --compare configs/gold.yaml -o vs_target.html
    neural-brdf view runs/tex/model.onnx --compare teacher.xml -o vs_teacher.html   # textured

    from neural_brdf.viewer import page as viewer
    viewer.write_viewer("model.onnx", "viewer.html", compare="other.onnx")
    page = viewer.page([viewer.Model("mine", glsl_source, albedo)])   # any GLSL

The page holds, BRDF-Explorer style (Burley's Disney BRDF Explorer): a sphere lit by a
directional light (drag on the sphere or use the sliders; exposure in stops), the
incidence-plane slice f cos(theta_o) for a chosen theta_i (linear or log), the same
slice as a polar lobe, and the directional albedo rho(theta_i).  With a second model
(``--compare``: another ONNX file, or a config whose analytic target is exported to ONNX
and generated the same way) the spheres stand side by side with a relative-difference
view, and the plots overlay both (first solid, second dashed).

Each model's shader is the code generated from its ONNX graph by
:mod:`neural_brdf.backends` (``neural_brdf_eval``), so the viewer shows exactly the
function onnxruntime evaluates.  Slices and lobes are evaluated in the shader; the
albedo curve is precomputed here with the MIS quadrature of
:mod:`neural_brdf.physics.quadrature` (onnxruntime) and embedded as JSON.

A textured file (inputs wi, wo, uv) is drawn on a textured sphere (:func:`sphere_frames`:
the sphere's uv, its frame's tangent along dp/du, the file's normal field applied as
Mitsuba's ``normalmap`` applies a normal, docs/codegen.md), its bound textures uploaded as
the generated GLSL expects them; its plots are at chosen points uv.  Its teacher
(``--compare teacher.xml``, or a config whose target is a Mitsuba file) has no graph: it is
evaluated here by Mitsuba at the page's own pixels for a fixed set of lights
(:data:`TEACHER_LIGHTS`, the page's light snaps to them) and at the same points uv, and
embedded (float16 with a scale per image, :func:`pack_half`).

The file has no external reference: the script and data are inline.  A model read from
an ONNX file carries the file itself (base64): the page reads its metadata_props from those
bytes with ``readOnnxMetadata`` (``neural_brdf/fileformat/onnx_metadata.js``, inlined before the
page's script; docs/portable.md) and shows the target and the physics figures.  For tests
the page exposes ``window.nbViewer`` (evalPairs, sphereRadiance, setState, metadata);
:func:`sphere_directions` is the sphere geometry of the page, for comparing its pixels
with onnxruntime.
"""

from __future__ import annotations

import base64
import html
import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neural_brdf import runfolder
from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write

SPHERE = 256  # sphere view size in pixels
ALBEDO_THETA = np.linspace(0.0, 89.0, 30)  # theta_i of the precomputed albedo curve, deg
ALBEDO_SAMPLES = 2048  # quadrature samples per theta_i
SCRIPT = Path(__file__).with_name("page.js")
# the file format's metadata reader, inlined before SCRIPT
METADATA_SCRIPT = Path(__file__).parents[1] / "fileformat" / "onnx_metadata.js"
TANGENT_EPS = 1e-6  # |(n.z, 0, -n.x)| below this: the tangent falls back to +x
# a textured sphere: the texture repeats REPEAT times across the visible half along u and
# from pole to pole along v (so texels are square at the equator)
REPEAT = 2.0
# where a textured model's plots are drawn (``--uv`` replaces them)
PROBES = ((0.5, 0.5), (0.25, 0.25), (0.75, 0.6), (0.1, 0.85))
# --uv's largest |U| and |V|: uv wraps by repeat, and the file and the page read it as
# float32, whose fraction beyond this is coarser than 2^-13 (at 2^24 it is gone)
MAX_UV = 1024.0
# a teacher is evaluated at these lights (theta from the view axis, phi), degrees
TEACHER_LIGHTS = tuple([(0, 30)] + [(t, p) for t in (35, 70) for p in (30, 120, 210, 300)])
SLICE_THETA_I = np.arange(90)  # a teacher's slices: theta_i in degrees (the page's slider)
SLICE_N = 181  # theta_o samples of a slice, -90 to 90 degrees (page.js)
HALF_MAX = 32768.0  # pack_half: the largest value of an image is stored as this

CSS = """
body { font: 14px/1.4 system-ui, sans-serif; color: #222; background: #fafafa; margin: 0; }
main { max-width: 1200px; margin: 0 auto; padding: 16px 20px; }
h1 { font-size: 20px; margin: 0 0 8px; }
/* each heading shrinks with its third (or whole) of the sphere canvas, which scales
   down to the page's width (its drawing buffer keeps its size) */
.labels { display: flex; max-width: 100%; }
.labels div { flex: 0 1 256px; min-width: 0; text-align: center; font-weight: 600;
              overflow-wrap: anywhere; }
#nb-gl { display: block; background: #222; cursor: crosshair; touch-action: none;
         max-width: 100%; height: auto; }
.controls { display: grid; grid-template-columns: max-content minmax(80px, 220px) 4em;
            gap: 4px 10px; align-items: center; margin: 12px 0; }
.plots { display: flex; flex-wrap: wrap; gap: 10px; align-items: flex-start; }
canvas.plot { border: 1px solid #ddd; max-width: 100%; height: auto; box-sizing: border-box; }
#nb-status, #nb-diff { color: #555; font-size: 13px; }
#nb-meta { color: #444; font-size: 13px; white-space: pre-wrap; overflow-wrap: anywhere;
           margin: 4px 0 8px; }
@media (max-width: 600px) {
  main { padding: 12px; }
  .controls { grid-template-columns: minmax(0, 1fr) minmax(80px, 1fr) 3.5em; }
}
"""


@dataclass
class Model:
    """One model of the page: its label, its GLSL (defining ``neural_brdf_eval``), its
    albedo curve {"theta": [deg], "rho": [[r, g, b]]} and, for a model read from a file,
    the ONNX file's bytes (the page reads their metadata).

    A textured model (``textured``: its GLSL takes uv) has one albedo curve per point
    of the page's ``probes``, the data of its bound textures (float32 [rows, channels]
    each, :func:`neural_brdf.backends.textures`), ``normal`` when its GLSL defines
    ``neural_brdf_normal``, and its ``metadata`` (the file's metadata_props, strings)
    instead of the file's bytes (the textures would be embedded twice).  A teacher has
    no GLSL: ``tabulated`` holds its images and slices (:func:`teacher_model`) and
    ``note`` says what it is."""

    name: str
    glsl: str | None
    albedo: dict | list[dict]
    onnx: bytes | None = None
    textured: bool = False
    normal: bool = False
    textures: tuple[np.ndarray, ...] = ()
    metadata: dict | None = None
    tabulated: dict | None = None
    note: str = ""


def albedo_curve(fn, theta_deg=ALBEDO_THETA, *, samples: int = ALBEDO_SAMPLES) -> dict:
    """rho(theta_i) per channel of a numpy ``fn(wi, wo)`` (:func:`quadrature.albedo_at`)."""
    from neural_brdf.physics import quadrature

    return curve(theta_deg, quadrature.albedo_at(fn, theta_deg, samples))


def _sphere_normals(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, on_sphere): the unit sphere's normal (size, size, 3) at each pixel, rows
    bottom-up, (x, y, 0) off the sphere."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, c)  # [row = y, column = x]
    r2 = x * x + y * y
    n = np.stack([x, y, np.sqrt(np.clip(1.0 - r2, 0.0, None))], -1)
    return n, r2 < 1.0


def sphere_directions(size: int, light) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wi, wo, on_sphere) of every pixel (size, size, 3), rows bottom-up like readPixels:
    the page's geometry (page.js, SPHERE_MAIN) in float64."""
    n, inside = _sphere_normals(size)
    x = n[..., 0]
    t = np.stack([n[..., 2], np.zeros_like(x), -n[..., 0]], -1)
    tl = np.linalg.norm(t, axis=-1, keepdims=True)
    t = np.where(tl > TANGENT_EPS, t / np.maximum(tl, TANGENT_EPS), [1.0, 0.0, 0.0])
    b = np.cross(n, t)
    light = np.asarray(light, dtype=np.float64)
    wi = np.stack([t @ light, b @ light, n @ light], -1)
    wo = np.stack([t[..., 2], b[..., 2], n[..., 2]], -1)
    return wi, wo, inside


def sphere_frames(size: int, light, repeat: float = REPEAT):
    """(wi, wo, uv, on_sphere) of every pixel of the textured sphere, rows bottom-up:
    :func:`sphere_directions` (whose tangent (n.z, 0, -n.x) is dp/du of this
    parametrisation) with uv = repeat (phi / pi + 1/2, 1 - theta / pi), phi = atan2(n.x,
    n.z) the longitude about the view's y axis and theta = acos(n.y) the angle from its
    pole (page.js, sphereTexturedMain)."""
    wi, wo, inside = sphere_directions(size, light)
    n, _ = _sphere_normals(size)
    u = np.arctan2(n[..., 0], n[..., 2]) / np.pi + 0.5
    v = 1.0 - np.arccos(np.clip(n[..., 1], -1.0, 1.0)) / np.pi
    return wi, wo, repeat * np.stack([u, v], -1), inside


def normal_frame(wi, wo, n):
    """wi and wo in the frame of the shading normal n (..., 3) as Mitsuba's ``normalmap``
    builds it and the page does (docs/codegen.md, "The normal field"): s = normalize(x -
    n n.x), t = n x s."""
    s = np.array([1.0, 0.0, 0.0]) - n * n[..., :1]
    s = s / np.linalg.norm(s, axis=-1, keepdims=True)
    t = np.cross(n, s)

    def to(w):
        return np.stack([np.sum(w * s, -1), np.sum(w * t, -1), np.sum(w * n, -1)], -1)

    return to(wi), to(wo)


def textured_radiance(fn, normal, size: int, light, repeat: float = REPEAT) -> np.ndarray:
    """The page's textured sphere (size, size, 3), rows bottom-up, of ``fn(wi, wo, uv)``
    and ``normal(uv)`` (None: the unperturbed normal) under a directional light of
    irradiance pi: pi f(wi', wo', uv) max(wi'.z, 0) with wi', wo' in the normal's frame,
    0 where the light is below the surface or off the sphere."""
    wi, wo, uv, inside = sphere_frames(size, light, repeat)
    out = np.zeros(wi.shape)
    lit = inside & (wi[..., 2] > 0)
    a, b, c = wi[lit], wo[lit], uv[lit]
    if normal is not None:
        a, b = normal_frame(a, b, normal(c))
    f = np.asarray(fn(a, b, c), dtype=np.float64)
    out[lit] = np.pi * f * np.clip(a[:, 2:3], 0.0, None)
    return out


def light_of(theta_deg: float, phi_deg: float) -> np.ndarray:
    """The page's light direction (page.js, lightDir) from its two angles in degrees."""
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def pack_half(x) -> dict:
    """float16 with a scale, base64: {"scale", "data"}; value = half * scale, the
    largest magnitude stored as HALF_MAX (relative precision 2^-11 down to about
    1e-9 of it)."""
    x = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        raise ValueError("pack_half: values must be finite")
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    scale = peak / HALF_MAX if peak > 0 else 1.0
    half = (x / scale).astype("<f2")
    return {"scale": scale, "data": base64.b64encode(half.tobytes()).decode("ascii")}


def unpack_half(packed: dict) -> np.ndarray:
    """The float64 values of :func:`pack_half` (flat)."""
    half = np.frombuffer(base64.b64decode(packed["data"]), dtype="<f2")
    return half.astype(np.float64) * packed["scale"]


def slice_pairs(theta_i_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The incidence-plane pairs of the page's slice at theta_i (page.js, slices):
    wi at -theta_i, wo from -90 to 90 degrees in SLICE_N steps (float32 as the page)."""
    ti = np.radians(theta_i_deg)
    to = np.radians(-90.0 + 180.0 * np.arange(SLICE_N) / (SLICE_N - 1))
    wi = np.tile([-np.sin(ti), 0.0, np.cos(ti)], (SLICE_N, 1))
    wo = np.stack([np.sin(to), np.zeros_like(to), np.cos(to)], -1)
    return wi.astype(np.float32), wo.astype(np.float32)


def _json_for_script(data) -> str:
    """JSON safe inside <script type="application/json">: no '</' to end the element."""
    return json.dumps(data, separators=(",", ":")).replace("</", "<\\/")


def _texture_json(t: np.ndarray) -> dict:
    t = np.ascontiguousarray(t, dtype="<f4")
    return {
        "rows": int(t.shape[0]),
        "channels": int(t.shape[1]),
        "data": base64.b64encode(t.tobytes()).decode("ascii"),
    }


def page(
    models: list[Model],
    *,
    title: str = "neural-brdf viewer",
    probes=PROBES,
    repeat: float = REPEAT,
) -> str:
    """The viewer page for one or two models, as an HTML string.  ``probes``: the points
    uv of a textured model's plots; ``repeat``: the textured sphere's (:func:`sphere_frames`)."""
    if not 1 <= len(models) <= 2:
        raise ValueError(f"models: one or two, got {len(models)}")
    textured = any(m.textured for m in models)
    tabulated = [m.tabulated for m in models if m.tabulated is not None]
    data = {
        "sphere": SPHERE,
        "textured": textured,
        "repeat": float(repeat),
        "probes": [[float(u), float(v)] for u, v in probes] if textured else [],
        "lights": [list(x) for x in tabulated[0]["lights"]] if tabulated else None,
        "models": [
            {
                "name": m.name,
                "glsl": m.glsl,
                "albedo": m.albedo,
                "onnx": None if m.onnx is None else base64.b64encode(m.onnx).decode("ascii"),
                "textured": m.textured,
                "normal": m.normal,
                "textures": [_texture_json(t) for t in m.textures],
                "metadata": m.metadata,
                "tabulated": m.tabulated,
                "note": m.note,
            }
            for m in models
        ],
    }
    labels = [m.name for m in models] + (["relative difference"] if len(models) > 1 else [])
    label_html = "".join(f"<div>{html.escape(s)}</div>" for s in labels)
    legend = (
        ""
        if len(models) == 1
        else f"<p>Plots: <b>{html.escape(models[0].name)}</b> solid, "
        f"<b>{html.escape(models[1].name)}</b> dashed.  Difference: max over RGB of "
        "|A − B| / max(A, B), log colour scale from 10<sup>−3</sup> (blue) to 1 "
        "(yellow).</p>"
    )
    sliders = "".join(
        f'<label for="{i}">{html.escape(lab)}</label><input type="range" id="{i}" '
        f'min="{lo}" max="{hi}" step="{st}"><span id="{i}-v"></span>'
        for i, lab, lo, hi, st in [
            ("nb-thetaL", "light θ from the view axis [deg]", 0, 89, 1),
            ("nb-phiL", "light φ [deg]", 0, 359, 1),
            ("nb-ev", "exposure [stops]", -6, 6, 0.25),
            ("nb-thetaI", "slice incidence θi [deg]", 0, 89, 1),
        ]
    )
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{html.escape(title)}</title>
<style>{CSS}</style></head><body><main>
<h1>{html.escape(title)}</h1>
<p>Drag on a sphere to move the light (a directional light of irradiance π: a white
Lambertian facing it shows radiance 1).  Everything is drawn with the GLSL generated from
the model's ONNX graph.{_textured_text(models, repeat)}</p>
<pre id="nb-meta"></pre>
<div class="labels">{label_html}</div>
<canvas id="nb-gl"></canvas>
<div id="nb-diff"></div>
<div class="controls">{sliders}
<label for="nb-log">log scale slices</label><input type="checkbox" id="nb-log"><span></span>
{_probe_select(probes) if textured else ""}</div>
{legend}
<div class="plots">
<canvas class="plot" id="nb-slice" width="400" height="300"></canvas>
<canvas class="plot" id="nb-polar" width="320" height="220"></canvas>
<canvas class="plot" id="nb-albedo" width="330" height="300"></canvas>
</div>
<pre id="nb-status">loading</pre>
<script type="application/json" id="nb-data">{_json_for_script(data)}</script>
<script>
{METADATA_SCRIPT.read_text(encoding="utf-8")}
{SCRIPT.read_text(encoding="utf-8")}
</script>
</main></body></html>
"""


def _textured_text(models: list[Model], repeat: float) -> str:
    if not any(m.textured for m in models):
        return ""
    text = (
        f"  The sphere is textured: uv = {repeat:g} (φ/π + ½, 1 − θ/π), φ the longitude and "
        "θ the angle from the top pole, the tangent along ∂p/∂u; a normal field is applied "
        "as Mitsuba's normalmap applies a normal (its flip and shadowing term are not).  "
        "The plots show f in the shading frame at the chosen point uv."
    )
    if any(m.tabulated is not None for m in models):
        text += (
            "  The teacher was evaluated by Mitsuba when the page was written, at the same "
            "pixels, for a fixed set of lights: the light snaps to the nearest of them."
        )
    return html.escape(text)


def _probe_select(probes) -> str:
    options = "".join(
        f'<option value="{k}">u {u:.3g}, v {v:.3g}</option>' for k, (u, v) in enumerate(probes)
    )
    return (
        '<label for="nb-probe">plots at the point</label>'
        f'<select id="nb-probe">{options}</select><span></span>'
    )


# ------------------------------------------------------------------ from ONNX files
def glsl_of(model, *, lobe: dict | None = None) -> str:
    """GLSL of an ONNX model (a path) through the code generator's registry."""
    try:
        from neural_brdf import backends
    except ImportError:
        raise InputError(
            "view: the GLSL code generator (neural_brdf.backends) is not "
            "available in this installation"
        ) from None
    return backends.generate(str(model), "glsl", lobe=lobe)


def curve(theta_deg, rho) -> dict:
    """An albedo curve of the page: {"theta": [deg], "rho": [[r, g, b]]}, rounded."""
    return {
        "theta": [round(float(x), 4) for x in theta_deg],
        "rho": [[round(float(v), 6) for v in row] for row in np.asarray(rho)],
    }


def onnx_model(path, label: str, *, albedo: dict | None = None, probes=PROBES) -> Model:
    """A model of the page from an ONNX file: its generated GLSL and its albedo curve
    (a textured file: one per point of ``probes``, its textures and its metadata)."""
    from neural_brdf.runtime import load

    brdf = load(path)  # a one-line InputError on a missing or bad file
    if brdf.textured:
        from neural_brdf import backends

        curves = [albedo_curve(at_uv(brdf.eval, uv)) for uv in probes]
        return Model(
            label,
            glsl_of(path),
            curves,
            textured=True,
            normal=brdf.has_normal_field,
            textures=tuple(backends.textures(str(path))),
            metadata=dict(brdf.metadata),
        )
    if albedo is None:
        albedo = albedo_curve(brdf.eval)
    return Model(label, glsl_of(path), albedo, Path(path).read_bytes())


def at_uv(fn, uv):
    """A textured ``fn(wi, wo, uv)`` as a ``fn(wi, wo)`` at one point uv (float32, as a
    shader's uv): the page's plots and the report's figures."""

    def at(wi, wo):
        shape = np.broadcast_shapes(np.shape(wi)[:-1], np.shape(wo)[:-1])
        return fn(wi, wo, np.broadcast_to(np.asarray(uv, np.float32), shape + (2,)))

    return at


def mitsuba_teacher(xml):
    """The Mitsuba teacher of an XML file: a MitsubaTarget, or a TexturedMitsubaTarget
    when it varies over the surface (as training builds it); an InputError naming the
    file when Mitsuba is missing or cannot use it."""
    try:
        from neural_brdf.measured.mitsuba import MitsubaTarget, VariesOverSurface
    except ImportError as e:
        raise InputError(f"--compare {xml}: a Mitsuba teacher needs Mitsuba 3 ({e})") from None
    try:
        return MitsubaTarget(xml, key="--compare")
    except VariesOverSurface:
        from neural_brdf.measured.textured import TexturedMitsubaTarget

        return TexturedMitsubaTarget(xml, key="--compare")


def teacher_model(
    teacher, label: str, *, textured: bool, probes=PROBES, repeat: float = REPEAT
) -> Model:
    """A Mitsuba teacher (:func:`mitsuba_teacher`) as a model of the page, evaluated here
    before its energy bound (what Mitsuba renders): its sphere at each of
    TEACHER_LIGHTS (the page's pixels and, for a textured page, its uv and the
    teacher's normal map applied as the file's normal field is), its slices at every
    integer theta_i and its albedo curve, at each point of ``probes`` when ``textured``
    (one point otherwise)."""
    varying = bool(getattr(teacher, "spatially_varying", False))
    if varying and not textured:
        raise InputError(
            f"--compare {teacher.source}: a textured teacher (it varies over the surface); "
            "compare it with a textured model (inputs wi, wo, uv)"
        )
    if varying:
        fn, normal = teacher.eval, teacher.normal_field
    else:
        raw = getattr(teacher, "teacher", teacher.eval)  # Mitsuba's f before the bound

        def fn(wi, wo, uv):
            return raw(wi, wo)

        normal = None
    points = probes if textured else [(0.5, 0.5)]
    _, inside = _sphere_normals(SPHERE)  # the same pixels at every light
    images = [
        pack_half(textured_radiance(fn, normal, SPHERE, light_of(*tp), repeat)[inside])
        for tp in TEACHER_LIGHTS
    ]
    pairs = [slice_pairs(float(t)) for t in SLICE_THETA_I]
    wi = np.concatenate([a for a, _ in pairs]).astype(np.float64)
    wo = np.concatenate([b for _, b in pairs]).astype(np.float64)
    slices, curves = [], []
    for uv in points:
        at = at_uv(fn, uv)
        slices.append(pack_half(at(wi, wo)))
        curves.append(albedo_curve(at))
    return Model(
        label,
        None,
        curves if textured else curves[0],
        textured=textured,
        tabulated={
            "lights": [[float(x) for x in t] for t in TEACHER_LIGHTS],
            "images": images,
            "slices": slices,
        },
        note=(
            f"{label}: Mitsuba's eval of {Path(teacher.source).name} ({teacher.plugin}), "
            f"before any energy bound, evaluated when the page was written at "
            f"{len(TEACHER_LIGHTS)} lights" + (f" and {len(points)} points uv" if textured else "")
        ),
    )


def analytic_model(
    name: str, params: dict, label: str, *, albedo: dict | None = None, lobe: dict | None = None
) -> Model:
    """An analytic model (a config's target), exported to ONNX and generated like a
    trained one; its sampling lobe (unused by the page) is fitted as for the plugin
    (:func:`neural_brdf.physics.lobe_fit.fit_onnx` keeps it for the plugin's next load) unless
    ``lobe`` is given.  ``albedo``: a precomputed curve (:func:`curve`), else one by
    quadrature."""
    from neural_brdf.export import analytic_onnx
    from neural_brdf.physics import lobe_fit

    given = lobe
    from neural_brdf.runtime import load

    payload = analytic_onnx(name, params)
    with tempfile.TemporaryDirectory(prefix="nbrdf-view-") as tmp:
        onnx_path = Path(tmp) / "reference.onnx"
        onnx_path.write_bytes(payload)
        glsl = glsl_of(onnx_path, lobe=given if given is not None else lobe_fit.fit_onnx(payload))
        if albedo is None:
            albedo = albedo_curve(load(onnx_path).eval)
    return Model(label, glsl, albedo)


def _label(path: Path) -> str:
    return f"{path.parent.name}/{path.name}" if path.parent.name else path.name


def models_for(model, compare=None, *, probes=PROBES, warn=None) -> list[Model]:
    """The page's models: ``model`` (.onnx) and optionally ``compare``: another .onnx of
    the same kind (textured or not), a Mitsuba teacher (.xml), or a config (.yaml) whose
    analytic target, or Mitsuba teacher, is compared.  ``warn``: called with train's
    one-line warnings about the config (:func:`neural_brdf.config.load`: an empty one)."""
    from neural_brdf import config
    from neural_brdf.train import data

    model = Path(model)
    if model.suffix.lower() != ".onnx":
        raise InputError(f"{model}: expected an ONNX model (.onnx)")
    first = onnx_model(model, _label(model), probes=probes)
    out = [first]
    if compare is None:
        return out
    compare = Path(compare)
    if compare.suffix.lower() == ".onnx":
        second = onnx_model(compare, _label(compare), probes=probes)
        if second.textured != first.textured:
            kinds = {True: "textured (inputs wi, wo, uv)", False: "homogeneous (wi, wo)"}
            raise InputError(
                f"--compare {compare}: a {kinds[second.textured]} model beside a "
                f"{kinds[first.textured]} one; compare models of one kind, or a textured "
                "model with its Mitsuba teacher (.xml)"
            )
        out.append(second)
    else:  # a Mitsuba teacher, or a config (any other name, as validate --reference reads it)
        xml = compare
        if compare.suffix.lower() != ".xml":  # a config: its analytic target, or its teacher
            cfg = config.load(compare, warn=warn)
            data.refuse_images(cfg.target, str(compare))  # its target.model: the unused default
            if cfg.target.data is not None:
                raise InputError(
                    f"{compare}: target.data: the viewer compares analytic targets and "
                    "Mitsuba teachers only (a measured table has no ONNX graph)"
                )
            if cfg.target.mitsuba is None and first.textured:
                raise InputError(
                    f"{compare}: target.model: a textured model is compared with its "
                    "Mitsuba teacher (target.mitsuba, or the .xml) or another textured file"
                )
            if cfg.target.mitsuba is None:
                # a bad model or parameter: train's message (target.params: ...), after the file
                data.build_target(cfg.target, source=str(compare))
                name, params = cfg.target.model, dict(cfg.target.params)
                return out + [analytic_model(name, params, f"target: {name}")]
            xml = Path(cfg.target.mitsuba)
        teacher = mitsuba_teacher(xml)
        label = f"teacher: {xml.name}"
        out.append(teacher_model(teacher, label, textured=first.textured, probes=probes))
    return out


def parse_probes(texts) -> tuple[tuple[float, float], ...]:
    """``--uv U,V`` values (repeatable) as the page's probes; PROBES when none."""
    if not texts:
        return PROBES
    out = []
    for text in texts:
        parts = str(text).split(",")
        try:
            u, v = (float(x) for x in parts)
        except ValueError:
            raise InputError(
                f"--uv {text}: expected two numbers U,V (e.g. --uv 0.5,0.25)"
            ) from None
        if not (np.isfinite(u) and np.isfinite(v)):
            raise InputError(f"--uv {text}: U and V must be finite")
        if max(abs(u), abs(v)) > MAX_UV:
            raise InputError(
                f"--uv {text}: U and V must be within +-{MAX_UV:g} (uv wraps: give its "
                "fraction; a float32 uv this large loses it)"
            )
        out.append((u, v))
    return tuple(out)


def page_title(model) -> str:
    """The page's title for the file ``model``: a run's model.onnx with its run folder's
    name ("quickstart/model.onnx"), so that two runs' pages are told apart in a browser's
    tabs; any other file by its name."""
    path = Path(model)
    run = path.resolve().parent.name if path.name == runfolder.MODEL else ""
    return f"neural-brdf viewer: {run + '/' if run else ''}{path.name}"


def write_viewer(model, out, *, compare=None, probes=PROBES, warn=None) -> Path:
    """Write the viewer of ``model`` (and ``compare``) to ``out``; returns the path.
    ``warn``: as for :func:`models_for`."""
    out = Path(out)
    if out.suffix.lower() not in (".html", ".htm"):
        raise InputError(f"-o {out}: the viewer is an HTML file (.html)")
    if not out.parent.is_dir():
        raise InputError(f"-o {out}: cannot write (no folder {out.parent})")
    models = models_for(model, compare, probes=probes, warn=warn)
    text = page(models, title=page_title(model), probes=probes)
    try:
        atomic_write(out, text.encode("utf-8"))
    except OSError as e:
        raise InputError(f"{out}: cannot write ({e.strerror})") from None
    return out
