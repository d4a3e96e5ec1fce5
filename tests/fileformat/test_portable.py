"""One file that every consumer reads (issue 23, docs/portable.md).

* the exported graph runs, with the same answers, in the newest onnxruntime, the oldest
  that pyproject allows (1.18.1, in the venv .venv-ort-old), onnxruntime-web (wasm, under
  Node), onnx2torch and onnx's ReferenceEvaluator: a batch of 0 rows, hostile rows (NaN,
  infinities, zero length) giving exactly 0 without touching the others, bit-exact
  reciprocity, and agreement with the newest onnxruntime to PORTABLE_TOL;
* the graph has no optional input omitted in the middle (Clip's max), no ReduceSum (which
  onnxruntime < 1.32 mis-shapes on 0 rows) and no Shape (which onnx's converter cannot
  take below opset 15), only ops that neural_brdf.graph lowers, and it passes onnx's full
  check; the rewrite that makes it so changes no output bit;
* :func:`neural_brdf.fileformat.portable.convert_opset` gives the file at opsets 13 to 21,
  bit-identical in onnxruntime and running in 1.18;
* the metadata: version 2 is JSON where it has structure (the target an object, the
  training config JSON), files of version 1 still read, and the JavaScript reader of the
  viewer (neural_brdf/fileformat/onnx_metadata.js, run in Node) reads what Python's onnx reads, the
  viewer page included;
* docs/portable.md's table is what benchmarks/results/portable.json holds.

A consumer that is not installed fails its test with the command that installs it
(bash .ci/run installs them all); nothing here skips.  The models are networks with random
weights, bright so that the albedo table is in the graph (as in tests/test_total_graph.py):
the plumbing is under test, not a fit.
"""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

import analytic
import neural_brdf
import portable_consumers as pc
from cli_helpers import ROOT
from neural_brdf import config, export, fileformat, graph, runtime, validate
from neural_brdf.errors import InputError
from neural_brdf.fileformat import portable, reader
from neural_brdf.fileformat.metadata import Metadata
from neural_brdf.viewer import page as viewer

# Measured (benchmarks/results/portable.json): 1.9e-6 (onnxruntime 1.18), 1.9e-6 (-web),
# 2.5e-6 (onnx2torch), 1.3e-6 (reference) against onnxruntime 1.32.  The contract: 1e-5,
# the export's own torch-vs-onnxruntime parity tolerance (export.parity_tol).
PORTABLE_TOL = 1e-5
GRAPHS = pc.GRAPHS
OPSETS = (13, 14, 15, 18, 21)
TINY = [
    "model.hidden=[16,16]",
    "normalization.samples=1024",
    "validation.furnace_dirs=6",
    "validation.furnace_samples=2048",
    "validation.pairs=2000",
    "validation.accuracy_samples=2048",
    "export.parity_pairs=512",
]


def _fail_if_missing(fn, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except pc.ConsumerMissing as e:
        pytest.fail(str(e), pytrace=False)


@pytest.fixture(scope="module", params=GRAPHS)
def model_file(request, tmp_path_factory):
    path = tmp_path_factory.mktemp(request.param) / "model.onnx"
    path.write_bytes(export.to_onnx_bytes(pc.random_model(request.param), 17))
    return path


@pytest.fixture(scope="module")
def measured(model_file):
    return _fail_if_missing(pc.measure, model_file)


# ------------------------------------------------------------------ every consumer
@pytest.mark.parametrize("consumer", pc.CONSUMERS)
def test_every_consumer_runs_the_file_alike(measured, consumer):
    fig = measured[consumer]
    assert not fig["errors"], fig["errors"]  # the empty batch included
    assert pc.passed(fig), fig
    assert fig["max_rel_diff"] <= PORTABLE_TOL, fig
    assert fig["reciprocity_bit_exact"], fig
    if consumer == "onnxruntime-1.18":
        assert fig["version"] == pc.OLD_ORT
    assert pc.passed(measured["onnxruntime"]) and measured["onnxruntime"]["reciprocity_bit_exact"]


def test_a_missing_consumer_fails_with_the_install_command(monkeypatch, tmp_path):
    monkeypatch.setattr(pc, "OLD_PYTHON", tmp_path / "no-venv" / "bin" / "python")
    with pytest.raises(pc.ConsumerMissing, match="pip install onnxruntime==1.18.1"):
        pc.check_installed("onnxruntime-1.18")
    monkeypatch.setattr(pc, "JS", tmp_path)
    with pytest.raises(pc.ConsumerMissing, match="npm ci"):
        pc.check_installed("onnxruntime-web")


# ------------------------------------------------------------------ the graph itself
def test_the_graph_is_portable_in_form(model_file):
    proto = onnx.load(str(model_file))
    onnx.checker.check_model(proto, full_check=True)
    ops = {n.op_type for n in proto.graph.node}
    assert ops <= graph.SUPPORTED_OPS, ops - graph.SUPPORTED_OPS
    assert not ops & {"ReduceSum", "Shape", "ConstantOfShape"}, ops
    for n in proto.graph.node:
        assert all(n.input), (n.name, list(n.input))  # no optional input left out
        if n.op_type == "Clip":
            assert len(n.input) == 3, n.name
    graph.lower(proto)  # the C/GLSL/WGSL and Dr.Jit back ends' lowering takes it


@pytest.mark.parametrize("kind", GRAPHS)
def test_the_rewrite_changes_no_output_bit(kind):
    model = pc.random_model(kind)
    before = export.to_onnx_bytes(model, 17, portable=False)
    after = export.to_onnx_bytes(model, 17)
    ops = [n.op_type for n in onnx.load_from_string(before).graph.node]
    assert "ReduceSum" in ops and "Shape" in ops  # torch wrote what the rewrite removes
    assert any(
        n.op_type == "Clip" and "" in n.input for n in onnx.load_from_string(before).graph.node
    )
    inputs = pc.cases(20_000)
    for name in ("random", "hostile", "swapped"):
        wi, wo = inputs[name]
        a, b = (
            ort.InferenceSession(p, providers=["CPUExecutionProvider"]).run(
                ["f"], {"wi": wi, "wo": wo}
            )[0]
            for p in (before, after)
        )
        assert np.array_equal(a, b), name
    with torch.no_grad():  # and torch agrees with the file as it agreed before
        ref = model(torch.from_numpy(inputs["random"][0]), torch.from_numpy(inputs["random"][1]))
    sess = ort.InferenceSession(after, providers=["CPUExecutionProvider"])
    got = sess.run(["f"], {"wi": inputs["random"][0], "wo": inputs["random"][1]})[0]
    assert export.relative_difference(got.astype(np.float64), ref.numpy().astype(np.float64)) <= (
        PORTABLE_TOL
    )


# ------------------------------------------------------------------ opsets
def test_convert_opset_13_to_21(model_file):
    figs = _fail_if_missing(pc.opset_figures, model_file, OPSETS)
    for opset, row in figs.items():
        assert row["onnxruntime"] == 0.0, (opset, row)  # bit-identical: a relabelling
        assert row["onnxruntime-1.18"] <= PORTABLE_TOL, (opset, row)
        assert row["onnxruntime empty batch"] and row["onnxruntime-1.18 empty batch"], row
    with pytest.raises(ValueError, match="supported are 13"):
        portable.convert_opset(model_file, 12)


def test_onnx_version_converter_cannot_go_below_14():
    """Why convert_opset relabels instead (docs/portable.md, "Opsets"): onnx has no
    adapter down from opset 14 even for Add."""
    h = onnx.helper
    g = h.make_graph(
        [h.make_node("Add", ["x", "x"], ["y"])],
        "g",
        [h.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [2])],
        [h.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [2])],
    )
    m = h.make_model(g, opset_imports=[h.make_opsetid("", 17)])
    with pytest.raises(Exception, match="No Adapter From Version \\$?14 for Add"):
        onnx.version_converter.convert_version(m, 13)
    assert portable.convert_opset(m, 13).opset_import[0].version == 13


def test_convert_opset_drops_a_default_attribute_older_opsets_lack():
    # torch writes Reshape's allowzero = 0 (a textured graph has one); opset 13's Reshape
    # has no such attribute, so relabelling must drop it, and keep a value that matters
    h = onnx.helper
    g = h.make_graph(
        [h.make_node("Reshape", ["x", "s"], ["y"], allowzero=0)],
        "g",
        [h.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [2, 3])],
        [h.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [3, 2])],
        [h.make_tensor("s", onnx.TensorProto.INT64, [2], [3, 2])],
    )
    m = h.make_model(g, opset_imports=[h.make_opsetid("", 17)])
    out = portable.convert_opset(m, 13)  # before: ValidationError, unrecognized allowzero
    assert out.opset_import[0].version == 13 and not out.graph.node[0].attribute
    x = np.arange(6, dtype=np.float32).reshape(2, 3)
    sess = ort.InferenceSession(out.SerializeToString(), providers=["CPUExecutionProvider"])
    np.testing.assert_array_equal(sess.run(["y"], {"x": x})[0], x.reshape(3, 2))
    assert len(portable.convert_opset(m, 14).graph.node[0].attribute) == 1  # 14 knows it
    m.graph.node[0].attribute[0].i = 1
    with pytest.raises(ValueError, match="Reshape"):
        portable.convert_opset(m, 13)


# ------------------------------------------------------------------ metadata
@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A full export (metadata included) of a bright isotropic network, said to be fitted
    to the quickstart's analytic target; and the same file as version 1 wrote it."""
    cfg = config.load(ROOT / "configs" / "quickstart.yaml", TINY)
    target = analytic.create(cfg.target.model, **cfg.target.params)
    raw = pc.random_raw("isotropic")
    model, _ = export.normalized_model(raw, cfg)
    folder = tmp_path_factory.mktemp("exported")
    path = folder / "model.onnx"
    export.export(model, cfg, path, measure=validate.physics, target=target)
    old = onnx.load(str(path))  # as the code before metadata_version wrote it
    meta = {p.key: p.value for p in old.metadata_props}
    meta.pop("metadata_version")
    meta["target"] = target.describe()
    meta["training_config"] = cfg.to_yaml()
    for k in ("max_albedo", "reciprocity_error", "min_value"):
        meta[k] = repr(float(meta[k]))
    del old.metadata_props[:]
    onnx.helper.set_model_props(old, meta)
    v1 = folder / "v1.onnx"
    onnx.save(old, v1)
    return cfg, target, path, v1


def test_metadata_is_json_where_it_has_structure(exported):
    cfg, target, path, _ = exported
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert props["metadata_version"] == "2"
    homogeneous = [k for k in runtime.JSON_KEYS if k != "texture"]  # texture: a textured file's
    assert "texture" not in props
    for key in homogeneous:  # strict JSON: no NaN or Infinity
        assert "NaN" not in props[key] and "Infinity" not in props[key], key
        json.loads(props[key])
    t = json.loads(props["target"])
    assert t == {
        "kind": "analytic",
        "model": target.name,
        "params": json.loads(json.dumps(cfg.target.params)),
        "resolved": json.loads(json.dumps(target.params)),
        "description": target.describe(),
    }
    assert analytic.create(t["model"], **t["params"]).describe() == target.describe()
    assert config.from_dict(json.loads(props["training_config"])) == cfg
    text = {"producer", "frame", "units", "encoding", "normalization"}
    assert set(props) == set(homogeneous) | text
    brdf = neural_brdf.load(path)
    assert brdf.metadata_version == 2 and brdf.target == t
    assert config.from_dict(brdf.config) == cfg
    assert brdf.meta["hemispherical_albedo"] == json.loads(props["hemispherical_albedo"])


def test_version_1_metadata_still_reads(exported):
    cfg, target, path, v1 = exported
    new, old = neural_brdf.load(path), neural_brdf.load(v1)
    assert old.metadata_version == 1 and "metadata_version" not in old.metadata
    # the analytic.create(...) repr, parsed by ast: all but the parameters as given
    assert old.target == {k: v for k, v in new.target.items() if k != "params"}
    assert config.from_dict(old.config) == cfg
    assert old.meta["max_albedo"] == new.meta["max_albedo"]
    assert old.meta["sampling_lobe"] == new.meta["sampling_lobe"]
    assert runtime.parse_target("MERL gold-metallic-paint.binary (1000 measured bins)")["kind"] == (
        "measured"
    )
    assert runtime.parse_target("__import__('os').system('x')") == {
        "kind": "unspecified",
        "description": "__import__('os').system('x')",
    }
    assert runtime.read_metadata({"max_albedo": "inf"})["max_albedo"] == "inf"


def test_the_typed_metadata_writes_what_the_file_holds(exported):
    # Metadata is how the exporter writes: read back and written again, the strings and
    # their order are the file's, bit for bit
    cfg, target, path, v1 = exported
    props = reader.props(reader.load(path))
    info = Metadata.from_props(props)
    assert info.to_props() == props and list(info.to_props()) == list(props)
    assert neural_brdf.load(path).info == info
    assert info.metadata_version == 2 and info.format_version == fileformat.FORMAT_VERSION
    assert info.target == json.loads(props["target"])
    assert info.max_albedo == float(props["max_albedo"]) and info.max_albedo > 0
    assert info.sampling_lobe == json.loads(props["sampling_lobe"])
    assert config.from_dict(info.training_config) == cfg
    # one JSON object: strict JSON, every key of the file's schema
    assert set(json.loads(json.dumps(info.to_json(), allow_nan=False))) == set(props)
    # a version-1 file reads into the same object, but for the parameters as given
    old = Metadata.from_props(reader.props(reader.load(v1)))
    assert old.metadata_version == 1 and old.max_albedo == info.max_albedo
    assert old.target == {k: v for k, v in info.target.items() if k != "params"}
    assert old.sampling_lobe == info.sampling_lobe
    # unknown keys are kept as text; a non-finite figure is null in JSON
    odd = Metadata.from_props({"max_albedo": "inf", "x-other": "1"})
    assert odd.max_albedo == float("inf") and odd.other == {"x-other": "1"}
    assert odd.to_json() == {"metadata_version": 1, "max_albedo": None, "x-other": "1"}
    assert odd.to_props()["max_albedo"] == "inf"  # as the exporter writes a lone inf


def test_the_one_loader_names_a_file_that_is_not_onnx(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\xff\xff not onnx")
    with pytest.raises(InputError, match=r"bad\.onnx: not a loadable ONNX model"):
        reader.load(bad)
    with pytest.raises(InputError, match="model bytes: not a loadable ONNX model"):
        reader.load(b"\x08\xff\xff")
    (tmp_path / "empty.onnx").write_bytes(b"")  # protobuf reads it as an empty message
    with pytest.raises(InputError, match=r"empty\.onnx: not an ONNX model \(it has no graph"):
        reader.load(tmp_path / "empty.onnx")
    assert graph.load is reader.load  # the graph lowering reads through it


def test_javascript_reader_reads_what_python_onnx_reads(exported, tmp_path):
    _, _, path, v1 = exported
    # a file with long, non-ASCII values (multi-byte lengths) and none at all
    h = onnx.helper
    g = h.make_graph(
        [h.make_node("Identity", ["x"], ["y"])],
        "g",
        [h.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
        [h.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])],
    )
    odd = h.make_model(g)
    h.set_model_props(odd, {"é ключ": "θ → ∞ 🙂", "long": "x" * 70_000, "empty": ""})
    odd_path, bare = tmp_path / "odd.onnx", tmp_path / "bare.onnx"
    onnx.save(odd, odd_path)
    onnx.save(h.make_model(g), bare)
    files = [path, v1, odd_path, bare]
    got = _fail_if_missing(pc.read_metadata_js, *files)
    for f, r in zip(files, got):
        props = {p.key: p.value for p in onnx.load(str(f)).metadata_props}
        assert r["props"] == props, f
        assert list(r["props"]) == list(props)  # in file order
        py = runtime.read_metadata(props)
        for key in runtime.JSON_KEYS:
            if key in props and isinstance(py[key], (dict, list, int, float)):
                if not (key in ("target", "training_config") and py["metadata_version"] == 1):
                    assert r["decoded"][key] == py[key], (f, key)
        assert r["decoded"]["metadata_version"] == py["metadata_version"]
        if f != v1:  # JavaScript decodes into the typed object's JSON (version 2, none)
            assert r["decoded"] == Metadata.from_props(props).to_json(), f
    assert got[1]["decoded"]["target"] == got[1]["props"]["target"]  # v1: text stays text
    # the two lists of JSON keys are one list
    js = (ROOT / "neural_brdf" / "fileformat" / "onnx_metadata.js").read_text()
    listed = js.split("const ONNX_JSON_KEYS = [")[1].split("];")[0]
    assert sorted(json.loads("[" + listed + "]")) == sorted(runtime.JSON_KEYS)


def test_the_viewer_page_reads_the_metadata_from_the_file(exported, tmp_path):
    from harness import gpu_browser

    _, _, path, _ = exported
    out = viewer.write_viewer(path, tmp_path / "viewer.html")
    with gpu_browser.Session(width=1000, height=900) as s:
        s.open(out)
        assert s.evaluate("document.getElementById('nb-status').textContent") == "ready"
        assert list(s.errors) == []
        got = s.evaluate("JSON.stringify(nbViewer.metadata(0))")
        text = s.evaluate("document.getElementById('nb-meta').textContent")
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    decoded = json.loads(got)
    assert decoded["target"] == json.loads(props["target"])
    assert decoded["training_config"] == json.loads(props["training_config"])
    assert decoded["encoding"] == props["encoding"] and decoded["metadata_version"] == 2
    assert "fitted to microfacet" in text and "metadata version 2" in text


# ------------------------------------------------------------------ the docs
def _bench():
    spec = importlib.util.spec_from_file_location(
        "portable_bench", ROOT / "benchmarks" / "portable.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_docs_table_is_the_json():
    bench = _bench()
    data = json.loads(bench.OUT.read_text())
    page = bench.DOC.read_text()
    assert bench.render(data) in page, (
        "docs/portable.md is stale: python benchmarks/portable.py --docs"
    )
    for model in data["models"].values():
        for consumer in pc.CONSUMERS:
            assert pc.passed(model["consumers"][consumer]), (consumer, model["consumers"][consumer])


def test_ci_installs_every_consumer():
    ci = (ROOT / ".ci" / "run").read_text()
    assert f"onnxruntime=={pc.OLD_ORT}" in ci and ".venv-ort-old" in ci
    assert "npm ci" in ci and "ONNXRUNTIME_NODE_INSTALL=skip" in ci
    assert f"onnx2torch=={pc.ONNX2TORCH}" in ci
    lock = json.loads((ROOT / "tests" / "js" / "package-lock.json").read_text())
    assert lock["packages"]["node_modules/onnxruntime-web"]["version"] == "1.30.0"
