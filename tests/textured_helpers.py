"""Shared by the textured model's tests: one torch thread per module (import
:func:`one_torch_thread`), an onnxruntime session on one thread, rows of
(wi, wo, uv) with hostile entries, the albedo of a textured model at fixed uv by
analytic's cosine quadrature (independent of the MIS quadrature that builds the tables),
incidences in the xz plane, and deliberately bright conditioned lobes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import onnxruntime as ort
import pytest
import torch

from analytic import physics
from neural_brdf.fileformat import OUTPUT, SIGNATURES

INPUTS = SIGNATURES[1]  # ("wi", "wo", "uv")


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """One torch thread (the machine is shared), before the module's fixtures build;
    autouse in every module that imports it."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def session(payload: bytes) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(payload, opts, providers=["CPUExecutionProvider"])


def run(sess: ort.InferenceSession, wi, wo, uv) -> np.ndarray:
    feeds = {k: np.ascontiguousarray(x, np.float32) for k, x in zip(INPUTS, (wi, wo, uv))}
    return sess.run([OUTPUT], feeds)[0]


def rows(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs above the horizon (10 % within 1 degree of it), a quarter anywhere on the
    sphere, uv in [-3, 3)^2."""
    rng = np.random.default_rng(seed)
    wi = physics.random_directions(n, seed)
    wo = physics.random_directions(n, seed + 1)
    k = n // 4
    anywhere = rng.normal(size=(k, 6))
    wi[:k] = anywhere[:, :3] / np.linalg.norm(anywhere[:, :3], axis=-1, keepdims=True)
    wo[:k] = anywhere[:, 3:] / np.linalg.norm(anywhere[:, 3:], axis=-1, keepdims=True)
    uv = rng.uniform(-3.0, 3.0, (n, 2))
    return wi.astype(np.float32), wo.astype(np.float32), uv.astype(np.float32)


def albedos_of(
    fns: list[Callable[[torch.Tensor, torch.Tensor], torch.Tensor]], wi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-weighted Sobol quadrature (analytic.physics.albedo_of, 4096 directions per
    wi) of each torch function f(wi, wo) -> (N, 3): (len(fns), len(wi), 3) albedos and
    standard errors."""
    rhos, errs = [], []
    for f in fns:

        def fn(a, b, f=f):
            with torch.no_grad():
                return f(torch.as_tensor(a).float(), torch.as_tensor(b).float()).double().numpy()

        rho, err = physics.albedo_of(fn, wi, n=4096, seed=5, return_error=True)
        rhos.append(rho)
        errs.append(err)
    return np.stack(rhos), np.stack(errs)


def albedos(model, uvs: np.ndarray, wi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`albedos_of` of a textured ``model(wi, wo, uv)`` at each uv of ``uvs``."""
    fns = [
        (lambda x, y, c=c: model(x, y, torch.from_numpy(c).float().expand(len(x), 2))) for c in uvs
    ]
    return albedos_of(fns, wi)


def incidences(*deg: float) -> np.ndarray:
    """Unit directions at the polar angles ``deg`` (degrees) in the xz plane, (n, 3)."""
    t = np.radians(deg)
    return np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], -1)


def bright_conditioned(resolution: int):
    """One network with 2 heads and one latent input, large random weights (raw albedos
    far above 1, changing a lot with s), and a ``resolution``² field whose latent spans
    [0, 1]: (the raw TexturedBRDF, its field)."""
    from neural_brdf.train.model import RawBRDF
    from neural_brdf.train.textured_model import TexturedBRDF, WeightField

    torch.manual_seed(11)
    net = RawBRDF("isotropic", [16], "relu", grid_size=4, heads=2, latent=1)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0.0, 2.0)
        net.mlp.head.bias.fill_(3.0)
        # the latent's column of the first layer large: the lobes change a lot with s
        net.mlp.body[0].weight[:, -1].normal_(0.0, 6.0)
    field = WeightField(resolution, 2, init_std=2.0, latent=1)
    with torch.no_grad():
        field.logits[:, -1] = -12.0
        field.latent_logits.normal_(0.0, 3.0)
    return TexturedBRDF([net.eval()], field).eval(), field


def small_run_config(path, xml, *, texture: str, train: str, normalization: str) -> None:
    """Write a small, fast textured CLI config to ``path``: the teacher ``xml``, and the
    ``texture``, ``train`` and ``normalization`` sections as YAML flow maps (the part a
    test is about); a small pool, validation and parity check."""
    path.write_text(
        f"target: {{mitsuba: {xml}}}\n"
        f"texture: {{{texture}}}\n"
        f"train: {{{train}}}\n"
        "data: {pool_size: 8192, batch_size: 1024}\n"
        "validation: {pairs: 2000, furnace_dirs: 32, furnace_samples: 4096, "
        "accuracy_samples: 8192}\n"
        f"normalization: {{{normalization}}}\n"
        "export: {parity_pairs: 512}\n"
    )


def assert_file_matches(model, payload: bytes, seed: int) -> None:
    """The file ``payload`` of the textured ``model``: reciprocal bit for bit through
    onnxruntime, finite and >= 0 on any row, and equal to torch's model where both
    directions are above the horizon."""
    sess = session(payload)
    wi, wo, uv = rows(8192, seed)
    a = run(sess, wi, wo, uv)
    np.testing.assert_array_equal(a, run(sess, wo, wi, uv))
    assert np.isfinite(a).all() and a.min() >= 0.0
    with torch.no_grad():
        ref = model(torch.from_numpy(wi), torch.from_numpy(wo), torch.from_numpy(uv)).numpy()
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    np.testing.assert_allclose(a[up], ref[up], rtol=1e-4, atol=1e-6)
