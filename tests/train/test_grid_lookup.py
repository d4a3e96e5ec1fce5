"""The feature grid's two look-ups: torch's ``grid_sample`` (training and image fits) and
the four gathers that the ONNX graph holds (every back end).  They must be one function:
a file is trained through the first and rendered through the second."""

from __future__ import annotations

import unittest.mock

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from analytic import physics
from neural_brdf import export
from neural_brdf.train.model import FeatureGrid, RawBRDF


def _gathered(grid: FeatureGrid, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The look-up the exporter traces (the graph's Gathers)."""
    with unittest.mock.patch("torch.onnx.is_in_onnx_export", return_value=True):
        return grid(u, v)


def _coords(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    u, v = torch.rand(n, generator=g), torch.rand(n, generator=g)
    # the edges, the corners and a node of the grid, where a swapped axis or a shifted
    # node shows at once
    edge = torch.tensor([0.0, 1.0, 0.0, 1.0, 0.5, 1e-7, 1.0 - 1e-7, 3.0 / 31.0])
    u[: len(edge)], v[: len(edge)] = edge, edge.flip(0)
    return u, v


@pytest.mark.parametrize("size", [2, 5, 32])
def test_the_sampled_look_up_is_the_gathered_one(size):
    torch.manual_seed(size)
    grid = FeatureGrid(size, 4, init_std=1.0)
    u, v = _coords(20_000, size)
    sampled, gathered = grid(u, v), _gathered(grid, u, v)
    scale = grid.table.abs().max().item()
    assert sampled.shape == gathered.shape == (20_000, 4)
    np.testing.assert_allclose(sampled.detach(), gathered.detach(), rtol=0, atol=2e-6 * scale)

    # the table's gradients too (what training and the image stage step with)
    weight = torch.randn(20_000, 4)
    (g_sampled,) = torch.autograd.grad((grid(u, v) * weight).sum(), grid.table)
    (g_gathered,) = torch.autograd.grad((_gathered(grid, u, v) * weight).sum(), grid.table)
    np.testing.assert_allclose(
        g_sampled, g_gathered, rtol=0, atol=1e-5 * g_gathered.abs().max().item()
    )


def test_the_sampled_look_up_reads_the_nodes_in_order():
    """Node (i, j) at (u, v) = (i, j) / (K - 1), row-major: the table's own layout."""
    k = 4
    grid = FeatureGrid(k, 2)
    with torch.no_grad():
        grid.table.copy_(torch.arange(k * k * 2, dtype=torch.float32).reshape(k * k, 2))
    i, j = torch.meshgrid(torch.arange(k), torch.arange(k), indexing="ij")
    u, v = i.flatten() / (k - 1.0), j.flatten() / (k - 1.0)
    np.testing.assert_allclose(grid(u.float(), v.float()).detach(), grid.table.detach(), atol=1e-5)


@pytest.mark.parametrize(
    ("encoding", "coords"), [("isotropic", "theta"), ("anisotropic", "half_disc")]
)
def test_the_exported_graph_gathers_and_agrees_with_torch(encoding, coords, tmp_path):
    torch.manual_seed(0)
    raw = RawBRDF(encoding, [16], "relu", grid_size=8, grid_channels=4, grid_coords=coords)
    with torch.no_grad():
        raw.grid.table.normal_(0.0, 1.0)  # features that matter to the output
    model = onnx.load_from_string(export.to_onnx_bytes(raw.eval(), 17))
    ops = {node.op_type for node in model.graph.node}
    assert "GridSample" not in ops and "Gather" in ops

    wi = torch.from_numpy(physics.random_directions(4000, 1)).float()
    wo = torch.from_numpy(physics.random_directions(4000, 2)).float()
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    (got,) = session.run(None, {"wi": wi.numpy(), "wo": wo.numpy()})
    with torch.no_grad():
        ref = raw(wi, wo).numpy()
    assert np.abs(ref).max() > 0.1
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * np.abs(ref).max())


def test_the_sampled_network_stays_exactly_reciprocal():
    torch.manual_seed(1)
    raw = RawBRDF("isotropic", [16], "relu", grid_size=16, grid_channels=4)
    with torch.no_grad():
        raw.grid.table.normal_(0.0, 1.0)
        wi = torch.from_numpy(physics.random_directions(5000, 3)).float()
        wo = torch.from_numpy(physics.random_directions(5000, 4)).float()
        assert torch.equal(raw(wi, wo), raw(wo, wi))
