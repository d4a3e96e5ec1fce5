"""A textured Mitsuba BSDF as a spatially varying teacher (neural_brdf/measured/textured.py,
procedural.py; issue 30, the first building block of spatially varying models).

Every reference is computed here on its own: the texture files are read back with
``mi.Bitmap`` and numpy, a HOMOGENEOUS Mitsuba BSDF is built from one texel's values and
evaluated by Mitsuba, and Mitsuba's own ``normalmap`` wrapper is compared with the nested
BSDF in the frame that normalmap.cpp builds.  16 x 16 textures keep it fast.

* (a) f at a texel centre is the homogeneous BSDF of that texel's values; so is the pdf
  (roughplastic's: of the texture's mean, as Mitsuba's sampler chooses its lobes);
* (b) f is reciprocal to float32 rounding at random uv (principled without its normal
  map, roughplastic); Mitsuba's normalmap-wrapped BSDF is not (why it is kept apart);
* (c) 0 below the horizon and for non-finite input, finite and >= 0 elsewhere;
* (d) normal_field is normalize(2 texel - 1) and reproduces Mitsuba's normalmap (and
  bumpmap) wrapper from the nested BSDF; a bump bitmap's field in the file (its texels
  read as the file does) follows the teacher's between texel centres (a mean error of a
  few % of the mean tilt, was 39 to 89 %), and one far from it is warned in one line;
* (e) a missing texture file, a non-RGB variant, a transmissive BSDF: one-line InputError;
* (f) f varies over uv; max_albedo agrees with an independent quadrature.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neural_brdf.errors import InputError
from neural_brdf.validate import normal_field_error

pytestmark = pytest.mark.mitsuba

SIZE = 16
TEXELS = [(0, 0), (3, 11), (9, 4), (15, 15)]  # (column i, row j)


@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


@pytest.fixture(scope="module")
def xmls(mi, tmp_path_factory) -> dict[str, Path]:
    from neural_brdf.measured.procedural import write_teacher

    folder = tmp_path_factory.mktemp("textured")
    return {k: write_teacher(folder / k, k, size=SIZE) for k in ("principled", "roughplastic")}


@pytest.fixture(scope="module")
def targets(xmls):
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    return {k: TexturedMitsubaTarget(p) for k, p in xmls.items()}


def texel(mi, path: Path, i: int, j: int) -> np.ndarray:
    """The stored value of column i, row j, read back from the file."""
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)[j, i]


def centre(i: int, j: int) -> np.ndarray:
    return np.array([(i + 0.5) / SIZE, (j + 0.5) / SIZE])


def pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions above the horizon (polar angles up to ~87 degrees)."""
    rng = np.random.default_rng(seed)

    def hemi():
        z = 0.05 + 0.95 * rng.random(n)
        phi = 2 * math.pi * rng.random(n)
        r = np.sqrt(1 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)

    return hemi(), hemi()


def interaction(mi, wi: np.ndarray, uv: np.ndarray | None = None):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(np.ascontiguousarray(wi.T, dtype=np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    si.n = mi.Vector3f(0.0, 0.0, 1.0)
    if uv is not None:
        si.uv = mi.Point2f(np.ascontiguousarray(uv.T, dtype=np.float32))
    return si


def mitsuba_f(mi, bsdf, wi, wo, uv=None) -> np.ndarray:
    """Mitsuba's eval / cos(theta_o) of ``bsdf``, computed here on its own."""
    vec = mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32))
    value = bsdf.eval(mi.BSDFContext(), interaction(mi, wi, uv), vec)
    return np.array(value, dtype=np.float64).T / wo[:, 2:3]


def homogeneous(mi, kind: str, folder: Path, i: int, j: int):
    """The BSDF of texel (i, j) with constant parameters, as Mitsuba builds it."""

    def v(name):
        return ", ".join(repr(float(x)) for x in np.atleast_1d(texel(mi, folder / name, i, j)))

    if kind == "principled":
        xml = f"""<bsdf version="3.0.0" type="principled">
            <rgb name="base_color" value="{v("base_color.exr")}"/>
            <float name="roughness" value="{v("roughness.exr")}"/>
            <float name="metallic" value="{v("metallic.exr")}"/>
            <float name="specular" value="0.5"/></bsdf>"""
    else:
        xml = f"""<bsdf version="3.0.0" type="roughplastic">
            <string name="distribution" value="ggx"/><float name="alpha" value="0.2"/>
            <float name="int_ior" value="1.5"/>
            <rgb name="diffuse_reflectance" value="{v("diffuse.exr")}"/></bsdf>"""
    return mi.load_string(xml)


# ------------------------------------------------------------------ (a)
@pytest.mark.parametrize("kind", ["principled", "roughplastic"])
def test_a_texel_centre_is_the_homogeneous_bsdf_of_its_values(mi, kind, xmls, targets):
    t = targets[kind]
    wi, wo = pairs(128, 1)
    for i, j in TEXELS:
        uv = np.tile(centre(i, j), (len(wi), 1))
        ref = homogeneous(mi, kind, xmls[kind].parent, i, j)
        np.testing.assert_allclose(t.eval(wi, wo, uv), mitsuba_f(mi, ref, wi, wo), rtol=2e-5)
        if kind == "roughplastic":
            # roughplastic.cpp picks its lobes by the diffuse texture's MEAN luminance
            # (Texture::mean(), the whole bitmap's; Rec. 709 weights), not the texel's:
            # its pdf at any uv is that of a homogeneous grey roughplastic of that mean.
            rgb = np.array(mi.Bitmap(str(xmls[kind].parent / "diffuse.exr")), dtype=np.float64)
            mean = float((rgb @ [0.212671, 0.715160, 0.072169]).mean())
            ref = mi.load_string(
                '<bsdf version="3.0.0" type="roughplastic"><float name="alpha" value="0.2"/>'
                '<string name="distribution" value="ggx"/><float name="int_ior" value="1.5"/>'
                f'<float name="diffuse_reflectance" value="{mean!r}"/></bsdf>'
            )
        ref_pdf = np.array(
            ref.pdf(
                mi.BSDFContext(),
                interaction(mi, wi),
                mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32)),
            ),
            dtype=np.float64,
        )
        np.testing.assert_allclose(t.pdf(wi, wo, uv), ref_pdf, rtol=2e-5)
    # the sampler's directions are above the horizon with a positive density
    u = np.random.default_rng(2).random((len(wi), 2))
    uv = np.random.default_rng(3).random((len(wi), 2))
    drawn = t.sample(wi, uv, u)
    ok = drawn[:, 2] > 0
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.linalg.norm(drawn[ok], axis=-1), 1.0, atol=1e-6)
    assert np.all(t.pdf(wi[ok], drawn[ok], uv[ok]) > 0)


# ------------------------------------------------------------------ (b)
def asymmetry(t, n: int = 4096) -> float:
    wi, wo = pairs(n, 4)
    uv = np.random.default_rng(5).random((n, 2))
    a, b = t.eval(wi, wo, uv), t.eval(wo, wi, uv)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(a), 1e-12)))


@pytest.mark.parametrize("kind", ["principled", "roughplastic"])
def test_f_is_reciprocal_to_float32_rounding(kind, targets):
    # Measured (Mitsuba 3.9.1, llvm_ad_rgb): max relative |f(wi,wo) - f(wo,wi)| / f of
    # ~1e-6 for both: float32 rounding of formulas symmetric in (wi, wo).  roughplastic's
    # diffuse term (1 - F(wi)) (1 - F(wo)) / (1 - internal) is symmetric too.
    assert asymmetry(targets[kind]) < 2e-5


def test_mitsubas_normalmap_wrapper_is_not_reciprocal(mi, xmls, targets):
    """Why the normal map is a separate field: Mitsuba's normalmap-wrapped BSDF is not
    reciprocal (the shadowing term depends on wo alone), by far more than rounding."""
    wrapped = dict(_kids(mi, mi.load_file(str(xmls["principled"]))))["brdf_0"]
    assert wrapped.class_name() == "NormalMap"
    wi, wo = pairs(4096, 6)
    uv = np.random.default_rng(7).random((len(wi), 2))
    a, b = mitsuba_f(mi, wrapped, wi, wo, uv), mitsuba_f(mi, wrapped, wo, wi, uv)
    both = (a > 1e-6) & (b > 1e-6)
    rel = np.max(np.abs(a - b)[both] / a[both])
    assert rel > 1e-3, rel


def _kids(mi, obj):
    class Collect(mi.TraversalCallback):
        def __init__(self):
            super().__init__()
            self.found = []

        def put(self, name, value, flags, *rest):
            if isinstance(value, mi.Object):
                self.found.append((name, value))

    cb = Collect()
    obj.traverse(cb)
    return cb.found


# ------------------------------------------------------------------ (c)
def test_zero_below_the_horizon_and_finite_everywhere(targets):
    t = targets["principled"]
    wi, wo = pairs(256, 8)
    uv = np.random.default_rng(9).random((256, 2)) * 3 - 1  # outside [0, 1]: wrapped
    f = t.eval(wi, wo, uv)
    assert np.all(np.isfinite(f)) and np.all(f >= 0) and f.max() > 0
    below = wo * [1, 1, -1]
    assert np.all(t.eval(wi, below, uv) == 0) and np.all(t.eval(below, wo, uv) == 0)
    flat = wo * [1, 1, 0]
    assert np.all(t.eval(wi, flat, uv) == 0)
    bad_uv = uv.copy()
    bad_uv[::2] = np.nan
    g = t.eval(wi, wo, bad_uv)
    assert np.all(g[::2] == 0) and np.array_equal(g[1::2], f[1::2])
    nan_wi = wi.copy()
    nan_wi[:, 0] = np.inf
    assert np.all(t.eval(nan_wi, wo, uv) == 0)
    assert np.all(t.pdf(wi, below, uv) == 0)
    assert np.all(t.sample(below, uv, np.full((256, 2), 0.5))[:, 2] < 0)
    # broadcasting: one pair at many uv
    assert t.eval(wi[0], wo[0], uv).shape == (256, 3)


# ------------------------------------------------------------------ (d)
def test_normal_field_is_the_decoded_normal_map(mi, xmls, targets):
    t = targets["principled"]
    folder = xmls["principled"].parent
    for i, j in TEXELS:
        n = 2 * texel(mi, folder / "normal.exr", i, j) - 1
        n /= np.linalg.norm(n)
        np.testing.assert_allclose(t.normal_field(centre(i, j)[None])[0], n, atol=2e-6)
    uv = np.random.default_rng(10).random((64, 2))
    field = t.normal_field(uv)
    tilt = np.degrees(np.arccos(field[:, 2]))
    assert 0.1 < tilt.max() < 5.0  # gentle, not flat
    np.testing.assert_array_equal(targets["roughplastic"].normal_field(uv), [[0, 0, 1]] * 64)


def wrapper_from_nested(t, wi, wo, uv):
    """eval cos of Mitsuba's normalmap / bumpmap wrapper, rebuilt here from the target
    (the nested BSDF) and its normal_field: the nested BSDF in the frame that
    normalmap.cpp / bumpmap.cpp build (s = normalize(x - n n_x), t = n x s), times their
    shadowing term (Estevez et al., Ray Tracing Gems 2019: 2 / (1 + sqrt(1 + a2
    tan^2 theta_o)), a2 = min(1, tan^2 theta_n / 8)).  Returns it and the rows where wo
    is clearly on the same side of both normals."""
    n = t.normal_field(uv)
    s = np.array([1.0, 0, 0]) - n * n[:, :1]
    s /= np.linalg.norm(s, axis=-1, keepdims=True)
    tt = np.cross(n, s)

    def local(w):
        return np.stack([(w * s).sum(-1), (w * tt).sum(-1), (w * n).sum(-1)], -1)

    wi_p, wo_p = local(wi), local(wo)
    tan2_n = (1 - n[:, 2] ** 2) / n[:, 2] ** 2
    tan2_o = (1 - wo[:, 2] ** 2) / wo[:, 2] ** 2
    shadow = 2 / (1 + np.sqrt(1 + np.minimum(0.125 * tan2_n, 1.0) * tan2_o))
    return t.eval(wi_p, wo_p, uv) * wo_p[:, 2:3] * shadow[:, None], wo_p[:, 2] > 0.05


def near_normal_pairs(n: int, seed: int):
    """wi within ~17 degrees of the normal, so the wrappers' flip never applies."""
    wi, wo = pairs(n, seed)
    wi = wi * [0.3, 0.3, 1]
    return wi / np.linalg.norm(wi, axis=-1, keepdims=True), wo


def test_normal_field_reproduces_mitsubas_normalmap(mi, xmls, targets):
    t = targets["principled"]
    wrapped = dict(_kids(mi, mi.load_file(str(xmls["principled"]))))["brdf_0"]
    wi, wo = near_normal_pairs(512, 12)
    uv = np.random.default_rng(11).random((512, 2))
    mine, keep = wrapper_from_nested(t, wi, wo, uv)
    theirs = mitsuba_f(mi, wrapped, wi, wo, uv) * wo[:, 2:3]
    np.testing.assert_allclose(mine[keep], theirs[keep], rtol=2e-4, atol=1e-7)
    # and the tilt matters: without it the nested BSDF is visibly different
    plain = t.eval(wi, wo, uv) * wo[:, 2:3]
    assert np.max(np.abs(plain[keep] - theirs[keep])) > 1e-3 * theirs[keep].max()


def test_a_bumpmap_is_unwrapped_and_its_normal_field_reproduces_mitsubas(mi, xmls):
    """bumpmap.cpp's normal is that of p + scale h n for dp_du = x, dp_dv = y (the
    target's interaction): Mitsuba's bumpmap is evaluated here at such an interaction."""
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    path = xmls["principled"].parent / "bump.xml"
    path.write_text(
        '<bsdf version="3.0.0" type="bumpmap"><float name="scale" value="0.05"/>'
        '<texture type="bitmap" name="height"><string name="filename" value="roughness.exr"/>'
        '<boolean name="raw" value="true"/></texture>'
        '<bsdf type="roughplastic"><float name="alpha" value="0.3"/></bsdf></bsdf>'
    )
    t = TexturedMitsubaTarget(path)
    assert t.plugin == "bumpmap > RoughPlastic" and t.normal_map["plugin"] == "bumpmap"
    wi, wo = near_normal_pairs(512, 15)
    uv = np.random.default_rng(16).random((512, 2))
    mine, keep = wrapper_from_nested(t, wi, wo, uv)
    si = interaction(mi, wi, uv)
    si.dp_du, si.dp_dv = mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0)
    vec = mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32))
    theirs = np.array(mi.load_file(str(path)).eval(mi.BSDFContext(), si, vec), dtype=np.float64).T
    assert np.degrees(np.arccos(t.normal_field(uv)[:, 2])).max() > 1.0  # a real tilt
    np.testing.assert_allclose(mine[keep], theirs[keep], rtol=2e-4, atol=1e-7)


# ------------------------------------------------------------------ (d) a bump bitmap's field
# The gradient of a bitmap's bilinear height is constant in u across each cell between
# four texel centres and jumps at the centres.  Sampled at the bitmap's own texel centres
# (one side's difference or the other's), the file's field lagged by half a texel: a mean
# error of 8.5 deg against a mean tilt of 22 deg on the smooth map below (scale 0.5), 50
# against 62 deg on the noise, silently.  The file's field (its texels through
# NormalField, the file's bilinear look-up) is scored against the teacher's normal_field
# (Mitsuba's eval_1_grad at each uv, checked against Mitsuba's bumpmap wrapper above) by
# validate.normal_field_error.

# the file's mean error over the teacher's mean tilt: 0.7 to 1.6 % sampled inside the
# cells, 39 to 89 % at the bitmap's texel centres (these maps, scales 0.5 and 0.05)
BUMP_SHARE = 0.05


def bump_teacher(mi, folder: Path, *, shape: tuple[int, int], scale: float, noise: bool) -> Path:
    """A bumpmap of an 8-bit PNG height map (raw) over a roughconductor at alpha 0.3."""
    rng = np.random.default_rng(3)
    rows, cols = shape
    if noise:
        h = rng.random(shape)
    else:  # smooth relief and a little noise
        v, u = np.meshgrid(
            (np.arange(rows) + 0.5) / rows, (np.arange(cols) + 0.5) / cols, indexing="ij"
        )
        h = 0.5 + 0.2 * np.sin(2 * np.pi * u) * np.cos(4 * np.pi * v) + 0.05 * rng.random(shape)
    folder.mkdir(parents=True, exist_ok=True)
    rgb = np.repeat(h[..., None], 3, -1).astype(np.float32)  # written now, not in a thread
    mi.util.write_bitmap(str(folder / "height.png"), rgb, write_async=False)
    xml = folder / "bump.xml"
    xml.write_text(
        f'<bsdf version="3.0.0" type="bumpmap"><float name="scale" value="{scale}"/>'
        '<texture type="bitmap" name="height"><string name="filename" value="height.png"/>'
        '<boolean name="raw" value="true"/></texture>'
        '<bsdf type="roughconductor"><float name="alpha" value="0.3"/></bsdf></bsdf>'
    )
    return xml


def file_normal(texels: np.ndarray):
    """The file's normal(uv): its texels looked up as the file does (NormalField)."""
    from neural_brdf.train.textured_model import NormalField

    field = NormalField(texels)

    def normal(uv):
        with torch.no_grad():
            return field(torch.as_tensor(uv, dtype=torch.float32)).double().numpy()

    return normal


def mean_tilt(t) -> float:
    n = t.normal_field(np.random.default_rng(5).random((4096, 2)))
    return float(np.degrees(np.arccos(np.clip(n[:, 2], -1, 1))).mean())


@pytest.mark.parametrize(
    "shape, scale, noise",
    [((16, 16), 0.5, False), ((16, 16), 0.05, False), ((16, 16), 0.5, True), ((10, 24), 0.5, True)],
)
def test_a_bump_bitmaps_file_field_follows_mitsubas_between_texel_centres(
    mi, tmp_path, shape, scale, noise
):
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    t = TexturedMitsubaTarget(bump_teacher(mi, tmp_path, shape=shape, scale=scale, noise=noise))
    tilt = mean_tilt(t)
    assert tilt > 1.0  # a real relief
    figures = normal_field_error(file_normal(t.normal_texels()), t, n=20000, seed=6)
    assert figures["mean_deg"] < BUMP_SHARE * tilt, (figures, tilt)


@pytest.mark.parametrize(
    "plugin, to_uv, share",
    [
        ("normalmap", '<scale x="3" y="3"/>', 1e-3),  # texel centres on texel centres
        ("normalmap", '<rotate z="1" angle="90"/><scale x="2" y="1"/>', 1e-3),
        ("normalmap", '<scale x="2.5" y="1.5"/>', 0.05),  # sampled twice per texel
        ("bumpmap", '<scale x="3" y="2"/>', BUMP_SHARE),
    ],
)
def test_a_map_repeated_by_to_uv_is_sampled_over_its_repeats(mi, tmp_path, plugin, to_uv, share):
    """A bitmap's to_uv repeats it over the surface's uv square: the file's normal field
    is sampled over the repeats (a 64² normal map at scale 3: 192²), not at the bitmap's
    own 64² texels, which lay 3 copies under 64 samples (7.3 degrees off on average
    against a mean tilt of 20)."""
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    x = (np.arange(64) + 0.5) / 64
    if plugin == "normalmap":  # stripes along u, 8 periods: 2 t - 1 is the normal
        n = np.zeros((64, 64, 3))
        n[..., 2] = 1.0
        n[..., 0] = 0.6 * np.sin(2 * np.pi * 8 * x)[None, :]
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        texture = (n * 0.5 + 0.5).astype(np.float32)
        extra = ""
    else:  # a smooth height over both axes
        h = 0.5 + 0.2 * np.sin(2 * np.pi * 4 * x)[None, :] * np.cos(2 * np.pi * 3 * x)[:, None]
        texture = np.repeat(h[..., None], 3, -1).astype(np.float32)
        extra = '<float name="scale" value="0.02"/>'
    mi.util.write_bitmap(str(tmp_path / "map.exr"), texture, write_async=False)
    name = "normalmap" if plugin == "normalmap" else "height"
    xml = tmp_path / "mat.xml"
    xml.write_text(
        f'<bsdf version="3.0.0" type="{plugin}">{extra}'
        f'<texture type="bitmap" name="{name}"><string name="filename" value="map.exr"/>'
        f'<boolean name="raw" value="true"/><transform name="to_uv">{to_uv}</transform>'
        "</texture>"
        '<bsdf type="roughplastic"><float name="alpha" value="0.15"/></bsdf></bsdf>'
    )
    t = TexturedMitsubaTarget(xml)
    tilt = mean_tilt(t)
    assert tilt > 1.0  # a real relief
    texels = t.normal_texels()
    assert texels.shape[0] * texels.shape[1] > 64 * 64  # more than the bitmap's own
    figures = normal_field_error(file_normal(texels), t, n=20000, seed=6)
    assert figures["mean_deg"] < share * tilt, (figures, tilt, texels.shape)


def test_a_teacher_finer_than_the_field_is_warned_in_one_line(mi, tmp_path):
    """A checkerboard of 2 x 3 repeats (hard edges) is 28 % off in a 32² field after
    training, with no word; f cos sampled at the field's texel centres and interpolated
    is already far off it between them: a warning names the field and the fix.  A
    smooth procedural teacher (the tour's kind) gets none, nor a field fine enough."""
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget
    from neural_brdf.train.textured_model import DETAIL_WARN, detail_error, detail_warning

    xml = tmp_path / "checker.xml"
    xml.write_text(
        '<bsdf type="diffuse" version="3.0.0"><texture type="checkerboard" name="reflectance">'
        '<rgb name="color0" value="0.8, 0.1, 0.1"/><rgb name="color1" value="0.1, 0.1, 0.8"/>'
        '<transform name="to_uv"><scale x="2" y="3"/></transform></texture></bsdf>'
    )
    t = TexturedMitsubaTarget(xml)
    line = detail_warning(t, 32)
    assert line is not None and len(line.splitlines()) == 1
    for needle in (str(xml), "32x32 texels", f"{100 * detail_error(t, 32):.0f} %", "texture."):
        assert needle in line, line
    assert detail_error(t, 32) > 2 * DETAIL_WARN
    # a finer field: the band where bilinear texels blur the cells' edges narrows
    assert detail_error(t, 256) < detail_error(t, 32)
    smooth = TexturedMitsubaTarget(write_teacher(tmp_path / "tour", "roughplastic", size=64))
    assert detail_warning(smooth, 32) is None
    assert 0.0 < detail_error(smooth, 32) < DETAIL_WARN  # measured, not skipped


def test_a_field_far_from_the_teachers_is_warned_in_one_line(mi, tmp_path, targets):
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    xml = bump_teacher(mi, tmp_path, shape=(16, 16), scale=0.5, noise=False)
    t = TexturedMitsubaTarget(xml)
    # the field sampled at the bitmap's own texel centres, where the gradient jumps
    centres = (np.arange(16) + 0.5) / 16
    uv = np.stack(np.meshgrid(centres, centres, indexing="xy"), -1).reshape(-1, 2)
    at_centres = t.normal_field(uv).reshape(16, 16, 3)
    far = normal_field_error(file_normal(at_centres), t, n=20000, seed=6)
    assert far["mean_deg"] > 0.2 * mean_tilt(t)  # the defect, as a file of these texels had it
    line = t.normal_field_warning(far)
    assert line is not None and len(line.splitlines()) == 1
    for needle in (str(xml), f"{far['mean_deg']:.2f} deg", f"{far['max_deg']:.1f} deg", "bumpmap"):
        assert needle in line, line
    # the file's own field: no line; no figures, or a teacher without a map: none either
    near = normal_field_error(file_normal(t.normal_texels()), t, n=20000, seed=6)
    assert t.normal_field_warning(near) is None
    assert t.normal_field_warning(None) is None
    assert targets["roughplastic"].normal_field_warning(far) is None


# ------------------------------------------------------------------ (e)
def test_a_missing_texture_file_is_one_line_naming_it(mi, tmp_path):
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    xml = write_teacher(tmp_path, "principled", size=4)
    (tmp_path / "roughness.exr").unlink()
    with pytest.raises(InputError) as e:
        TexturedMitsubaTarget(xml)
    msg = str(e.value)
    assert len(msg.splitlines()) == 1 and "roughness.exr" in msg and str(xml) in msg


def test_unusable_variants_and_bsdfs_are_one_line(mi, tmp_path):
    from neural_brdf.measured.procedural import write_teacher
    from neural_brdf.measured.textured import TexturedMitsubaTarget

    xml = write_teacher(tmp_path, "roughplastic", size=4)
    with pytest.raises(InputError, match="target.variant: .scalar_spectral.: .*RGB"):
        TexturedMitsubaTarget(xml, variant="scalar_spectral")
    glass = tmp_path / "glass.xml"
    glass.write_text(
        '<bsdf version="3.0.0" type="principled"><float name="spec_trans" value="0.5"/>'
        '<texture type="bitmap" name="base_color"><string name="filename" '
        'value="diffuse.exr"/></texture></bsdf>'
    )
    with pytest.raises(InputError, match="transmits") as e:
        TexturedMitsubaTarget(glass)
    assert str(glass) in str(e.value) and len(str(e.value).splitlines()) == 1


# ------------------------------------------------------------------ (f)
def test_the_target_varies_over_uv_and_is_a_spatially_varying_target(mi, xmls, targets):
    from neural_brdf import target

    t = targets["principled"]
    assert isinstance(t, target.SpatiallyVarying) and target.spatially_varying(t)
    assert target.kind_of(t) == "mitsuba" and not t.anisotropic
    wi, wo = pairs(1, 13)
    uv = np.array([centre(i, j) for i, j in TEXELS])
    f = t.eval(np.repeat(wi, len(uv), 0), np.repeat(wo, len(uv), 0), uv)
    # the texels differ in the files, so their f differ
    for a in range(len(uv)):
        for b in range(a):
            assert np.max(np.abs(f[a] - f[b])) > 1e-3 * f.max()


def test_a_scenes_one_textured_bsdf_is_the_teacher(mi, xmls, targets):
    """docs/mitsuba.md: a file may be a scene with one top-level <bsdf>; textured, it was
    refused as "Mitsuba cannot evaluate it ('Scene' object has no attribute 'eval')"."""
    import xml.etree.ElementTree as ET

    from neural_brdf.measured.textured import TexturedMitsubaTarget

    bare = xmls["roughplastic"]
    bsdf = ET.parse(bare).getroot()
    bsdf.attrib.pop("version", None)
    scene = ET.Element("scene", version="3.0.0")
    scene.append(bsdf)
    path = bare.with_name("in_a_scene.xml")  # beside the bare file: its textures resolve
    ET.ElementTree(scene).write(path)
    t = TexturedMitsubaTarget(path)
    wi, wo = pairs(64, 5)
    uv = np.random.default_rng(2).random((64, 2))
    assert np.array_equal(t.eval(wi, wo, uv), targets["roughplastic"].eval(wi, wo, uv))


def test_max_albedo_is_the_quadrature_of_f_cos(mi, targets):
    """Mitsuba's sample weights averaged vs a cosine-weighted Monte Carlo of f here."""
    t = targets["roughplastic"]
    uv = np.array([centre(3, 11)])
    est = t.max_albedo(uv, theta_deg=(0.0, 60.0), samples=1 << 15)[0]
    rng = np.random.default_rng(14)
    n = 1 << 16
    r, phi = np.sqrt(rng.random(n)), 2 * math.pi * rng.random(n)
    wo = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - r * r)], -1)
    ref = 0.0
    for theta in (0.0, 60.0):
        wi = np.array([math.sin(math.radians(theta)), 0.0, math.cos(math.radians(theta))])
        ref = np.maximum(ref, math.pi * t.eval(wi, wo, np.tile(uv, (n, 1))).mean(0))
    np.testing.assert_allclose(est, ref, rtol=0.03)
