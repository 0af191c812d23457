"""``followbus models``: where each model file is found on the search path, and whether it is intact."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..vision.models import (
    MODEL_ROLES,
    MODELS_ENV,
    ModelCheck,
    check_model,
    checksums_path,
    find_all_copies,
    known_checksums,
    restore_hint,
    search_path,
    shipped_models_dir,
)
from .command import describe

EXIT_PROBLEM = 1

DESCRIPTION = f"""\
List the model search path and, for every model the project ships (models/SHA256SUMS), each copy found
on it, its size and whether its SHA-256 matches. The first copy is the one the detection node loads;
the others are shadowed. Exit status 1 when a shipped model is missing or the copy in use is corrupt.

The search path, first match wins: --model-dir (as the detection node's model_dir parameter),
${MODELS_ENV} ({os.pathsep}-separated), the repository's models/, then ../shared/models.
Detectors verify the same checksums when they load a model, so a truncated download or a bad edit
fails with a message naming the file instead of producing wrong detections."""

EPILOG = f"""\
examples:
  followbus models                         check the shipped models
  followbus models --build-int8            rebuild models/yolox_nano_640_int8.onnx (the recipe: vision/quantize.py)
  followbus models --model-dir /opt/models as the node with `model_dir: /opt/models`
  {MODELS_ENV}=/opt/models followbus models
  git checkout -- models                   restore the shipped files after a MISMATCH"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``followbus models``' arguments and help (its row is in tools/cli.py's table)."""
    describe(p, DESCRIPTION, EPILOG, raw=True)
    p.add_argument("--model-dir", metavar="DIR", default=None,
                   help="a directory tried first, like the detection node's model_dir parameter")
    p.add_argument("--build-int8", action="store_true",
                   help="instead: quantize yolox_nano_640.onnx to INT8 (onnxruntime static quantization, "
                        "vision/quantize.py) and print its SHA-256 against models/SHA256SUMS; needs `onnx` "
                        "(pip install 'followbus[quantize]')")
    p.add_argument("--calibration", metavar="DIR", action="append",
                   help="with --build-int8: images to calibrate on, repeatable (default: the evaluation data, "
                        "../shared/data, when present, else frames of the built-in scenes; the shipped file "
                        "used ../shared/data)")
    p.add_argument("--output", metavar="FILE", type=Path, default=None,
                   help="with --build-int8: where to write it (default models/yolox_nano_640_int8.onnx)")


def _mb(size_bytes: int) -> str:
    return f"{size_bytes / 1e6:.2f} MB"


def _origin(directory: Path, model_dir: str | None) -> str:
    """Why a directory is on the search path, for the listing."""
    tags = []
    explicit = Path(model_dir).expanduser() if model_dir else None
    if explicit is not None and directory == (explicit.parent if explicit.is_file() else explicit).resolve():
        tags.append("--model-dir")
    env = [Path(p.strip()).expanduser().resolve() for p in os.environ.get(MODELS_ENV, "").split(os.pathsep)
           if p.strip()]
    if directory in env:
        tags.append(f"${MODELS_ENV}")
    if directory == shipped_models_dir().resolve():
        tags.append("shipped with the repository")
    if not tags and directory.name == "models" and directory.parent.name == "shared":
        tags.append("../shared")
    state = "" if directory.is_dir() else ", absent"
    return f" ({', '.join(tags)}{state})" if tags or state else ""


def _describe(check: ModelCheck) -> str:
    if check.ok:
        return "SHA-256 OK"
    return f"SHA-256 MISMATCH: {check.sha256}, expected {check.expected_sha256}"


INT8_MODEL = "yolox_nano_640_int8.onnx"


def build_int8(args: argparse.Namespace) -> int:
    """``--build-int8``: the recipe of the shipped INT8 detector, re-run."""
    from ..evaluation.datasets import find_data_root
    from ..vision.models import file_sha256, resolve_model
    from ..vision.quantize import calibration_images, quantize_yolox, read_frames, scene_frames

    try:
        import onnx  # noqa: F401  (quantization only)
    except ImportError:
        print("followbus models: --build-int8 needs onnx: pip install 'followbus[quantize]'", file=sys.stderr)
        return 2
    folders = [Path(c) for c in args.calibration or []]
    root = None if folders else find_data_root()
    images = calibration_images(folders or ([root] if root else []))
    if folders and not images:
        print(f"followbus models: no images under {', '.join(map(str, folders))}", file=sys.stderr)
        return 2
    frames = read_frames(images) if images else scene_frames()
    print(f"calibrating on {len(images) or 'built-in scene'} frames{f' from {root}' if root else ''}")
    out = args.output or shipped_models_dir() / INT8_MODEL
    quantize_yolox(resolve_model("yolox_nano_640.onnx", args.model_dir), out, frames, 640)
    sha, expected = file_sha256(out), known_checksums().get(INT8_MODEL)
    same = "matches models/SHA256SUMS" if sha == expected else f"differs from models/SHA256SUMS ({expected})"
    print(f"wrote {out}: SHA-256 {sha} ({same})")
    return 0


def cmd_models(args: argparse.Namespace) -> int:
    return build_int8(args) if args.build_int8 else check_models(args)


def check_models(args: argparse.Namespace) -> int:
    """The listing: the search path and every copy of every shipped model, checked."""
    model_dir: str | None = args.model_dir
    dirs = search_path(model_dir)
    _print_search_path(dirs, model_dir)

    sums = known_checksums()
    if not sums:
        print(f"\nno checksums: {checksums_path()} is missing or empty; restore models/ with `git checkout -- models`")
        return EXIT_PROBLEM
    print(f"checksums: {checksums_path()}\n")

    problems: list[str] = []
    for name in sorted(sums):
        problems += _check_shipped_model(name, sums, model_dir)
    _print_other_onnx(dirs, sums)

    if problems:
        print(f"\n{len(problems)} problem(s): {'; '.join(problems)}")
        return EXIT_PROBLEM
    print(f"\nall {len(sums)} shipped models present and intact")
    return 0


def _print_search_path(dirs: list[Path], model_dir: str | None) -> None:
    print("model search path (first match wins):")
    for i, d in enumerate(dirs, 1):
        print(f"  {i}. {d}{_origin(d, model_dir)}")


def _check_shipped_model(name: str, sums: dict[str, str], model_dir: str | None) -> list[str]:
    """List every copy of one shipped model on the search path, checked; its problems (none when intact)."""
    role = MODEL_ROLES.get(name, "")
    print(f"{name}: {role}" if role else name)
    copies = find_all_copies(name, model_dir)
    if not copies:
        print("  MISSING: in no directory of the search path; restore it with "
              f"`git checkout -- models/{name}`")
        return [f"{name} missing"]
    problems = [_check_copy(path, sums, used=k == 0) for k, path in enumerate(copies)]
    return [problem for problem in problems if problem]


def _check_copy(path: Path, sums: dict[str, str], *, used: bool) -> str | None:
    """One line (and a restore hint) for one copy; a problem only for the copy in use: the others are shadowed."""
    label = "used" if used else "also"
    try:
        check = check_model(path, sums)
    except OSError as exc:
        print(f"  {label}  {path}  unreadable: {exc.strerror or exc}")
        return f"{path} unreadable" if used else None
    print(f"  {label}  {path}  {_mb(check.size_bytes)}  {_describe(check)}")
    if check.ok:
        return None
    print(f"        {restore_hint(path)}")
    return f"{path} corrupt" if used else None


def _print_other_onnx(dirs: list[Path], sums: dict[str, str]) -> None:
    others = sorted({p for d in dirs if d.is_dir() for p in d.glob("*.onnx") if p.name not in sums})
    if others:
        print("\nother ONNX files on the search path (loaded without a checksum when named by model_file):")
        for p in others:
            print(f"  {p}  {_mb(p.stat().st_size)}")
