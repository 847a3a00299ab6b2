"""The `cubecam` command line: help texts, `emulate` start-up output and errors, `list`,
and `flash` (dry-run command lines, missing PlatformIO, missing Spresense platform)."""

from __future__ import annotations

import shlex
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cubecam import boards
from cubecam.cli import COMMANDS, main
from cubecam.testdata import CameraSpec, write_recording
from fakeboard import FakeBoard
from toolcheck import CUBECAM, REPO, assert_one_line_error, run_cubecam

PIO = shutil.which("pio") or str(Path(sys.executable).parent / "pio")


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
    ("provision", ["--port", "--ssid", "--password-file", "--name", "--quality", "--fps", "--mode", "--ip", "--config"]),
    ("monitor", ["DEV", "--duration"]),
    ("list", ["--no-names"]),
    ("flash", ["--port", "--all", "--dry-run", "--project", "--ssid", "--password-file"]),
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


# --- flash ---


def test_flash_dry_run_prints_the_exact_commands(capsys, tmp_path):
    project = tmp_path / "fw"
    rc = main(["flash", "--port", "/dev/ttyUSB0", "--dry-run", "--project", str(project), "--pio", PIO,
               "--ssid", "lab", "--password-file", "/home/me/wifi.txt", "--name", "cam1", "--fps", "7.5"])
    assert rc == 0
    lines = capsys.readouterr().out.splitlines()
    assert [shlex.split(line) for line in lines] == [
        [PIO, "run", "-d", str(project), "-e", "spresense"],
        [PIO, "run", "-d", str(project), "-e", "spresense", "-t", "upload", "--upload-port", "/dev/ttyUSB0"],
        ["cubecam", "provision", "--port", "/dev/ttyUSB0", "--ssid", "lab", "--password-file", "/home/me/wifi.txt",
         "--name", "cam1", "--fps", "7.5"],
    ]


def test_flash_dry_run_all_boards_without_provisioning(capsys, monkeypatch):
    monkeypatch.setattr(boards, "attached_boards", lambda: [boards.Board("/dev/ttyUSB0", "a", ""),
                                                            boards.Board("/dev/ttyUSB1", "b", "")])
    assert main(["flash", "--all", "--dry-run", "--pio", PIO, "--project", "/fw"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"{PIO} run -d /fw -e spresense",
                     f"{PIO} run -d /fw -e spresense -t upload --upload-port /dev/ttyUSB0",
                     f"{PIO} run -d /fw -e spresense -t upload --upload-port /dev/ttyUSB1"]


def test_flash_dry_run_never_shows_a_password(capsys, monkeypatch):
    assert main(["flash", "--port", "/dev/ttyUSB0", "--dry-run", "--ssid", "lab"]) == 0
    out = capsys.readouterr().out
    assert "password from stdin or a prompt" in out


def test_flash_all_without_boards(monkeypatch, capsys):
    monkeypatch.setattr(boards, "attached_boards", lambda: [])
    rc = main(["flash", "--all", "--dry-run"])
    assert_one_line_error(rc, capsys.readouterr().err, "no boards attached")


def test_flash_without_platformio(tmp_path, capsys):
    rc = main(["flash", "--port", "/dev/ttyUSB0", "--pio", str(tmp_path / "no-pio")])
    assert_one_line_error(rc, capsys.readouterr().err, "PlatformIO (pio) not found", "pip install platformio")


@pytest.mark.skipif(not Path(PIO).exists(), reason="PlatformIO is not installed in this environment")
def test_flash_without_the_spresense_platform(tmp_path):
    project = tmp_path / "fw"
    project.mkdir()
    (project / "platformio.ini").write_text(
        "[env:spresense]\nplatform = https://github.com/maxgerhardt/platform-sonyspresense.git\n"
        "board = spresense\nframework = arduino\n")
    done = run_cubecam("flash", "--port", "/dev/ttyUSB0", "--project", str(project), "--pio", PIO, timeout=90,
                       env={"PLATFORMIO_CORE_DIR": str(tmp_path / "pio-core"),
                            "PLATFORMIO_SETTING_ENABLE_TELEMETRY": "No",
                            "PLATFORMIO_SETTING_CHECK_PLATFORMIO_INTERVAL": "9999"})
    assert_one_line_error(done.returncode, done.stderr, "Spresense platform for PlatformIO is not installed",
                          "pio pkg install")


@pytest.mark.skipif(not Path(PIO).exists(), reason="PlatformIO is not installed in this environment")
def test_flash_without_a_project(tmp_path, capsys):
    rc = main(["flash", "--port", "/dev/ttyUSB0", "--project", str(tmp_path), "--pio", PIO])
    assert_one_line_error(rc, capsys.readouterr().err, "platformio.ini: missing")


@pytest.mark.skipif(not Path(PIO).exists() or not (REPO / "platformio.ini").exists(),
                    reason="needs PlatformIO and the repository's platformio.ini")
def test_flash_of_the_repository_project_without_the_platform(tmp_path):
    done = run_cubecam("flash", "--port", "/dev/ttyUSB0", "--pio", PIO, timeout=90,
                       env={"PLATFORMIO_CORE_DIR": str(tmp_path / "pio-core"),
                            "PLATFORMIO_SETTING_ENABLE_TELEMETRY": "No"})
    assert_one_line_error(done.returncode, done.stderr, "platform-sonyspresense", str(REPO / "platformio.ini"))
