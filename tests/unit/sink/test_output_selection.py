"""Choosing outputs: the config's [[outputs]] tables, the command-line flags, and their errors."""

import argparse
import dataclasses

import pytest
from sink_helpers import free_port

from cubetrack.app.outputs import OutputSpec, close_sinks, config_output_specs, merge_outputs, output_sinks
from cubetrack.cli.outputs import add_output_arguments, flag_output_specs
from cubetrack.core.errors import ConfigError
from cubetrack.core.layout import paper_cube_layout, write_layout
from cubetrack.io.config import read_tracker_config
from cubetrack.sink.foxglove import FoxgloveSink
from cubetrack.sink.output_params import OUTPUT_TYPES, Ros2OutputParams, output_params, parse_address
from cubetrack.sink.vrpn import VrpnParams, VrpnSink


@pytest.mark.parametrize("text,expected", [
    ("", ("127.0.0.1", 3883)), ("0.0.0.0:4000", ("0.0.0.0", 4000)), ("4000", ("127.0.0.1", 4000)),
    ("192.168.1.5", ("192.168.1.5", 3883)), ("[::1]:4000", ("::1", 4000)), ("localhost:0", ("localhost", 0)),
])
def test_addresses(text, expected):
    assert parse_address(text, ("127.0.0.1", 3883), "--vrpn") == expected


@pytest.mark.parametrize("text,message", [("host:port", "not ADDR:PORT"), ("1.2.3.4:70000", "out of range")])
def test_bad_addresses(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_address(text, ("127.0.0.1", 3883), "--vrpn")


def flags(*argv) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_output_arguments(parser)
    return parser.parse_args(list(argv))


def test_flags_become_output_tables():
    specs = flag_output_specs(flags("--vrpn", "--foxglove", "0.0.0.0:9000", "--ros2", "--ros-distro", "humble",
                                    "--ros-bridge", "--zenoh-connect", "tcp/10.0.0.1:7447", "--mcap", "x.mcap"))
    tables = {s.type: s.table for s in specs}
    assert tables["vrpn"] == {"type": "vrpn", "address": ""}
    assert tables["foxglove"]["address"] == "0.0.0.0:9000"
    assert tables["ros2"] == {"type": "ros2", "distro": "humble", "profile": "bridge", "connect": ["tcp/10.0.0.1:7447"]}
    assert tables["mcap"]["path"] == "x.mcap"
    assert flag_output_specs(flags()) == []


def test_config_outputs_resolve_paths_against_the_config_and_flags_replace_them(tmp_path):
    write_layout(paper_cube_layout(), tmp_path / "cube.toml")
    port = free_port()
    (tmp_path / "lab.toml").write_text(
        '[[robots]]\nname = "robot"\nlayout = "cube.toml"\n'
        f'[[outputs]]\ntype = "vrpn"\naddress = "127.0.0.1:{port}"\n'
        '[[outputs]]\ntype = "mcap"\npath = "out/session.mcap"\nimage_fps = 5\n')
    (tmp_path / "out").mkdir()
    config = read_tracker_config(tmp_path / "lab.toml")
    specs = config_output_specs(config)
    assert [s.type for s in specs] == ["vrpn", "mcap"] and specs[0].where.endswith("lab.toml: outputs[0]")
    sinks = output_sinks(specs)
    try:
        vrpn, mcap = sinks
        assert isinstance(vrpn, VrpnSink) and vrpn.port == port
        assert isinstance(mcap, FoxgloveSink) and mcap.path == tmp_path / "out" / "session.mcap"
        assert vrpn.view_interval_s == 0 and mcap.view_interval_s == 0.2  # image_fps = 5
    finally:
        close_sinks(sinks)
        close_sinks(sinks)  # closing twice is harmless (a session closes them first)
    other = free_port()
    merged = merge_outputs(specs, flag_output_specs(flags("--vrpn", str(other))))
    assert [(s.type, s.table.get("address")) for s in merged] == [("mcap", None), ("vrpn", str(other))]


@pytest.mark.parametrize("table,message", [
    ({"type": "pigeon"}, "type must be one of zenoh, ros2, vrpn, foxglove, mcap"),
    ({"type": "vrpn", "adress": "x"}, "unknown key"),
    ({"type": "vrpn", "address": "host:port"}, "not ADDR:PORT"),
    ({"type": "mcap"}, "needs path"),
    ({"type": "ros2", "distro": "noetic"}, "'noetic' is not one of 'humble', 'iron', 'jazzy', 'kilted', 'rolling'"),
    ({"type": "ros2", "domain_id": 300}, "domain_id must be 0..232"),
    ({"type": "zenoh", "connect": "127.0.0.1:7447"}, "Zenoh locators"),
    ({"type": "zenoh", "mode": "broker"}, "'broker' is not one of 'peer', 'client', 'router'"),
    ({"type": "zenoh", "zenoh_config": "missing.json5"}, "not found"),
    ({"type": "mcap", "path": "s.mcap", "image_fps": -1}, "image_fps must be a non-negative number"),
    ({"type": "foxglove", "image_fps": "fast"}, "expected a number"),
])
def test_bad_output_tables_are_one_line_errors(tmp_path, table, message):
    with pytest.raises(ConfigError, match=message) as err:
        output_sinks([OutputSpec(table, tmp_path, "lab.toml: outputs[0]")])
    assert str(err.value).startswith("lab.toml: outputs[0]") and "\n" not in str(err.value)


def test_every_output_table_reads_into_its_params_class_with_the_documented_defaults():
    """[[outputs]] is a params section like the others: each type's table maps 1:1 onto a params
    dataclass whose fields carry a doc (shown by cubetrack defaults); a key left out keeps its default."""
    for kind, cls in OUTPUT_TYPES.items():
        params = output_params({"type": kind}, "t")
        assert params == cls() and all(f.metadata.get("doc") for f in dataclasses.fields(cls))
    ros = output_params({"type": "ros2", "distro": "humble", "domain_id": 7, "connect": "tcp/10.0.0.1:7447"}, "t")
    assert ros == Ros2OutputParams(connect=("tcp/10.0.0.1:7447",), distro=ros.distro, domain_id=7)
    assert ros.distro.value == "humble"


def test_outputs_started_before_a_failure_are_closed_again(tmp_path):
    port = free_port()
    with pytest.raises(ConfigError):
        output_sinks([OutputSpec({"type": "vrpn", "address": str(port)}, tmp_path, "a"),
                      OutputSpec({"type": "mcap"}, tmp_path, "b")])
    again = VrpnSink(VrpnParams(port=port))  # the first server was closed: its port is free again
    again.close()


def test_a_foxglove_server_and_an_mcap_file_alike_share_one_sink(tmp_path):
    port = free_port()
    both = [OutputSpec({"type": "foxglove", "address": f"127.0.0.1:{port}"}, tmp_path, "--foxglove"),
            OutputSpec({"type": "vrpn", "address": f"127.0.0.1:{free_port()}"}, tmp_path, "--vrpn"),
            OutputSpec({"type": "mcap", "path": "s.mcap"}, tmp_path, "--mcap")]
    sinks = output_sinks(both)
    try:
        vrpn, foxglove = sinks  # one context builds each message once for the server and the file
        assert isinstance(vrpn, VrpnSink) and isinstance(foxglove, FoxgloveSink)
        assert foxglove.port == port and foxglove.path == tmp_path / "s.mcap" and foxglove.in_line
        assert f"ws://127.0.0.1:{port}" in foxglove.where and "s.mcap" in foxglove.where
    finally:
        close_sinks(sinks)
    (tmp_path / "s.mcap").unlink()
    # fresh ports: the closed server's port may not be free again at once
    both = [OutputSpec({"type": "foxglove", "address": f"127.0.0.1:{free_port()}"}, tmp_path, "--foxglove"),
            OutputSpec({"type": "vrpn", "address": f"127.0.0.1:{free_port()}"}, tmp_path, "--vrpn"),
            OutputSpec({"type": "mcap", "path": "s.mcap", "image_fps": 0}, tmp_path, "--mcap")]  # every image
    sinks = output_sinks(both)
    try:
        assert [type(s) for s in sinks] == [FoxgloveSink, VrpnSink, FoxgloveSink]  # apart: they differ
        assert sinks[0].view_interval_s == 0.1 and sinks[2].view_interval_s == 0
    finally:
        close_sinks(sinks)
