"""Helpers of the output tests (unit and end to end): free loopback ports, a Zenoh router standing
in for ``rmw_zenohd``, Zenoh peers, a session with two robots and three cameras, poses to send.

A module of its own (not conftest.py) so that tests in other folders can import it by name."""

import socket

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.records import CameraWatchState, TrackedPose


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port nothing listens on right now (TCP and UDP both free)."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
            tcp.bind(("127.0.0.1", 0))
            port = tcp.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                try:
                    udp.bind(("127.0.0.1", port))
                except OSError:
                    continue
            return port
    raise RuntimeError("no free port")


def open_router():
    """A Zenoh router on 127.0.0.1 (what ``ros2 run rmw_zenoh_cpp rmw_zenohd`` would be): (session, locator)."""
    import zenoh

    locator = f"tcp/127.0.0.1:{free_port()}"
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", f'["{locator}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config), locator


def peer(connect: str):
    """A plain Zenoh peer session connected to ``connect`` (the consumer's side)."""
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", f'["{connect}"]')
    config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def wait_connected(consumer, producer, timeout_s: float = 15.0) -> None:
    """Until a sample put by session ``producer`` reaches session ``consumer`` (routes are set up:
    a loaded machine can take seconds, and samples sent before that are lost)."""
    import threading
    import time

    key = f"probe/{producer.zid()}"
    arrived = threading.Event()
    sub = consumer.declare_subscriber(key, lambda sample: arrived.set())
    deadline = time.monotonic() + timeout_s
    while not arrived.wait(0.1):
        producer.put(key, b"")
        if time.monotonic() > deadline:
            raise TimeoutError("the two Zenoh sessions never reached each other")
    sub.undeclare()


def look_at(position, target) -> np.ndarray:
    """T_world_cam of an optical frame at ``position`` looking at ``target`` (z forward, y down)."""
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = position
    return T


INTRINSICS = CameraIntrinsics(640, 480, np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), np.zeros(5))


def tracked(robot: str, i: int, *, velocity=True) -> TrackedPose:
    """The ``i``-th pose of a robot turning at 0.5 rad/s about z while moving along x at 0.2 m/s."""
    t = 1_700_000_000.0 + 0.05 * i
    yaw = 0.5 * 0.05 * i
    q = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-3, 2e-3, 3e-3]) if velocity else None
    return TrackedPose(robot, t, np.array([0.01 * i, 0.5, 0.06]), q, ("cam-a", "cam b"), ("top",), 0.02,
                       velocity_m_s=np.array([0.2, 0.0, 0.0]) if velocity else None,
                       angular_velocity_rad_s=np.array([0.0, 0.0, 0.5]) if velocity else None,
                       covariance=cov)


def rejoined(camera: str, position, time_s: float = 1_700_000_001.0) -> CameraWatchState:
    """What the camera watching tells outputs when ``camera`` rejoins, re-calibrated to a pose at
    ``position`` looking at the origin (issue 27)."""
    return CameraWatchState(camera, time_s, "rejoined", message="re-calibrated from 200 sightings; rejoined",
                            T_world_cam=look_at(np.array(position, float), [0, 0, 0]))
