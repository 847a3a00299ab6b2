"""The sinks of a session, assembled from a config: files always, the configured outputs besides.

Outputs come from the config's ``[[outputs]]`` tables and from command-line flags
(:mod:`cubetrack.cli.outputs`), both as :class:`OutputSpec`; docs/outputs.md lists the keys."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics
from cubetrack.core.errors import ConfigError
from cubetrack.io.config import TrackerConfig
from cubetrack.sink.base import CameraSetup, FileSink, Outputs, SessionInfo, Sink


def session_info(config: TrackerConfig, intrinsics: dict[str, CameraIntrinsics],
                 extrinsics: dict[str, CameraExtrinsics] | None) -> SessionInfo:
    """The static facts every sink is opened with."""
    extrinsics = extrinsics or {}
    cameras = tuple(CameraSetup(name, extrinsics[name].T_world_cam if name in extrinsics else None, intr)
                    for name, intr in intrinsics.items())
    return SessionInfo(config.world, cameras, {r.name: r.layout for r in config.robots})


def open_outputs(config: TrackerConfig, intrinsics: dict[str, CameraIntrinsics],
                 extrinsics: dict[str, CameraExtrinsics] | None, out_dir, sinks: Sequence[Sink] = ()
                 ) -> tuple[Outputs, FileSink]:
    """The session's outputs, opened: the trajectory files in ``out_dir`` and ``sinks``."""
    files = FileSink(out_dir, tuple(r.name for r in config.robots))
    outputs = Outputs([files, *sinks])
    outputs.open(session_info(config, intrinsics, extrinsics))
    return outputs, files


OUTPUT_KEYS = {
    "zenoh": {"prefix", "listen", "connect", "mode", "zenoh_config"},
    "ros2": {"distro", "domain_id", "profile", "namespace", "world_frame", "listen", "connect", "mode", "zenoh_config"},
    "vrpn": {"address"},
    "foxglove": {"address", "image_fps"},
    "mcap": {"path", "image_fps"},
}
DEFAULT_ADDRESSES = {"vrpn": ("127.0.0.1", 3883), "foxglove": ("127.0.0.1", 8765)}


@dataclass(frozen=True, slots=True)
class OutputSpec:
    """One output as the config's ``[[outputs]]`` table or a command-line flag gives it:
    the raw ``table`` (with ``type``), the folder relative paths in it resolve against, and
    where it came from (for error messages)."""

    table: dict
    base: Path
    where: str

    @property
    def type(self) -> str:
        return self.table["type"]


def config_output_specs(config: TrackerConfig) -> list[OutputSpec]:
    """The config's ``[[outputs]]`` tables."""
    return [OutputSpec(table, config.path.parent, f"{config.path}: outputs[{i}]")
            for i, table in enumerate(config.outputs)]


def merge_outputs(from_config: list[OutputSpec], from_flags: list[OutputSpec]) -> list[OutputSpec]:
    """The config's outputs, each replaced by a flag of the same type (one server per port)."""
    flagged = {spec.type for spec in from_flags}
    return [spec for spec in from_config if spec.type not in flagged] + from_flags


def parse_address(text: str, default: tuple[str, int], where: str) -> tuple[str, int]:
    """``ADDR:PORT``, ``ADDR`` or ``PORT`` -> (host, port), defaults filling what is missing."""
    host, _, port = text.rpartition(":") if ":" in text else (("", "", text) if text.isdigit() else (text, "", ""))
    host = host.strip("[]") or default[0]
    try:
        number = int(port) if port else default[1]
    except ValueError:
        raise ConfigError(f"{where}: {text!r} is not ADDR:PORT (e.g. 127.0.0.1:{default[1]})") from None
    if not 0 <= number <= 65535:
        raise ConfigError(f"{where}: port {number} out of range 0..65535")
    return host, number


def _locators(spec: OutputSpec, key: str) -> tuple[str, ...]:
    value = spec.table.get(key, [])
    value = [value] if isinstance(value, str) else value
    if not isinstance(value, list) or not all(isinstance(v, str) and "/" in v for v in value):
        raise ConfigError(f"{spec.where}: {key} must be Zenoh locators such as \"tcp/127.0.0.1:7447\"")
    return tuple(value)


def _zenoh_endpoints(spec: OutputSpec, ros: bool):
    from cubetrack.sink.zenoh_session import json_endpoints, ros_endpoints

    mode = spec.table.get("mode", "peer")
    if mode not in ("peer", "client", "router"):
        raise ConfigError(f"{spec.where}: mode must be peer, client or router, got {mode!r}")
    config_file = spec.table.get("zenoh_config")
    config_file = spec.base / config_file if config_file else None
    if config_file is not None and not config_file.is_file():
        raise ConfigError(f"{spec.where}: Zenoh config {config_file} not found")
    return (ros_endpoints if ros else json_endpoints)(_locators(spec, "listen"), _locators(spec, "connect"), mode,
                                                      config_file)


def _sink(spec: OutputSpec, default_domain_id: int, robots: tuple[str, ...]) -> Sink:
    table, where = spec.table, spec.where
    if spec.type == "zenoh":
        from cubetrack.sink.zenoh_json import ZenohJsonParams, ZenohJsonSink

        return ZenohJsonSink(ZenohJsonParams(prefix=str(table.get("prefix", "cubetrack"))),
                             _zenoh_endpoints(spec, ros=False))
    if spec.type == "ros2":
        from cubetrack.sink.rmw_zenoh import Distro
        from cubetrack.sink.ros2 import Ros2Params, Ros2Profile, Ros2Sink

        try:
            params = Ros2Params(profile=Ros2Profile(table.get("profile", "rmw_zenoh")),
                                distro=Distro(table.get("distro", "jazzy")),
                                domain_id=int(table.get("domain_id", default_domain_id)),
                                namespace=str(table.get("namespace", "")),
                                world_frame=str(table.get("world_frame", "world")))
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"{where}: {exc} (profile: rmw_zenoh | bridge; distro: "
                              f"{' | '.join(d.value for d in Distro)})") from None
        return Ros2Sink(params, _zenoh_endpoints(spec, ros=True))
    if spec.type == "vrpn":
        from cubetrack.sink.vrpn import VrpnParams, VrpnSink

        host, port = parse_address(str(table.get("address", "")), DEFAULT_ADDRESSES["vrpn"], where)
        return VrpnSink(VrpnParams(host=host, port=port), robots)
    return _foxglove_sink([spec])


def _foxglove_params(spec: OutputSpec):
    from cubetrack.sink.foxglove import FoxgloveParams

    try:
        return FoxgloveParams(**{key: spec.table[key] for key in ("image_fps",) if key in spec.table})
    except ConfigError as exc:
        raise ConfigError(f"{spec.where}: {exc}") from None


def _foxglove_sink(specs: list[OutputSpec]) -> Sink:
    """The Foxglove server and/or MCAP file of ``specs`` (one of each at most, same parameters)
    as one sink: one foxglove-sdk context builds and encodes each message once for both."""
    from cubetrack.sink.foxglove import FoxgloveSink

    server = mcap = None
    for spec in specs:
        if spec.type == "foxglove":
            server = parse_address(str(spec.table.get("address", "")), DEFAULT_ADDRESSES["foxglove"], spec.where)
        elif "path" not in spec.table:
            raise ConfigError(f"{spec.where}: an mcap output needs path = \"<file>.mcap\"")
        else:
            mcap = spec.base / str(spec.table["path"])
    return FoxgloveSink(server=server, mcap=mcap, params=_foxglove_params(specs[0]))


def _grouped(specs: list[OutputSpec]) -> list[list[OutputSpec]]:
    """Each output alone, except a Foxglove server and an MCAP file with the same parameters:
    those together (:func:`_foxglove_sink`)."""
    foxglove = [s for s in specs if s.type in ("foxglove", "mcap")]
    if len(foxglove) == 2 and foxglove[0].type != foxglove[1].type and \
            _foxglove_params(foxglove[0]) == _foxglove_params(foxglove[1]):
        return [[s] for s in specs if s not in foxglove] + [foxglove]
    return [[s] for s in specs]


def output_sinks(specs: list[OutputSpec], default_domain_id: int = 0, robots: tuple[str, ...] = ()) -> list[Sink]:
    """Start every output (servers bind, sessions open now, so a bad address fails before the
    session; the configured ``robots`` are announced at once, e.g. as VRPN trackers); on an error
    the ones already started are closed again."""
    for spec in specs:
        if spec.table.get("type") not in OUTPUT_KEYS:
            raise ConfigError(f"{spec.where}: type must be one of {', '.join(OUTPUT_KEYS)}, "
                              f"got {spec.table.get('type')!r}")
        unknown = set(spec.table) - OUTPUT_KEYS[spec.type] - {"type"}
        if unknown:
            raise ConfigError(f"{spec.where}: unknown key(s) {', '.join(sorted(unknown))} for a {spec.type} output; "
                              f"known: {', '.join(sorted(OUTPUT_KEYS[spec.type]))}")
    sinks: list[Sink] = []
    try:
        for group in _grouped(specs):
            sinks.append(_sink(group[0], default_domain_id, robots) if len(group) == 1 else _foxglove_sink(group))
    except BaseException:
        close_sinks(sinks)
        raise
    return sinks


def start_outputs(specs: list[OutputSpec], default_domain_id: int = 0, robots: tuple[str, ...] = ()) -> list[Sink]:
    """The outputs a tracking session runs, all together in a process of their own
    (:class:`~cubetrack.sink.process.OutputProcess`), so that their work does not take the
    tracker's process's CPU; none for no specs. A bad output fails here, before the session."""
    from cubetrack.sink.process import OutputProcess

    return [OutputProcess(partial(output_sinks, specs, default_domain_id, robots))] if specs else []


def close_sinks(sinks: Sequence[Sink]) -> None:
    """Close outputs (harmless for ones a session already closed)."""
    for sink in sinks:
        sink.close()
