"""How things move in the simulated arena: the robot's path (and its speed along it), the
uneven floor and vibration that tilt and bounce the robot, and people walking through.

Everything here is an exact function of time: the ground truth is the same function the
renderer draws, evaluated at the instant a row of an image was exposed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

from cubetrack.core.errors import SimulationError
from cubetrack.core.geometry import make_T

_SHARP_WAYPOINTS = 8
_SHARP_MIN_SEGMENT_M = 0.3
_SHARP_MAX_TURN_DEG = 150.0
_SHARP_STEP_M = 0.001  # resolution of the speed profile along the path
# distance between a sharp-path robot's drive wheels: the 0.25 m wide robot body (wheels at its sides);
# with the path's wheel acceleration limit it bounds the yaw acceleration, 2 accel / track
WHEEL_TRACK_M = 0.25
_SHARP_STRAIGHT_CURVATURE = 1e-6  # 1/m: below it a sharp path runs straight


class RobotPath:
    """A closed path on the floor travelled at constant speed, heading along the path.

    ``figure8``: x = a sin(th), y = b sin(2 th) (crosses the arena centre, so the robot drives
    over the world marker). ``rectangle``: the superellipse |x/a|^4 + |y/b|^4 = 1.
    """

    def __init__(self, kind: str, half_extent_m: tuple[float, float], speed_m_s: float, start_fraction: float):
        self.kind = kind
        self.a, self.b = half_extent_m
        self.speed_m_s = speed_m_s
        th = np.linspace(0.0, 2.0 * math.pi, 20001)
        pts = self._point(th)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self._theta = th
        self._arc = np.concatenate([[0.0], np.cumsum(seg)])
        self.length_m = float(self._arc[-1])
        self._s0 = start_fraction * self.length_m

    def _point(self, th: np.ndarray) -> np.ndarray:
        if self.kind == "figure8":
            return np.stack([self.a * np.sin(th), self.b * np.sin(2.0 * th)], axis=-1)
        c, s = np.cos(th), np.sin(th)
        return np.stack([self.a * np.sign(c) * np.sqrt(np.abs(c)), self.b * np.sign(s) * np.sqrt(np.abs(s))], axis=-1)

    def pose(self, t_s: float) -> tuple[np.ndarray, float]:
        """Ground position (x, y) in metres and heading (rad) ``t_s`` seconds after the start."""
        s = (self._s0 + self.speed_m_s * t_s) % self.length_m
        th = float(np.interp(s, self._arc, self._theta))
        eps = 1e-5
        p = self._point(np.array([th - eps, th, th + eps]))
        d = p[2] - p[0]
        return p[1], math.atan2(d[1], d[0])


@dataclass(frozen=True, slots=True)
class _Piece:
    """A straight segment (``radius_m`` 0) or a circular arc of a :class:`SharpPath`."""

    start_m: float       # arc length at the piece's start
    length_m: float
    origin: np.ndarray   # segment: start point; arc: centre
    angle_rad: float     # segment: heading; arc: polar angle of the start point about the centre
    radius_m: float = 0.0
    turn: float = 0.0    # arc: +1 counter-clockwise, -1 clockwise

    def pose(self, s_m: float) -> tuple[np.ndarray, float]:
        u = s_m - self.start_m
        if self.radius_m == 0.0:
            d = np.array([math.cos(self.angle_rad), math.sin(self.angle_rad)])
            return self.origin + u * d, self.angle_rad
        a = self.angle_rad + self.turn * u / self.radius_m
        p = self.origin + self.radius_m * np.array([math.cos(a), math.sin(a)])
        return p, a + self.turn * math.pi / 2.0


class SharpPath:
    """A closed loop through random waypoints in the path's extent, its corners rounded by arcs
    of ``turn_radius_m`` (smaller where the segments are short), driven at up to ``speed_m_s``,
    accelerating and braking at ``accel_m_s2``, and slow enough in each turn that the yaw rate
    stays at most ``turn_rate_rad_s``. Turns of up to 150 degrees: sharp turns at speed.

    A wheeled robot cannot step its yaw rate: the curvature ramps linearly into and out of each
    arc (a clothoid transition: the arcs' curvature averaged over a sliding window of arc
    length), long enough that at the turn's speed the yaw acceleration stays within what the
    wheels can do, ``2 accel_m_s2 / WHEEL_TRACK_M``; where the curvature ramps more steeply
    (shorter arcs) the robot drives slower."""

    def __init__(self, half_extent_m: tuple[float, float], speed_m_s: float, accel_m_s2: float,
                 turn_rate_rad_s: float, turn_radius_m: float, start_fraction: float, rng: np.random.Generator):
        points = self._waypoints(half_extent_m, rng)
        self.pieces = self._round_corners(points, turn_radius_m)
        self.length_m = self.pieces[-1].start_m + self.pieces[-1].length_m
        self.yaw_accel_limit_rad_s2 = 2.0 * accel_m_s2 / WHEEL_TRACK_M
        n = max(math.ceil(self.length_m / _SHARP_STEP_M), 16)
        s = np.linspace(0.0, self.length_m, n + 1)
        ds = self.length_m / n
        curvature = self._transition_curvature(s, ds, speed_m_s, turn_rate_rad_s, turn_radius_m)
        self._xy, self._yaw = self._integrate(s, ds, curvature)
        # speed limit along the path: through each turn (where the curvature is not zero) one
        # speed, at which the yaw rate v k stays within turn_rate_rad_s and the yaw acceleration
        # v^2 dk/ds within the wheels' limit; braking and accelerating happen on the straights
        turn_limit = np.minimum(turn_rate_rad_s / np.maximum(np.abs(curvature), 1e-12),
                                np.sqrt(self.yaw_accel_limit_rad_s2
                                        / np.maximum(np.abs(np.gradient(curvature, ds)), 1e-12)))
        limit = np.minimum(speed_m_s, self._per_turn_minimum(turn_limit, np.abs(curvature) > _SHARP_STRAIGHT_CURVATURE))
        v = self._speed_profile(limit, accel_m_s2, ds)
        # time along the path: constant acceleration between profile points
        dt = 2.0 * ds / (v[:-1] + v[1:])
        self._s = s
        self._t = np.concatenate([[0.0], np.cumsum(dt)])
        self.lap_s = float(self._t[-1])
        self._t0 = float(np.interp(start_fraction * self.length_m, s, self._t))

    @staticmethod
    def _per_turn_minimum(values: np.ndarray, turning: np.ndarray) -> np.ndarray:
        """``values`` with each closed-loop run of ``turning`` samples set to the run's minimum."""
        out = values.copy()
        if turning.all():
            return np.full_like(values, values.min())
        shift = int(np.argmin(turning))  # a straight sample: runs start after it
        order = np.roll(np.arange(len(values)), -shift)
        run = np.cumsum(~turning[order])  # the same id along one run of turning samples
        on = turning[order]
        for r in np.unique(run[on]):
            idx = order[on & (run == r)]
            out[idx] = values[idx].min()
        return out

    @staticmethod
    def _speed_profile(limit_m_s: np.ndarray, accel_m_s2: float, ds: float) -> np.ndarray:
        """The fastest speed under ``limit_m_s`` reached accelerating and braking at ``accel_m_s2``
        (twice round the loop, so the limits carry over the start)."""
        v2 = limit_m_s**2
        n = len(v2) - 1
        for _ in range(2):
            for k in range(1, n + 1):
                v2[k] = min(v2[k], v2[k - 1] + 2.0 * accel_m_s2 * ds)
            v2[0] = min(v2[0], v2[n] + 2.0 * accel_m_s2 * ds)
            for k in range(n - 1, -1, -1):
                v2[k] = min(v2[k], v2[k + 1] + 2.0 * accel_m_s2 * ds)
            v2[n] = min(v2[n], v2[0] + 2.0 * accel_m_s2 * ds)
        return np.sqrt(v2)

    def _transition_curvature(self, s: np.ndarray, ds: float, speed_m_s: float, turn_rate_rad_s: float,
                              turn_radius_m: float) -> np.ndarray:
        """Signed curvature (1/m) at ``s``: the arcs' curvature averaged over a window as long as
        the yaw rate of a turn at full radius needs to ramp up at the yaw acceleration limit."""
        starts = np.array([p.start_m for p in self.pieces])
        k_piece = np.array([p.turn / p.radius_m if p.radius_m > 0 else 0.0 for p in self.pieces])
        k = k_piece[np.clip(np.searchsorted(starts, s[:-1], "right") - 1, 0, None)]
        v_turn = min(speed_m_s, turn_rate_rad_s * turn_radius_m)
        ramp_m = v_turn**2 / (turn_radius_m * self.yaw_accel_limit_rad_s2)
        window = max(round(ramp_m / ds) | 1, 1)
        smooth = uniform_filter1d(k, window, mode="wrap")
        return np.append(smooth, smooth[0])

    def _integrate(self, s: np.ndarray, ds: float, curvature: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (x, y) and headings at ``s`` of the path with ``curvature``, placed on the
        designed path at the middle of its first straight and closed (the small gap the
        transitions leave spread evenly along the loop)."""
        first = self.pieces[0]
        mid = round((first.start_m + 0.5 * first.length_m) / ds)
        heading = np.concatenate([[0.0], np.cumsum(0.5 * (curvature[:-1] + curvature[1:]) * ds)])
        turns = round((heading[-1] - heading[0]) / (2.0 * math.pi))
        heading -= s / s[-1] * (heading[-1] - heading[0] - 2.0 * math.pi * turns)  # closes to whole turns
        heading += first.angle_rad - heading[mid]
        tangent = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
        xy = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * (tangent[:-1] + tangent[1:]) * ds, axis=0)])
        gap = xy[-1] - xy[0]
        xy -= np.outer(s / s[-1], gap)
        tangent -= gap / s[-1]
        xy += first.pose(first.start_m + 0.5 * first.length_m)[0] - xy[mid]
        return xy, np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))

    @staticmethod
    def _waypoints(half_extent_m: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
        a, b = 0.9 * half_extent_m[0], 0.9 * half_extent_m[1]
        for _ in range(10_000):
            p = rng.uniform([-a, -b], [a, b], (_SHARP_WAYPOINTS, 2))
            seg = np.roll(p, -1, axis=0) - p
            length = np.linalg.norm(seg, axis=1)
            if length.min() < _SHARP_MIN_SEGMENT_M:
                continue
            d_in, d_out = np.roll(seg, 1, axis=0), seg
            cos_turn = np.sum(d_in * d_out, axis=1) / (np.roll(length, 1) * length)
            if np.degrees(np.arccos(np.clip(cos_turn, -1, 1))).max() <= _SHARP_MAX_TURN_DEG:
                return p
        raise SimulationError("no sharp path fits the path extent; enlarge path_size_m")

    @staticmethod
    def _round_corners(p: np.ndarray, radius_m: float) -> tuple[_Piece, ...]:
        n = len(p)
        seg = np.roll(p, -1, axis=0) - p
        length = np.linalg.norm(seg, axis=1)
        heading = np.arctan2(seg[:, 1], seg[:, 0])
        # at waypoint i the path turns from segment i-1 to segment i
        turn = (heading - np.roll(heading, 1) + math.pi) % (2 * math.pi) - math.pi
        half = np.tan(np.abs(turn) / 2.0)
        radius = np.minimum(radius_m, 0.45 * np.minimum(length, np.roll(length, 1)) / np.maximum(half, 1e-9))
        tangent = radius * half  # distance from the waypoint to where the arc starts and ends
        pieces: list[_Piece] = []
        s = 0.0
        for i in range(n):
            j = (i + 1) % n
            d = seg[i] / length[i]
            straight = length[i] - tangent[i] - tangent[j]
            pieces.append(_Piece(s, float(straight), p[i] + tangent[i] * d, float(heading[i])))
            s += straight
            # the arc at waypoint j, from segment i into segment j
            if abs(turn[j]) > 1e-9:
                sign = 1.0 if turn[j] > 0 else -1.0
                start = p[j] - tangent[j] * d
                normal = sign * np.array([-d[1], d[0]])
                centre = start + radius[j] * normal
                v = start - centre
                arc = float(radius[j] * abs(turn[j]))
                pieces.append(_Piece(s, arc, centre, math.atan2(v[1], v[0]), float(radius[j]), sign))
                s += arc
        return tuple(pieces)

    def pose(self, t_s: float) -> tuple[np.ndarray, float]:
        """Ground position (x, y) in metres and heading (rad) ``t_s`` seconds after the start."""
        t = (self._t0 + t_s) % self.lap_s
        s = float(np.interp(t, self._t, self._s))
        xy = np.array([np.interp(s, self._s, self._xy[:, 0]), np.interp(s, self._s, self._xy[:, 1])])
        return xy, float(np.interp(s, self._s, self._yaw))


HAND_LIFT_M = (0.05, 0.35)     # a hand-held body's ground frame is this high above the floor (its range)
HAND_TILT_DEG = 25.0           # ... tilts this far about the horizontal axes (amplitude of each)
HAND_YAW_DEG = 70.0            # ... and turns this far about the vertical (amplitude)
HAND_TURN_RAD_S = 0.8          # ... at this RMS angular speed (a wrist turning an object to look at it)
_HAND_WAVES = 3                # sinusoids per axis
_HAND_FREQ_SPREAD = (0.6, 1.4)  # each sinusoid's frequency, relative to the axis's mean


class HandPath:
    """Free 6-DoF motion of a body carried by hand: every axis of position and orientation a sum
    of ``_HAND_WAVES`` sinusoids of random phase and frequency (smooth, no floor contact). The
    position stays within ``half_extent_m`` (x, y) and ``HAND_LIFT_M`` (height of the ground
    frame), its RMS speed over the horizontal axes is ``speed_m_s``; the orientation tilts up to
    about ``HAND_TILT_DEG`` and turns up to ``HAND_YAW_DEG`` at ``HAND_TURN_RAD_S`` RMS. Walking-hand
    motion: 0.1-0.5 m/s (the real footage's board moved at about 0.085 m/s, ../shared/data/real
    README), frequencies of a fraction of a hertz; the source of these sizes is that footage and
    the arm's reach (a desk-sized volume), not a motion-capture study."""

    def __init__(self, half_extent_m: tuple[float, float], speed_m_s: float, rng: np.random.Generator):
        lift_mid, lift_half = (HAND_LIFT_M[0] + HAND_LIFT_M[1]) / 2.0, (HAND_LIFT_M[1] - HAND_LIFT_M[0]) / 2.0
        amplitudes = np.array([*half_extent_m, lift_half, *np.radians([HAND_TILT_DEG, HAND_TILT_DEG, HAND_YAW_DEG])])
        self.centre = np.array([0.0, 0.0, lift_mid, 0.0, 0.0, 0.0])
        self.amplitude = amplitudes / _HAND_WAVES  # per sinusoid: the sum never leaves the range
        spread = rng.uniform(*_HAND_FREQ_SPREAD, (6, _HAND_WAVES))
        self.phase = rng.uniform(0.0, 2.0 * math.pi, (6, _HAND_WAVES))
        # RMS speed of one axis with angular frequencies c * spread: c * a * sqrt(sum(spread^2) / 2)
        unit = self.amplitude[:, None] * np.sqrt(0.5 * np.sum(spread**2, axis=1, keepdims=True))
        omega = np.empty((6, _HAND_WAVES))
        horizontal = math.sqrt(float(np.sum(unit[:2] ** 2)))
        omega[:3] = spread[:3] * speed_m_s / horizontal
        omega[3:] = spread[3:] * HAND_TURN_RAD_S / math.sqrt(float(np.sum(unit[3:] ** 2)))
        self.omega = omega

    def T_world_robot(self, t_s: float) -> np.ndarray:
        """The carried body's ground frame (x forward, z up when level) ``t_s`` seconds after the start."""
        x = self.centre + self.amplitude * np.sin(self.omega * t_s + self.phase).sum(axis=1)
        return make_T(Rotation.from_euler("ZYX", [x[5], x[4], x[3]]).as_matrix(), x[:3])


def make_path(kind: str, half_extent_m: tuple[float, float], speed_m_s: float, start_fraction: float,
              accel_m_s2: float, turn_rate_rad_s: float, turn_radius_m: float,
              rng: np.random.Generator) -> RobotPath | SharpPath | HandPath:
    """The path a robot drives, or the hand-held motion of ``handheld`` (``rng`` places a sharp
    path's waypoints, or draws the hand's sinusoids)."""
    if kind == "sharp":
        return SharpPath(half_extent_m, speed_m_s, accel_m_s2, turn_rate_rad_s, turn_radius_m, start_fraction, rng)
    if kind == "handheld":
        return HandPath(half_extent_m, speed_m_s, rng)
    return RobotPath(kind, half_extent_m, speed_m_s, start_fraction)


class _Waves:
    """A random sum of sinusoids with a given standard deviation (``size`` independent channels)."""

    def __init__(self, rng: np.random.Generator, std: float, count: int, low: float, high: float, size: int):
        self.freq = rng.uniform(low, high, (size, count))
        self.phase = rng.uniform(0.0, 2.0 * math.pi, (size, count))
        self.amplitude = std * math.sqrt(2.0 / count)

    def __call__(self, t: float) -> np.ndarray:
        return self.amplitude * np.sin(2.0 * math.pi * self.freq * t + self.phase).sum(axis=1)


class Terrain:
    """An uneven floor under a vibrating robot: the floor's height is a sum of plane waves
    (wavelengths 0.4-1.5 m, ``bumps_m`` std); the robot stands on it at four wheels (80 % of its
    length and width), so it tilts with the floor's slope; on top it bounces (``bounce_m`` std)
    and wobbles in roll and pitch (``wobble_rad`` std each), both 3-12 Hz."""

    def __init__(self, bumps_m: float, bounce_m: float, wobble_rad: float, footprint_m: tuple[float, float],
                 floor_rng: np.random.Generator, vibration_rng: np.random.Generator):
        count = 6
        self.k = 2.0 * math.pi / floor_rng.uniform(0.4, 1.5, count)
        angle = floor_rng.uniform(0.0, 2.0 * math.pi, count)
        self.direction = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        self.phase = floor_rng.uniform(0.0, 2.0 * math.pi, count)
        self.bumps = bumps_m * math.sqrt(2.0 / count)
        self.bounce = _Waves(vibration_rng, bounce_m, 3, 3.0, 12.0, 1)
        self.wobble = _Waves(vibration_rng, wobble_rad, 3, 3.0, 12.0, 2)
        hx, hy = 0.4 * footprint_m[0], 0.4 * footprint_m[1]
        self.wheels = np.array([[hx, hy], [hx, -hy], [-hx, hy], [-hx, -hy]])  # FL FR BL BR, robot frame

    def height_m(self, xy: np.ndarray) -> np.ndarray:
        """Floor height at (N, 2) points, metres."""
        return self.bumps * np.sin(self.k * (np.asarray(xy) @ self.direction.T) + self.phase).sum(axis=-1)

    def T_world_robot(self, xy: np.ndarray, yaw_rad: float, t_s: float) -> np.ndarray:
        """The robot's ground frame (x forward, z up) at ground point ``xy`` heading ``yaw_rad``."""
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        wheels = xy + self.wheels @ np.array([[c, s], [-s, c]])
        z = self.height_m(wheels)
        p = np.column_stack([wheels, z])
        forward = (p[0] + p[1]) - (p[2] + p[3])
        left = (p[0] + p[2]) - (p[1] + p[3])
        x_axis = forward / np.linalg.norm(forward)
        z_axis = np.cross(forward, left)
        z_axis /= np.linalg.norm(z_axis)
        R = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
        roll, pitch = self.wobble(t_s)
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        # Euler "xy" (extrinsic): R_y(pitch) @ R_x(roll)
        wobble = np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])
        return make_T(R @ wobble, [xy[0], xy[1], float(z.mean()) + float(self.bounce(t_s)[0])])


PERSON_SPEED_M_S = (1.0, 1.5)
PERSON_BODY_M = (0.28, 0.45, 1.45)   # depth (along the walk), width, height of the body box
PERSON_HEAD_M = (0.2, 0.18, 0.25)
_PERSON_PAUSE_S = 8.0                # mean pause between two crossings
_PERSON_START_RADIUS_M = 3.5         # people walk in from this far out and leave as far
_PERSON_CAMERA_CLEARANCE_M = 0.6
_PERSON_ROBOT_CLEARANCE_M = 0.5


@dataclass(frozen=True, slots=True)
class Crossing:
    """A person walking in a straight line from ``start`` to ``end`` (floor points, metres)."""

    start_s: float
    end_s: float
    start: np.ndarray
    end: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class Person:
    """A person who crosses the arena again and again (a box body and a box head)."""

    crossings: tuple[Crossing, ...]
    albedo: float

    def T_world_person(self, t_s: float) -> np.ndarray | None:
        """The person's floor frame (x along the walk, z up) at ``t_s``, or None when away."""
        for c in self.crossings:
            if c.start_s <= t_s <= c.end_s:
                u = (t_s - c.start_s) / (c.end_s - c.start_s)
                d = c.end - c.start
                heading = math.atan2(d[1], d[0])
                p = c.start + u * d
                return make_T(Rotation.from_euler("z", heading).as_matrix(), [p[0], p[1], 0.0])
        return None


def plan_people(count: int, duration_s: float, cameras_xy: np.ndarray, robot_xy_at, rng: np.random.Generator
                ) -> tuple[Person, ...]:
    """``count`` people, each crossing the arena on straight lines through its middle (within
    0.9 m of the centre) at 1.0-1.5 m/s, pausing about 8 s out of the room between crossings;
    a crossing never comes within 0.6 m of a camera nor within 0.5 m of a robot
    (``robot_xy_at(t)``: (N, 2) robot ground points at scene time t)."""
    people = []
    for _ in range(count):
        crossings = []
        t = float(rng.uniform(-6.0, 0.5 * _PERSON_PAUSE_S))
        while t < duration_s:
            crossing = None
            for _attempt in range(200):
                angle = rng.uniform(0.0, 2.0 * math.pi)
                offset = rng.uniform(-0.9, 0.9)
                d = np.array([math.cos(angle), math.sin(angle)])
                n = np.array([-d[1], d[0]])
                half = math.sqrt(_PERSON_START_RADIUS_M**2 - offset**2)
                start, end = offset * n - half * d, offset * n + half * d
                # closest approach of the line to each camera
                along = np.clip((cameras_xy - start) @ d, 0.0, 2.0 * half)
                gap = np.linalg.norm(cameras_xy - (start + along[:, None] * d), axis=1)
                if gap.min() < _PERSON_CAMERA_CLEARANCE_M:
                    continue
                duration = 2.0 * half / rng.uniform(*PERSON_SPEED_M_S)
                times = np.linspace(t, t + duration, 60)
                walk = start + ((times - t) / duration)[:, None] * (end - start)
                if all(np.linalg.norm(robot_xy_at(tk) - w, axis=1).min() >= _PERSON_ROBOT_CLEARANCE_M
                       for tk, w in zip(times, walk, strict=True)):
                    crossing = Crossing(t, t + duration, start, end)
                    break
                t += 0.5  # wait for the robot to pass
            if crossing is not None:
                crossings.append(crossing)
                t = crossing.end_s
            t += float(rng.exponential(_PERSON_PAUSE_S))
        people.append(Person(tuple(crossings), float(rng.uniform(0.1, 0.5))))
    return tuple(people)
