"""``followbus demo`` prepares the graph without knowing its node names: ``--scene`` goes to the params marked
``demo: source``, the source's first ground-truth box to those marked ``demo: init_box`` (no process starts)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.tools.cli import demo_graph
from followbus.tools.errors import UsageError

from .conftest import REPO


def _renamed_graph(tmp_path: Path) -> Path:
    """graph.yaml with capture called ``camera`` and re-ID ``finder``: a demo that looked nodes up by name misses
    both."""
    text = (REPO / "graph.yaml").read_text()
    for old, new in (("capture", "camera"), ("reid", "finder")):
        text = re.sub(rf"^  {old}:", f"  {new}:", text, flags=re.M)
        text = text.replace(f"from: {old}/", f"from: {new}/")
    path = tmp_path / "renamed.yaml"
    path.write_text(text)
    return path


def _annotated_folder(root: Path) -> Path:
    (root / "img").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(root / "img" / f"{i + 1:06d}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
    (root / "groundtruth.txt").write_text("10,12,20,30\n11,12,20,30\n12,12,20,30\n")
    return root


def test_demo_gives_the_first_truth_box_to_the_node_that_takes_one(tmp_path, capsys):
    seq = _annotated_folder(tmp_path / "seq")
    graph, overrides = demo_graph(str(_renamed_graph(tmp_path)), None, [f"camera.source={seq}"])
    assert graph.nodes["finder"].params["init_box"] == [10.0, 12.0, 20.0, 30.0]
    assert overrides == [f"camera.source={seq}", "finder.init_box=[10.00, 12.00, 20.00, 30.00]"]
    assert "target: the first ground-truth box (10.0, 12.0, 20.0, 30.0)" in capsys.readouterr().out
    # A box given in the graph (or by --set) is the user's: the demo does not replace it.
    _, kept = demo_graph(str(_renamed_graph(tmp_path)), None, [f"camera.source={seq}", "finder.init_box=[1,2,3,4]"])
    assert kept == [f"camera.source={seq}", "finder.init_box=[1,2,3,4]"]


def test_demo_scene_goes_to_the_source_node_whatever_its_name(tmp_path):
    graph, overrides = demo_graph(str(_renamed_graph(tmp_path)), "lookalike", [])
    assert graph.nodes["camera"].params["source"] == "scene:lookalike"
    assert overrides == ["camera.source=scene:lookalike"]  # a scene has no first box to give


def test_demo_scene_without_a_source_node_is_a_usage_error(tmp_path):
    path = tmp_path / "no-source.yaml"
    path.write_text("name: t\nnamespace: t\nnodes:\n  clock:\n    run: followbus.nodes.diagnostics\n")
    with pytest.raises(UsageError, match="--scene: no node of .* takes a source"):
        demo_graph(str(path), "lookalike", [])
