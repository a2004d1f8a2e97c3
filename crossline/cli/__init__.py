"""The ``crossline`` command: one subcommand per stage of the workflow.

Each subcommand is what a Snakemake rule runs; it can be run by hand just the same.
Errors in the input (a broken capture, a missing artefact) end with a message that names
the file and exit status 2; nothing half-written is left behind.

The code is split by idea (issue 21.3) into this package's modules: ``args`` (the registry
of subcommands, the argument types they share), ``capture`` (simulate, check), ``calibrate``
(the three calibrations), ``scan`` (extract-stripes, gather-stripes, triangulate),
``products`` (fuse, export-cloud, report, certificate). This module keeps the parser and the
entry point (``build_parser``, ``main``) and re-exports ``COMMANDS``; ``__main__`` runs
``main`` for ``python -m crossline.cli``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from crossline import __version__
from crossline.cli.args import COMMANDS

# The subcommands register themselves in COMMANDS as their modules are imported: the order
# of these imports is the order of `crossline --help` (the workflow's), so keep it.
# isort: off
from crossline.cli import capture  # noqa: F401
from crossline.cli import calibrate  # noqa: F401
from crossline.cli import scan  # noqa: F401
from crossline.cli import products  # noqa: F401
# isort: on

log = logging.getLogger("crossline")


# ----------------------------------------------------------------------------- main


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``crossline`` command."""
    parser = argparse.ArgumentParser(
        prog="crossline",
        description=(
            "Cross-line laser scanner on a measuring arm: capture folders to calibrations, "
            "point clouds and accuracy reports. Each subcommand is one stage of the "
            "Snakemake workflow; run `crossline <command> --help` for its options."
        ),
    )
    parser.add_argument("--version", action="version", version=f"crossline {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="<command>", required=True)
    for name, (summary, details, configure) in COMMANDS.items():
        sp = sub.add_parser(
            name, help=summary, description=f"{summary[0].upper()}{summary[1:]}.\n\n{details}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        configure(sp)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``crossline`` command."""
    # One BLAS/OpenMP thread, set before numpy loads: OpenBLAS picks its kernels by the
    # thread count it starts with, so the same calibration would differ in its last bits
    # between a 1-core and a 2-core run (see the threadpool_limits note below).
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from crossline.errors import CrosslineError

    try:
        import cv2
        from threadpoolctl import threadpool_limits

        # Determinism: BLAS reductions and OpenCV's internal parallel loops can sum in a
        # different order with a different number of threads, which changes the last bits
        # of a calibration. So every numerical kernel runs on one thread, and a stage's
        # --threads (the rule's `threads`) is spent on its own pool of workers over images
        # or frames, whose results are combined in a fixed order.
        cv2.setNumThreads(1)
        with threadpool_limits(limits=1):
            return int(args.func(args) or 0)
    except CrosslineError as exc:
        print(f"crossline {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file the user named cannot be read or written
        where = exc.filename if exc.filename is not None else "a file"
        print(f"crossline {args.command}: error: {where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"crossline {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: said in one line; the traceback only when asked for
        if args.verbose:
            log.exception("internal error")
        print(f"crossline {args.command}: internal error: {type(exc).__name__}: {exc} (a bug in "
              f"crossline, not in the input: please report it with this command line; -v shows "
              f"where)", file=sys.stderr)
        return 3
