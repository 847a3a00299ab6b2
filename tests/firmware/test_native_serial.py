"""cubecam-native's serial port over a real pty: Improv Wi-Fi serial v1 and the line
console of contracts section 2, as a provisioning tool or a terminal sees them."""

from __future__ import annotations

import random
import subprocess
import time
import urllib.request

import pytest
import serial

from tests.helpers.native import NativeNode

SECRET = "correct-horse-42"


def improv_frame(ftype: int, data: bytes) -> bytes:
    body = b"IMPROV" + bytes([1, ftype, len(data)]) + data
    return body + bytes([sum(body) & 0xFF])


def rpc(command: int, *strings: str) -> bytes:
    payload = b"".join(bytes([len(s.encode())]) + s.encode() for s in strings)
    return improv_frame(0x03, bytes([command, len(payload)]) + payload) + b"\n"


class Port:
    """The host side of the node's serial port: splits Improv frames from text lines."""

    def __init__(self, path: str):
        self.ser = serial.Serial(path, 115200, timeout=0.05)
        self.raw = bytearray()
        self.frames: list[tuple[int, bytes]] = []
        self.lines: list[str] = []

    def send(self, data: bytes) -> None:
        self.ser.write(data)

    def pump(self) -> None:
        self.raw += self.ser.read(4096)
        while self.raw:
            if self.raw.startswith(b"IMPROV"):
                if len(self.raw) < 9 or len(self.raw) < 10 + self.raw[8]:
                    return
                n = self.raw[8]
                frame = bytes(self.raw[: 10 + n])
                assert frame[-1] == sum(frame[:-1]) & 0xFF, "bad checksum from the node"
                self.frames.append((frame[7], frame[9:-1]))
                del self.raw[: 10 + n]
                if self.raw.startswith(b"\n"):
                    del self.raw[:1]
                continue
            if b"IMPROV".startswith(bytes(self.raw[:6])) and b"\n" not in self.raw:
                return
            nl = self.raw.find(b"\n")
            if nl < 0:
                return
            self.lines.append(self.raw[:nl].decode("utf-8", "replace"))
            del self.raw[: nl + 1]

    def wait(self, predicate, timeout: float = 5.0):
        deadline = time.monotonic() + timeout
        while True:
            self.pump()
            result = predicate()
            if result:
                return result
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out; frames={self.frames} lines={self.lines}")

    def command(self, line: str, timeout: float = 5.0) -> list[str]:
        """Send one console line; return the answer lines up to OK / ERR (log lines left out)."""
        self.pump()  # earlier output is not part of this answer
        start = len(self.lines)
        self.send(line.encode() + b"\n")
        def is_end(line: str) -> bool:
            return line == "OK" or line.startswith("ERR ")

        self.wait(lambda: any(is_end(line) for line in self.lines[start:]), timeout)
        answer = [line for line in self.lines[start:] if not line.startswith("[")]
        end = next(i for i, line in enumerate(answer) if is_end(line))
        return answer[: end + 1]

    def rpc_frames(self, data: bytes, count: int, timeout: float = 5.0) -> list[tuple[int, bytes]]:
        self.pump()
        start = len(self.frames)
        self.send(data)
        self.wait(lambda: len(self.frames) - start >= count, timeout)
        return self.frames[start : start + count]

    def close(self) -> None:
        self.ser.close()


def strings_of(result: bytes) -> list[str]:
    out, pos = [], 2
    assert result[1] == len(result) - 2
    while pos < len(result):
        n = result[pos]
        out.append(result[pos + 1 : pos + 1 + n].decode())
        pos += 1 + n
    return out


@pytest.fixture
def fresh(native_binary, jpeg_dir):
    """An unprovisioned node (new settings) whose SSID 'bad-net' cannot be joined."""
    with NativeNode(jpeg_dir, ssid=None, fail_ssids=("bad-net",)) as n:
        port = Port(n.pty_path)
        yield n, port
        port.close()


def test_console_commands_answer_ok_or_err(fresh):
    node, port = fresh
    help_lines = port.command("help")
    assert help_lines[0] == "commands:" and help_lines[-1] == "OK"
    for cmd in ("get", "save", "factory-reset"):
        assert port.command("set name cam-7")[-1] == "OK"
        assert port.command(cmd)[-1] == "OK"
    values = port.command("get")
    assert values[:-1] == [
        "name=cubecam", "ssid=", "password=(empty)", "mode=station", "ip=dhcp", "port=80",
        "jpeg_quality=70", "fps=15", "hdr=auto",
    ]
    assert port.command("bogus") == ["ERR 1 unknown command; try help"]
    assert port.command("set fps 60")[-1].startswith("ERR 4 fps must be 30, 15 or 7.5")
    assert port.command("set password short")[-1].startswith("ERR 4 password must be 8 to 63")
    assert port.command("set ip 10.0.0.9/24,10.0.0.1") == ["OK"]
    assert port.command("get ip") == ["ip=10.0.0.9/24,10.0.0.1", "OK"]
    status = port.command("status")
    assert "link=unconfigured" in status and status[-1] == "OK"


def test_password_is_write_only(fresh):
    node, port = fresh
    assert port.command(f"set password {SECRET}") == ["OK"]
    assert port.command("save") == ["OK"]
    assert port.command("get password") == ["password=(set)", "OK"]
    port.command("get")
    port.command("status")
    port.command("reboot")
    port.wait(lambda: any("[I][config] password=(set)" in line for line in port.lines))
    assert SECRET not in "\n".join(port.lines)
    assert SECRET not in node.log_text()
    assert SECRET.encode() in node.settings_path.read_bytes()  # stored, only never shown


def test_improv_state_device_info_and_scan(fresh):
    node, port = fresh
    (ftype, data), = port.rpc_frames(rpc(0x02), 1)
    assert (ftype, data) == (0x01, b"\x02")  # READY (authorized)
    (ftype, data), = port.rpc_frames(rpc(0x03), 1)
    assert ftype == 0x04 and data[0] == 0x03
    assert strings_of(data) == ["cubecam", "0.1.0", "POSIX", "cubecam"]
    results = port.rpc_frames(rpc(0x04), 4)
    assert all(f == 0x04 and d[0] == 0x04 for f, d in results)
    assert strings_of(results[0][1]) == ["cubetrack-lab", "-41", "YES"]
    assert strings_of(results[1][1]) == ["cubetrack-guest", "-67", "NO"]
    assert results[3][1] == b"\x04\x00"  # end of the list


def test_improv_provisioning_joins_serves_and_persists(fresh, native_binary, jpeg_dir):
    node, port = fresh
    frames = port.rpc_frames(rpc(0x01, "cubetrack-lab", SECRET), 3)
    assert frames[0] == (0x01, b"\x03")  # PROVISIONING
    assert frames[1] == (0x01, b"\x04")  # PROVISIONED
    assert frames[2][0] == 0x04 and frames[2][1][0] == 0x01
    url = strings_of(frames[2][1])[0]
    assert url == node.wait_until_listening()
    with urllib.request.urlopen(url + "status", timeout=5) as r:
        assert r.status == 200
    (ftype, data), state_url = port.rpc_frames(rpc(0x02), 2)
    assert data == b"\x04" and strings_of(state_url[1]) == [url]
    assert SECRET not in "\n".join(port.lines)
    settings = node.settings_path.read_bytes()
    port.close()
    node.stop()
    # The saved credentials bring a restarted node online by themselves.
    again = NativeNode(jpeg_dir, ssid=None, settings_path=node.settings_path.parent.parent / "kept.bin")
    again.settings_path.write_bytes(settings)
    with again:
        assert again.wait_until_listening().startswith("http://127.0.0.1:")
    again.settings_path.unlink()


def test_improv_provisioning_failure_reports_unable_to_connect(fresh):
    node, port = fresh
    frames = port.rpc_frames(rpc(0x01, "bad-net", SECRET), 3)
    assert frames == [(0x01, b"\x03"), (0x02, b"\x03"), (0x01, b"\x02")]
    assert port.command("get ssid") == ["ssid=", "OK"]  # nothing was kept


def test_improv_rejects_what_the_module_cannot_take(fresh):
    node, port = fresh
    frames = port.rpc_frames(rpc(0x01, "x" * 33, SECRET), 1)
    assert frames == [(0x02, b"\x01")]
    port.wait(lambda: any(line == "[E][improv] ssid must be at most 32 bytes" for line in port.lines))
    frames = port.rpc_frames(rpc(0x01, "lab", "p" * 64), 1)
    assert frames == [(0x02, b"\x01")]


def test_improv_bad_checksum_and_unknown_rpc(fresh):
    node, port = fresh
    bad = bytearray(rpc(0x02))
    bad[-2] ^= 0xFF
    assert port.rpc_frames(bytes(bad), 1) == [(0x02, b"\x01")]
    assert port.rpc_frames(rpc(0x7F), 1) == [(0x02, b"\x02")]


def test_a_stalled_improv_frame_is_dropped_and_the_console_still_answers(fresh):
    node, port = fresh
    port.send(rpc(0x02)[:8])
    time.sleep(0.3)
    assert port.command("get fps") == ["fps=15", "OK"]
    rng = random.Random(5)
    port.send(bytes(rng.randrange(256) for _ in range(3000)))
    time.sleep(0.3)
    port.send(b"\n")
    time.sleep(0.2)
    assert port.command("get fps") == ["fps=15", "OK"]
    (ftype, data), = port.rpc_frames(rpc(0x02), 1)
    assert ftype == 0x01


def test_every_log_line_is_a_whole_tagged_line(fresh):
    node, port = fresh
    assert port.command("reboot") == ["OK"]
    port.wait(lambda: "[I][link] no network configured; waiting for Improv or the console" in port.lines)
    text = node.log_text()
    assert text.endswith("\n")  # so an Improv frame always starts a line
    lines = text.split("\n")[:-1]
    assert lines.count("OK") == 1  # the answer to reboot
    assert all(line.startswith("[") and "] " in line for line in lines if line != "OK"), lines


def test_console_settings_apply_after_save_and_reboot(native_binary, jpeg_dir):
    with NativeNode(jpeg_dir, fps=30) as node:
        port = Port(node.pty_path)
        try:
            assert port.command("set fps 7.5") == ["OK"]
            assert port.command("set name hall-cam") == ["OK"]
            assert port.command("save") == ["OK"]
            assert port.command("reboot") == ["OK"]
            url = node.wait_until_listening()
            with urllib.request.urlopen(url + "status", timeout=5) as r:
                import json

                st = json.load(r)
            assert st["name"] == "hall-cam"
            assert st["fps"]["configured"] == 7.5
            assert st["uptime_ms"] < 5000  # the device clock restarted with the boot
            port.wait(lambda: any(line == "[I][boot] cubecam 0.1.0 on POSIX" for line in port.lines))
        finally:
            port.close()


def test_stdio_serial_mode(native_binary, jpeg_dir, tmp_path):
    proc = subprocess.Popen(
        [str(native_binary), "--images", str(jpeg_dir), "--settings", str(tmp_path / "s.bin"),
         "--serial", "stdio", "--port", "0"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    try:
        proc.stdin.write(b"get fps\nset fps 30\nget fps\n")
        proc.stdin.flush()
        lines: list[bytes] = []
        deadline = time.monotonic() + 10
        while lines.count(b"OK") < 3:
            assert time.monotonic() < deadline, lines
            lines.append(proc.stdout.readline().rstrip(b"\n"))
        answers = [line for line in lines if not line.startswith(b"[")]
        assert answers == [b"fps=15", b"OK", b"OK", b"fps=30", b"OK"]
    finally:
        proc.terminate()
        proc.wait(5)
    assert proc.returncode == 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--images", "/nonexistent-cubecam"], b"cannot open image folder"),
        (["--images", "{jpegs}", "--set", "fps=12"], b"fps must be 30, 15 or 7.5"),
        (["--images", "{jpegs}", "--set", "password=short"], b"password must be 8 to 63"),
        (["--serial", "pty"], b"usage: cubecam-native"),
        (["--images", "{jpegs}", "--port", "http"], b"usage: cubecam-native"),
    ],
)
def test_command_line_errors_exit_2_with_one_line(native_binary, jpeg_dir, tmp_path, args, message):
    args = [a.replace("{jpegs}", str(jpeg_dir)) for a in args]
    result = subprocess.run([str(native_binary), "--settings", str(tmp_path / "s.bin"), *args],
                            capture_output=True, timeout=10)
    assert result.returncode == 2
    assert message in result.stderr
    assert b"=short" not in result.stderr  # a refused password is not shown either
