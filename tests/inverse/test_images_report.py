"""The report and the export of an images fit (issue 29, item 5): an images run is
described as what it is, never against the default ``target.model`` (a Lambertian).

* ``neural-brdf report`` of an images run: an "Images fit" section with the views (scene
  and image names, film sizes from the images' headers), the fit's figures, its losses
  from log.csv, the coverage figure, its warning and the ``coverage.png`` map embedded;
  no accuracy, peak or render against a target, and no "lambertian" outside the config;
  without a coverage figure in metrics.json it says so;
* ``neural-brdf export`` of an images run's checkpoint writes ``{"kind": "images",
  "views": N}`` into the metadata, measured with no reference;
* ``neural-brdf train`` of an images config writes the report and its last line names
  report.html; a run that writes no report does not name one.

The images run folder is made as a fit and :func:`neural_brdf.pipeline.finish` leave it,
without a fit: the shared tiny run's checkpoint (conftest.tiny_run) becomes the network,
``pipeline.finish`` exports and validates it with no target (as for a fit), and
config.yaml, log.csv, coverage.png and the views' EXR headers are written here.  Only
the last test (marked mitsuba) computes a real coverage figure; the rest need no Mitsuba
and render nothing.
"""

from __future__ import annotations

import base64
import html
import json
import re
import shutil
import struct
import time
from pathlib import Path

import pytest
import yaml

from neural_brdf import config, export, pipeline, validate
from neural_brdf.fileformat import reader
from neural_brdf.tooling.cli import main
from neural_brdf.train.session import LOG_COLUMNS, load_checkpoint
from neural_brdf.viewer import plots, report

FILM = (24, 16)  # width, height of the views' films (their EXR data windows)
VIEWS = 3
COVERAGE_ALT = "Coverage of the (θh, θd) domain"


# ------------------------------------------------------------------ an images run, by hand
def exr_header(width: int, height: int) -> bytes:
    """The header of a scanline OpenEXR file of this size: what ``exr_size`` reads (the
    pixels are not needed for it)."""

    def attr(name: str, kind: str, value: bytes) -> bytes:
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    channels = b"".join(c + b"\0" + struct.pack("<i4xii", 2, 1, 1) for c in (b"B", b"G", b"R"))
    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    return (
        b"\x76\x2f\x31\x01"
        + struct.pack("<i", 2)
        + attr("channels", "chlist", channels + b"\0")
        + attr("compression", "compression", b"\0")
        + attr("dataWindow", "box2i", box)
        + attr("displayWindow", "box2i", box)
        + attr("lineOrder", "lineOrder", b"\0")
        + attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
        + b"\0"
    )


def images_config(tiny_run: Path, views: Path) -> config.Config:
    """The tiny run's config with ``target.images`` (VIEWS views in ``views``) instead of
    its Lambertian: the default target.model stays ``lambertian`` in the resolved config."""
    raw = yaml.safe_load((tiny_run / "config.yaml").read_text())
    raw["name"] = "copper-fit"
    raw["target"] = {
        "images": [
            {"scene": str(views / f"view{k}.xml"), "image": str(views / f"view{k}.exr")}
            for k in range(1, VIEWS + 1)
        ]
    }
    cfg = config.from_dict(raw)
    assert cfg.target.images is not None and cfg.target.model == "lambertian"
    return cfg


def write_views(views: Path) -> None:
    views.mkdir(parents=True, exist_ok=True)
    for k in range(1, VIEWS + 1):
        (views / f"view{k}.xml").write_text('<scene version="3.0.0"/>\n')
        (views / f"view{k}.exr").write_bytes(exr_header(*FILM))


def coverage_summary(views: Path, figure: float = 0.005) -> dict:
    """A coverage summary as neural_brdf.inverse.coverage.summary writes it (the keys the
    report reads): a thin one, a flash capture's."""
    return {
        "figure": figure,
        "definition": "share of the (wi, wo) domain with both cosines > 0.1 (...)",
        "bins": [32, 32],
        "min_cos": 0.1,
        "threshold": 0.05,
        "warn_below": 0.25,
        "theta_d_observed_deg": [0.0, 2.8125],
        "theta_d_rows_observed": 1,
        "bins_mixed_per_pixel": 2.5,
        "per_view": [
            {
                "scene": str(views / f"view{k}.xml"),
                "figure": figure,
                "pixels": FILM[0] * FILM[1],
                "pixels_lit": 200 + k,
            }
            for k in range(1, VIEWS + 1)
        ],
        "picture": "coverage.png",
    }


def training_figures(views: Path, *, with_coverage: bool = True) -> dict:
    """metrics.json's ``training`` of an images fit (neural_brdf.inverse.fit)."""
    names = ", ".join(f"view{k}.exr" for k in range(1, VIEWS + 1))
    out = {
        "steps": 10,
        "device": "llvm_ad_rgb",
        "train_seconds": 1.5,
        "render_seconds": 1.0,
        "final_loss": 0.0213,
        "final_image_loss": 0.0211,
        "final_albedo_penalty": 0.0002,
        "final_max_albedo_estimate": 0.93,
        "spp_per_step": 8,
        "primal_spp_per_step": 32,
        "views": VIEWS,
        "init": None,
        "target": f"{VIEWS} images ({names}) by inverse rendering",
    }
    if with_coverage:
        out["coverage"] = coverage_summary(views)
    return out


def write_log(run_dir: Path, extra: tuple[str, ...] = ()) -> None:
    """log.csv as the fit's session writes it: LOG_COLUMNS (no held-out BRDF error) and
    the loop's own columns, here sparse like a held-out loss."""
    lines = [",".join((*LOG_COLUMNS, *extra))]
    for step in range(1, 11):
        row = [str(step), f"{0.5 / step:.6f}", "0.01", f"{0.1 * step:.2f}", ""]
        row += [f"{0.6 / step:.6f}" if step % 5 == 0 else "" for _ in extra]
        lines.append(",".join(row))
    (run_dir / "log.csv").write_text("\n".join(lines) + "\n")


def png_of(text: str) -> bytes:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 2))
    ax = fig.subplots()
    ax.imshow([[0.0, 1.0], [0.5, 0.2]])
    ax.set_title(text)
    return plots.png_bytes(fig)


def make_images_run(
    tiny_run: Path,
    folder: Path,
    *,
    with_coverage: bool = True,
    report_too: bool = False,
    extra: dict | None = None,
) -> Path:
    """An images run folder, as fit + pipeline.finish leave it (without the fit)."""
    views, run_dir = folder / "views", folder / "run"
    write_views(views)
    run_dir.mkdir(parents=True)
    cfg = images_config(tiny_run, views)
    (run_dir / "config.yaml").write_text(cfg.to_yaml())
    shutil.copy(tiny_run / "ckpt.pt", run_dir / "ckpt.pt")
    write_log(run_dir, extra=("heldout_loss",))
    if with_coverage:
        (run_dir / "coverage.png").write_bytes(png_of("coverage"))
    raw = export.raw_from_checkpoint(load_checkpoint(run_dir / "ckpt.pt"), cfg)
    training = training_figures(views, with_coverage=with_coverage)
    training.update(extra or {})
    pipeline.finish(cfg, run_dir, raw, training, t0=time.perf_counter(), report=report_too)
    return run_dir


@pytest.fixture(scope="module")
def images_run(tiny_run, tmp_path_factory) -> Path:
    return make_images_run(tiny_run, tmp_path_factory.mktemp("images"))


def visible_text(page: str) -> str:
    """The page's text outside the resolved config (whose target keeps the default
    ``model: lambertian`` beside ``images``) and the data URIs."""
    page = re.sub(r"<pre>.*?</pre>", "", page, flags=re.S)
    page = re.sub(r'"data:[^"]*"', '""', page)
    return html.unescape(re.sub(r"<[^>]+>", " ", page))


def embedded_pngs(page: str) -> dict[str, bytes]:
    found = re.findall(r'<img src="data:image/png;base64,([^"]+)" alt="([^"]+)"', page)
    return {html.unescape(alt): base64.b64decode(data) for data, alt in found}


# ------------------------------------------------------------------ report
def test_report_of_an_images_run_describes_the_fit(images_run, tmp_path):
    metrics = json.loads((images_run / "metrics.json").read_text())
    assert "accuracy" not in metrics and "peak" not in metrics  # finish had no target
    paths = report.write_report(images_run, tmp_path / "out", render=False)
    page = paths["html"].read_text()
    text = visible_text(page)
    # no analytic target anywhere: not named, not compared with, no verdict against it
    assert "lambertian" not in text.lower()
    assert "FAIL" not in text and "**FAIL**" not in paths["md"].read_text()
    for absent in ("Accuracy", "rel. RMSE", "highlight's peak", "against the reference"):
        assert absent not in text, absent
    # an images fit: its views, figures and losses
    assert "<h2>Images fit</h2>" in page
    assert f"images: {VIEWS} views (view1.exr, view2.exr, view3.exr)" in text
    for k in range(1, VIEWS + 1):
        assert f"<td>view{k}.xml</td><td>view{k}.exr</td><td>{FILM[0]} × {FILM[1]}</td>" in page
    assert "last image loss (relative MSE)" in text and "0.0211" in text
    pngs = embedded_pngs(page)
    assert "The fit's losses" in pngs and "heldout_loss" in text
    assert "Training curve" not in pngs  # the sample-based curve (held-out f cos error)
    # what the images determine: the figure, the warning and the map itself
    assert "coverage of the (wi, wo) domain" in text and "0.5 %" in text
    assert "Warning: coverage: the images observe 0.5 %" in text
    assert pngs[COVERAGE_ALT] == (images_run / "coverage.png").read_bytes()
    assert (tmp_path / "out" / report.image_name("coverage")).is_file()  # beside report.md
    # the physics checks stay
    assert "Physics checks" in text and "reciprocity" in text


def test_report_without_a_coverage_figure_says_so(tiny_run, tmp_path):
    run_dir = make_images_run(tiny_run, tmp_path, with_coverage=False)
    page = report.write_report(run_dir, render=False)["html"].read_text()
    text = visible_text(page)
    assert "<h2>Images fit</h2>" in page and "lambertian" not in text.lower()
    assert "No coverage figure in metrics.json" in text
    assert COVERAGE_ALT not in embedded_pngs(page)


def test_report_shows_the_contenders_and_the_first_choice(tiny_run, tmp_path):
    # images.start_continue_within: the contenders fitted further, the choice made again
    # on their continued losses (neural_brdf.inverse.starts.contend); the report gives
    # each continued loss beside the first and names the family chosen before
    start = {
        "family": "principled",
        "first_choice": "roughplastic",
        "params": {"roughness": 0.5},
        "candidates": [
            {"family": "diffuse", "val_loss": 0.0063, "train_loss": 0.0033, "seconds": 7.0},
            {
                "family": "roughplastic",
                "val_loss": 0.00111,
                "train_loss": 0.00127,
                "seconds": 12.8,
                "continued_val_loss": 0.00111,
            },
            {
                "family": "principled",
                "val_loss": 0.00143,
                "train_loss": 0.00056,
                "seconds": 10.4,
                "continued_val_loss": 2.34e-06,
            },
        ],
        "seconds": 110.0,
    }
    init = {"target": "Mitsuba Principled (teacher.xml)", "seconds": 130.0, "start": start}
    run_dir = make_images_run(tiny_run, tmp_path, extra={"init": init})
    text = " ".join(
        visible_text(report.write_report(run_dir, render=False)["html"].read_text()).split()
    )
    assert (
        "start principled (chosen of 3 by the held-out pixels after the contenders' further "
        "fits; roughplastic before), distilled" in text
    )
    assert "principled 0.00143 0.00056 10.4 s 2.34e-06 chosen" in text
    assert "roughplastic 0.00111 0.00127 12.8 s 0.00111 principled 0.00143" in text


def test_report_of_a_named_start_does_not_describe_autos_choice(tiny_run, tmp_path):
    """images.start: roughplastic fits that family alone: the paragraph said "every
    family fitted ... the simplest one within the noise of the best"."""
    import inspect

    from neural_brdf.inverse import starts
    from neural_brdf.viewer.report import images as images_report

    assert f'"rule": "{images_report.NAMED}"' in inspect.getsource(starts)  # (one rule)
    start = {
        "family": "roughplastic",
        "params": {"alpha": 0.2},
        "val_loss": 0.0011,
        "rule": images_report.NAMED,
        "candidates": [
            {"family": "roughplastic", "val_loss": 0.0011, "train_loss": 0.001, "seconds": 9.0}
        ],
        "seconds": 9.0,
    }
    init = {"target": "Mitsuba roughplastic (teacher.xml)", "seconds": 20.0, "start": start}
    run_dir = make_images_run(tiny_run, tmp_path, extra={"init": init})
    text = " ".join(
        visible_text(report.write_report(run_dir, render=False)["html"].read_text()).split()
    )
    assert "Start: the family images.start names" in text
    assert "every family fitted" not in text


def test_report_shows_the_cross_check_of_an_inconclusive_split(tiny_run, tmp_path):
    # images.start_cross_folds: a choice the split tied by its standard error alone,
    # settled over folds of the training tiles (neural_brdf.inverse.starts.cross_check);
    # the report names the check, its figures and what it chose, and why the choice moved
    start = {
        "family": "clearcoat",
        "first_choice": "principled",
        "params": {"roughness": 0.4},
        "candidates": [
            {"family": "principled", "val_loss": 0.00141, "train_loss": 0.00175},
            {"family": "clearcoat", "val_loss": 0.00131, "train_loss": 0.00134},
        ],
        "cross_check": {
            "folds": 2,
            "families": ["principled", "clearcoat"],
            "tiles": 470,
            "rival_gain": 0.000132,
            "standard_error": 2.9e-05,
            "chosen": "clearcoat",
            "seconds": 43.0,
        },
        "seconds": 150.0,
    }
    init = {"target": "Mitsuba Principled (teacher.xml)", "seconds": 170.0, "start": start}
    run_dir = make_images_run(tiny_run, tmp_path, extra={"init": init})
    text = " ".join(
        visible_text(report.write_report(run_dir, render=False)["html"].read_text()).split()
    )
    assert (
        "start clearcoat (chosen of 2 by the held-out pixels after the cross-check over "
        "folds of the training tiles; principled before), distilled" in text
    )
    assert (
        "start's cross-check clearcoat against principled (the split tied them by its "
        "standard error): held-out loss lower by 0.00013 +- 2.9e-05 over 470 tiles (the "
        "split's and 2 folds of the training tiles); clearcoat chosen" in text
    )


def test_report_shows_the_catch_up_of_a_warm_starts_sources(tiny_run, tmp_path):
    # images.start_catch_up: the first pick warm-started from another family, which was
    # fitted as many steps further (neural_brdf.inverse.starts.catch_up); the report says
    # what was picked first, what was fitted further and its held-out loss before and after
    start = {
        "family": "roughconductor",
        "first_pick": "roughconductor_aniso",
        "params": {"alpha": 0.1},
        "candidates": [
            {"family": "roughconductor", "val_loss": 0.000981, "train_loss": 0.00102},
            {"family": "roughconductor_aniso", "val_loss": 0.000978, "train_loss": 0.00101},
        ],
        "caught_up": {
            "roughconductor": {
                "steps": 80,
                "val_loss_before": 0.00112,
                "val_loss_after": 0.000981,
                "kept": True,
                "seconds": 9.5,
            }
        },
        "seconds": 90.0,
    }
    init = {"target": "Mitsuba roughconductor (teacher.xml)", "seconds": 110.0, "start": start}
    run_dir = make_images_run(tiny_run, tmp_path, extra={"init": init})
    text = " ".join(
        visible_text(report.write_report(run_dir, render=False)["html"].read_text()).split()
    )
    assert (
        "start's catch-up roughconductor_aniso picked first; the families it starts from "
        "fitted as long: roughconductor 80 steps more, held-out loss 0.00112 -> 0.000981" in text
    )
    # the choice stayed: said so, and a continuation not kept is marked
    start["caught_up"]["roughconductor"]["kept"] = False
    start["family"] = start.pop("first_pick")
    run_dir = make_images_run(tiny_run, tmp_path / "stays", extra={"init": init})
    text = " ".join(
        visible_text(report.write_report(run_dir, render=False)["html"].read_text()).split()
    )
    assert (
        "the families the chosen one starts from fitted as long: roughconductor 80 steps "
        "more, held-out loss 0.00112 -> 0.000981 (not kept); it stays" in text
    )


def test_the_loss_plot_holds_the_starts_held_out_loss_and_marks_the_kept_weights(
    tiny_run, tmp_path
):
    # log.csv begins at the first step, but the stage scores the start before it and
    # keeps it when no step beats it: the plot and its caption show that score (step 0,
    # metrics.json's start_loss) and mark the weights kept, so that a falling held-out
    # curve above an unseen start does not read as an improvement
    from neural_brdf.inverse.fit import HELDOUT_COLUMN
    from neural_brdf.viewer.report import images
    from neural_brdf.viewer.report.run import load_run

    assert images.HELDOUT == HELDOUT_COLUMN
    # write_log's held-out losses: 0.12 at step 5, 0.06 at step 10
    val = {"start_loss": 0.04, "best_loss": 0.04, "best_step": 0, "kept": "the start"}
    run_dir = make_images_run(tiny_run, tmp_path, extra={"validation": val})
    page = report.write_report(run_dir, render=False)["html"].read_text()
    text = " ".join(visible_text(page).split())
    assert "(step 0: the start's, before the first step, from metrics.json)" in text
    assert (
        "The star: the weights the stage kept, the lowest held-out loss (the start, 0.04)" in text
    )
    series = images.loss_series(load_run(run_dir).log)
    assert list(series[images.HELDOUT][0]) == [5, 10]  # log.csv's own: no step 0
    held = images.held_out_series(val, series[images.HELDOUT])
    assert held is not None and list(held[0]) == [0, 5, 10]
    series[images.HELDOUT] = held
    fig = images.loss_figure(series, images.kept_point(val))
    lines = {
        ln.get_label(): (list(ln.get_xdata()), list(ln.get_ydata())) for ln in fig.axes[0].lines
    }
    assert lines[images.HELDOUT] == ([0, 5, 10], [0.04, 0.12, 0.06])
    assert lines["kept: the start"] == ([0], [0.04])
    assert images.kept_point({**val, "best_step": 10, "best_loss": 0.06})[2] == "kept: step 10"
    assert images.held_out_series(None, series["loss"]) is series["loss"]
    assert images.kept_point(None) is None


def test_report_lists_the_start_candidates_and_the_choice(tiny_run, tmp_path):
    # an auto start (neural_brdf.inverse.starts.network_start): every family fitted, one
    # chosen, one left out; the report names each with its losses and marks the choice
    start = {
        "family": "roughplastic",
        "params": {"alpha": 0.15},
        "candidates": [
            {"family": "diffuse", "val_loss": 0.0412, "train_loss": 0.0398, "seconds": 7.5},
            {"family": "roughplastic", "val_loss": 0.00213, "train_loss": 0.0019, "seconds": 12.25},
            {"family": "blend", "val_loss": 0.00209, "train_loss": 0.0018, "seconds": 21.0},
        ],
        "left_out": {"roughconductor_aniso": "model.encoding 'isotropic' is isotropic"},
        "seconds": 40.75,
    }
    init = {"target": "Mitsuba RoughPlastic (teacher.xml)", "seconds": 60.0, "start": start}
    run_dir = make_images_run(tiny_run, tmp_path, extra={"init": init})
    page = report.write_report(run_dir, render=False)["html"].read_text()
    text = " ".join(visible_text(page).split())
    assert "start roughplastic (chosen of 3 by the held-out pixels), distilled" in text
    assert "roughplastic 0.00213 0.0019 12.2 s chosen" in text
    assert "diffuse 0.0412 0.0398 7.5 s" in text and "blend 0.00209 0.0018 21.0 s" in text
    assert "diffuse 0.0412 0.0398 7.5 s chosen" not in text
    assert "roughconductor_aniso left out: model.encoding 'isotropic' is isotropic" in text
    assert "half vector" not in text
    assert "choice's held-out pixels" not in text  # the start holds no val_loss here
    # the start's held-out loss against the targets' noise, and a poor start's verdict
    poor = {
        **start,
        "val_loss": 0.0024,
        "target_noise": 0.00011,
        "poor": {
            "val_loss": 0.0024,
            "target_noise": 0.00011,
            "excess": 0.00229,
            "limit": 0.0015,
            "steps": 450,
        },
    }
    called = make_images_run(tiny_run, tmp_path / "poor", extra={"init": {**init, "start": poor}})
    text = " ".join(
        visible_text(report.write_report(called, render=False)["html"].read_text()).split()
    )
    assert (
        "the chosen family's held-out loss (its analytic BSDF, as chosen) 0.0024 "
        "(the targets' own noise"
        in text
        and "0.00011" in text
    )
    assert "poor: no family fits the views" in text
    assert "0.0023 above the noise > images.poor_start_loss 0.0015" in text
    assert "ran at train.lr for up to 450 steps (images.poor_start_steps)" in text
    assert "poor at once" not in text  # its contenders and refinement ran
    # poor at once (images.poor_start_early_loss): no contender, no refinement, said
    far = {**poor, "uncontested": "far above its floor", "early_loss": 0.03}
    at_once = make_images_run(tiny_run, tmp_path / "far", extra={"init": {**init, "start": far}})
    text = " ".join(
        visible_text(report.write_report(at_once, render=False)["html"].read_text()).split()
    )
    assert (
        "poor at once, its first choice above the noise by more than "
        "images.poor_start_early_loss 0.03: no contender fitted further, not refined" in text
    )
    good = {**start, "val_loss": 0.0012, "target_noise": 0.0011}
    fine = make_images_run(tiny_run, tmp_path / "fine", extra={"init": {**init, "start": good}})
    text = " ".join(
        visible_text(report.write_report(fine, render=False)["html"].read_text()).split()
    )
    assert (
        "the chosen family's held-out loss (its analytic BSDF, as chosen) 0.0012" in text
        and "poor:" not in text
    )
    assert "warned" not in text
    # far above its noise but not poor (inverse.fit.far_above_noise): the warning, repeated
    above = {
        **start,
        "val_loss": 0.00053,
        "target_noise": 8.8e-7,
        "far_above_noise": {"ratio": 602.3, "excess": 0.000529, "limit": 0.0015},
    }
    warned = make_images_run(tiny_run, tmp_path / "w", extra={"init": {**init, "start": above}})
    text = " ".join(
        visible_text(report.write_report(warned, render=False)["html"].read_text()).split()
    )
    assert (
        "warned: 602 times the targets' noise, not poor by images.poor_start_loss 0.0015 "
        "(0.00053 above the noise); if the fitted views stay far from their images, set it "
        "below 0.00053" in text
    )
    # an anisotropic start's network has its grid over the half vector's disc: said
    aniso = {**start, "family": "roughconductor_aniso", "grid_coords": "half_disc"}
    moved = make_images_run(tiny_run, tmp_path / "aniso", extra={"init": {**init, "start": aniso}})
    text = " ".join(
        visible_text(report.write_report(moved, render=False)["html"].read_text()).split()
    )
    assert "distilled into the network (its grid over the half vector's disc)" in text
    assert "after an isotropic start" not in text
    # an isotropic start's network has the isotropic encoding (images.isotropic_encoding)
    iso = {**start, "encoding": "isotropic", "encoding_moved": True}
    moved = make_images_run(tiny_run, tmp_path / "iso", extra={"init": {**init, "start": iso}})
    text = " ".join(
        visible_text(report.write_report(moved, render=False)["html"].read_text()).split()
    )
    assert "distilled into the network (the isotropic encoding, after an isotropic start)" in text
    # a run with no fitted start says so, and lists no candidates
    plain = make_images_run(tiny_run, tmp_path / "plain")
    text = visible_text(report.write_report(plain, render=False)["html"].read_text())
    assert "a constant (no fitted start)" in text and "start family" not in text


def test_report_cli_of_an_images_run_says_it_cannot_render(images_run, tmp_path, monkeypatch):
    monkeypatch.setattr(plots, "mitsuba_unavailable", lambda: "Mitsuba 3 is switched off")
    out = tmp_path / "cli"
    assert main(["report", str(images_run), "-o", str(out)]) == 0
    text = visible_text((out / "report.html").read_text())
    assert "No render: Mitsuba 3 is switched off" in text
    assert "Images fit" in text and "lambertian" not in text.lower()


def test_the_coverage_warning_follows_the_figure():
    from neural_brdf.viewer.report import images as images_report

    cov = coverage_summary(Path("v"), figure=0.6)
    assert images_report.coverage_warning(cov) is None
    cov["figure"] = 0.1
    assert "10.0 %" in (images_report.coverage_warning(cov) or "")
    cov["warning"] = "said by the fit"
    assert images_report.coverage_warning(cov) == "said by the fit"


# ------------------------------------------------------------------ export
def test_export_of_an_images_run_has_no_lambertian_target(images_run, tmp_path, capsys):
    out = tmp_path / "again.onnx"
    code = main(["export", str(images_run), "-o", str(out)])
    stdout = capsys.readouterr().out
    assert code == 0, stdout
    assert f"(an images fit of {VIEWS} views)" in stdout
    meta = reader.props(reader.load(out))
    target = json.loads(meta["target"])
    assert target["kind"] == "images" and target["views"] == VIEWS, target
    assert "lambertian" not in json.dumps(target).lower()
    assert target["description"].startswith(f"{VIEWS} images (view1.exr")
    # the same entry as the run's own model.onnx, which the pipeline wrote with no target
    own = json.loads(reader.props(reader.load(images_run / "model.onnx"))["target"])
    assert own == target
    info = export.export_run(images_run, tmp_path / "api.onnx", measure=validate.physics)
    assert info["target"]["kind"] == "images" and info["target"]["views"] == VIEWS


# ------------------------------------------------------------------ train's last line
@pytest.mark.parametrize("writes_report", [True, False])
def test_train_names_report_html_only_when_written(
    tiny_run, tmp_path, monkeypatch, capsys, writes_report
):
    """``neural-brdf train`` of an images config, its fit replaced by the tiny run's
    weights: the pipeline's real export, validation and (images) report follow."""
    from neural_brdf.inverse import fit as inverse

    views = tmp_path / "views"
    write_views(views)
    cfg = images_config(tiny_run, views)
    cfg_path = tmp_path / "fit.yaml"
    cfg_path.write_text(cfg.to_yaml())

    def fake_fit(cfg, run_dir, **_):
        t0 = time.perf_counter()
        run_dir = Path(run_dir)
        (run_dir / "config.yaml").write_text(cfg.to_yaml())
        write_log(run_dir)
        (run_dir / "coverage.png").write_bytes(png_of("coverage"))
        raw = export.raw_from_checkpoint(load_checkpoint(tiny_run / "ckpt.pt"), cfg)
        return raw, training_figures(views), t0, cfg

    monkeypatch.setattr(inverse, "fit", fake_fit)
    monkeypatch.setattr(plots, "mitsuba_unavailable", lambda: "Mitsuba 3 is switched off")
    if not writes_report:  # a pipeline that skips the report (as run_many without --report)
        finish = pipeline.finish
        monkeypatch.setattr(
            pipeline, "finish", lambda *a, **k: finish(*a, **{**k, "report": False})
        )
    run_dir = tmp_path / "run"
    code = main(["train", str(cfg_path), "--out", str(run_dir)])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert code == 0, last
    assert last.startswith(f"run: {run_dir}")
    assert (run_dir / "report.html").is_file() == writes_report
    assert ("report.html" in last) == writes_report, last
    seconds = json.loads((run_dir / "metrics.json").read_text())["seconds"]
    assert ("report" in seconds) == writes_report
    if writes_report:
        page = (run_dir / "report.html").read_text()
        assert "<h2>Images fit</h2>" in page
        assert "lambertian" not in visible_text(page).lower()
        assert COVERAGE_ALT in embedded_pngs(page)


# ------------------------------------------------------------------ with Mitsuba
@pytest.mark.mitsuba
def test_report_shows_the_coverage_a_fit_computes(tiny_run, tmp_path):
    """coverage.assess on three flash views (a thin coverage: the warning), as the fit
    calls it, into metrics.json: the report shows its figure, warning and map; the views'
    film sizes come from real EXR files."""
    from neural_brdf.inverse import coverage
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as example
    from neural_brdf.viewer.report import images as images_report

    inverse.use_variant("llvm_ad_rgb")
    run_dir = make_images_run(tiny_run, tmp_path)
    views = tmp_path / "views"
    res = 12
    for k, (az, el) in enumerate(example.VIEWS[:VIEWS]):
        emitters = example.capture_emitters("flash", k)
        xml = example.scene_xml(az, el, resolution=res, emitters=emitters)
        (views / f"view{k + 1}.xml").write_text(xml)
        example.write_exr(
            views / f"view{k + 1}.exr", example.render_file(views / f"view{k + 1}.xml", 4)
        )
    scenes = [views / f"view{k}.xml" for k in range(1, VIEWS + 1)]
    info, warning = coverage.assess(scenes, picture=run_dir / "coverage.png", rays=res * res * 8)
    assert warning is not None  # a flash: the retro-reflection line only
    metrics = json.loads((run_dir / "metrics.json").read_text())
    metrics["training"]["coverage"] = json.loads(json.dumps(info))
    validate.write_json(metrics, run_dir / "metrics.json")
    page = report.write_report(run_dir, render=False)["html"].read_text()
    text = visible_text(page)
    assert f"{100 * info['figure']:.1f} %" in text
    assert "Warning: " + warning in text
    assert embedded_pngs(page)[COVERAGE_ALT] == (run_dir / "coverage.png").read_bytes()
    for k in range(1, VIEWS + 1):
        assert images_report.exr_size(views / f"view{k}.exr") == (res, res)
        assert f"<td>view{k}.exr</td><td>{res} × {res}</td>" in page
