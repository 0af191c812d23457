"""``followbus monitor``: a read-only view of a running graph from another machine: the terminal dashboard
(this module) and, with ``--web``, the web view (``webview.py``), both rendering the snapshots of
viewing/monitor.py's :class:`BusMonitor` (the state kept from the bus)."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from ...bus.session import ZenohSettings
from ...viewing.monitor import VALUE_STALE_S, BusMonitor, GraphInfo

RATE_SETTLE_S = 2.0
SEPARATOR = "=" * 72  # between snapshots when stdout is not a terminal


def monitor_settings(graph_path: str | None, connect: list[str] | None, user: str | None = None,
                     password: str | None = None, ca: str | None = None) -> ZenohSettings:
    """Client settings for a viewer on the laptop (tools/connect.py client_settings, the one builder)."""
    from ..connect import client_settings

    return client_settings(graph_path, connect, user, password, ca, viewer=True)


def graph_info(graph_path: str | None, namespace: str | None = None) -> GraphInfo:
    """What the viewers take from ``graph_path`` (when it exists; with this process's domain applied, as
    every command loads a graph), ``namespace`` winning over the graph's; without a graph file the namespace
    every other command would use ($FOLLOWBUS_NAMESPACE, $FOLLOWBUS_DOMAIN: tools/domains.py)."""
    from ..command import load_graph
    from ..domains import DefaultGraph, apply_domain

    graph = load_graph(graph_path) if graph_path and Path(graph_path).exists() else None
    if graph is None and not namespace:
        namespace = apply_domain(DefaultGraph()).namespace
    return GraphInfo.from_graph(graph, namespace)


# -- terminal rendering (rich: colours and in-place redraw on a terminal, plain text in a pipe) ------------
STATE_STYLE = {"up": "green", "stalled": "bold yellow", "done": "cyan", "down": "bold red"}
TRUST_STYLE = {"verified": "green", "unverified": "yellow", "spoofed?": "bold red"}
TARGET_STYLE = {"TRACKING": "green", "REACQUIRED": "cyan", "OCCLUDED": "yellow", "LOST": "red"}
PIPE_WIDTH = 200  # not a terminal: wide enough that no row wraps (scripts split lines into fields)


def _clock(ns: int) -> str:
    return time.strftime("%H:%M:%S", time.localtime(ns / 1e9))


def _num(value: Any, fmt: str = ".1f", missing: str = "-") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return missing
    return format(value, fmt)


def _count(value: int, style: str) -> Text:
    return Text(str(value), style=style if value else "")


def _table(columns: list[str], rows: list[list[str | Text]]) -> Table:
    # No rules (two spaces between columns: the topic table fits 80 columns) and no padding at the sides: a row
    # starts with its first field, as grep and split expect. Cells are Text, never markup ("[follow]").
    table = Table(box=None, pad_edge=False, header_style="bold", show_header=any(columns))
    for name in columns:
        # On a narrow terminal only the last column (the trust reason, the target) wraps.
        table.add_column(name, no_wrap=name != columns[-1], min_width=len("spoofed?" if name == "check" else name),
                         justify="left" if name in (columns[0], "state", "dir", "check", "") else "right")
    for row in rows:
        table.add_row(*(cell if isinstance(cell, Text) else Text(cell) for cell in row))
    return table


def _group_line(group: dict[str, Any]) -> str:
    if not group.get("valid"):
        return f"(no group yet)  frame {group['frame_seq']}"
    fwd, left = group["centre_robot_m"]
    return (f"{'LOST ' if group['lost'] else ''}{group['members']} members, {group['others']} left out, "
            f"{len(group.get('ellipses', []))} ellipses  centre {fwd:.2f} m ahead {left:+.2f} m left  "
            f"{group['speed_mps']:.2f} m/s  step {group['step_ms']:.1f} ms  frame {group['frame_seq']}")


def render(snap: dict[str, Any], height: int | None = None, width: int | None = None) -> Group:
    """The dashboard: a status line, the target and the motor command (each with its age), node health, per-topic
    statistics (cut to ``height`` lines, when given)."""
    if snap["connected"]:
        link = Text("connected", "green")
    else:
        error = f" ({snap['last_error'][:80]})" if snap.get("last_error") else ""
        link = Text(f"robot unreachable since {_clock(snap['unreachable_since_ns'])}{error}", "bold red")
    head = Text.assemble(("followbus monitor", "bold"), f"  {', '.join(snap['endpoints'])}  ns={snap['namespace']}"
                         f"  {_clock(snap['now_ns'])}  ", link)
    nodes, topics = [], []
    for n in snap["nodes"]:
        for_s = (snap["now_ns"] - n["since_ns"]) / 1e9 if n["since_ns"] else None
        trust = n["trust"] + (f" ({n['trust_reason']})" if n["trust_reason"] else "")
        state = n.get("state") or ("up" if n["alive"] else "down")
        nodes.append([n["name"], Text(state.upper() if state == "down" else state, STATE_STYLE.get(state, "")),
                      _num(for_s, ".0f"),
                      str(n["restarts"]), _num(n["pid"], "d"), _num(n["uptime_s"], ".0f"),
                      _count(n["handler_errors"], "red"), Text(trust, TRUST_STYLE.get(n["trust"], ""))])
        topics += [[f"{key} @{n['name']}", t.get("direction", "?"), _num(t.get("rate_hz")),
                    _num(t.get("latency_p50_ms")), _num(t.get("latency_p99_ms")), _count(t.get("drops", 0), "yellow"),
                    _count(t.get("lost", 0), "yellow"), _count(t.get("decode_errors", 0), "red")]
                   for key, t in sorted(n["topics"].items())]
    state = _state_rows(snap)
    group = snap.get("group")
    if group:  # group following (graph.group.yaml)
        state.insert(0, ["group", _group_line(group)])
    for link in snap.get("links", []):  # links that deliver nothing, or less than is sent (bus/links.py)
        state.append(["link", Text(link, "yellow")])
    if snap["decode_errors"]:
        state.append(["monitor", Text(f"{snap['decode_errors']} decode errors", "red")])
    if snap.get("namespaces_hint"):
        state.append(["monitor", Text(snap["namespaces_hint"], "yellow")])
    # As many topics as the terminal has lines for, so that the target and motor lines stay on screen (80x24).
    if height is not None:
        room = height - (len(head.wrap(Console(width=width or 80), width or 80)) + 2 * len(state) + len(nodes) + 6)
        if len(topics) > max(room, 1):
            more = len(topics) - max(room - 1, 0)
            topics = topics[:max(room - 1, 0)] + [[f"... {more} more (followbus topics)", "", "", "", "", "", "", ""]]
    topic_columns = ["topic (as seen by node)", "dir", "rate Hz", "p50 ms", "p99 ms", "drops", "lost", "dec err"]
    return Group(head, "", _table(["node", "state", "for s", "restarts", "pid", "uptime s", "errs", "check"], nodes),
                 "", _table(topic_columns, topics), "", _table(["", ""], state))


def _aged(label: str, value: Any, age: float | None, stale_s: float) -> list[Any]:
    """A state row whose value carries its age; past ``stale_s`` struck through, dimmed and labelled stale."""
    if age is None:
        return [label, value]
    text = value.copy() if isinstance(value, Text) else Text(str(value))
    if age > stale_s:
        text.stylize("dim strike")
        return [label, Text.assemble(text, (f"  STALE {age:.0f} s", "bold yellow"))]
    return [label, Text.assemble(text, (f"  {age:.1f} s", "dim"))]


def _state_rows(snap: dict[str, Any]) -> list[list[Any]]:
    target, cmd = snap.get("target"), snap.get("command")
    ages, stale_s = snap.get("ages", {}), snap.get("stale_after_s", VALUE_STALE_S)
    target_text = "(no track yet)" if not target else Text.assemble(
        (target["state"], TARGET_STYLE.get(target["state"], "")),
        f"  box {target['box']}  v {target['velocity']} px/s  frame {target['frame_seq']}"
        f"  centre err {_num(snap.get('centre_error_px'))} px")
    motor_text = (f"vx {cmd['vx_mps']:+.2f} m/s  vy {cmd['vy_mps']:+.2f} m/s  wz {cmd['wz_radps']:+.2f} rad/s  "
                  f"[{cmd['reason']}]  capture->command {_num(cmd['latency_ms'])} ms" if cmd else "(no command yet)")
    return [_aged("target", target_text, ages.get("track") if target else None, stale_s),
            _aged("eta_k", _num(snap.get("eta"), ".4f"), ages.get("template") if snap.get("eta") is not None
                  else None, stale_s),
            _aged("motor", motor_text, ages.get("command") if cmd else None, stale_s)]


def show(console: Console, snap: dict[str, Any]) -> None:
    """Print one dashboard: coloured on a terminal; otherwise plain lines without the cells' trailing blanks."""
    with console.capture() as captured:
        console.print(render(snap))
    text = captured.get()
    console.file.write(text if console.is_terminal else "".join(line.rstrip() + "\n" for line in text.splitlines()))
    console.file.flush()


def _all_up(snap: dict[str, Any], expected: list[str]) -> bool:
    by_name = {n["name"]: n for n in snap["nodes"]}
    names = expected or list(by_name)
    # Rates are over a window: a node up for less than RATE_SETTLE_S would show misleadingly low ones.
    return bool(names) and all(by_name.get(n, {}).get("alive") and by_name[n]["topics"]
                               and (by_name[n]["uptime_s"] or 0.0) >= RATE_SETTLE_S for n in names)


def _show(args: Any, info: GraphInfo, monitor: BusMonitor) -> int | None:
    """The dashboard until --seconds (for ever without); with --once one snapshot, and its exit status."""
    console = Console()  # colours on a terminal; in a pipe plain text (no ANSI), wide enough that no row wraps
    console = console if console.is_terminal else Console(width=PIPE_WIDTH)
    if args.once:
        # Wait for every node's token and a status message (topic rates), or the time limit.
        deadline = time.monotonic() + (args.seconds or 5.0)
        while time.monotonic() < deadline and not _all_up(monitor.snapshot(), info.nodes):
            time.sleep(0.1)
        snap = monitor.snapshot()
        show(console, snap)
        return 0 if snap["connected"] and _all_up(snap, info.nodes) else 1
    deadline = None if args.seconds is None else time.monotonic() + args.seconds
    if console.is_terminal:
        # Cut to the terminal's height: taller than the screen, Live cannot redraw in place (lines pile up).
        with Live(console=console, auto_refresh=False, vertical_overflow="crop") as live:
            while deadline is None or time.monotonic() < deadline:
                live.update(render(monitor.snapshot(), console.size.height, console.size.width), refresh=True)
                time.sleep(0.5)
    else:
        while deadline is None or time.monotonic() < deadline:
            console.file.write(SEPARATOR + "\n")
            show(console, monitor.snapshot())
            time.sleep(0.5)
    return None


def run_monitor(args: Any) -> int:
    """``followbus monitor``: terminal dashboard, one snapshot (--once), or the web view (--web)."""
    from ..connect import check_credentials

    settings = monitor_settings(args.graph, args.connect, args.user, args.password, args.ca)
    if getattr(args, "connect_timeout", None) is not None:
        settings.connect_timeout_ms = max(1, round(args.connect_timeout * 1000))
    info = graph_info(args.graph, args.namespace)
    check_credentials(settings)  # a refused password is one line (exit 2), not a robot shown unreachable
    if args.web is not None:
        from .webview import serve

        return serve(settings, info, args.bind, args.web, args.seconds, token=args.web_token)
    monitor = BusMonitor(settings, info).start()
    try:
        code = _show(args, info, monitor)
    except KeyboardInterrupt:
        # Ctrl-C ends the process at once (tools/cli.py _exit_interrupted) with the session left open: closing it
        # first waits on the link (the reader thread, each undeclare), past a user's patience and a test's 20 s on
        # a slow or loaded one. The monitor owns nothing to finish; the robot sees the session end with the process.
        raise
    except BaseException:
        monitor.close()
        raise
    monitor.close()
    if code is not None:
        return code
    if not monitor.ever_connected:  # a timed run that never saw the graph: not a success
        from ..connect import explain_connect_failure

        print(f"followbus: {explain_connect_failure(settings)}", file=sys.stderr)
        return 2
    return 0
