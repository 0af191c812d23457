"""docs/writing-a-node.md as a user follows it: its node file and graph written out (they are docs/examples/ too),
then its commands run as written, with the `followbus` command a user has, in a fresh directory: check, launch
with a recording, replay --verify. And a node with one input and one output takes at most twelve lines of Python
(the API's size: tests/test_node_api.py)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import REPO, free_port

pytestmark = pytest.mark.slow

PAGE = REPO / "docs" / "writing-a-node.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.M | re.S)
FILE_MARK = re.compile(r"^# file: (\S+)\n")


def _blocks() -> list[tuple[str, str]]:
    return [(m.group(1), m.group(2)) for m in FENCE.finditer(PAGE.read_text())]


def _files() -> dict[str, str]:
    """The page's files: each block whose first line is ``# file: NAME``, without that line."""
    files = {}
    for _, text in _blocks():
        mark = FILE_MARK.match(text)
        if mark:
            files[mark.group(1)] = text[mark.end():]
    return files


def _commands() -> list[str]:
    return [line for lang, text in _blocks() if lang == "sh" for line in text.splitlines() if line.strip()]


def test_the_page_shows_the_example_files_as_they_are():
    files = _files()
    assert set(files) == {"people_count.py", "people.yaml"}
    for name, text in files.items():
        assert text == (REPO / "docs" / "examples" / name).read_text(), f"docs/examples/{name} and the page differ"


def test_the_readme_shows_the_template_node_as_it_is():
    readme = (REPO / "README.md").read_text()
    block = readme[readme.index("<!-- node example:"):]
    block = block[block.index("```python\n") + len("```python\n"):]
    assert block[:block.index("```")] == (REPO / "docs" / "examples" / "people_count.py").read_text()


def test_a_node_with_one_input_and_one_output_is_at_most_twelve_lines():
    code = [line for line in _files()["people_count.py"].splitlines() if line.strip()]
    assert len(code) <= 12, code


def test_the_commands_of_the_page_run_as_written(tmp_path):
    for name, text in _files().items():
        (tmp_path / name).write_text(text)
    followbus = Path(sys.executable).parent / "followbus"  # the command a user runs (not python -m: cwd not first)
    env = {k: v for k, v in os.environ.items() if k != "FOLLOWBUS_DOMAIN"}  # a private port and namespace instead
    env.update(FOLLOWBUS_PORT=str(free_port()), FOLLOWBUS_NAMESPACE=f"docs{os.getpid()}")
    outputs = []
    for command in _commands():
        argv = shlex.split(command)
        assert argv[0] == "followbus", command
        result = subprocess.run([str(followbus), *argv[1:]], cwd=tmp_path, env=env, capture_output=True, text=True,
                                timeout=300, stdin=subprocess.DEVNULL)
        assert result.returncode == 0, f"{command}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
        outputs.append(result.stdout + result.stderr)
    assert [c.split()[1] for c in _commands()] == ["check", "launch", "replay"]
    replay = outputs[-1]
    assert "verify: OK" in replay, replay
    compared = int(re.search(r"(\d+) compared, \1 identical, 0 differing, 0 missing, 0 extra", replay).group(1))
    assert compared > 0, replay
