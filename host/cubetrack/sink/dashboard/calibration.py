"""What the dashboard's calibration panel tells the person at the cameras
(:mod:`cubetrack.app.dashboard` runs the steps): advice on a calibrated camera from its figures, on
a camera that could not be calibrated from why, and the count of instants a drive has given the
bundle adjustment so far."""

from __future__ import annotations

import math
from collections.abc import Iterable

from cubetrack.sink.dashboard.state import DashboardParams


def calibration_advice(spread_cm: float, spread_deg: float, reprojection_px: float, marker_side_px: float,
                       inliers: int, sightings: int, params: DashboardParams) -> list[str]:
    """What to do about a calibrated camera (empty: it is good). Each rule names the figure it
    looked at; see :class:`~cubetrack.sink.dashboard.state.DashboardParams` for the limits."""
    advice = []
    if math.isfinite(marker_side_px) and marker_side_px < params.min_marker_side_px:
        advice.append(f"the world marker is only {marker_side_px:.0f} px wide in this camera: move the camera "
                      f"closer to it or print a bigger marker (then set [world] marker_size)")
    if spread_cm > params.max_spread_cm or spread_deg > params.max_spread_deg:
        advice.append(f"the per-frame poses scatter by {spread_cm:.2f} cm / {spread_deg:.2f}°: check the focus "
                      "and the lighting, and that neither the camera nor the marker moved")
    if not math.isfinite(reprojection_px) or reprojection_px > params.max_reprojection_px:
        seen = "not found in its frames" if not math.isfinite(reprojection_px) else f"{reprojection_px:.2f} px away"
        advice.append(f"the world marker's corners are {seen} from where the calibrated pose puts them: check "
                      "the camera's focus and its camera_info (intrinsics)")
    if sightings and inliers < params.min_inlier_fraction * sightings:
        advice.append(f"only {inliers} of {sightings} sightings agreed: something moved or covered the marker "
                      "while collecting; collect again")
    return advice


def missing_advice(reason: str, camera_status: str, last_error: str) -> list[str]:
    """What to do about a camera that could not be calibrated."""
    if camera_status in ("down", "stale", "waiting"):
        tail = f" (last error: {last_error})" if last_error else ""
        return [f"the camera sent no usable frames: check its power, its Wi-Fi and its url in the config{tail}"]
    if "no world marker" in reason or "found in 0 of" in reason:
        return ["the camera never saw the whole world marker: turn or move it until the marker is in view"]
    return [("the camera saw the world marker too rarely: make sure the whole marker is in view and nothing "
             "covers it, then collect again")]



class InstantCounter:
    """Counts, while driving, the instants the bundle adjustment will find
    (:func:`cubetrack.calib.bundle.group_instants`): sightings of one robot by at least
    ``min_cameras`` cameras within ``max_span_s``, each sighting in one instant only. Counted
    from the poses (one per processed frame), so a lower bound: the drive recording keeps the
    frames the live loop had no time for."""

    def __init__(self, max_span_s: float, min_cameras: int):
        self.max_span_s = max_span_s
        self.min_cameras = min_cameras
        self.count = 0
        self._unused: dict[str, list[tuple[float, str]]] = {}  # robot -> (time, camera) in no instant yet

    def add(self, robot: str, time_s: float, cameras: Iterable[str]) -> bool:
        """Take one pose's sightings; whether they completed an instant."""
        unused = [(t, c) for t, c in self._unused.get(robot, ()) if abs(time_s - t) <= self.max_span_s]
        unused += [(time_s, c) for c in cameras]
        if len({c for _, c in unused}) >= self.min_cameras:
            self.count += 1
            unused = []
        self._unused[robot] = unused
        return not unused
