"""`cubecam provision` and `cubecam monitor` against a fake board on a real pty: the happy
paths, and misbehaving devices (garbage, bad checksums, silence, a vanished port, a node that
cannot join, a node that refuses a setting) — a clear one-line error and exit 1, never a hang
or a traceback."""

from __future__ import annotations

import io
import threading
import time
import tomllib

import pytest
from fakeboard import FakeBoard
from toolcheck import assert_one_line_error, run_cubecam

from cubecam import link
from cubecam.cli import main

PASSWORD = "correct-horse-battery"


@pytest.fixture
def password_file(tmp_path):
    f = tmp_path / "wifi.txt"
    f.write_text(PASSWORD + "\n")
    return f


def provision(capsys, board: FakeBoard, *extra: str, password_file=None, timeout="3") -> tuple[int, str, str]:
    args = ["provision", "--port", board.path, "--ssid", "lab", "--boot-timeout", timeout, "--join-timeout", timeout]
    if password_file is not None:
        args += ["--password-file", str(password_file)]
    rc = main(args + list(extra))
    out, err = capsys.readouterr()
    return rc, out, err


def test_station_provisioning_prints_name_and_url(capsys, password_file):
    with FakeBoard() as board:
        rc, out, err = provision(capsys, board, password_file=password_file)
    assert rc == 0, err
    assert out == "fake1 http://192.168.1.50/\n"
    assert board.received_passwords == [PASSWORD]
    assert board.saved["ssid"] == "lab"
    assert PASSWORD not in out + err


def test_settings_go_through_the_console_then_a_reboot(capsys, password_file):
    with FakeBoard() as board:
        rc, out, err = provision(capsys, board, "--name", "cam3", "--quality", "70", "--fps", "7.5",
                                 "--ip", "192.168.1.33/24,192.168.1.1", password_file=password_file)
    assert rc == 0, err
    assert board.commands == ["set name cam3", "set jpeg_quality 70", "set fps 7.5",
                              "set ip 192.168.1.33/24,192.168.1.1", "save", "reboot"]
    assert board.boots == 2
    assert out == "cam3 http://192.168.1.33/\n"


def test_access_point_mode_uses_the_console(capsys, password_file):
    with FakeBoard() as board:
        rc, out, err = provision(capsys, board, "--mode", "ap", password_file=password_file)
    assert rc == 0, err
    assert board.commands[:3] == ["set mode ap", "set ssid lab", "set password ***"]
    assert board.saved["mode"] == "ap" and board.received_passwords == [PASSWORD]
    assert PASSWORD not in out + err


def test_waits_for_a_booting_board(capsys, password_file):
    with FakeBoard(boot_delay_s=1.5) as board:
        t0 = time.monotonic()
        rc, out, err = provision(capsys, board, password_file=password_file)
    assert rc == 0, err
    assert time.monotonic() - t0 >= 1.5


def test_password_from_stdin(capsys, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO(PASSWORD + "\n"))
    with FakeBoard() as board:
        rc, out, err = provision(capsys, board)
    assert rc == 0, err
    assert board.received_passwords == [PASSWORD]


def test_password_from_a_prompt(capsys, monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr("sys.stdin", Tty())
    monkeypatch.setattr("getpass.getpass", lambda prompt: PASSWORD)
    with FakeBoard() as board:
        rc, _, err = provision(capsys, board)
    assert rc == 0, err
    assert board.received_passwords == [PASSWORD]


def test_open_network_and_scan(capsys):
    with FakeBoard() as board:
        rc, out, err = provision(capsys, board, "--open", "--scan")
    assert rc == 0, err
    assert out.splitlines()[:2] == ["lab\t-48 dBm\tsecured", "guest\t-71 dBm\topen"]
    assert board.received_passwords == [""]


def test_config_gets_the_camera(capsys, password_file, tmp_path):
    config = tmp_path / "tracker.toml"
    config.write_text('# my setup\n[world]\nmarker_size = 0.25\n\n[[robots]]\nname = "r"\nlayout = "cube.toml"\n')
    with FakeBoard() as board:
        rc, _, err = provision(capsys, board, "--name", "cam9", "--config", str(config), password_file=password_file)
    assert rc == 0, err
    text = config.read_text()
    assert text.startswith("# my setup\n")
    doc = tomllib.loads(text)
    assert doc["cameras"] == [{"name": "cam9", "url": "http://192.168.1.50/stream"}]
    assert doc["robots"][0]["name"] == "r"


@pytest.mark.parametrize("behaviour, extra, fragments", [
    ("normal", ("--ssid", "nojoin"), ("could not join 'nojoin'", "unable to connect")),
    ("normal", ("--fps", "12"), ("refused `set fps 12`", "ERR 4 fps must be 30, 15 or 7.5")),
    ("silent", (), ("no Improv answer in 2 s", "nothing was received")),
    ("garbage", (), ("no Improv answer in 2 s", "bytes were received")),
    ("bad_checksum", (), ("no Improv answer in 2 s", "bad checksum")),
    ("vanish_on_wifi", (), ("the port went away",)),
    ("no_join_answer", (), ("did not report joining 'lab' within 2 s",)),
])
def test_misbehaving_devices_give_one_line_errors(capsys, password_file, behaviour, extra, fragments):
    with FakeBoard(behaviour) as board:
        t0 = time.monotonic()
        rc, out, err = provision(capsys, board, *extra, password_file=password_file, timeout="2")
        elapsed = time.monotonic() - t0
    assert_one_line_error(rc, err, board.path, *fragments)
    assert elapsed < 6.0
    assert PASSWORD not in out + err


def test_misbehaving_device_through_the_real_command(password_file):
    with FakeBoard("garbage") as board:
        done = run_cubecam("provision", "--port", board.path, "--ssid", "lab", "--password-file", str(password_file),
                           "--boot-timeout", "2", timeout=20)
    assert_one_line_error(done.returncode, done.stderr, "no Improv answer in 2 s")


def test_unknown_serial_device():
    done = run_cubecam("provision", "--port", "/dev/cubecam-no-such-port", "--ssid", "lab", "--open")
    assert_one_line_error(done.returncode, done.stderr, "/dev/cubecam-no-such-port", "cannot open serial port")
    done = run_cubecam("monitor", "/dev/cubecam-no-such-port", "--duration", "1")
    assert_one_line_error(done.returncode, done.stderr, "cannot open serial port")


@pytest.mark.parametrize("args, fragment", [
    (("--password-file", "/nonexistent/pw"), "cannot read the password file"),
    (("--ip", "10.0.0.5/24,10.1.0.1", "--open"), "outside 10.0.0.0/24"),
    (("--ip", "static", "--open"), "use dhcp or a.b.c.d/prefix,gateway"),
    (("--quality", "0", "--open"), "JPEG quality must be 1..100"),
    (("--name", "bad name", "--open"), "name 'bad name'"),
], ids=["password-file", "gateway", "ip", "quality", "name"])
def test_bad_options_are_refused_before_touching_the_port(capsys, args, fragment):
    rc = main(["provision", "--port", "/dev/cubecam-no-such-port", "--ssid", "lab", *args])
    assert_one_line_error(rc, capsys.readouterr().err, fragment)


def test_empty_password_needs_open(capsys, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO("\n"))
    rc = main(["provision", "--port", "/dev/null", "--ssid", "lab"])
    assert_one_line_error(rc, capsys.readouterr().err, "--open")


def test_port_is_opened_with_dtr_and_rts_low():
    with FakeBoard("silent") as board:
        port = link.open_serial(board.path)
        try:
            assert port.dtr is False and port.rts is False and port.timeout == link.READ_SLICE_S
        finally:
            port.close()


def test_monitor_shows_log_lines(capsys):
    with FakeBoard() as board:
        rc = main(["monitor", board.path, "--duration", "0.8"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "[I] cam: frame" in out


def test_monitor_reports_a_vanished_port(capsys):
    with FakeBoard() as board:
        unplug = threading.Timer(0.5, board.close)
        unplug.start()
        rc = main(["monitor", board.path, "--duration", "5"])
        unplug.join()
    assert_one_line_error(rc, capsys.readouterr().err, "went away")


def test_a_port_held_by_another_program(capsys):
    with FakeBoard("silent") as board:
        holder = link.open_serial(board.path)
        try:
            rc = main(["provision", "--port", board.path, "--ssid", "lab", "--open"])
        finally:
            holder.close()
    assert_one_line_error(rc, capsys.readouterr().err, "cannot open serial port (in use)")
