"""Opening the Zenoh session an output publishes on: loopback unless told otherwise.

Two starting points: :func:`json_endpoints` (the plain JSON output: a peer listening on
``tcp/127.0.0.1:7447``; when something already listens there, typically a router, it connects
to it instead) and :func:`ros_endpoints` (exactly how an rmw_zenoh node connects: a peer that
connects to the router at ``tcp/localhost:7447``, listens on ``tcp/localhost:0``, gossips its
address to the router only, UDP multicast scouting off, timestamping on). ``config_file``
(a Zenoh JSON5 config) replaces all of that when given.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass, replace
from pathlib import Path

from cubetrack.sink.base import OutputError, is_loopback_host

log = logging.getLogger(__name__)

DEFAULT_PORT = 7447


@dataclass(frozen=True, slots=True)
class ZenohEndpoints:
    """How a session joins Zenoh: ``mode`` (peer | client | router), the locators it
    ``listen``s on and ``connect``s to, or a whole Zenoh ``config_file``. ``ros`` adds
    rmw_zenoh's session settings (gossip to the router, timestamping)."""

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    config_file: Path | None = None
    ros: bool = False
    fallback_connect: bool = False  # listen failed because the port is taken: connect there instead
    lease_ms: int | None = None  # a peer silent this long is dropped, its liveliness tokens with it (Zenoh: 10 s)


def json_endpoints(listen: tuple[str, ...] = (), connect: tuple[str, ...] = (), mode: str = "peer",
                   config_file: Path | None = None) -> ZenohEndpoints:
    """The JSON output's session: by default a peer on ``tcp/127.0.0.1:7447``."""
    default = not listen and not connect and config_file is None
    return ZenohEndpoints(mode, listen or ((f"tcp/127.0.0.1:{DEFAULT_PORT}",) if not connect else ()),
                          connect, config_file, ros=False, fallback_connect=default)


def ros_endpoints(listen: tuple[str, ...] = (), connect: tuple[str, ...] = (), mode: str = "peer",
                  config_file: Path | None = None) -> ZenohEndpoints:
    """An rmw_zenoh node's session (DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5)."""
    return ZenohEndpoints(mode, listen or ("tcp/localhost:0",), connect or (f"tcp/localhost:{DEFAULT_PORT}",),
                          config_file, ros=True)


def is_loopback(locator: str) -> bool:
    """Whether a locator such as ``tcp/127.0.0.1:7447`` names a loopback address."""
    match = re.match(r"^[a-z0-9]+/(\[[^\]]*\]|[^:/]*)", locator)
    return is_loopback_host(match.group(1).strip("[]") if match else "")


def _config(endpoints: ZenohEndpoints):
    import zenoh

    if endpoints.config_file is not None:
        try:
            return zenoh.Config.from_file(str(endpoints.config_file))
        except Exception as exc:
            raise OutputError(f"{endpoints.config_file}: not a usable Zenoh config: {exc}") from None
    config = zenoh.Config()
    settings = {
        "mode": endpoints.mode,
        "listen/endpoints": list(endpoints.listen),
        "connect/endpoints": list(endpoints.connect),
        "scouting/multicast/enabled": False,
        # open returns once the peers' subscriptions are known: the first samples are not lost
        "open/return_conditions/connect_scouted": True,
        "open/return_conditions/declares": True,
    }
    if endpoints.lease_ms is not None:
        settings["transport/link/tx/lease"] = endpoints.lease_ms
    if endpoints.ros:
        settings.update({
            "scouting/gossip/enabled": True,
            "scouting/gossip/target": {"router": ["router", "peer"], "peer": ["router"]},
            "timestamping/enabled": {"router": True, "peer": True, "client": True},
            "queries_default_timeout": 60000,
        })
    for key, value in settings.items():
        try:
            config.insert_json5(key, json.dumps(value))
        except Exception as exc:
            raise OutputError(f"Zenoh setting {key} = {value!r} refused: {exc}") from None
    return config


def open_session(endpoints: ZenohEndpoints, what: str):
    """Open a Zenoh session for output ``what``; a one-line :class:`OutputError` when it cannot."""
    import zenoh

    config = _config(endpoints)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        if endpoints.fallback_connect and "in use" in str(exc):
            log.info("%s: %s is taken (a Zenoh router?); connecting to it", what, endpoints.listen[0])
            return open_session(replace(endpoints, connect=endpoints.listen, listen=("tcp/127.0.0.1:0",),
                                        fallback_connect=False), what)
        raise OutputError(f"{what}: cannot open the Zenoh session ({_first_line(exc)})") from None
    where = ", ".join(endpoints.listen) or "(nothing)"
    if endpoints.config_file is not None:
        log.info("%s: Zenoh session from %s", what, endpoints.config_file)
    elif all(is_loopback(e) for e in endpoints.listen):
        log.info("%s: Zenoh %s listening on %s, connecting to %s", what, endpoints.mode, where,
                 ", ".join(endpoints.connect) or "nothing")
    else:
        log.warning("%s: Zenoh %s listening on %s: reachable from other machines", what, endpoints.mode, where)
    return session


def _first_line(exc: Exception) -> str:
    return str(exc).split(" at /")[0].splitlines()[0]
