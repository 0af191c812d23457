"""graph.yaml as a YAML tree: read (a regular text file only), composed with line marks that name their file,
and merged onto the files it extends (``extends:``)."""

from __future__ import annotations

import io
import stat
from pathlib import Path
from typing import Any

import yaml

from .spec import GraphError, SourceLine

_SCALARS = yaml.SafeLoader("")  # only used to construct scalar values from composed nodes

def line_of(node: yaml.Node) -> SourceLine:
    return SourceLine(node.start_mark.line + 1, node.start_mark.name)


def plain(node: yaml.Node, path: str) -> Any:
    """Convert a composed YAML node to Python values, rejecting duplicate keys."""
    if isinstance(node, yaml.MappingNode):
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            key = plain(key_node, path)
            if key in out:
                raise GraphError(path, line_of(key_node), f"duplicate key {key!r}")
            out[key] = plain(value_node, path)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [plain(item, path) for item in node.value]
    return _SCALARS.construct_object(node, deep=True)


def mapping_items(node: yaml.Node, path: str, what: str) -> list[tuple[str, yaml.Node, yaml.Node]]:
    if not isinstance(node, yaml.MappingNode):
        raise GraphError(path, line_of(node), f"{what} must be a mapping")
    items = []
    for key_node, value_node in node.value:
        if not isinstance(key_node, yaml.ScalarNode):
            raise GraphError(path, line_of(key_node), f"{what}: keys must be plain names")
        items.append((key_node.value, key_node, value_node))
    return items




_NULL_TAG = "tag:yaml.org,2002:null"


def read_text(path: str, text: str | None, read_from: tuple[str, int | None] | None = None) -> str:
    if text is not None:
        return text
    try:
        # Only a regular file: reading a FIFO waits for a writer for ever, /dev/zero never ends.
        if not stat.S_ISREG(Path(path).stat().st_mode):
            raise GraphError(read_from[0] if read_from else path, read_from[1] if read_from else None,
                             f"{'extends: ' if read_from else ''}{path} is not a regular file")
        return Path(path).read_text()
    except OSError as exc:
        if read_from is not None:  # a base file: the error is the extends line's
            raise GraphError(read_from[0], read_from[1], f"extends: cannot read {path}: {exc.strerror}") from exc
        raise GraphError(path, None, f"cannot read: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        where = (read_from[0], read_from[1]) if read_from else (path, None)
        raise GraphError(*where, f"{'extends: ' if read_from else ''}{path} is not a text file ({exc.reason})") \
            from exc


# libyaml's parser where PyYAML was built with it: a tenth of the pure-Python one's time (evaluation builds the
# graph once per sequence and run).
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _compose(path: str, text: str) -> yaml.Node:
    stream = io.StringIO(text)
    stream.name = path  # type: ignore[misc]  # every mark, so every line, names this file
    loader = _LOADER(stream)
    try:
        root = loader.get_single_node()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        context = getattr(exc, "context", None)
        detail = f"{problem} ({context})" if context else problem
        raise GraphError(path, mark.line + 1 if mark else None, f"invalid YAML: {detail}") from exc
    finally:
        loader.dispose()
    if root is None:
        raise GraphError(path, 1, "empty graph file")
    return root


def compose_graph(path: str, text: str, chain: tuple[tuple[str, str], ...]) -> tuple[yaml.Node, list[str]]:
    """The file's YAML tree with every file it extends merged under it, and the files (base first).

    ``chain``: the (path, resolved path) of the files that extend this one, to tell a cycle."""
    root = _compose(path, text)
    if not isinstance(root, yaml.MappingNode):
        return root, [path]  # the validator says what is wrong with it
    items = _unique_items(root, ())
    if "extends" not in items:
        return root, [path]
    key_node, value_node = items["extends"]
    line = line_of(value_node)
    target = plain(value_node, path)
    if not isinstance(target, str) or not target.strip():
        raise GraphError(path, line, "extends must be the path of a graph file (relative to this one)")
    base = str(Path(path).parent / target)
    chain = (*chain, (path, str(Path(path).resolve())))
    if str(Path(base).resolve()) in {resolved for _, resolved in chain}:
        raise GraphError(path, line, f"extends: cycle {' -> '.join([*(p for p, _ in chain), base])}")
    base_root, files = compose_graph(base, read_text(base, None, (path, line)), chain)
    if not isinstance(base_root, yaml.MappingNode):
        raise GraphError(base, line_of(base_root), "graph must be a mapping")
    own = yaml.MappingNode(root.tag, [(k, v) for k, v in root.value if k is not key_node], start_mark=root.start_mark,
                           end_mark=root.end_mark, flow_style=root.flow_style)
    return _merge(base_root, own, (), base), [*files, path]


def _unique_items(node: yaml.MappingNode, where: tuple[str, ...]) -> dict[str, tuple[yaml.Node, yaml.Node]]:
    items: dict[str, tuple[yaml.Node, yaml.Node]] = {}
    for key_node, value_node in node.value:
        if not isinstance(key_node, yaml.ScalarNode):
            raise GraphError(node.start_mark.name, line_of(key_node), f"{_dotted(where)}: keys must be plain names")
        if key_node.value in items:
            raise GraphError(node.start_mark.name, line_of(key_node),
                             f"duplicate key {_dotted((*where, key_node.value))!r}")
        items[key_node.value] = (key_node, value_node)
    return items


def _dotted(where: tuple[str, ...]) -> str:
    return ".".join(where) or "graph"


def _is_param_value(where: tuple[str, ...]) -> bool:
    """Whether ``where`` is (inside) one parameter's value: it replaces whole, and null there is a value (an
    Optional parameter's None), where everywhere else null removes the key."""
    return len(where) >= 4 and where[0] == "nodes" and where[2] == "params"


def _shorthand_key(where: tuple[str, ...]) -> str | None:
    """The key a scalar shorthand stands for here: an input 'capture/frame' is {from: capture/frame}, a restart
    'on-failure' is {policy: on-failure}."""
    if len(where) == 4 and where[0] == "nodes" and where[2] == "inputs":
        return "from"
    if len(where) == 3 and where[0] == "nodes" and where[2] == "restart":
        return "policy"
    return None


def _merge(base: yaml.Node, over: yaml.Node, where: tuple[str, ...], base_file: str) -> yaml.Node:
    """``over`` applied on top of ``base``: mappings merge key by key, anything else replaces."""
    shorthand = _shorthand_key(where)
    if shorthand and isinstance(over, yaml.MappingNode) and isinstance(base, yaml.ScalarNode):
        # {queue: 8} over 'capture/frame' keeps the source: the shorthand becomes the mapping it stands for.
        key = yaml.ScalarNode("tag:yaml.org,2002:str", shorthand, start_mark=base.start_mark, end_mark=base.end_mark)
        base = yaml.MappingNode("tag:yaml.org,2002:map", [(key, base)], start_mark=base.start_mark,
                                end_mark=base.end_mark, flow_style=True)
    if not (isinstance(base, yaml.MappingNode) and isinstance(over, yaml.MappingNode)) or _is_param_value(where):
        return over
    merged = _unique_items(base, where)
    for key, (key_node, value_node) in _unique_items(over, where).items():
        if value_node.tag == _NULL_TAG and not _is_param_value((*where, key)):
            if key not in merged:
                raise GraphError(over.start_mark.name, line_of(key_node),
                                 f"{_dotted((*where, key))}: null removes nothing ({base_file} has no such key)")
            del merged[key]
        elif key in merged:
            base_key, base_value = merged[key]
            value = _merge(base_value, value_node, (*where, key), base_file)
            # A mapping merged into the base's is still declared where the base declared it (a node's line).
            merged[key] = (key_node if value is value_node else base_key, value)
        else:
            merged[key] = (key_node, value_node)
    return yaml.MappingNode(over.tag, list(merged.values()), start_mark=over.start_mark, end_mark=over.end_mark,
                            flow_style=base.flow_style)

