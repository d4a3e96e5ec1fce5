#!/usr/bin/env bash
# Build the wheel, install it into a fresh virtual environment and use it from an empty
# folder: `neural-brdf --version`, `neural-brdf presets`, a short `neural-brdf train
# quickstart` (exit 0, model.onnx written), the ONNX producer fields, the light import
# path (no torch for neural_brdf.load), then an editable install of the same tree.
#
#   .ci/wheel_check.sh                 # from the repository root; PYTHON=python3 by default
#
# Needs network (or a local index) for pip: torch==2.13.0 (the CPU build) is installed
# first so that resolving the wheel's dependencies pulls no CUDA build.
set -euo pipefail

PYTHON=${PYTHON:-python3}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
START=$(date +%s)
step() { echo "== wheel_check: $* ($(( $(date +%s) - START )) s)"; }
fail() { echo "wheel_check: FAILED: $*" >&2; exit 1; }
quiet() { "$@" > "$TMP/log.txt" 2>&1 || { cat "$TMP/log.txt"; fail "$*"; }; }   # pip chatter

step "copy the working tree (tracked and untracked, not ignored files)"
mkdir "$TMP/src"
(cd "$ROOT" && git ls-files -co --exclude-standard -z | tar --null -cf - -T -) \
    | tar -xf - -C "$TMP/src"

step "build the wheel"
quiet "$PYTHON" -m pip wheel --no-deps --wheel-dir "$TMP/dist" "$TMP/src"
WHEEL=$(ls "$TMP"/dist/neural_brdf-*.whl)
echo "$WHEEL"
"$PYTHON" - "$WHEEL" <<'PY'
import sys, zipfile
names = zipfile.ZipFile(sys.argv[1]).namelist()
need = ["neural_brdf/configs/gold.yaml", "neural_brdf/configs/quickstart.yaml",
        "neural_brdf/configs/defaults.yaml", "neural_brdf/configs/sweeps/furnace.yaml",
        "neural_brdf/py.typed", "analytic/py.typed", "analytic/data/"]
missing = [n for n in need if not any(x.startswith(n) for x in names)]
missing += [] if any(x.endswith(".dist-info/licenses/LICENSE") for x in names) else ["LICENSE"]
stray = [x for x in names if x.split("/")[0] in ("configs", "tests", "benchmarks")]
if missing or stray:
    sys.exit(f"wheel: missing {missing}, stray top-level files {stray[:5]}")
print(f"wheel: {len(names)} files, presets and py.typed inside")
PY

step "fresh venv: torch (CPU) first, then the wheel"
"$PYTHON" -m venv "$TMP/venv"
PY="$TMP/venv/bin/python"
quiet "$PY" -m pip install torch==2.13.0
quiet "$PY" -m pip install "$WHEEL"
NB="$TMP/venv/bin/neural-brdf"

step "use it from an empty folder"
mkdir "$TMP/work"
cd "$TMP/work"
unset PYTHONPATH
VERSION=$("$PY" -c 'import importlib.metadata as m; print(m.version("neural-brdf"))')
[ "$("$NB" --version)" = "neural-brdf $VERSION" ] || fail "--version is not $VERSION"
"$NB" --help > /dev/null
"$NB" presets | tee presets.txt
grep -q '^gold ' presets.txt && grep -q '^quickstart ' presets.txt || fail "presets list"
set +e
"$NB" train no_such_preset 2> err.txt; code=$?
set -e
[ "$code" = 2 ] && grep -q "no_such_preset" err.txt || fail "unknown preset: exit $code"

"$NB" train quickstart --out run \
    --set train.steps=60 --set train.progress=false --set model.hidden=[16,16] \
    --set data.batch_size=256 --set data.pool_size=2048 \
    --set normalization.table_size=17 --set normalization.samples=2048 \
    --set validation.furnace_dirs=6 --set validation.furnace_samples=4096 \
    --set validation.pairs=2000 --set validation.accuracy_samples=2048 \
    --set export.parity_pairs=512 || fail "train quickstart: exit $?"
[ -f run/model.onnx ] && [ -f run/metrics.json ] || fail "no run/model.onnx"
set +e
"$NB" train quickstart --out run 2> err.txt; code=$?
set -e
[ "$code" = 2 ] && grep -q -- "--overwrite" err.txt || fail "retrain over a finished run: exit $code"

"$PY" - "$VERSION" <<'PY'
import sys
import numpy as np
import neural_brdf
f = neural_brdf.load("run/model.onnx").eval(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.6, 0.8]))
assert f.shape == (3,) and np.all(np.isfinite(f)) and np.all(f > 0), f
heavy = [m for m in ("torch", "pydantic", "matplotlib") if m in sys.modules]
assert not heavy, f"neural_brdf.load imported {heavy}"
import onnx
proto = onnx.load("run/model.onnx")
assert proto.producer_name == "neural-brdf", proto.producer_name
assert proto.producer_version == sys.argv[1], proto.producer_version
assert proto.model_version >= 1 and proto.doc_string, "model_version / doc_string"
print(f"installed wheel: f = {f}, producer {proto.producer_name} {proto.producer_version}")
PY

step "editable install of the same tree"
quiet "$PY" -m pip install --no-deps -e "$TMP/src"
"$PY" - "$TMP/src" <<'PY'
import sys
from importlib.resources import files
from pathlib import Path
from neural_brdf import presets
assert files("neural_brdf.configs").joinpath("gold.yaml").is_file(), "editable resources"
assert presets.directory().resolve() == (Path(sys.argv[1]) / "configs").resolve(), \
    presets.directory()
print(f"editable: presets from {presets.directory()}")
PY
"$NB" presets > /dev/null

step "OK"
echo "wheel_check: passed in $(( $(date +%s) - START )) s"
