"""The `cubecam` command line: help texts, `emulate` start-up output and errors, and `list`
(`flash` is in test_cubecam_flash.py)."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fakeboard import FakeBoard
from toolcheck import CUBECAM, REPO, assert_one_line_error, run_cubecam

from cubecam import boards
from cubecam.cli import COMMANDS, main
from cubecam.testdata import CameraSpec, write_recording


def test_top_level_help_lists_every_command():
    done = run_cubecam("--help")
    assert done.returncode == 0
    for name in COMMANDS:
        assert name in done.stdout


def test_console_script_is_installed():
    script = Path(sys.executable).parent / "cubecam"
    assert script.exists(), "pip install -e . declares the cubecam console script"
    done = subprocess.run([str(script), "--version"], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0 and done.stdout.startswith("cubecam ")


@pytest.mark.parametrize("command, options", [
    ("emulate", ["--recording", "--images", "--port", "--addresses", "--loop", "--latency", "--jitter", "--drop-rate",
                 "--bandwidth", "--disconnect-every", "--stall-after", "--corrupt-every"]),
    ("provision", ["--port", "--ssid", "--password-file", "--name", "--quality", "--fps", "--mode", "--ip",
                   "--config"]),
    ("monitor", ["DEV", "--duration"]),
    ("list", ["--no-names"]),
    ("flash", ["--port", "--all", "--builder", "--dry-run", "--burn-bootloader", "--sketch", "--project", "--ssid",
               "--password-file"]),
])
def test_every_command_documents_its_options(capsys, command, options):
    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    for option in options:
        assert option in out, (command, option)


# --- emulate ---


@pytest.fixture
def rec(tmp_path) -> Path:
    return write_recording(tmp_path / "rec", [CameraSpec("cam1", corrupt_files=1), CameraSpec("cam2")], frames=10)


def test_emulate_prints_each_camera_and_the_skipped_count(rec):
    proc = subprocess.Popen([*CUBECAM, "emulate", "--recording", str(rec), "--port", "0", "--duration", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    try:
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    lines = out.splitlines()
    assert [line.split()[0] for line in lines] == ["cam1", "cam2"]
    for line in lines:
        url = line.split()[1]
        assert url.startswith("http://127.0.0.1:") and url.endswith("/stream")
    assert "1 skipped (1 corrupt frame file)" in err


def test_emulate_serves_until_the_end_with_exit_at_end(rec):
    t0 = time.monotonic()
    done = run_cubecam("emulate", "--recording", str(rec), "--port", "0", "--exit-at-end")
    assert done.returncode == 0, done.stderr
    assert 0.8 < time.monotonic() - t0 < 15


def test_emulate_missing_recording(tmp_path):
    done = run_cubecam("emulate", "--recording", str(tmp_path / "nope"))
    assert_one_line_error(done.returncode, done.stderr, "nope", "recording folder not found")


def test_emulate_port_in_use(rec):
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        done = run_cubecam("emulate", "--recording", str(rec), "--port", str(port), "--duration", "1")
    assert_one_line_error(done.returncode, done.stderr, f"127.0.0.1:{port} is in use")


def test_emulate_bad_fault_option(rec):
    done = run_cubecam("emulate", "--recording", str(rec), "--drop-rate", "2")
    assert_one_line_error(done.returncode, done.stderr, "drop rate")


# --- list ---


def test_list_without_boards(monkeypatch, capsys):
    monkeypatch.setattr(boards, "attached_boards", lambda: [])
    assert main(["list"]) == 0
    assert "no boards attached" in capsys.readouterr().err


def test_list_shows_boards_with_their_names(monkeypatch, capsys):
    with FakeBoard(name="cam4") as board:
        monkeypatch.setattr(boards, "attached_boards",
                            lambda: [boards.Board(board.path, "0001", "CP2102N USB to UART Bridge Controller")])
        assert main(["list", "--timeout", "2"]) == 0
    out = capsys.readouterr().out
    assert out.split("\t")[:3] == [board.path, "cam4", "0001"]


def test_attached_boards_filters_by_usb_id(monkeypatch):
    from serial.tools import list_ports_common

    def port(device, vid, pid):
        p = list_ports_common.ListPortInfo(device)
        p.vid, p.pid, p.serial_number = vid, pid, "sn-" + device[-1]
        return p

    monkeypatch.setattr("serial.tools.list_ports.comports",
                        lambda: [port("/dev/ttyUSB1", 0x10C4, 0xEA60), port("/dev/ttyACM0", 0x2341, 0x0043),
                                 port("/dev/ttyUSB0", 0x10C4, 0xEA60)])
    assert [b.device for b in boards.attached_boards()] == ["/dev/ttyUSB0", "/dev/ttyUSB1"]
