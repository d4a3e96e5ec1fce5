"""The views of an image fit: photographs, their scenes, the fitted BSDF's slot, the loss.

    from neural_brdf.inverse import views
    vs = views.read_views(cfg)                     # a config whose target is images
    views.prepare_views(vs, views.bsdf_element("diffuse"))

What :mod:`neural_brdf.inverse.fit`, :mod:`neural_brdf.inverse.starts` and
:mod:`neural_brdf.inverse.coverage` all build on, below each of them: a :class:`View` (a
scene, its target and its split), reading and checking the scenes and images (one-line
errors naming the file), the XML of a scene with the fitted BSDF in its ``<bsdf
id="fit">`` slot, the variant, the relative MSE and its weights, the targets' own
noise, and rendering a view.  :mod:`neural_brdf.inverse.fit` hands these names on (its
module doc describes the loss and the checks).
"""

from __future__ import annotations

import contextlib
import copy
import os
import re
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neural_brdf import config as cfgmod
from neural_brdf import limits
from neural_brdf.errors import InputError, Interrupted, not_a_file
from neural_brdf.measured.mitsuba import INCLUDE_DEPTH, include_candidates

# Integrators a fit renders with, by the scene's <integrator type>: Mitsuba's C++ ones
# are differentiated by recording their AD graph; "prb" is replaced by "prb_basic" with
# the same properties, since Mitsuba 3.9's prb aborts in evaluated-loop mode (which
# dr.wrap needs): "jit_assemble(): schedule contains variable ... incompatible size".
INTEGRATORS = {
    "path": "path",
    "direct": "direct",
    "prb": "prb_basic",
    "prb_basic": "prb_basic",
    "direct_projective": "direct_projective",
}
VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
FLOAT32_TINY = float(np.finfo(np.float32).tiny)  # 1.18e-38: xml_float
REL_EPS = 1e-2  # the relative MSE's offset (Lehtinen et al. 2018 use 0.01)
TORCH_THREADS = 1  # torch's threads in an image fit (neural_brdf.inverse.fit.fit_neural)
# Bytes a render holds per sample in flight (path state, the AD graph of the gradient
# pass), from above: 1.2 to 1.8 KiB measured (16 x 16 film, 256 and 1024 spp, the
# example's path tracer of depth 3, primal and gradient passes).
LANE_BYTES = 2048


@dataclass
class View:
    """One scene and its target image."""

    scene_path: Path
    image_path: Path
    tree: ET.ElementTree[ET.Element]
    target: np.ndarray  # (H, W, 3) float32, linear RGB
    integrator: str  # the integrator type the fit uses
    scene: Any = None
    params: Any = None
    bsdf: Any = None
    target_tensor: Any = None
    weight_tensor: Any = None
    held_out: bool = False  # the whole view is held out (images.validation_views)
    held_out_pixels: np.ndarray | None = None  # (H, W) bool: ... these of its pixels
    object: np.ndarray | None = None  # (H, W) bool: the object's pixels (None: not found yet)
    # (H, W, 3): the photograph whose light sets the target's noise, a flash/no-flash
    # pair's flash photograph (the target is it minus the other); None: the target
    photograph: np.ndarray | None = None
    label: str = ""  # the target's name in metrics.json ("a.exr - b.exr" for a pair)

    def name(self) -> str:
        """The target's name: ``label``, else the image file's."""
        return self.label or self.image_path.name

    def validation_mask(self) -> np.ndarray | None:
        """(H, W) bool: the view's pixels in the validation split (None: none)."""
        if self.held_out:
            return np.ones(self.target.shape[:2], bool)
        return self.held_out_pixels

    def rel_weight(self) -> np.ndarray:
        """The relative MSE's per-pixel weight (:func:`rel_weight`), from the light the
        pixel's noise follows: the photograph's (a pair's flash photograph, whose noise
        its difference carries even where the flash adds little), else the target's."""
        return rel_weight(self.target if self.photograph is None else self.photograph)

    def fit_weight(self) -> np.ndarray:
        """The relative MSE's per-pixel weight (:meth:`rel_weight`) over the pixels the
        fit sees: held-out pixels weigh 0, the others n / (n - held out), so that the
        loss stays the mean over the fitted pixels."""
        w = self.rel_weight()
        if self.held_out_pixels is None:
            return w
        keep = ~self.held_out_pixels
        return (w * keep[..., None] * (keep.size / keep.sum())).astype(np.float32)


# ------------------------------------------------------------------ Mitsuba set-up
def variant_name(cfg: cfgmod.Config) -> str:
    """``target.variant``, else from ``train.device``: cuda_ad_rgb on CUDA, llvm_ad_rgb."""
    if cfg.target.variant is not None:
        return cfg.target.variant
    device = cfg.train.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return "cuda_ad_rgb" if device == "cuda" else "llvm_ad_rgb"


def start_training(cfg: cfgmod.Config, steps: int, *, poor: bool = False) -> dict[str, Any]:
    """The ``train`` section of a start's distillation into the network (sample-based
    training on the start, :func:`neural_brdf.inverse.starts.distill` and the ``ggx``
    start's): ``steps`` steps at ``images.start_train_lr`` (a ``poor`` start's:
    ``images.poor_start_train_lr``; either null: ``train.lr``) on :data:`TORCH_THREADS`
    threads, one checkpoint, no held-out errors."""
    lr = cfg.images.poor_start_train_lr if poor else cfg.images.start_train_lr
    return {
        **cfg.train.model_dump(),
        "steps": steps,
        "lr": cfg.train.lr if lr is None else lr,
        "threads": TORCH_THREADS,
        "eval_every": 0,
        "checkpoint_every": max(1, steps),
    }


def distillation_config(
    cfg: cfgmod.Config, target: dict[str, Any], name: str, train: dict[str, Any], source: str
) -> cfgmod.Config:
    """The config of a start's distillation into the network (sample-based training on
    ``target``, a teacher's ``target`` section; ``train``: :func:`start_training`): the
    images fit's ``cfg`` with that target, name and ``train`` section, and without its
    ``images`` section (back to the defaults), which no other target reads and parts
    of which are refused without ``target.images`` (``images.validation_views``)."""
    d = cfg.model_dump()
    d.pop("images", None)
    d.update(target=target, name=name, train=train)
    return cfgmod.from_dict(d, source=source)


def variant_key(cfg: cfgmod.Config) -> str:
    """The key that chose :func:`variant_name`'s variant, which its errors name."""
    if cfg.target.variant is not None:
        return "target.variant"
    return f"train.device: {cfg.train.device}, so the variant"


@contextlib.contextmanager
def jit_notes_off(views: list[View]):
    """Dr.Jit's warnings off (its log level Error) while the block runs, where a view
    renders with ``prb_basic``: in the evaluated-loop mode of an image step, Mitsuba 3.9's
    prb_basic makes Dr.Jit warn at every render and every adjoint pass that a virtual
    call inside it runs symbolically (``ad_call("compute_surface_interaction()"):
    currently inside some other symbolic operation, ...``), a note on its own scheduling:
    two lines per view and step, hundreds in a fit, and nothing the user can change."""
    import drjit as dr

    if not any(v.integrator == "prb_basic" for v in views):
        yield
        return
    level = dr.log_level()
    dr.set_log_level(dr.LogLevel.Error)
    try:
        yield
    finally:
        dr.set_log_level(level)


def use_variant(name: str, *, key: str = "target.variant"):
    """Set Mitsuba's variant ``name`` (a JIT AD RGB one) and register ``neural_brdf_ad``;
    returns the ``mitsuba`` module.  A variant this process cannot switch to raises
    InputError naming it and ``key``, the config key that chose it
    (:func:`variant_key`)."""
    if name not in VARIANTS:
        raise InputError(
            f"{key}: {name}: fitting from images needs a JIT AD RGB variant "
            f"({' or '.join(VARIANTS)})"
        )
    if name == "cuda_ad_rgb" and not torch.cuda.is_available():
        fix = "use llvm_ad_rgb" if key == "target.variant" else "set train.device: cpu"
        raise InputError(
            f"{key}: {name}: the network runs in torch on the renderer's arrays, "
            f"and this torch ({torch.__version__}) sees no CUDA GPU ({fix})"
        )
    try:
        import mitsuba as mi
    except ImportError:
        raise InputError(
            "target.images: needs Mitsuba 3 (pip install -e '.[mitsuba]' and libllvm19)"
        ) from None
    if mi.variant() != name:
        import sys

        loaded = sys.modules.get("neural_brdf.inverse.bsdf")
        if loaded is not None:
            raise InputError(
                f"{key}: {name}: this process already renders with {loaded.mi.variant()}"
            )
        try:
            mi.set_variant(name)
        except Exception as e:  # a missing LLVM or CUDA: Mitsuba raises several types
            raise InputError(f"{key}: {name}: not usable here ({str(e).splitlines()[0]})") from None
    from neural_brdf.inverse import bsdf as inverse_bsdf  # noqa: F401  (registers neural_brdf_ad)

    return mi


# ------------------------------------------------------------------ inputs
EXR_MAGIC = b"\x76\x2f\x31\x01"  # every OpenEXR file's first four bytes (its spec)
# the largest pixel an image may hold: the loss squares differences of pixels, and
# float32 holds squares up to 3.4e38, so 1e15 leaves room for the sums and the weights
PIXEL_MAX = 1e15


def check_file(path: Path, key: str, what: str) -> None:
    """InputError naming ``key`` and ``path`` unless ``path`` is a file (``what``: "image",
    "scene")."""
    if not path.is_file():
        raise InputError(f"{key}: {not_a_file(path, what)}")


def check_light(img: np.ndarray, key: str, what: str, fix: str, *, mean: bool = False) -> None:
    """InputError when ``img`` holds no light: its largest value (``mean``: its mean, for
    a flash/no-flash pair's difference, whose noise leaves positive pixels either way)
    is not above 0.  ``what`` names the image in the message, ``fix`` says what to do."""
    value = (float(img.mean()) if mean else float(img.max())) if img.size else 0.0
    if not value > 0.0:
        stat = "mean" if mean else "largest value"
        raise InputError(f"{key}: {what} holds no light ({stat} {value:.3g}); {fix}")


def read_image(path: Path, key: str) -> np.ndarray:
    """A linear RGB EXR -> (H, W, 3) float32; InputError naming the file otherwise."""
    import mitsuba as mi

    check_file(path, key, "image")
    if path.suffix.lower() != ".exr":
        raise InputError(f"{key}: {path}: expected a linear RGB OpenEXR image (.exr)")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as e:
        raise InputError(f"{key}: {path}: unreadable ({e.strerror or e})") from None
    if magic != EXR_MAGIC:  # Mitsuba reads a PNG or a JPEG by its content, whatever its name
        raise InputError(
            f"{key}: {path}: not an OpenEXR file (its first bytes are not EXR's), though "
            "named .exr; give the linear RGB EXR itself"
        )
    try:
        bmp = mi.Bitmap(str(path))
    except Exception as e:  # Mitsuba raises RuntimeError on a bad or truncated file
        raise InputError(
            f"{key}: {path}: unreadable EXR ({str(e).strip().splitlines()[-1][:120]})"
        ) from None
    fmt = bmp.pixel_format()
    if fmt not in (mi.Bitmap.PixelFormat.RGB, mi.Bitmap.PixelFormat.RGBA):
        raise InputError(
            f"{key}: {path}: a {fmt.name} image with {bmp.channel_count()} channel(s); "
            "expected linear RGB"
        )
    img = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
    arr = np.array(img, dtype=np.float32, copy=True).reshape(bmp.height(), bmp.width(), 3)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{key}: {path}: holds NaN or infinite pixels")
    top = float(np.abs(arr).max()) if arr.size else 0.0
    if top > PIXEL_MAX:
        raise InputError(
            f"{key}: {path}: a pixel of {top:.3g}, beyond {PIXEL_MAX:g}: the fit's squared "
            "errors would overflow float32; scale the image (and the scene's lights) down"
        )
    return arr


def negative_pixels(img: np.ndarray, key: str, path: Path) -> str | None:
    """A warning (one line) for an image with negative pixels, or None.  A radiance is
    never negative, but noise about 0 is (a denoiser's output, a frame with the ambient
    light subtracted); the relative loss takes such pixels as they are, so the fit goes on
    and the user is told how many there are and how far below 0 they go."""
    below = (img < 0).any(-1)
    if not below.any():
        return None
    n = int(below.sum())
    return (
        f"{key}: {path}: {n} pixels ({percent(n, below.size)} %) have a negative channel, down to "
        f"{float(img.min()):.3g} (the image's largest value is {float(img.max()):.3g}); "
        "fitted as they are, as noise about 0 (a radiance is never negative)"
    )


def percent(n: int, total: int) -> str:
    """``n`` of ``total`` (0 < n) as a percentage to show: "100", "1.3", "0.012", "< 0.01";
    never "100" for a part, never an exponent."""
    share = 100.0 * n / total
    if share < 0.01:
        return "< 0.01"
    text = f"{share:.1f}".removesuffix(".0") if share >= 1.0 else f"{share:.2g}"
    if n < total and float(text) >= 100.0:
        return "99.9"
    return text


PARAMETER = re.compile(r"(?<!\\)\$(\w*)")  # a $name left after substitution (\$: escaped)


def parse_xml(path: Path, key: str) -> ET.Element:
    """The root element of the XML file ``path``; InputError naming it otherwise."""
    try:
        return ET.parse(path).getroot()
    except (ET.ParseError, OSError, UnicodeDecodeError) as e:
        raise InputError(f"{key}: {path}: not a readable XML scene ({e})") from None


def substitute(el: ET.Element, params: dict[str, str], key: str, scene: Path) -> None:
    """Replace ``$name`` in ``el``'s attributes by ``params`` (the ``<default>``s read so
    far), as Mitsuba does: the longest name first, ``\\$`` escaped (left as it is, for
    Mitsuba to read again); a ``$name`` without a value raises InputError."""
    for attr, value in list(el.attrib.items()):
        if "$" not in value:
            continue
        for name in sorted(params, key=len, reverse=True):
            token, pos = "$" + name, 0
            while (pos := value.find(token, pos)) >= 0:
                if pos > 0 and value[pos - 1] == "\\":
                    pos += len(token)
                else:
                    value = value[:pos] + params[name] + value[pos + len(token) :]
                    pos += len(params[name])
        left = PARAMETER.search(value)
        if left:
            raise InputError(
                f"{key}: {scene}: <{el.tag} {attr}=...>: undefined parameter ${left.group(1)} "
                f'(give <default name="{left.group(1)}" value="..."/> before it)'
            )
        el.set(attr, value)


UPGRADED_BELOW = (2, 0, 0)  # Mitsuba upgrades a file of an older version as it reads it


def _version(text: str) -> tuple[int, ...] | None:
    """(major, minor, patch) of a file's ``version``, else None: Mitsuba 3.9.1 reads
    three numbers and refuses "2.0" and "3.0.0.1" alike ("invalid version number")."""
    parts = text.strip().split(".")
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        return None
    return tuple(int(p) for p in parts)


def check_version(root: ET.Element, path: Path, key: str, scene: Path, version: str | None) -> None:
    """An included file as Mitsuba reads it: its root has a ``version`` (Mitsuba refuses
    one without), and since its elements join the scene file's, whose version alone
    survives, it must be upgraded as that file is: both older than 2.0.0 (Mitsuba then
    renames ``alphaU`` to ``alpha_u`` and the like in each) or neither.  InputError
    otherwise."""
    own = root.get("version")
    where = f"{key}: {scene}: <include> of {path}"
    if own is None:
        raise InputError(f"{where}: missing version attribute in its root <{root.tag}>")
    mine = _version(own)
    if mine is None:
        raise InputError(f'{where}: version="{own}" is not a version such as 3.0.0')
    theirs = _version(version or "")
    if theirs is not None and (mine < UPGRADED_BELOW) != (theirs < UPGRADED_BELOW):
        raise InputError(
            f'{where}: version="{own}" and the scene\'s version="{version}" are read '
            "differently (Mitsuba upgrades a file older than 2.0.0): give the included "
            "file the scene's format and version"
        )


def expand(
    parent: ET.Element,
    params: dict[str, str],
    folders: list[Path],
    key: str,
    scene: Path,
    depth: int = 0,
    version: str | None = None,
) -> None:
    """Read ``parent``'s children as Mitsuba does, in document order: ``$name``
    substituted (:func:`substitute`), a ``<default>`` adding its parameter (unless one of
    that name is set already), an ``<include filename>`` replaced by the included file's
    elements (the children of its ``<scene>``, else its root), read the same way.  An
    included file is looked for in ``folders`` (the including file's folder first, then
    those that included it); at most :data:`INCLUDE_DEPTH` levels.  ``version``: the
    scene file's format version, which an included file's must match
    (:func:`check_version`)."""
    i = 0
    while i < len(parent):
        child = parent[i]
        substitute(child, params, key, scene)
        if child.tag == "default":
            name = child.get("name", "")
            if name and name not in params:
                params[name] = child.get("value", "")
        if child.tag != "include":
            expand(child, params, folders, key, scene, depth, version)
            i += 1
            continue
        filename = child.get("filename", "")
        if depth >= INCLUDE_DEPTH:
            raise InputError(
                f'{key}: {scene}: <include filename="{filename}">: more than {INCLUDE_DEPTH} '
                "nested includes (a file that includes itself?)"
            )
        if not filename.strip():
            raise InputError(f"{key}: {scene}: an <include> without a filename")
        candidates = include_candidates(filename, folders)
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            where = candidates[0]
            what = "is a folder, not a file" if where.is_dir() else "no such file"
            raise InputError(f'{key}: {scene}: <include filename="{filename}">: {where}: {what}')
        root = parse_xml(found, key)
        check_version(root, found, key, scene, version)
        substitute(root, params, key, scene)
        expand(root, params, [found.parent, *folders], key, scene, depth + 1, version)
        if root.tag == "scene":
            new = list(root)
        else:  # a single object, named by the include's name
            root.attrib.pop("version", None)  # (a file's root only: refused inside a scene)
            new = [root]
            if child.get("name"):
                root.set("name", child.get("name", ""))
        if new:
            new[-1].tail = child.tail
        parent[i : i + 1] = new
        i += len(new)


def read_scene(path: Path, key: str) -> tuple[ET.ElementTree[ET.Element], str]:
    """Parse a scene file and check it: (tree, integrator type the fit uses).  The tree
    is the scene as Mitsuba reads it: ``<include>`` files in place and ``$name``
    parameters replaced by their ``<default>`` values (:func:`expand`), so that the
    checks, and the fit's ``<bsdf id="fit">``, see what Mitsuba loads."""
    check_file(path, key, "scene")
    root = parse_xml(path, key)
    substitute(root, {}, key, path)
    expand(root, {}, [path.resolve().parent], key, path, version=root.get("version"))
    tree: ET.ElementTree[ET.Element] = ET.ElementTree(root)
    if root.tag != "scene":
        raise InputError(f"{key}: {path}: not a Mitsuba scene (root <{root.tag}>)")
    fits = [e for e in root.iter("bsdf") if e.get("id") == "fit"]
    if not fits:
        raise InputError(f'{key}: {path}: no <bsdf id="fit"> (the BSDF to fit)')
    if len(fits) > 1:
        raise InputError(f'{key}: {path}: {len(fits)} elements <bsdf id="fit">; expected one')
    if not fit_is_used(root):
        wrapper = _fit_wrapper(root)  # (used through a reference: inside, fit_is_used)
        if wrapper is not None:
            named = f'<bsdf type="{wrapper.get("type", "")}" id="{wrapper.get("id")}">'
            raise InputError(
                f'{key}: {path}: <bsdf id="fit"> is nested in {named}, which a shape '
                "uses: the object's pixels are those whose ray meets a shape whose own "
                'BSDF is the fit; give the shape <ref id="fit"/> itself'
            )
        raise InputError(
            f'{key}: {path}: no <shape> uses <bsdf id="fit"> (refer to it in a shape with '
            '<ref id="fit"/>, or nest it there)'
        )
    for film in root.iter("film"):
        for fmt in film.findall("string"):
            value = (fmt.get("value") or "").strip().lower()
            if fmt.get("name") == "pixel_format" and value != "rgb":
                raise InputError(
                    f"{key}: {path}: the film's pixel_format is {fmt.get('value')!r}; a fit "
                    "compares RGB renders with RGB images: give 'rgb' (the default)"
                )
    integrators = root.findall("integrator")
    kind = integrators[0].get("type", "") if integrators else "path"
    if kind not in INTEGRATORS:
        raise InputError(
            f"{key}: {path}: integrator {kind!r}: a fit renders with {', '.join(INTEGRATORS)}"
        )
    for depth in integrators[0].findall("integer") if integrators else []:
        value = (depth.get("value") or "").strip()
        if depth.get("name") == "max_depth" and value in ("0", "1"):
            # Mitsuba's path length counts the camera ray: 1 sees the emitters alone,
            # so the object renders black and the images never reach the BSDF
            raise InputError(
                f"{key}: {path}: the integrator's max_depth is {value}: it renders no light "
                "reflected by a surface, so the images say nothing of the BSDF; give 2 "
                "(direct light) or more, or -1"
            )
    return tree, INTEGRATORS[kind]


def fit_is_used(root: ET.Element) -> bool:
    """Does a ``<shape>`` use ``<bsdf id="fit">``: a ``<ref id="fit"/>`` inside it (at any
    depth: in a ``twosided``, say), or the BSDF itself nested in it?  Read from the XML:
    ``mi.traverse`` lists a BSDF that no shape uses too (Mitsuba 3.9)."""
    return any(
        e.tag in ("ref", "bsdf") and e.get("id") == "fit"
        for shape in root.iter("shape")
        for e in shape.iter()
    )


def scene_text(
    tree: ET.ElementTree[ET.Element], bsdf: ET.Element, integrator: str | None = None
) -> str:
    """The scene with ``<bsdf id="fit">`` replaced by ``bsdf`` (and the top-level
    integrator's type set to ``integrator``)."""
    tree = copy.deepcopy(tree)
    root = tree.getroot()
    for parent in root.iter():
        for i, child in enumerate(list(parent)):
            if child.tag == "bsdf" and child.get("id") == "fit":
                new = copy.deepcopy(bsdf)
                new.set("id", "fit")
                new.tail = child.tail
                parent[i] = new
    if integrator is not None:
        found = root.findall("integrator")
        if found:
            found[0].set("type", integrator)
        else:
            root.insert(0, ET.Element("integrator", {"type": integrator}))
    return ET.tostring(root, encoding="unicode")


def bsdf_element(kind: str, **props) -> ET.Element:
    """``<bsdf type=kind>`` with typed children: str -> string, float -> float, int ->
    integer, a 3-sequence -> rgb."""
    el = ET.Element("bsdf", {"type": kind})
    for name, value in props.items():
        if isinstance(value, bool):
            ET.SubElement(el, "boolean", {"name": name, "value": str(value).lower()})
        elif isinstance(value, int):
            ET.SubElement(el, "integer", {"name": name, "value": str(value)})
        elif isinstance(value, float):
            ET.SubElement(el, "float", {"name": name, "value": xml_float(value)})
        elif isinstance(value, str):
            ET.SubElement(el, "string", {"name": name, "value": value})
        else:
            text = ", ".join(xml_float(float(v)) for v in value)
            ET.SubElement(el, "rgb", {"name": name, "value": text})
    return el


def xml_float(x: float) -> str:
    """``x`` as Mitsuba's XML parser reads it: its float32 ``stof`` throws on a value
    below float32's smallest normal (a fitted principled's metallic, sin^2 of a tiny
    free variable, reached 1.6e-134), which float32 holds as 0 anyway."""
    return repr(0.0 if abs(x) < FLOAT32_TINY else x)


def load_scene(path: Path, text: str):
    """``mi.load_string`` with the scene's folder on Mitsuba's file resolver (relative
    file names in the scene resolve as ``mi.load_file`` resolves them)."""
    import mitsuba as mi

    fr = mi.file_resolver()  # type: ignore[operator]  # the stub types it as an object
    saved = [fr[i] for i in range(len(fr))]
    fr.prepend(str(path.resolve().parent))
    try:
        return mi.load_string(text)
    except Interrupted:  # Ctrl-C or SIGTERM, the run's own: not the scene's fault
        raise
    except Exception as e:  # Mitsuba reports every load error as a multi-line RuntimeError
        lines = [s.strip() for s in str(e).strip().splitlines() if s.strip()]
        stop = interruption_in(lines[-1] if lines else "")
        if stop is not None:
            raise stop from None
        raise InputError(f"{path}: Mitsuba cannot load it: {lines[-1][:200]}") from None
    finally:
        fr.clear()
        for entry in saved:
            fr.append(entry)


# The last line of the traceback that Mitsuba puts into the RuntimeError it raises when
# Python code it calls (a Python plugin's constructor: neural_brdf_ad) raised: the
# exception's (qualified) name and message
RAISED = re.compile(r"^(?:[\w.]*\.)?(\w+)(?::\s*(.*))?$")


def interruption_in(line: str) -> BaseException | None:
    """The Ctrl-C, SIGTERM or exit that Mitsuba wrapped in a load error whose last line
    is ``line`` (:data:`RAISED`: ``KeyboardInterrupt:``, the CLI's SIGTERM, a
    :class:`~neural_brdf.errors.Interrupted`, ``SystemExit``), raised again as such;
    None for any other error."""
    import signal

    m = RAISED.match(line.strip())
    if m is None:
        return None
    name, message = m.group(1), (m.group(2) or "").strip()
    if name == "Interrupted":
        return Interrupted(message or "interrupted")
    if name == "SystemExit":
        return SystemExit(int(message) if message.lstrip("-").isdigit() else message or None)
    if name not in ("KeyboardInterrupt", "_Terminated"):
        return None
    e = KeyboardInterrupt(message)
    if name == "_Terminated":  # the CLI's SIGTERM (a KeyboardInterrupt): exit code 143
        e.signum = signal.SIGTERM  # type: ignore[attr-defined]
    return e


def film_size(scene) -> tuple[int, int]:
    """(height, width) of the first sensor's film (its crop window)."""
    w, h = scene.sensors()[0].film().crop_size()
    return int(h), int(w)


def read_photograph(path: Path, key: str, *, lit: bool = False) -> np.ndarray:
    """:func:`read_image`, and a one-line warning on stderr when it has negative pixels
    (:func:`negative_pixels`).  ``lit``: the image must hold light
    (:func:`check_light`; a photograph without the flash may be black)."""
    img = read_image(path, key)
    if lit:
        check_light(
            img,
            key,
            str(path),
            "a target is a photograph of the lit object (an all-black or all-negative "
            "image: the wrong file, or its exposure)",
        )
    warning = negative_pixels(img, key, path)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    return img


def read_views(cfg: cfgmod.Config) -> list[View]:
    """Parse and check every ``target.images`` entry (scenes are loaded later)."""
    views = []
    seen: dict[tuple[Any, Any, Any], int] = {}
    images: dict[Any, tuple[int, Any]] = {}  # an image's file -> (its entry, its scene's)
    entries = cfg.target.images or []
    for k, item in enumerate(entries):
        key = f"target.images[{k}]"
        for field, value in (("scene", item.scene), ("image", item.image)):
            if not value.strip():
                raise InputError(f"{key}.{field}: empty; give the {field} file's path")
        if item.subtract is not None and not item.subtract.strip():
            raise InputError(
                f"{key}.subtract: empty; give the photograph without the flash, or leave "
                "subtract out"
            )
        scene_path, image_path = Path(item.scene), Path(item.image)
        same = (
            file_identity(item.scene),
            file_identity(item.image),
            item.subtract and file_identity(item.subtract),
        )
        if same in seen:  # it would weigh twice in every loss
            raise InputError(
                f"{key}: the same scene and image as target.images[{seen[same]}]; list "
                "each view once"
            )
        seen[same] = k
        first, its_scene = images.setdefault(same[1], (k, same[0]))
        if its_scene != same[0]:  # a copy-paste slip: one camera's photograph for another's
            raise InputError(
                f"{key}.image: {image_path}: also the image of target.images[{first}], whose "
                f"scene is another ({Path(entries[first].scene).name}, here "
                f"{scene_path.name}); a photograph is one camera's view: give each scene its own"
            )
        tree, integrator = read_scene(scene_path, key + ".scene")
        target = read_photograph(image_path, key + ".image", lit=True)
        photograph = None
        if item.subtract is not None:  # a flash/no-flash pair: the flash's light alone
            other = Path(item.subtract)
            ambient = read_photograph(other, key + ".subtract")
            if ambient.shape != target.shape:
                raise InputError(
                    f"{key}.subtract: {other}: {ambient.shape[1]}x{ambient.shape[0]} pixels, "
                    f"but its image {image_path.name} is {target.shape[1]}x{target.shape[0]}"
                )
            photograph, target = target, target - ambient
            check_light(  # swapped, or the same photograph twice
                target,
                key + ".subtract",
                f"{other}: {image_path.name} - {other.name}",
                "image is the photograph with the flash, subtract the one without",
                mean=True,
            )
        view = View(scene_path, image_path, tree, target, integrator)
        view.photograph, view.label = photograph, item.label()
        views.append(view)
    if not views:
        raise InputError("target.images: empty; give at least one {scene, image} pair")
    return views


def file_identity(path: str) -> Any:
    """What makes two paths the same file: (device, inode) of an existing one (a link or
    another spelling of it too), else its resolved path."""
    try:
        st = os.stat(path)
    except OSError:
        return os.path.realpath(path)
    return (st.st_dev, st.st_ino)


def split_views(views: list[View], images: cfgmod.Images, seed: int) -> None:
    """Mark the validation split on ``views``: the views ``images.validation_views``
    whole, and in every other view a share ``images.validation_pixels`` of its tiles of
    ``images.validation_block`` x ``validation_block`` pixels (rounded, at least one,
    never all), drawn without repetition from ``seed`` and the view's index alone (a
    view added leaves the others' masks as they were).  Tiles rather than single pixels:
    a held-out pixel then mostly has held-out neighbours, which see nearly the same
    pairs (wi, wo), so the split measures how the fit does on directions it did not see;
    the choice of a start (:func:`neural_brdf.inverse.starts.pick`) takes the tiles as
    its independent units."""
    share, block = images.validation_pixels, images.validation_block
    for k, v in enumerate(views):
        v.held_out, v.held_out_pixels = k in images.validation_views, None
        if v.held_out or share <= 0:
            continue
        tile = tiles(v.target.shape, block)
        n = int(tile.max()) + 1
        if n < 2:
            h, w = v.target.shape[:2]
            fix = (
                "give a smaller block"
                if block > 1
                else "hold out whole views (images.validation_views) or none "
                "(images.validation_pixels: 0)"
            )
            raise InputError(
                f"images.validation_pixels: {v.image_path} ({w}x{h} pixels) is one tile of "
                f"images.validation_block={block}; it cannot be split ({fix})"
            )
        m = min(max(round(share * n), 1), n - 1)
        chosen = np.random.default_rng([seed, 29, k]).choice(n, size=m, replace=False)
        v.held_out_pixels = np.isin(tile, chosen)


def tiles(shape: tuple[int, ...], block: int) -> np.ndarray:
    """(H, W) int: the index of each pixel's ``block`` x ``block`` tile, row-major."""
    h, w = shape[:2]
    across = (w + block - 1) // block
    return (np.arange(h)[:, None] // block) * across + np.arange(w)[None, :] // block


def fitted_views(views: list[View]) -> list[View]:
    """The views the fit renders (those not held out whole)."""
    return [v for v in views if not v.held_out]


def check_films(views: list[View]) -> None:
    """Load every scene as it is (its own fit BSDF) and check that something uses the
    fit BSDF and that the target image has the film's size."""
    for v in views:
        scene = load_scene(v.scene_path, scene_text(v.tree, fit_element(v.tree)))
        if fit_bsdf(scene) is None:
            raise InputError(f'{v.scene_path}: no shape uses <bsdf id="fit">')
        check_seen(scene, v.scene_path)
        sensors = scene.sensors()
        if len(sensors) > 1:  # mi.render's default, as its image was rendered
            print(
                f"warning: {v.scene_path}: {len(sensors)} sensors; the fit renders "
                "the first (scene.sensors()[0]), as mi.render does by default: its image must "
                "be that camera's view",
                file=sys.stderr,
            )
        channels = sensors[0].film().base_channels_count()
        if channels != 3:
            raise InputError(
                f"{v.scene_path}: the film renders {channels} channel(s); a fit compares RGB "
                "renders with RGB images (an hdrfilm with pixel_format 'rgb')"
            )
        check_size(v, scene)


def check_seen(scene, path: Path) -> None:
    """InputError naming ``path`` when the loaded ``scene`` has no camera or no emitter
    (what every view needs; :func:`check_films`, and the coverage before its rays)."""
    if not scene.sensors():
        raise InputError(f"{path}: no <sensor>: a view needs its camera")
    if not scene.emitters():
        raise InputError(
            f"{path}: no emitter (no <emitter>, no emissive shape): nothing "
            "lights the object, so its image holds nothing of its BRDF"
        )


def check_render_sizes(views: list[View], images: cfgmod.Images) -> None:
    """limits.TooLarge naming the ``images`` key whose samples per pixel would make one
    render of the largest film hold more than the memory budget (:data:`LANE_BYTES` a
    sample): the image stage's, its held-out scorings' and the start's fits'."""
    h, w = max((v.target.shape[:2] for v in views), key=lambda s: s[0] * s[1])
    # (key, renders of that many samples per pixel: the refinement's primal pass has twice)
    for key, times in (
        ("spp", 1),
        ("primal_spp", 1),
        ("validation_spp", 1),
        ("start_spp", 1),
        ("start_primal_spp", 1),
        ("start_refine_spp", 2),
    ):
        spp = getattr(images, key)
        limits.check_bytes(
            f"images.{key}",
            float(h * w) * spp * times * LANE_BYTES,
            hint=f"give fewer samples per pixel (the largest film is {w}x{h})",
        )


def check_size(view: View, scene) -> None:
    h, w = film_size(scene)
    if view.target.shape[:2] != (h, w):
        th, tw = view.target.shape[:2]
        raise InputError(
            f"{view.image_path}: {tw}x{th} pixels, but the film of {view.scene_path} is {w}x{h}"
        )


# ------------------------------------------------------------------ losses
def relative_mse(img, target, weight):
    """The relative MSE of HDR images (module doc); ``weight`` = 1 / (y_bar^2 + eps)."""
    import drjit as dr

    d = img - target
    return dr.mean(d * d * weight, axis=None)


def rel_weight(target: np.ndarray) -> np.ndarray:
    y = target.mean(-1, keepdims=True)
    return np.broadcast_to(1.0 / (y * y + REL_EPS), target.shape).astype(np.float32)


# The targets' noise (target_noise): the residual of a pixel against the mean of its four
# neighbours, whose variance is 1.25 sigma^2 for independent pixels; the smallest
# NOISE_KEEP of the pixels' weighted squares are averaged (the rest are edges and
# highlights, signal rather than noise), and NOISE_SCALE makes that mean the noise's own
# relative variance for Mitsuba's default film (the Gaussian reconstruction filter
# correlates neighbours, the trim drops the tail): fitted on the development set's
# targets against a second render of each with another seed: 0.75 to 1.13 times the
# second render's figure on 9 of the 10 sets of views (five materials, under an
# environment and under point and area lights), 9.4 times high on the one whose views
# hold sharp anisotropic highlights, which only makes a start look better than it is
# (the test set's, held out: benchmarks/target_noise.py).  For independent pixel noise
# (a box filter) the same estimate is about 2.75 times high.
NOISE_KEEP = 0.95

NOISE_SCALE = 3.0


def is_poor(loss: float | None, limit: float | None, noise: float | None) -> bool:
    """:func:`poor_start`'s verdict alone: a held-out ``loss`` above the targets' ``noise``
    (0 when None) by more than ``limit`` (None: never poor)."""
    if limit is None or loss is None:
        return False
    return bool(float(loss) - (noise or 0.0) > limit)


def target_noise(views: list[View]) -> float | None:
    """An estimate, from the target images alone, of the part of a held-out loss (the
    relative MSE, :func:`rel_weight`) that the targets' own noise sets: a model that
    renders the true material scores about this, not 0.  Over the object's pixels
    (``view.object``, eroded by one pixel so that every neighbour is on the object) of
    the views the fit renders, the run's held-out pixels left out; None without any.
    See :data:`NOISE_SCALE` for how it is made and how far to trust it."""
    terms = []
    for v in fitted_views(views):
        if v.object is None:
            continue
        obj = np.pad(v.object, 1, constant_values=False)
        inner = v.object & obj[:-2, 1:-1] & obj[2:, 1:-1] & obj[1:-1, :-2] & obj[1:-1, 2:]
        if v.held_out_pixels is not None:
            inner &= ~v.held_out_pixels
        if not inner.any():
            continue
        y = v.target.astype(np.float64)
        mean4 = np.zeros_like(y)  # edge-padded neighbours: only inner pixels are read
        pad = np.pad(y, ((1, 1), (1, 1), (0, 0)), mode="edge")
        for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
            mean4 += pad[dy : dy + y.shape[0], dx : dx + y.shape[1]] / 4.0
        q = v.rel_weight() * (y - mean4) ** 2 / 1.25
        terms.append(q[inner].ravel())
    if not terms:
        return None
    q = np.sort(np.concatenate(terms))
    kept = q[: max(1, int(NOISE_KEEP * q.size))]
    return float(NOISE_SCALE * kept.mean())


def fit_bsdf(scene):
    """The scene's ``<bsdf id="fit">`` object, or None when nothing references it."""
    import mitsuba as mi

    nodes = mi.traverse(scene).hierarchy
    return next((n for n in nodes if isinstance(n, mi.BSDF) and n.id() == "fit"), None)


def prepare_views(views: list[View], bsdf: ET.Element) -> None:
    """Load every view's scene with ``bsdf`` as ``<bsdf id="fit">`` and check its film
    size; ``view.params`` are that BSDF's own parameters (``mi.traverse(bsdf)``)."""
    import mitsuba as mi

    for v in views:
        v.scene = load_scene(v.scene_path, scene_text(v.tree, bsdf, v.integrator))
        check_size(v, v.scene)
        v.bsdf = fit_bsdf(v.scene)
        if v.bsdf is None:
            raise InputError(f'{v.scene_path}: no shape uses <bsdf id="fit">')
        v.params = mi.traverse(v.bsdf)
        v.target_tensor = mi.TensorXf(v.target)
        v.weight_tensor = mi.TensorXf(v.fit_weight())


# ------------------------------------------------------------------ rendering a view
def fit_element(tree: ET.ElementTree[ET.Element]) -> ET.Element:
    """The scene's own ``<bsdf id="fit">`` (e.g. the true material of a synthetic view)."""
    return next(e for e in tree.getroot().iter("bsdf") if e.get("id") == "fit")


def render_view(view: View, bsdf: ET.Element, *, spp: int, seed: int) -> np.ndarray:
    """Render ``view``'s scene as it is, with ``bsdf`` as ``<bsdf id="fit">`` (its own
    integrator, Mitsuba's symbolic mode): (H, W, 3) float32."""
    import mitsuba as mi

    scene = load_scene(view.scene_path, scene_text(view.tree, bsdf))
    img = mi.render(scene, spp=spp, seed=seed)  # type: ignore[arg-type]  # stub: mi.UInt32
    return np.asarray(img, dtype=np.float32)[..., :3]


FILTER_REACH = 2  # pixels: how far the film's default (Gaussian) filter reaches


def sphere_mask(view: View, erode: int | None = None) -> np.ndarray:
    """(H, W) bool: pixels whose centre ray hits a shape with ``<bsdf id="fit">``, and
    whose neighbours within ``erode`` pixels do too (None: as far as the film's filter
    reaches, :func:`fit_hits`), so that no background enters a pixel of the mask."""
    hit, _, reach = fit_hits(view)
    return eroded(hit, reach if erode is None else erode)


def fit_hits(view: View) -> tuple[np.ndarray, np.ndarray, int]:
    """(hit, front, reach): (H, W) bool each, the pixels whose centre ray hits a shape
    with ``<bsdf id="fit">`` (the scene's own, from ``view.tree``), and those of them
    where it meets the front of the surface (the side the fitted BSDF, one-sided,
    reflects on); and the pixels the film's reconstruction filter reaches beyond its
    own (its border size: :data:`FILTER_REACH` for Mitsuba's default Gaussian, 0 for a
    box, 6 for a Gaussian of stddev 1.5, whose splats a fixed 2 left in the object's
    outline)."""
    import mitsuba as mi

    scene = load_scene(view.scene_path, scene_text(view.tree, fit_element(view.tree)))
    reach = int(scene.sensors()[0].film().rfilter().border_size())
    h, w = film_size(scene)
    idx = np.arange(h * w)
    pos = mi.Point2f(((idx % w) + 0.5) / w, ((idx // w) + 0.5) / h)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    hit = si.is_valid() & (si.bsdf() == mi.BSDFPtr(fit_bsdf(scene)))
    front = hit & (mi.Frame3f.cos_theta(si.wi) > 0.0)
    return (
        np.asarray(hit.numpy(), dtype=bool).reshape(h, w),
        np.asarray(front.numpy(), dtype=bool).reshape(h, w),
        reach,
    )


def eroded(mask: np.ndarray, erode: int) -> np.ndarray:
    """``mask``'s pixels whose neighbours within ``erode`` pixels (a square) are in it too."""
    h, w = mask.shape
    out = mask.copy()
    for dy in range(-erode, erode + 1):
        for dx in range(-erode, erode + 1):
            shifted = np.zeros_like(mask)
            ys, xs = slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0))
            yd, xd = slice(max(-dy, 0), h + min(-dy, 0)), slice(max(-dx, 0), w + min(-dx, 0))
            shifted[yd, xd] = mask[ys, xs]
            out &= shifted
    return out


def check_sees_object(view: View, key: str, hit: np.ndarray, front: np.ndarray) -> None:
    """InputError naming ``key`` (``target.images[k].scene``) and the scene when the
    view sees no pixel of the fitted object: no pixel's centre ray meets the front of a
    shape that uses ``<bsdf id="fit">`` (``hit``, ``front``: :func:`fit_hits`).  Such a
    view renders nothing of the BRDF: its camera looks away, sits inside the object or
    behind something that hides it (its target would still weigh in the loss and the
    noise estimate)."""
    if front.any():
        return
    fix = "fix its <sensor>, or leave the view out"
    outer = None if hit.any() else _fit_wrapper(view.tree.getroot())
    wrapper = None if outer is None else outer.get("type", "")
    if hit.any():
        why = (
            f"its camera sees only the back of the surface ({int(hit.sum())} pixels), as "
            f"from inside the object; {fix}"
        )
    elif wrapper is not None:
        why = (
            f'<bsdf id="fit"> is nested in a <bsdf type="{wrapper}">, and the object\'s '
            "pixels are those whose ray meets a shape whose own BSDF is the fit; give the "
            'shape <ref id="fit"/> itself'
        )
    else:
        why = (
            'no pixel\'s centre ray meets a shape that uses <bsdf id="fit"> (the camera '
            f"looks away from the object, or something hides it); {fix}"
        )
    raise InputError(
        f"{key}: {view.scene_path}: the view sees no pixel of the fitted object: {why}"
    )


def _fit_wrapper(root: ET.Element) -> ET.Element | None:
    """A ``<bsdf>`` that holds ``<bsdf id="fit">`` (or ``<ref id="fit"/>``) below it (a
    ``twosided``, say) and that a shape uses, nested in the shape or referred to by it
    (``<ref id="X"/>``), else None."""
    used = {e.get("id") for shape in root.iter("shape") for e in shape.iter("ref")}
    nested = [b for shape in root.iter("shape") for b in shape.iter("bsdf")]
    others = [b for b in root.iter("bsdf") if b.get("id") is not None and b.get("id") in used]
    for outer in nested + others:
        if outer.get("id") == "fit":
            continue
        if any(e.get("id") == "fit" for e in outer.iter() if e is not outer):
            return outer
    return None


def bsdf_text(bsdf: ET.Element) -> str:
    """The XML of a standalone Mitsuba BSDF from its element (its ``id`` dropped)."""
    el = copy.deepcopy(bsdf)
    el.attrib.pop("id", None)
    return '<bsdf version="3.0.0"' + ET.tostring(el, encoding="unicode")[len("<bsdf") :]


def mitsuba_bsdf(bsdf: ET.Element):
    """A standalone Mitsuba BSDF from its XML element."""
    import mitsuba as mi

    return mi.load_string(bsdf_text(bsdf))


def mitsuba_f_cos(bsdf, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """f cos(theta_o) of a Mitsuba BSDF at local directions (N, 3) -> (N, 3)."""
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*(np.ascontiguousarray(wi[:, j], np.float32) for j in range(3)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
    wo_ = mi.Vector3f(*(np.ascontiguousarray(wo[:, j], np.float32) for j in range(3)))
    value = bsdf.eval(mi.BSDFContext(), si, wo_)
    return np.stack([np.asarray(value[j].numpy(), np.float64) for j in range(3)], -1)
