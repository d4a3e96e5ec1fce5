"""A textured teacher with a normal map: the file carries its normal field (issue 30,
docs/model.md, "The normal field"), end to end through `neural-brdf train`.

One tiny run (a 16 x 16 procedural ``principled`` behind a ``normalmap``, 2 lobes, 20
steps; accuracy is not under test here).  The references are independent of the code
under test: Mitsuba's own normalmap texture evaluated through the teacher
(``TexturedMitsubaTarget.normal_field``), onnxruntime on the file, the raw ONNX graph.

* ``model.onnx`` has the outputs (f, n); its metadata ``texture.normal_field`` says how
  n is made and applied (source, resolution, the normalmap's two flags);
* n(uv) from onnxruntime (``runtime.load(...).normal``) is the teacher's normal at
  random uv, between texel centres and outside [0, 1) included, to float32 precision;
  ``metrics.json`` reports that distance, and it is not 0 for a flat field;
* ``neural-brdf export RUN`` from the checkpoint writes the same field;
* a teacher without a normal map gives a file with the one output f (covered by
  tests/train/test_textured_pipeline.py).
"""

from __future__ import annotations

import json
from html import unescape
from pathlib import Path

import numpy as np
import onnx
import pytest

from cli_helpers import cli

pytestmark = pytest.mark.mitsuba

SETTINGS = """\
target: {{mitsuba: {xml}}}
texture: {{lobes: 2, resolution: 4, validation_uv: 4}}
train: {{steps: 20, checkpoint_every: 20, log_every: 10, eval_every: 20, progress: false}}
data: {{pool_size: 4096, batch_size: 1024}}
validation: {{pairs: 1000, furnace_dirs: 32, furnace_samples: 2048, accuracy_samples: 4096}}
normalization: {{samples: 2048}}
export: {{parity_pairs: 256}}
"""


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    xml = write_teacher(tmp_path_factory.mktemp("teacher"), "principled", size=16, seed=2)
    return xml, TexturedMitsubaTarget(xml)


@pytest.fixture(scope="module")
def run(teacher, tmp_path_factory) -> Path:
    from neural_brdf.tooling.cli import main

    folder = tmp_path_factory.mktemp("normal_run")
    cfg = folder / "nf.yaml"
    cfg.write_text(SETTINGS.format(xml=teacher[0]))
    assert main(["train", str(cfg), "--out", str(folder / "run")]) == 0
    return folder / "run"


def random_uv(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.5, 2.5, (n, 2)).astype(np.float32)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def test_the_file_has_the_normal_output_and_its_metadata(run):
    proto = onnx.load(str(run / "model.onnx"))
    assert [o.name for o in proto.graph.output] == ["f", "n"]
    tex = json.loads({p.key: p.value for p in proto.metadata_props}["texture"])
    field = tex["normal_field"]
    assert field["output"] == "n" and field["source"] == "normalmap"
    assert field["resolution"] == [16, 16]  # the bitmap's own
    assert field["flip_invalid_normals"] is True and field["use_shadowing_function"] is True


def test_the_normal_is_the_teachers_between_texels(run, teacher):
    import neural_brdf

    model = neural_brdf.load(run / "model.onnx")
    assert model.has_normal_field
    uv = random_uv(5000, 3)
    got = model.normal(uv)
    ref = teacher[1].normal_field(uv)
    tilt = angle_deg(ref, [0.0, 0.0, 1.0])
    assert tilt.max() > 1.0  # the teacher's map tilts: a flat field would fail below
    assert angle_deg(got, ref).max() < 0.01
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), 1.0, atol=1e-6)
    # invalid uv: the unperturbed normal, never NaN
    bad = model.normal(np.array([[np.nan, 0.2], [np.inf, 0.1], [0.3, -np.inf]], np.float32))
    np.testing.assert_array_equal(bad, [[0, 0, 1]] * 3)
    m = json.loads((run / "metrics.json").read_text())["normal_field"]
    assert m["in_file"] is True and m["max_deg"] < 0.01
    assert m["teacher_max_tilt_deg"] > 1.0
    html = unescape((run / "report.html").read_text())
    assert "carries the teacher's normal field" in html and "normal map included" in html


def test_export_from_the_checkpoint_writes_the_same_field(run, capsys, tmp_path):
    import neural_brdf

    code, _, err = cli(capsys, "export", str(run), "-o", str(tmp_path / "again.onnx"))
    assert code == 0, err
    uv = random_uv(2000, 4)
    a = neural_brdf.load(run / "model.onnx").normal(uv)
    b = neural_brdf.load(tmp_path / "again.onnx").normal(uv)
    np.testing.assert_array_equal(a, b)
