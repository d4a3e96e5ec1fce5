"""Shared fixtures: where the independent reference data lives."""

from __future__ import annotations

from pathlib import Path

import pytest

# The reference data the tests compare with, in the repository (tests/data/README.md:
# each file's origin and terms), so that a clone alone runs the whole suite.
DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    assert DATA.is_dir(), f"reference data not found at {DATA} (tests/data/README.md)"
    return DATA


# The four real-data fixtures of the MERL tests: a diffuse, a plastic, a metallic paint
# and a metal, from the NBRDF networks fitted to the MERL measurements.
MATERIALS = ["white-diffuse-bball", "gray-plastic", "gold-metallic-paint", "aluminium"]


@pytest.fixture(scope="session")
def nbrdf_npz(data_dir):
    return data_dir / "nbrdf" / "merl_nbrdf_weights.npz"


@pytest.fixture(scope="session")
def abc_csv(data_dir):
    return data_dir / "merl_abc_low2012_params.csv"


@pytest.fixture(scope="session")
def baked_materials(nbrdf_npz, tmp_path_factory):
    """name -> (NBRDF callable, path of its MERL file), written once per session
    (reciprocal NBRDF evaluation at every bin centre; about 10 s per material)."""
    from neural_brdf.measured import merl

    folder = tmp_path_factory.mktemp("nbrdf")
    out = {}
    for name in MATERIALS:
        fn = merl.nbrdf_fixture(nbrdf_npz, name, reciprocal=True)
        path = folder / f"{name}.binary"
        merl.bake(fn, path)
        out[name] = (fn, path)
    return out


@pytest.fixture(scope="session")
def wgpu_device():
    """A WebGPU device for the generated WGSL: lavapipe, Mesa's CPU Vulkan, in CI."""
    import wgpu

    adapter = wgpu.gpu.request_adapter_sync(power_preference="high-performance")
    assert adapter is not None, "no WebGPU adapter (install mesa-vulkan-drivers: lavapipe)"
    return adapter.request_device_sync()


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """One finished run of the tiny config (cli_helpers.TINY, the Lambertian preset),
    trained once per session with ``neural-brdf train``: its folder holds every file a
    run writes (report and viewer included).  Tests that read a run share it; a test
    that changes it works on a copy (``shutil.copytree``)."""
    from cli_helpers import SETS
    from neural_brdf.tooling.cli import main

    folder = tmp_path_factory.mktemp("tiny") / "run"
    code = main(["train", "lambert", "--out", str(folder), *SETS])
    assert code in (0, 1), f"the shared tiny run failed (exit {code})"  # 1: a check failed
    assert (folder / "model.onnx").is_file() and (folder / "report.html").is_file()
    return folder


@pytest.fixture(scope="module")
def mi():
    """Mitsuba in ``llvm_ad_rgb`` with the images fit's differentiable plugin registered
    (:func:`neural_brdf.inverse.fit.use_variant`): the tests of tests/inverse.  A file
    that needs Mitsuba set up otherwise defines its own ``mi``, which takes precedence."""
    from neural_brdf.inverse import fit as inverse

    return inverse.use_variant("llvm_ad_rgb")
