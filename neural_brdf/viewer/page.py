"""An interactive BRDF viewer: one self-contained HTML file that draws generated GLSL in WebGL2.

    neural-brdf view runs/quickstart/model.onnx -o viewer.html
    neural-brdf view runs/a/model.onnx --compare runs/b/model.onnx -o ab.html
    neural-brdf view runs/quickstart/model.onnx --compare configs/gold.yaml -o vs_target.html

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

from neural_brdf.errors import InputError
from neural_brdf.fileio import atomic_write

SPHERE = 256  # sphere view size in pixels
ALBEDO_THETA = np.linspace(0.0, 89.0, 30)  # theta_i of the precomputed albedo curve, deg
ALBEDO_SAMPLES = 2048  # quadrature samples per theta_i
SCRIPT = Path(__file__).with_name("page.js")
# the file format's metadata reader, inlined before SCRIPT
METADATA_SCRIPT = Path(__file__).parents[1] / "fileformat" / "onnx_metadata.js"
TANGENT_EPS = 1e-6  # |(n.z, 0, -n.x)| below this: the tangent falls back to +x

CSS = """
body { font: 14px/1.4 system-ui, sans-serif; color: #222; background: #fafafa; margin: 0; }
main { max-width: 1200px; margin: 0 auto; padding: 16px 20px; }
h1 { font-size: 20px; margin: 0 0 8px; }
.labels { display: flex; } .labels div { width: 256px; text-align: center; font-weight: 600; }
#nb-gl { display: block; background: #222; cursor: crosshair; touch-action: none; }
.controls { display: grid; grid-template-columns: max-content 220px 4em; gap: 4px 10px;
            align-items: center; margin: 12px 0; }
.plots { display: flex; flex-wrap: wrap; gap: 10px; align-items: flex-start; }
canvas.plot { border: 1px solid #ddd; }
#nb-status, #nb-diff { color: #555; font-size: 13px; }
#nb-meta { color: #444; font-size: 13px; white-space: pre-wrap; margin: 4px 0 8px; }
"""


@dataclass
class Model:
    """One model of the page: its label, its GLSL (defining ``neural_brdf_eval``), its
    albedo curve {"theta": [deg], "rho": [[r, g, b]]} and, for a model read from a file,
    the ONNX file's bytes (the page reads their metadata)."""

    name: str
    glsl: str
    albedo: dict
    onnx: bytes | None = None


def albedo_curve(fn, theta_deg=ALBEDO_THETA, *, samples: int = ALBEDO_SAMPLES) -> dict:
    """rho(theta_i) per channel of a numpy ``fn(wi, wo)`` (:func:`quadrature.albedo_at`)."""
    from neural_brdf.physics import quadrature

    return curve(theta_deg, quadrature.albedo_at(fn, theta_deg, samples))


def sphere_directions(size: int, light) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wi, wo, on_sphere) of every pixel (size, size, 3), rows bottom-up like readPixels:
    the page's geometry (page.js, SPHERE_MAIN) in float64."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, c)  # [row = y, column = x]
    r2 = x * x + y * y
    inside = r2 < 1.0
    n = np.stack([x, y, np.sqrt(np.clip(1.0 - r2, 0.0, None))], -1)
    t = np.stack([n[..., 2], np.zeros_like(x), -n[..., 0]], -1)
    tl = np.linalg.norm(t, axis=-1, keepdims=True)
    t = np.where(tl > TANGENT_EPS, t / np.maximum(tl, TANGENT_EPS), [1.0, 0.0, 0.0])
    b = np.cross(n, t)
    light = np.asarray(light, dtype=np.float64)
    wi = np.stack([t @ light, b @ light, n @ light], -1)
    wo = np.stack([t[..., 2], b[..., 2], n[..., 2]], -1)
    return wi, wo, inside


def _json_for_script(data) -> str:
    """JSON safe inside <script type="application/json">: no '</' to end the element."""
    return json.dumps(data, separators=(",", ":")).replace("</", "<\\/")


def page(models: list[Model], *, title: str = "neural-brdf viewer") -> str:
    """The viewer page for one or two models, as an HTML string."""
    if not 1 <= len(models) <= 2:
        raise ValueError(f"models: one or two, got {len(models)}")
    data = {
        "sphere": SPHERE,
        "models": [
            {
                "name": m.name,
                "glsl": m.glsl,
                "albedo": m.albedo,
                "onnx": None if m.onnx is None else base64.b64encode(m.onnx).decode("ascii"),
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
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>{CSS}</style></head><body><main>
<h1>{html.escape(title)}</h1>
<p>Drag on a sphere to move the light (a directional light of irradiance π: a white
Lambertian facing it shows radiance 1).  Everything is drawn with the GLSL generated from
the model's ONNX graph.</p>
<pre id="nb-meta"></pre>
<div class="labels">{label_html}</div>
<canvas id="nb-gl"></canvas>
<div id="nb-diff"></div>
<div class="controls">{sliders}
<label for="nb-log">log scale slices</label><input type="checkbox" id="nb-log"><span></span>
</div>
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


def onnx_model(path, label: str, *, albedo: dict | None = None) -> Model:
    """A model of the page from an ONNX file: its generated GLSL and its albedo curve."""
    from neural_brdf.runtime import load

    brdf = load(path)  # a one-line InputError on a missing or bad file
    if albedo is None:
        albedo = albedo_curve(brdf.eval)
    return Model(label, glsl_of(path), albedo, Path(path).read_bytes())


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


def models_for(model, compare=None) -> list[Model]:
    """The page's models: ``model`` (.onnx) and optionally ``compare`` (.onnx or a config)."""
    from neural_brdf import config

    model = Path(model)
    if model.suffix != ".onnx":
        raise InputError(f"{model}: expected an ONNX model (.onnx)")
    out = [onnx_model(model, _label(model))]
    if compare is not None:
        compare = Path(compare)
        if compare.suffix == ".onnx":
            out.append(onnx_model(compare, _label(compare)))
        elif compare.suffix in (".yaml", ".yml"):
            cfg = config.load(compare)
            if cfg.target.data is not None or cfg.target.mitsuba is not None:
                raise InputError(
                    f"{compare}: target.{'data' if cfg.target.data else 'mitsuba'}: "
                    "the viewer compares analytic targets only (measured data and "
                    "Mitsuba teachers have no ONNX graph)"
                )
            out.append(
                analytic_model(
                    cfg.target.model, dict(cfg.target.params), f"target: {cfg.target.model}"
                )
            )
        else:
            raise InputError(
                f"--compare {compare}: expected a model (.onnx) or a config "
                "(.yaml) whose analytic target is compared"
            )
    return out


def write_viewer(model, out, *, compare=None) -> Path:
    """Write the viewer of ``model`` (and ``compare``) to ``out``; returns the path."""
    out = Path(out)
    if out.suffix not in (".html", ".htm"):
        raise InputError(f"-o {out}: the viewer is an HTML file (.html)")
    if not out.parent.is_dir():
        raise InputError(f"-o {out}: cannot write (no folder {out.parent})")
    models = models_for(model, compare)
    text = page(models, title=f"neural-brdf viewer: {Path(model).name}")
    try:
        atomic_write(out, text.encode("utf-8"))
    except OSError as e:
        raise InputError(f"{out}: cannot write ({e.strerror})") from None
    return out
