"""Run ``cubecam-native`` -- the camera-node firmware core built for the host --
from tests.

``build_native()`` builds it once per test session (``make -C firmware native``);
``NativeNode`` starts it on a folder of JPEG files, waits until it listens and
stops it again::

    with NativeNode(images_dir, fps=30) as node:
        requests.get(node.base_url + "status")
        serial.Serial(node.pty_path, 115200, timeout=1)   # Improv + console

The node speaks the HTTP API and the serial protocol of the project's
contracts (sections 1 and 2) exactly as the firmware on the board does; see
``firmware/README.md`` for its command line.
"""

from __future__ import annotations

import fcntl
import os
import queue
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FIRMWARE_DIR = REPO / "firmware"
NATIVE_BINARY = FIRMWARE_DIR / "build" / "cubecam-native"

_build_lock = threading.Lock()
_built: Path | None = None


class NativeNodeError(RuntimeError):
    """cubecam-native could not be built or did not come up."""


def make_firmware(*args: str) -> subprocess.CompletedProcess[str]:
    """``make -C firmware -j N *args``, one at a time across processes: the test suite runs in two
    pytest-xdist workers, and two makes writing the same ``firmware/build`` at once could link a
    binary that the other is running, or interleave half-written objects. The lock is a file in
    ``firmware/build``; the second make finds the targets up to date."""
    build = FIRMWARE_DIR / "build"
    build.mkdir(exist_ok=True)
    jobs = str(max(1, min(4, os.cpu_count() or 1)))
    with open(build / ".make.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return subprocess.run(["make", "-C", str(FIRMWARE_DIR), "-j", jobs, *args], capture_output=True, text=True)


def build_native() -> Path:
    """Build ``firmware/build/cubecam-native`` (once per session) and return its path."""
    global _built
    with _build_lock:
        if _built is None:
            result = make_firmware("native")
            if result.returncode != 0:
                raise NativeNodeError(
                    "make -C firmware native failed:\n" + result.stdout[-4000:] + result.stderr[-4000:]
                )
            _built = NATIVE_BINARY
        return _built


class NativeNode:
    """A running ``cubecam-native``.

    images_dir: folder of ``*.jpg`` files served as camera frames (name order, cycled).
    fps: camera rate, one of 30, 15, 7.5 (the ISX019's); None keeps the stored setting.
    port: TCP port, 0 = an ephemeral one (kept across simulated reboots).
    settings_path: settings record file; None = a fresh file in a temporary folder.
    serial: "pty" (Improv + console on a pseudo-terminal, see ``pty_path``) or None.
    ssid: written to the settings before boot so the node joins its simulated
        network and serves HTTP at once (start() waits for it); None leaves the
        settings alone (a new settings file then means an unprovisioned node
        waiting for Improv) and start() returns without waiting for HTTP: call
        wait_until_listening() once the node should be online.
    fail_ssids: joining these SSIDs fails (for provisioning error paths).
    join_ms: simulated time to join a network.
    settings: more ``key: value`` settings to write before boot (console keys).
    """

    def __init__(
        self,
        images_dir: str | os.PathLike,
        fps: float | None = None,
        port: int = 0,
        settings_path: str | os.PathLike | None = None,
        serial: str | None = "pty",
        ssid: str | None = "cubetrack-lab",
        fail_ssids: tuple[str, ...] = (),
        join_ms: int = 100,
        settings: dict[str, str] | None = None,
        bind: str = "127.0.0.1",
        startup_timeout: float = 20.0,
    ) -> None:
        if serial not in ("pty", None):
            raise ValueError("serial must be 'pty' or None")
        self.images_dir = Path(images_dir)
        self._fps = fps
        self._requested_port = port
        self._serial = serial
        self._ssid = ssid
        self._fail_ssids = tuple(fail_ssids)
        self._join_ms = join_ms
        self._settings = dict(settings or {})
        self._bind = bind
        self._timeout = startup_timeout
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self.settings_path = Path(settings_path) if settings_path is not None else None
        self.process: subprocess.Popen[str] | None = None
        self.pty_path: str | None = None
        self.port: int | None = None
        self.base_url: str | None = None
        self.log_path: Path | None = None
        self._lines: queue.Queue[str] = queue.Queue()
        self.stdout_lines: list[str] = []

    # -- lifecycle ---------------------------------------------------------
    def command(self) -> list[str]:
        """The command line this node runs."""
        cmd = [
            str(build_native()),
            "--images", str(self.images_dir),
            "--settings", str(self.settings_path),
            "--port", str(self._requested_port),
            "--bind", self._bind,
            "--serial", "pty" if self._serial == "pty" else "none",
            "--join-ms", str(self._join_ms),
            "--tee-serial",
        ]
        sets = dict(self._settings)
        if self._fps is not None:
            sets["fps"] = f"{self._fps:g}"
        if self._ssid is not None:
            sets["ssid"] = self._ssid
        for key, value in sets.items():
            cmd += ["--set", f"{key}={value}"]
        for ssid in self._fail_ssids:
            cmd += ["--fail-ssid", ssid]
        return cmd

    def start(self) -> NativeNode:
        self._tmp = tempfile.TemporaryDirectory(prefix="cubecam-native-")
        if self.settings_path is None:
            self.settings_path = Path(self._tmp.name) / "settings.bin"
        self.log_path = Path(self._tmp.name) / "serial.log"
        cmd = self.command()
        log = open(self.log_path, "w")
        try:
            self.process = subprocess.Popen(
                cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log, text=True, bufsize=1
            )
        finally:
            log.close()
        threading.Thread(target=self._pump_stdout, daemon=True).start()
        try:
            if self._serial == "pty":
                self.pty_path = self.wait_for_line("serial: ").split(": ", 1)[1]
            if self._ssid is not None:
                self.wait_until_listening()
        except BaseException:
            self.stop()
            raise
        return self

    def wait_until_listening(self, timeout: float | None = None) -> str:
        """Wait for the next ``http: <url>`` line; sets base_url and port."""
        url = self.wait_for_line("http: ", timeout).split(": ", 1)[1].strip()
        self.base_url = url
        self.port = int(url.rstrip("/").rsplit(":", 1)[1])
        return url

    def wait_for_line(self, prefix: str, timeout: float | None = None) -> str:
        """Return the next stdout line starting with prefix."""
        deadline = time.monotonic() + (self._timeout if timeout is None else timeout)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise NativeNodeError(f"cubecam-native printed no {prefix!r} line; log:\n{self.log_text()}")
            try:
                line = self._lines.get(timeout=min(remaining, 0.2))
            except queue.Empty:
                if self.process is not None and self.process.poll() is not None and self._lines.empty():
                    raise NativeNodeError(
                        f"cubecam-native exited with {self.process.returncode}; log:\n{self.log_text()}"
                    ) from None
                continue
            if line.startswith(prefix):
                return line.rstrip("\n")

    def _pump_stdout(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        for line in self.process.stdout:
            self.stdout_lines.append(line)
            self._lines.put(line)

    def log_text(self) -> str:
        """Everything the node wrote to its serial port (and errors) so far."""
        if self.log_path is None or not self.log_path.exists():
            return ""
        return self.log_path.read_text(errors="replace")

    def stop(self) -> int | None:
        """Stop the node (SIGTERM, then SIGKILL after 5 s); returns its exit status."""
        code = None
        if self.process is not None:
            if self.process.poll() is None:
                self.process.terminate()
                try:
                    self.process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
            code = self.process.returncode
            if self.process.stdout is not None:
                self.process.stdout.close()
        if self._tmp is not None:
            shutil.rmtree(self._tmp.name, ignore_errors=True)
            self._tmp = None
        return code

    def __enter__(self) -> NativeNode:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
