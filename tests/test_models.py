"""Shipped models: files, licences and checksums in models/; verification at load; `followbus models`;
`backend: auto` without a model is an error, not a silent HOG fallback."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from followbus.nodes.detection import DetectionParams, detector_from_params
from followbus.vision.detectors import (
    DetectorUnavailable,
    HogDetector,
    YoloxDetector,
    make_detector,
    resolve_detector_model,
)
from followbus.vision.models import (
    MODEL_ROLES,
    MODELS_ENV,
    ModelCorrupt,
    file_sha256,
    known_checksums,
    search_path,
    verify_model,
)

from .conftest import REPO, followbus_argv, run_followbus

MODELS = REPO / "models"
# the model graph.yaml's detection node loads (the demo's and eval's default detector)
_DETECTION = yaml.safe_load((REPO / "graph.yaml").read_text())["nodes"]["detection"]["params"]
GRAPH_MODEL = ("yolox_nano_dynamic.onnx" if _DETECTION.get("input_shape") == "fit"
               else "yolox_nano_{}.onnx".format(_DETECTION["input_size_px"]))
SHIPPED = ("osnet_x0_25_msmt17.onnx", "yolox_nano_416.onnx", "yolox_nano_512.onnx", "yolox_nano_640.onnx",
           "yolox_nano_640_int8.onnx", "yolox_nano_dynamic.onnx")
APACHE, MIT = "LICENSE.yolox-onnx.Apache-2.0", "LICENSE.osnet-torchreid.MIT"
LICENCES = {"yolox_nano_416.onnx": APACHE, "yolox_nano_512.onnx": APACHE, "yolox_nano_640.onnx": APACHE,
            "yolox_nano_640_int8.onnx": APACHE, "yolox_nano_dynamic.onnx": APACHE, "osnet_x0_25_msmt17.onnx": MIT}


def _truncated_copy(directory: Path, name: str = "yolox_nano_416.onnx") -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    dst = directory / name
    dst.write_bytes((MODELS / name).read_bytes()[:1_000_000])
    return dst


def _without_models(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Steer the search path so that neither the repository's models/ nor any ../shared/models is on it."""
    monkeypatch.chdir(tmp_path)  # <cwd>/../shared/models
    monkeypatch.setattr("followbus.vision.models.REPO_ROOT", tmp_path / "repo")  # models/ and <repo>/../shared
    monkeypatch.delenv(MODELS_ENV, raising=False)


# ----------------------------------------------------------------------------- the files


def test_shipped_models_are_present_intact_licensed_and_not_ignored() -> None:
    sums = known_checksums()
    assert sorted(sums) == sorted(p.name for p in MODELS.glob("*.onnx")) == list(SHIPPED)
    assert set(MODEL_ROLES) == set(SHIPPED)
    readme = (MODELS / "README.md").read_text()
    for name in SHIPPED:
        path = MODELS / name
        check = verify_model(path)
        assert check.known and check.ok and check.sha256 == sums[name] == file_sha256(path)
        assert 0.9e6 <= check.size_bytes <= 3.7e6
        assert name in readme and sums[name] in readme and LICENCES[name] in readme
        assert (MODELS / LICENCES[name]).stat().st_size > 500
    assert "Copyright (c) 2018 Kaiyang Zhou" in (MODELS / "LICENSE.osnet-torchreid.MIT").read_text()
    assert "Apache License" in (MODELS / "LICENSE.yolox-onnx.Apache-2.0").read_text()
    # The files must reach a clone: .gitignore may not exclude any of them (exit 1 = nothing ignored).
    files = [str(p.relative_to(REPO)) for p in MODELS.iterdir()]
    ignored = subprocess.run(["git", "check-ignore", *files], cwd=REPO, capture_output=True, text=True)
    assert ignored.returncode == 1 and not ignored.stdout, ignored.stdout
    # sha256sum(1) reads the same file.
    if shutil.which("sha256sum"):
        res = subprocess.run(["sha256sum", "-c", "SHA256SUMS"], cwd=MODELS, capture_output=True, text=True)
        assert res.returncode == 0 and res.stdout.count(": OK") == len(SHIPPED), res.stdout + res.stderr


def test_the_repository_models_come_first_after_explicit_settings(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    env_dir, explicit = tmp_path / "env", tmp_path / "explicit"
    monkeypatch.setenv(MODELS_ENV, str(env_dir))
    path = search_path(str(explicit))
    assert path[:3] == [explicit.resolve(), env_dir.resolve(), MODELS.resolve()]
    monkeypatch.delenv(MODELS_ENV)
    assert search_path()[0] == MODELS.resolve()
    assert resolve_detector_model("auto") == MODELS / "yolox_nano_416.onnx"
    assert resolve_detector_model("yolox", input_size=640) == MODELS / "yolox_nano_640.onnx"
    assert resolve_detector_model("hog") is None


# ----------------------------------------------------------------------------- verification at load


def test_a_truncated_or_altered_copy_is_refused_with_a_clear_message(tmp_path: Path) -> None:
    bad = _truncated_copy(tmp_path / "m")
    expected = known_checksums()["yolox_nano_416.onnx"]
    with pytest.raises(DetectorUnavailable) as err:
        make_detector("auto", model_dir=str(tmp_path / "m"))
    msg = str(err.value)
    assert "\n" not in msg
    assert str(bad) in msg and "corrupt or truncated" in msg and "1000000 bytes" in msg
    assert expected in msg and file_sha256(bad) in msg and "followbus models" in msg
    with pytest.raises(DetectorUnavailable, match="corrupt"):
        make_detector("yolox", model_dir=str(bad))  # model_dir naming the file itself
    with pytest.raises(ModelCorrupt):
        YoloxDetector(bad)  # any construction path verifies, not only the factory
    # Same size, one byte flipped: only the hash can tell.
    data = bytearray((MODELS / "yolox_nano_416.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad.write_bytes(bytes(data))
    with pytest.raises(DetectorUnavailable, match="corrupt") as err:
        make_detector("yolox", model_dir=str(tmp_path / "m"))
    assert f"({len(data)} bytes)" in str(err.value)


def test_a_shipped_file_points_at_git_checkout(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A damaged file inside the repository's models/ says how to restore it."""
    repo = tmp_path / "repo"
    _truncated_copy(repo / "models", "yolox_nano_640.onnx")
    shutil.copy(MODELS / "SHA256SUMS", repo / "models" / "SHA256SUMS")
    _without_models(monkeypatch, tmp_path)
    with pytest.raises(DetectorUnavailable, match=r"git checkout -- models/yolox_nano_640\.onnx"):
        make_detector("auto", input_size=640)


def test_an_unknown_model_loads_without_checksum_and_an_invalid_one_is_a_clear_error(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    own = tmp_path / "my_detector.onnx"
    shutil.copy(MODELS / "yolox_nano_416.onnx", own)
    with caplog.at_level(logging.INFO, logger="followbus.vision.models"):
        det = make_detector("yolox", model_dir=str(tmp_path), model_file="my_detector.onnx")
    assert isinstance(det, YoloxDetector) and det.model_path == own
    assert any("without a checksum" in r.getMessage() and str(own) in r.getMessage() for r in caplog.records)
    (tmp_path / "yolov8n.onnx").write_bytes(b"not an onnx model")
    with pytest.raises(DetectorUnavailable) as err:
        make_detector("yolov8", model_dir=str(tmp_path))
    msg = str(err.value)
    assert "\n" not in msg and "cannot be loaded by onnxruntime" in msg and str(tmp_path / "yolov8n.onnx") in msg


# ----------------------------------------------------------------------------- backend: auto without a model


def test_auto_without_a_model_is_a_one_line_error_and_hog_stays_explicit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _without_models(monkeypatch, tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DetectorUnavailable) as err:
        make_detector("auto", model_dir=str(empty))
    msg = str(err.value)
    assert "\n" not in msg and "yolox_nano_416.onnx" in msg
    assert err.value.search_path == search_path(str(empty)) and str(empty) in msg
    assert str(tmp_path / "repo" / "models") in msg  # the search path is printed, not just "not found"
    assert "git checkout -- models" in msg and "backend: hog" in msg and MODELS_ENV in msg
    # The detection node builds its detector the same way (graph.yaml's default is auto).
    assert DetectionParams().backend == "auto"
    with pytest.raises(DetectorUnavailable, match="backend 'auto' needs the YOLOX model"):
        detector_from_params(DetectionParams(model_dir=str(empty)))
    assert isinstance(make_detector("hog"), HogDetector)
    assert isinstance(detector_from_params(DetectionParams(backend="hog")), HogDetector)


def _run_without_models(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """The followbus CLI as a real process whose model search path holds nothing (REPO_ROOT steered away)."""
    code = ("import sys; import followbus.vision.models as m; from pathlib import Path; "
            f"m.REPO_ROOT = Path({str(tmp_path / 'repo')!r}); "
            "from followbus.tools.cli import main; sys.exit(main(sys.argv[1:]))")
    env = {k: v for k, v in os.environ.items() if k != MODELS_ENV}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60,
                          cwd=tmp_path, env=env, stdin=subprocess.DEVNULL)


def test_demo_refuses_to_start_without_a_model_and_node_exits_with_one_line(tmp_path: Path, graph_file) -> None:
    graph = shutil.copy(REPO / "graph.yaml", tmp_path / "graph.yaml")
    res = _run_without_models(tmp_path, "demo", "--graph", str(graph), "--duration", "1")
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert f"backend 'auto' needs the YOLOX model {GRAPH_MODEL}" in lines[0] and "backend: hog" in lines[0]
    assert "launching" not in res.stdout  # nothing was started
    # The detection node itself, as a real process: checked before it starts (DetectionParams.check), one line,
    # exit status 2.
    g = graph_file("  detection:\n    run: followbus.nodes.detection\n    inputs:\n"
                   "      frame: {from: capture/frame}\n    outputs: [detections]\n    params: {backend: auto}\n"
                   "  capture:\n    run: followbus.nodes.capture\n    outputs: [frame]\n")
    res = _run_without_models(tmp_path, "node", "detection", "--graph", str(g))
    assert res.returncode == 2, res.stdout + res.stderr
    errors = res.stderr.strip().splitlines()
    assert len(errors) == 1 and "Traceback" not in res.stderr, res.stderr
    assert "backend 'auto' needs the YOLOX model" in errors[0] and str(tmp_path / "repo" / "models") in errors[0]


def test_demo_refuses_a_corrupt_model_before_launching(tmp_path: Path) -> None:
    bad = _truncated_copy(tmp_path / "m", GRAPH_MODEL)
    res = run_followbus("demo", "--set", f"detection.model_dir={bad.parent}", "--duration", "1", timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stdout + res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and str(bad) in res.stderr and "corrupt" in res.stderr
    # check and launch too, before any node starts (detection and redetection crash-looped on it until their
    # restart budget was spent, and `check` said ok).
    for argv in (["check", str(REPO / "graph.yaml")], ["launch", str(REPO / "graph.yaml"), "--duration", "5"]):
        res = run_followbus(*argv, "--set", f"detection.model_dir={bad.parent}", timeout=60)
        assert res.returncode == 2 and "Traceback" not in res.stderr, res.stdout + res.stderr
        assert len(res.stderr.strip().splitlines()) == 1 and str(bad) in res.stderr and "corrupt" in res.stderr
        assert "started" not in res.stdout + res.stderr


# ----------------------------------------------------------------------------- followbus models


def test_followbus_models_lists_and_checks_the_shipped_models() -> None:
    res = run_followbus("models", timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    out = res.stdout
    assert f"1. {MODELS.resolve()} (shipped with the repository)" in out
    for name in SHIPPED:
        assert f"used  {MODELS.resolve() / name}" in out
    assert out.count("SHA-256 OK") >= len(SHIPPED) and "MISMATCH" not in out and "MISSING" not in out
    assert f"all {len(SHIPPED)} shipped models present and intact" in out
    help_text = run_followbus("models", "--help", timeout=60).stdout
    assert "SHA256SUMS" in help_text and MODELS_ENV in help_text and "--model-dir" in help_text


def test_followbus_models_fails_on_a_corrupt_copy_first_on_the_path(tmp_path: Path) -> None:
    bad = _truncated_copy(tmp_path / "m")
    (tmp_path / "m" / "mine.onnx").write_bytes(b"x" * 10)
    env = {**os.environ, MODELS_ENV: str(tmp_path / "m")}
    res = subprocess.run(followbus_argv("models"), capture_output=True, text=True, timeout=60, cwd=REPO, env=env,
                         stdin=subprocess.DEVNULL)
    assert res.returncode == 1, res.stdout + res.stderr
    out = res.stdout
    assert f"used  {bad}" in out and "SHA-256 MISMATCH" in out and known_checksums()["yolox_nano_416.onnx"] in out
    assert f"also  {MODELS.resolve() / 'yolox_nano_416.onnx'}" in out  # the good copy is shadowed, and shown
    assert str(tmp_path / "m" / "mine.onnx") in out  # other ONNX files are listed, unchecked
    assert "1 problem(s)" in out and "corrupt" in out
    # --model-dir puts it first the same way.
    res = run_followbus("models", "--model-dir", str(tmp_path / "m"), timeout=60)
    assert res.returncode == 1 and f"used  {bad}" in res.stdout and "(--model-dir)" in res.stdout


def test_followbus_models_reports_a_missing_model(tmp_path: Path) -> None:
    repo_models = tmp_path / "repo" / "models"
    repo_models.mkdir(parents=True)
    shutil.copy(MODELS / "SHA256SUMS", repo_models / "SHA256SUMS")
    present = [name for name in SHIPPED if name != "yolox_nano_640.onnx"]
    for name in present:
        shutil.copy(MODELS / name, repo_models / name)
    res = _run_without_models(tmp_path, "models")
    assert res.returncode == 1, res.stdout + res.stderr
    assert "yolox_nano_640.onnx" in res.stdout and "MISSING" in res.stdout
    assert "git checkout -- models/yolox_nano_640.onnx" in res.stdout and "1 problem(s)" in res.stdout
    assert res.stdout.count("SHA-256 OK") == len(present)


def test_other_commands_report_a_corrupt_model_in_one_line(tmp_path: Path) -> None:
    """`followbus eval` builds its detector in-process: a bad model is a usage error there too, no traceback."""
    bad = _truncated_copy(tmp_path / "m")
    env = {**os.environ, MODELS_ENV: str(tmp_path / "m")}
    res = subprocess.run(followbus_argv("eval", "scene:wall-occlusion", "--detector", "yolox", "--max-frames", "5",
                                        "--out", str(tmp_path / "res")),
                         capture_output=True, text=True, timeout=120, cwd=REPO, env=env, stdin=subprocess.DEVNULL)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("followbus: ")]
    assert len(errors) == 1 and str(bad) in errors[0] and "corrupt" in errors[0], res.stderr
