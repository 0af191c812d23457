"""``followbus param get|set NODE.PARAM [VALUE]``: a running node's parameters (bus/live_params.py answers)."""

from __future__ import annotations

import json

from ..errors import UsageError

ANSWER_TIMEOUT_S = 3.0


def _split(target: str) -> tuple[str, str]:
    node, dot, param = target.partition(".")
    if not dot or not node or not param:
        raise UsageError(f"{target!r}: name a node's parameter as NODE.PARAM, e.g. reid.reid_threshold")
    return node, param


def _ask(args, payload: bytes | None) -> dict:
    from ...bus.live_params import param_key
    from ..command import namespace, settings
    from ..connect import open_client_session

    node, param = _split(args.target)
    ns = namespace(args)
    joined = settings(args)
    session = open_client_session(joined)
    try:
        replies = list(session.get(param_key(ns, node, param), payload=payload, timeout=ANSWER_TIMEOUT_S))
        answers = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        if not answers:
            raise UsageError(_no_answer(session, joined, ns, node))
    finally:
        session.close()
    if not answers[0].get("ok"):
        raise UsageError(answers[0].get("error", "refused"))
    return answers[0]


def _no_answer(session, joined, ns: str, node: str) -> str:
    """Why no node answered: it is not running, or it is and the graph's access control dropped our query (Zenoh
    drops a denied query without a word), or it is and did not answer in time."""
    from ..connect import auth_user
    from ..live.silence import alive_nodes

    if node not in alive_nodes(session, ns, timeout_s=1.0):
        return (f"node {node!r} is not running in namespace {ns} (no answer in {ANSWER_TIMEOUT_S:g} s; "
                "`followbus nodes` lists the nodes up)")
    user = auth_user(joined.config)
    if user is None:
        return f"node {node!r} is up but did not answer in {ANSWER_TIMEOUT_S:g} s"
    return (f"param refused: {', '.join(joined.connect)} forwards no parameter query from user {user} (node {node!r} "
            "is up; access control: a read-only identity; param needs one allowed to, e.g. --user operator)")


def cmd_param_get(args) -> int:
    answer = _ask(args, None)
    live = "" if answer.get("live") else "  (not live-tunable: set at launch)"
    print(f"{args.target} = {json.dumps(answer['value'])}{live}")
    return 0


def cmd_param_set(args) -> int:
    from ...bus.graph import GraphError, parse_value

    try:
        value = parse_value(args.value, f"{args.target} {args.value}")  # as --set reads a value
    except GraphError as exc:
        raise UsageError(exc.message) from None
    answer = _ask(args, json.dumps(value).encode())
    print(f"{args.target}: {json.dumps(answer['before'])} -> {json.dumps(answer['value'])}")
    return 0
