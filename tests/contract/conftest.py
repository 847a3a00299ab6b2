"""The implementations under test: the Python emulator and the firmware's host build
``cubecam-native``. Both serve the same synthetic frames at the same rate; every test in this
folder runs against each (``node`` fixture)."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from cubecam.testdata import write_images

FPS = 15.0  # one of the ISX019 rates (30, 15, 7.5) that the firmware accepts
FRAMES = 40
WIDTH, HEIGHT = 640, 480  # VGA: what the firmware reports (its configured resolution)
MAX_CLIENTS = 4  # both: firmware kMaxClients, emulator default
REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Node:
    kind: str
    host: str
    port: int
    fps: float = FPS
    width: int = WIDTH
    height: int = HEIGHT
    max_clients: int = MAX_CLIENTS

    @property
    def base_url(self) -> str:
        return f"http://{self.host}:{self.port}/"


def wait_for_frames(n: Node, timeout_s: float = 10.0) -> Node:
    """Wait until the node has a frame to serve (it answers /capture with 200)."""
    from contract_http import get

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if get(n.host, n.port, "/capture").status == 200:
                return n
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise AssertionError(f"{n.kind} at {n.base_url} served no frame within {timeout_s} s")
        time.sleep(0.05)


@pytest.fixture(scope="session")
def contract_images(tmp_path_factory) -> Path:
    return write_images(tmp_path_factory.mktemp("contract-images"), FRAMES, WIDTH, HEIGHT)


def _native_helper():
    """tests/helpers/native.py (written with the firmware). Missing, the firmware half of the
    conformance suite fails (it used to skip, so the suite passed with half of it gone)."""
    if not (REPO / "tests" / "helpers" / "native.py").exists():
        pytest.fail("tests/helpers/native.py is missing: the firmware's half of the conformance suite cannot run",
                    pytrace=False)
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from tests.helpers import native  # noqa: PLC0415

    return native


@pytest.fixture(scope="module", params=["emulator", "native"])
def node(request, contract_images, tmp_path_factory):
    if request.param == "emulator":
        from cubecam.emulator import Emulator

        with Emulator(images=contract_images, fps=FPS, name="contract", loop=True) as emu:
            port = int(emu.base_urls["contract"].rsplit(":", 1)[1].strip("/"))
            yield wait_for_frames(Node("emulator", "127.0.0.1", port))
        return
    native = _native_helper()
    native.build_native()
    settings = tmp_path_factory.mktemp("native") / "settings.bin"
    with native.NativeNode(contract_images, fps=FPS, port=0, settings_path=settings, serial=None) as n:
        assert n.port is not None
        yield wait_for_frames(Node("native", "127.0.0.1", n.port))


def wait_until_idle(n: Node, timeout_s: float = 5.0) -> None:
    """Wait until the node counts no client but the /status request asking. A node notices a
    closed stream only when its next part fails to send, so clients a test has closed may still
    hold slots for a few frame periods; the next test must not meet them (they would make it a
    503 test)."""
    import json

    from contract_http import get

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            a = get(n.host, n.port, "/status")
            if a.status == 200 and json.loads(a.body)["clients"] <= 1:
                return
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise AssertionError(f"{n.kind} at {n.base_url} still counts closed clients after {timeout_s} s")
        time.sleep(0.05)


@pytest.fixture(autouse=True)
def node_idle_between_tests(request):
    """Every test starts on a node with all of its client slots free."""
    if "node" in request.fixturenames:
        wait_until_idle(request.getfixturevalue("node"))
    yield
