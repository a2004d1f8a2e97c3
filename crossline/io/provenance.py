"""Where results come from: source files a stage depends on, checksums, version and commit.

``module_files`` lets the workflow declare the library code of each stage as an input
(found by reading import statements, nothing is imported), so that editing a module
re-runs exactly the stages that use it.
"""

from __future__ import annotations

import ast
import hashlib
import subprocess
from functools import cache
from pathlib import Path

__all__ = ["file_sha256", "git_commit", "module_files"]

PACKAGE_ROOT = Path(__file__).resolve().parents[1]


def _module_path(name: str) -> Path | None:
    parts = name.split(".")
    if parts[0] != "crossline":
        return None
    base = PACKAGE_ROOT.joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(path: Path, module: str) -> set[str]:
    """Names of crossline modules imported anywhere in a file (top level or inside functions)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    # imports under ``if TYPE_CHECKING:`` never run (crossline/__init__.py names its
    # lazily loaded exports there), so they make no stage depend on a module
    typing_only = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and _is_type_checking(node.test)
        for stmt in node.body
        for inner in ast.walk(stmt)
    }
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.add(mod)
            # ``from crossline import sim`` imports a submodule, not a name
            found.update(f"{mod}.{a.name}" for a in node.names)
    return {m for m in found if m == "crossline" or m.startswith("crossline.")}


@cache
def module_files(*modules: str) -> tuple[str, ...]:
    """Source files (paths relative to the repository) of crossline modules and all they import.

    Parent packages' ``__init__.py`` are included, since importing a submodule runs them.
    """
    todo = list(modules)
    seen: set[Path] = set()
    while todo:
        name = todo.pop()
        parts = name.split(".")
        for i in range(1, len(parts) + 1):
            path = _module_path(".".join(parts[:i]))
            if path is None or path in seen:
                continue
            seen.add(path)
            mod = ".".join(parts[:i])
            todo.extend(_imports(path, mod))
    root = PACKAGE_ROOT.parent
    return tuple(sorted(str(p.relative_to(root)) for p in seen))


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def git_commit(path: str | Path = PACKAGE_ROOT) -> str | None:
    """The git commit of the source tree (with ``-dirty`` if modified), or None outside git."""
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--abbrev=40"],
            cwd=path, capture_output=True, text=True, timeout=10, check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None
