"""A textured teacher that Mitsuba 3 evaluates: f depends on the surface position (issue 30,
the first building block of spatially varying models).

    from neural_brdf.measured.textured import TexturedMitsubaTarget
    teacher = TexturedMitsubaTarget("teacher.xml")   # InputError naming the file if unusable
    teacher.eval(wi, wo, uv)        # f (N, 3), 1/sr, no cosine, at texture coordinates uv
    teacher.sample(wi, uv, u), teacher.pdf(wi, wo, uv)    # Mitsuba's own sampler
    teacher.normal_field(uv)        # the normal map's shading normal (N, 3), tangent frame

The file holds one ``<bsdf>`` (as for :class:`~neural_brdf.measured.mitsuba.MitsubaTarget`)
whose parameters may be textures (``bitmap``, ``checkerboard``, ...); relative texture
file names are resolved against the XML's folder by Mitsuba's file resolver, and a
missing one is refused naming it.  Wrappers are unwrapped to the BSDF they hold:

* ``twosided``: its front BSDF (a BRDF has one side);
* ``normalmap`` and ``bumpmap``: the nested BSDF.  The target's f is the NESTED BSDF in
  the unperturbed shading frame: the map is not baked into f, since Mitsuba's wrappers
  are not reciprocal (they flip the normal by wi, and multiply by a shadowing term of wo
  alone).  The map is exposed as :meth:`TexturedMitsubaTarget.normal_field`, the
  perturbed normal at uv in the tangent frame, as Mitsuba's plugins compute it (Mitsuba
  3.9.1, src/bsdfs/normalmap.cpp and bumpmap.cpp, ``frame()``):

  - normalmap: n = normalize(2 t(uv) - 1), t the texture's RGB (bilinear lookup);
  - bumpmap: n = normalize(-s dh/du, -s dh/dv, 1), h the texture, s its ``scale``: the
    normal of the displaced surface p + h n with dp_du = x, dp_dv = y (a flat unit
    square whose position is uv, as the interaction here is built);

  the perturbed frame is then s = normalize(x - n n_x), t = n x s (Gram-Schmidt of the
  tangent x).  Mitsuba also flips (n_x, n_y) where wi lies below the perturbed plane
  (``flip_invalid_normals``, Schuessler et al. 2017) and multiplies by the shadowing
  term 2 / (1 + sqrt(1 + a2 tan^2 theta_o)), a2 = min(1, tan^2 theta_n / 8)
  (``use_shadowing_function``, Estevez et al., "A Microfacet-Based Shadowing Function
  to Solve the Bump Terminator Problem", Ray Tracing Gems 2019); :attr:`normal_map`
  records which, read from the XML.  A renderer that wants Mitsuba's look applies them.

f is Mitsuba's ``BSDF.eval`` / cos(theta_o) at a surface interaction with ``si.uv`` = uv,
the identity shading frame (z the normal, x the tangent dp_du) and ``si.p`` = (u, v, 0),
in an RGB JIT variant.  There is no energy bound here (a later model bounds it): the
albedo at given uv is estimated by :meth:`TexturedMitsubaTarget.max_albedo`.

Refused, one line naming the file: a file Mitsuba cannot load, a missing texture file
(named), a non-RGB variant, a BSDF that transmits or has a delta lobe, or a roughness
of 0 somewhere (``mitsuba.check_rough``: a bitmap alpha's texel, or f cos at random uv).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from neural_brdf.errors import InputError
from neural_brdf.measured.base import _unit
from neural_brdf.measured.mitsuba import (
    CHUNK,
    _children,
    _first,
    _hemisphere,
    _mitsuba,
    _np,
    _tensor,
    check_file,
    check_reflective,
    check_rough,
    interaction,
    load,
    nested_normal_map,
    one_bsdf,
    resolver_for,
    sample_rows,
    variant_scope,
)

DEFAULT_VARIANT = "llvm_ad_rgb"
WRAPPERS = {"TwoSidedBRDF": "twosided", "NormalMap": "normalmap", "BumpMap": "bumpmap"}
# the anisotropy probe: pairs x uv, turned about the normal
PROBE_PAIRS = 64
PROBE_UV = 16
ANISO_TOL = 1e-3  # relative RMS change under a turn (float32 noise ~1e-6)
# max_albedo's defaults
ALBEDO_THETA_DEG = (0.0, 30.0, 60.0, 80.0)
ALBEDO_SAMPLES = 4096
# normal_field_warning: the file's normal field is worth a line when its mean error (as
# validate measures it) exceeds both.  Sampled as normal_texels does, bump maps of 16²
# read 0.02 to 0.8 deg (0.7 to 1.6 % of their mean tilt of 2.4 to 62 deg) and a bitmap
# normal map 1e-5 deg; sampled at the bitmap's texel centres they read 0.96 to 50 deg
# (39 to 89 %).  Below half a degree the file's relief is the teacher's to the eye.
NORMAL_WARN_DEG = 0.5
NORMAL_WARN_SHARE = 0.1  # of the teacher's mean tilt
NORMAL_WARN_UV = 4096  # random uv for that mean tilt


def _as_rows(x: Any, width: int) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.shape[-1:] != (width,):
        raise ValueError(f"expected a (..., {width}) array, got {a.shape}")
    return a


def bump_factor(texels: int, resolution: int) -> int:
    """How many samples a bump bitmap's texel gets along an axis of ``texels``
    (:meth:`TexturedMitsubaTarget.normal_texels`): even, so that no sample falls on a texel
    centre (odd factors put one there), at least 2, and enough for ``resolution`` in all."""
    return max(2, 2 * math.ceil(resolution / (2 * texels)))


# the normal field's texels per axis at most, where a bitmap's to_uv repeats it (a
# 1024² map tiled 4 times: 4096², 200 MB of float32 normals in the file)
MAX_NORMAL_TEXELS = 4096


def texels_over_surface(ru: int, rv: int, to_uv: np.ndarray) -> tuple[int, int]:
    """(Ru, Rv) texels over the surface's uv square for a bitmap of ``ru`` x ``rv`` texels
    that Mitsuba looks up at to_uv (a 3 x 3 matrix) times (u, v, 1): the texel edges that
    a line along u (along v) crosses per unit, |M00| ru + |M10| rv (|M01| ru + |M11| rv).
    A whole-number scale, quarter turn or flip, shifted by whole texels, keeps every
    sample on a texel centre, so the bilinear field is the texture's own, as without
    to_uv; any other transform is sampled twice as finely (its texel centres fall between
    the samples), and at most :data:`MAX_NORMAL_TEXELS` per axis.  (The file repeats its
    uv square: a to_uv whose pattern does not, a turn by 30 degrees, is matched inside it
    only.)"""
    m = to_uv[:2, :2]
    m = np.where(np.abs(m - np.round(m)) < 1e-6, np.round(m), m)  # a rotation's 6e-17
    if np.array_equal(m, np.eye(2)) and not to_uv[:2, 2].any():
        return ru, rv
    per_u = abs(m[0, 0]) * ru + abs(m[1, 0]) * rv
    per_v = abs(m[0, 1]) * ru + abs(m[1, 1]) * rv
    shift = to_uv[:2, 2] * np.array([ru, rv])  # in texels
    exact = (  # whole numbers, one per row and column (a scale, a quarter turn, a flip)
        np.array_equal(m, np.round(m))
        and np.array_equal(np.count_nonzero(m, axis=0), [1, 1])
        and np.array_equal(np.count_nonzero(m, axis=1), [1, 1])
        and np.allclose(shift, np.round(shift), atol=1e-6)
    )
    factor = 1 if exact else 2
    n_u = min(MAX_NORMAL_TEXELS, max(1, math.ceil(factor * per_u - 1e-9)))
    n_v = min(MAX_NORMAL_TEXELS, max(1, math.ceil(factor * per_v - 1e-9)))
    return n_u, n_v


class TexturedMitsubaTarget:
    """One textured BSDF of a Mitsuba XML file as a spatially varying target (module
    doc): a :class:`neural_brdf.target.SpatiallyVarying` of kind ``"mitsuba"``."""

    kind = "mitsuba"

    def __init__(
        self, path: str | Path, *, variant: str = DEFAULT_VARIANT, key: str = "target.mitsuba"
    ):
        self.path = Path(path)
        self.source = str(path)
        self.variant = variant
        where = self._where = f"{key}: {self.source}"
        check_file(self.path, where)
        mi = self._mi = _mitsuba(self.variant, key)
        self.normal_map: dict[str, Any] | None = None
        self.warnings: list[str] = []  # printed once by the run (pipeline.teacher_warnings)
        self.excess: dict[str, Any] | None = None  # measure_excess()
        self._normal_tex: Any = None
        self._bump_scale = 0.0
        with self._scope():
            self._check_files(where)
            # wrappers included: what a scene of the teacher renders (a scene's one <bsdf>,
            # not the scene, which has no eval)
            obj = self.whole_bsdf = one_bsdf(mi, load(mi, self.path, where), where)
            self.bsdf, self.plugin = self._unwrap(obj, where)
            self._probe_whole(where)
            check_reflective(self.bsdf, self.plugin, where)
            check_rough(mi, self.bsdf, self.plugin, where)
            self.anisotropic = self._probe_anisotropy(where)

    @property
    def spatially_varying(self) -> Literal[True]:
        return True

    # ------------------------------------------------------------------ loading
    def _scope(self) -> contextlib.AbstractContextManager[None]:
        """Mitsuba's variant is the teacher's inside (:func:`variant_scope`)."""
        return variant_scope(self._mi, self.variant)

    def _xml(self, where: str) -> ET.Element:
        try:
            return ET.parse(self.path).getroot()
        except (ET.ParseError, OSError) as e:
            raise InputError(f"{where}: not a readable XML file ({_first(e)})") from None

    def _check_files(self, where: str) -> None:
        """Every ``filename`` string of the XML resolves, against the XML's folder first
        (as Mitsuba's loader does) through a copy of Mitsuba's file resolver; a missing
        one is named.  Also reads the normal/bump map's flags (module doc)."""
        mi = self._mi
        root = self._xml(where)
        resolver = resolver_for(mi, self.path)
        for el in root.iter("string"):
            if el.get("name") != "filename":
                continue
            value = el.get("value", "")
            if "$" in value:  # a parameter ($name): left to Mitsuba's loader
                continue
            if not Path(str(resolver.resolve(value))).is_file():
                raise InputError(
                    f"{where}: texture file {value!r} not found (relative names are "
                    f"resolved against {self.path.resolve().parent})"
                )
        for el in root.iter("texture"):  # the file's textures wrap by repeat (docs/mitsuba.md)
            if el.get("type") != "bitmap":
                continue
            strings = {m.get("name"): m.get("value", "") for m in el.findall("string")}
            mode = strings.get("wrap_mode", "repeat")
            name = el.get("name") or el.get("id") or "bitmap"
            texture = f"the texture {name!r} ({strings.get('filename')})"
            if mode != "repeat":
                self.warnings.append(
                    f"{where}: {texture} has wrap_mode {mode}, but the file's textures wrap "
                    "by repeat: within half a texel of its borders (and at uv outside [0, "
                    "1)) the file differs"
                )
            if strings.get("filter_type") == "nearest":  # a field blends its texels
                self.warnings.append(
                    f"{where}: {texture} has filter_type nearest, but the file's textures "
                    "are interpolated bilinearly: between texel centres, where the teacher "
                    "steps from one texel to the next, the file blends them"
                )
        for el in root.iter("bsdf"):
            if el.get("type") in ("normalmap", "bumpmap"):
                flags = {b.get("name"): b.get("value", "true") for b in el.findall("boolean")}
                self.normal_map = {
                    "plugin": el.get("type"),
                    "flip_invalid_normals": flags.get("flip_invalid_normals", "true") == "true",
                    "use_shadowing_function": flags.get("use_shadowing_function", "true") == "true",
                }
                break

    def _unwrap(self, obj: Any, where: str) -> tuple[Any, str]:
        mi = self._mi
        obj = one_bsdf(mi, obj, where)
        names = []
        while obj.class_name() in WRAPPERS:
            name = WRAPPERS[obj.class_name()]
            names.append(name)
            kids = dict(_children(mi, obj))
            if name == "twosided":
                inner = kids.get("brdf_0")
            else:
                inner = kids.get("nested_bsdf")
                if self._normal_tex is not None:
                    raise InputError(f"{where}: more than one normal or bump map")
                if name == "normalmap":
                    self._normal_tex = kids.get("normalmap")
                else:
                    self._normal_tex = kids.get("nested_texture")
                    self._bump_scale = float(mi.traverse(obj)["scale"])
                    self.warnings.append(
                        f"{where}: a bumpmap's relief depends on the mesh (Mitsuba tilts "
                        "the normal by the height's gradient over |dp/du|, |dp/dv|); the "
                        "file holds it for |dp/du| = |dp/dv| = 1, so on a mesh of another "
                        "uv scale it differs from the teacher; a normalmap does not "
                        "(docs/mitsuba.md, Textured materials)"
                    )
                if self.normal_map is None:  # not found in the XML (a scene's reference)
                    self.normal_map = {"plugin": name}
            if inner is None:
                raise InputError(f"{where}: a {name} BSDF without a nested BSDF")
            obj = inner
        names.append(obj.class_name())
        nested = nested_normal_map(mi, obj)
        if nested is not None:  # else trained as Mitsuba's non-reciprocal wrapper
            raise InputError(
                f"{where}: a {nested} inside {obj.class_name()}: only a normal or bump map "
                "around the whole material (within twosided) goes into the file's normal "
                "field, and inside it the teacher is not reciprocal; move it outside"
            )
        return obj, " > ".join(names)

    def _probe_whole(self, where: str) -> None:
        """Mitsuba evaluates the whole teacher, its normal or bump map included (as the
        report and the viewer render it), at a few random uv: else a map Mitsuba cannot
        read (a normal map of one channel) trained and failed in the report."""
        mi, rng = self._mi, np.random.default_rng(11)
        uv = rng.random((PROBE_PAIRS, 2))
        wi = _hemisphere(rng.random((PROBE_PAIRS, 2)), z_min=0.1)
        wo = _hemisphere(rng.random((PROBE_PAIRS, 2)), z_min=0.1)
        try:
            self.whole_bsdf.eval(mi.BSDFContext(), interaction(mi, wi, uv), _tensor(mi, wo))
        except Exception as e:  # a plugin that needs what a bare interaction lacks
            raise InputError(f"{where}: Mitsuba cannot evaluate it ({_first(e)})") from None

    def _probe_anisotropy(self, where: str) -> bool:
        """The same pairs at PROBE_UV random uv, turned about the normal: anisotropic
        when the value changes (as MitsubaTarget's probe)."""
        rng = np.random.default_rng(7)
        n = PROBE_PAIRS * PROBE_UV
        z_min = math.sin(math.radians(3.0))
        wi = _hemisphere(rng.random((n, 2)), z_min=z_min)
        wo = _hemisphere(rng.random((n, 2)), z_min=z_min)
        uv = np.repeat(rng.random((PROBE_UV, 2)), PROBE_PAIRS, 0)
        try:
            base = self._eval_cos(wi, wo, uv)
        except Exception as e:  # a plugin that needs what a bare interaction lacks
            raise InputError(f"{where}: Mitsuba cannot evaluate it ({_first(e)})") from None
        if not np.all(np.isfinite(base)) or base.min() < 0:
            raise InputError(f"{where}: {self.plugin} gives negative or non-finite values")
        scale = max(float(np.sqrt(np.mean(base**2))), 1e-30)
        diff = 0.0
        for phi in (0.7, 1.9, 2.6):
            c, s = math.cos(phi), math.sin(phi)
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            turned = self._eval_cos(wi @ rot.T, wo @ rot.T, uv)
            diff = max(diff, float(np.sqrt(np.mean((turned - base) ** 2))))
        return diff / scale > ANISO_TOL

    # ------------------------------------------------------------------ Mitsuba calls
    def _eval_cos(self, wi: np.ndarray, wo: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Mitsuba's eval (f cos theta_o), (K, 3) float64, for unit (K, 3) pairs."""
        mi = self._mi
        with self._scope():
            out = self.bsdf.eval(mi.BSDFContext(), interaction(self._mi, wi, uv), _tensor(mi, wo))
            return _np(out)

    def _rows(
        self, wi: Any, wo: Any, uv: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, ...]]:
        """Broadcast (…, 3), (…, 3), (…, 2) -> flat rows, the batch shape and the mask of
        rows with finite entries and both directions strictly above the horizon."""
        a, b, c = _as_rows(wi, 3), _as_rows(wo, 3), _as_rows(uv, 2)
        batch = np.broadcast_shapes(a.shape[:-1], b.shape[:-1], c.shape[:-1])
        a = np.broadcast_to(a, batch + (3,)).reshape(-1, 3)
        b = np.broadcast_to(b, batch + (3,)).reshape(-1, 3)
        c = np.broadcast_to(c, batch + (2,)).reshape(-1, 2)
        ok = (
            np.all(np.isfinite(a), -1)
            & np.all(np.isfinite(b), -1)
            & np.all(np.isfinite(c), -1)
            & (a[:, 2] > 0)
            & (b[:, 2] > 0)
        )
        return a, b, c, ok, batch

    # ------------------------------------------------------------------ the target API
    def eval(self, wi: Any, wo: Any, uv: Any) -> np.ndarray:
        """f (..., 3) float64, 1/sr, no cosine, at texture coordinates uv (..., 2); 0 below
        the horizon and where an entry is not finite (the edges of base.eval_pairs)."""
        a, b, c, ok, batch = self._rows(wi, wo, uv)
        out = np.zeros((len(a), 3))
        rows = np.flatnonzero(ok)
        for s in range(0, len(rows), CHUNK):
            r = rows[s : s + CHUNK]
            x, y = _unit(a[r]), _unit(b[r])
            out[r] = self._eval_cos(x, y, c[r]) / y[:, 2:3]
        return out.reshape(batch + (3,))

    def f(self, wi: torch.Tensor, wo: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        out = self.eval(wi, wo, uv)
        return torch.from_numpy(out).to(device=wi.device, dtype=wi.dtype)

    def _sample_rows(self, wi: np.ndarray, uv: np.ndarray, u: np.ndarray) -> tuple[Any, Any]:
        """Mitsuba's (BSDFSample3f, weight) for unit wi rows.  The lobe choice
        (``sample1``) is a uniform number from a hash of ``u`` (as MitsubaTarget)."""
        seed = int.from_bytes(hashlib.blake2b(u.tobytes(), digest_size=8).digest(), "little")
        s1 = np.random.default_rng(seed).random(len(u))
        return sample_rows(self._mi, self.bsdf, wi, uv, s1, u)

    def sample(self, wi: Any, uv: Any, u: Any) -> np.ndarray:
        """wo (..., 3) for wi (..., 3) at uv (..., 2) from u (..., 2) in [0, 1)^2 by
        Mitsuba's sampler; a failed sample, or wi at or below the horizon, gives
        (0, 0, -1) (below the horizon)."""
        a, c, uu = _as_rows(wi, 3), _as_rows(uv, 2), _as_rows(u, 2)
        batch = np.broadcast_shapes(a.shape[:-1], c.shape[:-1], uu.shape[:-1])
        a = np.broadcast_to(a, batch + (3,)).reshape(-1, 3)
        c = np.broadcast_to(c, batch + (2,)).reshape(-1, 2)
        uu = np.ascontiguousarray(np.broadcast_to(uu, batch + (2,)).reshape(-1, 2))
        out = np.tile([0.0, 0.0, -1.0], (len(a), 1))
        ok = np.flatnonzero(np.all(np.isfinite(a), -1) & np.all(np.isfinite(c), -1) & (a[:, 2] > 0))
        for s in range(0, len(ok), CHUNK):
            r = ok[s : s + CHUNK]
            with self._scope():
                bs, _ = self._sample_rows(_unit(a[r]), c[r], np.ascontiguousarray(uu[r]))
                wo, pdf = _np(bs.wo), _np(bs.pdf)
            good = (pdf > 0) & np.isfinite(pdf) & (wo[:, 2] > 0) & np.all(np.isfinite(wo), -1)
            wo[~good] = (0.0, 0.0, -1.0)
            out[r] = wo
        return out.reshape(batch + (3,))

    def pdf(self, wi: Any, wo: Any, uv: Any) -> np.ndarray:
        """The density (...,) of :meth:`sample`'s wo per solid angle (Mitsuba's pdf);
        0 below the horizon."""
        a, b, c, ok, batch = self._rows(wi, wo, uv)
        out = np.zeros(len(a))
        rows = np.flatnonzero(ok)
        mi = self._mi
        for s in range(0, len(rows), CHUNK):
            r = rows[s : s + CHUNK]
            with self._scope():
                si = interaction(self._mi, _unit(a[r]), c[r])
                out[r] = _np(self.bsdf.pdf(mi.BSDFContext(), si, _tensor(mi, _unit(b[r]))))
        return out.reshape(batch)

    def normal_field(self, uv: Any) -> np.ndarray:
        """The perturbed shading normal (..., 3) at uv (..., 2), in the tangent frame, as
        Mitsuba's normalmap / bumpmap computes it for wi = z (module doc); (0, 0, 1)
        without a map."""
        c = _as_rows(uv, 2)
        batch = c.shape[:-1]
        c = c.reshape(-1, 2)
        out = np.tile([0.0, 0.0, 1.0], (len(c), 1))
        if self._normal_tex is None or len(c) == 0:
            return out.reshape(batch + (3,))
        ok = np.flatnonzero(np.all(np.isfinite(c), -1))
        n = self._raw_normal(c[ok])
        out[ok] = n / np.linalg.norm(n, axis=-1, keepdims=True)
        return out.reshape(batch + (3,))

    def _is_bump(self) -> bool:
        return self.normal_map is not None and self.normal_map["plugin"] == "bumpmap"

    def _raw_normal(self, uv: np.ndarray) -> np.ndarray:
        """The map's unnormalised normal (K, 3) at finite uv (K, 2), before Mitsuba's
        normalize: 2 t - 1 of a normalmap, (-s h_u, -s h_v, 1) of a bumpmap."""
        out = np.empty((len(uv), 3))
        for s in range(0, len(uv), CHUNK):
            r = slice(s, s + CHUNK)
            with self._scope():
                si = interaction(self._mi, np.tile([0.0, 0.0, 1.0], (len(uv[r]), 1)), uv[r])
                if self._is_bump():
                    # bumpmap.cpp frame(): cross(dp_du + n s h_u, dp_dv + n s h_v)
                    g = _np(self._normal_tex.eval_1_grad(si)) * self._bump_scale
                    out[r] = np.c_[-g[:, 0], -g[:, 1], np.ones(len(g))]
                else:
                    # normalmap.cpp frame(): n = normalize(fmadd(texture, 2, -1))
                    out[r] = 2.0 * _np(self._normal_tex.eval(si)) - 1.0
        return out

    def normal_texels(self, default_resolution: int = 512) -> np.ndarray | None:
        """The normal field as texels for the file (``train.textured_model.NormalField``):
        (Rv, Ru, 3) unnormalised normals at the texel centres ((i + 0.5) / Ru, (j + 0.5)
        / Rv), or None without a map.

        A normalmap's texels are its texture's own 2 t - 1 (at a texel centre a bitmap's
        bilinear look-up is the texel itself), at the bitmap's resolution over the uv
        square it covers (:func:`texels_over_surface`: a to_uv scale of 3 repeats a 64²
        map 3 times, so 192²; sampled at 64² it was 7.3 degrees off on average), so
        bilinear interpolation and normalisation reproduce Mitsuba's normal between
        centres too.
        A procedural texture is sampled at ``default_resolution`` texel centres.  A bump
        map's normal is the gradient of the bitmap's bilinear height, which is constant
        in u (linear in v) across each cell between four texel centres and JUMPS at the
        centres: sampled there it is one side's difference or the other's (float32
        decides), and the file's blend between centres lags by half a texel (a mean error
        of 8.5 deg on a 16² map with a mean tilt of 22 deg).  So a bitmap's gradient is
        sampled :func:`bump_factor` (even) times per texel and axis: every sample lies
        inside a cell, where it is the gradient's mean over its own texel (constant or
        linear there), and only the file's texels astride a jump blend across it: the mean
        error falls as 1 / factor (0.16 deg at 512² there), the largest stays about half
        the largest jump.  ``validate`` measures it (docs/model.md, "The normal field")."""
        if self._normal_tex is None:
            return None
        mi = self._mi
        with self._scope():
            data = mi.traverse(self._normal_tex).get("data")
            to_uv = mi.traverse(self._normal_tex).get("to_uv")
        shape = tuple(int(d) for d in data.shape) if data is not None else ()
        rv, ru = shape[:2] if len(shape) >= 2 else (default_resolution, default_resolution)
        if len(shape) >= 2 and to_uv is not None:
            ru, rv = texels_over_surface(ru, rv, np.array(to_uv.matrix, dtype=np.float64))
        if len(shape) >= 2 and self._is_bump():
            rv *= bump_factor(rv, default_resolution)
            ru *= bump_factor(ru, default_resolution)
        u = (np.arange(ru) + 0.5) / ru
        v = (np.arange(rv) + 0.5) / rv
        uv = np.stack(np.meshgrid(u, v, indexing="xy"), -1).reshape(-1, 2)  # row j, column i
        out = self._raw_normal(uv)
        return out.reshape(rv, ru, 3)

    @property
    def where(self) -> str:
        """How errors and warnings name this teacher: ``target.mitsuba: PATH``."""
        return self._where

    def normal_field_warning(self, figures: dict[str, Any] | None) -> str | None:
        """One warning line when the file's normal field is far from the teacher's:
        ``figures`` is ``validate.normal_field_error``'s (metrics.json ``normal_field``),
        large when its mean error exceeds NORMAL_WARN_DEG and NORMAL_WARN_SHARE of the
        teacher's mean tilt (at NORMAL_WARN_UV random uv); None otherwise.  The error has
        no limit in ``passed``: the run goes on, and says so (docs/mitsuba.md)."""
        if not figures or self._normal_tex is None:
            return None
        uv = np.random.default_rng(0).random((NORMAL_WARN_UV, 2))
        tilt = float(np.degrees(np.arccos(np.clip(self.normal_field(uv)[:, 2], -1, 1))).mean())
        mean = float(figures["mean_deg"])
        if not mean > max(NORMAL_WARN_DEG, NORMAL_WARN_SHARE * tilt):
            return None
        plugin = (self.normal_map or {}).get("plugin", "normal map")
        return (
            f"{self._where}: the file's normal field ({plugin}) is "
            f"{mean:.2f} deg from the teacher's on average (max {figures['max_deg']:.1f} deg), "
            f"against a teacher's tilt of {tilt:.2f} deg on average (max "
            f"{figures['teacher_max_tilt_deg']:.1f} deg): its relief shades differently"
        )

    def max_albedo(
        self,
        uv: Any,
        *,
        theta_deg: tuple[float, ...] = ALBEDO_THETA_DEG,
        samples: int = ALBEDO_SAMPLES,
        seed: int = 0,
    ) -> np.ndarray:
        """The directional albedo A(wi) = int f cos dwo at uv (K, 2), maximised over the
        incidences ``theta_deg`` (azimuth 0; and 90 degrees too when anisotropic), per
        channel: (K, 3).  Estimated by Mitsuba's sampler: the mean of its sample weight
        f cos / pdf over ``samples`` draws (failed draws weigh 0)."""
        c = _as_rows(uv, 2).reshape(-1, 2)
        phis = (0.0, 90.0) if self.anisotropic else (0.0,)
        rng = np.random.default_rng(seed)
        best = np.zeros((len(c), 3))
        for t in theta_deg:
            for p in phis:
                th, ph = math.radians(t), math.radians(p)
                w = [math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)]
                wi = np.tile(w, (len(c) * samples, 1))
                cc = np.repeat(c, samples, 0)
                u = rng.random((len(wi), 2))
                with self._scope():
                    _, weight = self._sample_rows(wi, cc, u)
                    wt = _np(weight)
                wt = np.where(np.isfinite(wt), wt, 0.0)
                best = np.maximum(best, wt.reshape(len(c), samples, 3).mean(1))
        return best

    def measure_excess(
        self, *, points: int = 16, samples: int = 2048, seed: int = 0, tol: float = 1e-3
    ) -> dict[str, Any] | None:
        """Where and by how much the teacher's albedo exceeds 1 + ``tol``
        (:meth:`max_albedo` at ``points`` random uv), kept in :attr:`excess` for the
        file's metadata and the report; None when it does not.  A model learns the
        teacher's energy-bounded version: each of its lobes is normalised."""
        uv = np.random.default_rng(seed).random((points, 2))
        a = self.max_albedo(uv, samples=samples, seed=seed + 1)
        k = int(np.argmax(a.max(-1)))
        top = float(a[k].max())
        self.excess = (
            {
                "max_albedo": top,
                "at_uv": uv[k].round(5).tolist(),
                "uv_points": points,
                "share_of_uv_above_1": float(np.mean(a.max(-1) > 1.0 + tol)),
                "learned": "the energy-bounded version: each lobe of the model is normalised",
            }
            if top > 1.0 + tol
            else None
        )
        return self.excess

    def describe(self) -> str:
        text = f"Mitsuba {self.plugin} ({self.source}, {self.variant}), spatially varying"
        if self.normal_map is not None:
            text += f"; {self.normal_map['plugin']} as a separate normal field"
        if self.anisotropic:
            text += ", anisotropic"
        return text
