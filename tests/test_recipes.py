"""docs/architecture.md's recipes, followed as a newcomer would: each test adds one new
file (written here into a temporary folder) and its line in one table, and checks that
the rest of the project picks it up with nothing else touched.

* an analytic model: ``analytic/toy.py`` and its line in ``analytic._MODELS``: it is then a
  training target, a validation reference and a physics-checked model;
* a code-generation back end: ``backends/toy.py`` (Python + numpy source, written from the
  lowered graph) and its line in ``backends.REGISTRY`` (``TARGETS``, computed from it at
  import, is patched here as the import would have given it): ``neural-brdf
  codegen --target toy`` writes it, and its output agrees with onnxruntime.

The encoding and the measured-format recipes have their own tests beside the registries
they extend (tests/train/, tests/measured/).
"""

from __future__ import annotations

import importlib
import sys
import textwrap

import numpy as np
import pytest

import analytic
from cli_helpers import SETS, cli
from neural_brdf import backends, runtime

TOY_MODEL = '''
"""A toy model for the recipe test: a tinted Lambertian with a Phong-like sheen,
f = kd / pi + ks (n + 2) / (2 pi) max(0, r . wo)^n, r the mirror of wi: reciprocal, since
r(wi) . wo = r(wo) . wi."""

import math

import torch

from .base import BRDF, rgb


class Toy(BRDF):
    name = "toy"
    param_space = {"kd": ("rgb", 0.0, 0.5)}

    def __init__(self, *, kd=(0.4, 0.3, 0.2), ks=0.3, n=20.0):
        super().__init__(kd=rgb("kd", kd), ks=float(ks), n=float(n))

    def _f(self, wi, wo):
        kd = self.const(self.params["kd"], wi) / math.pi
        r = torch.stack([-wi[..., 0], -wi[..., 1], wi[..., 2]], -1)
        c = (r * wo).sum(-1, keepdim=True).clamp_min(0.0)
        n = self.params["n"]
        return kd + self.params["ks"] * (n + 2) / (2 * math.pi) * c**n
'''


@pytest.fixture
def toy_model(tmp_path, monkeypatch):
    """analytic/toy.py (in a folder added to the package's path) and its _MODELS line."""
    (tmp_path / "toy.py").write_text(textwrap.dedent(TOY_MODEL))
    monkeypatch.setattr(analytic, "__path__", [*analytic.__path__, str(tmp_path)])
    monkeypatch.setitem(analytic._MODELS, "toy", ("toy", "Toy"))
    yield "toy"
    sys.modules.pop("analytic.toy", None)


def test_recipe_an_analytic_model(toy_model, tmp_path, capsys):
    brdf = analytic.create(toy_model, ks=0.2)
    wi = np.array([[0.3, 0.1, 0.95]]) / np.linalg.norm([0.3, 0.1, 0.95])
    wo = np.array([[-0.2, 0.4, 0.89]]) / np.linalg.norm([-0.2, 0.4, 0.89])
    assert np.allclose(brdf.eval(wi, wo), brdf.eval(wo, wi), rtol=1e-12)
    assert analytic.reciprocity_error(brdf) < 1e-6
    config = tmp_path / "toy.yaml"
    config.write_text("target: {model: toy, params: {ks: 0.2}}\n")
    code, out, err = cli(capsys, "train", str(config), "--out", str(tmp_path / "run"), *SETS)
    assert code in (0, 1), err
    assert "rel_rmse" in out  # validated against the toy as its reference
    meta = runtime.load(tmp_path / "run" / "model.onnx").target
    assert "toy" in meta.get("description", "") or meta.get("model") == "toy", meta


TOY_BACKEND = '''
"""A toy back end for the recipe test: the lowered graph as a Python function on numpy
arrays (one assignment per instruction)."""

import numpy as np

from neural_brdf import graph

UNARY = {"neg": "-{0}", "abs": "np.abs({0})", "sqrt": "np.sqrt({0})", "exp": "np.exp({0})",
         "log": "np.log({0})", "floor": "np.floor({0})", "ceil": "np.ceil({0})",
         "sin": "np.sin({0})", "cos": "np.cos({0})", "atan": "np.arctan({0})",
         "asin": "np.arcsin({0})", "acos": "np.arccos({0})", "tanh": "np.tanh({0})",
         "not": "~{0}", "isnan": "np.isnan({0})", "isinf": "np.isinf({0})"}
BINARY = {"add": "{0} + {1}", "sub": "{0} - {1}", "mul": "{0} * {1}", "div": "{0} / {1}",
          "max": "np.maximum({0}, {1})", "min": "np.minimum({0}, {1})",
          "pow": "np.power({0}, {1})", "eq": "{0} == {1}", "lt": "{0} < {1}",
          "le": "{0} <= {1}", "gt": "{0} > {1}", "ge": "{0} >= {1}", "and": "{0} & {1}",
          "or": "{0} | {1}", "xor": "{0} ^ {1}"}
TYPES = {"float": "np.float32", "int": "np.int32", "bool": "np.bool_"}


class ToyRenderer:
    name = "toy"

    def generate(self, model, *, lobe=None):
        prog = graph.lower(model)
        out = ["import numpy as np", "", "np.seterr(all='ignore')", ""]
        out += [f"T{k} = np.array({t.tolist()!r}, dtype=np.{t.dtype})"
                for k, t in enumerate(prog.tables)]
        out += ["", "def f(" + ", ".join(prog.inputs) + "):"]
        for i, ins in enumerate(prog.instrs):
            a = [f"v{j}" for j in ins.args]
            if ins.op == "const":
                e = f"{TYPES[ins.dtype]}({ins.attr!r})"
            elif ins.op == "input":
                e = f"{ins.attr[0]}[:, {ins.attr[1]}].astype(np.float32)"
            elif ins.op in UNARY:
                e = UNARY[ins.op].format(*a)
            elif ins.op in BINARY:
                e = BINARY[ins.op].format(*a)
            elif ins.op == "fma":
                e = "{0} * {1} + {2}".format(*a)
            elif ins.op == "select":
                e = "np.where({0}, {1}, {2})".format(*a)
            elif ins.op == "cast":
                e = f"np.asarray({a[0]}).astype({TYPES[ins.dtype]})"
            elif ins.op == "gather":
                e = f"T{ins.attr}[np.clip({a[0]}, 0, len(T{ins.attr}) - 1)]"
            else:
                raise graph.UnsupportedOnnxOp(f"toy back end: {ins.op}")
            out.append(f"    v{i} = {e}")
        cols = prog.outputs["f"]
        n = "len(" + next(iter(prog.inputs)) + ")"
        stacked = ", ".join(f"np.broadcast_to(v{c}, ({n},))" for c in cols)
        out.append(f"    return np.stack([{stacked}], -1).astype(np.float32)")
        return "\\n".join(out) + "\\n"
'''


@pytest.fixture
def toy_backend(tmp_path, monkeypatch):
    """backends/toy.py (a module in a folder on sys.path) and its registry lines."""
    (tmp_path / "toy_backend.py").write_text(textwrap.dedent(TOY_BACKEND))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(backends.REGISTRY, "toy", ("toy_backend", "ToyRenderer"))
    monkeypatch.setattr(backends, "TARGETS", (*backends.TARGETS, "toy"))
    yield "toy"
    sys.modules.pop("toy_backend", None)


def test_recipe_a_code_generation_back_end(toy_backend, tiny_run, tmp_path, capsys):
    model = tiny_run / "model.onnx"
    out = tmp_path / "brdf.py"
    code, _, err = cli(capsys, "codegen", str(model), "--target", toy_backend, "-o", str(out))
    assert code == 0, err
    spec = importlib.util.spec_from_file_location("generated_brdf", out)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rng = np.random.default_rng(0)
    wi, wo = (rng.normal(size=(4096, 3)).astype(np.float32) for _ in range(2))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    got = module.f(wi, wo)
    ref = runtime.load(model).eval(wi, wo)
    assert got.shape == ref.shape == (4096, 3)
    assert np.max(np.abs(got - ref) / np.maximum(np.abs(ref), 1e-3)) < 1e-4
