"""Training runs: determinism, resume, Ctrl-C, divergence, export parity and metadata."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import neural_brdf
from analytic import physics
from neural_brdf import config, export, fileformat, pipeline, validate
from neural_brdf.train import data, loop

CONFIGS = Path(__file__).resolve().parents[2] / "configs"

# Small everything: these runs check mechanics, not accuracy.
TINY = [
    "train.steps=12",
    "train.warmup=2",
    "train.checkpoint_every=5",
    "train.log_every=2",
    "train.eval_every=4",
    "train.progress=false",
    "model.hidden=[16,16]",
    "data.batch_size=256",
    "data.pool_size=2048",
    "normalization.table_size=17",
    "normalization.grid_size=7",
    "normalization.samples=2048",
    "validation.furnace_dirs=6",
    "validation.furnace_samples=4096",
    "validation.pairs=2000",
    "validation.accuracy_samples=2048",
    "export.parity_pairs=512",
]


def tiny(*extra, preset="lambert"):
    return config.load(CONFIGS / f"{preset}.yaml", TINY + list(extra))


def weights(run_dir: Path) -> dict:
    return torch.load(run_dir / "ckpt.pt", weights_only=True)["model"]


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_training_is_deterministic_per_seed(tmp_path):
    loop.train(tiny(), tmp_path / "a")
    loop.train(tiny(), tmp_path / "b")
    loop.train(tiny("train.seed=1"), tmp_path / "c")
    assert same(weights(tmp_path / "a"), weights(tmp_path / "b"))
    assert not same(weights(tmp_path / "a"), weights(tmp_path / "c"))


def test_resume_continues_exactly(tmp_path):
    # a constant schedule, so that stopping at step 5 changes nothing but the stop
    const = "train.schedule=constant"
    loop.train(tiny(const), tmp_path / "straight")
    loop.train(tiny(const, "train.steps=5"), tmp_path / "split")
    assert torch.load(tmp_path / "split" / "ckpt.pt", weights_only=True)["step"] == 5
    _, fig = loop.train(tiny(const), tmp_path / "split", resume=True)
    assert same(weights(tmp_path / "straight"), weights(tmp_path / "split"))
    # the loop's record names the resume and what changed there (train.steps alone)
    assert fig["resumes"] == [{"step": 5, "changed": {"train.steps": [5, 12]}}]
    with open(tmp_path / "split" / "log.csv") as fh:
        steps = [int(r["step"]) for r in csv.DictReader(fh)]
    assert steps == sorted(set(steps)) and steps[-1] == 12


def test_device_auto_and_cpu_give_the_same_weights_and_record_the_device(tmp_path):
    # auto is cuda where torch sees a GPU, else cpu: on a CPU machine it must be the cpu run
    _, fig_cpu = loop.train(tiny("train.device=cpu"), tmp_path / "cpu")
    _, fig_auto = loop.train(tiny("train.device=auto"), tmp_path / "auto")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert fig_cpu["device"] == "cpu" and fig_auto["device"].startswith(expected)
    if expected == "cpu":
        assert same(weights(tmp_path / "cpu"), weights(tmp_path / "auto"))
    # checkpoints hold CPU tensors whatever the device, so any machine can resume them
    assert all(v.device.type == "cpu" for v in weights(tmp_path / "auto").values())


def test_device_cuda_trains_on_a_gpu_or_is_refused_by_name(tmp_path):
    cfg = tiny("train.device=cuda")
    if torch.cuda.is_available():
        raw, fig = loop.train(cfg, tmp_path / "gpu")
        assert fig["device"].startswith("cuda") and next(raw.parameters()).device.type == "cpu"
    else:
        with pytest.raises(config.ConfigError, match=r"^train\.device: cuda"):
            loop.train(cfg, tmp_path / "gpu")
        assert not (tmp_path / "gpu" / "ckpt.pt").exists()


def test_device_must_be_cpu_cuda_or_auto():
    with pytest.raises(config.ConfigError, match="train.device"):
        tiny("train.device=tpu")


def test_resume_refuses_a_different_model(tmp_path):
    loop.train(tiny("train.steps=3"), tmp_path / "r")
    with pytest.raises(config.ConfigError, match="model"):
        loop.train(tiny("model.hidden=[8]"), tmp_path / "r", resume=True)


def test_ctrl_c_leaves_a_resumable_checkpoint(tmp_path, monkeypatch):
    real_batch = data.Pool.batch
    calls = {"n": 0}

    def batch(self):
        calls["n"] += 1
        if calls["n"] == 4:  # Ctrl-C arrives in the middle of step 4
            os.kill(os.getpid(), signal.SIGINT)
        return real_batch(self)

    monkeypatch.setattr(data.Pool, "batch", batch)
    with pytest.raises(loop.Interrupted, match="--resume"):
        loop.train(tiny(), tmp_path / "i")
    ckpt = torch.load(tmp_path / "i" / "ckpt.pt", weights_only=True)
    assert ckpt["step"] == 4  # the step in flight was completed, then saved
    monkeypatch.setattr(data.Pool, "batch", real_batch)
    loop.train(tiny(), tmp_path / "i", resume=True)
    loop.train(tiny(), tmp_path / "ref")
    assert same(weights(tmp_path / "i"), weights(tmp_path / "ref"))


def test_divergence_stops_and_keeps_a_good_checkpoint(tmp_path, monkeypatch):
    real_loss = loop.loss_fn
    calls = {"n": 0}

    def loss_fn(*args, **kwargs):
        calls["n"] += 1
        loss = real_loss(*args, **kwargs)
        return loss * float("nan") if calls["n"] == 8 else loss  # step index 7

    monkeypatch.setattr(loop, "loss_fn", loss_fn)
    with pytest.raises(loop.Diverged, match="checkpoint"):
        loop.train(tiny("train.checkpoint_every=3"), tmp_path / "d")
    ckpt = torch.load(tmp_path / "d" / "ckpt.pt", weights_only=True)
    assert ckpt["step"] == 6  # the last checkpoint before the NaN
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values())


@pytest.fixture(scope="module")
def gold_run(tmp_path_factory):
    """A short anisotropic-capable microfacet run, exported (shared by the tests below):
    the 3 x 64 network, whose torch and onnxruntime agree to 1e-5 everywhere (a grid
    model's may differ by twice its float32 precision: export.export)."""
    run_dir = tmp_path_factory.mktemp("gold")
    cfg = tiny("train.steps=30", "model.encoding=anisotropic", preset="mlp/gold")
    report = pipeline.run(cfg, run_dir)
    return run_dir, cfg, report


def test_run_writes_the_contract_files(gold_run):
    run_dir, cfg, report = gold_run
    for name in ["config.yaml", "ckpt.pt", "log.csv", "model.onnx", "metrics.json"]:
        assert (run_dir / name).is_file(), name
    assert config.load(run_dir / "config.yaml") == cfg
    assert report["passed"] is True
    assert set(report["checks"]) == {"reciprocity", "min_value", "max_albedo"}
    assert 0.0 <= report["accuracy"]["rel_rmse"]


def test_export_is_one_file_with_dynamic_batch_and_metadata(gold_run):
    run_dir, cfg, _ = gold_run
    proto = onnx.load(run_dir / "model.onnx")
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in proto.graph.initializer)
    assert not list(run_dir.glob("*.onnx.data"))
    model = neural_brdf.load(run_dir / "model.onnx")
    meta = model.metadata
    for key in [
        "format_version",
        "frame",
        "encoding",
        "target",
        "max_albedo",
        "reciprocity_error",
        "training_config",
    ]:
        assert meta.get(key), key
    assert meta["encoding"] == "anisotropic"
    assert config.from_dict(model.config) == cfg
    assert float(meta["max_albedo"]) <= 1.0 + cfg.validation.albedo_tol
    for n in [1, 3, 1000]:
        wi = physics.random_directions(n, 1)
        wo = physics.random_directions(n, 2)
        assert model.eval(wi, wo).shape == (n, 3)
    assert model.eval(np.zeros((2, 5, 3)) + [0, 0, 1], [0, 0, 1]).shape == (2, 5, 3)


def test_torch_and_onnxruntime_agree(gold_run, tmp_path):
    run_dir, cfg, _ = gold_run
    ckpt = export.load_checkpoint(run_dir / "ckpt.pt")
    raw = export.raw_from_checkpoint(ckpt, cfg)
    target = data.build_target(cfg.target)
    torch_model, _ = export.normalized_model(raw, cfg, target)
    onnx_model = neural_brdf.load(run_dir / "model.onnx")
    pairs = export.parity_pairs(4096, 77)
    wi, wo = pairs[:, :3], pairs[:, 3:]
    with torch.no_grad():
        ref = torch_model(wi, wo).double().numpy()
    got = onnx_model.eval(wi.numpy(), wo.numpy()).astype(np.float64)
    assert (ref > 0).any() and (ref == 0).any()  # both sides of the horizon were tested
    assert np.array_equal(got[ref == 0], ref[ref == 0])
    floor = 0.1 * ref[ref > 0].mean()  # see export.PARITY_FLOOR
    assert np.max(np.abs(got - ref) / np.maximum(np.abs(ref), floor)) <= 1e-5


def test_export_cli_function_rebuilds_the_same_model(gold_run, tmp_path):
    run_dir, _, _ = gold_run
    info = export.export_run(run_dir, tmp_path / "again.onnx", measure=validate.physics)
    a = neural_brdf.load(run_dir / "model.onnx")
    b = neural_brdf.load(tmp_path / "again.onnx")
    wi, wo = physics.random_directions(500, 3), physics.random_directions(500, 4)
    assert np.array_equal(a.eval(wi, wo), b.eval(wi, wo))
    assert info["parity_rel_error"] <= 1e-5


def test_validation_flags_a_non_physical_model(tmp_path):
    """An exported raw network (no normalisation) with huge outputs fails the furnace."""
    raw = loop.RawBRDF("isotropic", [8], "silu", init_value=50.0).eval()
    path = tmp_path / "raw.onnx"
    path.write_bytes(export.to_onnx_bytes(raw, 17))
    settings = config.Validation(furnace_dirs=4, furnace_samples=1024, pairs=1000)
    report = validate.report(path, settings=settings)
    assert report["passed"] is False
    assert report["checks"]["max_albedo"]["passed"] is False
    assert report["checks"]["reciprocity"]["passed"] is True


def test_exported_run_is_total_over_hostile_rows(gold_run):
    """export() writes the total graph: NaN/inf/zero rows give 0, scaled rows don't matter."""
    run_dir, _, _ = gold_run
    brdf = neural_brdf.load(run_dir / "model.onnx")
    rng = np.random.default_rng(0)
    wi = np.abs(rng.normal(size=(64, 3))).astype(np.float32)
    wo = np.abs(rng.normal(size=(64, 3))).astype(np.float32)
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    ref = brdf.eval(wi, wo)
    wi[3], wi[4], wo[5] = [np.nan, 0, 1], [0, 0, 0], [0, np.inf, 1]
    wo[6:] *= 3.0
    got = brdf.eval(wi, wo)
    assert np.array_equal(got[3:6], np.zeros((3, 3), np.float32))
    assert np.allclose(got[6:], ref[6:], rtol=1e-5, atol=0)


def test_run_files_get_normal_permissions(gold_run):
    """Atomic writes used to leave mkstemp's 0600; now 0666 less the umask, like open()."""
    run_dir, _, _ = gold_run
    mask = os.umask(0o022)
    os.umask(mask)
    for name in ("model.onnx", "metrics.json", "ckpt.pt", "config.yaml", "report.html"):
        assert os.stat(run_dir / name).st_mode & 0o777 == 0o666 & ~mask, name


def test_onnx_file_describes_itself(gold_run):
    run_dir, cfg, _ = gold_run
    proto = onnx.load(run_dir / "model.onnx")
    assert proto.producer_name == "neural-brdf"
    assert proto.producer_version == neural_brdf.__version__
    assert (
        proto.model_version
        == fileformat.FORMAT_VERSION
        == int(neural_brdf.load(run_dir / "model.onnx").metadata["format_version"])
    )
    doc = proto.doc_string
    target = data.build_target(cfg.target).describe()
    for needle in [target, "anisotropic", "wi, wo", "1/sr", "horizon", "albedo-normalised"]:
        assert needle in doc, needle


# ------------------------------------------------------------------ a killed process
KILL_STEPS = 600
KILL_SETS = TINY + [
    f"train.steps={KILL_STEPS}",
    "train.checkpoint_every=20",
    "train.log_every=10",
    "train.eval_every=0",
]


def train_cli(run_dir: Path, *extra: str) -> subprocess.Popen:
    sets = [a for kv in KILL_SETS for a in ("--set", kv)]
    env = dict(os.environ, PYTHONPATH=str(CONFIGS.parent))
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "neural_brdf",
            "train",
            "lambert",
            "--out",
            str(run_dir),
            *sets,
            *extra,
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def logged_steps(run_dir: Path) -> int:
    try:
        rows = (run_dir / "log.csv").read_text().splitlines()[1:]
    except OSError:
        return 0
    return max((int(r.split(",")[0]) for r in rows if r.count(",") >= 4), default=0)


@pytest.mark.slow
def test_sigkill_mid_run_then_resume_matches_an_uninterrupted_run(tmp_path):
    killed, straight = tmp_path / "killed", tmp_path / "straight"
    proc = train_cli(killed)
    deadline = time.monotonic() + 300
    while logged_steps(killed) < 120 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.kill()  # SIGKILL: no handler, no last checkpoint
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    step = torch.load(killed / "ckpt.pt", weights_only=True)["step"]
    assert 100 <= step < KILL_STEPS and not (killed / "model.onnx").exists()

    refused = train_cli(killed)  # no --resume: refused, nothing touched
    _, err = refused.communicate(timeout=300)
    assert refused.returncode == 2 and "--resume" in err and "Traceback" not in err
    resumed = train_cli(killed, "--resume")
    reference = train_cli(straight)
    for p in (resumed, reference):
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    a = json.loads((killed / "metrics.json").read_text())
    b = json.loads((straight / "metrics.json").read_text())
    assert a["training"]["steps"] == b["training"]["steps"] == KILL_STEPS
    assert a["training"]["final_loss"] == b["training"]["final_loss"]
    assert a["accuracy"] == b["accuracy"] and a["checks"] == b["checks"]
    assert same(weights(killed), weights(straight))
    with open(killed / "log.csv") as fh:
        steps = [int(r["step"]) for r in csv.DictReader(fh)]
    assert steps == list(range(10, KILL_STEPS + 1, 10))  # no row lost or repeated


def test_metrics_carry_the_furnace_curve_the_report_plots(gold_run):
    _, cfg, report = gold_run
    curve = report["furnace"]["curve"]
    theta, rho = np.array(curve["theta_deg"]), np.array(curve["rho"])
    # one row per polar angle: (furnace_dirs + 1) // 2 of them for an anisotropic model
    assert rho.shape == ((cfg.validation.furnace_dirs + 1) // 2, 3)
    assert np.all(np.diff(theta) > 0) and theta[0] == 0.0 and 80.0 < theta[-1] < 90.0
    # azimuth-averaged rows (an anisotropic model): none above the validator's maximum
    assert rho.max() <= report["checks"]["max_albedo"]["value"] + 1e-12
    assert rho.min() > 0.0
