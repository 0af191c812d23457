"""Model files: the search path they are looked up on, and their checksums.

The YOLOX-nano and OSNet ONNX files ship in the repository's ``models/`` (with their licences and
``models/SHA256SUMS``). Every consumer resolves a bare filename through the same ordered list of
directories, can print that list when nothing is found, and checks a file of a known name against
its SHA-256 before loading it, so a truncated or altered copy fails with a message instead of an
onnxruntime traceback or, worse, wrong detections.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

MODELS_ENV = "FOLLOWBUS_MODELS"
# Repo root = parent of the vision/ directory (the package is installed editable, so this
# points at the checkout rather than site-packages).
REPO_ROOT = Path(__file__).resolve().parents[1]
CHECKSUMS_FILE = "SHA256SUMS"

# What each shipped file is for (the checksums themselves live in models/SHA256SUMS only).
MODEL_ROLES = {
    "yolox_nano_416.onnx": "YOLOX-nano person detector, 416 px square input (detection backend auto/yolox, "
                           "input_shape: square)",
    "yolox_nano_512.onnx": "YOLOX-nano person detector, 512 px input (input_size_px: 512, --detector yolox512)",
    "yolox_nano_640.onnx": "YOLOX-nano person detector, 640 px input (input_size_px: 640, --detector yolox640)",
    "yolox_nano_dynamic.onnx": "YOLOX-nano person detector taking any input height and width (input_shape: fit, "
                               "graph.yaml's; the weights of yolox_nano_640.onnx)",
    "yolox_nano_640_int8.onnx": "YOLOX-nano@640 statically quantized to INT8 (--detector yolox640-int8; recipe: "
                                "vision/quantize.py; not for use: its detector ceiling is 38.8 %, BENCHMARKS.md)",
    "osnet_x0_25_msmt17.onnx": "OSNet-x0.25 person re-ID embedding (MSMT17)",
}


class ModelError(RuntimeError):
    """A model file cannot be used: missing, corrupt, or rejected by onnxruntime. The message says what to do."""


class ModelNotFound(ModelError):
    """No directory of the search path holds the file."""

    def __init__(self, filename: str, tried: list[Path]) -> None:
        self.filename = filename
        self.tried = tried
        super().__init__(f"model {filename} not found; model search path tried: {', '.join(map(str, tried))}")


class ModelCorrupt(ModelError):
    """The file's SHA-256 differs from the one recorded for its name."""


def shipped_models_dir() -> Path:
    return REPO_ROOT / "models"


def search_path(explicit_dir: str | os.PathLike[str] | None = None) -> list[Path]:
    """Directories tried by :func:`find_model`, in order, without duplicates.

    1. ``explicit_dir`` (a graph parameter; if it names a file, its parent directory),
    2. every entry of ``$FOLLOWBUS_MODELS`` (``os.pathsep``-separated),
    3. ``<repo>/models/`` (the shipped models),
    4. ``<repo>/../shared/models`` and ``<cwd>/../shared/models``.
    """
    candidates: list[Path] = []
    if explicit_dir:
        p = Path(explicit_dir).expanduser()
        candidates.append(p.parent if p.is_file() else p)
    for part in os.environ.get(MODELS_ENV, "").split(os.pathsep):
        if part.strip():
            candidates.append(Path(part.strip()).expanduser())
    candidates.append(shipped_models_dir())
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
    An absolute ``filename`` that exists is returned as is. Nothing is verified here
    (see :func:`resolve_model`).
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


def find_all_copies(filename: str, explicit_dir: str | os.PathLike[str] | None = None) -> list[Path]:
    """Every copy of ``filename`` on the search path, in search order (the first is the one used)."""
    return [d / filename for d in search_path(explicit_dir) if (d / filename).is_file()]


def format_search_path(explicit_dir: str | os.PathLike[str] | None = None) -> str:
    """One-line rendering of the search path, for error and log messages."""
    return ", ".join(str(p) for p in search_path(explicit_dir))


# ----------------------------------------------------------------------------- checksums


def checksums_path() -> Path:
    return shipped_models_dir() / CHECKSUMS_FILE


def known_checksums() -> dict[str, str]:
    """``filename -> sha256`` from ``models/SHA256SUMS`` (``sha256sum`` format); empty when it is absent."""
    path = checksums_path()
    try:
        text = path.read_text(encoding="utf-8")
    except OSError:
        return {}
    sums: dict[str, str] = {}
    for line in text.splitlines():
        parts = line.strip().split(maxsplit=1)
        if len(parts) == 2 and len(parts[0]) == 64:
            sums[parts[1].lstrip("*")] = parts[0].lower()  # '*' marks binary mode in sha256sum output
    return sums


# (resolved path, size, mtime_ns) -> sha256: a detector built twice in a process hashes its file once.
_HASH_CACHE: dict[tuple[str, int, int], str] = {}


def file_sha256(path: str | os.PathLike[str]) -> str:
    p = Path(path).resolve()
    st = p.stat()
    key = (str(p), st.st_size, st.st_mtime_ns)
    if key not in _HASH_CACHE:
        h = hashlib.sha256()
        with p.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _HASH_CACHE[key] = h.hexdigest()
    return _HASH_CACHE[key]


@dataclass(frozen=True)
class ModelCheck:
    """A model file measured against ``models/SHA256SUMS``."""

    path: Path
    size_bytes: int
    sha256: str
    expected_sha256: str | None  # None: not a file name the project ships

    @property
    def known(self) -> bool:
        return self.expected_sha256 is not None

    @property
    def ok(self) -> bool:
        return self.expected_sha256 is None or self.sha256 == self.expected_sha256


def check_model(path: str | os.PathLike[str], sums: dict[str, str] | None = None) -> ModelCheck:
    p = Path(path)
    sums = known_checksums() if sums is None else sums
    return ModelCheck(p, p.stat().st_size, file_sha256(p), sums.get(p.name))


def restore_hint(path: Path) -> str:
    """What to do about a bad model file, depending on where it is."""
    shipped = shipped_models_dir()
    if path.resolve().parent == shipped.resolve():
        return f"restore it with `git checkout -- models/{path.name}`"
    return (f"replace it with a good copy (the repository ships one in {shipped}) or remove it so the next copy "
            "on the model search path is used")


def verify_model(path: str | os.PathLike[str]) -> ModelCheck:
    """Check a model file before loading it; raises :class:`ModelCorrupt` on a SHA-256 mismatch.

    Files whose name is not in ``models/SHA256SUMS`` (a user's own export) pass unchecked, logged.
    """
    p = Path(path)
    try:
        result = check_model(p)
    except OSError as exc:
        raise ModelError(f"model file {p} cannot be read: {exc.strerror or exc}") from exc
    if not result.known:
        if p.name in MODEL_ROLES:  # a shipped name, but the checksum table itself is gone
            log.warning("no checksum for %s: %s is missing; loading it unverified", p, checksums_path())
        else:
            log.info("model %s is not one the project ships: loaded without a checksum", p)
    elif not result.ok:
        raise ModelCorrupt(
            f"model file {p} is corrupt or truncated ({result.size_bytes} bytes): SHA-256 {result.sha256}, "
            f"expected {result.expected_sha256} ({checksums_path()}); {restore_hint(p)} "
            "(`followbus models` checks every copy)")
    return result


def resolve_model(filename: str, explicit_dir: str | os.PathLike[str] | None = None) -> Path:
    """:func:`find_model` then :func:`verify_model`: the path of a good copy, or a :class:`ModelError`."""
    path = find_model(filename, explicit_dir)
    if path is None:
        raise ModelNotFound(filename, search_path(explicit_dir))
    verify_model(path)
    return path
