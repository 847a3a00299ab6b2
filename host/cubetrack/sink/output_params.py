"""The ``[[outputs]]`` tables of a tracker config (contracts §4, docs/outputs.md): one params
dataclass per output ``type``, declared like every stage's section (:func:`cubetrack.core.params.param`
and the ``check`` helpers), read by :func:`output_params` and printed by ``cubetrack defaults``.
The command-line output flags make the same tables (:mod:`cubetrack.cli.outputs`)."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

from cubetrack.core.errors import ConfigError
from cubetrack.core.params import check, check_non_negative, param, params_from_table
from cubetrack.sink.rmw_zenoh import Distro
from cubetrack.sink.ros2 import Ros2Profile
from cubetrack.sink.vrpn import DEFAULT_PORT as VRPN_PORT

FOXGLOVE_PORT = 8765
LOOPBACK = "127.0.0.1"


@enum.unique
class ZenohMode(enum.Enum):
    PEER = "peer"
    CLIENT = "client"
    ROUTER = "router"


def parse_address(text: str, default: tuple[str, int], where: str) -> tuple[str, int]:
    """``ADDR:PORT``, ``ADDR`` or ``PORT`` -> (host, port), ``default`` filling what is missing;
    ConfigError naming ``where`` for anything else."""
    host, _, port = text.rpartition(":") if ":" in text else (("", "", text) if text.isdigit() else (text, "", ""))
    host = host.strip("[]") or default[0]
    try:
        number = int(port) if port else default[1]
    except ValueError:
        raise ConfigError(f"{where}: {text!r} is not ADDR:PORT (e.g. 127.0.0.1:{default[1]})") from None
    if not 0 <= number <= 65535:
        raise ConfigError(f"{where}: port {number} out of range 0..65535")
    return host, number


@dataclass(frozen=True, slots=True)
class ZenohEndpointParams:
    """Where a Zenoh-based output's session connects (the keys ``zenoh`` and ``ros2`` share)."""

    listen: tuple[str, ...] = param((), "Zenoh locators to listen on, e.g. [\"tcp/0.0.0.0:7447\"] (every interface); "
                                        "empty: the output's default (docs/zenoh.md)")
    connect: tuple[str, ...] = param((), "Zenoh routers or peers to connect to, e.g. [\"tcp/192.168.1.10:7447\"]")
    mode: ZenohMode = param(ZenohMode.PEER, "Zenoh session mode: peer | client | router")
    zenoh_config: str = param("", "a whole Zenoh JSON5 config used as is, relative to the config's folder "
                                  "(empty: none)")

    def __post_init__(self) -> None:
        for key in ("listen", "connect"):
            check(all("/" in v for v in getattr(self, key)),
                  f"{key} must be Zenoh locators such as \"tcp/127.0.0.1:7447\", got {list(getattr(self, key))}")


@dataclass(frozen=True, slots=True)
class ZenohOutputParams(ZenohEndpointParams):
    """``type = "zenoh"``: JSON on Zenoh (docs/zenoh.md)."""

    prefix: str = param("cubetrack", "first chunk(s) of every key: <prefix>/robots/<robot>/pose ...")


@dataclass(frozen=True, slots=True)
class Ros2OutputParams(ZenohEndpointParams):
    """``type = "ros2"``: ROS 2 topics over Zenoh (docs/ros2.md)."""

    distro: Distro = param(Distro.JAZZY, "ROS 2 distribution (its type hashes): "
                                         + " | ".join(d.value for d in Distro))
    domain_id: int | None = param(None, "ROS_DOMAIN_ID, 0..232; unset: the environment's $ROS_DOMAIN_ID, else 0")
    profile: Ros2Profile = param(Ros2Profile.RMW_ZENOH, "rmw_zenoh: for ROS 2 nodes on rmw_zenoh; bridge: for "
                                                        "zenoh-bridge-ros2dds (ROS 2 on DDS)")
    namespace: str = param("", "prefix of the robot topics: \"/lab\" -> /lab/<robot>/pose")
    world_frame: str = param("world", "frame id of the world")

    def __post_init__(self) -> None:
        ZenohEndpointParams.__post_init__(self)
        check(self.domain_id is None or 0 <= self.domain_id <= 232,
              f"domain_id must be 0..232, got {self.domain_id}")


@dataclass(frozen=True, slots=True)
class VrpnOutputParams:
    """``type = "vrpn"``: VRPN trackers <robot>@ADDR:PORT (docs/vrpn.md)."""

    address: str = param(f"{LOOPBACK}:{VRPN_PORT}", "where to serve: ADDR:PORT, ADDR or PORT (the rest as here); "
                                                     "loopback unless another address is given")

    def __post_init__(self) -> None:
        parse_address(self.address, (LOOPBACK, VRPN_PORT), "address")

    @property
    def host_port(self) -> tuple[str, int]:
        return parse_address(self.address, (LOOPBACK, VRPN_PORT), "address")


@dataclass(frozen=True, slots=True)
class ImageRateParams:
    """The key the Foxglove server and the MCAP file share."""

    image_fps: float = param(10.0, "camera images (and their annotations) per camera per second at most; 0: every "
                                   "frame (each image costs the tracker's process 0.2-0.5 ms, docs/foxglove.md)")

    def __post_init__(self) -> None:
        check_non_negative(self, "image_fps", unit="images per second")


@dataclass(frozen=True, slots=True)
class FoxgloveOutputParams(ImageRateParams):
    """``type = "foxglove"``: a Foxglove WebSocket server (docs/foxglove.md)."""

    address: str = param(f"{LOOPBACK}:{FOXGLOVE_PORT}", "where to serve: ADDR:PORT, ADDR or PORT (the rest as "
                                                         "here); loopback unless another address is given")

    def __post_init__(self) -> None:
        ImageRateParams.__post_init__(self)
        parse_address(self.address, (LOOPBACK, FOXGLOVE_PORT), "address")

    @property
    def host_port(self) -> tuple[str, int]:
        return parse_address(self.address, (LOOPBACK, FOXGLOVE_PORT), "address")


@dataclass(frozen=True, slots=True)
class McapOutputParams(ImageRateParams):
    """``type = "mcap"``: the Foxglove channels recorded to a file (docs/foxglove.md)."""

    path: str = param("", "the .mcap file, relative to the config's folder (required: a table without it is refused; "
                          "never overwrites a file)")


OutputParams = (ZenohOutputParams | Ros2OutputParams | VrpnOutputParams | FoxgloveOutputParams
                | McapOutputParams)
OUTPUT_TYPES: dict[str, type[OutputParams]] = {
    "zenoh": ZenohOutputParams,
    "ros2": Ros2OutputParams,
    "vrpn": VrpnOutputParams,
    "foxglove": FoxgloveOutputParams,
    "mcap": McapOutputParams,
}


def output_params(table: dict[str, Any], where: str) -> OutputParams:
    """The params of one ``[[outputs]]`` table (its ``type`` picks the class; a single locator may be
    given as a string); ConfigError naming ``where`` for a bad type, key or value."""
    kind = table.get("type")
    if kind not in OUTPUT_TYPES:
        raise ConfigError(f"{where}: type must be one of {', '.join(OUTPUT_TYPES)}, got {kind!r}")
    values = {key: [value] if key in ("listen", "connect") and isinstance(value, str) else value
              for key, value in table.items() if key != "type"}
    return params_from_table(OUTPUT_TYPES[kind], values, where)


def output_type(params: OutputParams) -> str:
    """The ``type`` of an output's params."""
    return next(name for name, cls in OUTPUT_TYPES.items() if type(params) is cls)

