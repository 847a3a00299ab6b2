"""The VRPN tracker server against a client written from the protocol facts, over loopback."""

import socket
import struct
import time

import numpy as np
import pytest
from sink_helpers import tracked
from vrpn_client import PingWatcher, TrackerClient, connect, recv_exact

from cubetrack.sink.base import OutputError
from cubetrack.sink.vrpn import VrpnParams, VrpnSink, parse_lob_request


@pytest.fixture
def sink(session_info):
    sink = VrpnSink(VrpnParams(port=0))
    sink.open(session_info)
    yield sink
    sink.close()


def test_configured_robots_are_trackers_and_pings_are_answered_before_the_session_opens(session_info):
    sink = VrpnSink(VrpnParams(port=0), robots=("robot 1!", "2nd"))  # the server starts, no session yet
    watcher = PingWatcher(sink.port, "robot_1")
    try:
        assert _wait(lambda: watcher.pong_at is not None)
        assert set(watcher.described_at) == {"robot_1", "robot_2nd"}  # found by name at once
        sink.open(session_info)
        sink.pose(tracked("robot 1!", 0))
        assert _wait(lambda: watcher.poses)
    finally:
        watcher.close()
        sink.close()
    # answered at the first ping after the call-back (pings go once a second); nothing printed
    assert watcher.pong_at - watcher.connected_at < 1.5 and not watcher.warnings and not watcher.errors
    assert [sender for sender, _, _ in watcher.poses] == ["robot_1"]  # the session's first pose
    assert watcher.poses[0][1] == pytest.approx(tracked("robot 1!", 0).time_s, abs=1e-6)


def test_a_sink_without_configured_robots_names_none_until_the_session_opens(session_info):
    sink = VrpnSink(VrpnParams(port=0))
    try:
        assert sink.server.senders == []
        sink.open(session_info)
        assert sink.server.senders == ["robot_1", "robot_2nd"]
    finally:
        sink.close()


def _wait(predicate, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


def clients_of(sink) -> int:
    return len(sink.server.clients)


@pytest.mark.parametrize("mode", ["lob", "tcp"])
def test_a_client_gets_descriptions_then_pos_quat_and_velocity_in_vrpn_order(sink, mode):
    client = TrackerClient(sink.port, "robot_1", mode)
    try:
        assert client.server_cookie[:16] == b"vrpn: ver. 07.38" and client.server_cookie[16:19] == b"  0"
        assert client.server_cookie[19:] == b"\x00" * 5
        assert client.wait_for(lambda c: "vrpn_Base pong_message" in c.order)  # answered its ping
        for i in range(5):
            sink.pose(tracked("robot 1!", i))
        sink.pose(tracked("2nd", 0, velocity=False))
        assert client.wait_for(lambda c: len(c.poses("robot_1")) == 5 and c.poses("robot_2nd"))
    finally:
        client.close()
    assert set(client.senders.values()) == {"robot_1", "robot_2nd"}
    assert {"vrpn_Tracker Pos_Quat", "vrpn_Tracker Velocity", "vrpn_Base pong_message"} <= set(client.types.values())
    assert not any(name.startswith("undescribed") for _, name, _, _ in client.reports)
    pong = next(r for r in client.reports if r[1] == "vrpn_Base pong_message")
    assert pong[0] == "robot_1" and pong[3] == b""  # from the tracker that pinged, empty body
    poses = client.poses("robot_1")
    for i, (t, sensor, position, quaternion) in enumerate(poses):
        expected = tracked("robot 1!", i)
        assert sensor == 0
        assert t == pytest.approx(expected.time_s, abs=1e-6)  # header time = capture time
        np.testing.assert_allclose(position, expected.position_m)
        np.testing.assert_allclose(quaternion, expected.quaternion_xyzw)  # x, y, z, w on the wire
    velocities = [r for r in client.reports if r[1] == "vrpn_Tracker Velocity" and r[0] == "robot_1"]
    assert len(velocities) == 5 and not any(r[0] == "robot_2nd" and r[1] == "vrpn_Tracker Velocity"
                                            for r in client.reports)
    sensor, pad, vx, vy, vz, qx, qy, qz, qw, dt = struct.unpack(">ii8d", velocities[0][3])
    assert len(velocities[0][3]) == 72 and (sensor, pad) == (0, 0)
    assert (vx, vy, vz) == (0.2, 0.0, 0.0) and dt == 1.0
    assert (qx, qy) == (0.0, 0.0) and qz == pytest.approx(np.sin(0.25)) and qw == pytest.approx(np.cos(0.25))


def test_a_stalled_client_never_blocks_the_tracker_and_a_vanished_one_is_forgotten(sink):
    good = TrackerClient(sink.port, "robot_1")
    stalled = connect(sink.port, rcvbuf=4096)  # cookie exchange, then it never reads again
    stalled.sendall(b"vrpn: ver. 07.38  0" + b"\x00" * 5)
    recv_exact(stalled, 24)
    vanished = connect(sink.port, mode="tcp")
    vanished.sendall(b"vrpn: ver. 07.38  0" + b"\x00" * 5)
    try:
        assert good.wait_for(lambda c: "vrpn_Base pong_message" in c.order)
        assert good.wait_for(lambda c: clients_of(sink) == 3)
        vanished.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        vanished.close()  # reset, mid-session
        n = 20000
        for i in range(n):  # returns although one client reads nothing
            sink.pose(tracked("robot 1!", i, velocity=False))
        last = tracked("robot 1!", n - 1).time_s
        assert good.wait_for(lambda c: any(abs(p[0] - last) < 1e-6 for p in c.poses("robot_1")), timeout_s=20)
        assert good.wait_for(lambda c: clients_of(sink) == 2)  # the vanished one is gone
        states = {c.address[1]: c for c in sink.server.clients.values()}
        stalled_state = states.pop(stalled.getsockname()[1])
        (good_state,) = states.values()
    finally:
        good.close()
        stalled.close()
    assert stalled_state.dropped > 0 and stalled_state.queued_bytes <= sink.server.params.max_queued_bytes
    # every pose reached the good client or was counted as dropped for it (a burst can outrun it too)
    assert len(good.poses("robot_1")) + good_state.dropped == n
    assert sink.server.dropped >= stalled_state.dropped + good_state.dropped  # (+ any for the vanished one)
    assert [p[0] for p in good.poses("robot_1")] == sorted(p[0] for p in good.poses("robot_1"))


def test_hostile_peers_are_refused_without_harm(sink):
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tcp_bad_cookie = connect(sink.port, mode="tcp")
    try:
        for junk in (b"", b"hello", b"127.0.0.1 80\x00", b"127.0.0.1;rm 5000\x00", b"x" * 300):
            udp.sendto(junk, ("127.0.0.1", sink.port))
        tcp_bad_cookie.sendall(b"vrpn: ver. 08.00  0" + b"\x00" * 5)  # another major version
        recv_exact(tcp_bad_cookie, 24)
        assert tcp_bad_cookie.recv(1) == b""  # dropped after the cookie
        liar = connect(sink.port, mode="tcp")  # a valid cookie, then a length below the header size
        liar.sendall(b"vrpn: ver. 07.38  0" + b"\x00" * 5 + struct.pack(">IIIiiI", 8, 0, 0, 0, 0, 0))
        recv_exact(liar, 24)
        liar.settimeout(5)
        while liar.recv(4096):
            pass
        liar.close()
        client = TrackerClient(sink.port, "robot_1")  # the server still serves
        assert client.wait_for(lambda c: "vrpn_Base pong_message" in c.order)  # it has taken the client in
        sink.pose(tracked("robot 1!", 0))
        assert client.wait_for(lambda c: len(c.poses("robot_1")) == 1)
        client.close()
    finally:
        udp.close()
        tcp_bad_cookie.close()


def test_call_back_requests_are_parsed_like_the_cpp_server():
    assert parse_lob_request(b"127.0.0.1 51549\x00") == ("127.0.0.1", 51549)
    assert parse_lob_request(b"127.0.0.1 1023\x00") is None  # below 1024
    assert parse_lob_request(b"127.0.0.1 51549 extra\x00") is None
    assert parse_lob_request(b"host-name 5000\x00") is None  # only letters, digits and dots


def test_requests_naming_another_address_are_ignored(sink):
    other = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    other.bind(("127.0.0.2", 0))
    other.listen(1)
    other.settimeout(1.5)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            udp.sendto(b"127.0.0.2 %d\x00" % other.getsockname()[1], ("127.0.0.1", sink.port))
        with pytest.raises(socket.timeout):
            other.accept()  # the request came from 127.0.0.1: no call-back to 127.0.0.2
    finally:
        other.close()


def test_a_port_in_use_is_a_one_line_error(sink):
    with pytest.raises(OutputError, match=f"cannot listen on 127.0.0.1:{sink.port}"):
        VrpnSink(VrpnParams(port=sink.port))
