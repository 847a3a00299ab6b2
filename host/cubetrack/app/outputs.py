"""The sinks of a session, assembled from a config: files always, the configured outputs besides."""

from __future__ import annotations

from typing import Sequence

from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics
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
