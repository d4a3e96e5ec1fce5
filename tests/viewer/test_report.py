"""Run reports: the figures' data, the files, and the page as headless Chromium shows it.

The page checks use Debian's chromium (CI installs it); they never skip.  The report
under test is the one training writes at the end of a tiny run, Mitsuba render included
where Mitsuba is installed (CI installs it too).  A Mitsuba teacher's run (a tiny one of
a homogeneous teacher) is checked for its render beside the teacher, its captions and
its resolved config (at the end).
"""

from __future__ import annotations

import base64
import io
import json
import math
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from PIL import Image

import analytic
from cli_helpers import ROOT, SETS, TINY, assert_one_line_error, cli
from harness import browser, gpu_browser
from neural_brdf import config
from neural_brdf.tooling.cli import main
from neural_brdf.viewer import plots, report

GOLD = ROOT / "configs" / "gold.yaml"
FIGURES = {"albedo", "slices", "lobes", "rusinkiewicz", "loss"}  # always drawn


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("report") / "gold"
    code = main(
        [
            "train",
            str(GOLD),
            "--out",
            str(run_dir),
            *SETS,
            "--set",
            "train.steps=60",
            "--set",
            "train.log_every=10",
            "--set",
            "train.eval_every=30",
            "--set",
            "train.threads=1",
        ]
    )
    assert code == 0
    return run_dir


def expected_figures() -> set[str]:
    return FIGURES | ({"render"} if plots.mitsuba_unavailable() is None else set())


class _Images(HTMLParser):
    def __init__(self, page: str):
        super().__init__()
        self.images, self.tags = [], set()
        self.feed(page)

    def handle_starttag(self, tag, attrs):
        self.tags.add(tag)
        if tag == "img":
            self.images.append(dict(attrs))


def decode(png: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(png)) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB"), dtype=np.float64)


def assert_not_blank(pixels: np.ndarray, what: str, *, min_colours: int = 16) -> None:
    assert pixels.size > 0, what
    assert pixels.std() > 10.0, f"{what}: nearly uniform (std {pixels.std():.1f})"
    colours = len(np.unique(pixels.reshape(-1, 3), axis=0))
    assert colours >= min_colours, f"{what}: only {colours} distinct colours"


def data_uri_pngs(page: str) -> dict[str, bytes]:
    out = {}
    for img in _Images(page).images:
        src = img["src"]
        assert src.startswith("data:image/png;base64,"), src[:60]
        out[img["alt"]] = base64.b64decode(src.split(",", 1)[1], validate=True)
    return out


# ------------------------------------------------------------------ the report of a run
def test_training_writes_the_report(tiny_run):
    assert (tiny_run / "report.html").is_file() and (tiny_run / "report.md").is_file()
    seconds = json.loads((tiny_run / "metrics.json").read_text())["seconds"]
    assert seconds["report"] > 0
    parts = seconds["train"] + seconds["export"] + seconds["validate"] + seconds["report"]
    assert seconds["total"] >= parts
    # an analytic target's accuracy pairs are drawn apart from training's
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    assert metrics["accuracy"]["pairs_from"] == "sampled"
    said = f"on {metrics['accuracy']['pairs']} held-out pairs"
    assert said in (tiny_run / "report.md").read_text()


def test_html_is_self_contained_and_every_image_is_a_drawn_png(tiny_run):
    page = (tiny_run / "report.html").read_text()
    parsed = _Images(page)
    assert not parsed.tags & {"script", "link", "iframe", "object"}
    assert not re.search(r'(src|href)="(?!data:)', page)  # no external asset
    images = data_uri_pngs(page)
    assert len(images) == len(parsed.images) == len(expected_figures())
    for alt, png in images.items():
        assert_not_blank(decode(png), alt)
    for text in (
        "Physics checks",
        "reciprocity",
        "max_albedo",
        "rel. RMSE",
        "Config",
        "name: gold",
    ):
        assert text in page
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    for band, v in metrics["accuracy"]["rel_rmse_by_incidence"].items():
        shown = "-" if v is None else f"{100 * v:.3f} %"
        # (a cell with a number and its unit does not wrap: class nw)
        td = '<td class="nw">' if v is not None else "<td>"
        assert f"<td>rel. RMSE, {band}</td>{td}{shown}</td>" in page
    if plots.mitsuba_unavailable() is not None:
        assert "No render: Mitsuba 3 is not available" in page


def test_markdown_links_the_same_pngs_as_the_html(tiny_run):
    md = (tiny_run / "report.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert sorted(links) == sorted(report.image_name(k) for k in expected_figures())
    files = {(tiny_run / name).read_bytes() for name in links}
    assert files == set(data_uri_pngs((tiny_run / "report.html").read_text()).values())
    assert "| reciprocity |" in md and "**ok**" in md


@pytest.mark.slow
def test_the_page_in_headless_chromium(tiny_run, tmp_path):
    shot = tmp_path / "screenshot.png"
    seen = browser.screenshot(tiny_run / "report.html", shot)
    page_pngs = data_uri_pngs((tiny_run / "report.html").read_text())
    # every image decoded by the browser, at the size of the PNG we wrote
    assert len(seen["images"]) == len(page_pngs)
    for img in seen["images"]:
        assert img["complete"] and img["width"] > 0 and img["height"] > 0, img
        assert img["width"] == decode(page_pngs[img["alt"]]).shape[1], img
    assert seen["text"] > 2000  # tables and the config are there
    assert 3000 < seen["height"] < browser.MAX_HEIGHT  # figures stack up, nothing collapsed
    pixels = decode(shot.read_bytes())
    assert pixels.shape[:2] == (seen["height"], browser.WIDTH)
    assert_not_blank(pixels, "screenshot", min_colours=500)
    assert (pixels.min(-1) < 200).mean() > 0.05  # ink, not a white page


def test_the_browser_probe_catches_a_broken_image(tiny_run, tmp_path):
    page = (tiny_run / "report.html").read_text()
    start = page.index("data:image/png;base64,") + len("data:image/png;base64,")
    broken = tmp_path / "broken.html"
    broken.write_text(page[:start] + "iVBORw0KGgoAAAAgarbage" + page[start + 4000 :])
    widths = [img["width"] for img in browser.inspect(broken)["images"]]
    assert widths[0] == 0 and all(w > 0 for w in widths[1:])


def test_report_cli_writes_elsewhere_and_says_when_it_cannot_render(
    tiny_run, tmp_path, capsys, monkeypatch
):
    monkeypatch.setattr(plots, "mitsuba_unavailable", lambda: "Mitsuba 3 is switched off")
    out = tmp_path / "elsewhere"
    assert main(["report", str(tiny_run), "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert str(out / "report.html") in said
    # every file it wrote is named: a viewer.html of the folder's is replaced
    written = sorted(p.name for p in out.iterdir() if p.name not in ("report.html", "report.md"))
    assert "viewer.html" in written and said.rstrip().endswith(", ".join(written)), said
    page = (out / "report.html").read_text()
    assert "No render: Mitsuba 3 is switched off" in page
    assert set(data_uri_pngs(page)) == {
        "Directional albedo (white furnace)",
        "Incidence-plane slices",
        "Polar lobes",
        "(θh, θd) slice",
        "Training curve",
    }
    assert not list(out.glob(".*"))  # no temp file left behind


def test_a_target_without_reference_gets_a_note(tiny_run, tmp_path):
    run_dir = copy_run(tiny_run, tmp_path)
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    cfg["target"] = {"data": str(tmp_path / "missing.binary")}
    (run_dir / "config.yaml").write_text(yaml.safe_dump(cfg))
    paths = report.write_report(run_dir, render=False)
    page = paths["html"].read_text()
    assert "No reference: the measured target" in page and "missing.binary" in page
    assert "reference (dashed)" not in page
    assert set(FIGURES) <= set(paths)


@pytest.mark.parametrize(
    "where, key, said",
    [
        # the albedo bound's nodes estimated again (normalization.refine)
        (("export", "normalization"), "refined_nodes", "3 estimated again with more points"),
        # the furnace's directions measured again (validation.furnace_refine)
        (("checks", "max_albedo"), "remeasured", "3 directions over the limit measured again"),
    ],
)
def test_the_physics_says_how_many_figures_it_measured_again(tiny_run, tmp_path, where, key, said):
    run_dir = copy_run(tiny_run, tmp_path)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    entry = metrics[where[0]][where[1]]
    assert key in entry  # the run records the count, 0 or more
    for count in (3, 0):
        entry[key] = count
        (run_dir / "metrics.json").write_text(json.dumps(metrics))
        page = report.write_report(run_dir, render=False)["html"].read_text()
        assert (said in page) is (count == 3)
        assert "table nodes needed scaling" in page


def copy_run(run_dir, tmp_path):
    dst = tmp_path / "copy"
    dst.mkdir()
    for name in report.RUN_FILES:
        shutil.copy(run_dir / name, dst / name)
    return dst


@pytest.mark.parametrize(
    "name, damage, needle",
    [
        (None, None, "no such run directory"),
        ("metrics.json", "{", "not valid JSON"),
        ("metrics.json", '{"checks": {}}', "checks: expected an object of the checks, got an"),
        # (a checks that is there but no object was said to be missing)
        ("metrics.json", '{"checks": 5}', "checks: expected an object of the checks, got int"),
        ("metrics.json", '{"passed": true}', "checks: missing"),
        ("metrics.json", "[1, 2]", "not a JSON object"),
        (
            "metrics.json",
            '{"checks": {"reciprocity": {"value": "x", "limit": 0, "passed": true}}}',
            "checks.reciprocity.value: not a number",
        ),
        (
            "metrics.json",
            '{"checks": {"reciprocity": {"value": 0, "limit": 0, "passed": true}}, '
            '"hemispherical_albedo": [0.5, "x", 0.5]}',
            "hemispherical_albedo.1: not a number",
        ),
        ("log.csv", "step,loss\n10,abc\n", "line 2: not a number"),
        ("log.csv", "a,b\n1,2\n", "expected a CSV"),
        ("config.yaml", "train: {stepz: 3}\n", "train.stepz"),
        ("model.onnx", b"\x00garbage", "not a loadable ONNX model"),
        ("model.onnx", None, "missing"),
    ],
)
def test_bad_run_dir_is_one_line_and_exit_2(tiny_run, tmp_path, capsys, name, damage, needle):
    run_dir = copy_run(tiny_run, tmp_path)
    if name is None:
        run_dir = tmp_path / "nope"
    elif damage is None:
        (run_dir / name).unlink()
    elif isinstance(damage, bytes):
        (run_dir / name).write_bytes(damage)
    else:
        (run_dir / name).write_text(damage)
    code = main(["report", str(run_dir)])
    err = capsys.readouterr().err
    assert_one_line_error(code, err, needle, name or "nope")
    assert not (run_dir / "report.html").exists()


PHONE = (390, 844)  # a phone's page width and height, CSS pixels


def test_the_page_fits_a_phone(tmp_path):
    from neural_brdf.viewer.report.blocks import Heading, Table, Text, to_html

    wide = Table(  # as wide as the peak table of an anisotropic model, or wider
        ["θi", "φi", "towards"] + [f"{o:g}°" for o in (0, 0.01, 0.03, 0.1, 0.3, 1)],
        [["45°", "90°", "horizon"] + ["1.53 %"] * 6] * 4,
    )
    page = to_html([Heading("report", 1), Text("At the peak: 0.18 % (limit 3 %)."), wide])
    assert '<meta name="viewport" content="width=device-width, initial-scale=1">' in page
    path = tmp_path / "report.html"
    path.write_text(page)
    with gpu_browser.Session(width=PHONE[0], height=PHONE[1]) as s:
        s.open(path)
        page_width, table_box = s.evaluate(
            "(() => { const t = document.querySelector('table').parentElement;"
            " return [document.documentElement.scrollWidth,"
            " [t.clientWidth, t.scrollWidth, getComputedStyle(t).overflowX]]; })()"
        )
        cell = s.evaluate(  # the lines its text takes
            "(() => { const c = document.querySelectorAll('td')[3], r = document.createRange();"
            " r.selectNodeContents(c); const tops = new Set([...r.getClientRects()]"
            ".map((b) => Math.round(b.top))); return [tops.size, c.textContent]; })()"
        )
    assert page_width <= PHONE[0]  # the page is not widened by the table
    assert table_box[2] == "auto" and table_box[1] > table_box[0]  # it scrolls in its box
    assert cell == [1, "1.53 %"]  # a number keeps its unit on its line


# ------------------------------------------------------------------ the plots' data
GGX = analytic.create(
    "microfacet", distribution="ggx", alpha=0.25, fresnel="conductor", material="Au"
)
GGX_REF = analytic.create(
    "microfacet", distribution="ggx", alpha=0.3, fresnel="conductor", material="Au"
)
LAMBERT = analytic.create("lambertian", albedo=[0.8, 0.6, 0.4])


def lines(fig, prefix: str) -> list:
    return [ln for ax in fig.axes for ln in ax.lines if ln.get_label().startswith(prefix)]


@pytest.mark.parametrize(
    "draw",
    [
        lambda: plots.incidence_slices(GGX.eval, GGX_REF.eval),
        lambda: plots.polar_lobes(GGX.eval, GGX_REF.eval),
        lambda: plots.rusinkiewicz_images(GGX.eval, GGX_REF.eval, n=48),
        lambda: plots.albedo_curve(GGX.eval, GGX_REF.eval, n_theta=10, samples=1024),
        lambda: plots.incidence_slices(GGX.eval),
        lambda: plots.rusinkiewicz_images(GGX.eval, n=48),
        lambda: plots.loss_curve(
            np.arange(1, 11), np.geomspace(1, 1e-3, 10), np.array([5, 10]), np.array([0.03, 0.01])
        ),
    ],
    ids=["slices", "lobes", "rusinkiewicz", "albedo", "slices-alone", "rusinkiewicz-alone", "loss"],
)
def test_each_plot_draws_something(draw):
    fig = draw()
    data = [ln.get_ydata() for ax in fig.axes for ln in ax.lines] + [
        np.ma.filled(im.get_array(), np.nan) for ax in fig.axes for im in ax.images
    ]
    assert any(np.isfinite(np.asarray(d, dtype=float)).sum() > 5 for d in data)
    assert_not_blank(decode(plots.png_bytes(fig)), "figure")


def test_albedo_curve_plots_the_known_albedo():
    fig = plots.albedo_curve(
        LAMBERT.eval, analytic.create("lambertian", albedo=0.5).eval, n_theta=8, samples=16384
    )
    # quadrature noise at 16384 points: 4e-4 measured
    for ln, expected in zip(lines(fig, "neural"), (0.8, 0.6, 0.4)):
        np.testing.assert_allclose(ln.get_ydata(), expected, atol=1.5e-3)
    for ln in lines(fig, "reference"):
        np.testing.assert_allclose(ln.get_ydata(), 0.5, atol=1.5e-3)
    assert len(lines(fig, "neural")) == len(lines(fig, "reference")) == 3
    (furnace,) = lines(fig, "furnace")
    assert np.all(np.asarray(furnace.get_ydata()) == 1.0)


def test_albedo_curve_shows_a_model_above_the_furnace_limit():
    bright = analytic.create("lambertian", albedo=1.0)
    fig = plots.albedo_curve(lambda a, b: 1.25 * bright.eval(a, b), n_theta=6, samples=16384)
    for ln in lines(fig, "neural"):
        np.testing.assert_allclose(ln.get_ydata(), 1.25, atol=2e-3)
    assert fig.axes[0].get_ylim()[1] > 1.25  # drawn, not cut off


BRUSHED = analytic.create(
    "microfacet", distribution="ggx", alpha_x=0.15, alpha_y=0.45, fresnel="conductor", material="Al"
)


def rotated(fn, phi: float):
    """``fn`` turned by ``phi`` about the normal: its incidence plane is fn's plane at
    azimuth phi."""
    c, s = math.cos(phi), math.sin(phi)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return lambda wi, wo: fn(wi @ rot.T, wo @ rot.T)


def test_an_anisotropic_albedo_figure_averages_both_curves_over_azimuth():
    theta, azimuths, samples = np.array([0.0, 50.0, 80.0]), 16, 8192
    # the validator's curve of an anisotropic model: averaged over azimuth, computed here
    # as the mean of in-plane curves of the BRDF turned about the normal
    averaged = np.mean(
        [
            plots.albedo_values(rotated(BRUSHED.eval, (k + 0.5) * 2 * math.pi / azimuths), theta)
            for k in range(azimuths)
        ],
        0,
    )
    in_plane = plots.albedo_values(BRUSHED.eval, theta)
    assert abs(in_plane[-1] - averaged[-1]).max() > 0.03  # the figure's former false gap
    fig = plots.albedo_curve(
        BRUSHED.eval,
        BRUSHED.eval,
        samples=samples,
        measured=(theta, averaged),
        azimuths=azimuths,
    )
    for neural, reference in zip(lines(fig, "neural"), lines(fig, "reference"), strict=True):
        np.testing.assert_allclose(reference.get_xdata(), neural.get_xdata())
        np.testing.assert_allclose(reference.get_ydata(), neural.get_ydata(), atol=5e-3)


@pytest.mark.parametrize("azimuths", [16, 0])
def test_the_albedo_caption_says_how_both_curves_were_measured(azimuths):
    from neural_brdf.viewer.report import sections
    from neural_brdf.viewer.report.blocks import Image as Figure

    run = SimpleNamespace(
        dir=Path("run"),
        config=config.from_dict({}),
        metrics={"checks": {"reciprocity": {"value": 0.0, "limit": 1e-6, "passed": True}}},
        model=SimpleNamespace(textured=False),
    )
    blocks = sections._physics(run, b"", True, azimuths)
    (figure,) = [b for b in blocks if isinstance(b, Figure) and b.key == "albedo"]
    averaged = f"both curves averaged over {azimuths} azimuths of wi" in figure.caption
    assert averaged is (azimuths > 0)
    assert ("incidence plane" in figure.caption) is (azimuths == 0)
    assert "the reference's by the same quadrature" in figure.caption


def test_the_albedo_legend_is_beside_the_axes_covering_no_curve():
    # a measured material's albedo falls towards grazing into the lower-left corner
    falling = analytic.create("lambertian", albedo=0.3)
    fig = plots.albedo_curve(falling.eval, LAMBERT.eval, n_theta=6, samples=2048)
    fig.canvas.draw()
    (ax,) = fig.axes
    legend = (ax.get_legend() or fig.legends[0]).get_window_extent()
    assert not legend.overlaps(ax.get_window_extent())


def test_slices_plot_f_cos_in_the_incidence_plane():
    fig = plots.incidence_slices(LAMBERT.eval, theta_i_deg=(0.0, 60.0))
    neural = lines(fig, "neural")
    assert len(neural) == 6  # 3 channels x 2 panels
    for ln, albedo in zip(neural, [0.8, 0.6, 0.4] * 2):
        x, y = np.asarray(ln.get_xdata()), np.asarray(ln.get_ydata())
        np.testing.assert_allclose(y, albedo / math.pi * np.cos(np.radians(x)), rtol=1e-6)


def test_rusinkiewicz_images_show_the_relative_error():
    fig = plots.rusinkiewicz_images(lambda a, b: 1.1 * LAMBERT.eval(a, b), LAMBERT.eval, n=32)
    neural, reference, error = (ax.images[0].get_array() for ax in fig.axes if ax.images)
    np.testing.assert_allclose(error, 0.1, rtol=1e-6)
    luminance = 0.2126 * 0.8 + 0.7152 * 0.6 + 0.0722 * 0.4  # Rec. 709
    np.testing.assert_allclose(reference, math.log10(luminance / math.pi), rtol=1e-6)
    np.testing.assert_allclose(neural - reference, math.log10(1.1), rtol=1e-6)


def test_rusinkiewicz_grid_round_trips_through_the_angles():
    import torch

    wi, wo = plots.rusinkiewicz_grid(16)
    th, _, td, pd = analytic.frame.rusinkiewicz(torch.from_numpy(wi), torch.from_numpy(wo))
    a = (np.arange(16) + 0.5) * (0.5 * math.pi / 16)
    np.testing.assert_allclose(th.numpy(), np.broadcast_to(a, (16, 16)), atol=1e-9)
    np.testing.assert_allclose(td.numpy(), np.broadcast_to(a[:, None], (16, 16)), atol=1e-9)
    np.testing.assert_allclose(pd.numpy(), math.pi / 2, atol=1e-9)


# ------------------------------------------------------------------ a Mitsuba teacher's run
# The render section of a HOMOGENEOUS teacher's run shows the teacher, rendered by
# Mitsuba, beside the model (it showed the model alone): its panel is checked against
# Mitsuba's own render of the teacher's XML in the same scene, to the PNG's rounding.  A
# textured file's caption says the teacher's normal (or bump) map is left out only when
# the teacher has one, that it is included when the file carries the normal field, and
# nothing of a map when there is none (``_rendering`` with the render itself replaced).
# The resolved config.yaml of a teacher's run holds no analytic target.model / params (it
# showed ``model: lambertian``, an unused default); the run still resumes, reports and
# exports, and an analytic run's config keeps them.
XML = ROOT / "configs" / "mitsuba" / "roughplastic.xml"  # a blue rough plastic, twosided
QUANTUM = 1.0 / 255.0  # a PNG's 8-bit rounding


@pytest.fixture(scope="module")
def mi():  # (Mitsuba's variant before the renderer's module is imported)
    import mitsuba

    if mitsuba.variant() is None:
        mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


@pytest.fixture(scope="module")
def teacher_run(mi, tmp_path_factory) -> tuple[Path, Path]:
    """(run folder, config) of a tiny run of a homogeneous Mitsuba teacher (report
    written)."""
    folder = tmp_path_factory.mktemp("teacher_run")
    shutil.copy(XML, folder / "teacher.xml")
    cfg = folder / "plastic.yaml"
    cfg.write_text("target: {mitsuba: teacher.xml}\n")
    run = folder / "run"
    assert main(["train", str(cfg), "--out", str(run), *SETS]) in (0, 1)  # 1: a check failed
    assert (run / "report.md").is_file()
    return run, cfg


def render_caption(run: Path) -> str:
    (line,) = [ln for ln in (run / "report.md").read_text().splitlines() if "preview" in ln]
    return line


@pytest.mark.mitsuba
def test_the_report_renders_a_homogeneous_teacher_beside_the_model(mi, teacher_run):
    import matplotlib.image as mpimg

    from neural_brdf.renderers import render as nbr
    from neural_brdf.viewer.report.run import RENDER_RESOLUTION as RES
    from neural_brdf.viewer.report.run import RENDER_SPP

    run, _ = teacher_run
    caption = render_caption(run)
    assert "the teacher (Mitsuba's own BSDF)" in caption and "PSNR" in caption
    assert "normal map" not in caption  # a homogeneous teacher has none
    img = mpimg.imread(run / "report-render.png")[..., :3].astype(np.float64)
    strip = img.shape[0] - RES
    gap = (img.shape[1] - 3 * RES) // 2
    assert gap >= 2, img.shape  # three panels: neural | teacher | difference
    neural, target = (img[strip:, i * (RES + gap) : i * (RES + gap) + RES] for i in range(2))
    scene = nbr.render_scene(mi.load_file(str(XML)), resolution=RES, spp=RENDER_SPP)
    teacher = nbr.to_display(scene)
    assert np.abs(target - teacher).max() <= 2 * QUANTUM
    assert np.abs(neural - teacher).mean() > 10 * QUANTUM  # the tiny model is not the teacher


@pytest.mark.mitsuba
def test_a_teacher_runs_config_has_no_analytic_target(teacher_run, tiny_run):
    run, cfg = teacher_run
    target = yaml.safe_load((run / "config.yaml").read_text())["target"]
    assert "model" not in target and "params" not in target, target
    assert target["mitsuba"] == str((cfg.parent / "teacher.xml").resolve())
    # read back, it is the config the run trained (the dropped keys at their defaults)
    again = config.load(run / "config.yaml", run=True)
    assert again.model_dump() == config.load(cfg, TINY).model_dump()
    # an analytic run keeps its model and parameters
    analytic = yaml.safe_load((tiny_run / "config.yaml").read_text())["target"]
    assert analytic["model"] == config.load(tiny_run / "config.yaml").target.model


@pytest.mark.mitsuba
def test_a_teacher_run_still_resumes_reports_and_exports(capsys, teacher_run, tmp_path):
    run, cfg = teacher_run
    code, out, err = cli(capsys, "train", str(cfg), "--out", str(run), "--resume", *SETS)
    assert code == 0 and "already finished" in out, err
    code, out, err = cli(capsys, "report", str(run), "-o", str(tmp_path / "again"))
    assert code == 0, err
    assert "the teacher (Mitsuba's own BSDF)" in render_caption(tmp_path / "again")
    code, out, err = cli(capsys, "export", str(run), "-o", str(tmp_path / "again.onnx"))
    assert code in (0, 1) and (tmp_path / "again.onnx").is_file(), err


# ------------------------------------------------------------------ the textured caption
@pytest.fixture(scope="module")
def teachers(mi, tmp_path_factory) -> dict:
    """Textured teachers: the procedural roughplastic (no normal map) and principled (a
    normal map), 8 x 8 texels."""
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    folder = tmp_path_factory.mktemp("textured")
    return {
        kind: TexturedMitsubaTarget(write_teacher(folder / kind, kind, size=8))
        for kind in ("roughplastic", "principled")
    }


def rendering(monkeypatch, tmp_path, reference, *, normal_field: bool):
    """The report's render section of a textured file (with or without the teacher's
    normal field) beside ``reference``, the render itself replaced: (caption, the BSDF
    object handed to the render)."""
    from neural_brdf.viewer import plots
    from neural_brdf.viewer.report import sections

    handed = {}

    def spheres(model_path, out_png, *, reference_bsdf=None, **kwargs):
        import matplotlib.image as mpimg

        handed["bsdf"] = reference_bsdf
        mpimg.imsave(out_png, np.zeros((4, 12, 3)))
        return 30.0

    monkeypatch.setattr(plots, "spheres", spheres)
    run = SimpleNamespace(
        config=config.from_dict({"target": {"mitsuba": str(reference.path)}}),
        model=SimpleNamespace(textured=True, has_normal_field=normal_field),
        dir=tmp_path,
    )
    blocks = sections._rendering(run, True, reference)
    (image,) = [b for b in blocks if hasattr(b, "caption")]
    return image.caption, handed["bsdf"]


@pytest.mark.mitsuba
def test_a_teacher_without_a_normal_map_is_not_said_to_have_one(monkeypatch, tmp_path, teachers):
    teacher = teachers["roughplastic"]
    assert teacher.normal_map is None  # the case
    caption, bsdf = rendering(monkeypatch, tmp_path, teacher, normal_field=False)
    assert "the teacher (Mitsuba's own BSDF)" in caption and "map" not in caption, caption
    assert bsdf is teacher.bsdf


@pytest.mark.mitsuba
def test_a_teacher_with_a_normal_map_says_whether_it_is_shown(monkeypatch, tmp_path, teachers):
    teacher = teachers["principled"]
    assert teacher.normal_map is not None  # the case
    caption, bsdf = rendering(monkeypatch, tmp_path, teacher, normal_field=False)
    assert "its normal map left out as the file's is" in caption, caption
    assert bsdf is teacher.bsdf  # the nested BSDF, as the file has no normal field
    caption, bsdf = rendering(monkeypatch, tmp_path, teacher, normal_field=True)
    assert "normal map included" in caption and "left out" not in caption, caption
    assert bsdf is teacher.whole_bsdf
