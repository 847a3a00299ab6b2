"""A fake camera node on a real pty, speaking Improv serial v1 and the line console as the
firmware does (contracts §2), with switchable misbehaviour.

The board side is started first and the slave is made raw at once (a new pty echoes and
pyserial flushes input on open). Behaviours:

- ``normal``: answers everything; joining succeeds unless the SSID is in ``fail_ssids``;
- ``silent``: never sends a byte;
- ``garbage``: sends random bytes (no newline-delimited frames) and never answers;
- ``bad_checksum``: answers, but every frame's checksum is wrong;
- ``vanish_on_wifi``: the port disappears (master closed) when Wi-Fi settings arrive;
- ``no_join_answer``: accepts Wi-Fi settings, then never reports success or failure;
- ``garbled_echo``: answers normally, but first echoes what it receives with the byte before
  each chunk's final newline flipped (a terminal in echo mode on a noisy line: the host's own
  Improv frames come back with bad checksums, console lines come back as text).

``boot_delay_s`` keeps it silent for a while first (a booting board), then it prints a boot
banner. It also prints a log line every ``log_every_s`` to interleave with the answers.
"""

from __future__ import annotations

import os
import random
import select
import threading
import time
import tty

from cubecam import improv

URL_TEMPLATE = "http://192.168.1.{n}/"


class FakeBoard:
    def __init__(self, behaviour: str = "normal", name: str = "fake1", boot_delay_s: float = 0.0,
                 fail_ssids: tuple[str, ...] = ("nojoin",), join_delay_s: float = 0.2, log_every_s: float = 0.15):
        self.behaviour = behaviour
        self.boot_delay_s = boot_delay_s
        self.fail_ssids = fail_ssids
        self.join_delay_s = join_delay_s
        self.log_every_s = log_every_s
        self.settings = {"name": name, "ssid": "", "password": "", "mode": "station", "ip": "dhcp",
                         "port": "80", "jpeg_quality": "80", "fps": "15", "hdr": "auto"}
        self.edited = dict(self.settings)
        self.saved: dict | None = None
        self.commands: list[str] = []      # console lines received (password values masked)
        self.received_passwords: list[str] = []
        self.online = False
        self.boots = 0
        self._parser = improv.Parser()
        self._stop = threading.Event()
        self._pending: list[tuple[float, bytes]] = []
        self._rng = random.Random(4)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self._thread = threading.Thread(target=self._run, daemon=True, name="fakeboard")

    def __enter__(self) -> FakeBoard:
        self._booted_at = time.monotonic() + self.boot_delay_s
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    # --- output ---

    def _write(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except OSError:
            pass

    def _later(self, delay_s: float, data: bytes) -> None:
        self._pending.append((time.monotonic() + delay_s, data))

    def _frame(self, frame: bytes) -> bytes:
        if self.behaviour == "bad_checksum":
            frame = frame[:-1] + bytes(((frame[-1] + 1) & 0xFF,))
        return frame + b"\n"

    def _state(self) -> bytes:
        state = improv.State.PROVISIONED if self.online else improv.State.READY
        out = self._frame(improv.encode_current_state(state))
        if self.online:
            out += self._frame(improv.encode_rpc_result(improv.Command.GET_CURRENT_STATE, [self.url]))
        return out

    @property
    def url(self) -> str:
        ip = self.settings["ip"]
        if ip != "dhcp":
            return f"http://{ip.split('/')[0]}/"
        return URL_TEMPLATE.format(n=50)

    # --- the loop ---

    def _run(self) -> None:
        next_log = time.monotonic()
        banner_sent = False
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                ready, _, _ = select.select([self.master], [], [], 0.02)
            except (OSError, ValueError):
                return
            data = b""
            if ready:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    data = b""
            if self.behaviour == "silent":
                continue
            if self.behaviour == "garbage":
                junk = bytes(self._rng.randrange(256) for _ in range(64)).replace(b"\n", b"")
                self._write(junk)
                continue
            if now < self._booted_at:
                continue  # booting: input is lost, as on a board that is not up yet
            if self.behaviour == "garbled_echo" and len(data) >= 2:
                cut = len(data) - 2 if data.endswith(b"\n") else len(data) - 1
                self._write(data[:cut] + bytes((data[cut] ^ 0x01,)) + data[cut + 1:])
            if not banner_sent:
                self.boots += 1
                self._write(b"[I] boot: fake cubecam node\n")
                banner_sent = True
            for ev in self._parser.feed(data):
                if isinstance(ev, improv.Frame):
                    self._on_frame(ev)
                elif isinstance(ev, improv.Line):
                    self._on_line(ev.text)
                if self._stop.is_set():
                    return
            for item in [p for p in self._pending if p[0] <= now]:
                self._pending.remove(item)
                self._write(item[1])
            if self.log_every_s and now >= next_log:
                self._write(f"[I] cam: frame {int(now * 10) % 100000} captured\n".encode())
                next_log = now + self.log_every_s
            if getattr(self, "_reboot_at", None) and now >= self._reboot_at:
                self._reboot_at = None
                self.settings = dict(self.saved or self.settings)
                self.edited = dict(self.settings)
                self.online = bool(self.settings["ssid"]) and self.settings["ssid"] not in self.fail_ssids
                self._booted_at = now + 0.3
                banner_sent = False

    def _on_frame(self, frame: improv.Frame) -> None:
        if frame.type != improv.FrameType.RPC:
            return
        command, strings = improv.decode_rpc(frame)
        if command == improv.Command.GET_CURRENT_STATE:
            self._write(self._state())
        elif command == improv.Command.GET_DEVICE_INFO:
            self._write(self._frame(improv.encode_rpc_result(
                improv.Command.GET_DEVICE_INFO, ["cubecam", "0.0-fake", "Spresense", self.settings["name"]])))
        elif command == improv.Command.GET_WIFI_NETWORKS:
            for ssid, rssi, secured in (("lab", -48, "YES"), ("guest", -71, "NO")):
                networks = [ssid, str(rssi), secured]
                self._write(self._frame(improv.encode_rpc_result(improv.Command.GET_WIFI_NETWORKS, networks)))
            self._write(self._frame(improv.encode_rpc_result(improv.Command.GET_WIFI_NETWORKS, [])))
        elif command == improv.Command.WIFI_SETTINGS:
            ssid, password = strings
            self.received_passwords.append(password)
            if self.behaviour == "vanish_on_wifi":
                self._stop.set()
                os.close(self.master)
                os.close(self.slave)
                self.master = self.slave = -1
                return
            self._write(self._frame(improv.encode_current_state(improv.State.PROVISIONING)))
            if self.behaviour == "no_join_answer":
                return
            if ssid in self.fail_ssids:
                self._later(self.join_delay_s, self._frame(improv.encode_error_state(improv.Error.UNABLE_TO_CONNECT))
                            + self._frame(improv.encode_current_state(improv.State.READY)))
                return
            self.online = True
            for d in (self.settings, self.edited):
                d.update(ssid=ssid, password=password, mode="station")
            self.saved = dict(self.settings)
            self._later(self.join_delay_s, self._frame(improv.encode_current_state(improv.State.PROVISIONED))
                        + self._frame(improv.encode_rpc_result(improv.Command.WIFI_SETTINGS, [self.url])))
        else:
            self._write(self._frame(improv.encode_error_state(improv.Error.UNKNOWN_RPC)))

    def _on_line(self, text: str) -> None:
        text = text.strip()
        if not text:
            return
        word, _, rest = text.partition(" ")
        if word == "set" and rest.startswith("password "):
            self.received_passwords.append(rest.partition(" ")[2])
            self.commands.append("set password ***")
        else:
            self.commands.append(text)
        if word == "set":
            key, _, value = rest.partition(" ")
            error = self._check(key, value)
            if error:
                self._write(f"ERR {error}\n".encode())
                return
            self.edited[key] = value
            self._write(b"OK\n")
        elif word == "get":
            if rest == "password":
                self._write(f"password={'(set)' if self.edited['password'] else '(empty)'}\nOK\n".encode())
            elif rest in self.edited:
                self._write(f"{rest}={self.edited[rest]}\nOK\n".encode())
            else:
                self._write(b"ERR 3 unknown key; try help\n")
        elif word == "save":
            self.saved = dict(self.edited)
            self._write(b"[I] settings: saved\nOK\n")
        elif word == "reboot":
            self._write(b"OK\n")
            self._reboot_at = time.monotonic() + 0.1
        elif word in ("help", "status"):
            self._write(f"name={self.settings['name']}\nOK\n".encode())
        else:
            self._write(b"ERR 1 unknown command; try help\n")

    def _check(self, key: str, value: str) -> str | None:
        if key not in self.edited:
            return "3 unknown key; try help"
        if key == "fps" and value not in ("30", "15", "7.5"):
            return "4 fps must be 30, 15 or 7.5"
        if key == "jpeg_quality" and not (value.isdigit() and 1 <= int(value) <= 100):
            return "4 jpeg_quality must be 1-100"
        return None
