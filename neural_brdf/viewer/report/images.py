"""The report of an images fit (``target.images``, docs/inverse.md): the views, the
fit's losses over its steps and what the images determine (the coverage figure, its
warning and its map), in place of the accuracy against a target, which such a fit has
not got.  Everything comes from the run folder: ``config.yaml`` (the views),
``metrics.json`` (``training``, ``training.coverage``: neural_brdf.inverse.coverage's
``summary``), ``log.csv`` and ``coverage.png``; nothing here needs Mitsuba."""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from neural_brdf import runfolder
from neural_brdf.inverse.coverage import percent_text
from neural_brdf.viewer import plots
from neural_brdf.viewer.report.blocks import Block, Heading, Image, Table, Text
from neural_brdf.viewer.report.run import Run

COVERAGE_PICTURE = runfolder.COVERAGE  # the map a fit writes beside metrics.json
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXR_MAGIC = b"\x76\x2f\x31\x01"
EXR_HEADER_BYTES = 1 << 16  # a header's attributes, read no further
# figures of metrics.json's ``training`` shown in the fit's table: key -> (label, format)
FIT_FIGURES = {
    "steps": ("steps of the image fit", ".0f"),
    "final_loss": ("last loss (image + albedo penalty)", ".4g"),
    "final_image_loss": ("last image loss (relative MSE)", ".4g"),
    "final_albedo_penalty": ("last albedo penalty", ".3g"),
    "final_max_albedo_estimate": ("last max albedo estimate (raw network)", ".4f"),
    "spp_per_step": ("samples per pixel per step (gradient pass)", ".0f"),
    "primal_spp_per_step": ("samples per pixel per step (primal pass)", ".0f"),
    "render_seconds": ("render time", ".1f"),
}


# log.csv's columns of an images fit beyond the common ones, said in the loss caption
HELDOUT = "heldout_loss"  # (neural_brdf.inverse.fit.HELDOUT_COLUMN)
COLUMN_TEXT = {
    HELDOUT: "the same relative MSE over the validation split's held-out pixels",
}


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def _finite(x: Any) -> float | None:
    """A JSON number as a float, else None (write_json stores inf / nan as strings)."""
    if isinstance(x, bool) or not isinstance(x, (int, float, str)):
        return None
    try:
        v = float(x)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def exr_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an OpenEXR file's data window, read from its header alone;
    None for a missing or foreign file.  The fit checks that each image has its scene's
    film size, so this is the view's film size."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(EXR_HEADER_BYTES)
    except OSError:
        return None
    if head[:4] != EXR_MAGIC:
        return None
    pos = 8  # magic, version
    while pos < len(head) and head[pos] != 0:
        end = head.find(b"\0", pos)
        kind_end = head.find(b"\0", end + 1)
        if end < 0 or kind_end < 0 or kind_end + 5 > len(head):
            return None
        name, kind = head[pos:end], head[end + 1 : kind_end]
        (size,) = struct.unpack("<i", head[kind_end + 1 : kind_end + 5])
        value = head[kind_end + 5 : kind_end + 5 + size]
        if name == b"dataWindow" and kind == b"box2i" and len(value) == 16:
            x0, y0, x1, y1 = struct.unpack("<4i", value)
            return (x1 - x0 + 1, y1 - y0 + 1) if x1 >= x0 and y1 >= y0 else None
        pos = kind_end + 5 + max(size, 0)
    return None


def _film(entry: Any, image: Path) -> str:
    """A view's film size: from metrics.json's ``training.views[k]`` when it holds one
    (``width`` and ``height``, or ``film``: [width, height]), else from the image."""
    if isinstance(entry, dict):
        w, h = _finite(entry.get("width")), _finite(entry.get("height"))
        film = entry.get("film")
        if (w is None or h is None) and isinstance(film, list) and len(film) == 2:
            w, h = _finite(film[0]), _finite(film[1])
        if w is not None and h is not None:
            return f"{w:.0f} × {h:.0f}"
    size = exr_size(image)
    return "-" if size is None else f"{size[0]} × {size[1]}"


def _coverage_dict(run: Run) -> dict | None:
    training = run.metrics.get("training")
    cov = training.get("coverage") if isinstance(training, dict) else None
    return cov if isinstance(cov, dict) else None


def coverage_figure(run: Run) -> float | None:
    """metrics.json's ``training.coverage.figure`` (a share of the domain), or None."""
    cov = _coverage_dict(run)
    return None if cov is None else _finite(cov.get("figure"))


def _per_view(cov: dict | None, scene: str) -> dict:
    """The coverage summary's entry of the view whose scene is ``scene`` (a fit assesses
    its fitted views only: a held-out view has none), or {}."""
    views = cov.get("per_view") if cov else None
    entries = [v for v in views if isinstance(v, dict)] if isinstance(views, list) else []
    for same in (lambda a: a == scene, lambda a: Path(a).name == Path(scene).name):
        found = [v for v in entries if same(str(v.get("scene")))]
        if len(found) == 1:
            return found[0]
    return {}


def _pct(x: Any, digits: int = 1) -> str:
    v = _finite(x)
    return "-" if v is None else f"{100 * v:.{digits}f} %"


def _views(run: Run) -> list[Block]:
    views = run.config.target.images or []
    training = run.metrics.get("training")
    given = training.get("views") if isinstance(training, dict) else None
    cov = _coverage_dict(run)
    held = _held_out(run)
    rows = []
    for k, view in enumerate(views):
        scene, image = Path(view.scene), Path(view.image)
        entry = given[k] if isinstance(given, list) and k < len(given) else None
        row = [str(k + 1), scene.name, view.label(), _film(entry, image)]
        if held:
            row.append("held out" if view.label() in held else "fitted")
        if cov is not None:
            pv = _per_view(cov, view.scene)
            lit = _finite(pv.get("pixels_lit"))
            row += [_pct(pv.get("figure")), "-" if lit is None else f"{lit:.0f}"]
        rows.append(row)
    header = ["view", "scene", "image", "film (W × H)"] + (["role"] if held else [])
    if cov is not None:
        header += ["coverage alone", "lit pixels"]
    return [
        Text(
            f"Fitted to {_plural(len(views), 'view')} by differentiable rendering in "
            "Mitsuba 3 (docs/inverse.md): each scene rendered with the network as its "
            '<bsdf id="fit">, compared with its image.  There is no reference BRDF: the '
            "report shows the physics checks and the fit's own figures, and no accuracy "
            "against a target."
        ),
        Table(header, rows),
    ]


def _validation(run: Run) -> Any:
    """metrics.json's ``training.validation`` (the split's record), None without one."""
    training = run.metrics.get("training")
    return training.get("validation") if isinstance(training, dict) else None


def _held_out(run: Run) -> set[str]:
    """The image names of the views a validation split holds out (metrics.json's
    ``training.validation.views``)."""
    val = _validation(run)
    names = val.get("views") if isinstance(val, dict) else None
    return {str(n) for n in names} if isinstance(names, list) else set()


def _validation_rows(val: Any) -> list[list[str]]:
    """The validation split's figures (``training.validation``), when the fit had one."""
    if not isinstance(val, dict):
        return []
    rows = []
    for key, label in (
        # the network distilled from that family, scored on the same pixels with the
        # image stage's own samples (images.validation_spp): the same quantity, not
        # the same estimate; the distillation's error shows as a difference too
        ("start_loss", "held-out loss of the network's start (the distilled family)"),
        ("best_loss", "best held-out loss"),
        ("last_loss", "last held-out loss"),
    ):
        v = _finite(val.get(key))
        step = _finite(val.get(key.replace("_loss", "_step")))
        if v is not None:
            rows.append([label, f"{v:.4g}" + ("" if step is None else f" (step {step:.0f})")])
    if isinstance(val.get("kept"), str):
        rows.append(["weights kept", val["kept"]])
    stop = _finite(val.get("stopped_at"))
    if stop is not None:
        rows.append(
            ["image stage stopped", f"at step {stop:.0f} (images.patience {val.get('patience')})"]
        )
    return rows


def _fit_figures(run: Run) -> list[Block]:
    training = run.metrics.get("training")
    if not isinstance(training, dict):
        return []
    rows = []
    for key, (label, spec) in FIT_FIGURES.items():
        v = _finite(training.get(key))
        if v is not None:
            rows.append([label, format(v, spec) + (" s" if key.endswith("seconds") else "")])
    init = training.get("init")
    chosen = init.get("start") if isinstance(init, dict) else None
    if isinstance(chosen, dict) and isinstance(chosen.get("family"), str):
        n = len(chosen.get("candidates") or [])
        how = f"chosen of {n} by the held-out pixels" if n > 1 else "named in the config"
        # the network as the start moved it (inverse.starts.model_for_start)
        moved = (  # images.anisotropic_grid
            " (its grid over the half vector's disc)"
            if chosen.get("grid_coords") == "half_disc"
            else ""
        )
        if chosen.get("encoding_moved") is True:  # images.isotropic_encoding
            moved += f" (the {chosen.get('encoding')} encoding, after an isotropic start)"
        first = chosen.get("first_choice")
        check = chosen.get("cross_check")
        check = check if isinstance(check, dict) else None
        if isinstance(first, str):  # the contenders' fits or the cross-check changed it
            why = (
                "the cross-check over folds of the training tiles"
                if check is not None and check.get("chosen") == chosen["family"]
                else "the contenders' further fits"
            )
            how += f" after {why}; {first} before"
        rows.append(["start", f"{chosen['family']} ({how}), distilled into the network{moved}"])
        caught = chosen.get("caught_up")
        if isinstance(caught, dict) and caught:  # images.start_catch_up
            rows.append(["start's catch-up", _catch_up_text(caught, chosen.get("first_pick"))])
        if check is not None:  # images.start_cross_folds
            rows.append(["start's cross-check", _cross_check_text(check)])
        rows += _start_noise_rows(chosen)
    elif isinstance(init, dict) and isinstance(init.get("target"), str):
        rows.append(["start", init["target"]])
    elif "init" in training and init is None:
        rows.append(["start", "a constant (no fitted start)"])
    rows += _validation_rows(training.get("validation"))
    out: list[Block] = [Table(["figure", "value"], rows)] if rows else []
    return out + _start_candidates(chosen)


def _catch_up_text(caught: dict, first: object) -> str:
    """A line for the families a warm-started first pick started from, fitted further
    until they had as many steps (inverse.starts.catch_up)."""
    parts = []
    for name, r in caught.items():
        before, after = _finite(r.get("val_loss_before")), _finite(r.get("val_loss_after"))
        text = f"{name} {r.get('steps')} steps more"
        if before is not None and after is not None:
            text += f", held-out loss {before:.4g} -> {after:.4g}"
        parts.append(text + ("" if r.get("kept") else " (not kept)"))
    said = "; ".join(parts)
    if isinstance(first, str):  # the choice made again picked another family
        return f"{first} picked first; the families it starts from fitted as long: {said}"
    return f"the families the chosen one starts from fitted as long: {said}; it stays"


def _cross_check_text(check: dict) -> str:
    """A line for an inconclusive split's cross-check (inverse.starts.cross_check)."""
    names = check.get("families") or ["?", "?"]
    gain, se = _finite(check.get("rival_gain")), _finite(check.get("standard_error"))
    text = f"{names[-1]} against {names[0]} (the split tied them by its standard error)"
    if gain is not None and se is not None:
        text += (
            f": held-out loss lower by {gain:.2g} +- {se:.2g} over {check.get('tiles')} "
            f"tiles (the split's and {check.get('folds')} folds of the training tiles)"
        )
    return text + f"; {check.get('chosen')} chosen"


def _start_noise_rows(chosen: dict) -> list[list[str]]:
    """The chosen start's held-out loss against the targets' own noise (estimated from
    the images: ``target_noise``), and whether images.poor_start_loss called it poor
    (at once, by images.poor_start_early_loss)."""
    loss, noise = _finite(chosen.get("val_loss")), _finite(chosen.get("target_noise"))
    if loss is None:
        return []
    text = f"{loss:.4g}"
    if noise is not None:
        text += f" (the targets' own noise, estimated from the images: {noise:.2g})"
    rows = [["the chosen family's held-out loss (its analytic BSDF, as chosen)", text]]
    poor = chosen.get("poor")
    if isinstance(poor, dict):
        above, limit = _finite(poor.get("excess")), _finite(poor.get("limit"))
        said = "poor: no family fits the views; the image stage ran at train.lr"
        steps = poor.get("steps")
        if isinstance(steps, int):
            said += f" for up to {steps} steps (images.poor_start_steps)"
        if above is not None and limit is not None:
            said += f" ({above:.2g} above the noise > images.poor_start_loss {limit:g})"
        early = _finite(chosen.get("early_loss"))
        if chosen.get("uncontested") == "far above its floor" and early is not None:
            said += (
                f"; poor at once, its first choice above the noise by more than "
                f"images.poor_start_early_loss {early:g}: no contender fitted further, "
                "not refined"
            )
        rows.append(["start's fit", said])
    far = chosen.get("far_above_noise")
    if isinstance(far, dict) and not isinstance(poor, dict):
        ratio, above = _finite(far.get("ratio")), _finite(far.get("excess"))
        limit = _finite(far.get("limit"))
        if ratio is not None and above is not None and limit is not None:
            rows.append(
                [
                    "start's fit",
                    f"warned: {ratio:.0f} times the targets' noise, not poor by "
                    f"images.poor_start_loss {limit:g} ({above:.2g} above the noise); if the "
                    f"fitted views stay far from their images, set it below {above:.2g}",
                ]
            )
    return rows


# the rule a start records when images.start named its family (neural_brdf/inverse/starts.py)
NAMED = "images.start names the family"


def _start_candidates(chosen: Any) -> list[Block]:
    """The families fitted for the start (``training.init.start.candidates``): each one's
    held-out and training loss, its time and whether the choice's rule tied it with the
    best; the held-out loss of each contender after its further fit
    (``images.start_continue_within``); the families left out, with why."""
    if not isinstance(chosen, dict) or not isinstance(chosen.get("candidates"), list):
        return []
    rows = []
    for c in chosen["candidates"]:
        if not isinstance(c, dict):
            continue
        val, train, secs = (_finite(c.get(k)) for k in ("val_loss", "train_loss", "seconds"))
        further = _finite(c.get("continued_val_loss"))
        after = "" if further is None else f"{further:.4g}"
        mark = "chosen" if c.get("family") == chosen.get("family") else ""
        rows.append(
            [
                str(c.get("family")),
                "" if val is None else f"{val:.4g}",
                "" if train is None else f"{train:.4g}",
                "" if secs is None else f"{secs:.1f} s",
                after,
                mark,
            ]
        )
    left = chosen.get("left_out")
    if isinstance(left, dict):
        rows += [[str(k), "", "", "", "", f"left out: {why}"] for k, why in left.items()]
    if not rows:
        return []
    header = ["start family", "held-out loss", "training loss", "fit time", "continued", "verdict"]
    if chosen.get("rule") == NAMED:  # (starts.choose: images.start gives the family)
        said = (
            "Start: the family images.start names, fitted to the training pixels, scored "
            "on the held-out pixels (relative MSE without the render's noise), refined and "
            "distilled into the network."
        )
    else:
        said = (
            "Start: every family fitted to the training pixels, scored on the held-out "
            "pixels (relative MSE without the render's noise); the families within "
            "images.start_continue_within of the best, images.start_continue_max at most, "
            "fitted further (continued), and the "
            "simplest one within the noise of the best refined and distilled into the "
            "network."
        )
    return [Text(said), Table(header, rows)]


def loss_series(log: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The fit's losses in log.csv: ``loss`` (the step's image loss + albedo penalty) and
    every column the loop added; name -> (steps, values), finite values only."""
    step = np.asarray(log["step"], dtype=np.float64)
    series = {"loss": np.asarray(log["loss"], dtype=np.float64)}
    series.update(log.get("columns") or {})
    out = {}
    for name, values in series.items():
        values = np.asarray(values, dtype=np.float64)
        keep = np.isfinite(values)
        if values.shape == step.shape and keep.any():
            out[name] = (step[keep], values[keep])
    return out


def held_out_series(
    val: Any, logged: tuple[np.ndarray, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray] | None:
    """The held-out losses a fit scored: log.csv's (``logged``, from the first step on)
    after the start's, scored before the first step (metrics.json's
    ``training.validation.start_loss``) at step 0; None without either."""
    start = _finite(val.get("start_loss")) if isinstance(val, dict) else None
    if start is None:
        return logged
    steps, values = logged if logged is not None else (np.zeros(0), np.zeros(0))
    if steps.size and steps[0] == 0:
        return steps, values
    return np.concatenate([[0.0], steps]), np.concatenate([[start], values])


def kept_point(val: Any) -> tuple[float, float, str] | None:
    """(step, held-out loss, label) of the weights the image stage kept (the lowest
    held-out loss: ``training.validation``'s best), None without a split."""
    if not isinstance(val, dict):
        return None
    step, loss = _finite(val.get("best_step")), _finite(val.get("best_loss"))
    if step is None or loss is None:
        return None
    return step, loss, "kept: the start" if step == 0 else f"kept: step {step:.0f}"


def loss_figure(
    series: dict[str, tuple[np.ndarray, np.ndarray]],
    kept: tuple[float, float, str] | None = None,
) -> Figure:
    """The losses over the steps, log scale where every value is positive; ``kept``:
    the weights the stage kept, marked on the held-out loss."""
    fig = Figure(figsize=(7, 4), layout="constrained")
    ax = fig.subplots()
    positive = all(np.all(v > 0) for _, v in series.values())
    for name, (s, v) in series.items():
        sparse = len(v) < 20
        ax.plot(s, v, "o-" if sparse else "-", lw=1.4, ms=4, label=name)
    if kept is not None:
        ax.plot([kept[0]], [kept[1]], "*", ms=14, color="black", zorder=5, label=kept[2])
        positive = positive and kept[1] > 0
    if positive:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(True, alpha=0.3)
    # beside the axes, where no curve runs under it (the constrained layout makes room)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.set_title("image fit: losses", fontsize=10)
    return fig


def _losses(run: Run) -> list[Block]:
    series = loss_series(run.log)
    if not series:
        return [Text("No steps of the image fit were logged (log.csv).", note=True)]
    val = _validation(run)
    held = held_out_series(val, series.get(HELDOUT))
    if held is not None:  # the scorings, from the start's on
        series[HELDOUT] = held
    kept = kept_point(val)
    others = [n for n in series if n != "loss"]
    said = "".join(f"; {n}: {COLUMN_TEXT.get(n, 'a column the fit logged')}" for n in others)
    if held is not None and held[0].size and held[0][0] == 0:
        said += " (step 0: the start's, before the first step, from metrics.json)"
    if kept is not None:
        said += (
            f". The star: the weights the stage kept, the lowest held-out loss "
            f"({kept[2].removeprefix('kept: ')}, {kept[1]:.4g}); the training loss, one "
            f"render of few samples a step over other pixels, holds the render's noise "
            f"and the albedo penalty, which the held-out estimate (two renders with "
            f"independent seeds) leaves out"
        )
    return [
        Image(
            "images-loss",
            "The fit's losses",
            f"log.csv per logged step: loss, the step's image loss (the relative MSE of "
            f"the renders against the images, averaged over the views) plus the albedo "
            f"penalty{said}.",
            plots.png_bytes(loss_figure(series, kept)),
        )
    ]


def coverage_warning(cov: dict) -> str | None:
    """The warning of a coverage summary: its own (``warning``) when it holds one, else
    the text of neural_brdf.inverse.coverage.warning when the figure is below
    ``warn_below``."""
    if isinstance(cov.get("warning"), str):
        return cov["warning"] or None
    figure, below = _finite(cov.get("figure")), _finite(cov.get("warn_below"))
    if figure is None or below is None or figure >= below:
        return None
    min_cos = _finite(cov.get("min_cos"))
    given = cov.get("per_view")
    views = given if isinstance(given, list) else []
    unlit = [
        str(v.get("scene"))
        for v in views
        if isinstance(v, dict) and _finite(v.get("pixels_lit")) == 0
    ]
    lines = f"; no lit pixel of the fit BSDF in {', '.join(unlit)}" if unlit else ""
    return (
        f"coverage: the images observe {percent_text(figure)} % of the (wi, wo) domain "
        f"with both cosines > {min_cos if min_cos is not None else 0.1:g} (below "
        f"{100 * below:.0f} %){lines}: the rest of the BRDF comes from the start and the "
        "network's prior, not the images; add views or lights at other angles to the "
        "camera (docs/inverse.md)"
    )


def _coverage(run: Run) -> list[Block]:
    blocks: list[Block] = [Heading("What the images determine", 3)]
    cov = _coverage_dict(run)
    if cov is None:
        return blocks + [
            Text(
                "No coverage figure in metrics.json (training.coverage): `python -m "
                "neural_brdf.inverse.coverage config.yaml -o coverage.png` computes it "
                "from the scenes.",
                note=True,
            )
        ]
    rows = [["coverage", _pct(cov.get("figure"))]]
    band = cov.get("theta_d_observed_deg")
    if isinstance(band, list) and len(band) == 2 and all(_finite(x) is not None for x in band):
        n_rows = _finite(cov.get("theta_d_rows_observed"))
        of = cov.get("bins")
        total = f" of {of[1]}" if isinstance(of, list) and len(of) == 2 else ""
        rows.append(
            [
                "θd observed",
                f"{float(band[0]):.1f}° to {float(band[1]):.1f}°"
                + ("" if n_rows is None else f" ({n_rows:.0f}{total} rows)"),
            ]
        )
    mixed = _finite(cov.get("bins_mixed_per_pixel"))
    if mixed is not None:
        rows.append(["bins mixed per pixel", f"{mixed:.3g}"])
    definition = cov.get("definition")
    blocks += [
        Text(
            "The part of the (wi, wo) domain the views observe, from the cameras, the "
            "shapes and the emitters alone (neural_brdf/inverse/coverage.py): "
            + (f"the {definition}." if isinstance(definition, str) else "see docs/inverse.md.")
            + "  Elsewhere the fitted BRDF is its start's and the network's prior, not "
            "the images'."
        ),
        Table(["", ""], rows),
    ]
    warning = coverage_warning(cov)
    if warning:
        blocks.append(Text(f"Warning: {warning}", note=True))
    name = Path(str(cov.get("picture") or COVERAGE_PICTURE)).name  # in the run folder only
    png = _run_png(run, name)
    if png is not None:
        blocks.append(
            Image(
                "coverage",
                "Coverage of the (θh, θd) domain",
                f"{name}: the observed density ρ over the half and difference angles in "
                "colour where a bin is observed, grey where it is not, white beyond the "
                "dashed line (a cosine below the domain's).",
                png,
            )
        )
    else:
        blocks.append(Text(f"No coverage map: {name} is not a PNG in the run folder.", note=True))
    return blocks


def _run_png(run: Run, name: str) -> bytes | None:
    """The bytes of the PNG ``name`` in the run folder, or None (missing, unreadable, or
    not a PNG)."""
    path = run.dir / name
    try:
        png = path.read_bytes() if path.is_file() else None
    except OSError:
        return None
    return png if png is not None and png.startswith(PNG_SIGNATURE) and len(png) > 24 else None


def _determined(run: Run) -> list[Block]:
    training = run.metrics.get("training")
    det = training.get("determined") if isinstance(training, dict) else None
    if not isinstance(det, dict):
        return [
            Text(
                "No map of what the views determine in metrics.json (training.determined): "
                "`python -m neural_brdf.inverse.determined config.yaml -o determined.png` "
                "computes it from the scenes and images.",
                note=True,
            )
        ]
    rows = [
        ["determined (the domain)", _pct(det.get("figure"))],
        [f"… of the {det.get('reference', 'start')}'s light", _pct(det.get("energy_figure"))],
    ]
    if "observed_figure" in det:  # the coverage, the most the map can count
        rows.append(["observed (the coverage, at most)", _pct(det.get("observed_figure"))])
    by = det.get("by_bin_width_deg")
    if isinstance(by, dict):
        for width, entry in by.items():
            if isinstance(entry, dict):
                rows.append([f"in {width}° bins", _pct(entry.get("figure"))])
    definition = det.get("definition")
    blocks: list[Block] = [
        Text(
            "Where the views determine f near the fitted material, from the same scenes and the "
            "targets' noise (neural_brdf/inverse/determined.py): the "
            + (f"{definition}." if isinstance(definition, str) else "see docs/inverse.md.")
            + "  A bin every pixel mixes in the same proportion is observed but not "
            "determined."
        ),
        Table(["", ""], rows),
    ]
    energy, below = _finite(det.get("energy_figure")), _finite(det.get("warn_energy_below"))
    if energy is not None and below is not None and energy < below:
        blocks.append(
            Text(
                f"Warning: the views determine only {100 * energy:.1f} % of the fitted "
                "material's reflected light: the rest of the fitted BRDF is the start's "
                "family and the network's prior.",
                note=True,
            )
        )
    name = Path(str(det.get("picture") or runfolder.DETERMINED)).name
    png = _run_png(run, name)
    if png is not None:
        blocks.append(
            Image(
                "determined",
                "What the views determine in the (θh, θd) domain",
                f"{name}: the width of the finest bin whose level the views fix to the "
                "tolerance, black where none does, white beyond the domain; grey contours: "
                "the fitted material's reflected light.",
                png,
            )
        )
    else:
        blocks.append(
            Text(f"No determination map: {name} is not a PNG in the run folder.", note=True)
        )
    return blocks


def section(run: Run) -> list[Block]:
    """The "Images fit" section: the views, the fit's figures and losses, the coverage
    and what the views determine."""
    return (
        [Heading("Images fit")]
        + _views(run)
        + _fit_figures(run)
        + _losses(run)
        + _coverage(run)
        + _determined(run)
    )


def target_text(run: Run) -> str:
    """The summary's target line: the views, by their image file names."""
    views = run.config.target.images or []
    names = ", ".join(v.label() for v in views)
    return f"images: {_plural(len(views), 'view')} ({names}), fitted by inverse rendering"
