"""The ``crossline`` command's registry of subcommands and the argument types they share.

``command`` registers a subcommand in ``COMMANDS`` (its summary, its details and the function
that adds its arguments), in the order the subcommands are defined; ``crossline.cli`` builds
the parser from it. The argparse types (``_bool``, ``_checked`` and the checked numbers made
with it, ``_board_spec``), the check of parquet inputs and the ``--threads`` option are shared
by the subcommands of ``crossline.cli.capture``, ``.calibrate``, ``.scan`` and ``.products``.
Split from ``crossline.cli`` (issue 21.3), which re-exports ``COMMANDS``.
"""

from __future__ import annotations

import argparse
import textwrap
from collections.abc import Callable
from pathlib import Path

COMMANDS: dict[str, tuple[str, str, Callable[[argparse.ArgumentParser], None]]] = {}


def command(name: str, summary: str, details: str = ""):
    """Register a subcommand: the decorated function adds its arguments and sets ``func``."""

    def wrap(fn: Callable[[argparse.ArgumentParser], None]):
        COMMANDS[name] = (summary, textwrap.dedent(details).strip(), fn)
        return fn

    return wrap


def _bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes", "on"):
        return True
    if text.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _checked(kind: type, ok, what: str, *, auto: bool = False):
    """An argparse type: a ``kind`` value for which ``ok`` holds, or with ``auto`` also 'auto' (None)."""
    expected = f"'auto' or {what}" if auto else what

    def parse(text: str):
        if auto and text.lower() == "auto":
            return None
        try:
            x = kind(text)
        except ValueError:
            x = None
        if x is None or not ok(x):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return x

    return parse


_auto_or_fraction = _checked(float, lambda x: 0 < x < 1, "a number in (0, 1)", auto=True)
_auto_or_count = _checked(int, lambda n: n >= 1, "a positive integer", auto=True)
_auto_or_positive = _checked(float, lambda x: x > 0, "a number > 0", auto=True)
_positive = _checked(float, lambda x: x > 0, "a number > 0")
_unit_interval = _checked(float, lambda x: 0 <= x <= 1, "a number in [0, 1]")


def _board_spec(text: str):
    from crossline.board import Board

    try:
        return Board.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _parquet_inputs(paths: list[Path], what: str) -> None:
    """Raise a CrosslineError naming the first of ``paths`` that is not a readable parquet file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from crossline.errors import CrosslineError

    for path in paths:
        try:
            pq.ParquetFile(path)
        except OSError as exc:
            if isinstance(exc, pa.ArrowException):
                raise CrosslineError(f"{path}: not a {what} file (parquet: {exc})") from None
            raise CrosslineError(f"{path}: cannot read the {what} file ({exc.strerror or exc})") from None
        except (pa.ArrowException, ValueError) as exc:
            raise CrosslineError(f"{path}: not a {what} file (parquet: {exc})") from None


def _threads(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=1, help="CPU threads to use (default 1)")
