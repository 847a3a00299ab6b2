"""Outputs in a process of their own: reachable as before, failures reported as one line before
the session, a dead output process never reaching the pipeline."""

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from foxglove_client import read_mcap
from sink_helpers import free_port, tracked
from vrpn_client import TrackerClient

from cubetrack.app.outputs import OutputSpec, close_sinks, start_outputs
from cubetrack.core.errors import ConfigError
from cubetrack.sink.base import Decoupled, OutputError, Outputs
from cubetrack.sink.process import OutputProcess


def spec(table: dict, tmp_path) -> OutputSpec:
    return OutputSpec(table, tmp_path, f"lab.toml: outputs ({table['type']})")


def test_outputs_run_in_a_child_process_and_serve_as_before(tmp_path, session_info):
    port = free_port()
    sinks = start_outputs([spec({"type": "mcap", "path": "s.mcap"}, tmp_path),
                           spec({"type": "vrpn", "address": f"127.0.0.1:{port}"}, tmp_path)])
    try:
        (remote,) = sinks
        assert isinstance(remote, OutputProcess) and f"127.0.0.1:{port}" in remote.where
        assert "s.mcap" in remote.where and remote.wants_views  # the MCAP file shows camera images
        child = remote._process
        assert child.is_alive() and child.pid != os.getpid()
        with Outputs(sinks) as outputs:
            outputs.open(session_info)
            client = TrackerClient(port, "robot_1")  # the server listens in the child
            try:
                for i in range(5):
                    outputs.pose(tracked("robot 1!", i))
                assert client.wait_for(lambda c: len(c.poses("robot_1")) == 5, timeout_s=20)
            finally:
                client.close()
        child.join(10)
        assert not child.is_alive()  # closing the session ends the output process
    finally:
        close_sinks(sinks)
    assert (tmp_path / "s.mcap").stat().st_size > 0  # written and closed by the child


def test_a_bad_output_fails_before_the_session_with_its_one_line_reason(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(OutputError) as err:
            start_outputs([spec({"type": "vrpn", "address": f"127.0.0.1:{port}"}, tmp_path)])
    assert str(port) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"^lab.toml: outputs \(zenoh\).mode: 'broker' is not one of 'peer'"):
        start_outputs([spec({"type": "zenoh", "mode": "broker"}, tmp_path)])


def test_an_output_process_that_dies_stops_without_reaching_the_pipeline(tmp_path, session_info, caplog):
    sinks = start_outputs([spec({"type": "vrpn", "address": f"127.0.0.1:{free_port()}"}, tmp_path)])
    remote = sinks[0]
    with Outputs(sinks) as outputs:
        outputs.open(session_info)
        os.kill(remote._process.pid, signal.SIGKILL)
        remote._process.join(10)
        decoupled = outputs.sinks[0]
        assert isinstance(decoupled, Decoupled)
        for i in range(200):  # never raises: the pipeline goes on
            outputs.pose(tracked("robot 1!", i))
        decoupled._thread.join(10)
        assert decoupled.failed == "the outputs' process has ended"
    assert "output outputs process failed" in caplog.text


def test_when_the_tracker_is_killed_the_output_process_ends_with_its_mcap_file_whole(tmp_path):
    """A tracker process (here a script) feeds 20 poses to an MCAP output in its output process,
    then is killed with SIGKILL: the output process ends by itself (cubetrack.core.lifetime) and
    closes the file first, so all 20 poses read back."""
    script = tmp_path / "tracker.py"
    script.write_text(textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from sink_helpers import tracked
        from cubetrack.app.outputs import OutputSpec, start_outputs
        from cubetrack.core.cameras import WorldConfig
        from cubetrack.core.layout import paper_cube_layout
        from cubetrack.sink.base import Outputs, SessionInfo

        if __name__ == "__main__":  # (the output process is spawned: it imports this file)
            (sink,) = start_outputs([OutputSpec({{"type": "mcap", "path": "s.mcap"}}, Path({str(tmp_path)!r}), "t")])
            outputs = Outputs([sink])
            outputs.open(SessionInfo(WorldConfig(), (), {{"robot": paper_cube_layout()}}))
            for i in range(20):
                outputs.pose(tracked("robot", i))
            time.sleep(1.0)  # handed over
            print(sink._process.pid, flush=True)
            time.sleep(120)
    """))
    tracker = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    child = int(tracker.stdout.readline())
    tracker.kill()
    tracker.wait()
    deadline = time.monotonic() + 20
    while Path(f"/proc/{child}").exists() and Path(f"/proc/{child}/stat").read_text().split(") ")[1][0] != "Z":
        assert time.monotonic() < deadline, "the output process outlived its tracker"
        time.sleep(0.1)
    _, messages = read_mcap(tmp_path / "s.mcap")
    assert len(messages["/robots/robot/pose"]) == 20


def test_items_cross_the_pipe_as_compact_tuples_and_come_back_equal():
    import dataclasses
    import math
    import pickle

    import numpy as np

    from cubetrack.core.records import CameraHealth, CameraView, Detection
    from cubetrack.io.output_wire import pack_output as pack
    from cubetrack.io.output_wire import unpack_output as unpack

    def same(a, b) -> bool:
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return a is not None and b is not None and np.array_equal(a, b) and np.shape(a) == np.shape(b)
        if isinstance(a, float) and math.isnan(a):
            return isinstance(b, float) and math.isnan(b)
        if isinstance(a, tuple):
            return type(b) is tuple and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
        if isinstance(a, dict):
            return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        if hasattr(a, "__slots__"):
            return type(a) is type(b) and all(same(getattr(a, f), getattr(b, f)) for f in a.__slots__)
        return a == b

    corners = np.array([[1.5, 2.0], [10.0, 2.5], [9.5, 11.0], [1.0, 10.0]])
    items = [("pose", tracked("robot 1!", 3)), ("pose", tracked("2nd", 4, velocity=False)),
             ("pose", dataclasses.replace(tracked("3rd", 5), smoothed=True, smooth_lag_s=0.05)),
             ("camera_view", CameraView("cam-a", 7, 1_700_000_000.25, b"\xff\xd8jpeg",
                                        (Detection(4, corners, 80.0, "DICT_4X4_50"), Detection(9, corners + 1, 81.0)),
                                        {"robot 1!": np.arange(40.0).reshape(20, 2)})),
             ("camera_health", CameraHealth("cam b", 1_700_000_001.0, True, 29.5, 100, 2, 1, 0, 0.01,
                                            transfer_latency_s=float("nan"), last_error="timeout"))]
    for kind, value in items:
        packed = pack(kind, value)
        assert "cubetrack" not in str(pickle.dumps(packed))  # plain values only: no record classes pickled
        again_kind, again = unpack(*pickle.loads(pickle.dumps(packed)))
        assert again_kind == kind and same(value, again), kind
    assert not same(items[0][1], unpack(*pack("pose", tracked("robot 1!", 4)))[1])  # the comparison can fail
