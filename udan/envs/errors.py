"""Errors for bad environment requests: CLIs turn them into a one-line message and exit code 2."""

from __future__ import annotations

import argparse
from typing import NoReturn


class EnvConfigError(ValueError):
    """An environment request that cannot be honoured (bad range, too many agents for the map)."""


class UnknownEnvError(EnvConfigError):
    """A name that is not in the registry."""


def parse_range(value: int | str | tuple[int, int] | list[int], what: str) -> tuple[int, int]:
    """``3``, ``"1-5"`` or ``(1, 5)`` -> ``(lo, hi)``; rejects empty, inverted, negative."""
    if isinstance(value, bool):
        raise EnvConfigError(f"{what}: expected a count or a range like 1-5, got {value!r}")
    if isinstance(value, int):
        lo = hi = value
    elif isinstance(value, str):
        parts = value.strip().split("-")
        if len(parts) not in (1, 2) or not all(p.strip().isdigit() for p in parts):
            raise EnvConfigError(f"{what}: expected a count or a range like 1-5, got {value!r}")
        lo, hi = int(parts[0]), int(parts[-1])
    else:
        try:
            lo, hi = (int(v) for v in value)
        except (TypeError, ValueError):
            raise EnvConfigError(
                f"{what}: expected a count or a (lo, hi) pair, got {value!r}"
            ) from None
    if lo < 0:
        raise EnvConfigError(f"{what}: negative count {lo}")
    if hi < lo:
        raise EnvConfigError(f"{what}: inverted range {lo}-{hi} (empty)")
    return lo, hi


class OneLineParser(argparse.ArgumentParser):
    """argparse, but a bad option is one line on stderr (no usage block), still exit code 2:
    the command-line convention of every tool of the project (edge, HIL, mock firmware)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")
