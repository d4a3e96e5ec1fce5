"""The validator's verdicts and its seam with export (issue 28).

* ``neural-brdf validate`` exits 1 when any check of its report fails, the peak included
  (docs/cli.md); ``report["passed"]`` stays the physics verdict, training's;
* the physics measured on the graph before it is written (the pipeline's one
  measurement, for the metadata and metrics.json) is what validate measures on the file;
* the target is passed as ``target``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from cli_helpers import ROOT, TINY, cli
from neural_brdf import config, export, validate
from neural_brdf.train.model import RawBRDF

LAMBERT = ROOT / "configs" / "lambert.yaml"
GOLD = ROOT / "configs" / "quickstart.yaml"  # GGX gold: a highlight a dim network lacks


@pytest.fixture(scope="module")
def dim_model(tmp_path_factory):
    """A dim, nearly constant network (about 0.05/sr: reciprocal, positive, albedo about
    0.16), exported with the physics validate measured on its graph: every physics check
    passes, and against a gold target the peak fails."""
    cfg = config.load(LAMBERT, TINY)
    raw = RawBRDF("isotropic", [16, 16], "silu", init_value=0.05, grazing_power=0.0).eval()
    built = export.build(raw, cfg)
    phys = validate.physics(built.eval, anisotropic=built.anisotropic, settings=cfg.validation)
    path = tmp_path_factory.mktemp("dim") / "model.onnx"
    export.write(built, cfg, path, physics=phys, target_desc="a dim test network")
    return path, phys


@pytest.fixture(scope="module")
def against_gold(dim_model):
    return validate.report(dim_model[0], target=config.load(GOLD))


def test_validate_exits_1_when_only_the_peak_fails(capsys, dim_model, tmp_path):
    out = tmp_path / "report.json"
    code, stdout, err = cli(
        capsys, "validate", str(dim_model[0]), "--reference", str(GOLD), "--json", str(out)
    )
    report = json.loads(out.read_text())
    assert report["passed"] is True  # the physics
    assert report["peak"]["passed"] is False and "FAIL" in stdout
    assert code == 1, err


def test_passed_adds_the_peak_to_the_physics(dim_model, against_gold):
    assert validate.physics_passed(against_gold) and against_gold["passed"] is True
    assert against_gold["peak"]["passed"] is False
    assert validate.passed(against_gold) is False
    alone = validate.report(dim_model[0])  # no target: physics only, no peak
    assert "peak" not in alone and validate.passed(alone) is True
    failed = {**alone, "checks": {**alone["checks"], "min_value": {"passed": False}}}
    assert not validate.physics_passed(failed) and not validate.passed(failed)


def test_physics_measured_before_writing_is_what_the_file_gives(dim_model):
    """The pipeline measures the graph once, before writing it (its metadata needs the
    figures), and hands that to the report: the file itself gives the same."""
    path, phys = dim_model
    again = validate.report(path)
    for key in ("checks", "hemispherical_albedo", "furnace"):
        assert again[key] == phys[key], key


# ------------------------------------------------ the furnace's second measurement
def sharp_grazing(true_albedo: float):
    """A GGX mirror (alpha 0.05, no Fresnel) scaled so that its largest directional
    albedo, reached at grazing incidence, is ``true_albedo``: the lobe the furnace's
    fixed proposals fit worst there.  The scale comes from a 2^18-point quadrature."""
    import analytic
    from neural_brdf.physics import quadrature

    brdf = analytic.create("microfacet", alpha=0.05)
    theta = np.radians(90.0 - 0.01)
    wi = torch.tensor([[np.sin(theta), 0.0, np.cos(theta)]], dtype=torch.float64)
    top = quadrature.albedo(quadrature.from_numpy(brdf.eval), wi, 1 << 18, seed=99)[0].max()
    scale = true_albedo / float(top)
    return lambda a, b: scale * brdf.eval(a, b)


def furnace_verdicts(fn, refine: int) -> list[tuple[float, int]]:
    """(max albedo, directions measured again) of 256-point furnaces, eight seeds."""
    out = []
    for seed in range(8):
        s = config.Validation(
            furnace_samples=256, furnace_dirs=16, pairs=200, furnace_refine=refine, seed=seed
        )
        c = validate.physics(fn, anisotropic=False, settings=s)["checks"]["max_albedo"]
        out.append((c["value"], c["remeasured"]))
    return out


def test_a_furnace_over_the_limit_by_its_noise_alone_is_measured_again_and_passes():
    fn = sharp_grazing(0.95)
    once = furnace_verdicts(fn, refine=1)
    # the noise this guards against: a model at 0.95 read over 1 + 1e-3 by some seed
    assert any(v > 1.001 for v, _ in once), once
    assert all(n == 0 for _, n in once)
    again = furnace_verdicts(fn, refine=16)
    assert all(v <= 1.001 for v, _ in again), again
    for (v1, _), (v16, n) in zip(once, again):
        assert (n > 0) == (v1 > 1.001)  # only directions over the limit are measured again
        if n:
            assert abs(v16 - 0.95) < 0.02, v16  # ... and the second measurement is closer


def test_a_furnace_truly_over_the_limit_stays_over_it_measured_again():
    verdicts = furnace_verdicts(sharp_grazing(1.03), refine=16)
    assert all(v > 1.01 and n > 0 for v, n in verdicts), verdicts


def test_the_table_names_the_uv_of_a_textured_files_hemispherical_albedo():
    """A textured file's hemispherical albedo is that of the uv where the furnace found
    its largest albedo: the table says which (one texel's colour, not the material's)."""
    checks = {
        "reciprocity": {"value": 0.0, "limit": 1e-6, "passed": True},
        "max_albedo": {"value": 0.9, "limit": 1.001, "passed": True, "at_uv": [0.25, 0.75]},
    }
    report = {"checks": checks, "hemispherical_albedo": [0.8, 0.2, 0.1], "passed": True}
    report["model"] = "m.onnx"
    row = next(x for x in validate.format_table(report).splitlines() if "hemispherical" in x)
    assert "0.8000, 0.2000, 0.1000 (at uv 0.250, 0.750" in row
    checks["max_albedo"]["at_uv"] = [-0.75, 1.75]  # the furnace probes uv outside [0, 1)
    row = next(x for x in validate.format_table(report).splitlines() if "hemispherical" in x)
    assert "(at uv 0.250, 0.750" in row  # the same texel: textures repeat
    del checks["max_albedo"]["at_uv"]  # a homogeneous file's: no uv
    row = next(x for x in validate.format_table(report).splitlines() if "hemispherical" in x)
    assert "uv" not in row and "0.8000, 0.2000, 0.1000" in row


@pytest.mark.parametrize("scale", [1e-300, 1.0, 1e200])
def test_the_relative_rmse_does_not_depend_on_the_values_scale(scale):
    """A valid file of tiny values (a MERL file of 1e-300) squared to 0 and read a
    157-digit percentage; huge ones overflow the same way: the figure is a ratio, the
    same at any scale."""
    rng = np.random.default_rng(0)
    wo = np.tile([[0.0, 0.0, 1.0]], (64, 1))
    wi = wo.copy()
    ref = rng.uniform(0.5, 1.5, (64, 3))
    off = ref * (1.0 + rng.choice([-0.1, 0.1], (64, 3)))  # 10 % off everywhere
    got = validate._accuracy_report(wi, wo, ref * scale, off * scale)
    assert got["rel_rmse"] == pytest.approx(0.1, rel=1e-9)
    assert got["rel_rmse_by_incidence"]["cos_i 0.5-1"] == pytest.approx(0.1, rel=1e-9)


def test_accuracy_notes_name_what_the_physics_verdict_does_not_see():
    """train's exit code is the physics'; a peak beyond its limit (validate exits 1 on it)
    or a relative RMSE above POOR_ACCURACY gets a line of its own (a principled teacher
    at roughness 0 trained to 99.9 % with physics PASSED and nothing said)."""
    good = {
        "peak": {"value": 0.005, "limit": 0.03, "passed": True},
        "accuracy": {"rel_rmse": 0.004},
    }
    assert validate.accuracy_notes(good) == []
    assert validate.accuracy_notes({}) == []  # an images fit: neither figure
    off = {**good, "peak": {"value": 9.3, "limit": 0.03, "passed": False}}
    (line,) = validate.accuracy_notes(off)
    assert "peak is 930.00 % off" in line and "limit 3 %" in line and "validate" in line
    assert validate.accuracy_notes(off, peak=False) == []  # validate's exit code has it
    # as the table prints it: 3.006 % was "3.0 % off (limit 3 %)", which reads as within
    just = {**good, "peak": {"value": 0.03006, "limit": 0.03, "passed": False}}
    (line,) = validate.accuracy_notes(just)
    assert "peak is 3.01 % off" in line
    poor = {**good, "accuracy": {"rel_rmse": validate.POOR_ACCURACY + 0.1}}
    (line,) = validate.accuracy_notes(poor)
    assert "relative RMSE of f cos 60.0 %" in line and "does not reproduce" in line
    assert validate.accuracy_notes(poor, peak=False) == [line]
