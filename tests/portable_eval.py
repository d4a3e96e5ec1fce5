"""Evaluate an exported model with one consumer, in its own interpreter:

    python tests/portable_eval.py CONSUMER MODEL.onnx DIR

CONSUMER is ``onnxruntime`` (whatever onnxruntime this interpreter has: the old-runtime
venv ``.venv-ort-old`` runs this file with onnxruntime 1.18.1 and numpy < 2),
``onnx2torch`` (the file converted to a torch module) or ``reference`` (onnx's
ReferenceEvaluator).  The protocol is tests/js/ort_web_eval.mjs's: DIR/cases.json lists
{"name", "n"}, DIR/NAME.wi.f32 and NAME.wo.f32 hold n x 3 little-endian float32; this
writes DIR/NAME.f.f32 for each case that ran and DIR/results.json, {"version", "cases":
{NAME: {"dims"} or {"error"}}}.  A failing case is recorded, not fatal; a file that
does not load fails every case (version null).

Standalone on purpose (numpy and the consumer only, not neural_brdf): the old-runtime venv
has nothing else.  onnx2torch imports torchvision for its NMS and RoIAlign converters
only, and PyPI's torchvision does not import beside the CPU torch wheel (it is built for
the CUDA one), so where no torchvision is installed a stub stands in for it: the graph
uses neither op.  Used by tests/portable_consumers.py.
"""

from __future__ import annotations

import json
import sys
import types
import warnings
from pathlib import Path

import numpy as np


def _onnxruntime(model: str):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    session = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])

    def run(wi, wo):
        return session.run(["f"], {"wi": wi, "wo": wo})[0]

    return ort.__version__, run


def _stub_torchvision() -> None:
    import importlib.util

    if importlib.util.find_spec("torchvision") is not None:
        return

    def missing(*args, **kwargs):
        raise NotImplementedError("torchvision stub (tests/portable_eval.py)")

    tv, ops = types.ModuleType("torchvision"), types.ModuleType("torchvision.ops")
    ops.nms = ops.roi_align = ops.box_convert = missing
    tv.ops = ops
    sys.modules["torchvision"], sys.modules["torchvision.ops"] = tv, ops


def _onnx2torch(model: str):
    _stub_torchvision()
    from importlib.metadata import version

    import onnx2torch
    import torch

    torch.set_num_threads(1)
    module = onnx2torch.convert(model).eval()

    def run(wi, wo):
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # onnx2torch's Slice: a torch deprecation
            return module(torch.from_numpy(wi), torch.from_numpy(wo)).numpy()

    return version("onnx2torch"), run


def _reference(model: str):
    import onnx
    from onnx.reference import ReferenceEvaluator

    ev = ReferenceEvaluator(model)

    def run(wi, wo):
        return ev.run(["f"], {"wi": wi, "wo": wo})[0]

    return onnx.__version__, run


CONSUMERS = {"onnxruntime": _onnxruntime, "onnx2torch": _onnx2torch, "reference": _reference}


def _message(e: Exception) -> str:
    lines = [x for x in str(e).strip().splitlines() if x.strip()]
    return f"{type(e).__name__}: {lines[-1][:400] if lines else ''}"


def main(argv: list[str]) -> int:
    consumer, model, folder = argv
    folder = Path(folder)
    listing = json.loads((folder / "cases.json").read_text())
    try:
        version, run = CONSUMERS[consumer](model)
    except Exception as e:  # the file does not load (or convert): every case fails so
        msg = _message(e)
        results = {"version": None, "cases": {c["name"]: {"error": msg} for c in listing}}
        (folder / "results.json").write_text(json.dumps(results))
        return 0
    results = {"version": version, "cases": {}}
    for case in listing:
        name, n = case["name"], case["n"]
        wi = np.fromfile(folder / f"{name}.wi.f32", dtype="<f4").reshape(n, 3)
        wo = np.fromfile(folder / f"{name}.wo.f32", dtype="<f4").reshape(n, 3)
        try:
            f = np.ascontiguousarray(run(wi, wo), dtype="<f4")
        except Exception as e:  # recorded per case: the test reports which failed and why
            results["cases"][name] = {"error": _message(e)}
            continue
        f.tofile(folder / f"{name}.f.f32")
        results["cases"][name] = {"dims": list(f.shape)}
    (folder / "results.json").write_text(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
