"""The repository's structure is visible to tools that read files, not only to the installed package.

pyproject maps bus/, nodes/, tools/, ... into ``followbus.*`` (package-dir), so an absolute
``from followbus.bus.node import Node`` cannot be followed by path from the source tree: a structure drawing or an
editor's go-to-definition lost every arrow between the folders. Inside the package folders imports are therefore
explicit and relative (``from ..bus.node import Node``), and each must name a file of this repository.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = ("bus", "msgs", "nodes", "tools", "tracking", "control", "vision", "evaluation", "replay",
                "reliability", "viewing", "followbus")


def _modules() -> list[Path]:
    return sorted(p for d in PACKAGE_DIRS for p in (REPO / d).rglob("*.py"))


def _target(path: Path, node: ast.ImportFrom) -> Path:
    base = path.parent
    for _ in range(node.level - 1):
        base = base.parent
    return base.joinpath(*node.module.split(".")) if node.module else base


def _resolves(target: Path, names: list[str]) -> bool:
    if target.with_suffix(".py").is_file():
        return True
    init = target / "__init__.py"
    if init.is_file():  # a package: each name is one of its modules or something its __init__ defines
        tree = ast.parse(init.read_text(encoding="utf-8"))
        defined = {t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}
        defined |= {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        defined |= {a.asname or a.name for n in tree.body if isinstance(n, ast.ImportFrom) for a in n.names}
        return all((target / f"{n}.py").is_file() or n in defined for n in names)
    return False


def test_the_package_folders_import_each_other_by_relative_path():
    absolute = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            top = (node.module or "").split(".")[0] if isinstance(node, ast.ImportFrom) else ""
            if isinstance(node, ast.ImportFrom) and node.level == 0 and top == "followbus":
                absolute.append(f"{path.relative_to(REPO)}:{node.lineno} from {node.module}")
            elif isinstance(node, ast.Import) and any(a.name.split(".")[0] == "followbus" for a in node.names):
                absolute.append(f"{path.relative_to(REPO)}:{node.lineno} import followbus...")
    assert not absolute, "use relative imports inside the package folders:\n" + "\n".join(absolute)


def test_every_internal_import_names_a_file_of_the_repository():
    unresolved, count = [], 0
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                count += 1
                target = _target(path, node)
                if REPO not in target.resolve().parents or not _resolves(target, [a.name for a in node.names]):
                    where = f"{path.relative_to(REPO)}:{node.lineno}"
                    unresolved.append(f"{where} from {'.' * node.level}{node.module or ''}")
    assert count > 100, "the package folders should import each other"
    assert not unresolved, "imports that name no file of the repository:\n" + "\n".join(unresolved)


# --- tools/ as rooms ---------------------------------------------------------------------------------

# What stays at the top of tools/: the command line and what every room uses. Anything else belongs in a room.
TOOLS_TOP = {"__init__", "cli", "command", "errors", "connect", "domains", "launch", "demo", "models_cmd"}
TOOLS_ROOMS = {"recording", "live", "bench", "runs"}
LIBRARY_DIRS = ("bus", "msgs", "nodes", "tracking", "control", "vision", "evaluation", "replay", "reliability",
                "viewing")


def test_tools_is_rooms_not_a_hall():
    top = {p.stem for p in (REPO / "tools").glob("*.py")}
    assert top <= TOOLS_TOP, f"modules left flat in tools/ (put them in a room: {sorted(TOOLS_ROOMS)}): " \
                             f"{sorted(top - TOOLS_TOP)}"
    rooms = {p.parent.name for p in (REPO / "tools").glob("*/__init__.py")}
    assert rooms == TOOLS_ROOMS, rooms
    for room in rooms:  # each room lists its own commands, the rows tools/cli.py puts together
        assert (REPO / "tools" / room / "commands.py").is_file(), room


def test_every_package_folder_is_installed():
    """A folder with __init__.py that pyproject does not list is left out of a wheel (an editable install
    finds it anyway, so only a clean install shows it)."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"followbus." + ".".join(p.parent.relative_to(REPO).parts)
             for d in PACKAGE_DIRS if d != "followbus" for p in (REPO / d).rglob("__init__.py")}
    assert found <= listed, f"not in pyproject's [tool.setuptools] packages: {sorted(found - listed)}"


def test_the_libraries_never_import_the_tools():
    """bus/, nodes/ and the pure modules are what the tools are built on: never the other way round (reading
    a recording is bus/recording.py's, so capture can read one too)."""
    wrong = []
    for path in sorted(p for d in LIBRARY_DIRS for p in (REPO / d).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                target = _target(path, node).resolve()
                if target == REPO / "tools" or REPO / "tools" in target.parents:
                    wrong.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert not wrong, "imports of tools/ from below it:\n" + "\n".join(wrong)


def test_only_bus_recording_reads_mcap():
    """One reader of recordings: the mcap library's readers (and the byte-level parsing beside them) are used in
    bus/recording.py alone; tools write through mcap's writer and read through bus/recording.py (recover too:
    salvage_records)."""
    readers = {"mcap.reader": None, "mcap.stream_reader": None, "mcap.data_stream": {"ReadDataStream"}}
    users = set()
    for path in sorted(p for d in PACKAGE_DIRS for p in (REPO / d).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in readers:
                names = readers[node.module]
                if names is None or any(a.name in names for a in node.names):
                    users.add(str(path.relative_to(REPO)))
    assert users <= {"bus/recording.py"}, f"MCAP read outside bus/recording.py: {sorted(users - {'bus/recording.py'})}"


# --- messages are application types: bus/ is generic -------------------------------------------------

# Words of followbus's application (seed 000's tracker, the robot, the group follower), whole words in any case,
# and its message types, case-sensitive. "target" is not among them: bus/ uses it in its generic English sense
# (a thread's target, an override's target).
TRACKING_WORDS = re.compile(r"\b(kalman|re-?id|egomotion|odometry|motor|person|people|seeds?|tracker|tracking|tracks?"
                            r"|template|measurement|prior)\b", re.IGNORECASE)
APPLICATION_TYPES = re.compile(r"\b(TrackState|Detections|GroundTruth|MotorCommand|CameraMotion|GroundPoints"
                               r"|GroupState)\b")


def _imported_folders(path: Path) -> set[str]:
    """The top-level repository folders a module imports from (relative imports)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            target = _target(path, node).resolve()
            if REPO in target.parents:
                found.add(target.relative_to(REPO).parts[0])
    return found


def test_bus_knows_no_tracking_word():
    """bus/ is the generic layer: any message type, no word of the application, code and comments alike (the
    tracking messages and their ROS 2 mapping are msgs/'s)."""
    hits = []
    for path in sorted((REPO / "bus").rglob("*.py")):
        for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            found = TRACKING_WORDS.findall(line) + APPLICATION_TYPES.findall(line)
            if found:
                hits.append(f"{path.relative_to(REPO)}:{lineno} {sorted(set(found))}: {line.strip()}")
    assert not hits, "tracking vocabulary in bus/:\n" + "\n".join(hits)


def test_bus_imports_nothing_above_it_and_msgs_only_the_bus():
    """Layering: bus/ <- msgs/ <- tracking/, control/, vision/ <- nodes/ <- tools/."""
    wrong = [f"{p.relative_to(REPO)} imports {sorted(_imported_folders(p) - {'bus'})}"
             for p in sorted((REPO / "bus").rglob("*.py")) if _imported_folders(p) - {"bus"}]
    wrong += [f"{p.relative_to(REPO)} imports {sorted(_imported_folders(p) - {'bus', 'msgs'})}"
              for p in sorted((REPO / "msgs").rglob("*.py")) if _imported_folders(p) - {"bus", "msgs"}]
    assert not wrong, "\n".join(wrong)


def test_no_hand_written_bridge_between_messages_and_algorithms():
    """The algorithms use the message types themselves: no conversion module, no twin class of a message."""
    assert not (REPO / "nodes" / "convert.py").exists(), "nodes/convert.py is back: use the msgs/ types in tracking/"
    message_types = {n.name for p in (REPO / "msgs").glob("*.py") for n in ast.parse(p.read_text()).body
                     if isinstance(n, ast.ClassDef) and any(getattr(b, "id", "") == "Message" for b in n.bases)}
    assert {"Prior", "CameraMotion", "GroundPoints", "Odometry", "Measurement", "Track"} <= message_types
    twins = [f"{p.relative_to(REPO)}:{n.lineno} class {n.name}"
             for d in PACKAGE_DIRS if d != "msgs" for p in sorted((REPO / d).rglob("*.py"))
             for n in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
             if isinstance(n, ast.ClassDef) and n.name in message_types | {"OdometrySample", "Posterior"}]
    assert not twins, "classes that duplicate a message type:\n" + "\n".join(twins)


def test_one_box():
    """One Box in the repository (msgs/box.py); everything else imports it."""
    defined = []
    for path in sorted(p for d in PACKAGE_DIRS for p in (REPO / d).rglob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            names = [t.id for t in getattr(node, "targets", [getattr(node, "target", None)]) if isinstance(t, ast.Name)]
            if "Box" in names or (isinstance(node, ast.ClassDef) and node.name == "Box"):
                defined.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert defined == ["msgs/box.py:" + defined[0].split(":")[1]] if len(defined) == 1 else False, defined


# --- the import graph --------------------------------------------------------------------------------


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(path: Path, node: ast.ImportFrom) -> list[tuple[str, str]]:
    """(module, name) pairs of a relative import: ``from .a import b`` names module a (or a.b when b is a module)."""
    target = _target(path, node)
    base = _module_name(target.with_suffix(".py")) if target.with_suffix(".py").is_file() else \
        ".".join(target.relative_to(REPO).parts)
    out = []
    for alias in node.names:
        module = f"{base}.{alias.name}"
        out.append((module, "") if (target / f"{alias.name}.py").is_file() else (base, alias.name))
    return out


def _import_graph() -> tuple[dict[str, set[str]], list[str]]:
    """Every first-party module -> the first-party modules it imports (at any depth of the file: a function's lazy
    import and an ``if TYPE_CHECKING:`` import are arrows too), read with ast (nothing is imported), and the
    imports of private names (``_x``) from another package."""
    graph: dict[str, set[str]] = {}
    private = []
    for path in _modules():
        name = _module_name(path)
        graph.setdefault(name, set())
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not (isinstance(node, ast.ImportFrom) and node.level > 0):
                continue
            for module, imported in _imported(path, node):
                if module != name:
                    graph[name].add(module)
                if imported.startswith("_") and module.split(".")[0] != name.split(".")[0]:
                    private.append(f"{path.relative_to(REPO)}:{node.lineno} {imported} from {module}")
    return graph, private


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each a cycle of imports."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles_and_no_private_names_across_packages():
    graph, private = _import_graph()
    assert len(graph) > 100 and sum(map(len, graph.values())) > 200, "the import graph should span the repository"
    cycles = _cycles(graph)
    assert not cycles, "import cycles (a module may not import itself through others):\n" + \
        "\n".join(" <-> ".join(c) for c in cycles)
    assert not private, "private names imported from another package (make them public where they live):\n" + \
        "\n".join(private)


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


# evaluation/ scores followers without a bus; its one module that runs the graph (the in-process runtime) is named.
EVALUATION_ON_THE_BUS = {"evaluation/graph_follower.py"}


def test_evaluation_uses_the_bus_only_where_declared():
    users = set()
    for path in sorted((REPO / "evaluation").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                target = _target(path, node).resolve()
                if target == REPO / "bus" or REPO / "bus" in target.parents:
                    users.add(str(path.relative_to(REPO)))
    assert users <= EVALUATION_ON_THE_BUS, f"bus imports in evaluation/ outside {sorted(EVALUATION_ON_THE_BUS)}: " \
                                           f"{sorted(users - EVALUATION_ON_THE_BUS)}"
    assert users == EVALUATION_ON_THE_BUS, "the declared module no longer uses the bus: drop it from the list"


def _complexity_blocks(blocks):
    """radon's blocks (it lists methods beside their classes already) with the closures nested in functions."""
    for block in blocks:
        yield block
        yield from _complexity_blocks(getattr(block, "closures", []))


def test_no_function_outside_the_tests_is_below_grade_c():
    """The guide's rule for small functions, kept by the suite: radon's cyclomatic grade C (complexity 20) or
    better everywhere but the tests (twelve grade-D functions had crept in before this test; each was split)."""
    from radon.complexity import cc_rank, cc_visit

    too_complex = []
    for path in sorted(REPO.rglob("*.py")):
        rel = path.relative_to(REPO)
        if rel.parts[0] in {"tests", "build"} or any(part.startswith(".") for part in rel.parts):
            continue
        for block in _complexity_blocks(cc_visit(path.read_text())):
            if cc_rank(block.complexity) > "C":
                too_complex.append(f"{rel}:{block.lineno} {block.name} {cc_rank(block.complexity)} "
                                   f"({block.complexity})")
    assert not too_complex, "split these along their phases:\n" + "\n".join(too_complex)


def test_no_module_of_the_bus_is_hard_to_maintain():
    """radon's maintainability index of every bus/ module is 10 or more: the generic layer is read and changed most,
    and a 900-line module of every concern (graph.py and node.py before they were split) scored 0."""
    from radon.metrics import mi_visit

    low = {str(p.relative_to(REPO)): round(mi_visit(p.read_text(), multi=True), 1)
           for p in sorted((REPO / "bus").rglob("*.py"))}
    low = {path: mi for path, mi in low.items() if mi < 10}
    assert not low, f"split these along their concerns (maintainability index < 10): {low}"
