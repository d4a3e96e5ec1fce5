"""The report's sections: summary, physics, accuracy and peak (an images fit: its own
section, :mod:`neural_brdf.viewer.report.images`), renders, viewer, training; each a
list of blocks."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from neural_brdf.errors import InputError
from neural_brdf.export import parity_allowed
from neural_brdf.inverse.coverage import percent_text
from neural_brdf.measured import formats
from neural_brdf.target import check_textured
from neural_brdf.train.encoding import is_anisotropic
from neural_brdf.validate import AZIMUTHS, uv_text
from neural_brdf.viewer import plots
from neural_brdf.viewer.page import at_uv
from neural_brdf.viewer.report import images
from neural_brdf.viewer.report.blocks import (
    Attachment,
    Block,
    Code,
    Heading,
    Image,
    Table,
    Text,
    Verdict,
)
from neural_brdf.viewer.report.run import (
    RENDER_RESOLUTION,
    RENDER_SPP,
    VIEWER_FILE,
    Run,
    _as_number,
    _number,
    reference_of,
)


# ------------------------------------------------------------------ content
def _fmt(x, spec: str = ".4g") -> str:
    return "-" if x is None else format(x, spec)


def check_passed(name: str, value: float, limit: float, stored) -> bool:
    """A physics check's verdict as its row shows it: its stored ``passed`` flag and its
    value within its limit (>= for min_value, <= for the others), both; a value that
    violates the limit it is shown beside fails whatever the flag says (NaN fails)."""
    within = value >= limit if name == "min_value" else value <= limit
    return stored is True and bool(within)


def physics_verdicts(m: dict, path: Path) -> dict[str, bool]:
    """Each physics check of metrics ``m``: :func:`check_passed`."""
    return {
        name: check_passed(
            name,
            _number(m, f"checks.{name}.value", path),
            _number(m, f"checks.{name}.limit", path),
            c.get("passed"),
        )
        for name, c in m["checks"].items()
    }


def peak_figures(peak: dict, path: Path) -> tuple[float, float, bool]:
    """The peak check's value, limit and verdict: its stored flag (``validate.passed``'s)
    and its value within its limit, both."""
    value = _as_number(peak.get("value"), "peak.value", path)
    limit = _as_number(peak.get("limit"), "peak.limit", path)
    return value, limit, bool(peak.get("passed", True)) and value <= limit


def _summary(run: Run) -> list:
    m, path, cfg = run.metrics, run.dir / "metrics.json", run.config
    rel = _number(m, "accuracy.rel_rmse", path, optional=True)
    rows: list[list] = [
        ["physics checks", Verdict(all(physics_verdicts(m, path).values()))],
    ]
    peak = m.get("peak")
    if isinstance(peak, dict):  # neural-brdf validate fails on it too
        value, limit, ok = peak_figures(peak, path)
        rows.append(
            [
                # (no-break spaces: a number keeps its unit)
                f"highlight's peak check: {100 * value:.2f}\u00a0% (limit {100 * limit:g}\u00a0%)",
                Verdict(ok),
            ]
        )
    rows += [
        [
            "target",
            (run.images and images.target_text(run))
            or cfg.target.data
            # a Mitsuba teacher: its description (plugin, file, any excess of albedo over 1)
            or (cfg.target.mitsuba and str(m.get("reference") or cfg.target.mitsuba))
            or f"{cfg.target.model} {json.dumps(cfg.target.params)}",
        ],
        [
            "model",
            f"{cfg.model.encoding} encoding, hidden {cfg.model.hidden}, {cfg.model.activation}",
        ],
    ]
    if run.images:  # no reference: what the images observe instead of an error
        figure = images.coverage_figure(run)
        if figure is not None:
            rows.append(["coverage of the (wi, wo) domain", f"{percent_text(figure)} %"])
    else:
        rows.append(["rel. RMSE of f cos θo", "-" if rel is None else f"{100 * rel:.3f} %"])
    rows += [
        [
            "max directional albedo",
            _fmt(_number(m, "checks.max_albedo.value", path, optional=True), ".6f"),
        ],
        ["training steps", _fmt(_number(m, "training.steps", path, optional=True), ".0f")],
    ]
    fit = _number(m, "seconds.fit", path, optional=True)
    train = _fmt(_number(m, "seconds.train", path, optional=True), ".1f") + " s"
    if _number(m, "seconds.start", path, optional=True) is None:
        rows.append(["training time", train])
    else:  # an images fit: its training is the image stage, after its start
        rows += [["fit time", _fmt(fit, ".1f") + " s"]] if fit is not None else []
        rows += [[IMAGES_STAGES["train"] + " time", train]]
    return [Heading(f"neural-brdf report: {cfg.name}", 1), Table(["", ""], rows)]


def _physics(
    run: Run,
    albedo_png: bytes,
    reference: bool = True,
    azimuths: int = 0,
    measured: bool = True,
) -> list:
    """The physics section; the albedo figure's curves (plots.albedo_curve) are averaged
    over ``azimuths`` azimuths of wi, or with 0 both in the incidence plane; ``measured``:
    its neural curve is the validator's (metrics.json's furnace.curve)."""
    m, path = run.metrics, run.dir / "metrics.json"
    rows = []
    for name, c in m["checks"].items():
        value, limit = (_number(m, f"checks.{name}.{k}", path) for k in ("value", "limit"))
        op = ">=" if name == "min_value" else "<="
        shown = f"{value:.6f}" if name == "max_albedo" else f"{value:.3g}"
        theta = _number(m, f"checks.{name}.at_theta_deg", path, optional=True)
        stderr = _number(m, f"checks.{name}.quadrature_stderr", path, optional=True)
        if theta is not None:
            shown += f" at θi = {theta:.2f}°"
        if stderr is not None:
            shown += f" (± {stderr:.1g})"
        again = c.get("remeasured")
        if isinstance(again, int) and again > 0:  # validate.furnace's second measurement
            shown += f"; {again} direction{'s' if again > 1 else ''} over the limit measured again"
        verdict = Verdict(check_passed(name, value, limit, c.get("passed")))
        rows.append([name, shown, f"{op} {limit:.6g}", verdict])
    parity = _number(m, "export.parity_rel_error", path, optional=True)
    if parity is not None:
        # export's own limit: parity_tol, or a few times the network's float32 precision
        precision = _number(m, "export.float32_rel_precision", path, optional=True)
        tol = parity_allowed(run.config.export.parity_tol, precision or 0.0)
        verdict = Verdict(parity <= tol)
        rows.append(["torch vs onnxruntime parity", f"{parity:.2g}", f"<= {tol:.3g}", verdict])
    blocks = [
        Heading("Physics checks"),
        Text(
            "Reciprocity and non-negativity over random pairs (10 % within 1° of "
            "grazing); the white furnace: the directional albedo ρ(θi) = ∫ f cos θo "
            "dωo by quadrature, whose maximum must stay below 1 + tolerance."
        ),
        Table(["check", "value", "limit", "result"], rows),
    ]
    hemi = m.get("hemispherical_albedo")
    if isinstance(hemi, list) and hemi:
        values = (_number(m, f"hemispherical_albedo.{i}", path) for i in range(len(hemi)))
        blocks.append(
            Text(
                "Hemispherical albedo (R, G, B): "
                + ", ".join(f"{v:.4f}" for v in values)
                + (  # (validate: that of the texel where the maximum was found)
                    f" at uv ({uv_text(uv)}), the texel of the maximum albedo"
                    if isinstance(uv := m["checks"].get("max_albedo", {}).get("at_uv"), list)
                    else ""
                )
            )
        )
    raw_max = _number(m, "export.normalization.raw_max_albedo", path, optional=True)
    if raw_max is not None:
        n = m["export"]["normalization"]
        blocks.append(
            Text(
                f"Albedo normalisation: the raw network's max albedo was "
                f"{raw_max:.4f}; {n.get('nodes_above_1', '?')} of "
                f"{n.get('nodes', '?')} table nodes needed scaling"
                + (
                    " (none: the division is the identity and the graph omits it)"
                    if n.get("in_graph") is False
                    else ""
                )
                + (
                    f"; {n['refined_nodes']} estimated again with more points "
                    "(normalization.refine)."
                    if isinstance(n.get("refined_nodes"), int) and n["refined_nodes"] > 0
                    else "."
                )
            )
        )
    blocks.append(
        Image(
            "albedo",
            "Directional albedo (white furnace)",
            (
                f"ρ(θi) per channel at uv {TEXTURED_UV}, the figures' uv, with wi in the "
                "incidence plane: the neural curve by quadrature"
                + (", the reference's too" if reference else "")
                + "; the dotted line is the furnace limit 1 (the validator's maximum over "
                "the texture is in the table above)."
                if getattr(run.model, "textured", False)  # (a test's run without a model)
                else "ρ(θi) per channel, "
                + (
                    f"both curves averaged over {azimuths} azimuths of wi (an anisotropic "
                    "model, as the validator's furnace measures it)"
                    if azimuths
                    else "wi in the incidence plane"
                )
                + ": the neural curve "
                + ("as the validator measured it" if measured else "by quadrature")
                + (", the reference's by the same quadrature" if reference else "")
                + "; the dotted line is the furnace limit 1, the cross the validator's "
                "measured maximum."
            ),
            albedo_png,
        )
    )
    return blocks


def _accuracy(run: Run, note: str | None, images: list[Image]) -> list:
    m, path = run.metrics, run.dir / "metrics.json"
    blocks: list[Block] = [Heading("Accuracy")]
    if note:
        blocks.append(Text(note, note=True))
    if isinstance(m.get("accuracy"), dict):
        rows = [
            [
                "rel. RMSE of f cos θo (all pairs)",
                f"{100 * _number(m, 'accuracy.rel_rmse', path):.3f} %",
            ]
        ]
        bands = m["accuracy"].get("rel_rmse_by_incidence")
        for band, v in bands.items() if isinstance(bands, dict) else ():
            v = None if v is None else _as_number(v, f"accuracy.rel_rmse_by_incidence.{band}", path)
            rows.append([f"rel. RMSE, {band}", "-" if v is None else f"{100 * v:.3f} %"])
        rows.append(["NBRDF log error", f"{_number(m, 'accuracy.nbrdf_log_error', path):.3g}"])
        pairs = _number(m, "accuracy.pairs", path, optional=True)
        # measured data are compared on every measured bin, which training draws from
        # (an earlier run's metrics.json lacks pairs_from: its reference, the reader's
        # describe(), starts with the name of a registered format)
        binned = m["accuracy"].get("pairs_from") == "measured bins" or str(
            m.get("reference", "")
        ).startswith(tuple(f"{f.name} " for f in formats.all_formats()))
        where = (
            "measured bin centres (every bin of the file, which training draws its pairs "
            "from: none is held out)"
            if binned
            else "held-out pairs"
        )
        blocks += [
            Text(
                f"Against the target on {_fmt(pairs, '.0f')} {where} "
                "(neural_brdf/validate.py): the relative RMSE of f cos θo, overall "
                "and by bands of cos θi, and the NBRDF log error, the mean of "
                "|log(1 + f̂ cos θo) − log(1 + f cos θo)|."
            ),
            Table(["metric", "value"], rows),
        ]
    if isinstance(m.get("peak"), dict):
        blocks += _peak(m["peak"], path)
    return blocks + images


def _peak(peak: dict, path: Path) -> list:
    """The validator's peak check: model / target at and near the mirror direction."""
    value, limit, ok = peak_figures(peak, path)
    given = peak.get("pairs")
    pairs: list = given if isinstance(given, list) else []
    offsets = sorted({p["offset_deg"] for p in pairs if isinstance(p, dict)})
    rows = []
    keys = sorted({(p["phi_deg"], p["theta_deg"], p["way"]) for p in pairs if p["offset_deg"]})
    for phi, theta, way in keys:
        # the pair at the mirror direction itself (offset 0) heads every row
        errors = {
            p["offset_deg"]: p["error"]
            for p in pairs
            if (p["phi_deg"], p["theta_deg"]) == (phi, theta)
            and (p["way"] == way or p["offset_deg"] == 0.0)
        }
        rows.append(
            [f"{theta:g}°", f"{phi:g}°", way]
            + [f"{100 * errors[o]:.2f} %" if o in errors else "-" for o in offsets]
        )
    verdict = "passed" if ok else "FAILED"
    return [
        Text(
            f"At the highlight's peak: {100 * value:.2f} % (limit {100 * limit:g} %, {verdict}). "
            "The largest |f̂ / f − 1| over RGB with wo at the exact mirror direction of wi and "
            "0.01 to 1 degree off it, towards the normal, towards the horizon and across the "
            "plane of incidence (both tangent planes for an anisotropic model). A defect "
            "there, such as a notch a fraction of a degree wide, is the visible highlight of "
            "a smooth material, yet it hardly moves the mean error above."
        ),
        Table(
            ["θi", "φi", "towards"] + [f"{o:g}°" for o in offsets],
            rows,
        ),
    ]


def teacher_to_render(model, reference) -> tuple[Any, str] | None:
    """The Mitsuba BSDF object that ``model`` (a :class:`neural_brdf.runtime.NeuralBRDF`)
    is rendered beside when ``reference`` is a Mitsuba teacher, homogeneous or textured
    (:func:`neural_brdf.train.data.build_target`'s), and the caption's words on it; None
    for any other reference (an analytic one is rendered from its name and parameters).

    A file that carries its teacher's normal field renders beside the whole teacher
    (normal or bump map included); any other beside the nested BSDF, and the words say
    that the teacher's map is left out only when it has one.  InputError when the
    teacher was loaded in another Mitsuba variant than the one the render runs in."""
    if getattr(reference, "kind", None) != "mitsuba" or getattr(reference, "bsdf", None) is None:
        return None
    import mitsuba as mi

    variant = getattr(reference, "variant", None)
    if variant is not None and mi.variant() != variant:
        raise InputError(
            f"the teacher was loaded in Mitsuba's {variant} variant and the render runs "
            f"in {mi.variant()}"
        )
    bsdf = reference.bsdf
    words = "Mitsuba's own BSDF"
    normal = getattr(reference, "normal_map", None)  # a textured teacher's map, if any
    if normal is not None:
        what = "bump map" if normal.get("plugin") == "bumpmap" else "normal map"
        if model.textured and model.has_normal_field:
            bsdf = getattr(reference, "whole_bsdf", bsdf)
            words += f", {what} included"
        else:
            words += f", its {what} left out as the file's is"
    if getattr(reference, "excess", None) is not None:  # the model learned it bounded
        words += ", its albedo above 1 not bounded as the model's is"
    return bsdf, words


def _rendering(run: Run, render: bool, reference) -> list:
    blocks = [Heading("Rendering")]
    why = (
        "rendering was switched off for this report" if not render else plots.mitsuba_unavailable()
    )
    if why:
        return blocks + [Text(f"No render: {why}.", note=True)]
    cfg = run.config
    ref = None
    if reference is not None and cfg.target.data is None and cfg.target.mitsuba is None:
        ref = {"model": cfg.target.model, "params": dict(cfg.target.params)}  # analytic
    with tempfile.TemporaryDirectory() as tmp:  # (read back: the PNG is embedded)
        png_path = Path(tmp) / "render.png"
        try:
            # a Mitsuba teacher, homogeneous or textured, is rendered by Mitsuba itself
            teacher, words = teacher_to_render(run.model, reference) or (None, "")
            psnr = plots.spheres(
                run.dir / "model.onnx",
                png_path,
                reference=ref,
                reference_bsdf=teacher,
                spp=RENDER_SPP,
                resolution=RENDER_RESOLUTION,
            )
        except InputError as e:  # e.g. an ONNX op the Mitsuba plugin lacks
            return blocks + [Text(f"No render: {e}.", note=True)]
        png = png_path.read_bytes()
    from neural_brdf.renderers.render import ERROR_GAIN

    caption = f"Mitsuba 3 preview, {RENDER_SPP} spp: neural"
    if teacher is not None:
        caption += (
            f" | the teacher ({words}) | "
            f"{ERROR_GAIN:g} x |difference| (PSNR {psnr:.1f} dB, Monte Carlo noise included)"
        )
    elif ref is not None:
        caption += (
            f" | reference | {ERROR_GAIN:g} x |difference| (PSNR {psnr:.1f} dB of "
            "neural against the reference, Monte Carlo noise included)"
        )
    return blocks + [Image("render", "Rendered spheres", caption, png, zoom=2)]


def _stored_lobe(path: Path) -> dict | None:
    """The sampling lobe in a model file's metadata, or None (older files, bad ones)."""
    from neural_brdf.fileformat import lobe as lobe_format
    from neural_brdf.fileformat import reader

    try:
        return lobe_format.from_metadata(reader.props(reader.load(path, external_data=False)))
    except InputError:  # unreadable, or a malformed lobe: the viewer then fits one
        return None


def _textured_viewer(run: Run, reference) -> list:
    """A textured model's viewer: its textured sphere beside its Mitsuba teacher's
    (evaluated when the report is written), or alone when the teacher is not at hand."""
    from neural_brdf.viewer import page as viewer

    try:
        models = [viewer.onnx_model(run.dir / "model.onnx", "neural")]
        if getattr(reference, "spatially_varying", False):
            name = Path(getattr(reference, "source", "teacher")).name
            models.append(viewer.teacher_model(reference, f"teacher: {name}", textured=True))
    except InputError as e:
        return [Text(f"No viewer: {e}.", note=True)]
    page = viewer.page(models, title=f"neural-brdf viewer: {run.config.name}")
    vs = " beside its Mitsuba teacher, with a difference view" if len(models) > 1 else ""
    return [
        Text(
            f"{VIEWER_FILE} draws the textured model{vs} in WebGL2 with the GLSL generated "
            "from its ONNX graph (its textures bound as the generated code expects): a lit "
            "textured sphere with a draggable light (with the teacher: snapped to the "
            f"{len(viewer.TEACHER_LIGHTS)} lights it was evaluated at), and the slices, "
            "the polar lobe and the albedo curve at chosen points uv.  It is written "
            "beside this report and carried inside it (the link saves it)."
        ),
        Attachment(
            VIEWER_FILE,
            f"Save {VIEWER_FILE} (interactive viewer, {len(page) // 1024} KiB)",
            page.encode("utf-8"),
        ),
    ]


def _viewer(run: Run, reference, curves: dict | None = None) -> list:
    """The interactive WebGL2 viewer (neural_brdf.viewer.page) of the model, beside its analytic
    target when it has one; a note when the GLSL code generator cannot translate it.
    ``curves``: the albedo curves of the report's plot (plots.albedo_curve's ``values``),
    shown by the page too."""
    from neural_brdf.viewer import page as viewer

    blocks = [Heading("Interactive viewer")]
    cfg = run.config
    curves = curves or {}
    if run.model.textured:
        return blocks + _textured_viewer(run, reference)

    def page_curve(key: str) -> dict | None:
        theta = curves.get(f"{key}_theta", curves.get("theta"))
        return viewer.curve(theta, curves[key]) if key in curves else None

    try:
        models = [viewer.onnx_model(run.dir / "model.onnx", "neural", albedo=page_curve("neural"))]
        if reference is not None and cfg.target.data is None and cfg.target.mitsuba is None:
            models.append(
                viewer.analytic_model(
                    cfg.target.model,
                    dict(cfg.target.params),
                    f"target: {cfg.target.model}",
                    albedo=page_curve("reference"),
                    lobe=_stored_lobe(run.dir / "model.onnx"),  # unused by the page
                )
            )
        elif cfg.target.mitsuba is not None and hasattr(reference, "teacher"):
            name = Path(cfg.target.mitsuba).name  # Mitsuba's eval, evaluated here
            models.append(viewer.teacher_model(reference, f"teacher: {name}", textured=False))
    except InputError as e:  # no code generator, or an op it does not know
        return blocks + [Text(f"No viewer: {e}.", note=True)]
    page = viewer.page(models, title=f"neural-brdf viewer: {cfg.name}")
    vs = " (beside its target, with a difference view)" if len(models) > 1 else ""
    if len(models) > 1 and models[1].tabulated is not None:
        vs = (
            " (beside its Mitsuba teacher, with a difference view; the teacher was "
            f"evaluated for {len(viewer.TEACHER_LIGHTS)} lights, to which the light snaps)"
        )
    return blocks + [
        Text(
            f"{VIEWER_FILE} draws the model{vs} in WebGL2 with the GLSL generated from its "
            "ONNX graph: a lit sphere with a draggable light, incidence-plane slices, the "
            "polar lobe and the albedo curve.  It is written beside this report and "
            "carried inside it (the link saves it); open it in a browser."
        ),
        Attachment(
            VIEWER_FILE,
            f"Save {VIEWER_FILE} (interactive viewer, {len(page) // 1024} KiB)",
            page.encode("utf-8"),
        ),
    ]


# the Training table: metrics.json's seconds.KEY in this order; an images fit's train is
# its image stage, after its start, and its fit the two with the checks around them
STAGES = ("start", "train", "fit", "export", "validate", "report", "total")
IMAGES_STAGES = {
    "start": "start (the families' fits, the choice, the distillation)",
    "train": "image stage",
    "fit": "whole fit (start included)",
}


def _training(run: Run) -> list:
    m, path, log = run.metrics, run.dir / "metrics.json", run.log
    labels = IMAGES_STAGES if _number(m, "seconds.start", path, optional=True) is not None else {}
    rows = [
        [labels.get(k, k), f"{_number(m, f'seconds.{k}', path):.1f} s"]
        for k in STAGES
        if _number(m, f"seconds.{k}", path, optional=True) is not None
    ]
    blocks: list[Block] = [Heading("Training")]
    if rows:
        blocks.append(Table(["stage", "time"], rows))
    if run.images:  # the fit's losses are drawn in its own section
        return blocks
    if len(log["step"]):
        blocks.append(
            Image(
                "loss",
                "Training curve",
                "Loss per logged step (log scale) and the held-out relative RMSE "
                "of f cos θo of the raw network (before normalisation).",
                plots.png_bytes(
                    plots.loss_curve(log["step"], log["loss"], log["val_step"], log["val_rel_rmse"])
                ),
            )
        )
    else:
        blocks.append(Text("No training steps were logged.", note=True))
    return blocks


TEXTURED_UV = (0.5, 0.5)  # where a textured model's figures are drawn


def _lobe_colour(tex: dict) -> str:
    """How the file's lobes get their colour (its ``texture.lobe_color``; older files: rgb)."""
    text = ""
    if tex.get("lobe_color") == "grey":
        text = " (grey: one output each, coloured by per-channel weights)"
    heads = tex.get("analytic_heads")
    if isinstance(heads, dict):  # texture.analytic_heads: the last lobes are closed forms
        text += f", the last {len(heads.get('heads', []))} analytic {heads.get('kind', '')} heads"
        text += " with a roughness α(uv) in the field"
    return text


def _textured_note(run: Run) -> list:
    """What a textured model's sections show (uv, the teacher's excess, the normal map)."""
    if not run.model.textured:
        return []
    tex = run.model.info.texture or {}
    res = tex.get("resolution") or ["?", "?"]
    text = (
        f"A textured model: f(wi, wo, uv) = Σk zk(uv) gk(wi, wo), {tex.get('lobes', '?')} "
        f"shared lobes{_lobe_colour(tex)} and a {res[0]} × {res[1]} field of their weights "
        "(wrapping, bilinear). The physics checks are at random uv (the furnace at "
        f"{len(run.metrics.get('furnace', {}).get('uv', []))} points, its largest albedo "
        f"at uv {_uv_or_unknown(run.metrics.get('checks', {}).get('max_albedo', {}))}); the "
        "accuracy is at random uv against the teacher's own eval; the figures below are at "
        f"uv {TEXTURED_UV}."
    )
    field = run.metrics.get("normal_field")
    if isinstance(field, dict) and field.get("in_file"):
        source = (tex.get("normal_field") or {}).get("source", "normal map")
        text += (
            f" The file carries the teacher's normal field ({source}, "
            f"applied by the renderer as a frame rotation): at {field.get('uv')} random uv it is "
            f"within {field.get('max_deg', 0):.3g}° of the teacher's (mean "
            f"{field.get('mean_deg', 0):.2g}°; the teacher tilts up to "
            f"{field.get('teacher_max_tilt_deg', 0):.3g}°)."
        )
    elif isinstance(field, dict):
        text += (
            f" The teacher has a normal map (tilts up to "
            f"{field.get('teacher_max_tilt_deg', 0):.3g}°) that this file does not carry."
        )
    projection = (run.metrics.get("training") or {}).get("projection")
    if isinstance(projection, dict):
        scaled = 100 * projection.get("bounded_texel_share", 0)
        text += (
            f" The field was projected onto the trained lobes at {projection.get('resolution')}"
            f"² texels (texture.project: each texel's weights fitted to the teacher on "
            f"{projection.get('pairs_per_texel')} pairs at its centre, in "
            f"{projection.get('seconds', 0):.0f} s; {scaled:.0f} % of the texels scaled down "
            "by the lobes' bound)."
        )
        refit = projection.get("refit")
        if isinstance(refit, dict):
            text += (
                f" Then the lobes were trained {refit.get('steps')} more steps on the "
                f"projected field (texture.refit_steps, in {refit.get('seconds', 0):.0f} s) "
                "and bounded again."
            )
    excess = run.metrics.get("teacher_excess")
    if isinstance(excess, dict):
        text += (
            f" The teacher's albedo reaches {excess.get('max_albedo', 0):.4f} (at uv "
            f"{excess.get('at_uv')}): the model learns its energy-bounded version."
        )
    return [Text(text, note=True)]


def _blocks(run: Run, render: bool) -> list:
    reference, note = reference_of(run.config)
    check_textured(reference, textured=run.model.textured, where=str(run.dir / "model.onnx"))
    neural = run.model.eval
    ref = reference.eval if reference is not None else None
    sampler = reference if hasattr(reference, "sample_t") else None
    if run.model.textured:  # the figures at one uv; the teacher's sampler depends on uv
        neural = at_uv(neural, TEXTURED_UV)
        ref = at_uv(ref, TEXTURED_UV) if ref is not None else None
        sampler = None
    m, path = run.metrics, run.dir / "metrics.json"
    theta = _number(m, "checks.max_albedo.at_theta_deg", path, optional=True)
    validated = None if theta is None else (theta, _number(m, "checks.max_albedo.value", path))
    samples = run.config.validation.furnace_samples  # as many as the validator's
    curves: dict = {}  # the albedo curves, computed once for the plot and the viewer
    curve = m.get("furnace", {}).get("curve") if isinstance(m.get("furnace"), dict) else None
    measured = None
    if run.model.textured:
        # the validator's curve and maximum are at its worst texel, and the figures (and
        # the teacher's curve) at TEXTURED_UV: the neural curve there too, by quadrature
        validated = None
    elif isinstance(curve, dict) and curve.get("theta_deg") and curve.get("rho"):
        measured = (curve["theta_deg"], curve["rho"])  # the validator's: no second quadrature
    # the validator's curve of an anisotropic model is averaged over azimuth: the
    # reference's too, over as many azimuths, so that like is drawn beside like
    azimuths = AZIMUTHS if measured is not None and is_anisotropic(run.config.model.encoding) else 0
    albedo = plots.png_bytes(
        plots.albedo_curve(
            neural,
            ref,
            samples=samples,
            sampler=sampler,
            validated_max=validated,
            values=curves,
            measured=measured,
            azimuths=azimuths,
        )
    )
    vs = "neural (solid) against the reference (dashed)" if ref is not None else "neural"
    figures = [
        Image(
            "slices",
            "Incidence-plane slices",
            f"f cos θo in the incidence plane (x-z) at θi = 0, 30, 60, 80°, log scale, "
            f"{vs}, per RGB channel.",
            plots.png_bytes(plots.incidence_slices(neural, ref)),
        ),
        Image(
            "lobes",
            "Polar lobes",
            f"The same slices as lobes (luminance), {vs}.",
            plots.png_bytes(plots.polar_lobes(neural, ref)),
        ),
        Image(
            "rusinkiewicz",
            "(θh, θd) slice",
            "log10 luminance of f over the half and difference angles at φd = 90°"
            + (", and the relative error of the neural model." if ref is not None else "."),
            plots.png_bytes(plots.rusinkiewicz_images(neural, ref)),
        ),
    ]
    if run.images:  # no target: the fit's own section, and the model's figures alone
        middle = images.section(run) + [Heading("The fitted BRDF")]
        middle += [Text(note, note=True)] if note else []
        middle += figures
    else:
        middle = _accuracy(run, note, figures)
    return (
        _summary(run)
        + _textured_note(run)
        + _physics(run, albedo, ref is not None, azimuths, measured is not None)
        + middle
        + _rendering(run, render, reference)
        + _viewer(run, reference, curves)
        + _training(run)
        + [
            Heading("Config"),
            Text("The resolved config.yaml of the run."),
            Code(run.config_text, "yaml"),
        ]
    )


def _uv_or_unknown(check: dict) -> str:
    """The furnace's uv of its largest albedo, as the tables print it (``validate.uv_text``)."""
    uv = check.get("at_uv")
    return f"({uv_text(uv)})" if isinstance(uv, list) and len(uv) == 2 else "unknown"
