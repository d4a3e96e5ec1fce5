"""The WebGL2 viewer of a textured file beside its Mitsuba teacher (issue 30: "the viewer
and the report show a textured object beside its teacher"), in headless Chromium.

A small textured ``principled`` with a normal map (16 x 16 procedural maps) is trained
once per module (a few dozen steps: the checks are of the page, not of the fit); its
training writes the report and its viewer.  The references are independent of the page:
onnxruntime on the file (f and its normal field n) with the page's geometry in float64
(:func:`neural_brdf.viewer.page.sphere_frames`), and Mitsuba's own ``eval`` of the
teacher through a fresh :class:`~neural_brdf.measured.textured.TexturedMitsubaTarget`.

* ``neural-brdf view model.onnx --compare teacher.xml`` writes one page that loads without
  an error and draws three panels (model, teacher, difference) and the plots;
* the model's textured sphere is f(wi', wo', uv) cos in the frame of the file's normal
  field at the sphere's uv, to the viewer's sphere tolerance; the same comparison without
  the normal field, or with v mirrored, fails (the page reads both);
* the teacher's panel is Mitsuba's eval at the same pixels, to float16's precision; the
  light snaps to the teacher's lights and the model is drawn at the snapped light;
* the plots at a chosen point uv are onnxruntime's and Mitsuba's there (and differ from
  another point's);
* a homogeneous Mitsuba teacher beside a homogeneous file (a Lambertian against
  Mitsuba's ``diffuse``) agrees to float16's precision, and is drawn the same beside
  the textured file;
* the run's report carries the textured viewer with its teacher;
* bad combinations exit 2 with one line.

Chromium and Mitsuba are required (CI installs both): nothing here skips.
"""

from __future__ import annotations

import base64
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cli_helpers import assert_one_line_error, cli
from harness import gpu_browser
from neural_brdf.runtime import load
from neural_brdf.viewer import page as viewer

pytestmark = pytest.mark.mitsuba

SETTINGS = """\
target: {{mitsuba: {xml}}}
texture: {{lobes: 3, resolution: 8, validation_uv: 8}}
train: {{steps: 40, checkpoint_every: 20, log_every: 10, eval_every: 20, progress: false}}
data: {{pool_size: 8192, batch_size: 1024}}
validation: {{pairs: 2000, furnace_dirs: 32, furnace_samples: 4096, accuracy_samples: 8192}}
normalization: {{samples: 4096}}
export: {{parity_pairs: 512}}
"""
# The page computes the geometry and uv in float32; near a texel edge of the normal field
# a shifted uv moves the normal, so the tolerance is on the peak radiance, as in
# test_viewer.py.  Measured on a 256^2 principled with its normal field (300 steps):
# up to 9.4e-4 of the peak (99th percentile 2.2e-4); the teacher's panel 2.4e-4.
SPHERE_TOL = 2e-3
HALF_TOL = 1e-3  # the teacher's images and slices are float16 (2^-11 relative) of the peak


@pytest.fixture(scope="module")
def teacher(tmp_path_factory) -> Path:
    from neural_brdf.measured.procedural import write_teacher

    return write_teacher(tmp_path_factory.mktemp("teacher"), "principled", size=16)


@pytest.fixture(scope="module")
def run(teacher, tmp_path_factory) -> Path:
    from neural_brdf.tooling.cli import main

    folder = tmp_path_factory.mktemp("textured_view")
    cfg = folder / "tx.yaml"
    cfg.write_text(SETTINGS.format(xml=teacher))
    assert main(["train", str(cfg), "--out", str(folder / "run")]) in (0, 1)
    return folder / "run"


@pytest.fixture(scope="module")
def model(run) -> Path:
    path = run / "model.onnx"
    brdf = load(path)
    assert brdf.textured and brdf.has_normal_field  # the case this file is about
    return path


@pytest.fixture(scope="module")
def session():
    with gpu_browser.Session(width=1200, height=1100) as s:
        yield s


@pytest.fixture(scope="module")
def page(model, teacher, tmp_path_factory):
    from neural_brdf.tooling.cli import main

    out = tmp_path_factory.mktemp("page") / "viewer.html"
    assert main(["view", str(model), "--compare", str(teacher), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def opened(page, session):
    session.open(page)
    state = session.evaluate("document.getElementById('nb-status').textContent")
    return state, list(session.errors)


@pytest.fixture(scope="module")
def mitsuba_teacher(teacher):
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    return TexturedMitsubaTarget(teacher)


def sphere_pixels(session, k: int, light) -> np.ndarray:
    data = session.evaluate(f"nbViewer.sphereRadiance({k}, {list(map(float, light))})")
    return np.frombuffer(base64.b64decode(data), np.float32).reshape(
        viewer.SPHERE, viewer.SPHERE, 4
    )


def float32_eval(fn):
    """fn(wi, wo, uv) on float32 inputs, as the page hands them to the shader."""

    def at(wi, wo, uv):
        return fn(wi.astype(np.float32), wo.astype(np.float32), uv.astype(np.float32))

    return at


def test_the_page_loads_and_draws_three_panels(opened, session, page, tmp_path):
    state, errors = opened
    assert state == "ready" and errors == []
    text = page.read_text()
    assert "<script src" not in text and "http://" not in text and "https://" not in text
    assert session.evaluate("nbViewer.models.length") == 2
    shot = tmp_path / "shot.png"
    session.screenshot(shot)
    rect = session.evaluate(
        "(() => { const r = document.getElementById('nb-gl')"
        ".getBoundingClientRect(); return [r.x, r.y, r.width, r.height]; })()"
    )
    assert rect[2] == 3 * viewer.SPHERE
    with Image.open(shot) as im:
        px = np.asarray(im.convert("RGB"), dtype=np.float64)
    x, y = int(np.ceil(rect[0])), int(np.ceil(rect[1]))
    for k in range(3):  # model, teacher, difference
        tile = px[y : y + viewer.SPHERE - 1, x + k * viewer.SPHERE : x + (k + 1) * viewer.SPHERE]
        disc = tile[64:192, 64:192]
        assert disc.std() > 5 and np.abs(disc - [33, 33, 38]).max(-1).mean() > 20, k
    meta = session.evaluate("document.getElementById('nb-meta').textContent")
    assert "Mitsuba's eval" in meta and "reciprocity error 0" in meta


def test_the_textured_sphere_is_onnxruntime_in_the_normal_fields_frame(opened, session, model):
    brdf = load(model)
    light = viewer.light_of(35, 30)  # one of the teacher's lights: not snapped away
    img = sphere_pixels(session, 0, light)
    _, _, _, inside = viewer.sphere_frames(viewer.SPHERE, light)
    assert np.array_equal(img[..., 3] == 1.0, inside)
    S = viewer.SPHERE
    expect = viewer.textured_radiance(float32_eval(brdf.eval), brdf.normal, S, light)
    peak = expect[inside].max()
    assert peak > 0 and (expect[inside].max(-1) > 1e-3 * peak).mean() > 0.3
    err = np.abs(img[..., :3] - expect)[inside].max() / peak
    assert err <= SPHERE_TOL, f"max |page - onnxruntime| = {err:.2e} of the peak"
    # the page reads the normal field and the texture: without the one, or with v
    # mirrored, the same comparison fails
    flat = viewer.textured_radiance(float32_eval(brdf.eval), None, S, light)
    assert np.abs(img[..., :3] - flat)[inside].max() / peak > 10 * SPHERE_TOL

    def mirrored(wi, wo, uv):
        return brdf.eval(wi, wo, uv * np.array([1.0, -1.0]))

    wrong = viewer.textured_radiance(float32_eval(mirrored), brdf.normal, S, light)
    assert np.abs(img[..., :3] - wrong)[inside].max() / peak > 10 * SPHERE_TOL


def test_the_teachers_panel_is_mitsubas_eval(opened, session, mitsuba_teacher):
    for theta, phi in (viewer.TEACHER_LIGHTS[0], viewer.TEACHER_LIGHTS[-1]):
        light = viewer.light_of(theta, phi)
        img = sphere_pixels(session, 1, light)
        expect = viewer.textured_radiance(
            mitsuba_teacher.eval, mitsuba_teacher.normal_field, viewer.SPHERE, light
        )
        _, _, _, inside = viewer.sphere_frames(viewer.SPHERE, light)
        assert np.array_equal(img[..., 3] == 1.0, inside)
        peak = expect[inside].max()
        assert peak > 0
        err = np.abs(img[..., :3] - expect)[inside].max() / peak
        assert err <= HALF_TOL, (theta, phi, err)


def test_the_light_snaps_to_the_teachers_lights(opened, session, model):
    asked = (58, 100)
    state = session.evaluate(f"nbViewer.setState({{thetaL: {asked[0]}, phiL: {asked[1]}}})")
    want = viewer.light_of(*asked)
    nearest = max(viewer.TEACHER_LIGHTS, key=lambda tp: float(viewer.light_of(*tp) @ want))
    assert nearest != asked and [state["thetaL"], state["phiL"]] == list(nearest)
    # the model is drawn at the snapped light: its panel is onnxruntime's there
    brdf = load(model)
    light = viewer.light_of(*nearest)
    expect = viewer.textured_radiance(float32_eval(brdf.eval), brdf.normal, viewer.SPHERE, light)
    shown = np.frombuffer(
        base64.b64decode(session.evaluate("nbViewer.shownRadiance(0)")), np.float32
    ).reshape(viewer.SPHERE, viewer.SPHERE, 4)  # as drawn by setState, not drawn again
    _, _, _, inside = viewer.sphere_frames(viewer.SPHERE, light)
    peak = expect[inside].max()
    assert np.abs(shown[..., :3] - expect)[inside].max() / peak <= SPHERE_TOL


def slice_values(session, state: dict) -> list[np.ndarray]:
    session.evaluate(f"nbViewer.setState({state!r})".replace("'", '"'))
    return [
        np.frombuffer(base64.b64decode(b), np.float32).reshape(viewer.SLICE_N, 3)
        for b in session.evaluate("nbViewer.sliceValues()")
    ]


def test_the_plots_are_at_the_chosen_point(opened, session, model, mitsuba_teacher):
    brdf = load(model)
    theta_i = 50
    wi, wo = viewer.slice_pairs(theta_i)
    cos = np.clip(wo[:, 2:3].astype(np.float64), 0.0, None)
    got = {}
    for probe in (1, 2):
        uv = np.broadcast_to(np.float32(viewer.PROBES[probe]), (len(wi), 2))
        mine, theirs = slice_values(session, {"thetaI": theta_i, "probe": probe})
        want_model = brdf.eval(wi, wo, uv) * cos
        want_teacher = mitsuba_teacher.eval(wi, wo, uv) * cos
        assert np.abs(mine - want_model).max() <= 1e-4 * want_model.max()
        assert np.abs(theirs - want_teacher).max() <= HALF_TOL * want_teacher.max()
        got[probe] = mine
    assert np.abs(got[1] - got[2]).max() > 1e-2 * got[1].max()  # uv reaches the shader


def lambertian_file(path: Path, albedo) -> Path:
    """A homogeneous file: the analytic Lambertian's graph with its fitted sampling lobe
    (the code generator needs one)."""
    import onnx
    from onnx import helper

    from neural_brdf.export import analytic_onnx
    from neural_brdf.fileformat import lobe as lobe_format
    from neural_brdf.physics import lobe_fit

    payload = analytic_onnx("lambertian", {"albedo": list(albedo)})
    proto = onnx.load_from_string(payload)
    lobe = lobe_format.to_json(lobe_fit.fit_onnx(payload))
    helper.set_model_props(proto, {lobe_format.KEY: lobe})
    path.write_bytes(proto.SerializeToString())
    return path


def test_a_textured_file_alone_with_its_own_points(model, session, tmp_path, capsys):
    out = tmp_path / "alone.html"
    code, _, err = cli(capsys, "view", str(model), "--uv", "0.3,0.7", "--uv=-1.5,2", "-o", str(out))
    assert code == 0, err
    session.open(out)
    assert session.evaluate("document.getElementById('nb-status').textContent") == "ready"
    assert session.errors == [] and session.evaluate("nbViewer.models.length") == 1
    assert session.evaluate("nbViewer.probes") == [[0.3, 0.7], [-1.5, 2.0]]
    assert session.evaluate("nbViewer.lights") is None  # no teacher: the light is free
    state = session.evaluate("nbViewer.setState({thetaL: 58, phiL: 100, probe: 1})")
    assert (state["thetaL"], state["phiL"]) == (58, 100)
    brdf = load(model)
    wi, wo = viewer.slice_pairs(state["thetaI"])
    (mine,) = slice_values(session, {})
    uv = np.broadcast_to(np.float32([-1.5, 2.0]), (len(wi), 2))
    want = brdf.eval(wi, wo, uv) * np.clip(wo[:, 2:3].astype(np.float64), 0.0, None)
    assert np.abs(mine - want).max() <= 1e-4 * want.max()


@pytest.mark.parametrize("textured", [False, True])
def test_a_homogeneous_teacher(textured, model, session, tmp_path, capsys):
    """Mitsuba's ``diffuse`` beside a homogeneous Lambertian file of the same albedo (the
    panels agree), or beside the textured file (the teacher's panel is the Lambertian's
    on the textured page: its teacher ignores uv and has no normal map)."""
    albedo = [0.6, 0.4, 0.2]
    onnx_path = model if textured else lambertian_file(tmp_path / "lambert.onnx", albedo)
    xml = tmp_path / "diffuse.xml"
    xml.write_text(
        '<bsdf version="3.0.0" type="diffuse"><rgb name="reflectance" '
        f'value="{", ".join(map(str, albedo))}"/></bsdf>'
    )
    out = tmp_path / "v.html"
    code, _, err = cli(capsys, "view", str(onnx_path), "--compare", str(xml), "-o", str(out))
    assert code == 0, err
    session.open(out)
    assert session.evaluate("document.getElementById('nb-status').textContent") == "ready"
    assert session.errors == []
    light = viewer.light_of(*viewer.TEACHER_LIGHTS[1])
    wi, _, inside = viewer.sphere_directions(viewer.SPHERE, light)
    expect = np.asarray(albedo) * np.clip(wi[..., 2:3], 0.0, None)  # pi * (albedo / pi) cos
    for k in (1,) if textured else (0, 1):
        img = sphere_pixels(session, k, light)
        assert np.abs(img[..., :3] - expect)[inside].max() <= HALF_TOL * expect.max(), k


def test_the_report_carries_the_textured_viewer(run, session):
    report = (run / "report.html").read_text()
    assert "beside its Mitsuba teacher" in report and "No viewer" not in report
    session.open(run / "viewer.html")
    assert session.evaluate("document.getElementById('nb-status').textContent") == "ready"
    assert session.errors == []
    names = session.evaluate("nbViewer.models")
    assert names[0] == "neural" and names[1].startswith("teacher: ")


@pytest.mark.parametrize(
    "case, needle",
    [
        ("textured_vs_homogeneous", "a homogeneous (wi, wo) model beside a textured"),
        ("homogeneous_vs_textured_teacher", "a textured teacher"),
        ("textured_vs_analytic_config", "target.model"),
        ("bad_uv", "--uv 0.5"),
        ("uv_of_homogeneous", "not a textured model"),
    ],
)
def test_bad_combinations_exit_2_with_one_line(case, needle, model, teacher, tmp_path, capsys):
    plain = lambertian_file(tmp_path / "plain.onnx", [0.5, 0.5, 0.5])
    cfg = tmp_path / "analytic.yaml"
    cfg.write_text("target:\n  model: lambertian\n")
    out = str(tmp_path / "v.html")
    args = {
        "textured_vs_homogeneous": [str(model), "--compare", str(plain)],
        "homogeneous_vs_textured_teacher": [str(plain), "--compare", str(teacher)],
        "textured_vs_analytic_config": [str(model), "--compare", str(cfg)],
        "bad_uv": [str(model), "--uv", "0.5"],
        "uv_of_homogeneous": [str(plain), "--uv", "0.5,0.5"],
    }[case]
    code, _, err = cli(capsys, "view", *args, "-o", out)
    assert_one_line_error(code, err, needle)
    assert not Path(out).exists()
