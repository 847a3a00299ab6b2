"""The Wi-Fi password never leaves the provisioning run (issue 12, item 5): `cubecam -vv provision`
with a distinctive password, against the fake board (tests/tools/fakeboard.py, including one that
echoes everything back garbled) and against the firmware core (cubecam-native on a pty), and
every output is searched for it -- stdout, stderr with debug logging, the tracker config written,
every other file the run left, the node's serial log, its status answers and console, a crash
report. A part of the password counts as a leak too."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from cubecam.cli import main
from cubecam.link import NodeLink
from cubecam.provision import ProvisionRequest
from cubecam.testdata import write_images

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "tools"))
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
from fakeboard import FakeBoard  # noqa: E402

from tests.helpers.native import NativeNode, build_native  # noqa: E402

PASSWORD = 'Wq7 "distinct", Pa55 phrase'  # comma, quotes and spaces (issue 12, item 6)
FRAGMENT = PASSWORD[3:15]  # ' "distinct",': any leak of most of it


def assert_absent(outputs: dict[str, str | bytes]) -> None:
    for where, text in outputs.items():
        raw = text.encode("utf-8", "replace") if isinstance(text, str) else text
        assert FRAGMENT.encode() not in raw, f"the password shows in {where}"


def files_under(folder: Path, *exclude: Path) -> dict[str, bytes]:
    return {str(p): p.read_bytes() for p in folder.rglob("*") if p.is_file() and p not in exclude}


def provision_cli(port: str, tmp_path: Path, *extra: str, timeout: float = 60) -> subprocess.CompletedProcess:
    password_file = tmp_path / "wifi-password"
    password_file.write_text(PASSWORD + "\n")
    return subprocess.run(
        [sys.executable, "-m", "cubecam.cli", "-vv", "provision", "--port", port, "--password-file", str(password_file),
         "--name", "cam1", "--config", str(tmp_path / "tracker.toml"), *extra],
        capture_output=True, text=True, timeout=timeout, cwd=tmp_path)


@pytest.mark.parametrize("behaviour,extra,ok", [
    ("garbled_echo", ["--ssid", "lab"], True),
    ("garbled_echo", ["--ssid", "cubecam-ap", "--mode", "ap"], True),
    ("garbled_echo", ["--ssid", "nojoin"], False),
])
def test_provisioning_a_fake_board_never_shows_the_password(tmp_path, behaviour, extra, ok):
    with FakeBoard(behaviour) as board:
        proc = provision_cli(board.path, tmp_path, "--boot-timeout", "5", "--join-timeout", "3", *extra)
        received = list(board.received_passwords)
    assert (proc.returncode == 0) == ok, proc.stderr[-3000:]
    assert received == [PASSWORD]  # it did travel, to the board only
    if behaviour == "garbled_echo":  # our own frames came back, and the debug log reported them
        assert "DEBUG cubecam.link" in proc.stderr and "bad Improv frame" in proc.stderr
    assert_absent({"stdout": proc.stdout, "stderr": proc.stderr,
                   **files_under(tmp_path, tmp_path / "wifi-password")})


def test_a_crash_during_provisioning_does_not_show_the_password(tmp_path, monkeypatch, capsys, caplog):
    def crash(self, ssid, password, timeout_s=0):
        raise RuntimeError("the link broke in an unexpected way")

    monkeypatch.setattr(NodeLink, "send_wifi", crash)
    (tmp_path / "pw").write_text(PASSWORD + "\n")
    caplog.set_level("DEBUG")
    with FakeBoard() as board:
        rc = main(["-vv", "provision", "--port", board.path, "--ssid", "lab", "--password-file", str(tmp_path / "pw"),
                   "--boot-timeout", "5"])
    out, err = capsys.readouterr()
    assert rc == 2 and "unexpected error" in caplog.text and "Traceback" in caplog.text
    assert_absent({"stdout": out, "stderr": err, "log": caplog.text})


def test_the_provisioning_request_does_not_show_the_password():
    req = ProvisionRequest(ssid="lab", password=PASSWORD, name="cam1")
    assert_absent({"repr": repr(req), "str": str(req)})
    assert req.password == PASSWORD


@pytest.fixture(scope="module")
def native_images(tmp_path_factory):
    if shutil.which("g++") is None or shutil.which("make") is None:
        pytest.skip("g++ and make are needed to build cubecam-native (tests/install.sh installs them)")
    build_native()
    return write_images(tmp_path_factory.mktemp("native-img"), 4, 320, 240)


@pytest.mark.parametrize("extra", [["--ssid", "lab"], ["--ssid", "cubecam-ap", "--mode", "ap"]], ids=["station", "ap"])
def test_provisioning_the_firmware_never_shows_the_password(tmp_path, native_images, extra):
    with NativeNode(native_images, fps=15, ssid=None, serial="pty") as node:
        proc = provision_cli(node.pty_path, tmp_path, "--boot-timeout", "10", "--join-timeout", "15", *extra)
        assert proc.returncode == 0, proc.stderr[-3000:]
        outputs = {"stdout": proc.stdout, "stderr": proc.stderr, **files_under(tmp_path, tmp_path / "wifi-password")}
        base_url = node.wait_until_listening(5)
        for path in ("status", "", "time"):
            with urllib.request.urlopen(base_url + path, timeout=5) as r:
                outputs[f"GET /{path}"] = r.read()
        assert json.loads(outputs["GET /status"])["name"] == "cam1"
        with NodeLink.open(node.pty_path) as console:
            for command in ("get password", "get", "status", "help"):
                outputs[f"console {command}"] = "\n".join(console.console(command))
        monitor = subprocess.run([sys.executable, "-m", "cubecam.cli", "monitor", node.pty_path, "--duration", "1"],
                                 capture_output=True, text=True, timeout=30)
        outputs.update({"monitor stdout": monitor.stdout, "monitor stderr": monitor.stderr})
        outputs.update({"node serial log": node.log_text(), "node stdout": "".join(node.stdout_lines)})
        stored = node.settings_path.read_bytes()
    assert PASSWORD.encode() in stored  # the node keeps it (in its flash) ...
    assert "(set)" in outputs["console get password"]
    assert_absent(outputs)  # ... and shows it nowhere
