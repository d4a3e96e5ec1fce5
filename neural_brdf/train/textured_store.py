"""A textured run's exported state, kept beside its checkpoint: ``RUN/textured.pt``.

With ``texture.project`` (and ``texture.refit_steps``) the file's model is not the
checkpoint's: after training, the field is projected texel by texel onto the lobes and
the lobes are refitted on it (``export.textured_for_export``), about 90 s for the
benchmark's recipe, and the refit is floating-point training, so its result depends on
the machine and its thread count.  ``neural-brdf export RUN`` used to do all of it again
from the checkpoint: slower than the training's other stages together, and a file equal
to the run's only on the same machine.

So the run keeps what the export made (:func:`save`): the final model's ``state_dict``
(the projected table, the refitted lobes), the lobes' table figures and the
projection's, a fingerprint of what made them (the config sections the export reads and
the trained weights), and f of the model at :data:`PROBE` fixed rows.  ``export RUN``
takes it (:func:`load`) when the fingerprint is the run's and the rebuilt model gives
the probe's f again; otherwise (a file from before, an edited config.yaml, another
checkpoint after ``--resume``, a damaged file) it says why on stderr and projects again,
as before.  Written atomically with torch.save, read with ``weights_only=True``: plain
tensors, strings and numbers, nothing executable.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neural_brdf import config as cfgmod
from neural_brdf.fileio import atomic_write, json_text
from neural_brdf.train.textured_model import FrozenWeightField, TexturedBRDF

KIND = "neural_brdf.textured_export"
VERSION = 1
PROBE = 256  # rows of (wi, wo, uv) whose f the loaded model must give again
PROBE_RTOL = 1e-4  # another machine's float sums differ in the last bits, not more
# the config sections export.textured_for_export reads (and the teacher)
SECTIONS = ("target", "model", "texture", "normalization", "train", "data")


def fingerprint(cfg: cfgmod.Config, trained: dict[str, torch.Tensor]) -> str:
    """SHA-256 of the config ``SECTIONS`` (JSON) and the trained ``state_dict`` (each
    tensor's name, shape, dtype and bytes, in key order)."""
    h = hashlib.sha256()
    sections = {s: getattr(cfg, s).model_dump(mode="json") for s in SECTIONS}
    h.update(json.dumps(sections, sort_keys=True).encode())
    for k in sorted(trained):
        t = trained[k].detach().cpu().contiguous()
        h.update(f"{k}:{tuple(t.shape)}:{t.dtype}".encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


def probe_rows() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:data:`PROBE` fixed rows (wi, wo, uv): directions above the horizon, uv in [0, 1)."""
    rng = np.random.default_rng(20261129)

    def hemi() -> torch.Tensor:
        v = rng.normal(size=(PROBE, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.05
        return torch.from_numpy(v / np.linalg.norm(v, axis=-1, keepdims=True)).float()

    return hemi(), hemi(), torch.from_numpy(rng.random((PROBE, 2))).float()


def _probe(model: TexturedBRDF) -> torch.Tensor:
    with torch.no_grad():
        return model(*probe_rows()).detach().clone()


def save(
    path: Path,
    model: TexturedBRDF,
    tables: list[dict[str, Any]],
    info: dict[str, Any],
    cfg: cfgmod.Config,
    trained: dict[str, torch.Tensor],
) -> None:
    """Keep ``model`` (export.textured_for_export's, before the normal field is added),
    its lobes' ``tables`` and the projection's ``info`` at ``path`` (atomically), for
    the ``cfg`` and ``trained`` weights that made them."""
    field = model.field
    if not isinstance(field, FrozenWeightField) or model.normal is not None:
        raise ValueError("textured_store.save: a normalised model, before its normal field")
    payload = {
        "kind": KIND,
        "version": VERSION,
        "fingerprint": fingerprint(cfg, trained),
        "field": {
            "resolution": field.resolution,
            "channels": field.channels,
            "latent": field.latent,
            "width": int(field.table.shape[1]),
        },
        "model": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "bound_envelope": model.bound_envelope,
        "probe": _probe(model),
        "tables": json_text(tables, indent=None),
        "info": json_text(info, indent=None),
    }
    buf = io.BytesIO()
    torch.save(payload, buf)
    atomic_write(path, bytes(buf.getbuffer()))


def _match_forms(model: TexturedBRDF, state: dict[str, torch.Tensor]) -> None:
    """Give each of the skeleton's lobes the form its kept state has.  Whether a lobe keeps
    its table or is folded into a constant (normalized_textured, FOLD_LIMIT) is decided
    by its own table, and a projected run's kept lobes were refitted after the
    checkpoint's: the checkpoint's lobe folded where the kept one did not, or the other
    way round (tests/train/test_textured_pipeline.py's projected run, once the
    training pairs reached normal incidence)."""
    from neural_brdf.train.conditioned import ConditionedNormalizedBRDF
    from neural_brdf.train.model import NormalizedBRDF
    from neural_brdf.train.textured_model import ScaledBRDF

    for k, lobe in enumerate(model.lobes):
        table = state.get(f"lobes.{k}.table")
        if isinstance(lobe, ScaledBRDF) and table is not None:
            # as normalized_textured decides: by the network's latent, not the table's
            # shape (an anisotropic lobe's table is (K, K, C) too)
            form = ConditionedNormalizedBRDF if lobe.raw.latent else NormalizedBRDF
            model.lobes[k] = form(lobe.raw, table).eval()
        elif f"lobes.{k}.scale" in state and isinstance(
            lobe, NormalizedBRDF | ConditionedNormalizedBRDF
        ):
            model.lobes[k] = ScaledBRDF(lobe.raw, lobe.table).eval()


def load(
    path: Path,
    cfg: cfgmod.Config,
    trained: dict[str, torch.Tensor],
    skeleton: Callable[[], TexturedBRDF],
) -> tuple[tuple[TexturedBRDF, list[dict[str, Any]], dict[str, Any]] | None, str]:
    """The kept (model, tables, info) when ``path`` holds them for ``cfg`` and
    ``trained``, else None; and a short reason.  ``skeleton``: the checkpoint's model
    normalised as the export normalises it (the same modules; its field is replaced by
    one of the kept size before the state is loaded)."""
    if not path.is_file():
        return None, f"no {path.name}"
    try:
        d = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a damaged or foreign file: project again
        return None, f"{path.name} unreadable ({type(e).__name__})"
    if not isinstance(d, dict) or d.get("kind") != KIND or d.get("version") != VERSION:
        return None, f"{path.name} is not a version-{VERSION} textured export"
    if d.get("fingerprint") != fingerprint(cfg, trained):
        return None, f"{path.name} was made from another config or checkpoint"
    try:
        f = d["field"]
        model = skeleton()
        _match_forms(model, d["model"])
        model.field = FrozenWeightField(
            torch.zeros(f["resolution"] ** 2, f["width"]),
            f["resolution"],
            channels=f["channels"],
            latent=f["latent"],
        )
        model.load_state_dict(d["model"])
        model.eval()
        again = _probe(model)
        if again.shape != d["probe"].shape or not torch.allclose(
            again, d["probe"], rtol=PROBE_RTOL, atol=PROBE_RTOL * float(d["probe"].abs().max())
        ):
            return None, f"{path.name} does not give its model's f again"
        model.bound_envelope = d["bound_envelope"]
        return (model, json.loads(d["tables"]), json.loads(d["info"])), "kept by the run"
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        return None, f"{path.name} does not fit this run's model ({type(e).__name__})"
