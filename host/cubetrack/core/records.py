"""Frozen records passed between pipeline stages: one record per frame, per marker, per estimate.

No parallel arrays: a detection carries its own id, corners and area. Arrays inside records are
never modified after construction (stages build new records instead).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics


@dataclass(frozen=True, slots=True, eq=False)
class Frame:
    """One JPEG frame from one camera, as a source delivers it.

    ``device_time_s`` is the node's X-Timestamp (its clock since boot, seconds);
    ``host_time_s`` the host's Unix time when the whole frame had arrived.
    """

    camera: str
    seq: int
    device_time_s: float
    host_time_s: float
    jpeg: bytes


@dataclass(frozen=True, slots=True, eq=False)
class Detection:
    """One detected square marker in one image.

    ``corners_px`` is (4, 2) float64, clockwise in the image starting at the marker's top-left
    corner (OpenCV order TL, TR, BR, BL), pixel-centre convention ((0, 0) = centre of the
    top-left pixel). ``area_px2`` is the shoelace area of those corners (paper eq. 3).
    ``dictionary`` names the OpenCV dictionary the id belongs to ("" = unspecified, matches any).
    Detection does not correct lens distortion and does not estimate pose.
    """

    marker_id: int
    corners_px: np.ndarray
    area_px2: float
    dictionary: str = ""


@dataclass(frozen=True, slots=True, eq=False)
class MarkerPose:
    """Pose of one detected marker in the camera optical frame (x right, y down, z forward).

    ``T_cam_marker`` is the chosen planar PnP solution: the one with the lower reprojection
    error, unless ambiguity resolution (e.g. the upright prior in ``cubetrack.estimate.pose``) swapped
    them; ``T_cam_marker_alt`` the other (IPPE returns two; None when only one was valid).
    Errors are RMS reprojection errors in pixels.
    """

    detection: Detection
    size_m: float
    T_cam_marker: np.ndarray
    reprojection_error_px: float
    T_cam_marker_alt: np.ndarray | None = None
    reprojection_error_alt_px: float = float("inf")


@dataclass(frozen=True, slots=True, eq=False)
class FaceObservation:
    """One cube face identified in one camera frame, with the cube pose it implies.

    ``T_world_cube`` is the cube frame's pose in the world frame as implied by this face alone;
    ``area_px2`` the marker's pixel area (the paper's quality measure).
    """

    face: str
    marker_pose: MarkerPose
    T_world_cube: np.ndarray
    area_px2: float


@dataclass(frozen=True, slots=True, eq=False)
class CameraEstimate:
    """The cube pose of one robot seen in one camera frame.

    ``capture_time_s`` is the estimated capture time on the host clock (Unix seconds);
    ``T_world_cube`` the camera's estimate of the cube frame in the world frame;
    ``area_px2`` the summed pixel area of the faces used; ``faces`` the per-face observations.
    """

    camera: str
    robot: str
    seq: int
    capture_time_s: float
    arrival_time_s: float
    T_world_cube: np.ndarray
    area_px2: float
    faces: tuple[FaceObservation, ...]
    reprojection_error_px: float


@dataclass(frozen=True, slots=True, eq=False)
class TrackedPose:
    """One fused pose of one robot: the cube frame in the world frame at ``time_s``.

    ``time_s`` is the estimated capture time on the host clock (Unix seconds);
    ``quaternion_xyzw`` is scalar-last. ``latency_s`` is how long after ``time_s`` the pose was
    output (capture -> output; offline replay reports the replayed arrival delay) and
    ``arrival_latency_s`` how long after its newest frame had arrived (arrival -> output; None
    where no frame produced it). ``predicted``: a pose the motion model predicted to ``time_s``
    (the host time it was output, for control loops), not a fused measurement.
    ``velocity_m_s`` and ``angular_velocity_rad_s`` are world-frame rates and ``covariance`` the
    (6, 6) covariance of the world-frame pose increment ``[δp (m), δθ (rad)]``, where the fusion
    estimates them (the filter does), else None. ``smoothed``: the smoother estimated it from
    sightings before and after it; ``smooth_lag_s``: with a fixed-lag smoother, how many seconds of
    later sightings (by capture time) it was smoothed over (None without one). Each is a field of
    the JSONL object (contracts §5) when set.
    """

    robot: str
    time_s: float
    position_m: np.ndarray
    quaternion_xyzw: np.ndarray
    cameras: tuple[str, ...]
    markers: tuple[str, ...]
    latency_s: float
    velocity_m_s: np.ndarray | None = None
    angular_velocity_rad_s: np.ndarray | None = None
    covariance: np.ndarray | None = None
    arrival_latency_s: float | None = None
    predicted: bool = False
    smoothed: bool = False
    smooth_lag_s: float | None = None


@dataclass(frozen=True, slots=True, eq=False)
class CubeSighting:
    """Everything one camera frame says about one robot's cube, as handed to fusion.

    ``detections`` are the frame's detections of the cube's ids and dictionary; ``estimate`` the
    single-camera cube pose from them (None when none could be made); ``T_world_cam`` the
    camera's pose used for this frame; ``intrinsics`` the camera's
    :class:`cubetrack.core.cameras.CameraIntrinsics`. Times are host-clock Unix seconds.
    """

    camera: str
    robot: str
    seq: int
    capture_time_s: float
    arrival_time_s: float
    detections: tuple[Detection, ...]
    estimate: CameraEstimate | None
    T_world_cam: np.ndarray
    intrinsics: CameraIntrinsics


@dataclass(frozen=True, slots=True)
class CameraHealth:
    """How one live camera is doing, as sinks and the dashboard show it (a snapshot).

    ``time_s`` host Unix time of the snapshot; ``frames_per_s`` over the last interval;
    ``frames``, ``dropped`` (frames the host gave up because it was behind), ``bad`` (broken
    parts) and ``reconnects`` count since the start; ``clock_offset_s`` (host minus device) and
    ``clock_drift_ppm`` from the camera's clock fit (NaN until known); ``transfer_latency_s``
    median arrival minus capture over the interval (NaN until known); ``jpeg_bytes`` the last
    frame's size; ``last_error`` the last connection or stream error ("" if none); ``timing`` how
    its frames are timed and what it lacks for it, e.g. ``no clock: stamped on arrival, latency
    ~40 ms assumed`` (:func:`cubetrack.source.timing.timing_note`; "" until known).
    """

    camera: str
    time_s: float
    connected: bool
    frames_per_s: float
    frames: int
    dropped: int
    bad: int
    reconnects: int
    clock_offset_s: float = float("nan")
    clock_drift_ppm: float = float("nan")
    transfer_latency_s: float = float("nan")
    jpeg_bytes: int = 0
    last_error: str = ""
    timing: str = ""


@dataclass(frozen=True, slots=True)
class CameraWatchState:
    """What the camera watching (issue 27, docs/calibration.md) says of one camera now, as the
    dashboard's camera tile shows it: ``state`` ``settling`` (no settled pose to judge it by yet),
    ``watched``, ``suspect``, ``moved``, ``re-calibrating`` or ``rejoined``; ``progress`` of a
    re-calibration (corners gathered over the corners it needs, 0..1); ``message`` one line;
    ``time_s`` host Unix time; ``T_world_cam`` the camera's new pose on ``rejoined`` (the pose the
    fusion uses from then on, which outputs publish in place of the session's), None otherwise."""

    camera: str
    time_s: float
    state: str
    progress: float = 0.0
    message: str = ""
    T_world_cam: np.ndarray | None = None


@dataclass(frozen=True, slots=True, eq=False)
class CameraView:
    """One processed camera frame, for outputs that show images (Foxglove, the dashboard).

    ``time_s`` the capture time (host Unix seconds); ``jpeg`` the frame as received;
    ``detections`` what detection found; ``predicted_corners_px`` robot name -> (N, 2) pixel
    positions of that robot's marker corners where the fusion expects them in this frame.
    """

    camera: str
    seq: int
    time_s: float
    jpeg: bytes
    detections: tuple[Detection, ...]
    predicted_corners_px: dict = field(default_factory=dict)


@dataclass(frozen=True, slots=True, eq=False)
class FrameJob:
    """One frame's per-frame work order, decided by the tracker (:class:`cubetrack.app.tracker.Tracker`)
    from the fusion's state: where detection looks (``regions``; None = the whole frame) and which
    robots' per-camera estimates the fusion asks for."""

    frame: Frame
    capture_time_s: float
    regions: tuple[tuple[int, int, int, int], ...] | None  # (x0, y0, x1, y1) image boxes
    estimate_robots: frozenset[str]
    predicted: tuple[Detection, ...] = ()  # the markers where the forecast puts them (projected corners)
    # instead of ``regions`` and ``predicted``: each robot's predicted cube pose in the camera
    # (robot, T_cam_cube 4x4), which the per-frame work projects into the two (a replay's worker does it)
    views: tuple[tuple[str, np.ndarray], ...] | None = None

    def plain(self, *, jpeg: bool = True, predicted: bool = True) -> tuple:
        """This job as plain values, which pickle several times faster than the records (between the
        processes of one tracker; :meth:`from_plain` turns them back); without the JPEG (``b""``) or
        the predicted markers when the other end does not need them."""
        f = self.frame
        markers = tuple((d.marker_id, d.corners_px, d.area_px2, d.dictionary)
                        for d in (self.predicted if predicted else ()))
        views = None if self.views is None else tuple((robot, T.ravel().tolist()) for robot, T in self.views)
        return (f.camera, f.seq, f.device_time_s, f.host_time_s, f.jpeg if jpeg else b"", self.capture_time_s,
                self.regions, tuple(self.estimate_robots), markers, views)

    @classmethod
    def from_plain(cls, values: tuple) -> FrameJob:
        """The job :meth:`plain` gave ``values`` of."""
        (camera, seq, device_time_s, host_time_s, jpeg, capture_time_s, regions, estimate_robots, predicted,
         views) = values
        return cls(Frame(camera, seq, device_time_s, host_time_s, jpeg), capture_time_s, regions,
                   frozenset(estimate_robots), tuple(Detection(*marker) for marker in predicted),
                   None if views is None else tuple((robot, np.array(T).reshape(4, 4)) for robot, T in views))


@enum.unique
class FrameOutcome(enum.Enum):
    REGIONS = "regions"  # detection searched only the regions (and found something, or had none)
    FULL_FRAME = "full frame"  # the whole frame was searched
    CORRUPT = "corrupt"  # the JPEG did not decode
    NO_CAMERA_POSE = "no camera pose"  # world-marker mode: the frame showed no world marker


@dataclass(frozen=True, slots=True, eq=False)
class FrameResult:
    """What the per-frame work made of a :class:`FrameJob`: a sighting per robot seen."""

    job: FrameJob
    outcome: FrameOutcome
    sightings: tuple[CubeSighting, ...] = ()
    error: str = ""
    dropped: Mapping[str, int] = field(default_factory=dict)  # markers found, then dropped: reason -> count
