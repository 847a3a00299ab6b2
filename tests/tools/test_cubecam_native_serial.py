"""`cubecam provision`, `list` and `monitor` against the real firmware core: ``cubecam-native``
(the node built for the host) with its serial port on a pty. Skipped when the firmware's test
helper is not there."""

from __future__ import annotations

import json
import sys
import urllib.request
from pathlib import Path

import pytest
from toolcheck import assert_one_line_error

from cubecam.boards import query_name
from cubecam.cli import main
from cubecam.testdata import write_images

REPO = Path(__file__).resolve().parents[2]
if not (REPO / "tests" / "helpers" / "native.py").exists():  # fail, never skip: the firmware half would go unseen
    pytest.fail("tests/helpers/native.py is missing: the native firmware's serial tests cannot run", pytrace=False)
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
from tests.helpers.native import NativeNode, build_native  # noqa: E402

PASSWORD = "native-secret-1"


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    build_native()
    return write_images(tmp_path_factory.mktemp("native-img"), 6, 640, 480)


@pytest.fixture
def password_file(tmp_path) -> Path:
    f = tmp_path / "pw"
    f.write_text(PASSWORD + "\n")
    return f


@pytest.fixture
def fresh_node(images):
    """An unprovisioned node (no SSID) with its console on a pty; joining "nojoin" fails."""
    with NativeNode(images, fps=15, ssid=None, serial="pty", fail_ssids=("nojoin",)) as node:
        yield node


def status(url: str) -> dict:
    with urllib.request.urlopen(url + "status", timeout=5) as r:
        return json.loads(r.read())


def provision(capsys, node, *extra: str) -> tuple[int, str, str]:
    rc = main(["provision", "--port", node.pty_path, "--ssid", "lab", "--boot-timeout", "10",
               "--join-timeout", "15", *extra])
    out, err = capsys.readouterr()
    return rc, out, err


def test_station_provisioning_brings_the_node_online(capsys, fresh_node, password_file):
    rc, out, err = provision(capsys, fresh_node, "--password-file", str(password_file))
    assert rc == 0, err + fresh_node.log_text()[-2000:]
    name, url = out.split()
    assert url.startswith("http://127.0.0.1:") and url.endswith("/")
    assert status(url)["name"] == name
    assert PASSWORD not in out + err


def test_settings_are_applied_after_the_reboot(capsys, fresh_node, password_file, tmp_path):
    config = tmp_path / "tracker.toml"
    rc, out, err = provision(capsys, fresh_node, "--password-file", str(password_file), "--name", "bench-cam",
                             "--fps", "7.5", "--quality", "60", "--config", str(config))
    assert rc == 0, err + fresh_node.log_text()[-2000:]
    name, url = out.split()
    doc = status(url)
    assert name == doc["name"] == "bench-cam"
    assert doc["fps"]["configured"] == 7.5 and doc["jpeg_quality"] == 60
    assert f'url = "{url}stream"' in config.read_text()


def test_a_network_the_node_cannot_join(capsys, fresh_node, password_file):
    rc, out, err = provision(capsys, fresh_node, "--password-file", str(password_file), "--ssid", "nojoin")
    assert_one_line_error(rc, err, "could not join 'nojoin'")


def test_the_node_refuses_a_bad_setting(capsys, fresh_node, password_file):
    rc, out, err = provision(capsys, fresh_node, "--password-file", str(password_file), "--fps", "12")
    assert_one_line_error(rc, err, "refused `set fps 12`", "ERR 4")


def test_scan_lists_networks(capsys, fresh_node):
    rc, out, err = provision(capsys, fresh_node, "--open", "--scan")
    assert rc == 0, err
    networks = [line for line in out.splitlines() if "\t" in line]
    assert networks and all(line.split("\t")[1].endswith(" dBm") for line in networks)


def test_list_reads_the_node_name(fresh_node):
    assert query_name(fresh_node.pty_path, 5.0)


def test_monitor_shows_the_node_log(capsys, fresh_node):
    assert main(["monitor", fresh_node.pty_path, "--duration", "1"]) == 0
