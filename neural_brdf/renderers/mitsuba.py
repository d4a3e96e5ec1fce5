"""Mitsuba 3 plugins for exported neural BRDFs and for the analytic models.

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")            # or cuda_ad_rgb
    import neural_brdf.renderers.mitsuba               # registers the two plugins below
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": "runs/quickstart/model.onnx"})
    ref = mi.load_dict({"type": "analytic_brdf", "model": "microfacet",
                        "params": '{"alpha": 0.3, "fresnel": "conductor", "material": "Au"}'})

The preview scene, PNG writing and PSNR are in :mod:`neural_brdf.renderers.render`.

This module holds the renderer plugins; the other modules that import mitsuba use it
(renderers/render.py: preview renders; inverse/fit.py, inverse/bsdf.py, inverse/scene.py:
fitting from images; viewer/plots.py and tooling/cli.py: to check that it is installed
and set a variant; measured/rgl/bake.py uses Mitsuba's own spectral tables, not these
plugins).  Importing this
module needs a Mitsuba variant to be set already (``mi.set_variant``); the plugins are
registered for that variant, which must be a JIT one (``llvm_*`` or ``cuda_*``; scalar
variants are refused when a plugin loads).

Evaluation.  The plugin never evaluates a retyped copy of the model.  The exported ONNX
graph is lowered once by :mod:`neural_brdf.graph` (constants folded, dense layers as
fused multiply-add chains with literal weights) and the instruction list is executed
with Dr.Jit arrays by :mod:`neural_brdf.backends.drjit` (:class:`OnnxProgram`).  In JIT
variants the whole graph is traced into the render's kernel, so rendering calls no
Python per sample; it runs inside a conditional, skipped for SIMD packets in which no
lane has both directions above the horizon.  An op the lowering lacks raises
:class:`UnsupportedOnnxOp` naming it when the model loads.

Textured models.  A graph with the inputs (wi, wo, uv) (``fileformat.SIGNATURES[1]``,
docs/model.md, "Spatially varying models: the contract") is evaluated at the surface
interaction's texture coordinates ``si.uv`` (the graph wraps them itself) in ``eval``
and in ``sample``'s weight; the local frame is Mitsuba's shading frame (dp_du the
tangent).  Its sampling lobe is global: the file's ``sampling_lobe``, or one fitted at
load to f at uniformly drawn uv.  A two-input graph is traced exactly as before.

Normal fields.  A textured graph with the second output ``n`` (the teacher's normal
map, docs/model.md, "The normal field") is applied as Mitsuba 3.9.1's ``normalmap``
applies its texture (src/bsdfs/normalmap.cpp): the normal n(si.uv), flipped to
(-n_x, -n_y, n_z) where wi lies below its plane (``flip_invalid_normals``), gives the
rotated frame n, s = normalize(x - n n_x), t = n x s; f, the pdf and the sampler run
with wi and wo in that frame; a pair is kept only where wo is on the same side of both
normals; eval and the sample weight are multiplied by Estevez et al.'s shadowing term
2 / (1 + sqrt(1 + a2 tan^2 theta_o)), a2 = min(1, tan^2 theta_n / 8) ("A
Microfacet-Based Shadowing Function to Solve the Bump Terminator Problem", Ray Tracing
Gems 2019; ``use_shadowing_function``).  Both flags come from the file's
``texture.normal_field`` metadata, as the teacher's wrapper had them.

The ``analytic_brdf`` plugin exports the analytic model's own torch ``f(wi, wo)`` to
ONNX with ``torch.onnx`` (in memory) and runs it through the same interpreter, so it is
as fast as the neural plugin and never calls back into torch while rendering.

Sampling (both plugins).  The mixture of :mod:`neural_brdf.fileformat.lobe`: cosine-weighted
hemisphere sampling (share 1 - w) and GGX visible-normal sampling of a reflection lobe
of roughness ``(alpha_x, alpha_y)`` (share w), turned by pi about the normal for a
retro lobe; ``pdf`` is the mixture density of ``sample``.  The neural plugin reads the
lobe from the ONNX metadata key ``sampling_lobe``, which the exporter writes; for files
exported before it did, it fits them when the model loads (about a second), as the
analytic plugin always does.  The sample weight is
computed by the very same traced functions as ``eval`` and ``pdf`` (value / pdf), so it
equals eval / pdf exactly; with a normal field, to rounding only (the sampled wo is
turned back to the unperturbed frame, and eval and pdf turn it again: docs/mitsuba.md).

Conventions (Mitsuba's): ``eval`` returns f * cos(theta_o), 0 when wi or
wo is at or below the horizon (one-sided, like Mitsuba's built-in BSDFs); ``pdf`` is 0
below the horizon; a sample below it has weight 0.  Directions follow the generated
code's rule (:mod:`neural_brdf.backends.lobe_ir`, the graph's): each is normalised
(:func:`_unit_or_invalid`) before the horizon test, the cosine and the pdf; one with a
NaN, an infinity or zero length gives eval 0 and pdf 0, and as wi a refused sample (wo
= (0, 0, -1), pdf 0, weight 0), as does a random number not finite or not in [0, 1].
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi

from neural_brdf.backends.drjit import OnnxProgram
from neural_brdf.errors import InputError, not_a_file
from neural_brdf.fileformat import NORMAL, OUTPUT, SIGNATURES, reader
from neural_brdf.fileformat import lobe as lobe_format
from neural_brdf.graph import SUPPORTED_OPS, UnsupportedOnnxOp
from neural_brdf.physics import lobe_fit

if mi.variant() is None:
    raise ImportError(
        "neural_brdf.renderers.mitsuba: set a Mitsuba variant first, e.g. "
        "mi.set_variant('llvm_ad_rgb'); the plugins register for that variant"
    )
if not mi.is_rgb:
    # The graph returns RGB.  In a spectral or monochrome variant a scene would load and
    # the render then die inside Mitsuba with a bare std::bad_cast, so refuse here.
    raise ImportError(
        f"neural_brdf.renderers.mitsuba: variant {mi.variant()!r} is not an RGB variant; "
        "the neural BSDF returns RGB values: use llvm_ad_rgb or cuda_ad_rgb "
        "(for spectral rendering, bake the model to an RGL .bsdf file for "
        "Mitsuba's own 'measured' plugin)"
    )

__all__ = [
    "SUPPORTED_OPS",
    "AnalyticBSDF",
    "NeuralBSDF",
    "OnnxProgram",
    "UnsupportedOnnxOp",
    "analytic_onnx",
    "read_model",
]


# ====================================================================== BSDF plugins
def _black(wi, wo, cos_o):
    return mi.Color3f(0.0)


def _black_uv(wi, wo, uv, cos_o):
    return mi.Color3f(0.0)


def _interp(c, xs, ys):
    """ys interpolated linearly at c over the ascending nodes xs, clamped at the ends."""
    y = mi.Float(ys[0])
    for k in range(1, len(xs)):
        if ys[k] != ys[k - 1]:
            t = dr.clip((c - xs[k - 1]) / (xs[k] - xs[k - 1]), 0.0, 1.0)
            y = y + t * (ys[k] - ys[k - 1])
    return y


def _turn(w):
    """A half turn about the normal, (x, y, z) -> (-x, -y, z): the retro lobe."""
    return mi.Vector3f(-w.x, -w.y, w.z)


def _unit_or_invalid(w):
    """(unit vector, valid) of any float direction by the exported graph's rule
    (:func:`neural_brdf.train.model.unit_or_invalid`, and the generated code's
    ``neural_brdf.backends.lobe_ir._unit_or_invalid``, the same operations): valid when
    the three components are finite and not all zero; divided by the largest absolute
    component, then by the length; an invalid direction becomes +z (the caller masks
    it).  So pdf(k wi, k' wo) is pdf(wi, wo) for k, k' > 0, as in the generated code, and
    a huge direction such as (3e38, 3e38, 3e38) means what it means to the graph."""
    finite = dr.isfinite(w.x) & dr.isfinite(w.y) & dr.isfinite(w.z)
    a = dr.abs(dr.select(finite, w, 0.0))
    m = dr.maximum(dr.maximum(a.x, a.y), a.z)
    ok = finite & (m > 0.0)
    # component by component: a Vector3f divided by a Float is a product with the
    # reciprocal, which is subnormal, so flushed to 0, for m above 2^126 (3e38)
    u, d = dr.select(ok, w, 0.0), dr.select(ok, m, 1.0)
    u = mi.Vector3f(u.x / d, u.y / d, u.z / d)
    n = dr.sqrt(u.x * u.x + u.y * u.y + u.z * u.z)
    return dr.select(ok, mi.Vector3f(u.x / n, u.y / n, u.z / n), mi.Vector3f(0.0, 0.0, 1.0)), ok


def _in_unit_interval(x):
    """Where a random number is finite and in [0, 1].  Not [0, 1): a sampler's float32
    rounding may reach 1.0 ((i + jitter) / n, say), and Mitsuba's warps take it; the
    generated code, whose callers are documented to pass [0, 1), refuses 1
    (neural_brdf.backends.lobe_ir)."""
    return dr.isfinite(x) & (x >= 0.0) & (x <= 1.0)


def _samples_ok(sample1, sample2):
    return _in_unit_interval(sample1) & _in_unit_interval(sample2.x) & _in_unit_interval(sample2.y)


def _unit_si(si):
    """(a copy of si with wi normalised by the graph's rule, valid)."""
    wi, ok = _unit_or_invalid(si.wi)
    usi = mi.SurfaceInteraction3f(si)
    usi.wi = wi
    return usi, ok


# where a sample is refused before it is drawn (wi not a direction, u not in [0, 1]):
# a direction below the horizon, as the generated code's rejected sample
_REJECTED = (0.0, 0.0, -1.0)


def _shadow_terminator(n, wo):
    """Estevez et al. 2019's shadowing term of a perturbed normal n (in the unperturbed
    frame) for wo: normalmap_helpers.h's eval_shadow_terminator."""
    alpha2 = dr.minimum(0.125 * mi.Frame3f.tan_theta_2(n), 1.0)
    return 2.0 / (1.0 + dr.sqrt(1.0 + alpha2 * mi.Frame3f.tan_theta_2(wo)))


class _GraphBSDF(mi.BSDF):
    """A BSDF evaluated by an ONNX graph (f, no cosine) with the mixture sampler."""

    normal_program: OnnxProgram | None = None
    normal_flags: dict = {}

    def _setup(self, program: OnnxProgram, lobe: dict, label: str):
        if not dr.is_jit_v(mi.Float):
            raise InputError(
                f"{label}: needs a JIT variant (llvm_ad_rgb, cuda_ad_rgb, ...); "
                f"the interpreter traces Dr.Jit arrays, and {mi.variant()} has none"
            )
        if tuple(program.inputs) not in SIGNATURES or program.outputs != [OUTPUT]:
            expected = " or ".join(str(list(s)) for s in SIGNATURES)
            raise InputError(
                f"{label}: expected inputs {expected} and output {OUTPUT!r}, "
                f"got {program.inputs} -> {program.outputs}"
            )
        self.program = program
        # a textured graph (inputs wi, wo, uv: docs/model.md, "Spatially varying models")
        # is evaluated at the interaction's texture coordinates si.uv
        self.textured = tuple(program.inputs) == SIGNATURES[1]
        self.lobe = lobe_format.complete(lobe)
        self.label = label
        self.lobe_table = self.lobe.get("table")
        # the largest share decides whether the GGX branch exists at all
        self.lobe_weight = (
            max(self.lobe_table["weight"]) if self.lobe_table else float(self.lobe["weight"])
        )
        self.lobe_retro = self.lobe["retro"]
        flags = (
            mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        )
        self.m_components = [flags]
        self.m_flags = flags

    # -- the three traced pieces; sample() reuses them so that weight == eval / pdf
    def _f_cos(self, si, wo, active):
        # wi and wo are normalised by the graph's rule for the horizon test and the
        # cosine (a non-finite or zero-length direction gives 0, a scaled one what the
        # unit one gives); the graph itself gets them as given and normalises them with
        # the same operations, so that it is onnxruntime's f at the given floats
        wi_u, ok_i = _unit_or_invalid(si.wi)
        wo_u, ok_o = _unit_or_invalid(wo)
        valid = active & ok_i & ok_o & (wi_u.z > 0.0) & (wo_u.z > 0.0)
        # (the cosine is the unit wo's, handed to _graph_f_cos, which the differentiable
        # plugin, neural_brdf.inverse.bsdf, overrides)
        # The graph runs inside a conditional, which Dr.Jit skips for a SIMD packet
        # (LLVM) or warp (CUDA) where no lane needs it: the unlit side of a light,
        # light samples below the horizon, paths that left the surface.
        if self.textured:
            return dr.if_stmt(
                (si.wi, wo, si.uv, wo_u.z), valid, self._graph_f_cos_uv, _black_uv, label="graph"
            )
        return dr.if_stmt((si.wi, wo, wo_u.z), valid, self._graph_f_cos, _black, label="graph")

    def _graph_f_cos(self, wi, wo, cos_o):
        out = self.program(wi=[wi.x, wi.y, wi.z], wo=[wo.x, wo.y, wo.z])[OUTPUT]
        return mi.Color3f(out[0], out[1], out[2]) * cos_o

    def _graph_f_cos_uv(self, wi, wo, uv, cos_o):
        """The textured graph at the texture coordinates ``uv`` (the host's si.uv, wrapped
        by the graph itself); the sampling lobe stays the file's global one."""
        out = self.program(wi=[wi.x, wi.y, wi.z], wo=[wo.x, wo.y, wo.z], uv=[uv.x, uv.y])[OUTPUT]
        return mi.Color3f(out[0], out[1], out[2]) * cos_o

    def _pdf(self, si, wo, active, unit=False):
        # the generated code's rule (neural_brdf.backends.lobe_ir): both directions
        # normalised as the graph does, 0 for a non-finite or zero-length one; unit:
        # they were, before a normal field's rotation (_rotated), and are used as they
        # are (so that a flat field gives the pdf of the file without it, bit for bit)
        wi = si.wi
        if not unit:
            wi, ok_i = _unit_or_invalid(wi)
            wo, ok_o = _unit_or_invalid(wo)
            active = active & ok_i & ok_o
        valid = active & (wi.z > 0.0) & (wo.z > 0.0)
        distr, w, ax, ay = self._lobe(wi)
        p = (1.0 - w) * mi.warp.square_to_cosine_hemisphere_pdf(wo)
        if self.lobe_weight > 0.0:  # a Python float: decided once, not per lane
            v = _turn(wo) if self.lobe_retro else wo
            m = dr.normalize(wi + v)
            dot_om = dr.dot(v, m)
            p_m = self._visible_pdf(distr, wi, m, ax, ay)
            p_ggx = dr.select(dot_om > 0.0, p_m / (4.0 * dot_om), 0.0)
            p = p + w * p_ggx
        return dr.select(valid, p, 0.0)

    def _lobe(self, wi):
        """The GGX or Beckmann distribution and share of the lobe for wi: constants, or with a
        per-incidence table interpolated linearly in cos theta_i
        (neural_brdf.fileformat.lobe.at)."""
        lobe, t = self.lobe, self.lobe_table
        kind = (
            mi.MicrofacetType.Beckmann
            if lobe["distribution"] == "beckmann"
            else mi.MicrofacetType.GGX
        )
        if not t:
            ax, ay, w = lobe["alpha_x"], lobe["alpha_y"], mi.Float(lobe["weight"])
        else:
            c = mi.Frame3f.cos_theta(wi)
            ax, ay, w = (_interp(c, t["cos_theta"], t[k]) for k in ("alpha_x", "alpha_y", "weight"))
        return mi.MicrofacetDistribution(kind, ax, ay, True), w, ax, ay

    def _visible_pdf(self, distr, wi, m, ax, ay):
        """The density of the visible normal m seen from wi.  For Beckmann, Mitsuba's
        pdf uses a rational approximation of Smith's G1 (up to 0.3 % off the exact
        density); here the exact Lambda(a) = (erf(a) - 1) / 2 + exp(-a^2) / (2 a
        sqrt(pi)), a = 1 / (alpha tan theta) (Walter et al. 2007, eq. 27), as in
        neural_brdf.physics.lobe_fit and the generated code."""
        if self.lobe["distribution"] != "beckmann":
            return distr.pdf(wi, m)
        cos_i = mi.Frame3f.cos_theta(wi)
        a2 = (ax * ax * wi.x * wi.x + ay * ay * wi.y * wi.y) / (cos_i * cos_i)
        a = dr.rsqrt(dr.maximum(a2, 1e-30))
        lam = 0.5 * (dr.erf(a) - 1.0) + dr.exp(-a * a) / (2.0 * math.sqrt(math.pi) * a)
        return distr.eval(m) * dr.maximum(dr.dot(wi, m), 0.0) / ((1.0 + lam) * cos_i)

    def _enabled(self, ctx) -> bool:
        return ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0) or ctx.is_enabled(
            mi.BSDFFlags.DiffuseReflection, 0
        )

    # -- the normal field (module doc, "Normal fields"): Mitsuba's normalmap.cpp
    def _frame(self, si):
        """The rotated frame at si (in the unperturbed local frame), as normalmap.cpp's
        frame(): n(si.uv) from the graph, flipped by wi, then Gram-Schmidt of x."""
        assert self.normal_program is not None
        cols = self.normal_program(uv=[si.uv.x, si.uv.y])[NORMAL]
        n = mi.Vector3f(cols[0], cols[1], cols[2])
        if self.normal_flags.get("flip_invalid_normals", True):
            flip = mi.Frame3f.cos_theta(si.wi) * dr.dot(si.wi, n) <= 0.0
            n = dr.select(flip, mi.Vector3f(-n.x, -n.y, n.z), n)
        frame = mi.Frame3f(dr.normalize(n))
        frame.s = dr.normalize(mi.Vector3f(1.0, 0.0, 0.0) - frame.n * frame.n.x)
        frame.t = dr.cross(frame.n, frame.s)
        return frame

    def _rotated(self, si, wo, active):
        """(frame, si with wi in the frame, wo in the frame, wo, active & same side), wi
        and wo normalised first by the graph's rule (a non-finite or zero-length one
        leaves active false), so that a scaled direction is turned as the unit one."""
        usi, ok_i = _unit_si(si)
        wo, ok_o = _unit_or_invalid(wo)
        frame = self._frame(usi)
        psi = mi.SurfaceInteraction3f(usi)
        psi.wi = frame.to_local(usi.wi)
        pwo = frame.to_local(wo)
        ok = active & ok_i & ok_o
        ok &= mi.Frame3f.cos_theta(wo) * mi.Frame3f.cos_theta(pwo) > 0.0
        return frame, psi, pwo, wo, ok

    def _shadowed(self, value, frame, wo):
        if self.normal_flags.get("use_shadowing_function", True):
            return value * _shadow_terminator(frame.n, wo)
        return value

    def eval(self, ctx, si, wo, active=True):
        if not self._enabled(ctx):
            return mi.Color3f(0.0)
        if self.normal_program is None:
            return self._f_cos(si, wo, active)
        frame, psi, pwo, wo, ok = self._rotated(si, wo, active)
        value = self._shadowed(self._f_cos(psi, pwo, ok), frame, wo)
        return dr.select(ok, value, 0.0)

    def pdf(self, ctx, si, wo, active=True):
        if not self._enabled(ctx):
            return mi.Float(0.0)
        if self.normal_program is None:
            return self._pdf(si, wo, active)
        _, psi, pwo, _, ok = self._rotated(si, wo, active)
        return dr.select(ok, self._pdf(psi, pwo, ok, unit=True), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        if not self._enabled(ctx):
            return mi.Color3f(0.0), mi.Float(0.0)
        if self.normal_program is None:
            return self._f_cos(si, wo, active), self._pdf(si, wo, active)
        frame, psi, pwo, wo, ok = self._rotated(si, wo, active)
        value = self._shadowed(self._f_cos(psi, pwo, ok), frame, wo)
        return dr.select(ok, value, 0.0), dr.select(ok, self._pdf(psi, pwo, ok, unit=True), 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        if self.normal_program is None or not self._enabled(ctx):
            return self._sample(ctx, si, sample1, sample2, active)
        usi, ok_i = _unit_si(si)
        frame = self._frame(usi)
        psi = mi.SurfaceInteraction3f(usi)
        psi.wi = frame.to_local(usi.wi)
        bs, weight = self._sample(ctx, psi, sample1, sample2, active & ok_i, unit=True)
        wo = frame.to_world(bs.wo)
        ok = active & ok_i & (mi.Frame3f.cos_theta(bs.wo) * mi.Frame3f.cos_theta(wo) > 0.0)
        bs.pdf = dr.select(ok, bs.pdf, 0.0)
        bs.wo = dr.select(ok_i & _samples_ok(sample1, sample2), wo, mi.Vector3f(*_REJECTED))
        weight = self._shadowed(weight, frame, wo)
        return bs, dr.select(ok, weight, 0.0)

    def _sample(self, ctx, si, sample1, sample2, active=True, unit=False):
        bs = dr.zeros(mi.BSDFSample3f)
        if not self._enabled(ctx):
            return bs, mi.Color3f(0.0)
        # the generated code's rule: wi normalised as the graph does; a non-finite or
        # zero-length wi, or a random number that is not finite or not in [0, 1], is a
        # refused sample: wo = (0, 0, -1), pdf 0, weight 0 (never a NaN direction)
        wi, ok_i = (si.wi, mi.Bool(True)) if unit else _unit_or_invalid(si.wi)
        drawn = ok_i & _samples_ok(sample1, sample2)
        sample1 = dr.select(drawn, sample1, 0.0)
        sample2 = dr.select(drawn, sample2, 0.0)
        wo = mi.warp.square_to_cosine_hemisphere(sample2)
        glossy = mi.Bool(False)
        if self.lobe_weight > 0.0:
            distr, w, _, _ = self._lobe(wi)
            m, _ = distr.sample(wi, sample2)
            glossy = sample1 < w
            v = mi.reflect(wi, m)
            wo = dr.select(glossy, _turn(v) if self.lobe_retro else v, wo)
        wo = dr.select(drawn, wo, mi.Vector3f(*_REJECTED))
        active = active & drawn & (wi.z > 0.0)
        pdf = self._pdf(si, wo, active, unit)
        value = self._f_cos(si, wo, active)
        ok = active & (pdf > 0.0)
        bs.wo = wo
        bs.pdf = dr.select(ok, pdf, 0.0)
        bs.eta = 1.0
        # which lobe of the mixture drew the sample (integrators such as the path
        # guiders and AOVs read it); both lobes are component 0 of the one BSDF
        bs.sampled_type = dr.select(
            glossy,
            mi.UInt32(+mi.BSDFFlags.GlossyReflection),
            mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
        )
        bs.sampled_component = mi.UInt32(0)
        return bs, dr.select(ok, value / pdf, 0.0)

    def traverse(self, callback):
        pass

    def to_string(self):
        return (
            f"{type(self).__name__}[{self.label}, sampling lobe "
            f"{self.lobe['distribution']} alpha="
            f"({self.lobe['alpha_x']:.4g}, {self.lobe['alpha_y']:.4g}) "
            f"{'retro ' if self.lobe_retro else ''}weight={self.lobe['weight']:.3g}"
            f"{' per-incidence table' if self.lobe_table else ''} "
            f"({self.lobe_source})]"
        )


def _resolve(filename: str) -> Path:
    path = Path(filename)
    if not path.is_absolute():
        # Mitsuba's resolver holds the scene file's folder while an XML scene loads.
        # mi.file_resolver() replaced Thread.file_resolver() (deprecated in 3.9, whose
        # warning escapes from a plugin constructor as a SystemError).
        resolver = (
            mi.file_resolver()  # type: ignore[operator]  # the stub types it as an object
            if hasattr(mi, "file_resolver")
            else mi.Thread.thread().file_resolver()
        )
        resolved = Path(str(resolver.resolve(str(path))))
        if resolved.is_file():
            path = resolved
    if not path.is_file():
        raise InputError(f"neural_brdf: {not_a_file(filename, 'model')}")
    return path


def read_model(filename) -> tuple[Path, OnnxProgram, dict | None]:
    """Resolve, load and check an exported model: (path, program of f, stored lobe or
    None).  A file's normal field (output n) is left out of the program: the plugin
    lowers it on its own (:class:`NeuralBSDF`).

    A missing or unusable file raises a one-line InputError.  :func:`render_preview`
    calls this before it loads a scene, because Mitsuba reports an exception raised in a
    plugin's constructor as a RuntimeError carrying the Python traceback."""
    path, proto, stored = _read_proto(filename)
    return path, OnnxProgram(proto, (OUTPUT,) if _has_normal(proto) else None), stored


def _read_proto(filename) -> tuple[Path, Any, dict | None]:
    """:func:`read_model` before lowering: (path, the loaded proto, stored lobe or None)."""
    path = _resolve(str(filename))
    try:
        proto = reader.load(path)
    except InputError as e:
        raise InputError(f"neural_brdf: {e}") from None
    try:
        # the contract first: a foreign graph would fail later inside onnxruntime (the
        # lobe's fit at load) with a message that names neither the file nor the fault
        reader.signature(proto, source=f"neural_brdf: {path}")
    except InputError as e:
        raise InputError(str(e)) from None
    try:
        stored = lobe_format.from_metadata(reader.props(proto))
    except InputError as e:
        raise InputError(f"neural_brdf: {path}: {e}") from None
    return path, proto, stored


def _has_normal(proto) -> bool:
    return NORMAL in [o.name for o in proto.graph.output]


class NeuralBSDF(_GraphBSDF):
    """``{'type': 'neural_brdf', 'filename': 'model.onnx'}``: an exported neural BRDF."""

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        if "filename" not in props:
            raise InputError("neural_brdf: the 'filename' property (an ONNX file) is required")
        path, proto, stored = _read_proto(props["filename"])  # the file is read once
        program = OnnxProgram(proto, (OUTPUT,) if _has_normal(proto) else None)
        self.lobe_source = "metadata" if stored else "fitted at load"
        if _has_normal(proto):  # a textured file with its normal field
            field = (reader.metadata(proto).texture or {}).get("normal_field") or {}
            self.normal_flags = {
                k: bool(field.get(k, True))
                for k in ("flip_invalid_normals", "use_shadowing_function")
            }
            self.normal_program = OnnxProgram(proto, (NORMAL,))
        self._setup(program, stored or lobe_fit.fit_onnx(path), str(path))


def analytic_onnx(model: str, params: dict | None = None) -> bytes:
    """The analytic model's own torch ``f(wi, wo)`` as ONNX bytes:
    :func:`neural_brdf.export.analytic_onnx` (one writer, so that the same model gives
    the same bytes here and in the viewer, and its lobe is fitted once)."""
    from neural_brdf.export import analytic_onnx as write

    return write(model, params)


def _analytic_params(props) -> tuple[str, dict]:
    model = props["model"] if "model" in props else None
    if not model:
        raise InputError("analytic_brdf: the 'model' property is required")
    params = {}
    if "params" in props:
        try:
            params = json.loads(props["params"])
        except json.JSONDecodeError as e:
            raise InputError(f"analytic_brdf: 'params' is not valid JSON ({e})") from None
        if not isinstance(params, dict):
            raise InputError(f"analytic_brdf: 'params' must be a JSON object, got {params!r}")
    for key in props.keys():
        if key in ("model", "params", "type", "id", "lobe"):
            continue
        value = props[key]
        if isinstance(value, (bool, int, float, str)):
            params[key] = value
        else:  # an RGB colour or a vector
            params[key] = [float(v) for v in value]
    return str(model), params


class AnalyticBSDF(_GraphBSDF):
    """``{'type': 'analytic_brdf', 'model': 'microfacet', 'params': '{...}'}``; parameters
    may also be given as plugin properties (``'alpha': 0.3``).  ``'lobe'``: a sampling
    lobe as JSON (the ``sampling_lobe`` metadata of a model of the same target, say),
    used instead of fitting one at load (about a second)."""

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        model, params = _analytic_params(props)
        payload = analytic_onnx(model, params)
        label = f"analytic {model} {json.dumps(params, sort_keys=True)}"
        if "lobe" in props:
            try:  # a whole stored lobe, or a partial one ({"alpha": a, "weight": w})
                given = json.loads(str(props["lobe"]))
                if not isinstance(given, dict):
                    raise ValueError(f"expected a JSON object, got {given!r}")
                lobe = lobe_format.complete(given)
            except (ValueError, InputError) as e:
                raise InputError(f"analytic_brdf: 'lobe': {e}") from None
            self.lobe_source = "given"
        else:
            lobe = lobe_fit.fit_onnx(payload)
            self.lobe_source = "fitted at load"
        self._setup(OnnxProgram(payload), lobe, label)


mi.register_bsdf("neural_brdf", lambda props: NeuralBSDF(props))
mi.register_bsdf("analytic_brdf", lambda props: AnalyticBSDF(props))
