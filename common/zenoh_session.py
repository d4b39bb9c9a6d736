"""Zenoh session configuration shared by every component (see docs/protocol.md, "Transport").

Settings chosen from measurements in the project notes:
* peers connect to the router and listen on loopback by default, so gossip gives
  them direct links (twice the throughput of routing everything, and no
  head-of-line blocking between components) without exposing a port;
* multicast scouting off (explicit endpoints only);
* shared memory off (a known silent-drop race under CPU load);
* a BLOCK publisher waits up to 60 s for a stalled consumer before zenoh closes
  the link (default 5 s, which loses data during a long checkpoint or GC pause).
"""

from __future__ import annotations

import json

import zenoh

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
DEFAULT_PEER_LISTEN = "tcp/127.0.0.1:0"
BLOCK_WAIT_BEFORE_CLOSE_US = 60_000_000
ROUTER_BLOCK_WAIT_BEFORE_CLOSE_US = 5_000_000

_log_initialised = False


def init_logging() -> None:
    """Show zenoh's own errors (closed transports, dropped oversize messages) once. Its Rust logger
    writes them to file descriptor 1: a component's log file, or the terminal (`silcr monitor --json`
    moves them to stderr to keep its output JSON)."""
    global _log_initialised
    if not _log_initialised:
        zenoh.init_log_from_env_or("error")
        _log_initialised = True


def _base(zenoh_config: str) -> zenoh.Config:
    if zenoh_config:
        try:
            return zenoh.Config.from_file(zenoh_config)
        except Exception as e:  # ZError or OSError: both mean the file is unusable
            raise ValueError(f"cannot load Zenoh config {zenoh_config}: {e}") from None
    return zenoh.Config()


def _common(conf: zenoh.Config, block_wait_us: int = BLOCK_WAIT_BEFORE_CLOSE_US) -> zenoh.Config:
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close", str(block_wait_us))
    return conf


_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def check_endpoint(endpoint: str) -> str:
    """`endpoint` if it is `<protocol>/<address>` with, for IP protocols, a host and a port in [1, 65535];
    else `ValueError` with one line naming the problem (Zenoh's own message carries its source paths)."""
    proto, sep, addr = endpoint.partition("/")
    if not sep or not proto or not addr:
        raise ValueError(f"{endpoint!r} is not a Zenoh endpoint: use <protocol>/<address>, e.g. tcp/127.0.0.1:7447")
    if proto in _IP_PROTOCOLS:
        host, colon, port = addr.split("?")[0].split("#")[0].rpartition(":")
        if not colon or not host.strip("[]") or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise ValueError(f"{endpoint!r}: a {proto} endpoint needs <host>:<port> with a port in [1, 65535], "
                             f"e.g. {proto}/127.0.0.1:7447")
    try:
        zenoh.Config().insert_json5("listen/endpoints", json.dumps([endpoint]))
    except zenoh.ZError as e:
        raise ValueError(f"{endpoint!r} is not a Zenoh endpoint: {str(e).split(' at /')[0]}") from None
    return endpoint


def session_config(
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    mode: str = "peer",
    zenoh_config: str = "",
) -> zenoh.Config:
    """Config for a component: a peer (or client) of the run's router."""
    conf = _common(_base(zenoh_config))
    try:
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("connect/endpoints", json.dumps(list(connect) or [DEFAULT_ROUTER]))
        if mode == "peer":
            conf.insert_json5("listen/endpoints", json.dumps(list(listen) or [DEFAULT_PEER_LISTEN]))
        elif listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if mode == "client":
            # Wait for the router instead of failing at once when it is not up yet.
            conf.insert_json5("connect/timeout_ms", "-1")
            conf.insert_json5("connect/exit_on_failure", "false")
    except zenoh.ZError as e:
        raise ValueError(f"invalid Zenoh endpoint or mode: {e}") from None
    return conf


def router_config(listen: list[str], connect: list[str] | None = None, zenoh_config: str = "") -> zenoh.Config:
    # The router forwards BLOCK messages (weights, control) to every actor. A link that
    # went dead without closing (a cable pulled, a veth down) fills its queue, and the
    # router then waits up to wait_before_close before dropping that link, stalling
    # every other link it serves meanwhile (measured: 60 s stalled the whole run and
    # cost a healthy actor its lease). Components keep the long wait for their own
    # publishers; the router gives up on a dead link after Zenoh's default 5 s.
    conf = _common(_base(zenoh_config), ROUTER_BLOCK_WAIT_BEFORE_CLOSE_US)
    try:
        conf.insert_json5("mode", '"router"')
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    except zenoh.ZError as e:
        raise ValueError(f"invalid Zenoh endpoint: {e}") from None
    return conf


def open_session(conf: zenoh.Config, zenoh_log: bool = True) -> zenoh.Session:
    """`zenoh_log=False`: leave zenoh's logger off, unless this process turned it on before (the launcher's own
    session, which lives in a Python API user's process: its lines would land in the user's standard output)."""
    if zenoh_log:
        init_logging()
    return zenoh.open(conf)
