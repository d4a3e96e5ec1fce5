"""Helpers of the command-line tests (tests/tooling/test_cli.py and the tests of other
parts that drive the CLI): a tiny training config, a real subprocess, the in-process CLI
and the one-line-error check."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from neural_brdf.tooling.cli import main

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "train.steps=10",
    "train.progress=false",
    "model.hidden=[16,16]",
    "data.batch_size=256",
    "data.pool_size=2048",
    "normalization.table_size=17",
    "normalization.samples=2048",
    "validation.furnace_dirs=6",
    "validation.furnace_samples=4096",
    "validation.pairs=2000",
    "validation.accuracy_samples=2048",
    "export.parity_pairs=512",
]
SETS = [a for kv in TINY for a in ("--set", kv)]


def run(*args, cwd=ROOT):
    """A real subprocess: checks that no traceback escapes and the exit status is real."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def into_closed_pipe(*args) -> tuple[int, str]:
    """``neural-brdf ARGS | head -0`` in a subprocess: the reader of stdout is gone
    before the first byte is written; (exit code, stderr)."""
    with subprocess.Popen(
        [sys.executable, "-m", "neural_brdf.tooling.cli", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    ) as proc:
        proc.stdout.close()
        err = proc.stderr.read().decode()
        return proc.wait(timeout=120), err


def cli(capsys, *args):
    """In-process ``neural-brdf ARGS`` (fast): (exit code, stdout, stderr)."""
    code = main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


def assert_one_line_error(code, err, *needles):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], lines[0]
