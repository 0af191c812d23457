"""Which graphs run on this machine, and a launch that refuses to start a node that already runs.

Every ``launch``/``demo``/``up`` holds an exclusive ``flock`` on ``<runs>/claims/<port>-<namespace>-<pid>.lock``
for its whole life, with its run record (name, graph file, namespace, endpoint, pid, start, the nodes it starts,
log directory) written in it. The kernel drops the lock when the process ends however it ends, so a record is
live exactly while its lock is held: no stale file, no reused pid can fool ``ps`` or the refusal. A launch is
refused when a node it would start already runs in its namespace on its endpoint (two captures feeding one set of
nodes, two motors answering one track stream); ``launch --only relay`` beside a running ``--only ticker`` of the
same graph is a legitimate split and is allowed. Claims of one (port, namespace) are made one at a time under
``<port>-<namespace>.guard``, so two launches started together cannot both pass. A graph started elsewhere
(another machine, an older followbus) is seen on the bus instead: liveliness tokens under ``<namespace>/@health/``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..domains import AUTO, MAX_DOMAIN, endpoint, parse_domain, well_known_port
from ..errors import UsageError

log = logging.getLogger(__name__)

RUNS_ENV = "FOLLOWBUS_RUNS"
CLAIM_RETRY_S = 0.5  # a `ps` holds a shared lock for a moment: a launch retries this long before it concludes
BUS_PROBE_S = 0.6


def runs_root() -> Path:
    """Where run records and detached runs' logs live: $FOLLOWBUS_RUNS, else ~/.local/state/followbus/runs."""
    given = os.environ.get(RUNS_ENV)
    if given:
        return Path(given)
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "followbus" / "runs"


@dataclass
class RunRecord:
    name: str
    graph: str
    namespace: str
    endpoint: str
    pid: int
    started: float
    nodes: list[str] = field(default_factory=list)
    command: str = "launch"
    log_dir: str = ""
    domain: int = 0
    uid: int = -1  # who started it: the claim file's owner (set when read)
    claim: str = ""  # the claim file (set when read)

    def uptime_s(self) -> float:
        return max(0.0, time.time() - self.started)

    @property
    def mine(self) -> bool:
        """Started by the user running this command (on a shared machine another user's graph runs beside)."""
        return self.uid == os.getuid()

    @property
    def user(self) -> str:
        import pwd

        try:
            return pwd.getpwuid(self.uid).pw_name
        except (KeyError, OverflowError):
            return str(self.uid)


def _claim_stem(port: int | None, namespace: str) -> str:
    return f"{port or 0}-{re.sub(r'[^A-Za-z0-9_.-]', '_', namespace)}"


def _claim_path(port: int | None, namespace: str, pid: int) -> Path:
    return runs_root() / "claims" / f"{_claim_stem(port, namespace)}-{pid}.lock"


def _guard_path(port: int | None, namespace: str) -> Path:
    return runs_root() / "claims" / f"{_claim_stem(port, namespace)}.guard"


def _read_record(path: Path) -> RunRecord | None:
    try:
        record = RunRecord(**json.loads(path.read_text() or "{}"))
        record.uid, record.claim = path.stat().st_uid, str(path)
        return record
    except (OSError, ValueError, TypeError):
        return None


def _held(path: Path) -> bool:
    """Whether a live process holds the claim (a shared lock cannot be had beside an exclusive one)."""
    try:
        with open(path) as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            return False
    except OSError:
        return False


def live_runs() -> list[RunRecord]:
    """Every graph running on this machine under this runs directory, oldest first."""
    out = []
    for path in sorted((runs_root() / "claims").glob("*.lock")):
        if _held(path) and (record := _read_record(path)) is not None:
            out.append(record)
    return sorted(out, key=lambda r: r.started)


class Claim:
    """This process's hold on (port, namespace); released at close or when the process ends."""

    def __init__(self, path: Path, handle: Any, record: RunRecord):
        self.path, self.handle, self.record = path, handle, record

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.handle.close()


def _try_lock(path: Path) -> Any | None:
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = open(path, "a+")  # noqa: SIM115 (held for the life of the run)
    deadline = time.monotonic() + CLAIM_RETRY_S
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return handle
        except BlockingIOError:
            if time.monotonic() >= deadline:
                handle.close()
                return None
            time.sleep(0.05)


def _bus_holder(graph: Any, starting: set[str]) -> str | None:
    """Nodes of ``starting`` alive on the graph's bus (seen by their liveliness tokens), described; None: none."""
    from ..connect import endpoint_listening

    if not any(endpoint_listening(ep) for ep in graph.zenoh.connect):
        return None
    import zenoh

    from ...bus.session import open_session

    settings = graph.zenoh.as_client()
    settings.connect_timeout_ms = 2000
    try:
        session = open_session(settings)
    except zenoh.ZError:
        return None  # something else listens there (or refuses us): launching will say so itself
    try:
        replies = session.liveliness().get(f"{graph.namespace}/@health/*", timeout=BUS_PROBE_S)
        alive = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}
    finally:
        session.close()
    nodes = sorted(alive & starting)
    if not nodes:
        return None
    return f"nodes {', '.join(nodes)} (started outside this machine's run records)"


def launched_nodes(graph: Any, only: list[str] | None = None) -> set[str]:
    """The nodes a launch of ``graph`` starts here: on a graph spread over hosts (bus/hosts.py) only this host's
    (the other hosts' are expected on the bus: a compute host joins a running robot), and of those ``--only``'s."""
    from ...bus.hosts import HOST_ENV, host_plan

    plan = host_plan(graph)
    names = set(graph.nodes) if len(plan) <= 1 else set(plan.get(os.environ.get(HOST_ENV, ""), []))
    return names & set(only) if only else names


def _live_claims(graph: Any) -> list[tuple[Path, RunRecord]]:
    stem = _claim_stem(well_known_port(graph.zenoh), graph.namespace)
    out = []
    for path in (runs_root() / "claims").glob(f"{stem}-*.lock"):
        if _held(path) and (record := _read_record(path)) is not None:
            out.append((path, record))
    return out


def _remove_dead_claims(graph: Any) -> None:
    """Claims of ended launches (their lock is free) go, with their health files; called under the guard, so no
    claim is half made."""
    stem = _claim_stem(well_known_port(graph.zenoh), graph.namespace)
    for path in (runs_root() / "claims").glob(f"{stem}-*.lock"):
        if not _held(path):
            with contextlib.suppress(OSError):
                path.unlink()
            with contextlib.suppress(OSError):
                path.with_suffix(HEALTH_SUFFIX).unlink()


# --- node health beside a run record (`followbus ps`) ----------------------------------------------------------

HEALTH_SUFFIX = ".health"
HEALTH_STALE_S = 5.0  # a launcher rewrites its health file every second: an older one says nothing


def health_path(graph: Any) -> Path:
    """The health file of this process's claim on ``graph`` (beside the claim: `<claim>.health`)."""
    return _claim_path(well_known_port(graph.zenoh), graph.namespace, os.getpid()).with_suffix(HEALTH_SUFFIX)


def write_health(path: Path, nodes: dict[str, dict[str, Any]]) -> None:
    """Replace the health file at once (a reader never sees half of one): each node's state and restarts."""
    if not path.with_suffix(".lock").exists():
        return  # no claim (a launcher run by a test or a bench, not by launch/demo/up): nobody lists it
    tmp = path.with_suffix(HEALTH_SUFFIX + ".tmp")
    tmp.write_text(json.dumps({"time": time.time(), "nodes": nodes}))
    os.replace(tmp, path)


def read_health(record: RunRecord) -> dict[str, dict[str, Any]] | None:
    """The nodes' health a running graph's launcher last wrote; None when there is none or it is stale."""
    try:
        data = json.loads(Path(record.claim).with_suffix(HEALTH_SUFFIX).read_text())
        if time.time() - float(data["time"]) > HEALTH_STALE_S or not isinstance(data["nodes"], dict):
            return None
        return data["nodes"]
    except (OSError, ValueError, TypeError, KeyError):
        return None


def holder(graph: Any, starting: set[str] | None = None) -> str | None:
    """Who already runs one of ``starting`` (default: every node of ``graph``) in ``graph``'s namespace on its
    endpoint, in words; None: nobody."""
    starting = set(graph.nodes) if starting is None else starting
    for _path, record in _live_claims(graph):
        if starting & set(record.nodes):
            return (f"graph {record.name!r} (pid {record.pid}, started by `followbus {record.command}`; "
                    f"`followbus down {record.pid}` stops it)")
    return _bus_holder(graph, starting)


def refusal(graph: Any, who: str) -> str:
    return (f"{who} is already running on {endpoint(graph)} with namespace {graph.namespace}: start this one in "
            "another domain (--domain N, FOLLOWBUS_DOMAIN=N, or --domain auto for the first free one)")


def _check_port_free(graph: Any) -> None:
    """UsageError when another process's connection holds the graph's well-known port: its peers could not meet
    there (each node would run alone, and the launch time out). A port in the kernel's ephemeral range is said once:
    an outgoing connection may take it at any start."""
    from ..connect import endpoint_held_without_listener, ephemeral_port_range

    port = well_known_port(graph.zenoh)
    for ep in graph.zenoh.listen:
        if endpoint_held_without_listener(ep):
            raise UsageError(f"port {port} ({ep}) is held by another process's connection and nothing listens there, "
                             "so this graph's nodes could not meet on it: start it in another domain (--domain N, or "
                             "--domain auto for the first free one) or on another --port")
    span = ephemeral_port_range()
    if port is not None and span is not None and span[0] <= port <= span[1]:
        log.warning("port %d lies in this machine's ephemeral port range (%d-%d): an outgoing connection may hold it "
                    "when the graph starts; a port below %d cannot be taken so", port, span[0], span[1], span[0])


def claim(graph: Any, command: str, log_dir: str = "", domain: int = 0, only: list[str] | None = None) -> Claim:
    """Hold the graph's (port, namespace) for the nodes this process starts, or raise UsageError naming who runs
    one of them already."""
    port = well_known_port(graph.zenoh)
    guard = _try_lock(_guard_path(port, graph.namespace))
    if guard is None:
        raise UsageError(refusal(graph, "another followbus launch (starting now)"))
    try:
        _remove_dead_claims(graph)
        starting = launched_nodes(graph, only)
        who = holder(graph, starting)
        if who is not None:
            raise UsageError(refusal(graph, who))
        _check_port_free(graph)
        path = _claim_path(port, graph.namespace, os.getpid())
        handle = _try_lock(path)
        if handle is None:  # this very process claimed it already
            raise UsageError(refusal(graph, "this process"))
        record = RunRecord(name=graph.name, graph=str(Path(graph.path).resolve()), namespace=graph.namespace,
                           endpoint=endpoint(graph), pid=os.getpid(), started=time.time(),
                           nodes=sorted(starting), command=command, log_dir=log_dir, domain=domain)
        handle.seek(0)
        handle.truncate()
        handle.write(json.dumps(asdict(record)))
        handle.flush()
        return Claim(path, handle, record)
    finally:
        guard.close()


def _load_at(path: str, domain: int) -> Any:
    from ..command import load_graph
    from ..domains import DOMAIN_ENV

    saved = os.environ.get(DOMAIN_ENV)
    os.environ[DOMAIN_ENV] = str(domain)
    try:
        return load_graph(path)
    finally:
        if saved is None:
            del os.environ[DOMAIN_ENV]
        else:
            os.environ[DOMAIN_ENV] = saved


def _first_domain() -> int:
    return parse_domain(os.environ.get("FOLLOWBUS_DOMAIN"), "$FOLLOWBUS_DOMAIN") or 0


def free_domain(path: str) -> tuple[int, str]:
    """The first domain from $FOLLOWBUS_DOMAIN (or 0) where nobody runs this graph, and the line saying why it is
    not the first ("" when it is)."""
    first = _first_domain()
    for domain in range(first, MAX_DOMAIN + 1):
        if holder(_load_at(path, domain)) is None:
            return domain, _moved(path, first, domain)
    raise UsageError(f"every domain {first}..{MAX_DOMAIN} has a graph running (`followbus ps` lists them)")


def _moved(path: str, first: int, domain: int) -> str:
    if domain == first:
        return ""
    taken, graph = _load_at(path, first), _load_at(path, domain)
    return (f"domain {first} ({endpoint(taken)}, namespace {taken.namespace}) is taken; running in domain {domain}: "
            f"{endpoint(graph)}, namespace {graph.namespace} (watch it with FOLLOWBUS_DOMAIN={domain} "
            "followbus monitor)")


def claim_for_launch(path: str, domain_text: str | None, command: str, log_dir: str = "",
                     only: list[str] | None = None) -> Claim:
    """Choose the graph's domain (``auto``: the first free one, said in one line), make it this process's
    domain (its nodes inherit it) and claim it; UsageError when a graph of the same namespace runs there."""
    from ..domains import set_domain

    if domain_text != AUTO:
        domain = parse_domain(domain_text)
        set_domain(domain=domain)
        return claim(_load_at(path, domain if domain is not None else _first_domain()), command, log_dir,
                     domain or 0, only)
    first = _first_domain()
    for domain in range(first, MAX_DOMAIN + 1):
        try:
            held = claim(_load_at(path, domain), command, log_dir, domain, only)
        except UsageError:
            continue
        set_domain(domain=domain)
        note = _moved(path, first, domain)
        if note:
            print(note, flush=True)
        return held
    raise UsageError(f"every domain {first}..{MAX_DOMAIN} has a graph running (`followbus ps` lists them)")


def claim_from_args(args: Any, command: str, log_dir: str = "") -> Claim:
    """launch/demo/up: the domain options (--domain, --namespace, --port) made this process's, then claimed."""
    from ..domains import parse_port, set_domain

    set_domain(namespace=getattr(args, "namespace", None), port=parse_port(getattr(args, "port", None)))
    only_text = getattr(args, "only", None)
    only = [n.strip() for n in only_text.split(",")] if only_text else None
    return claim_for_launch(args.graph, getattr(args, "domain", None), command, log_dir, only)
