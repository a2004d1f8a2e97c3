"""The stage configuration a report or certificate command is given: a dict, a JSON file or
JSON text (the workflow passes ``config.yaml`` as JSON), read once and checked to be an object."""

from __future__ import annotations

import json
from pathlib import Path

from crossline.errors import CrosslineError

__all__ = ["read_settings"]


def read_settings(config: str | Path | dict | None, what: str) -> dict:
    """A private, JSON-clean copy of the configuration; ``what`` names it in errors."""
    if config is None:
        full: object = {}
    elif isinstance(config, dict):
        full = json.loads(json.dumps(config))
    else:
        text = str(config)
        path = Path(text) if len(text) < 4096 and not text.lstrip().startswith("{") else None
        try:
            full = json.loads(path.read_text() if path is not None else text)
        except OSError as exc:
            raise CrosslineError(f"{path}: cannot read the {what} ({exc.strerror})") from exc
        except ValueError as exc:
            where = path if path is not None else "--config-json"
            raise CrosslineError(f"{where}: the {what} is not valid JSON ({exc})") from exc
    if not isinstance(full, dict):
        raise CrosslineError(f"the {what} must be a JSON object, got {type(full).__name__}")
    return full
