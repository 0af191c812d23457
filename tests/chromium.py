"""Headless Chromium for the web view's browser checks: find it, render a page, read its layout probe.

Outside CI a missing Chromium skips the browser checks with the reason; in CI (.ci/run installs Debian's
chromium package) it fails them, so the page is rendered in a real browser on every CI run.
"""

from __future__ import annotations

import html
import json
import os
import re
import shutil
import struct
import subprocess
import time
from pathlib import Path

import pytest

CANDIDATES = ("chromium", "chromium-browser", "google-chrome")
# Without the background-networking flags Chromium tries to reach the network (closed here).
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--run-all-compositor-stages-before-draw", "--hide-scrollbars")


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def chromium_path() -> str | None:
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    return None


def have_chromium() -> bool:
    """Whether the browser checks can run; in CI a missing browser fails the test right here."""
    if chromium_path() is None and in_ci():
        pytest.fail("CI must render the web view in a browser, but chromium is not installed (.ci/run installs it)")
    return chromium_path() is not None


def require_chromium() -> str:
    """The browser's path; skip (outside CI) or fail (in CI) when there is none."""
    if not have_chromium():
        pytest.skip("chromium not installed (apt-get install chromium): the web view was not rendered in a browser")
    return chromium_path() or ""


def _run(argv: list[str], profile: Path) -> subprocess.CompletedProcess:
    try:
        result = subprocess.run(argv, capture_output=True, text=True, timeout=90, stdin=subprocess.DEVNULL)
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    assert result.returncode == 0, result.stderr[-2000:]
    return result


def render_dom(url: str, tmp: Path, budget_ms: int, window: str = "1280,900") -> str:
    """The page's DOM after budget_ms of virtual time (scripts ran, fetches answered) at this window size."""
    profile = tmp / f"chromium-{time.monotonic_ns()}"
    argv = [require_chromium(), *FLAGS, f"--user-data-dir={profile}", f"--window-size={window}",
            f"--virtual-time-budget={budget_ms}", "--dump-dom", url]
    return _run(argv, profile).stdout


def docs_picture(name: str, tmp: Path) -> Path:
    """Where a test writes a page's picture that the README shows: a temporary file, unless the run is asked to
    refresh the README's pictures (``FOLLOWBUS_UPDATE_PICTURES=1``): then docs/NAME, to be committed. A test
    run leaves the checkout as it found it."""
    if os.environ.get("FOLLOWBUS_UPDATE_PICTURES") == "1":
        return Path(__file__).resolve().parents[1] / "docs" / name
    return tmp / name


def screenshot(url: str, out: Path, tmp: Path, budget_ms: int, window: str = "1280,900") -> tuple[int, int]:
    """Write a PNG of the page to ``out``; returns its (width, height) read back from the file."""
    profile = tmp / f"chromium-{time.monotonic_ns()}"
    shot = tmp / f"shot-{time.monotonic_ns()}.png"
    argv = [require_chromium(), *FLAGS, f"--user-data-dir={profile}", f"--window-size={window}",
            f"--virtual-time-budget={budget_ms}", f"--screenshot={shot}", url]
    _run(argv, profile)
    data = shot.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    width, height = struct.unpack(">II", data[16:24])  # IHDR
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(shot, out)
    return width, height


def page_layout(dom: str) -> dict:
    """The boxes the page exposes on <body data-layout=...> (video, health table, state text)."""
    match = re.search(r'<body[^>]*\sdata-layout="([^"]*)"', dom)
    assert match, "no layout probe on <body>: " + dom[:500]
    return json.loads(html.unescape(match.group(1)))


def element_text(dom: str, element_id: str) -> tuple[str, str]:
    """(data-state, text) of the element with this id (text without tags)."""
    match = re.search(rf'<(\w+) id="{element_id}"([^>]*)>(.*?)</\1>', dom, re.S)
    assert match, f"no #{element_id}: " + dom[:500]
    state = re.search(r'data-state="([^"]*)"', match.group(2))
    return (state.group(1) if state else ""), html.unescape(re.sub(r"<[^>]+>", "", match.group(3)))
