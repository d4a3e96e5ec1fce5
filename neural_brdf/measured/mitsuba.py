"""A teacher that Mitsuba 3 evaluates: ``target: {mitsuba: FILE.xml}`` (issue 30, item 1).

    from neural_brdf.measured.mitsuba import MitsubaTarget
    teacher = MitsubaTarget("roughplastic.xml")     # InputError naming the file if unusable
    teacher.eval(wi, wo)                            # f (N, 3), 1/sr, no cosine (numpy)
    teacher.sample_dir_t(wi, u), teacher.pdf_t(wi, wo)   # Mitsuba's own sampler (torch)

The file holds one ``<bsdf>`` (at its root, or the only top-level ``<bsdf>`` of a
``<scene>``), any plugin of an RGB variant; Mitsuba resolves its relative file names
(bitmaps, ``measured`` tables) against the XML's folder.  A ``twosided`` wrapper is
unwrapped to its front BSDF (a BRDF has one side).  The teacher is evaluated by
Mitsuba's own ``BSDF.eval`` in an RGB JIT variant (``llvm_ad_rgb`` unless the config's
``target.variant`` says ``cuda_ad_rgb``), in batches of :data:`CHUNK` pairs, at a
surface interaction in the local frame (fileformat.FRAME: the tangent is ``dp_du``,
x), and divided by cos(theta_o): Mitsuba's ``eval`` returns f cos(theta_o), this
module returns f, as every target does.  Its importance sampler is ``BSDF.sample`` and
``BSDF.pdf``, so the ``importance`` share of the training pairs, the accuracy pairs and
the quadratures' own proposal are the teacher's.

Refused, with one line naming the file (exit 2): a file Mitsuba cannot load (a spectral
table in an RGB variant included), a BSDF that transmits (dielectrics, masks, the
principled's ``spec_trans``), one with a delta (perfectly smooth) lobe, alone or beside
rough ones (a network of finite values cannot hold it, and Mitsuba's ``eval`` leaves
it out, so the file would silently lose it) or a rough one at roughness 0 anywhere on
the surface (:func:`check_rough`), one with negative or non-finite values (at
a probed uv, or a bitmap texel of NaN or inf), and one whose value depends on the position
on the surface (a texture, a normal or bump map): :class:`VariesOverSurface`, which
``train.data.build_target`` answers with a spatially varying teacher
(:mod:`neural_brdf.measured.textured`).  Spatial variation is probed, not guessed from
the plugin: the BSDF is evaluated at :data:`PROBE_UV` random texture coordinates (and
positions) on the same pairs, and a bitmap texture with more than one distinct texel
counts too.  Anisotropy is probed the same way (the same pairs turned about the
normal): ``anisotropic`` is True when the value depends on the azimuth.

Energy.  A teacher whose directional albedo A(w) = int f cos dwo exceeds 1 (Mitsuba's
``principled`` does, 1.04 to 1.19 at base colour 1, roughness 0.5) is learned as its
energy-bounded version, per RGB channel::

    f_b(wi, wo) = f(wi, wo) / max(1, A+(wi), A+(wo))

with A+ an upper bound of A over the polar angle (:meth:`MitsubaTarget.bound`).  Why
this form:

* reciprocal: the divisor is symmetric in (wi, wo) bit for bit (``max`` commutes, and
  A+ is a function of one direction), so f_b is exactly as reciprocal as f.  Dividing
  by max(1, A(wi)) alone, the per-incidence normalisation, is not;
* bounded: A_b(wi) = int f cos / max(1, A+(wi), A+(wo)) <= A(wi) / max(1, A+(wi)) <= 1
  wherever A+ >= A.  The geometric mean sqrt(A(wi) A(wo)), reciprocal as well, is not
  a bound: where A(wi) > 1 but the lobe points to directions with A(wo) < 1 the
  divisor falls back towards 1;
* minimal: where neither direction exceeds 1 the teacher is untouched, whereas the
  global max(1, max A) darkens every direction by the worst one's excess.

A+ is tabulated at :data:`THETA_NODES` polar angles by :func:`physics.quadrature.albedo`
(the teacher's own sampler among the proposals), plus :data:`SIGMAS` standard errors,
maximised over :data:`AZIMUTHS` azimuths for an anisotropic teacher, and read between
nodes as the larger of the two neighbours (an upper envelope where A is monotone
between nodes).  A teacher whose albedo stays within :data:`EXCESS_TOL` of 1 is left
as it is.  Where and by how much it exceeded 1 is in :attr:`MitsubaTarget.excess` and
in :meth:`~MitsubaTarget.describe` (the metadata's target description and the report).

Mitsuba is imported here, on first use, and only here: nothing else loads it for a
teacher.  Mitsuba computes in float32; f comes back as float64.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neural_brdf.errors import InputError
from neural_brdf.limits import bounded
from neural_brdf.measured.base import eval_pairs
from neural_brdf.physics import quadrature

VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")  # RGB JIT variants (target.variant's values)
DEFAULT_VARIANT = "llvm_ad_rgb"
CHUNK = 1 << 16  # pairs per Mitsuba call
# The probes at load: pairs, texture coordinates, and the tolerances of "varies"
PROBE_PAIRS = 256
PROBE_UV = 64
SPATIAL_TOL = 1e-6  # relative RMS change over uv; a uniform BSDF gives exactly 0
ANISO_TOL = 1e-3  # relative RMS change under a turn about the normal (float32 noise ~1e-6)
# f cos above this at the probe pairs (half from the teacher's sampler) is a delta lobe in
# all but name: a rough plugin at roughness ~0 (Mitsuba clamps alpha near 1e-4: 7e7 to
# 9e7 for roughplastic and roughconductor; alpha 1e-3 reaches 1e6, 0.01 about 1e4)
MAX_F_COS = 1e7
# ... and so at any uv (check_rough): PROBE_UV random uv, this many pairs at each, wo from
# the sampler at that uv (pairs drawn at uv 0.5 miss a lobe that is sharp elsewhere)
PEAK_PAIRS = 32
# the microfacet roughness of Mitsuba's rough plugins (principled's: roughness): a value,
# or a bitmap bound to one with a texel, at 0 or below is a delta lobe there (a lone texel
# is ~0 only near its centre: no probe sees it; principled at roughness 0 reaches only
# f cos ~1e4 at the probes, below MAX_F_COS, and trained to a 99.9 % error)
ALPHA_PARAMS = ("alpha", "alpha_u", "alpha_v", "roughness")
# The energy bound's table (module doc)
THETA_NODES = 46  # polar angles, 2 degrees apart, the last (90) moved to LAST_THETA_DEG
LAST_THETA_DEG = 89.9
AZIMUTHS = 8  # per polar angle, for an anisotropic teacher
ALBEDO_SAMPLES = 8192  # quadrature points per direction (half that when anisotropic)
SIGMAS = 3.0  # standard errors added to the tabulated albedo
EXCESS_TOL = 1e-3  # an albedo up to 1 + this is not an excess (validation.albedo_tol)
CHANNELS = ("R", "G", "B")

# Mitsuba's BSDFFlags bits (mi.BSDFFlags; fixed by its C++ enum)
_TRANSMISSION = 1 | 4 | 16 | 64 | 256  # Null, Diffuse/Glossy/Delta(1D) transmission
_DELTA_REFLECTION = 32 | 128  # DeltaReflection, Delta1DReflection
_SMOOTH_REFLECTION = 2 | 8  # DiffuseReflection, GlossyReflection


def _mitsuba(variant: str, key: str) -> Any:
    """The mitsuba module with ``variant`` set (set here if no other variant is set yet;
    else each call switches to it for its duration: see :meth:`MitsubaTarget._scope`)."""
    if variant not in VARIANTS:
        raise InputError(
            f"target.variant: {variant!r}: a Mitsuba teacher needs an RGB JIT variant "
            f"({' or '.join(VARIANTS)})"
        )
    try:
        import mitsuba as mi
    except ImportError:
        raise InputError(
            f"{key}: needs Mitsuba 3 (pip install -e '.[mitsuba]' and libllvm19)"
        ) from None
    if variant not in mi.variants():
        raise InputError(f"target.variant: {variant}: not a variant of this Mitsuba build")
    if mi.variant() is None:
        try:
            mi.set_variant(variant)
        except Exception as e:  # a missing LLVM or CUDA: Mitsuba raises several types
            raise InputError(f"target.variant: {variant}: not usable here ({_first(e)})") from None
    return mi


def _first(e: BaseException) -> str:
    """Mitsuba's message on one line, without its ``[parser.cpp:123]`` prefix, and an
    object's dump in it (``BitmapTexture[ name = ..., transform = ... ]``, 12 lines)
    shortened to ``[...]``, so that the sentence after it is kept."""
    text = " ".join(str(e).split())
    if text.startswith("[") and "] " in text:
        text = text.split("] ", 1)[1]
    return bounded(_without_dumps(text), 240)


def _without_dumps(text: str, longest: int = 40) -> str:
    """``text`` with each outermost ``[...]`` block longer than ``longest`` characters
    replaced by ``[...]`` (unbalanced brackets: ``text`` as it is)."""
    out, depth, start = [], 0, 0
    for i, c in enumerate(text):
        if c == "[":
            if depth == 0:
                out.append(text[start:i])
                start = i
            depth += 1
        elif c == "]" and depth:
            depth -= 1
            if depth == 0:
                block = text[start : i + 1]
                out.append(block if len(block) <= longest else "[...]")
                start = i + 1
    if depth:
        return text
    out.append(text[start:])
    return "".join(out)


@contextlib.contextmanager
def variant_scope(mi: Any, variant: str) -> Iterator[None]:
    """Mitsuba's variant is ``variant`` inside, the one before after (a no-op when it
    is already: a switch costs ~0.15 s, so a process that uses another variant pays it
    per call).  The teachers' (:class:`MitsubaTarget`, the textured one's) evaluations
    run inside it."""
    before = mi.variant()
    if before == variant:
        yield
        return
    mi.set_variant(variant)
    try:
        yield
    finally:
        if before is not None:
            mi.set_variant(before)


def _children(mi: Any, obj: Any) -> list[tuple[str, Any]]:
    """(name, object) of the objects ``obj`` holds (Mitsuba's traversal)."""

    class Collect(mi.TraversalCallback):
        def __init__(self) -> None:
            super().__init__()
            self.found: list[tuple[str, Any]] = []

        def put(self, name: str, value: Any, flags: Any, *rest: Any) -> None:
            if isinstance(value, mi.Object):
                self.found.append((name, value))

    cb = Collect()
    obj.traverse(cb)
    return cb.found


def check_file(path: Path, where: str) -> None:
    """InputError naming ``where`` unless ``path`` is a file: "no such file", or that it
    is a folder (a teacher is one XML file)."""
    if path.is_dir():
        raise InputError(f"{where}: is a folder, not a Mitsuba XML file")
    if not path.is_file():
        raise InputError(f"{where}: no such file")


def load(mi: Any, path: Path, where: str) -> Any:
    """``mi.load_file(path)``; InputError naming ``where`` when Mitsuba cannot load it,
    and naming the image when that is why (a bitmap file that is not an image: Mitsuba
    says only "read 6 out of 8 bytes" inside its plugin error)."""
    try:
        return mi.load_file(str(path))
    except Exception as e:  # Mitsuba's parser and plugins raise RuntimeError & co.
        bad = _unreadable_image(mi, path)
        if bad is not None:
            name, why = bad
            raise InputError(
                f"{where}: the texture file {name!r} cannot be read as an image ({why})"
            ) from None
        raise InputError(f"{where}: Mitsuba cannot load it ({_first(e)})") from None


# the most nested <include>s Mitsuba 3.9 loads (a chain of 15 exceeds its "maximum
# include recursion depth of 15": checked with mi.load_file)
INCLUDE_DEPTH = 14


def include_candidates(filename: str, folders: list[Path]) -> list[Path]:
    """Where an ``<include filename>`` is looked for, in order, as Mitsuba's loader
    does: an absolute name itself, then ``folders`` (the including file's folder first,
    then those of the files that included it), then the current folder; the first that
    is a file is the one included."""
    first = [Path(filename)] if Path(filename).is_absolute() else []
    return first + [folder / filename for folder in folders] + [Path(filename)]


def resolver_for(mi: Any, path: Path) -> Any:
    """Mitsuba's file resolver as its loader uses it for the XML at ``path`` (that
    folder first), as a copy: the global one is untouched."""
    resolver = mi.FileResolver(mi.file_resolver())
    resolver.prepend(str(path.resolve().parent))
    return resolver


def _unreadable_image(mi: Any, path: Path) -> tuple[str, str] | None:
    """(filename as written, Mitsuba's reason) of the first bitmap texture of the XML
    at ``path`` that exists but ``mi.Bitmap`` cannot read; None if there is none (only
    called when loading failed, so the images are read twice only then)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return None
    resolver = resolver_for(mi, path)
    for tex in root.iter("texture"):
        if tex.get("type") != "bitmap":
            continue
        for el in tex.findall("string"):
            value = el.get("value", "")
            if el.get("name") != "filename" or "$" in value:
                continue
            found = Path(str(resolver.resolve(value)))
            if not found.is_file():
                continue
            try:
                mi.Bitmap(str(found))
            except Exception as e:
                return value, _first(e)
    return None


def one_bsdf(mi: Any, obj: Any, where: str) -> Any:
    """The BSDF a loaded Mitsuba file holds: ``obj`` itself, or a scene's one top-level
    ``<bsdf>``; InputError naming ``where`` otherwise."""
    if isinstance(obj, mi.Scene):
        found = [o for _, o in _children(mi, obj) if isinstance(o, mi.BSDF)]
        if len(found) != 1:
            raise InputError(
                f"{where}: a scene with {len(found)} top-level <bsdf> elements; "
                "give a file holding one"
            )
        obj = found[0]
    if not isinstance(obj, mi.BSDF):
        raise InputError(
            f"{where}: holds a {obj.class_name()}, not a <bsdf> (give a file holding one)"
        )
    return obj


def _tensor(mi: Any, x: np.ndarray) -> Any:
    """(N, 3) float64 numpy -> mi.Vector3f."""
    return mi.Vector3f(np.ascontiguousarray(x.T, dtype=np.float32))


NORMAL_MAPS = {"NormalMap": "normalmap", "BumpMap": "bumpmap"}  # Mitsuba's classes


def nested_normal_map(mi: Any, obj: Any, depth: int = 0) -> str | None:
    """The plugin name of a normal or bump map among the BSDFs ``obj`` holds, at any
    depth (a ``blendbsdf`` of a ``normalmap``), or None."""
    for _, child in _children(mi, obj):
        if not isinstance(child, mi.BSDF):
            continue
        if child.class_name() in NORMAL_MAPS:
            return NORMAL_MAPS[child.class_name()]
        if depth < 16 and (found := nested_normal_map(mi, child, depth + 1)) is not None:
            return found
    return None


def _np(x: Any) -> np.ndarray:
    """A Mitsuba array of (3, N) or (N,) -> (N, 3) / (N,) float64 numpy."""
    return np.array(x, dtype=np.float64).T


def check_reflective(bsdf: Any, plugin: str, where: str) -> None:
    """InputError naming ``where`` unless ``bsdf`` (its name ``plugin``) is a BRDF of
    finite values: no transmission, no delta lobe, some rough reflection."""
    flags = int(bsdf.flags())
    if flags & _TRANSMISSION:
        raise InputError(
            f"{where}: {plugin} transmits light (or passes it through): a "
            "neural BRDF holds reflection only"
        )
    if flags & _DELTA_REFLECTION:
        what = "is delta-only" if not flags & _SMOOTH_REFLECTION else "has a delta lobe"
        raise InputError(
            f"{where}: {plugin} {what} (a perfectly smooth reflection, which a "
            "BRDF of finite values cannot hold): use a rough variant (e.g. "
            "roughconductor, roughplastic)"
        )
    if not flags & _SMOOTH_REFLECTION:
        raise InputError(f"{where}: {plugin} reflects nothing")


def check_rough(mi: Any, bsdf: Any, plugin: str, where: str) -> None:
    """InputError naming ``where`` when ``bsdf`` is a delta lobe in all but name somewhere
    on the surface (docs/mitsuba.md: refused, "a rough one at roughness 0 or below"): a
    roughness (:data:`ALPHA_PARAMS`) given as a number at 0 or below, a bitmap bound to
    one with a texel at 0 or below (each named), or
    f cos above :data:`MAX_F_COS` at one of :data:`PROBE_UV` random uv, wo drawn from the
    teacher's sampler at that uv.  Else such a teacher trained to a 100 % error and passed
    its physics (the probes at uv 0.5 saw only the rough part)."""
    import drjit as dr

    params = mi.traverse(bsdf)
    for k in params.keys():
        parts = k.split(".")
        value = params[k]
        name = parts[-2] if parts[-1] == "value" and len(parts) > 1 else parts[-1]
        if name in ALPHA_PARAMS and parts[-1] != "data":
            # a roughness given as a number (roughplastic's alpha is the parameter itself)
            number = np.asarray(value.numpy() if hasattr(value, "numpy") else value, float)
            if number.size == 1 and float(number.reshape(-1)[0]) <= 0:
                raise InputError(
                    f"{where}: {k.removesuffix('.value')} = {float(number.reshape(-1)[0]):g}: "
                    "a roughness of 0, a nearly delta lobe, which a BRDF of finite values "
                    "cannot hold: give a larger roughness"
                )
            continue
        if parts[-1] != "data" or len(parts) < 2 or parts[-2] not in ALPHA_PARAMS:
            continue
        if not dr.is_tensor_v(value):  # any type: an 8-bit PNG's is TensorXu8
            continue
        arr = np.asarray(value.numpy(), dtype=np.float64)
        texels = arr.reshape(-1, arr.shape[-1]) if arr.ndim == 3 else arr.reshape(-1, 1)
        if texels.shape[1] == 3:  # an RGB map read as a float: its luminance (bitmap.cpp)
            texels = texels @ np.array([[0.2126], [0.7152], [0.0722]])
        low = texels[:, 0] <= 0  # a NaN is not: refused as non-finite
        if low.any():
            raise InputError(
                f"{where}: the texture {k.removesuffix('.data')} holds {int(low.sum())} of "
                f"{len(texels)} texels at 0 or below (lowest {texels[low].min():.3g}): a "
                "roughness of 0 there, a nearly delta lobe (Mitsuba clamps it to a tiny width), "
                "which a BRDF of finite values cannot hold: give a larger roughness"
            )
    rng = np.random.default_rng(9)
    uv = np.repeat(rng.random((PROBE_UV, 2)), PEAK_PAIRS, 0)
    wi = _hemisphere(rng.random((len(uv), 2)), z_min=math.sin(math.radians(3.0)))
    try:
        s1 = rng.random(len(uv))
        bs, _ = sample_rows(mi, bsdf, wi, uv, s1, rng.random((2, len(uv))).T)
        si = interaction(mi, wi, uv)
        wo, pdf = _np(bs.wo), _np(bs.pdf)
        ok = (pdf > 0) & (wo[:, 2] > 1e-3) & np.all(np.isfinite(wo), -1)
        wo[~ok] = (0.0, 0.0, 1.0)
        value = np.where(ok[:, None], _np(bsdf.eval(mi.BSDFContext(), si, _tensor(mi, wo))), 0.0)
    except Exception as e:  # a plugin that needs what a bare interaction lacks
        raise InputError(f"{where}: Mitsuba cannot evaluate it ({_first(e)})") from None
    if not np.all(np.isfinite(value)) or value.min() < 0:
        raise InputError(f"{where}: {plugin} gives negative or non-finite values")
    if not value.max() > 0:  # else trained to a black file with "physics PASSED"
        raise InputError(
            f"{where}: {plugin} reflects no light at {PROBE_UV} random uv (f = 0 in every "
            "channel): a black material, or a texture that needs a mesh (such as "
            "mesh_attribute), which a teacher evaluated on its own cannot read"
        )
    top = value.max(-1)
    k = int(np.argmax(top))
    if top[k] > MAX_F_COS:
        raise InputError(
            f"{where}: {plugin} reaches f cos = {top[k]:.3g} at uv ({uv[k, 0]:.3f}, "
            f"{uv[k, 1]:.3f}) (a nearly delta lobe: a roughness of 0, or negative, somewhere "
            "on the surface), which a BRDF of finite values cannot hold: give a larger "
            "roughness"
        )


def sample_rows(
    mi: Any, bsdf: Any, wi: np.ndarray, uv: np.ndarray | None, s1: np.ndarray, u: np.ndarray
) -> tuple[Any, Any]:
    """Mitsuba's (BSDFSample3f, weight) of ``bsdf`` for unit ``wi`` rows (K, 3) at ``uv``
    (K, 2; None: 0.5), the lobe choice ``s1`` (K,) and the square's ``u`` (K, 2)."""
    return bsdf.sample(
        mi.BSDFContext(),
        interaction(mi, wi, uv),
        mi.Float(np.asarray(s1).astype(np.float32)),
        mi.Point2f(np.ascontiguousarray(np.asarray(u).T, dtype=np.float32)),
    )


def interaction(mi: Any, wi: np.ndarray, uv: np.ndarray | None = None) -> Any:
    """A surface interaction per row of unit ``wi`` (K, 3): the local frame itself as the
    shading frame (z the normal, tangent x = dp_du), si.uv = ``uv`` (K, 2; None: 0.5)
    and si.p = (u, v, 0), for a BSDF's eval, sample and pdf."""
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = _tensor(mi, wi)
    x, y, z = mi.Vector3f(1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0), mi.Vector3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(x, y, z)
    si.n = z
    si.dp_du, si.dp_dv = x, y
    if uv is None:
        uv = np.full((len(wi), 2), 0.5)
    si.uv = mi.Point2f(np.ascontiguousarray(uv.T, dtype=np.float32))
    si.p = mi.Point3f(np.ascontiguousarray(np.c_[uv, np.zeros(len(uv))].T, dtype=np.float32))
    return si


class VariesOverSurface(InputError):
    """The teacher varies over the surface: :class:`MitsubaTarget` (homogeneous) refuses
    it, and ``train.data.build_target`` builds a
    :class:`neural_brdf.measured.textured.TexturedMitsubaTarget` instead."""


class MitsubaTarget:
    """One BSDF of a Mitsuba XML file as a homogeneous training target (module doc): a
    :class:`neural_brdf.target.Sampled` of kind ``"mitsuba"``."""

    kind = "mitsuba"

    def __init__(
        self, path: str | Path, *, variant: str | None = None, key: str = "target.mitsuba"
    ):
        self.path = Path(path)
        self.source = str(path)
        self.variant = variant or DEFAULT_VARIANT
        where = f"{key}: {self.source}"
        check_file(self.path, where)
        mi = self._mi = _mitsuba(self.variant, key)
        with self._scope():
            obj = load(mi, self.path, where)
            self.bsdf, self.plugin = self._the_bsdf(obj, where)
            check_reflective(self.bsdf, self.plugin, where)
            self.anisotropic = False  # probed below (the sampler needs none of it)
            self.scale_table: np.ndarray | None = None
            self.excess: dict[str, Any] | None = None
            self._probe(where)
            self.albedo_table = self._bound()

    # ------------------------------------------------------------------ loading
    def _scope(self) -> contextlib.AbstractContextManager[None]:
        """Mitsuba's variant is the teacher's inside (:func:`variant_scope`)."""
        return variant_scope(self._mi, self.variant)

    def _the_bsdf(self, obj: Any, where: str) -> tuple[Any, str]:
        mi = self._mi
        obj = one_bsdf(mi, obj, where)
        names = []
        while obj.class_name() == "TwoSidedBRDF":  # unwrapped to its front side
            names.append("twosided")
            front = dict(_children(mi, obj)).get("brdf_0")
            if front is None:
                raise InputError(f"{where}: a twosided BSDF without a nested BSDF")
            obj = front
        if obj.class_name() in NORMAL_MAPS or nested_normal_map(mi, obj) is not None:
            # its frame turns with uv, even under a uniform map: the textured teacher takes
            # it apart (or refuses one inside another BSDF), never evaluated as it is here,
            # where the map's rotated frame makes f non-reciprocal
            raise VariesOverSurface(
                f"{where}: {obj.class_name()} holds a normal or bump map: a spatially "
                "varying teacher (measured.textured)"
            )
        names.append(obj.class_name())
        return obj, " > ".join(names)

    # ------------------------------------------------------------------ Mitsuba calls
    def _eval_cos(self, wi: np.ndarray, wo: np.ndarray, uv: np.ndarray | None = None) -> np.ndarray:
        """Mitsuba's eval (f cos theta_o), (K, 3) float64, for unit (K, 3) pairs."""
        mi = self._mi
        with self._scope():
            out = self.bsdf.eval(mi.BSDFContext(), interaction(mi, wi, uv), _tensor(mi, wo))
            return _np(out)

    def _raw(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """The teacher's f (unbounded) for unit pairs strictly above the horizon."""
        return self._eval_cos(wi, wo) / wo[:, 2:3]

    def teacher(self, wi, wo) -> np.ndarray:
        """Mitsuba's f = eval / cos(theta_o), before the energy bound, with the edges of
        :func:`~neural_brdf.measured.base.eval_pairs` (0 below the horizon)."""
        return eval_pairs(wi, wo, self._raw, chunk=CHUNK)

    def _sample(self, wi: np.ndarray, u: np.ndarray) -> np.ndarray:
        """wo (K, 3) from Mitsuba's sampler, (0, 0, -1) where it fails.  Its lobe choice
        (``sample1``) is a uniform number drawn from a hash of ``u``: independent of u,
        the same for the same u (a resumed run draws the same pairs)."""
        mi = self._mi
        seed = int.from_bytes(hashlib.blake2b(u.tobytes(), digest_size=8).digest(), "little")
        s1 = np.random.default_rng(seed).random(len(u))
        with self._scope():
            bs, _ = self.bsdf.sample(
                mi.BSDFContext(),
                interaction(mi, wi),
                mi.Float(s1.astype(np.float32)),
                mi.Point2f(np.ascontiguousarray(u.T, dtype=np.float32)),
            )
            wo, pdf = _np(bs.wo), _np(bs.pdf)
        bad = ~((pdf > 0) & np.isfinite(pdf) & (wo[:, 2] > 0) & np.all(np.isfinite(wo), -1))
        wo[bad] = (0.0, 0.0, -1.0)
        return wo

    def _pdf(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        mi = self._mi
        with self._scope():
            return _np(self.bsdf.pdf(mi.BSDFContext(), interaction(mi, wi), _tensor(mi, wo)))

    # ------------------------------------------------------------------ probes
    def _probe_pairs(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Pairs for the probes: wi uniform (above 3 degrees), wo half uniform, half from
        the teacher's sampler (so that a narrow lobe is seen)."""
        rng = np.random.default_rng(seed)
        n = PROBE_PAIRS
        wi = _hemisphere(rng.random((n, 2)), z_min=math.sin(math.radians(3.0)))
        wo = _hemisphere(rng.random((n, 2)), z_min=math.sin(math.radians(3.0)))
        half = n // 2
        drawn = self._sample(wi[:half], rng.random((half, 2)))
        ok = drawn[:, 2] > 1e-3
        wo[:half][ok] = drawn[ok]
        return wi, wo

    def _probe(self, where: str) -> None:
        varying_bitmap = self._varying_bitmap(where)  # first: names a texture of NaN or inf
        try:  # the sampler first (half the pairs), then eval
            wi, wo = self._probe_pairs(7)
            base = self._eval_cos(wi, wo)
        except Exception as e:  # a plugin that needs what a bare interaction lacks
            raise InputError(f"{where}: Mitsuba cannot evaluate it ({_first(e)})") from None
        if not np.all(np.isfinite(base)) or base.min() < 0:
            raise InputError(f"{where}: {self.plugin} gives negative or non-finite values")
        if base.max() > MAX_F_COS:  # else trained as is: a 100 % error and no word why
            raise InputError(
                f"{where}: {self.plugin} reaches f cos = {base.max():.3g} (a nearly delta "
                "lobe: a roughness of 0, or negative?), which a BRDF of finite values cannot "
                "hold: give a larger roughness"
            )
        scale = max(float(np.sqrt(np.mean(base**2))), 1e-30)
        # spatial variation: the same pairs at PROBE_UV random (uv, position)s
        rng = np.random.default_rng(8)
        uv = rng.random((PROBE_UV, 2))
        try:
            at = self._eval_cos(
                np.tile(wi, (PROBE_UV, 1)), np.tile(wo, (PROBE_UV, 1)), np.repeat(uv, len(wi), 0)
            )
        except Exception as e:
            raise InputError(f"{where}: Mitsuba cannot evaluate it ({_first(e)})") from None
        if not np.all(np.isfinite(at)) or at.min() < 0:  # else a NaN reads as "no change"
            raise InputError(f"{where}: {self.plugin} gives negative or non-finite values")
        check_rough(self._mi, self.bsdf, self.plugin, where)  # sharp away from uv 0.5
        change = float(np.sqrt(np.mean((at - np.tile(base, (PROBE_UV, 1))) ** 2))) / scale
        if change > SPATIAL_TOL or varying_bitmap:
            raise VariesOverSurface(
                f"{where}: {self.plugin} varies over the surface (a texture, normal or "
                "bump map): a spatially varying teacher (measured.textured)"
            )
        # anisotropy: the same pairs turned about the normal by a few azimuths
        turned = []
        for phi in (0.7, 1.9, 2.6):
            c, s = math.cos(phi), math.sin(phi)
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            turned.append(self._eval_cos(wi @ rot.T, wo @ rot.T))
        diff = max(float(np.sqrt(np.mean((t - base) ** 2))) for t in turned)
        self.anisotropic = diff / scale > ANISO_TOL

    def _varying_bitmap(self, where: str) -> bool:
        """A bitmap texture (a tensor parameter) with more than one distinct texel;
        InputError naming ``where`` and the texture if one holds a NaN or an inf (a
        texel the probes may miss, and a NaN would read as no variation)."""
        mi = self._mi
        params = mi.traverse(self.bsdf)
        for k in params.keys():
            value = params[k]
            if isinstance(value, mi.TensorXf) and k.endswith(".data"):
                arr = np.asarray(value.numpy(), dtype=np.float64)
                if not np.all(np.isfinite(arr)):
                    bad = int(np.count_nonzero(~np.isfinite(arr)))
                    raise InputError(
                        f"{where}: the texture {k.removesuffix('.data')} holds {bad} "
                        "non-finite values (NaN or inf)"
                    )
                flat = arr.reshape(-1, arr.shape[-1]) if arr.ndim > 1 else arr.reshape(-1, 1)
                if len(flat) > 1 and np.ptp(flat, axis=0).max() > 0:
                    return True
        return False

    # ------------------------------------------------------------------ the bound
    def _bound(self) -> dict[str, Any]:
        """Tabulate A+ and, if the teacher exceeds 1, set the divisor's table (module
        doc).  Returns the table as measured (theta, A, stderr), for the report."""
        step = 90.0 / (THETA_NODES - 1)
        theta = np.radians(np.r_[np.arange(THETA_NODES - 1) * step, LAST_THETA_DEG])
        phis = np.linspace(0.0, math.pi, AZIMUTHS, endpoint=False) if self.anisotropic else [0.0]
        t, p = np.meshgrid(theta, phis, indexing="ij")
        st = np.sin(t)
        dirs = torch.from_numpy(
            np.stack([st * np.cos(p), st * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
        )
        n = ALBEDO_SAMPLES // 2 if self.anisotropic else ALBEDO_SAMPLES  # 8 x the directions
        rho, err = quadrature.albedo(
            quadrature.from_numpy(self.teacher), dirs, n, seed=11, target=self
        )
        a = rho.numpy().reshape(len(theta), len(phis), 3)
        e = err.numpy().reshape(len(theta), len(phis), 3)
        upper = (a + SIGMAS * e).max(1)  # (T, 3): over the azimuths
        worst = np.unravel_index(np.argmax(a), a.shape)
        above = np.flatnonzero(a.max((1, 2)) > 1.0 + EXCESS_TOL)
        table = {
            "theta_deg": np.degrees(theta).tolist(),
            "albedo": a.max(1).tolist(),
            "max_albedo": float(a.max()),
        }
        if len(above):
            self.scale_table = np.maximum(upper, 1.0)
            self._theta = theta
            self.excess = {
                "max_albedo": float(a[worst]),
                "at_theta_deg": round(float(np.degrees(theta[worst[0]])), 2),
                "channel": CHANNELS[worst[2]],
                "above_1_theta_deg": [
                    round(float(np.degrees(theta[above[0]])), 2),
                    round(float(np.degrees(theta[above[-1]])), 2),
                ],
            }
        return table

    def bound(self, wi, wo) -> np.ndarray:
        """The energy bound's divisor max(1, A+(wi), A+(wo)) (..., 3), per channel:
        symmetric in (wi, wo) bit for bit; 1 everywhere for a teacher within 1."""
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        shape = np.broadcast_shapes(wi.shape, wo.shape)[:-1] + (3,)
        if self.scale_table is None:
            return np.ones(shape)
        return np.maximum(self._envelope(wi), self._envelope(wo)).reshape(shape)

    def _envelope(self, w: np.ndarray) -> np.ndarray:
        """A+ (>= 1) at the polar angle of each direction: the larger neighbour node."""
        assert self.scale_table is not None
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = w[..., 2] / np.linalg.norm(w, axis=-1)
        theta = np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0))
        k = np.clip(np.searchsorted(self._theta, theta, side="right") - 1, 0, len(self._theta) - 2)
        return np.maximum(self.scale_table[k], self.scale_table[k + 1])

    # ------------------------------------------------------------------ the Target API
    def _bounded(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        f = self._raw(wi, wo)
        if self.scale_table is None:
            return f
        return f / np.maximum(self._envelope(wi), self._envelope(wo))

    def eval(self, wi, wo) -> np.ndarray:
        """f (..., 3) float64, 1/sr, no cosine: the teacher, energy-bounded if it
        exceeds 1 (module doc); 0 below the horizon."""
        return eval_pairs(wi, wo, self._bounded, chunk=CHUNK)

    def f(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        out = self.eval(wi.detach().cpu().double().numpy(), wo.detach().cpu().double().numpy())
        return torch.from_numpy(out).to(device=wi.device, dtype=wi.dtype)

    def sample_dir_t(self, wi: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """wo for ``wi`` (..., 3) from ``u`` (..., 2) by Mitsuba's sampler; a failed
        sample, or wi at or below the horizon, gives (0, 0, -1) (below the horizon)."""
        batch = torch.broadcast_shapes(wi.shape[:-1], u.shape[:-1])
        shape = batch + (3,)
        a = wi.detach().cpu().double().expand(shape).reshape(-1, 3).numpy()
        uu = u.detach().cpu().double().expand(batch + (2,)).reshape(-1, 2).numpy()
        out = np.tile([0.0, 0.0, -1.0], (len(a), 1))
        ok = np.flatnonzero(np.all(np.isfinite(a), -1) & (a[:, 2] > 0))
        for s in range(0, len(ok), CHUNK):
            r = ok[s : s + CHUNK]
            w = a[r] / np.linalg.norm(a[r], axis=-1, keepdims=True)
            out[r] = self._sample(w, np.ascontiguousarray(uu[r]))
        return torch.from_numpy(out.reshape(shape)).to(device=wi.device, dtype=wi.dtype)

    def pdf_t(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """The density of :meth:`sample_dir_t`'s wo per solid angle (Mitsuba's pdf);
        0 below the horizon."""
        wi_b, wo_b = torch.broadcast_tensors(wi, wo)
        a = wi_b.detach().cpu().double().reshape(-1, 3).numpy()
        b = wo_b.detach().cpu().double().reshape(-1, 3).numpy()

        def lookup(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            return np.repeat(self._pdf(x, y)[:, None], 3, 1)

        pdf = eval_pairs(a, b, lookup, chunk=CHUNK)[:, 0]
        return torch.from_numpy(pdf.reshape(wi_b.shape[:-1])).to(device=wi.device, dtype=wi.dtype)

    def describe(self) -> str:
        text = f"Mitsuba {self.plugin} ({self.source}, {self.variant})"
        if self.anisotropic:
            text += ", anisotropic"
        x = self.excess
        if x is not None:
            lo, hi = x["above_1_theta_deg"]
            text += (
                f"; its albedo exceeds 1 (max {x['max_albedo']:.4f} in {x['channel']} at "
                f"theta_i {x['at_theta_deg']:g} deg; above 1 from {lo:g} to {hi:g} deg): "
                "learned energy-bounded, f / max(1, A(wi), A(wo))"
            )
        return text


def _hemisphere(u: np.ndarray, *, z_min: float = 0.0) -> np.ndarray:
    """Uniform directions on the hemisphere z >= z_min from u (N, 2) in [0, 1)^2."""
    z = z_min + (1.0 - z_min) * u[:, 0]
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = 2.0 * math.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
