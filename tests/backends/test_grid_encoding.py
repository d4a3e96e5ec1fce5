"""The learned feature grid (``model.grid``): export, back-end parity, physics, config, training.

A model with a grid is built in torch with random non-zero weights (speed and parity do
not depend on training), exported by the project's exporter, and evaluated by torch,
onnxruntime, the Dr.Jit interpreter and the generated C back end on the same pairs
(random, grazing, equal, opposite, mirrored; half below the horizon).
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch
from test_codegen import (
    C_TOL,
    EVERY_OP_LOBE,
    GPU_TOL,
    TINY_RUN,
    CProgram,
    glsl_validate,
    onnx_ref,
    pairs,
    wgsl_eval,
)

from analytic import physics
from cli_helpers import ROOT, assert_one_line_error, cli
from neural_brdf import backends, config, pipeline
from neural_brdf.export import relative_difference, to_onnx_bytes
from neural_brdf.physics.quadrature import albedo, from_numpy
from neural_brdf.train import encoding as enc
from neural_brdf.train.model import NormalizedBRDF, RawBRDF, TotalBRDF, albedo_table

GOLD = ROOT / "configs" / "gold.yaml"  # (any working directory)

GRID = 8
CHANNELS = 3
OPSET = 17
ALBEDO_TOL = 1e-3  # the validator's bound: max albedo <= 1 + 1e-3


def grid_raw(
    *, bright: float = 0.0, seed: int = 0, coords: str = "theta", cosine: bool = False
) -> RawBRDF:
    """1x16 ReLU over the features + an 8x8x3 grid; random non-zero weights.  ``bright``
    adds a large positive grid value and head bias (an albedo far above 1).  ``coords``
    "half_disc" makes it an anisotropic model with the grid over the half vector.
    ``cosine`` adds the second, cosine grid (``model.cosine_grid``), also 8x8x3."""
    torch.manual_seed(seed)
    raw = RawBRDF(
        "anisotropic" if coords == "half_disc" else "isotropic",
        [16],
        "relu",
        grid_size=GRID,
        grid_channels=CHANNELS,
        grid_init_std=0.5,
        grid_coords=coords,
        cosine_grid_size=GRID if cosine else 0,
        cosine_grid_channels=CHANNELS,
        cosine_grid_init_std=0.5,
    )
    with torch.no_grad():
        torch.nn.init.normal_(raw.mlp.head.weight, std=0.3)
        if bright:
            raw.grid.table.add_(bright)
            if cosine:
                raw.cos_grid.table.add_(bright)
            raw.mlp.head.bias.add_(bright)
    return raw


def total_model(raw: RawBRDF, table_size: int = 33, samples: int = 2048) -> TotalBRDF:
    table, _, _ = albedo_table(
        raw,
        size=9 if raw.anisotropic else table_size,
        anisotropic=raw.anisotropic,
        samples=samples,
        seed=0,
        sigmas=3.0,
        margin=ALBEDO_TOL,
    )
    return TotalBRDF(NormalizedBRDF(raw, table)).eval()


@pytest.fixture(scope="module", params=["theta", "half_disc", "theta+cosine"])
def exported(tmp_path_factory, request):
    coords, _, cosine = request.param.partition("+")
    model = total_model(grid_raw(coords=coords, cosine=bool(cosine)))
    path = tmp_path_factory.mktemp("grid") / "model.onnx"
    path.write_bytes(to_onnx_bytes(model, OPSET))
    return model, path


def torch_eval(model, wi, wo) -> np.ndarray:
    with torch.no_grad():
        return model(torch.from_numpy(wi), torch.from_numpy(wo)).numpy()


def test_grid_is_in_the_graph_as_gather(exported):
    model, path = exported
    proto = onnx.load(str(path))
    sizes = [int(np.prod(t.dims)) for t in proto.graph.initializer]
    grids = 1 + (model.model.raw.cos_grid is not None)
    assert sizes.count(GRID * GRID * CHANNELS) == grids
    tables = 0 if model.model.identity else 2 * (4 if model.anisotropic else 2)
    gathers = sum(n.op_type == "Gather" for n in proto.graph.node)
    assert gathers >= 4 * grids + tables  # four corners per grid + the albedo table's


def test_torch_onnxruntime_parity(exported):
    model, path = exported
    wi, wo = pairs()
    ref = torch_eval(model, wi, wo)
    assert np.count_nonzero(ref) > len(ref)  # not a trivially zero model
    assert relative_difference(onnx_ref(path, wi, wo), ref) <= C_TOL


@pytest.mark.mitsuba
def test_drjit_matches_onnxruntime(exported):
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from neural_brdf.backends.drjit import OnnxProgram

    _, path = exported
    wi, wo = pairs(seed=1)
    cols = OnnxProgram(path)(
        wi=[mi.Float(wi[:, k]) for k in range(3)], wo=[mi.Float(wo[:, k]) for k in range(3)]
    )["f"]
    got = np.stack([np.asarray(c) for c in cols], -1)
    assert relative_difference(got, onnx_ref(path, wi, wo)) <= C_TOL


def test_generated_c_matches_onnxruntime(exported, tmp_path):
    _, path = exported
    wi, wo = pairs(seed=2)
    got = CProgram(path, tmp_path / "c", lobe=EVERY_OP_LOBE).eval(wi, wo)  # any lobe: f only
    assert relative_difference(got, onnx_ref(path, wi, wo)) <= C_TOL


def test_generated_wgsl_matches_onnxruntime(exported, wgpu_device):
    """The grids' look-ups in WGSL, run on lavapipe (wgpu), against onnxruntime."""
    _, path = exported
    wi, wo = pairs(seed=7)
    got = wgsl_eval(wgpu_device, backends.generate(path, "wgsl", lobe=EVERY_OP_LOBE), wi, wo)
    assert relative_difference(got, onnx_ref(path, wi, wo)) <= GPU_TOL


def test_generated_glsl_compiles(exported, tmp_path):
    """GLSL (WebGL2 and Vulkan) accepts the grid's look-up (values: the viewer's tests)."""
    _, path = exported
    glsl_validate(backends.generate(path, "glsl", lobe=EVERY_OP_LOBE), tmp_path)


def test_reciprocity_is_bit_exact(exported):
    model, path = exported
    wi, wo = pairs(seed=3)
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    a, b = onnx_ref(path, wi, wo), onnx_ref(path, wo, wi)
    assert np.count_nonzero(a[up]) == a[up].size
    assert np.array_equal(a, b)
    assert np.array_equal(torch_eval(model, wi, wo), torch_eval(model, wo, wi))


def test_grid_changes_the_output():
    """The grid is used: changing one node's features changes f near that node."""
    raw = grid_raw()
    wi, wo = (torch.from_numpy(x) for x in pairs(seed=4))
    with torch.no_grad():
        before = raw(wi, wo)
        raw.grid.table.add_(1.0)
        after = raw(wi, wo)
    assert not torch.allclose(before, after)


def test_cosine_grid_changes_the_output_and_only_with_the_cosines():
    """The cosine grid is used, and it is indexed by the cosines alone: rotating both
    directions about the normal leaves its look-up unchanged (so f changes only where the
    theta grid and the features do), while moving one direction's elevation changes it."""
    raw = grid_raw(cosine=True)
    wi, wo = (torch.from_numpy(x) for x in pairs(seed=6))
    with torch.no_grad():
        before = raw(wi, wo)
        raw.cos_grid.table[0].add_(5.0)  # node (0, 0): mean cosine 0, equal cosines
        after = raw(wi, wo)
    changed = (before != after).any(-1)
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    mean_cos = 0.5 * (wi[:, 2] + wo[:, 2])
    ratio = (wi[:, 2] - wo[:, 2]).abs() / (wi[:, 2] + wo[:, 2])
    in_cell = up & (mean_cos < 1 / (GRID - 1)) & (ratio < 1 / (GRID - 1))
    assert changed[in_cell].all() and in_cell.any()
    assert not changed[up & ~in_cell].any()  # a node only reaches its four cells


@pytest.mark.parametrize("cosine", [False, True])
def test_furnace_bound_on_a_bright_grid(cosine):
    raw = grid_raw(bright=3.0, cosine=cosine)
    model = total_model(raw, samples=4096)
    dirs = torch.from_numpy(physics.random_directions(64, 11)).double()
    with torch.no_grad():
        raw_rho, _ = albedo(from_numpy(lambda a, b: torch_eval_raw(raw, a, b)), dirs, 4096, seed=12)
        rho, _ = albedo(
            from_numpy(lambda a, b: torch_eval(model, a.astype(np.float32), b.astype(np.float32))),
            dirs,
            4096,
            seed=12,
        )
    assert float(raw_rho.max()) > 2.0  # the raw grid model is far too bright
    assert float(rho.max()) <= 1.0 + ALBEDO_TOL


def torch_eval_raw(raw, wi, wo):
    with torch.no_grad():
        return raw(torch.from_numpy(wi).float(), torch.from_numpy(wo).float()).numpy()


@pytest.mark.parametrize(
    "value, key",
    [
        ("model.grid.size=1", "model.grid.size"),
        ("model.grid.size=-3", "model.grid.size"),
        ("model.grid.channels=0", "model.grid.channels"),
        ("model.grid.sizes=4", "model.grid.sizes"),
        ("model.cosine_grid.size=1", "model.cosine_grid.size"),
        ("model.cosine_grid.lr_scale=0", "model.cosine_grid.lr_scale"),
    ],
)
def test_bad_grid_config_is_exit_2_naming_the_key(capsys, tmp_path, value, key):
    code, _, err = cli(capsys, "train", str(GOLD), "--out", str(tmp_path / "r"), "--set", value)
    assert_one_line_error(code, err, key)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "grid, other, key",
    [
        # the raw ablation encoding has no grid axes
        ("model.grid.size=8", "model.encoding=raw", "model.grid"),
        ("model.cosine_grid.size=8", "model.encoding=raw", "cosine_grid"),
        # the half vector: anisotropic only
        ("model.grid.size=8", "model.grid.coords=half_disc", "grid.coords"),
    ],
)
def test_grid_on_an_encoding_without_its_axes_is_a_config_error(capsys, tmp_path, grid, other, key):
    code, _, err = cli(
        capsys,
        "train",
        str(GOLD),
        "--out",
        str(tmp_path / "r"),
        "--set",
        grid,
        "--set",
        other,
    )
    assert_one_line_error(code, err, key)
    assert not (tmp_path / "r").exists()


def test_half_disc_grid_sees_the_half_vectors_azimuth():
    """Rotating both directions about the normal moves the half vector on the grid: the
    half_disc look-up changes, while theta_h and theta_d (a theta grid's axes) do not."""
    raw = grid_raw(coords="half_disc")
    wi, wo = (torch.from_numpy(x) for x in pairs(seed=5))
    c, s_ = np.cos(np.pi / 2), np.sin(np.pi / 2)
    rot = torch.tensor([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
    grid = raw.grid
    x = raw.grid_features
    with torch.no_grad():
        fa = enc.features(wi, wo, "anisotropic")
        fb = enc.features(wi @ rot.T, wo @ rot.T, "anisotropic")
        ga = grid(0.5 * (fa[..., x[0]] + 1), 0.5 * (fa[..., x[1]] + 1))
        gb = grid(0.5 * (fb[..., x[0]] + 1), 0.5 * (fb[..., x[1]] + 1))
    assert not torch.allclose(ga, gb)
    # and theta_h, theta_d (features 0, 1) are the same: only the azimuth moved
    assert torch.allclose(fa[..., :2], fb[..., :2], atol=1e-5)


def test_training_reduces_the_error(tmp_path):
    sets = [s for s in TINY_RUN if not s.startswith(("train.steps", "model.hidden"))]
    sets += [
        "model.grid.size=8",
        "model.hidden=[16]",
        "model.activation=relu",
        "model.grid.lr_scale=3",
    ]
    errors = []
    for steps in (1, 300):  # train.steps must be >= 1: one step is as good as untrained
        cfg = config.load(GOLD, sets + [f"train.steps={steps}"])
        report = pipeline.run(cfg, tmp_path / f"s{steps}")
        errors.append(report["accuracy"]["rel_rmse"])
        assert report["checks"]["reciprocity"]["value"] == 0.0
        assert report["checks"]["max_albedo"]["passed"]
    assert errors[1] < 0.5 * errors[0], errors
