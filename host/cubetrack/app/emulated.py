"""Simulated cameras served over HTTP by the camera emulator, run as its own process.

``cubecam emulate`` (the device-side tools) serves a recording with the firmware's HTTP API. The
tracker never imports those tools: workflows that need served cameras (the demo, the live
benchmark) start the command as a child process, exactly as a user would, and read what it
serves from its ``--ready-file``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cubetrack.core.errors import SourceError

START_TIMEOUT_S = 60.0  # reading and checking a long recording's frames takes a while


class EmulatedCameras:
    """``cubecam emulate --recording REC`` on 127.0.0.1 (ephemeral ports) in a child process.

    Use as a context manager; inside it, ``urls`` maps each camera to its stream URL,
    ``period_s`` is the replay's length and ``clock_shift_s`` moves a recorded host time onto this
    machine's Unix time (live = recorded + shift). The process ends by itself after the last frame
    (``wait_finished``) and is stopped on exit.
    """

    def __init__(self, recording: str | Path, extra_args: tuple[str, ...] = ()):
        self.recording = Path(recording)
        self.extra_args = extra_args
        self.urls: dict[str, str] = {}
        self.period_s = 0.0
        self.clock_shift_s = 0.0
        self._process: subprocess.Popen | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None

    def __enter__(self) -> EmulatedCameras:
        self._tmp = tempfile.TemporaryDirectory(prefix="cubetrack-emulator-")
        ready = Path(self._tmp.name) / "ready.json"
        stderr = open(Path(self._tmp.name) / "stderr.txt", "w+b")
        command = [sys.executable, "-m", "cubecam", "emulate", "--recording", str(self.recording),
                   "--bind", "127.0.0.1", "--port", "0", "--exit-at-end", "--ready-file", str(ready),
                   "--parent-pid", str(os.getpid()),
                   *self.extra_args]
        try:
            self._process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                             stderr=stderr)
        except OSError as exc:
            stderr.close()
            self._tmp.cleanup()
            raise SourceError(f"cannot start the camera emulator: {exc.strerror}") from None
        self._stderr = stderr
        try:
            self._wait_ready(ready)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _wait_ready(self, ready: Path) -> None:
        assert self._process is not None  # started by __enter__
        deadline = time.monotonic() + START_TIMEOUT_S
        while not ready.exists():
            code = self._process.poll()
            if code is not None:
                self._stderr.seek(0)
                lines = self._stderr.read().decode("utf-8", "replace").strip().splitlines()
                raise SourceError(f"the camera emulator exited ({code}) before serving: "
                                  f"{lines[-1] if lines else 'no message'}")
            if time.monotonic() > deadline:
                raise SourceError(f"the camera emulator did not start serving within {START_TIMEOUT_S:.0f} s")
            time.sleep(0.02)
        doc = json.loads(ready.read_text(encoding="utf-8"))
        self.urls = dict(doc["urls"])
        self.period_s = float(doc["period_s"])
        self.clock_shift_s = float(doc["clock_shift_s"])

    def wait_finished(self, timeout_s: float) -> bool:
        """Wait until the replay has ended (the emulator exits after its last frame)."""
        assert self._process is not None, "wait_finished() inside the with block"
        try:
            self._process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return False
        return True

    def __exit__(self, *exc) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(5.0)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._stderr.close()
        if self._tmp is not None:
            self._tmp.cleanup()
