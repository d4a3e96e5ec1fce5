"""What a retro-reflective lobe shows each camera of benchmarks/images_any.py: the light
behind it.

    python benchmarks/images_behind_cameras.py      # a few seconds

A retroreflector sends light back where it came from, so under an environment a camera
sees, on every pixel, the environment around its own direction (seen from the object)
weighted by the lobe, on top of the diffuse term.  For each set's environments and each
camera of :data:`neural_brdf.inverse.scene.VIEWS` (three fitted, the fourth held out),
this measures the environment's mean radiance (RGB mean) in rings of angle around the
direction from the object to the camera, through Mitsuba's own ``envmap`` emitter as the
benchmark's scenes load it (so the map's orientation is Mitsuba's), and the mean under
the test set's retroreflector's lobe, cos^20 of that angle
(``analytic/retroreflective.py``).  It explains which parts of the lobe each view holds
(docs/inverse.md, Limits); it fits nothing.  Writes
benchmarks/results/images_behind_cameras.json.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "benchmarks"):  # run from a checkout without `pip install -e .`
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import numpy as np  # noqa: E402
from common import write_json  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
RINGS = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 45.0), (45.0, 90.0))  # degrees
EXPONENT = 20.0  # the test set's retroreflector (benchmarks/images_any.py)
DIRECTIONS = 1 << 20  # uniform directions on the sphere, one draw for every camera


def radiance_fn(env_path: Path):
    """Directions (N, 3) in world space -> the envmap's radiance (N, 3), as loaded by
    Mitsuba in the benchmark's scenes."""
    import drjit as dr
    import mitsuba as mi

    from neural_brdf.inverse import scene

    text = scene.scene_xml(0.0, 0.0, resolution=8, envmap=str(env_path))
    emitter = next(iter(mi.load_string(text).emitters()))

    def radiance(v: np.ndarray) -> np.ndarray:
        si = dr.zeros(mi.SurfaceInteraction3f, len(v))
        si.wi = mi.Vector3f(*(-v.T.astype(np.float32)))  # envmap.eval reads -si.wi
        value = emitter.eval(si)
        return np.stack([np.asarray(value.x), np.asarray(value.y), np.asarray(value.z)], -1)

    return radiance


def behind(radiance, directions: np.ndarray, camera: np.ndarray) -> dict:
    """The radiance around ``camera`` (unit): mean per ring and under cos^EXPONENT."""
    cos = np.clip(directions @ camera, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    lum = radiance(directions).mean(-1)
    lobe = np.clip(cos, 0.0, None) ** EXPONENT
    return {
        "rings": {
            f"{lo:g}-{hi:g}": float(lum[(angle >= lo) & (angle < hi)].mean()) for lo, hi in RINGS
        },
        "under_lobe": float((lobe * lum).sum() / lobe.sum()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=RESULTS / "images_behind_cameras.json")
    args = ap.parse_args(argv)

    import images_any
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from neural_brdf.inverse import scene

    rng = np.random.default_rng(0)
    directions = rng.normal(size=(DIRECTIONS, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    out: dict = {
        "benchmark": "images_behind_cameras",
        "rings_degrees": [list(r) for r in RINGS],
        "exponent": EXPONENT,
        "directions": DIRECTIONS,
        "views": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        for which, envs in images_any.SETS.items():
            for role, name in envs.items():
                path = Path(tmp) / f"{name}.exr"
                scene.write_exr(path, images_any.environment(name))
                radiance = radiance_fn(path)
                cams = {}
                for k, (az, el) in enumerate(scene.VIEWS):
                    label = f"view{k + 1}" if k < 3 else "heldout"
                    cams[label] = behind(radiance, directions, np.array(scene.direction(az, el)))
                out["views"][name] = {"set": which, "role": role, "cameras": cams}
    out["date"] = datetime.datetime.now().isoformat(timespec="seconds")
    out["machine"] = {"platform": platform.platform(), "mitsuba": mi.__version__}
    write_json(args.out, out)
    for name, entry in out["views"].items():
        for label, c in entry["cameras"].items():
            rings = ", ".join(f"{k}: {v:.2f}" for k, v in c["rings"].items())
            print(f"{name:8s} {label:8s} under the lobe {c['under_lobe']:.3f}  ({rings})")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
