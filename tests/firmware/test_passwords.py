"""Passwords users really have (issue 12, item 6): commas, quotes, spaces at either end and
UTF-8, end to end -- `cubecam provision` reading them from a file, a pipe or the prompt, over a
real pty to the firmware core (cubecam-native) by Improv (station) and by the console (access
point), kept byte for byte in the node's settings record and shown nowhere. How the node then
hands them to the GS2200M (quoted AT+WPAPSK, or the derived key in AT+WPSK) is tested over the
real GS2200-WiFi library in firmware/test/hostlib (test_hostlib.py) and firmware/test/test_gs2200m.cpp."""

from __future__ import annotations

import io
import subprocess
import sys

import pytest

from cubecam.errors import ProvisionError
from cubecam.provision import ProvisionRequest, read_password
from tests.helpers.native import NativeNode

# A comma with a bare quote: no form of AT+WPAPSK carries it, the node sends the key.
COMMA_QUOTES = ' say "hi", then  go '
PASSWORDS = [COMMA_QUOTES, 'back\\slash, "q" ', "caf\u00e9, cr\u00e8me br\u00fbl\u00e9e"]


def provision(port: str, tmp_path, password: str, *extra: str, via: str = "file") -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "cubecam.cli", "-vv", "provision", "--port", port, "--name", "cam1",
           "--boot-timeout", "10", "--join-timeout", "15", *extra]
    stdin = None
    if via == "file":
        (tmp_path / "pw").write_text(password + "\n", encoding="utf-8")
        cmd += ["--password-file", str(tmp_path / "pw")]
    else:
        stdin = password + "\n"
    return subprocess.run(cmd, input=stdin, capture_output=True, text=True, encoding="utf-8", timeout=90,
                          cwd=tmp_path, check=False)


SET_PASSWORD = ("import sys; from cubecam.link import NodeLink\n"
                "with NodeLink.open(sys.argv[1]) as n: n.console('set password ' + sys.argv[2], secret=True)")


def stored_password(node: NativeNode) -> bytes:
    """The password field of the node's settings record (firmware/cubecam/src/core/settings.h)."""
    record = node.settings_path.read_bytes()
    field = record[6 + 33 + 33:6 + 33 + 33 + 64]
    return field.split(b"\0", 1)[0]


@pytest.mark.parametrize("password", PASSWORDS, ids=["comma-quotes-spaces", "backslash", "utf8"])
@pytest.mark.parametrize("mode,via", [("station", "file"), ("ap", "stdin")])
def test_provisioning_keeps_the_password_byte_for_byte_and_shows_it_nowhere(
        native_binary, jpeg_dir, tmp_path, password, mode, via):
    extra = ["--ssid", "lab"] if mode == "station" else ["--ssid", "cubecam-ap", "--mode", "ap"]
    with NativeNode(jpeg_dir, fps=15, ssid=None) as node:
        proc = provision(node.pty_path, tmp_path, password, *extra, via=via)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert stored_password(node) == password.encode("utf-8")
        outputs = {"stdout": proc.stdout, "stderr": proc.stderr, "serial log": node.log_text(),
                   "node stdout": "".join(node.stdout_lines)}
    for where, text in outputs.items():
        assert password.strip() not in text, f"the password shows in {where}"
        assert password.strip()[:10] not in text, f"part of the password shows in {where}"


def test_the_node_refuses_only_what_is_no_wpa2_passphrase(native_binary, jpeg_dir, tmp_path):
    with NativeNode(jpeg_dir, fps=15, ssid=None) as node:
        for bad, message in [("x" * 64, "8 to 63 bytes"), ("tab\there12", "control characters")]:
            link = subprocess.run(  # past the tool's own check: the console of the node itself
                [sys.executable, "-c", SET_PASSWORD, node.pty_path, bad], capture_output=True, text=True, timeout=30,
                check=False)
            assert link.returncode != 0 and "ERR 4 password must" in link.stderr and message in link.stderr
            assert bad not in link.stderr
        proc = provision(node.pty_path, tmp_path, COMMA_QUOTES, "--ssid", "lab,2")
        assert proc.returncode != 0 and "printable ASCII without commas" in proc.stderr, proc.stderr[-2000:]
        assert COMMA_QUOTES.strip() not in proc.stderr + node.log_text()


@pytest.mark.parametrize("password", ["tab\there12", "bell\x07ringer", "x" * 64, "short"])
def test_the_tool_says_what_a_wpa2_password_is(password):
    with pytest.raises(ProvisionError, match="8 to 63 bytes|control characters") as err:
        ProvisionRequest(ssid="lab", password=password).check()
    assert password not in str(err.value)


@pytest.mark.parametrize("password", PASSWORDS + ["\u00e9" * 31 + "x"])  # 63 bytes of UTF-8
def test_the_tool_takes_every_wpa2_passphrase(password):
    assert ProvisionRequest(ssid="lab", password=password).check().password == password


def test_the_password_reads_unchanged_from_a_file_a_pipe_and_the_prompt(tmp_path):
    (tmp_path / "pw").write_text(COMMA_QUOTES + "\r\nsecond line\n", encoding="utf-8")
    assert read_password(str(tmp_path / "pw"), None, None) == COMMA_QUOTES
    assert read_password(None, io.StringIO(COMMA_QUOTES + "\n"), None) == COMMA_QUOTES

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert read_password(None, Tty(), lambda prompt: COMMA_QUOTES) == COMMA_QUOTES
