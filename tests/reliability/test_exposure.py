"""Every server the project starts binds loopback unless told otherwise, and says so when told
otherwise (issue 12, item 5): the camera emulator (library and `cubecam emulate`), the firmware
built for the host (cubecam-native), the VRPN, Foxglove and Zenoh outputs of `cubetrack track`, and
the dashboard. "Binds loopback" is checked from outside: a connection to this machine's own
network address is refused."""

from __future__ import annotations

import logging
import re
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from cubecam.emulator import Emulator
from cubecam.testdata import write_images

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
from tests.helpers.native import build_native  # noqa: E402

WARNING = "reachable from the network"


def network_address() -> str | None:
    """This machine's address on its outbound interface (no packet is sent); None without one."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("10.255.255.255", 1))
        except OSError:
            return None
        address = s.getsockname()[0]
    return None if address.startswith("127.") else address


def reachable(host: str, port: int) -> bool:
    try:
        socket.create_connection((host, port), timeout=1).close()
        return True
    except OSError:
        return False


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    return write_images(tmp_path_factory.mktemp("img"), 3, 160, 120)


def port_of(url: str) -> int:
    return int(re.search(r":(\d+)/", url).group(1))


def test_the_emulator_binds_loopback_by_default_and_is_silent_about_it(images, caplog):
    caplog.set_level(logging.WARNING)
    with Emulator(images=images, fps=5, name="cam") as emu:
        port = port_of(emu.base_urls["cam"])
        assert emu.base_urls["cam"].startswith("http://127.0.0.1:")
        assert reachable("127.0.0.1", port)
        outside = network_address()
        if outside is not None:
            assert not reachable(outside, port)
    assert WARNING not in caplog.text


def test_the_emulator_warns_when_it_serves_the_network(images, caplog):
    caplog.set_level(logging.WARNING)
    with Emulator(images=images, fps=5, name="cam", host="0.0.0.0") as emu:
        port = port_of(emu.base_urls["cam"])
        outside = network_address()
        if outside is not None:
            assert reachable(outside, port)  # told otherwise: it really serves the network ...
    assert WARNING in caplog.text and "camera cam" in caplog.text  # ... and says so


@pytest.mark.parametrize("bind,warned", [(None, False), ("0.0.0.0", True)])
def test_cubecam_emulate_says_when_it_serves_the_network(images, bind, warned):
    cmd = [sys.executable, "-m", "cubecam.cli", "emulate", "--images", str(images), "--port", "0", "--duration", "0.3"]
    proc = subprocess.run(cmd + (["--bind", bind] if bind else []), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert (WARNING in proc.stderr) is warned, proc.stderr
    if not bind:
        assert re.search(r"http://127\.0\.0\.1:\d+/stream", proc.stdout)


@pytest.mark.parametrize("bind", [None, "0.0.0.0"])
def test_cubecam_native_binds_loopback_unless_told_otherwise_and_says_so(images, bind):
    if shutil.which("g++") is None or shutil.which("make") is None:
        pytest.skip("g++ and make are needed to build cubecam-native (tests/install.sh installs them)")
    binary = build_native()
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [str(binary), "--images", str(images), "--settings", f"{tmp}/settings.bin", "--port", "0",
               "--serial", "none", "--set", "ssid=lab"] + (["--bind", bind] if bind else [])
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            for line in proc.stdout:
                if line.startswith("http: "):
                    port = port_of(line.split(": ", 1)[1].strip())
                    break
            else:
                pytest.fail("cubecam-native printed no http: line")
            assert reachable("127.0.0.1", port)
            outside = network_address()
            if outside is not None:
                assert reachable(outside, port) is (bind is not None)
        finally:
            proc.terminate()
            _, err = proc.communicate(timeout=10)
    assert ("reachable from the network" in err) is (bind is not None), err


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def output(kind: str, address: str):
    """An output server started as `cubetrack track --<kind> ADDRESS` starts it."""
    from cubetrack.app.outputs import OutputSpec, output_sinks

    return output_sinks([OutputSpec({"type": kind, "address": address}, Path("."), f"--{kind}")])[0]


@pytest.mark.parametrize("kind", ["vrpn", "foxglove"])
def test_vrpn_and_foxglove_bind_loopback_unless_told_otherwise_and_say_so(kind, caplog):
    caplog.set_level(logging.INFO)
    outside = network_address()
    for address, exposed in ((str(free_port()), False), (f"0.0.0.0:{free_port()}", True)):
        caplog.clear()
        sink = output(kind, address)
        try:
            port = sink.port if kind == "vrpn" else sink.server.port
            assert reachable("127.0.0.1", port)
            if outside is not None:
                assert reachable(outside, port) is exposed, (kind, address)
        finally:
            sink.close()
        assert ("reachable from other machines" in caplog.text) is exposed, caplog.text


def test_zenoh_listens_on_loopback_unless_told_otherwise_and_says_so(caplog):
    pytest.importorskip("zenoh")
    from cubetrack.sink.zenoh_session import json_endpoints, open_session, ros_endpoints

    assert json_endpoints().listen == ("tcp/127.0.0.1:7447",) and ros_endpoints().listen == ("tcp/localhost:0",)
    caplog.set_level(logging.INFO)
    outside = network_address()
    for host, exposed in (("127.0.0.1", False), ("0.0.0.0", True)):
        caplog.clear()
        port = free_port()
        session = open_session(json_endpoints(listen=(f"tcp/{host}:{port}",)), "zenoh output")
        try:
            assert reachable("127.0.0.1", port)
            if outside is not None:
                assert reachable(outside, port) is exposed
        finally:
            session.close()
        assert ("reachable from other machines" in caplog.text) is exposed, caplog.text


def test_the_dashboard_binds_loopback_unless_told_otherwise_and_says_so(caplog):
    from cubetrack.sink.dashboard.server import DashboardServer

    caplog.set_level(logging.INFO)
    outside = network_address()
    for host, exposed in (("127.0.0.1", False), ("0.0.0.0", True)):
        caplog.clear()
        server = DashboardServer(host=host, port=0) if host != "127.0.0.1" else DashboardServer(port=0)
        try:
            assert reachable("127.0.0.1", server.port)
            if outside is not None:
                assert reachable(outside, server.port) is exposed
        finally:
            server.close()
        assert ("reachable from other machines" in caplog.text) is exposed, caplog.text
