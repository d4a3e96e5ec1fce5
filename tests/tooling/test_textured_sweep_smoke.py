"""benchmarks/textured_sweep.py's machinery, at smoke budgets (``--smoke``: 20 steps, a
16k pool, a 32^2 projection with 16 pairs per texel, 20 refit steps, 2,000 scoring
pairs; the figures mean nothing; about a minute): a roughplastic teacher (no
roughness map: the breakdown by roughness is skipped, not a crash, which it was) with
grey lobes, and ``--cost`` (each file rendered in the BSDF-bound scene after the jobs).
The JSON is read back and checked against the files the run left in its work folder."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import onnx
import pytest

pytestmark = pytest.mark.mitsuba

REPO = Path(__file__).resolve().parents[2]


def test_a_roughplastic_smoke_run_with_grey_lobes_and_its_render_cost(tmp_path):
    out = tmp_path / "sweep.json"
    cmd = [
        sys.executable, str(REPO / "benchmarks" / "textured_sweep.py"), "--smoke",
        "--kind", "roughplastic", "--only", "grey_1start", "--seeds", "0",
        "--jobs", "1", "--threads", "1", "--cost", "1",
        "--work", str(tmp_path / "work"), "--out", str(out),
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    d = json.loads(out.read_text())
    assert d["teacher"].startswith("write_teacher(roughplastic")
    (run,) = d["runs"]
    assert "error" not in run, run.get("error")
    assert run["variant"] == "grey_1start" and len(run["rel_rmse_fixed_sets"]) == 2
    assert "roughness" not in run["breakdown"][0]  # no map, no breakdown by it
    # the file the run scored has grey lobes: K rows in the network's last layer
    proto = onnx.load(str(tmp_path / "work" / "grey_1start_s0" / "model.onnx"))
    (head,) = [t for t in proto.graph.initializer if t.name.endswith("mlp.head.weight")]
    assert tuple(head.dims)[0] == 4  # the recipe's K = 4 lobes, one output each
    cost = d["render_cost"]
    assert list(cost["best_s"]) == ["grey_1start_s0"] and cost["best_s"]["grey_1start_s0"] > 0
    assert cost["repeats"] == 1 and len(cost["render_wall_s"]["grey_1start_s0"]) == 1
