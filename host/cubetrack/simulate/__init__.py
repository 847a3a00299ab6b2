"""``cubetrack simulate``: a multi-camera recording of the paper's arena with exact ground truth.

Library use::

    from cubetrack.simulate import SimulationParams, simulate
    result = simulate(SimulationParams(cameras=5, height_m=1.2, tilt_deg=40, seed=3), "rec")
    result.T_world_cam["cam1"], result.intrinsics["cam1"], result.T_world_cube(t)

Modules: :mod:`~cubetrack.simulate.params` (the parameters; light to import),
:mod:`~cubetrack.simulate.scenario` (arena, cameras, robot, path),
:mod:`~cubetrack.simulate.timing` (clocks, captures, transfers, ``/time`` round trips),
:mod:`~cubetrack.simulate.render` (the exact anti-aliased renderer),
:mod:`~cubetrack.simulate.camera_motion` (bumped and drifting cameras),
:mod:`~cubetrack.simulate.simulation` (writing the recording). See docs/simulation.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from cubetrack.core.progress import Progress
from cubetrack.simulate.params import SimulationParams

if TYPE_CHECKING:
    from cubetrack.simulate.simulation import SimulatedCamera, SimulationResult

__all__ = ["SimulationParams", "SimulationResult", "SimulatedCamera", "simulate"]


def simulate(params: SimulationParams, out: str | Path, progress: Progress | None = None,
             overwrite: bool = False, workers: int | None = None) -> SimulationResult:
    """Render a simulated session into the recording folder ``out``; see
    :func:`cubetrack.simulate.simulation.simulate`."""
    from cubetrack.simulate.simulation import simulate as _simulate

    return _simulate(params, out, progress, overwrite, workers)


def __getattr__(name: str) -> Any:
    # the result types live with OpenCV-dependent code; import them only when asked for
    if name in ("SimulationResult", "SimulatedCamera"):
        from cubetrack.simulate import simulation

        return getattr(simulation, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
