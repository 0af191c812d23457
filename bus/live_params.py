"""A running node's parameters, read and changed over the bus (``followbus param get|set``, as ``ros2 param``).

Every node answers queries on ``<ns>/@param/<node>/<param>``: without a payload with the value it runs with;
with a JSON payload by setting it, when its params field is marked ``live`` (bus/node_params.py: only parameters
the node's code reads afresh on every message: a threshold, an age bound). A new value is validated as at
launch (``parse_params`` on the node's params with the value in), then written into the params
object the node runs with. Each change is published on ``<ns>/<node>/parameter_events`` (a NodeStatus whose
extra says which parameter, the value before and after), which ``followbus record`` records with the rest of
the namespace, and the node's status carries every value changed so far (``extra["params_set"]``).
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import logging
import threading
import time
from typing import Any

from .node_params import marked, param_names, parse_params
from .schemas import NodeStatus

log = logging.getLogger(__name__)

EVENTS_OUTPUT = "parameter_events"


def param_key(namespace: str, node: str, param: str = "*") -> str:
    return f"{namespace}/@param/{node}/{param}"


def _holders(params: Any) -> list[Any]:
    return list(params) if isinstance(params, tuple) else [params]


def current_value(params: Any, name: str) -> Any:
    for holder in _holders(params):
        if dataclasses.is_dataclass(holder) and name in {f.name for f in dataclasses.fields(holder)}:
            return getattr(holder, name)
    raise KeyError(name)


class LiveParams:
    """Answers get/set queries for one node (``runtime``: its NodeRuntime with session, spec, cls and params)."""

    def __init__(self, runtime: Any, publish: Any):
        self.runtime = runtime
        self.publish = publish  # (key, NodeStatus) -> None: the parameter event
        self.changed: dict[str, Any] = {}
        self._lock = threading.Lock()
        ns, name = runtime.graph.namespace, runtime.spec.name
        self.events_key = f"{ns}/{name}/{EVENTS_OUTPUT}"
        self._queryable = runtime.session.declare_queryable(param_key(ns, name), self._on_query)

    def _on_query(self, query: Any) -> None:
        param = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            answer = self.set(param, json.loads(payload)) if payload else self.get(param)
        except Exception as exc:  # a bad request is answered, never raised into zenoh's thread
            answer = {"ok": False, "error": str(exc)}
        query.reply(query.key_expr, json.dumps(answer, default=str).encode())

    def live(self) -> list[str]:
        return sorted(marked(self.runtime.cls.Params, "live"))

    def get(self, param: str) -> dict[str, Any]:
        try:
            value = current_value(self.runtime.params, param)
        except KeyError:
            close = difflib.get_close_matches(param, sorted(param_names(self.runtime.cls.Params)), n=1)
            hint = f" (did you mean {self.runtime.spec.name}.{close[0]}?)" if close else ""
            return {"ok": False, "error": f"node {self.runtime.spec.name!r} has no parameter {param!r}{hint}"}
        return {"ok": True, "value": value, "live": param in self.live()}

    def set(self, param: str, value: Any) -> dict[str, Any]:
        node = self.runtime.spec.name
        names = param_names(self.runtime.cls.Params)
        if param not in names:
            close = difflib.get_close_matches(param, sorted(names), n=1)
            hint = f"did you mean {node}.{close[0]}? " if close else ""
            return {"ok": False, "error": f"node {node!r} has no parameter {param!r} ({hint}live-tunable: "
                                          f"{', '.join(self.live()) or 'none'})"}
        if param not in self.live():
            live = ", ".join(self.live()) or "none"
            return {"ok": False, "error": f"{node}.{param} is not live-tunable (live: {live}); set it at launch "
                                          f"with --set {node}.{param}=VALUE"}
        raw = dict(self.runtime.spec.params, **{param: value})
        try:
            fresh = parse_params(self.runtime.cls.Params, raw)
        except Exception as exc:  # ParamError, or the dataclass's own check: as at launch
            return {"ok": False, "error": f"{node}.{param}: {exc}"}
        new = current_value(fresh, param)
        with self._lock:
            before = current_value(self.runtime.params, param)
            for holder in _holders(self.runtime.params):
                if dataclasses.is_dataclass(holder) and hasattr(holder, param):
                    setattr(holder, param, new)  # the object the node reads on its next message
            self.runtime.spec.params[param] = value
            self.changed[param] = new
        log.info("parameter %s set: %r -> %r", param, before, new)
        event = NodeStatus(node=node, state="param_set", extra={"param": param, "before": before, "value": new})
        event.header.stamp_ns = time.time_ns()
        self.publish(self.events_key, event)
        return {"ok": True, "value": new, "before": before, "live": True}

    def close(self) -> None:
        self._queryable.undeclare()
