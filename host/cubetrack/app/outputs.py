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
from cubetrack.sink.output_params import (
    FoxgloveOutputParams,
    ImageRateParams,
    McapOutputParams,
    OutputParams,
    Ros2OutputParams,
    VrpnOutputParams,
    ZenohEndpointParams,
    ZenohOutputParams,
    output_params,
)
from cubetrack.sink.zenoh_session import ZenohEndpoints, json_endpoints, ros_endpoints


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


@dataclass(frozen=True, slots=True)
class OutputSpec:
    """One output as the config's ``[[outputs]]`` table or a command-line flag gives it:
    the raw ``table`` (with ``type``; read into its params by
    :func:`cubetrack.sink.output_params.output_params`), the folder relative paths in it resolve
    against, and where it came from (for error messages)."""

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


def _zenoh_endpoints(params: ZenohEndpointParams, spec: OutputSpec, ros: bool) -> ZenohEndpoints:
    config_file = spec.base / params.zenoh_config if params.zenoh_config else None
    if config_file is not None and not config_file.is_file():
        raise ConfigError(f"{spec.where}: Zenoh config {config_file} not found")
    return (ros_endpoints if ros else json_endpoints)(params.listen, params.connect, params.mode.value, config_file)


def _sink(spec: OutputSpec, params: OutputParams, default_domain_id: int, robots: tuple[str, ...]) -> Sink:
    if isinstance(params, ZenohOutputParams):
        from cubetrack.sink.zenoh_json import ZenohJsonParams, ZenohJsonSink

        return ZenohJsonSink(ZenohJsonParams(prefix=params.prefix), _zenoh_endpoints(params, spec, ros=False))
    if isinstance(params, Ros2OutputParams):
        from cubetrack.sink.ros2 import Ros2Params, Ros2Sink

        domain_id = default_domain_id if params.domain_id is None else params.domain_id
        ros = Ros2Params(profile=params.profile, distro=params.distro, domain_id=domain_id,
                         namespace=params.namespace, world_frame=params.world_frame)
        return Ros2Sink(ros, _zenoh_endpoints(params, spec, ros=True))
    if isinstance(params, VrpnOutputParams):
        from cubetrack.sink.vrpn import VrpnParams, VrpnSink

        host, port = params.host_port
        return VrpnSink(VrpnParams(host=host, port=port), robots)
    return _foxglove_sink([(spec, params)])


def _foxglove_sink(outputs: list[tuple[OutputSpec, OutputParams]]) -> Sink:
    """The Foxglove server and/or MCAP file of ``outputs`` (one of each at most, same image rate)
    as one sink: one foxglove-sdk context builds and encodes each message once for both."""
    from cubetrack.sink.foxglove import FoxgloveParams, FoxgloveSink

    server = mcap = None
    image_fps = 0.0
    for spec, params in outputs:
        if isinstance(params, FoxgloveOutputParams):
            server = params.host_port
        elif isinstance(params, McapOutputParams):
            if not params.path:
                raise ConfigError(f"{spec.where}: an mcap output needs path = \"<file>.mcap\"")
            mcap = spec.base / params.path
        assert isinstance(params, ImageRateParams)  # _grouped: only these come here
        image_fps = params.image_fps
    return FoxgloveSink(server=server, mcap=mcap, params=FoxgloveParams(image_fps=image_fps))


def _grouped(outputs: list[tuple[OutputSpec, OutputParams]]) -> list[list[tuple[OutputSpec, OutputParams]]]:
    """Each output alone, except a Foxglove server and an MCAP file with the same image rate:
    those together (:func:`_foxglove_sink`)."""
    foxglove = [o for o in outputs if isinstance(o[1], FoxgloveOutputParams | McapOutputParams)]
    if len(foxglove) == 2 and type(foxglove[0][1]) is not type(foxglove[1][1]) and \
            foxglove[0][1].image_fps == foxglove[1][1].image_fps:  # type: ignore[union-attr]  # isinstance above
        return [[o] for o in outputs if o not in foxglove] + [foxglove]
    return [[o] for o in outputs]


def output_sinks(specs: list[OutputSpec], default_domain_id: int = 0, robots: tuple[str, ...] = ()) -> list[Sink]:
    """Start every output (servers bind, sessions open now, so a bad address fails before the
    session; the configured ``robots`` are announced at once, e.g. as VRPN trackers); on an error
    the ones already started are closed again."""
    outputs = [(spec, output_params(spec.table, spec.where)) for spec in specs]
    sinks: list[Sink] = []
    try:
        for group in _grouped(outputs):
            sinks.append(_sink(*group[0], default_domain_id, robots) if len(group) == 1 else _foxglove_sink(group))
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
