"""Model search path: where ONNX weights are looked up, in a fixed, printable order.

Weights are never committed (licences, size), so every consumer resolves a bare filename
through the same ordered list of directories and can print that list when nothing is found.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

MODELS_ENV = "FOLLOWBUS_MODELS"
# Repo root = parent of the vision/ directory (the package is installed editable, so this
# points at the checkout rather than site-packages).
REPO_ROOT = Path(__file__).resolve().parents[1]


def search_path(explicit_dir: str | os.PathLike[str] | None = None) -> list[Path]:
    """Directories tried by :func:`find_model`, in order, without duplicates.

    1. ``explicit_dir`` (a graph parameter; if it names a file, its parent directory),
    2. every entry of ``$FOLLOWBUS_MODELS`` (``os.pathsep``-separated),
    3. ``<repo>/models/``,
    4. ``<repo>/../shared/models`` and ``<cwd>/../shared/models``.
    """
    candidates: list[Path] = []
    if explicit_dir:
        p = Path(explicit_dir).expanduser()
        candidates.append(p.parent if p.is_file() else p)
    for part in os.environ.get(MODELS_ENV, "").split(os.pathsep):
        if part.strip():
            candidates.append(Path(part.strip()).expanduser())
    candidates.append(REPO_ROOT / "models")
    candidates.append(REPO_ROOT.parent / "shared" / "models")
    candidates.append(Path.cwd().parent / "shared" / "models")

    seen: set[Path] = set()
    unique: list[Path] = []
    for c in candidates:
        key = c.resolve(strict=False) if c.is_absolute() else (Path.cwd() / c).resolve(strict=False)
        if key not in seen:
            seen.add(key)
            unique.append(key)
    return unique


def find_model(filename: str, explicit_dir: str | os.PathLike[str] | None = None) -> Path | None:
    """Resolve a model file through :func:`search_path`; ``None`` when it is nowhere.

    ``explicit_dir`` may also name the model file itself, which then wins outright
    (a graph parameter pointing at a specific file must not be second-guessed).
    An absolute ``filename`` that exists is returned as is.
    """
    if explicit_dir:
        p = Path(explicit_dir).expanduser()
        if p.is_file():
            return p.resolve()
    direct = Path(filename).expanduser()
    if direct.is_absolute() and direct.is_file():
        return direct
    for d in search_path(explicit_dir):
        cand = d / filename
        if cand.is_file():
            log.debug("model %s found at %s", filename, cand)
            return cand
    return None


def format_search_path(explicit_dir: str | os.PathLike[str] | None = None) -> str:
    """One-line rendering of the search path, for error and log messages."""
    return ", ".join(str(p) for p in search_path(explicit_dir))
