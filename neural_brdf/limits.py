"""Limits on what a user's input may make the program allocate or print.

    from neural_brdf import limits
    limits.check_bytes("data.pool_size", 2**40 * 36)   # InputError before the allocation
    limits.bounded(message)                             # at most MAX_MESSAGE characters

Every size that comes from a config, a graph or a data file is checked against
:func:`memory_budget` *before* anything is allocated, so that a typo (``pool_size:
2621440000``) or a hostile file (an ONNX ``ConstantOfShape`` of 256 GiB) gives one line
naming the key or the file and exit code 2, not an allocator traceback or the kernel's
out-of-memory killer.  docs/cli.md states the limits:

* an error message is at most ``MAX_MESSAGE`` (1,000) characters: longer texts (a value
  echoed back from a YAML alias bomb) are cut in the middle;
* a config expands to at most ``MAX_CONFIG_NODES`` (100,000) YAML nodes, counted as
  Python sees them (an alias counts each time it is used), and its file is at most
  ``MAX_CONFIG_BYTES`` (1 MiB);
* one tensor or buffer may take at most ``MEMORY_SHARE`` (a half) of this machine's
  physical memory; ``NEURAL_BRDF_MEMORY_LIMIT`` (bytes, or with a K/M/G/T suffix) sets
  another budget, below or above.

This module imports nothing heavy (the CLI's error path uses it).
"""

from __future__ import annotations

import math
import os

from neural_brdf.errors import InputError

MAX_MESSAGE = 1000
MAX_CONFIG_NODES = 100_000
MAX_CONFIG_BYTES = 1 << 20
MEMORY_SHARE = 0.5
ENV_LIMIT = "NEURAL_BRDF_MEMORY_LIMIT"
_SUFFIXES = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


class TooLarge(InputError):
    """A size from the user's input exceeds a stated limit (exit code 2)."""


def bounded(text: str, limit: int = MAX_MESSAGE) -> str:
    """``text`` on one line of at most ``limit`` characters, cut in the middle (the
    start names the key or file, the end often says what was expected)."""
    text = " ".join(text.split("\n"))
    if len(text) <= limit:
        return text
    cut = " [...] "
    head = (limit - len(cut)) * 2 // 3
    tail = limit - len(cut) - head
    return text[:head] + cut + text[-tail:]


def physical_memory() -> int | None:
    """This machine's physical memory in bytes (None where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def memory_budget() -> int:
    """The most bytes one tensor or buffer may take: ``NEURAL_BRDF_MEMORY_LIMIT`` if set,
    else MEMORY_SHARE of the physical memory (8 GiB where it is unknown)."""
    text = os.environ.get(ENV_LIMIT, "").strip().upper().removesuffix("B")
    if text:
        unit = text[-1] if text[-1] in _SUFFIXES else ""
        try:
            value = float(text[: len(text) - len(unit)]) * _SUFFIXES[unit]
        except ValueError:
            value = math.nan
        # inf, nan, 0 or a negative size is no budget (inf gave a traceback; the others
        # fell back to the default without a word)
        if not (math.isfinite(value) and value >= 1):
            raise InputError(
                f"{ENV_LIMIT}={os.environ[ENV_LIMIT]!r}: expected a positive number of "
                "bytes, e.g. 8G"
            )
        return int(value)
    total = physical_memory()
    return int(MEMORY_SHARE * total) if total else 8 << 30


def human(nbytes: float) -> str:
    """1536 -> '1.5 KiB'."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(nbytes) < 1024 or unit == "PiB":
            return f"{nbytes:.0f} {unit}" if unit == "B" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    raise AssertionError("unreachable")


def check_bytes(what: str, nbytes: float, *, hint: str = "") -> None:
    """TooLarge naming ``what`` when ``nbytes`` exceeds :func:`memory_budget`."""
    budget = memory_budget()
    if nbytes > budget:
        source = f"{ENV_LIMIT}" if os.environ.get(ENV_LIMIT, "").strip() else "half this memory"
        more = f"; {hint}" if hint else ""
        raise TooLarge(
            bounded(
                f"{what}: would need {human(nbytes)}, more than the limit of "
                f"{human(budget)} ({source}){more}"
            )
        )


def count_nodes(data: object, limit: int = MAX_CONFIG_NODES) -> int:
    """The nodes of parsed YAML as Python sees them (a shared or recursive alias counts
    every time it is reached), counting stops just past ``limit``: so a billion-node
    alias bomb or a recursive alias costs ``limit`` steps, not its expansion."""
    count = 0
    stack = [data]
    while stack:
        node = stack.pop()
        count += 1
        if count > limit:
            return count
        if isinstance(node, dict):
            stack.extend(node.keys())
            stack.extend(node.values())
        elif isinstance(node, (list, tuple)):
            stack.extend(node)
    return count
