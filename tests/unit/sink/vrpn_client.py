"""A VRPN tracker client written from ../shared/reference/vrpn-facts.md, independently of the
server code: the call-back ("lob") handshake of a default C++ client (or a direct ``tcp://``
connection), the cookie, sender and type descriptions, pings, and report decoding.

It plays vrpn_Tracker_Remote: it describes ``VRPN Control`` and its tracker as senders 0 and
1 and the C++ list of types (ping 16, pong 17) as a real client does (facts §7), pings from
its tracker sender, and keeps every report it receives.
"""

from __future__ import annotations

import socket
import struct
import threading
import time

CLIENT_COOKIE = b"vrpn: ver. 07.35  0\x00\x00\x00\x00\x00"  # an older minor version, as a distro's client may be
CLIENT_TYPES = ["VRPN_Connection_Got_First_Connection", "VRPN_Connection_Got_Connection",
                "VRPN_Connection_Dropped_Connection", "VRPN_Connection_Dropped_Last_Connection",
                "vrpn_Tracker Pos_Quat", "vrpn_Tracker Velocity", "vrpn_Tracker Acceleration",
                "vrpn_Tracker To_Room", "vrpn_Tracker Unit_To_Sensor", "vrpn_Tracker Request_Tracker_To_Room",
                "vrpn_Tracker Request_Unit_To_Sensor", "vrpn_Tracker Workspace",
                "vrpn_Tracker Request_Tracker_Workspace", "vrpn_Tracker set_update_rate",
                "vrpn_Tracker Reset_Origin", "vrpn_Base text_message", "vrpn_Base ping_message",
                "vrpn_Base pong_message"]


def frame(sender: int, type_id: int, body: bytes, seq: int, time_s: float = 0.0) -> bytes:
    """Header (len = 24 + unpadded body, sec, usec, sender, type, seq; big-endian) + body + pad."""
    sec = int(time_s)
    head = struct.pack(">IIIiiI", 24 + len(body), sec, int((time_s - sec) * 1e6), sender, type_id, seq)
    return head + body + b"\x00" * (-len(body) % 8)


def describe(kind: int, ident: int, name: str, seq: int) -> bytes:
    name_z = name.encode() + b"\x00"
    return frame(ident, kind, struct.pack(">I", len(name_z)) + name_z, seq)


def connect(port: int, mode: str = "lob", rcvbuf: int | None = None, timeout_s: float = 5.0) -> socket.socket:
    """A TCP connection to the server: lob = ask it by UDP to call back, tcp = connect directly."""
    if mode == "tcp":
        return socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # inherited by the accepted socket
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    listener.settimeout(0.5)
    request = b"127.0.0.1 %d\x00" % listener.getsockname()[1]
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:  # a fresh socket per request, as C++ does
                udp.connect(("127.0.0.1", port))
                udp.send(request)
            try:
                sock, _ = listener.accept()
                sock.settimeout(timeout_s)
                return sock
            except TimeoutError:
                continue
        raise TimeoutError("the VRPN server never called back")
    finally:
        listener.close()


def recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("server closed the connection")
        data += chunk
    return data


class TrackerClient:
    """Connects, checks the server's cookie, describes itself, pings from ``tracker`` and
    collects reports on a thread: ``reports`` holds (sender name, type name, time, body)."""

    def __init__(self, port: int, tracker: str, mode: str = "lob", cookie: bytes = CLIENT_COOKIE):
        self.sock = connect(port, mode)
        self.sock.sendall(cookie)  # each side sends its cookie at once
        self.server_cookie = recv_exact(self.sock, 24)
        self.sock.settimeout(None)  # a quiet server (no robot seen yet) is not a broken one
        self.senders: dict[int, str] = {}
        self.types: dict[int, str] = {}
        self.reports: list[tuple[str, str, float, bytes]] = []
        self.order: list[str] = []  # "describe" / type names in arrival order
        self.closed = threading.Event()
        seq = 0
        out = b""
        for i, name in enumerate(["VRPN Control", tracker]):
            out += describe(-1, i, name, seq)
            seq += 1
        for i, name in enumerate(CLIENT_TYPES):
            out += describe(-2, i, name, seq)
            seq += 1
        out += frame(1, CLIENT_TYPES.index("vrpn_Base ping_message"), b"", seq)
        self.sock.sendall(out)
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            while True:
                head = recv_exact(self.sock, 24)
                length, sec, usec, sender, type_id, _ = struct.unpack(">IIIiiI", head)
                assert 24 <= length <= 64008, length
                padded = (length - 24) + (-(length - 24) % 8)
                body = recv_exact(self.sock, padded)[:length - 24]
                if type_id in (-1, -2):
                    (n,) = struct.unpack(">I", body[:4])
                    assert n == len(body) - 4 and body[-1] == 0 and len(body) <= 100
                    (self.senders if type_id == -1 else self.types)[sender] = body[4:4 + n - 1].decode()
                    self.order.append("describe")
                else:
                    # data before its descriptions would be dropped by a C++ client: keep it visible
                    name = self.types.get(type_id, f"undescribed type {type_id}")
                    self.order.append(name)
                    self.reports.append((self.senders.get(sender, f"undescribed sender {sender}"), name,
                                         sec + usec * 1e-6, body))
        except (ConnectionError, OSError, AssertionError):
            self.closed.set()

    def poses(self, tracker: str) -> list[tuple[float, int, tuple, tuple]]:
        """(time, sensor, position, quaternion x,y,z,w) of every Pos_Quat report of ``tracker``."""
        out = []
        for sender, name, t, body in list(self.reports):
            if sender == tracker and name == "vrpn_Tracker Pos_Quat":
                assert len(body) == 64  # a C++ client drops the connection on any other size
                sensor, pad, *values = struct.unpack(">ii7d", body)
                assert pad == sensor
                out.append((t, sensor, tuple(values[:3]), tuple(values[3:])))
        return out

    def wait_for(self, predicate, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate(self):
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        self.sock.close()


PING_WARN_AFTER_S = 3.0  # facts §10: a warning a second once the first unanswered ping is 3 s old
PING_ERROR_AFTER_S = 10.0  # ... and an error a second from 10 s on
LOB_FIRST_WAIT_S, LOB_RESEND_S = 1.0, 2.0  # facts §3.2: wait 1 s for the call-back, then re-send every 2 s


class PingWatcher:
    """A client that starts as a C++ ``vrpn_Tracker_Remote`` (``vrpn_print_devices``) does, before
    or after its server: its ping cycle starts at once (facts §10), it asks by UDP to be called back
    until the server does (facts §3.2), pings every second until a pong comes from its tracker's
    sender, and counts the lines the C++ client would print for the missing pong (``warnings``,
    ``errors``, each with its time). It keeps when each sender was described and every report.
    Runs on a thread until :meth:`close`."""

    def __init__(self, port: int, tracker: str):
        self.port, self.tracker = port, tracker
        self.started = time.monotonic()
        self.connected_at: float | None = None
        self.pong_at: float | None = None
        self.described_at: dict[str, float] = {}  # sender name -> when its description arrived
        self.warnings: list[float] = []
        self.errors: list[float] = []
        self.poses: list[tuple[str, float, bytes]] = []  # (sender, header time, body) of Pos_Quat reports
        self.last_ping = -1e9
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
            listener.bind(("127.0.0.1", 0))
            listener.listen(1)
            listener.settimeout(0.05)
            sock = self._connected(listener)
            if sock is not None:
                with sock:
                    self._serve(sock)

    def _connected(self, listener: socket.socket) -> socket.socket | None:
        """The call-back connection, cookies swapped and this client described (None: stopped)."""
        request = b"127.0.0.1 %d\x00" % listener.getsockname()[1]
        next_request = self.started
        while not self.stop.is_set():
            self._ping_clock(None)
            now = time.monotonic()
            if now >= next_request:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                    udp.sendto(request, ("127.0.0.1", self.port))
                next_request = now + (LOB_FIRST_WAIT_S if next_request == self.started else LOB_RESEND_S)
            try:
                sock, _ = listener.accept()
            except TimeoutError:
                continue
            sock.settimeout(5.0)
            sock.sendall(CLIENT_COOKIE)
            recv_exact(sock, 24)
            sock.sendall(b"".join([describe(-1, i, n, 0) for i, n in enumerate(["VRPN Control", self.tracker])]
                                  + [describe(-2, i, n, 0) for i, n in enumerate(CLIENT_TYPES)]))
            sock.settimeout(0.05)
            self.connected_at = time.monotonic()
            return sock
        return None

    def _ping_clock(self, sock: socket.socket | None) -> None:
        """The C++ ``client_mainloop``: once a second while no pong came, a ping (when connected)
        and, past 3 s (10 s) since the cycle began, a warning (an error)."""
        now = time.monotonic()
        if self.pong_at is not None or now - self.last_ping < 1.0:
            return
        self.last_ping = now
        if sock is not None:
            sock.sendall(frame(1, CLIENT_TYPES.index("vrpn_Base ping_message"), b"", 0))
        age = now - self.started
        if age >= PING_ERROR_AFTER_S:
            self.errors.append(now)
        elif age >= PING_WARN_AFTER_S:
            self.warnings.append(now)

    def _serve(self, sock: socket.socket) -> None:
        inbox = b""
        senders: dict[int, str] = {}
        types: dict[int, str] = {}
        while not self.stop.is_set():
            self._ping_clock(sock)
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            inbox += data
            while len(inbox) >= 24:
                length, sec, usec, sender, type_id, _ = struct.unpack_from(">IIIiiI", inbox)
                total = 24 + (length - 24) + (-(length - 24) % 8)
                if len(inbox) < total:
                    break
                body, inbox = inbox[24:length], inbox[total:]
                if type_id in (-1, -2):
                    name = body[4:4 + struct.unpack(">I", body[:4])[0] - 1].decode()
                    (senders if type_id == -1 else types)[sender] = name
                    if type_id == -1:
                        self.described_at.setdefault(name, time.monotonic())
                elif types.get(type_id) == "vrpn_Base pong_message" and senders.get(sender) == self.tracker:
                    self.pong_at = self.pong_at or time.monotonic()
                elif types.get(type_id) == "vrpn_Tracker Pos_Quat":
                    self.poses.append((senders.get(sender, "?"), sec + usec * 1e-6, body))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
