"""A VRPN tracker server: one tracker per robot, as motion-capture systems serve rigid bodies.

Clients (vrpn_client_ros, vrpn_mocap, libmotioncapture/crazyswarm, the Unity and Unreal
plugins, ``vrpn_print_devices``) open ``<robot>@host:3883``. The wire protocol, from VRPN's
``vrpn_Connection.C`` and ``vrpn_Tracker.C`` (facts in docs/vrpn.md):

- The server has a UDP and a TCP socket on the same port (3883 by default). A default-mode
  client sends a UDP datagram ``"<ip> <port>\\0"`` and waits for the server to connect to that
  TCP port ("lob" mode); a ``tcp://`` client connects to the TCP port itself.
- Both sides send a 24-byte cookie at once (``vrpn: ver. 07.38``, two spaces, ``'0'``, NULs);
  only ``vrpn: ver. 07.`` and the log-mode digit are checked.
- Then messages: a 24-byte big-endian header (length = 24 + unpadded body, seconds,
  microseconds, sender id, type id, sequence number), the body padded to 8 bytes. Sender and
  type names are described (types -1 and -2) before any data that uses them.
- ``vrpn_Tracker Pos_Quat``: int32 sensor, int32 sensor again, float64 position[3] in metres,
  float64 quaternion x, y, z, w (64 bytes). ``vrpn_Tracker Velocity``: int32 sensor twice,
  float64 velocity[3] (m/s), float64 vel_quat x, y, z, w (rotation over ``vel_quat_dt``),
  float64 vel_quat_dt (72 bytes). Header time = the pose's capture time (Unix).
- A client pings (``vrpn_Base ping_message``) from its tracker's sender; the server answers
  ``vrpn_Base pong_message`` from the same tracker name.

Everything is sent over TCP (clients read it in every mode). One sender per robot, sensor 0
(as OptiTrack Motive does), named by :func:`cubetrack.sink.names.identifiers`.

Never blocking the pipeline: :meth:`VrpnServer.publish` appends to per-client queues and sends
what each socket takes at once, never waiting; a thread does the rest of the socket work (what a
socket would not take, connections, reading) without blocking. A client that does not read keeps at most
``max_queued_bytes`` queued besides a 64 KiB socket buffer (the oldest whole messages are
dropped and counted, so it gets recent poses, not a growing backlog); one that
vanishes or breaks the protocol is dropped. A call-back request is honoured only towards the
address it came from, and at most ``max_clients`` clients are served.
"""

from __future__ import annotations

import logging
import math
import re
import selectors
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from cubetrack.core.records import TrackedPose
from cubetrack.sink.base import OutputError, SessionInfo, Sink, is_loopback_host
from cubetrack.sink.names import identifiers

log = logging.getLogger(__name__)

DEFAULT_PORT = 3883
MAGIC = b"vrpn: ver. 07.38"
COOKIE = MAGIC + b"  0" + b"\x00" * 5
COOKIE_SIZE = 24
HEADER = struct.Struct(">IIIiiI")  # length, seconds, microseconds, sender, type, sequence
MAX_MESSAGE = 64008  # a C++ receiver's buffer
SENDER_DESCRIPTION, TYPE_DESCRIPTION = -1, -2
POS_QUAT = "vrpn_Tracker Pos_Quat"
VELOCITY = "vrpn_Tracker Velocity"
PING = "vrpn_Base ping_message"
PONG = "vrpn_Base pong_message"
TYPES = (POS_QUAT, VELOCITY, PONG)  # our type ids are their indexes
POS_QUAT_BODY = struct.Struct(">ii3d4d")
VELOCITY_BODY = struct.Struct(">ii3d4dd")
VEL_QUAT_DT_S = 1.0
FLUSH_ON_CLOSE_S = 1.0  # at most this long, all clients together, for what is queued when the server closes
SEND_BUFFER_BYTES = 64 * 1024  # kernel buffer per client: a slow client gets recent poses, not a backlog


def pad8(n: int) -> int:
    return n + (-n % 8)


def message(time_s: float, sender: int, type_id: int, body: bytes, sequence: int) -> bytes:
    """One framed message: header, body, zero padding to a multiple of 8."""
    seconds = math.floor(time_s)
    micros = min(999_999, int(round((time_s - seconds) * 1e6)))
    header = HEADER.pack(HEADER.size + len(body), seconds & 0xFFFFFFFF, micros, sender, type_id, sequence & 0xFFFFFFFF)
    return header + body + b"\x00" * (-len(body) % 8)


def description_body(name: str) -> bytes:
    """Body of a sender or type description: uint32 length with the NUL, the name, NUL."""
    data = name.encode("ascii") + b"\x00"
    return struct.pack(">I", len(data)) + data


def pos_quat_body(sensor: int, position_m: np.ndarray, quaternion_xyzw: np.ndarray) -> bytes:
    return POS_QUAT_BODY.pack(sensor, sensor, *np.asarray(position_m, float), *np.asarray(quaternion_xyzw, float))


def velocity_body(sensor: int, velocity_m_s: np.ndarray, angular_rad_s: np.ndarray,
                  dt_s: float = VEL_QUAT_DT_S) -> bytes:
    """Velocity and the rotation ``angular_rad_s`` (world frame) makes in ``dt_s``, as vel_quat."""
    angle = float(np.linalg.norm(angular_rad_s)) * dt_s
    axis = np.asarray(angular_rad_s, float) / np.linalg.norm(angular_rad_s) if angle > 0 else np.zeros(3)
    quat = [*(axis * math.sin(angle / 2)), math.cos(angle / 2)]
    return VELOCITY_BODY.pack(sensor, sensor, *np.asarray(velocity_m_s, float), *quat, dt_s)


def cookie_ok(cookie: bytes) -> bool:
    """What a C++ peer checks: the magic up to its last ``.`` and a log mode digit 0..3."""
    text = cookie[:16]
    dot = text.rfind(b".")
    return (len(cookie) == COOKIE_SIZE and dot > 0 and text[:dot + 1] == MAGIC[:MAGIC.rfind(b".") + 1]
            and 0 <= cookie[18] - ord("0") <= 3)


_LOB = re.compile(rb"^([A-Za-z0-9.]{1,199}) (\d{1,5})\x00?$")


def parse_lob_request(datagram: bytes) -> tuple[str, int] | None:
    """``(host, port)`` of a call-back request (``"<host> <port>\\0"``), None if malformed."""
    match = _LOB.match(datagram)
    if not match:
        return None
    port = int(match.group(2))
    return (match.group(1).decode("ascii"), port) if 1024 <= port <= 65535 else None


class _Client:
    """One connected client: its socket, queues, and the names it described."""

    def __init__(self, sock: socket.socket, address: tuple[str, int], connecting: bool):
        self.sock = sock
        self.address = address
        self.connecting = connecting
        self.ready = False  # its cookie arrived and checked out
        self.inbox = bytearray()
        self.outbox: deque[bytes] = deque()
        self.partial = memoryview(b"")  # the message being sent, never dropped midway
        self.queued_bytes = 0
        self.sequence = 0
        self.senders: dict[int, str] = {}
        self.types: dict[int, str] = {}
        self.dropped = 0


@dataclass(frozen=True, slots=True)
class VrpnParams:
    """Where to listen (``host`` loopback unless another address is given) and the limits."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    max_clients: int = 32
    max_queued_bytes: int = 64 * 1024


class VrpnServer:
    """The protocol engine (module doc): sockets bound in the constructor, served by a thread."""

    def __init__(self, params: VrpnParams = VrpnParams()):
        self.params = params
        self.tcp, self.udp = _bind_pair(params.host, params.port)
        self.port = self.tcp.getsockname()[1]
        self.senders: list[str] = []
        self.clients: dict[socket.socket, _Client] = {}
        self.dropped = 0  # messages dropped for slow clients, all clients together
        self.lock = threading.Lock()
        self.selector = selectors.DefaultSelector()
        self.wake_r, self.wake_w = socket.socketpair()
        for sock in (self.tcp, self.udp, self.wake_r, self.wake_w):
            sock.setblocking(False)
        self.selector.register(self.tcp, selectors.EVENT_READ, "accept")
        self.selector.register(self.udp, selectors.EVENT_READ, "lob")
        self.selector.register(self.wake_r, selectors.EVENT_READ, "wake")
        self.closing = False
        self.thread = threading.Thread(target=self._serve, name="cubetrack-vrpn", daemon=True)
        self.thread.start()

    # --- called from the sink's thread -----------------------------------------------------
    def add_senders(self, names: list[str]) -> None:
        """Register tracker names (described to connected clients at once, to later ones on connect)."""
        with self.lock:
            new = [n for n in names if n not in self.senders]
            first = len(self.senders)
            self.senders.extend(new)
            for client in self.clients.values():
                if client.ready:
                    for i, name in enumerate(new, start=first):
                        self._queue(client, self._framed(client, i, SENDER_DESCRIPTION, description_body(name), 0.0))
        self._wake()

    @property
    def serving(self) -> bool:
        """Whether any client is ready for messages (without one, :meth:`publish` has nothing to do)."""
        return any(client.ready for client in list(self.clients.values()))

    def publish(self, sender: str, time_s: float, bodies: list[tuple[str, bytes]]) -> None:
        """Queue messages (type name, body) from tracker ``sender`` to every ready client."""
        sender_id = self.senders.index(sender)
        wake = False
        with self.lock:
            for client in self.clients.values():
                if client.ready:
                    for type_name, body in bodies:
                        self._queue(client, self._framed(client, sender_id, TYPES.index(type_name), body, time_s))
                    # sent from here while the socket takes it (no hand-over to the I/O thread); the
                    # I/O thread is woken for a rest the socket would not take, or a broken connection
                    if self._send_queued(client) is not None or client.partial or client.outbox:
                        wake = True
        if wake:
            self._wake()

    def close(self) -> None:
        if self.closing:
            return
        self.closing = True
        self._wake()
        self.thread.join(5)
        deadline = time.monotonic() + FLUSH_ON_CLOSE_S
        with self.lock:  # what clients still have queued goes out (the session's last poses), briefly
            for client in self.clients.values():
                if client.connecting:
                    continue
                try:
                    client.sock.settimeout(max(0.01, deadline - time.monotonic()))
                    client.sock.sendall(client.partial)
                    client.sock.sendall(b"".join(client.outbox))
                except OSError:
                    pass
        for sock in list(self.clients) + [self.tcp, self.udp, self.wake_r, self.wake_w]:
            sock.close()
        self.selector.close()

    # --- the I/O thread -----------------------------------------------------------------------
    def _wake(self) -> None:
        try:
            self.wake_w.send(b"x")
        except (BlockingIOError, OSError):
            pass  # already awake (or closing)

    def _framed(self, client: _Client, sender: int, type_id: int, body: bytes, time_s: float) -> bytes:
        data = message(time_s, sender, type_id, body, client.sequence)
        client.sequence += 1
        return data

    def _queue(self, client: _Client, data: bytes) -> None:
        client.outbox.append(data)
        client.queued_bytes += len(data)
        while client.queued_bytes > self.params.max_queued_bytes and len(client.outbox) > 1:
            client.queued_bytes -= len(client.outbox.popleft())
            client.dropped += 1
            self.dropped += 1

    def _serve(self) -> None:
        while not self.closing:
            for key, events in self.selector.select(timeout=1.0):
                try:
                    self._handle(key, events)
                except Exception as exc:  # a bug must not kill the server silently
                    log.error("VRPN server: %s", exc, exc_info=True)
            with self.lock:
                for client in list(self.clients.values()):
                    self._update_interest(client)

    def _handle(self, key: selectors.SelectorKey, events: int) -> None:
        if key.data == "wake":
            try:
                while self.wake_r.recv(4096):
                    pass
            except BlockingIOError:
                pass
        elif key.data == "accept":
            try:
                sock, address = self.tcp.accept()
            except OSError:
                return
            self._add_client(sock, address, connecting=False)
        elif key.data == "lob":
            self._lob_request()
        else:
            client = key.data
            if events & selectors.EVENT_WRITE:
                self._write(client)
            if events & selectors.EVENT_READ and client.sock in self.clients:
                self._read(client)

    def _lob_request(self) -> None:
        try:
            datagram, (source_ip, _) = self.udp.recvfrom(200)
        except OSError:
            return
        request = parse_lob_request(datagram)
        if request is None:
            log.debug("VRPN: ignoring a malformed call-back request from %s", source_ip)
            return
        host, port = request
        if host != source_ip:  # never connect anywhere a datagram says: only back to its sender
            log.warning("VRPN: call-back request from %s names %s; ignored", source_ip, host)
            return
        with self.lock:
            if any(c.address == (host, port) for c in self.clients.values()):
                return  # a repeated request while we connect or serve it
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        try:
            sock.connect_ex((host, port))
        except OSError:
            sock.close()
            return
        self._add_client(sock, (host, port), connecting=True)

    def _add_client(self, sock: socket.socket, address, connecting: bool) -> None:
        with self.lock:
            if len(self.clients) >= self.params.max_clients:
                log.warning("VRPN: %d clients already; refusing %s", len(self.clients), address)
                sock.close()
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
            client = _Client(sock, tuple(address), connecting)
            self.clients[sock] = client
            if not connecting:
                self._queue(client, COOKIE)
            self.selector.register(sock, selectors.EVENT_READ | selectors.EVENT_WRITE, client)
        log.info("VRPN client %s:%d %s", address[0], address[1], "calling back" if connecting else "connected")

    def _drop(self, client: _Client, why: str) -> None:
        with self.lock:
            if self.clients.pop(client.sock, None) is None:
                return
        self.selector.unregister(client.sock)
        client.sock.close()
        log.info("VRPN client %s:%d gone (%s); %d message(s) dropped for it", *client.address, why, client.dropped)

    def _update_interest(self, client: _Client) -> None:
        wants = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.connecting or client.partial or client.outbox
                                        else 0)
        self.selector.modify(client.sock, wants, client)

    def _write(self, client: _Client) -> None:
        if client.connecting:
            error = client.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if error:
                self._drop(client, f"call-back failed: {errno_name(error)}")
                return
            client.connecting = False
            with self.lock:
                client.outbox.appendleft(COOKIE)
                client.queued_bytes += COOKIE_SIZE
        with self.lock:
            failure = self._send_queued(client)
        if failure is not None:
            self._drop(client, failure)

    def _send_queued(self, client: _Client) -> str | None:
        """Send what ``client`` has queued until its socket would block (with the lock held, by
        either thread); the error that broke the connection, else None."""
        while True:
            if not client.partial:
                if not client.outbox:
                    return None
                data = client.outbox.popleft()
                client.queued_bytes -= len(data)
                client.partial = memoryview(data)
            try:
                sent = client.sock.send(client.partial)
            except BlockingIOError:
                return None
            except OSError as exc:
                return str(exc) or type(exc).__name__
            client.partial = client.partial[sent:]
            if client.partial:
                return None

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError as exc:
            self._drop(client, str(exc))
            return
        if not data:
            self._drop(client, "closed")
            return
        client.inbox += data
        if not client.ready:
            if len(client.inbox) < COOKIE_SIZE:
                return
            cookie, client.inbox = bytes(client.inbox[:COOKIE_SIZE]), client.inbox[COOKIE_SIZE:]
            if not cookie_ok(cookie):
                self._drop(client, f"not a VRPN 07 peer: {cookie[:19]!r}")
                return
            self._greet(client)
        self._messages(client)

    def _greet(self, client: _Client) -> None:
        """Cookie checked: describe our senders and types, then data may flow."""
        with self.lock:
            for i, name in enumerate(self.senders):
                self._queue(client, self._framed(client, i, SENDER_DESCRIPTION, description_body(name), 0.0))
            for i, name in enumerate(TYPES):
                self._queue(client, self._framed(client, i, TYPE_DESCRIPTION, description_body(name), 0.0))
            client.ready = True

    def _messages(self, client: _Client) -> None:
        inbox = client.inbox
        while len(inbox) >= HEADER.size:
            length, seconds, micros, sender, type_id, _ = HEADER.unpack_from(inbox)
            if length < HEADER.size or length > MAX_MESSAGE:
                self._drop(client, f"bad message length {length}")
                return
            total = HEADER.size + pad8(length - HEADER.size)
            if len(inbox) < total:
                return
            body = bytes(inbox[HEADER.size:length])
            del inbox[:total]
            if type_id in (SENDER_DESCRIPTION, TYPE_DESCRIPTION):
                if len(body) < 4 or len(body) > 100 or not 0 <= sender < 2000:
                    self._drop(client, "bad description")
                    return
                (n,) = struct.unpack_from(">I", body)
                name = body[4:4 + n].split(b"\x00")[0].decode("ascii", "replace")
                (client.senders if type_id == SENDER_DESCRIPTION else client.types)[sender] = name
            elif client.types.get(type_id) == PING:
                pinged = client.senders.get(sender)
                if pinged in self.senders:
                    with self.lock:
                        self._queue(client, self._framed(client, self.senders.index(pinged), TYPES.index(PONG), b"",
                                                         seconds + micros * 1e-6))


def errno_name(error: int) -> str:
    import errno
    import os

    return f"{errno.errorcode.get(error, error)} ({os.strerror(error)})"


def _bind_pair(host: str, port: int) -> tuple[socket.socket, socket.socket]:
    """A listening TCP socket and a UDP socket on the same ``host:port`` (port 0: any free one)."""
    for _ in range(20 if port == 0 else 1):
        tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            tcp.bind((host, port))
            udp.bind((host, tcp.getsockname()[1]))
            tcp.listen(8)
            return tcp, udp
        except OSError as exc:
            tcp.close()
            udp.close()
            error = exc
    raise OutputError(f"VRPN server cannot listen on {host}:{port} (UDP and TCP): {error.strerror or error}")


class VrpnSink(Sink):
    """Serves every robot as a VRPN tracker (module doc); the server starts in the constructor
    with ``robots`` (the configured ones) as its trackers, so that a client that connects before
    the session finds them and has its pings answered."""

    name = "vrpn"

    def __init__(self, params: VrpnParams = VrpnParams(), robots: tuple[str, ...] = ()):
        self.server = VrpnServer(params)
        self.trackers: dict[str, str] = {}
        self._announce(robots)
        where = f"{params.host}:{self.server.port}"
        self.where = f"VRPN trackers <robot>@{where}"
        if not is_loopback_host(params.host):
            log.warning("VRPN server listening on %s (UDP and TCP): reachable from other machines", where)
        else:
            log.info("VRPN server listening on %s (UDP and TCP, loopback only)", where)

    @property
    def port(self) -> int:
        return self.server.port

    def _announce(self, robots: tuple[str, ...]) -> None:
        self.trackers = identifiers(list(robots), "robot")
        self.server.add_senders(list(self.trackers.values()))

    def open(self, session: SessionInfo) -> None:
        self._announce(tuple(session.robots))
        host = self.server.params.host
        log.info("VRPN trackers: %s", ", ".join(f"{t}@{host}:{self.port}" for t in self.trackers.values()))

    def pose(self, pose: TrackedPose) -> None:
        tracker = self.trackers.get(pose.robot)
        if tracker is None or not self.server.serving:
            return
        bodies = [(POS_QUAT, pos_quat_body(0, pose.position_m, pose.quaternion_xyzw))]
        if pose.velocity_m_s is not None and pose.angular_velocity_rad_s is not None \
                and np.all(np.isfinite(pose.velocity_m_s)) and np.all(np.isfinite(pose.angular_velocity_rad_s)):
            bodies.append((VELOCITY, velocity_body(0, pose.velocity_m_s, pose.angular_velocity_rad_s)))
        self.server.publish(tracker, pose.time_s, bodies)

    def close(self) -> None:
        self.server.close()
