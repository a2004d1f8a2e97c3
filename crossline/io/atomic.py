"""Write artefacts atomically: a stage either leaves a complete file or none at all.

Every artefact is written to a temporary file next to its destination and renamed into
place (``os.replace`` is atomic on POSIX), so an interrupted or failing stage never
leaves a half-written file that a later run would take for a finished one.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import math
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from crossline.errors import CrosslineError

__all__ = ["WriteError", "atomic_path", "to_jsonable", "write_json", "write_parquet"]


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it onto ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a run killed outright (power cut, kill -9) leaves its temporary file: clear it
    for stale in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        stale.unlink(missing_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise WriteError(path, exc) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o644)
        os.replace(tmp_path, path)
    except OSError as exc:
        # the artefact's own write (a full disk, a quota), not an input the block read
        if exc.filename in (None, str(tmp_path), str(path)) or exc.errno in _DISK_ERRNOS:
            raise WriteError(path, exc) from exc
        raise
    finally:
        tmp_path.unlink(missing_ok=True)


_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


class WriteError(CrosslineError, OSError):
    """An artefact could not be written (full disk, quota, read-only): names the artefact."""

    def __init__(self, path: Path, exc: OSError):
        code = exc.errno
        if code is None:  # pyarrow says "... Detail: [errno 28] No space left on device"
            m = re.search(r"\[errno (\d+)\]", str(exc))
            code = int(m.group(1)) if m else None
        reason = os.strerror(code) if code else (exc.strerror or str(exc))
        self.message = f"cannot write {path}: {reason}; nothing of it was kept"
        super().__init__(self.message)
        self.errno = code
        self.filename = str(path)

    def __str__(self) -> str:
        return self.message


def to_jsonable(obj: Any) -> Any:
    """Plain-Python copy of ``obj`` (numpy arrays and scalars, Paths, tuples) for ``json``.

    Non-finite floats become ``None`` so that the JSON stays standard.
    """
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating | float):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically and deterministically."""
    text = json.dumps(to_jsonable(data), indent=2, allow_nan=False) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_parquet(path: str | Path, frame: Any) -> None:
    """Write a pandas DataFrame to parquet atomically, without the index, byte-reproducibly."""
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False, engine="pyarrow", compression="zstd")
