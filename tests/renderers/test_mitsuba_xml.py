"""Mitsuba 3 use as a renderer user writes it: XML scenes, variants, sample records.

* ``<bsdf type="neural_brdf">`` with a filename relative to the scene file loads through
  ``mi.load_file`` from any working folder and renders exactly what the dict form renders;
* ``analytic_brdf`` takes its parameters as ordinary XML properties;
* a spectral (or monochrome) variant is refused at import with a one-line error naming it,
  instead of a scene that loads and then dies in ``mi.render`` with ``std::bad_cast``;
* ``sample`` reports which lobe of the mixture drew the direction (diffuse or glossy).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from neural_brdf import export
from neural_brdf.train.model import NormalizedBRDF, RawBRDF, TotalBRDF, albedo_table

pytestmark = pytest.mark.mitsuba

RES, SPP = 24, 8
ANALYTIC = {"model": "microfacet", "alpha": 0.3, "fresnel": "conductor", "material": "Au"}

SCENE = """<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="-1"/></integrator>
    <sensor type="orthographic">
        <transform name="to_world">
            <scale x="1.1" y="1.1"/>
            <lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="{res}"/><integer name="height" value="{res}"/>
            <rfilter type="box"/>
        </film>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
    <shape type="sphere">
        {bsdf}
    </shape>
</scene>
"""


def _scene_dict(bsdf: dict) -> dict:
    import mitsuba as mi

    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": -1},
        "sensor": {
            "type": "orthographic",
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]
            )
            @ mi.ScalarTransform4f().scale([1.1, 1.1, 1.0]),
            "film": {"type": "hdrfilm", "width": RES, "height": RES, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": SPP},
        },
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "shape": {"type": "sphere", "bsdf": bsdf},
    }


@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    import neural_brdf.renderers.mitsuba  # noqa: F401  (registers the plugins)

    return mitsuba


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    """A folder holding model.onnx: a small random network (the plumbing is under test)."""
    torch.manual_seed(1)
    raw = RawBRDF("isotropic", [8, 8], "silu", init_value=0.2)
    table, _, _ = albedo_table(
        raw, size=16, anisotropic=False, samples=256, seed=0, sigmas=3.0, margin=1e-3
    )
    folder = tmp_path_factory.mktemp("scene")
    (folder / "model.onnx").write_bytes(
        export.to_onnx_bytes(TotalBRDF(NormalizedBRDF(raw, table).eval()), 17)
    )
    return folder


def _render(mi, scene) -> np.ndarray:
    return np.asarray(mi.render(scene, spp=SPP, seed=0), dtype=np.float64)


def test_xml_scene_with_relative_filename_renders_like_the_dict(
    mi, model_dir, tmp_path, monkeypatch
):
    xml = model_dir / "scene.xml"
    xml.write_text(
        SCENE.format(
            res=RES,
            spp=SPP,
            bsdf='<bsdf type="neural_brdf"><string name="filename" value="model.onnx"/></bsdf>',
        )
    )
    monkeypatch.chdir(tmp_path)  # the model is found beside the scene
    assert not (tmp_path / "model.onnx").exists()
    img = _render(mi, mi.load_file(str(xml)))
    ref = _render(
        mi,
        mi.load_dict(
            _scene_dict({"type": "neural_brdf", "filename": str(model_dir / "model.onnx")})
        ),
    )
    assert img.shape == (RES, RES, 3) and np.isfinite(img).all()
    centre = img[RES // 2 - 2 : RES // 2 + 2, RES // 2 - 2 : RES // 2 + 2]
    assert 0.01 < centre.mean() < 1.0 + 1e-3  # lit sphere, no energy gain
    assert np.allclose(img, ref, rtol=1e-5, atol=1e-6)


def test_xml_scene_with_a_missing_model_names_the_file(mi, tmp_path):
    xml = tmp_path / "scene.xml"
    xml.write_text(
        SCENE.format(
            res=RES,
            spp=SPP,
            bsdf='<bsdf type="neural_brdf"><string name="filename" value="nowhere.onnx"/></bsdf>',
        )
    )
    with pytest.raises(Exception, match="nowhere.onnx"):
        mi.load_file(str(xml))


def test_analytic_brdf_takes_plain_xml_properties(mi, tmp_path):
    props = (
        '<bsdf type="analytic_brdf"><string name="model" value="microfacet"/>'
        '<float name="alpha" value="0.3"/><string name="fresnel" value="conductor"/>'
        '<string name="material" value="Au"/></bsdf>'
    )
    xml = tmp_path / "analytic.xml"
    xml.write_text(SCENE.format(res=RES, spp=SPP, bsdf=props))
    img = _render(mi, mi.load_file(str(xml)))
    params = {k: v for k, v in ANALYTIC.items() if k != "model"}
    ref = _render(
        mi,
        mi.load_dict(
            _scene_dict(
                {
                    "type": "analytic_brdf",
                    "model": "microfacet",
                    "params": __import__("json").dumps(params),
                }
            )
        ),
    )
    assert np.allclose(img, ref, rtol=1e-5, atol=1e-6)
    gold = img[RES // 2, RES // 2]
    assert gold[0] > gold[2] > 0  # gold: red above blue


@pytest.mark.parametrize("variant", ["llvm_ad_spectral", "scalar_spectral", "llvm_ad_mono"])
def test_non_rgb_variant_is_refused_with_its_name(variant):
    code = textwrap.dedent(f"""
        import mitsuba as mi
        mi.set_variant({variant!r})
        import neural_brdf.renderers.mitsuba
    """)
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=dict(os.environ),
        timeout=300,
    )
    assert out.returncode != 0
    last = out.stderr.strip().splitlines()[-1]
    assert "ImportError" in last and variant in last and "RGB" in last, last


def test_sample_reports_the_lobe_that_drew_it(mi):
    import drjit as dr

    bsdf = mi.load_dict({"type": "analytic_brdf", **ANALYTIC})
    weight = bsdf.lobe_weight
    assert 0.0 < weight < 1.0
    n = 4096
    rng = np.random.default_rng(0)
    si = dr.zeros(mi.SurfaceInteraction3f)
    theta = np.radians(40.0)
    si.wi = mi.Vector3f(float(np.sin(theta)), 0.0, float(np.cos(theta)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    u1 = rng.random(n)
    bs, _ = bsdf.sample(mi.BSDFContext(), si, mi.Float(u1), mi.Point2f(rng.random((2, n))))
    kind = np.asarray(bs.sampled_type)
    glossy, diffuse = +mi.BSDFFlags.GlossyReflection, +mi.BSDFFlags.DiffuseReflection
    assert np.array_equal(kind == glossy, u1 < weight)
    assert np.array_equal(kind == diffuse, u1 >= weight)
