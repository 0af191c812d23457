"""A bad graph.yaml exits with status 2 and names the file, the line and the key."""

from __future__ import annotations

import dataclasses

import pytest

from .conftest import REPO, run_followbus

GOOD_NODES = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 10}
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs:
      tick: {from: ticker/tick, queue: 2, policy: drop_oldest}
"""


def test_good_graph_passes(graph_file):
    result = run_followbus("check", str(graph_file(GOOD_NODES)))
    assert result.returncode == 0, result.stderr
    assert "ok (2 nodes)" in result.stdout


# (what, nodes yaml, expected line in the file, text expected in the message)
# The file has 6 header lines (name, namespace, zenoh x3, nodes), so node text starts at line 7.
CASES = [
    ("unknown node key", GOOD_NODES.replace("    outputs: [tick]\n", "    outputs: [tick]\n    colour: red\n"),
     10, "unknown key 'colour'"),
    ("unknown producer node", GOOD_NODES.replace("from: ticker/tick", "from: camera/tick"),
     14, "unknown node 'camera'"),
    ("unknown output", GOOD_NODES.replace("from: ticker/tick", "from: ticker/frames"),
     14, "has no output 'frames'"),
    ("duplicate node name", GOOD_NODES + "  ticker:\n    run: followbus.nodes.diagnostics\n",
     15, "duplicate node name 'ticker'"),
    ("wrong type", GOOD_NODES.replace("queue: 2", "queue: two"), 14, "queue must be an integer"),
    ("unknown param", GOOD_NODES.replace("rate_hz: 10", "rate_hz: 10, speed: 3"), 10, "unknown parameter 'speed'"),
    ("wrong param type", GOOD_NODES.replace("rate_hz: 10", "rate_hz: fast"), 10, "'rate_hz' must be float"),
    ("missing run", GOOD_NODES.replace("    run: followbus.nodes.diagnostics\n", "", 1),
     7, "missing required key 'run'"),
    ("no such module", GOOD_NODES.replace("nodes.diagnostics\n", "nodes.nope\n", 1), 7, "No module named"),
    ("input the node does not take", GOOD_NODES.replace("      tick: {", "      tock: {"), 14, "has no input 'tock'"),
    ("bad policy", GOOD_NODES.replace("drop_oldest", "drop_newest"), 14, "policy must be one of"),
    ("future offset", GOOD_NODES.replace("queue: 2", "offset: 1"), 14, "offset must be 0 or -1"),
    ("bad restart policy", GOOD_NODES.replace("    outputs: [tick]\n", "    outputs: [tick]\n    restart: sometimes\n"),
     10, "restart: policy must be one of"),
    ("invalid yaml", GOOD_NODES.replace("outputs: [tick]", "outputs: [tick"), 10, "invalid YAML"),
]


@pytest.mark.parametrize("what,nodes,line,message", CASES, ids=[c[0] for c in CASES])
def test_bad_graph_exits_2_with_file_line_and_key(graph_file, what, nodes, line, message):
    path = graph_file(nodes)
    result = run_followbus("check", str(path))
    assert result.returncode == 2, (what, result.stdout, result.stderr)
    first = result.stderr.strip().splitlines()[-1]
    assert f"{path}:{line}:" in first, first
    assert message in first, first


def test_unknown_top_level_key_and_launch_also_exit_2(tmp_path):
    path = tmp_path / "g.yaml"
    path.write_text("name: x\nnodez: {}\n")
    result = run_followbus("launch", str(path), "--duration", "1")
    assert result.returncode == 2
    assert f"{path}:2: unknown key 'nodez'" in result.stderr


def test_missing_file_exits_2(tmp_path):
    result = run_followbus("check", str(tmp_path / "absent.yaml"))
    assert result.returncode == 2 and "absent.yaml" in result.stderr and "cannot read" in result.stderr


def test_robot_graph_runs_the_same_nodes_as_graph_yaml():
    """graph.robot.yaml differs from graph.yaml only in its bus; its node section drifted once (stale
    odometry sync and no feedback sync timeouts on the robot), so the two are compared here."""
    from followbus.bus.graph import load_graph

    def without_lines(value):  # where a key sits in its file is not what it means
        if isinstance(value, dict):
            return {k: without_lines(v) for k, v in value.items() if k not in ("line", "param_lines")}
        return [without_lines(v) for v in value] if isinstance(value, list) else value

    dev, robot = load_graph(REPO / "graph.yaml"), load_graph(REPO / "graph.robot.yaml")
    nodes = {g: {n: without_lines(dataclasses.asdict(spec)) for n, spec in graph.nodes.items()}
             for g, graph in (("dev", dev), ("robot", robot))}
    assert nodes["robot"] == nodes["dev"]
    assert robot.zenoh.mode == "router" and dev.zenoh.mode == "peer"


# --------------------------------------------------------------------------- graphs that cannot run (issue 25)

GRAPH_YAML = (REPO / "graph.yaml").read_text()
# (what, (old, new) replacements in graph.yaml, text expected in the one line)
CANNOT_RUN = [
    ("NaN gate", [("      gate_chi2: 9.488\n      camera", "      gate_chi2: .nan\n      camera")],
     "'gate_chi2' must be finite"),
    ("infinite param in a list", [("      tau_v: 220\n", "      tau_v: [1, .inf]\n")], "must be finite"),
    ("NaN sync timeout", [("    sync_timeout_ms: 300                   #", "    sync_timeout_ms: .nan  #")],
     "sync_timeout_ms must be a finite number > 0"),
    ("infinite sync timeout", [("    sync_timeout_ms: 300                   #", "    sync_timeout_ms: .inf  #")],
     "sync_timeout_ms must be a finite number > 0"),
    ("NaN lag bound", [("nodes:\n", "max_lag_ms: .nan\nnodes:\n")], "max_lag_ms must be a finite number"),
    ("same-frame cycle", [("template: {from: template/template, queue: 32, offset: -1, optional: true}",
                           "template: {from: template/template, queue: 32, optional: true}")],
     "same-frame cycle reid -> template -> reid"),
    ("zero input size", [("      input_size_px: 416\n", "      input_size_px: 0\n")],
     "input_size_px must be a positive multiple of 32"),
    ("capture of width 0", [('      pace: realtime ', '      width_px: 0\n      pace: realtime ')],
     "width_px must be >= 16"),
    # issue 36: accepted, then detection crash-looped on a 20 PiB allocation (a scene of that width alike)
    ("impossible input size", [("      input_size_px: 416\n", "      input_size_px: 100000000\n")],
     "input_size_px must be at most 4096"),
    ("scene wider than 8K", [('      pace: realtime ', '      width_px: 100000000\n      pace: realtime ')],
     "width_px must be at most 8192"),
    ("unknown zenoh config key", [("zenoh:\n", "zenoh:\n  config: {transport/auth/usrpwdd: {user: a}}\n")],
     "zenoh: config: transport/auth/usrpwdd: unknown key"),
    ("mistyped zenoh config value", [("zenoh:\n", "zenoh:\n  config: {transport/link/tls/enable_mtls: 'yes'}\n")],
     "expected a boolean"),
    ("impossible endpoint", [("listen: [tcp/127.0.0.1:7447]", "listen: [tcp/999.1.1.1:99999]")],
     "endpoint 'tcp/999.1.1.1:99999'"),
    ("bad IP address", [("connect: [tcp/127.0.0.1:7447]", "connect: [tcp/999.1.1.1:7447]")],
     "'999.1.1.1' is not an IP"),
    ("empty run", [("    run: followbus.nodes.motor\n", '    run: ""\n')], "run must name a Python module"),
    ("relative run", [("    run: followbus.nodes.motor\n", "    run: ..template\n")],
     "run must name a Python module"),
]


@pytest.mark.parametrize("what,edits,message", CANNOT_RUN, ids=[c[0] for c in CANNOT_RUN])
def test_check_refuses_a_graph_that_cannot_run(tmp_path, capsys, what, edits, message):
    from followbus.tools.cli import main

    text = GRAPH_YAML
    for old, new in edits:
        assert old in text, (what, old)
        text = text.replace(old, new, 1)
    path = tmp_path / "graph.yaml"
    path.write_text(text)
    assert main(["check", str(path)]) == 2, what
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert message in err and str(path) in err, err


def test_an_impossible_model_size_is_one_line_at_its_line(tmp_path, capsys):
    from followbus.tools.cli import main

    text = GRAPH_YAML.replace("      input_size_px: 416\n", "      input_size_px: 100000000\n", 1)
    path = tmp_path / "graph.yaml"
    path.write_text(text)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"followbus: {path}:{_line_of(text, 'input_size_px: 100000000')}: node 'detection': "
                          "input_size_px must be at most 4096"), err


def test_check_refuses_a_set_override_that_is_not_finite(capsys):
    from followbus.tools.cli import main

    assert main(["check", str(REPO / "graph.yaml"), "--set", "prediction.gate_chi2=.nan"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("followbus: --set prediction.gate_chi2=.nan:") and "must be finite" in err


# --------------------------------------------------------------------------- parameters a node does not read (issue 24)


def _check_error(capsys, path) -> str:
    from followbus.tools.cli import main

    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def _line_of(text: str, needle: str, after: str = "") -> int:
    """The 1-based line of the first ``needle`` after the first ``after``."""
    start = text.index(after)
    return text[:text.index(needle, start)].count("\n") + 1


def test_a_parameter_the_node_does_not_read_fails_check_at_its_line(tmp_path, capsys):
    """Re-ID gates with the prior's χ² (prediction's): a gate_chi2 on reid would be accepted and ignored."""
    text = GRAPH_YAML.replace("      reid_threshold: 0.75\n", "      reid_threshold: 0.75\n      gate_chi2: 12.0\n", 1)
    path = tmp_path / "graph.yaml"
    path.write_text(text)
    err = _check_error(capsys, path)
    line = _line_of(text, "gate_chi2: 12.0")
    assert f"{path}:{line}: node 'reid': reid does not read 'gate_chi2'; prediction does" in err, err
    launched = run_followbus("launch", str(path), "--duration", "1")  # refused before anything starts
    assert launched.returncode == 2 and f"{path}:{line}: node 'reid'" in launched.stderr, launched.stderr
    # A name no node reads at all: the node's own parameters are listed.
    path.write_text(GRAPH_YAML.replace("      tau_s: 45\n", "      tau_sat: 45\n", 1))
    err = _check_error(capsys, path)
    assert f"{path}:{_line_of(GRAPH_YAML, 'tau_s: 45')}: node 'template': unknown parameter 'tau_sat' (known: " in err


def test_an_unread_parameter_is_reported_in_the_file_that_sets_it(tmp_path, capsys):
    """Through ``extends``: the line of the file that holds the parameter, the override's or the base's."""
    over = tmp_path / "over.yaml"
    over.write_text(f"extends: {REPO / 'graph.yaml'}\nnodes:\n  template:\n    params:\n      gate_chi2: 9.0\n")
    assert f"{over}:5: node 'template': template does not read 'gate_chi2'; prediction does" in \
        _check_error(capsys, over)
    base_text = GRAPH_YAML.replace("      eta_base: 0.02\n", "      eta_base: 0.02\n      dt_ms: 33.0\n", 1)
    base = tmp_path / "base.yaml"
    base.write_text(base_text)
    over.write_text("extends: base.yaml\nnodes:\n  template:\n    params:\n      tau_v: 200\n")
    err = _check_error(capsys, over)
    assert f"{base}:{_line_of(base_text, 'dt_ms: 33.0', 'eta_base')}: node 'template': template does not read " \
           "'dt_ms'; prediction and redetection and reid do" in err, err


def test_a_parameter_out_of_range_points_at_its_line(tmp_path, capsys):
    """A tracking class's own range check names its parameter, so the error is at that line, not the node's."""
    text = GRAPH_YAML.replace("      reid_threshold: 0.75\n", "      reid_threshold: 1.75\n", 1)
    path = tmp_path / "graph.yaml"
    path.write_text(text)
    err = _check_error(capsys, path)
    assert f"{path}:{_line_of(text, 'reid_threshold: 1.75')}: node 'reid': ReidParams.reid_threshold must be in " \
           "[0, 1], got 1.75" in err, err



@pytest.mark.parametrize(("graph", "node", "param", "message"), [
    ("graph.yaml", "motor", "max_speed_mps: -2.0", "FollowParams.max_speed_mps must be finite and > 0, got -2.0"),
    ("graph.group.yaml", "group", "gate_chi2: -1.0", "GroupParams.gate_chi2 must be > 0, got -1.0"),
    ("graph.group.yaml", "groundplane", "focal_px: -1.0", "focal_px must be finite and > 0, got -1.0"),
    ("graph.group.yaml", "groundplane", "range_from: knee", "range_from must be 'foot' or 'width', not 'knee'"),
], ids=["follow", "group", "camera-geometry", "ground-plane"])
def test_every_range_check_points_at_its_parameter_line(tmp_path, capsys, graph, node, param, message):
    """The control, group and ground-plane classes check their own ranges too, naming the parameter."""
    over = tmp_path / "over.yaml"
    over.write_text(f"extends: {REPO / graph}\nnodes:\n  {node}:\n    params:\n      {param}\n")
    assert f"{over}:5: node '{node}': {message}" in _check_error(capsys, over)

def _attributes_read_by(module: str) -> set[str]:
    """Every attribute name the code of ``module`` and of the nodes/tracking/control/vision modules it imports
    (transitively, by relative import) reads: what a node's parameters can be read through."""
    import ast

    seen: set[str] = set()
    todo, attributes = [module], set()
    while todo:
        name = todo.pop()
        parts = name.split(".")
        path = REPO.joinpath(*parts[1:]).with_suffix(".py")
        if name in seen or len(parts) < 3 or parts[1] not in ("nodes", "tracking", "control", "vision") \
                or not path.exists():
            continue
        seen.add(name)
        tree = ast.parse(path.read_text())
        attributes |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
        todo += [".".join(parts[:len(parts) - n.level] + [n.module]) for n in ast.walk(tree)
                 if isinstance(n, ast.ImportFrom) and n.level and n.module]
    return attributes


def test_every_parameter_a_node_declares_is_read_by_its_code():
    """The other half of "a node declares exactly what it reads": no declared parameter that no code of the node
    reads (a setting that would be accepted and change nothing)."""
    from followbus.bus.graph_schema import node_runs

    for run, classes in node_runs("followbus.nodes").items():
        read = _attributes_read_by(run)
        unread = [f.name for c in classes for f in dataclasses.fields(c) if f.name not in read]
        assert not unread, f"{run} declares parameters no code of it reads: {unread}"


def test_a_renamed_parameter_still_loads_under_its_old_name(tmp_path, capsys, caplog):
    """detection's input_size became input_size_px (units in the names): a graph, or a recording's graph, written
    before still loads, with a warning; a bad value is still reported at its line."""
    from followbus.bus.graph import load_graph
    from followbus.bus.node_checks import validate_node

    path = tmp_path / "graph.yaml"
    path.write_text(GRAPH_YAML.replace("      input_size_px: 416\n", "      input_size: 640\n", 1))
    graph = load_graph(path)
    assert validate_node(graph, graph.nodes["detection"])[1].input_size_px == 640
    assert "'input_size' is now called 'input_size_px'" in caplog.text
    text = GRAPH_YAML.replace("      input_size_px: 416\n", "      input_size: 100\n", 1)
    path.write_text(text)
    err = _check_error(capsys, path)
    assert f"{path}:{_line_of(text, 'input_size: 100')}: node 'detection': input_size_px must be a positive " in err


@pytest.mark.parametrize("target", ["fifo", "/dev/zero", "directory"])
@pytest.mark.parametrize("command", ["check", "launch"])
def test_extends_only_a_regular_file(tmp_path, target, command):
    """A FIFO waits for a writer for ever and /dev/zero never ends: both hung `check` (issue 25)."""
    import os

    if target == "fifo":
        base = tmp_path / "base.yaml"
        os.mkfifo(base)
    elif target == "directory":
        base = tmp_path / "base.d"
        base.mkdir()
    else:
        base = target
    path = tmp_path / "g.yaml"
    path.write_text(f"extends: {base}\nnamespace: r2x\n")
    result = run_followbus(command, str(path), *(["--duration", "1"] if command == "launch" else []), timeout=30)
    assert result.returncode == 2, result.stderr
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1 and f"{path}:1: extends:" in err and "not a regular file" in err, err


def test_graph_file_itself_must_be_a_regular_file(tmp_path):
    import os

    fifo = tmp_path / "graph.yaml"
    os.mkfifo(fifo)
    result = run_followbus("check", str(fifo), timeout=30)
    assert result.returncode == 2 and "not a regular file" in result.stderr, result.stderr


@pytest.mark.parametrize("name", ["graph.yaml", "graph.group.yaml", "graph.robot.yaml"])
def test_every_node_of_a_shipped_graph_has_a_reader(name):
    """A node no other node reads only takes CPU from those that matter: graph.group.yaml ran graph.yaml's
    egomotion for nobody, and on a loaded machine that starved the group node into skipping seconds of frames."""
    from followbus.bus.graph import load_graph

    graph = load_graph(REPO / name)
    read = {spec.source_node for node in graph.nodes.values() for spec in node.inputs.values()}
    assert not [n for n in graph.nodes if n not in read], f"{name}: nodes nobody reads"


# Numbers where a negative value means something: a random seed, and the camera's pose on the robot.
SIGNED_PARAMS = {"seed", "camera_tilt_rad", "camera_forward_m", "camera_left_m"}


@pytest.mark.parametrize("graph_name", ["graph.yaml", "graph.group.yaml", "graph.robot.yaml"])
def test_every_number_of_the_shipped_graphs_refuses_a_negative_value(graph_name):
    """A duration, rate, threshold or count below 0 is a mistake `check`, `launch` and `param set` name, not a node
    that runs with it (a negative track age refused every track; a negative score gate let everything through)."""
    import importlib
    import typing

    from followbus.bus.node_params import params_classes, parse_params
    from followbus.tools.domains import load_graph

    graph = load_graph(str(REPO / graph_name))
    accepted = []
    for name, spec in graph.nodes.items():
        params_spec = importlib.import_module(spec.run).NODE.Params
        for cls in params_classes(params_spec):
            hints = typing.get_type_hints(cls)
            for field in dataclasses.fields(cls):
                if hints[field.name] not in (int, float) or field.name in SIGNED_PARAMS:
                    continue
                try:
                    parse_params(params_spec, {**(spec.params or {}), field.name: -1})
                except ValueError:
                    continue
                accepted.append(f"{name}.{field.name}")
    assert not accepted, f"{graph_name}: -1 accepted by {', '.join(accepted)}"
