"""The exceptions the command line maps to exit codes, in a module with no heavy imports.

    from neural_brdf.errors import InputError          # == neural_brdf.config.InputError
    raise InputError("train.steps: must be >= 0")      # -> one line on stderr, exit code 2

``runtime`` (onnxruntime only), ``cli`` and the light entry points import from here so
that evaluating an ONNX file or printing ``neural-brdf --help`` never loads torch or
pydantic.  ``config``, ``train`` and ``export`` re-export these same classes.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad input from the user (a file, a path, a value).  The message is one line and
    names the offending key or file; the CLI prints it and exits with code 2."""


class ConfigError(InputError):
    """A config file or override is invalid."""


class Diverged(RuntimeError):
    """The loss or the weights became NaN/inf (exit code 1)."""


class Interrupted(RuntimeError):
    """Ctrl-C: a checkpoint was written; ``--resume`` continues (exit code 130)."""

    signum: int | None = None  # the signal (SIGINT, SIGTERM): the CLI exits with 128 + it


class ParityError(RuntimeError):
    """onnxruntime does not reproduce the torch model to ``export.parity_tol`` (exit 1)."""


def module_parser(module: str, description: str):
    """The argument parser of a ``python -m MODULE`` tool: its usage names that command,
    and a bad argument is one line on stderr, ``error: python -m MODULE: ... (see
    --help)``, with exit code 2, as the ``neural-brdf`` command's."""
    import argparse

    class Parser(argparse.ArgumentParser):
        def error(self, message):
            self.exit(2, f"error: {self.prog}: {message} (see --help)\n")

    return Parser(prog=f"python -m {module}", description=description)


def not_a_file(path, what: str) -> str:
    """The message for a ``what`` file (``"model"``, ``"image"``, ...) given as ``path``,
    which is no file: a folder, or nothing at all."""
    from pathlib import Path

    if Path(path).is_dir():
        return f"{path}: is a folder, not a file (give the {what} file)"
    if Path(path).exists():  # /dev/stdin, /dev/null, a FIFO: read whole, it must be a file
        return f"{path}: not a regular file (a device or a pipe; give the {what} file)"
    return f"{path}: no such {what} file"
