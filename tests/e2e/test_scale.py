"""Workers and a fusion over real loopback Zenoh, end to end: a short simulated session served
over HTTP by the camera emulator (a child process), two `cubetrack worker` processes each reading
half of the cameras, one `cubetrack fuse` process -> poses that match the offline replay of the
same recording pose for pose (on the live clock), and a fusion that says which cameras it heard.
Two automatic workers share the cameras; one is SIGKILLed and the other takes its cameras over."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from cubetrack.app.demo import write_live_config
from cubetrack.app.emulated import EmulatedCameras
from cubetrack.app.worker import BUS_LEASE_MS
from cubetrack.evaluate.metrics import evaluate
from cubetrack.io.config import read_tracker_config
from cubetrack.io.trajectory import Trajectory, read_tum
from tests.helpers.scene import simulated_scene

pytestmark = pytest.mark.slow

DURATION_S = 6.0
RUN_S = 14.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def kill_leftovers(procs: list[subprocess.Popen]) -> None:
    """Kill what a test left running (after a failure)."""
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()


def cubetrack(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cubetrack.cli.main", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return simulated_scene(tmp_path_factory.mktemp("scale"), DURATION_S, seed=11, calibration_frames=60)


@pytest.fixture(scope="module")
def scaled_run(scene):
    """The emulator serves the recording in a loop (the processes take seconds to start on a
    loaded machine); the fusion starts after the workers (any order works)."""
    work, rec = scene
    port = free_port()
    with EmulatedCameras(rec, ("--loop",)) as emu:
        config = write_live_config(rec / "config.toml", emu.urls, work / "live_config.toml")
        cameras = [c.name for c in read_tracker_config(config).cameras]
        halves = [cameras[: len(cameras) // 2], cameras[len(cameras) // 2:]]
        common = ["--config", str(config), "--extrinsics", str(work / "extrinsics.toml"),
                  "--duration", str(RUN_S), "--status-every", "1"]
        workers = [cubetrack("worker", *common, "--cameras", ",".join(half),
                             "--bus-connect", f"tcp/127.0.0.1:{port}") for half in halves]
        fuse = cubetrack("fuse", *common, "--out", str(work / "fused"), "--bus-listen", f"tcp/127.0.0.1:{port}")
        outs = [p.communicate(timeout=RUN_S + 60) for p in (*workers, fuse)]
        codes = [p.returncode for p in (*workers, fuse)]
        shift_s, period_s = emu.clock_shift_s, emu.period_s
    assert codes == [0, 0, 0], outs
    return {"out": work / "fused", "cameras": cameras, "shift_s": shift_s, "period_s": period_s,
            "workers": outs[:2], "fuse": outs[2]}


def test_fused_poses_match_the_offline_replay(scene, scaled_run):
    work, rec = scene
    truth = read_tum(rec / "ground_truth.tum")
    offline = read_tum(work / "offline" / "robot.tum")
    fused = read_tum(scaled_run["out"] / "robot.tum")
    # the live clock: recorded + shift, plus a period per loop of the replay
    start_s, period_s = float(truth.times_s[0]), scaled_run["period_s"]
    loops = np.floor((fused.times_s - scaled_run["shift_s"] - start_s) / period_s)
    t_rec = fused.times_s - scaled_run["shift_s"] - loops * period_s
    score_fused = evaluate(Trajectory(t_rec, fused.positions_m, fused.quats_xyzw), truth)
    score_offline = evaluate(offline, truth)
    assert score_fused.position_rmse_m < score_offline.position_rmse_m + 0.003
    assert score_fused.detection_ratio >= 0.8
    # pose for pose where both output one for the same frame (capture times within 1 ms: the live
    # session's own clock sync against the recorded one). They differ a little because the sets of
    # sightings differ: the fusion searches whole frames (no region detection across processes), live
    # frames can be dropped, and the replay sees more late sightings (they fold in without a pose)
    t_off = offline.times_s
    i = np.searchsorted(t_off, t_rec).clip(1, len(t_off) - 1)
    i = np.where(np.abs(t_off[i - 1] - t_rec) < np.abs(t_off[i] - t_rec), i - 1, i)
    same = (np.abs(t_off[i] - t_rec) < 0.001) & (t_rec > start_s + 1.0)  # not a loop's first second
    diff_mm = np.linalg.norm(fused.positions_m[same] - offline.positions_m[i[same]], axis=1) * 1000
    median_mm, p90_mm, max_mm = np.percentile(diff_mm, [50, 90, 100])
    print(f"fused {score_fused.position_rmse_m * 100:.2f} cm vs offline {score_offline.position_rmse_m * 100:.2f} cm; "
          f"{same.sum()} of {len(t_rec)} poses matched, position difference median {median_mm:.3f} mm, "
          f"90% {p90_mm:.3f} mm, max {max_mm:.3f} mm")
    assert same.sum() >= 0.25 * len(t_rec)
    # a pose now and then differs more (a frame one side dropped changes that step's sightings: seen
    # once in ~10 runs, one pose of 101 at 20 mm), never many
    assert median_mm < 0.5 and p90_mm < 5.0 and np.mean(diff_mm > 15.0) <= 0.02 and max_mm < 50.0
    lines = [json.loads(line) for line in (scaled_run["out"] / "robot.jsonl").read_text().splitlines()]
    assert {c for line in lines for c in line["cameras"]} == set(scaled_run["cameras"])


def test_the_fusion_says_which_cameras_it_heard(scaled_run):
    stdout, stderr = scaled_run["fuse"]
    for camera in scaled_run["cameras"]:
        assert f"{camera} (" in stdout
    status = [line for line in stderr.splitlines() if line.startswith("fuse: ") and "hearing" in line]
    assert status and all(c in status[-2] for c in scaled_run["cameras"]), stderr
    assert any(" 2 worker(s), hearing" in line for line in status), stderr  # their liveliness tokens
    for stdout, _ in scaled_run["workers"]:
        assert "published" in stdout


def test_a_worker_with_an_unknown_camera_is_one_clear_line(scene, tmp_path):
    work, rec = scene
    p = cubetrack("worker", "--config", str(rec / "config.toml"), "--extrinsics", str(work / "extrinsics.toml"),
                  "--cameras", "nosuch", "--duration", "1")
    _, stderr = p.communicate(timeout=60)
    assert p.returncode != 0 and "no camera nosuch" in stderr and len(stderr.strip().splitlines()) == 1


def test_the_fusion_counts_and_skips_what_is_not_a_sighting(scene, tmp_path):
    """A hostile or broken peer on the sighting keys: junk, a truncated message and a camera
    the config does not know are refused and counted; the fusion goes on."""
    from cubetrack.app.config import load_config
    from cubetrack.app.fusion_service import run_fusion
    from cubetrack.app.worker import fuse_endpoints, worker_endpoints
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.sighting_wire import SightingMessage, encode_sighting
    from cubetrack.io.worker_bus import sighting_key
    from cubetrack.sink.zenoh_session import open_session

    work, rec = scene
    config, _ = load_config(rec / "config.toml")
    port, stop, lines, result = free_port(), threading.Event(), [], []
    fusion = threading.Thread(target=lambda: result.append(run_fusion(
        config, read_extrinsics(work / "extrinsics.toml"), tmp_path / "out",
        fuse_endpoints(listen=(f"tcp/127.0.0.1:{port}",)), stop=stop, status=lines.append, status_every_s=0.2)))
    fusion.start()
    peer = open_session(worker_endpoints(connect=(f"tcp/127.0.0.1:{port}",)), "test")
    good = encode_sighting(SightingMessage("nosuch", 1, 0.0, 1.0, 1.0, "full frame", ()))
    try:
        deadline = time.monotonic() + 20
        while not any("refused" in line for line in lines) and time.monotonic() < deadline:
            for data in (b"GET / HTTP/1.0", good[:-1], good):  # until the fusion is there
                peer.put(sighting_key("cam1"), data)
            time.sleep(0.2)
        time.sleep(0.5)
    finally:
        stop.set()
        fusion.join(30)
        peer.close()
    assert result and result[0].bad_messages >= 3
    assert sum(result[0].heard.values()) == 0 and not result[0].interrupted


class Bus:
    """The test's own Zenoh peer on the sighting bus: when each camera's sightings arrive and
    who claims each camera (the liveliness tokens the workers hold)."""

    def __init__(self, port: int, hub: bool = False):
        """``hub``: listen on ``port`` (the workers' default peer) instead of connecting there."""
        from cubetrack.app.worker import fuse_endpoints, worker_endpoints
        from cubetrack.io.sighting_wire import decode_messages
        from cubetrack.io.worker_bus import CLAIMS_KEY, SHARD_SIGHTINGS_KEY, SIGHTINGS_KEY, ClaimBoard
        from cubetrack.sink.zenoh_session import open_session

        self.received: dict[str, list[float]] = {}  # camera -> time.monotonic() each sighting came here
        self.stamped: dict[str, list[float]] = {}  # camera -> the frame's arrival at its worker (Unix s)
        self.board = ClaimBoard()
        locator = (f"tcp/127.0.0.1:{port}",)
        endpoints = fuse_endpoints(listen=locator) if hub else worker_endpoints(connect=locator)
        self.session = open_session(endpoints, "test")

        def sighting(sample) -> None:   # a lone sighting or a worker's batch of a robot's (docs/scaling.md)
            for message in decode_messages(bytes(sample.payload)):
                self.received.setdefault(message.camera, []).append(time.monotonic())
                self.stamped.setdefault(message.camera, []).append(message.arrival_time_s)

        # a robot's own key, or (once the fusion claims the robot) the fusion's: both are what the workers publish
        self.subscribers = [self.session.declare_subscriber(f"{key}/**", sighting)
                            for key in (SIGHTINGS_KEY, SHARD_SIGHTINGS_KEY)]
        self.watcher = self.session.liveliness().declare_subscriber(
            f"{CLAIMS_KEY}/**", lambda s: self.board.token(str(s.key_expr), not str(s.kind).endswith("DELETE")),
            history=True)

    def holders(self) -> dict[str, set[str]]:
        return {c: w for c, w in self.board.snapshot()[1].items() if w}

    def heard_since(self, camera: str, t: float) -> bool:
        return any(a > t for a in self.received.get(camera, ())[-5:])

    def longest_gap_s(self, camera: str, start_s: float, end_s: float) -> float:
        """The longest stretch of Unix time in [start_s, end_s] without a frame of ``camera``
        (stamped by the worker that read it, so a slow test process does not count)."""
        stamps = sorted(t for t in self.stamped.get(camera, ()) if start_s < t < end_s)
        return float(np.max(np.diff([start_s, *stamps, end_s])))

    def close(self) -> None:
        for subscriber in self.subscribers:
            subscriber.undeclare()
        self.watcher.undeclare()
        self.session.close()


def fused_poses(path) -> list[dict]:
    """The poses of a fusion's JSONL so far (flushed per pose; a line being written is skipped)."""
    poses = []
    for line in path.read_text().splitlines() if path.exists() else ():
        try:
            poses.append(json.loads(line))
        except json.JSONDecodeError:
            break
    return poses


def wait_for(condition, timeout_s: float, what: str, procs) -> float:
    """Poll ``condition`` until true; the time.monotonic() it became true."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
            for p in procs:
                p.kill()
            stderrs = [p.communicate(timeout=30)[1][-2000:] for p in procs]
            pytest.fail(f"{what}: not within {timeout_s} s; stderr: {stderrs}")
        time.sleep(0.02)
    return time.monotonic()


# A killed worker's tokens go when the kernel closes its socket (milliseconds), a frozen one's
# (SIGSTOP: a hung or unplugged host) when the lease expires; then the survivor's next check
# (at once on a token change) claims. Sightings follow after connect, the first /time round trip
# and a frame (~0.03 s on a quiet machine). The bounds leave a loaded machine 2 s.
LEASE_S = BUS_LEASE_MS / 1000
TAKEOVER_CLAIM_S = {"SIGKILL": 2.0, "SIGSTOP": LEASE_S + 2.0}
TAKEOVER_SIGHTING_S = {"SIGKILL": 3.0, "SIGSTOP": LEASE_S + 3.0}


@pytest.mark.parametrize("how", ["SIGKILL", "SIGSTOP"])
def test_a_dead_workers_cameras_are_taken_over(scene, tmp_path, how):
    """Two workers without --cameras claim disjoint, fair shares; one is killed (SIGKILL) or
    frozen (SIGSTOP) mid-run: the other claims its cameras within TAKEOVER_CLAIM_S and their
    sightings resume within TAKEOVER_SIGHTING_S, while the survivor's own cameras never stop and
    the fusion keeps producing poses. A frozen worker that wakes up (SIGCONT) finds its cameras
    taken: in the end every camera has one reader again."""
    work, rec = scene
    port = free_port()
    with EmulatedCameras(rec, ("--loop",)) as emu:
        config = write_live_config(rec / "config.toml", emu.urls, work / "auto_config.toml")
        cameras = [c.name for c in read_tracker_config(config).cameras]
        common = ["--config", str(config), "--extrinsics", str(work / "extrinsics.toml"), "--duration", "120",
                  "--status-every", "1"]
        fuse = cubetrack("fuse", *common, "--out", str(tmp_path / "fused"), "--bus-listen", f"tcp/127.0.0.1:{port}")
        bus = Bus(port)
        workers = [cubetrack("worker", *common, "--bus-connect", f"tcp/127.0.0.1:{port}") for _ in range(2)]
        procs = [fuse, *workers]
        try:
            ids = [f"-{w.pid}" for w in workers]

            def owners() -> dict[str, list[int]]:
                return {c: [i for i, suffix in enumerate(ids) for w in ws if w.endswith(suffix)]
                        for c, ws in bus.holders().items()}

            def settled() -> bool:  # both workers hold a share (a slow starter is not yet in the pool)
                o = owners()
                return (all(len(o.get(c, ())) == 1 for c in cameras) and {o[c][0] for c in cameras} == {0, 1}
                        and all(bus.heard_since(c, time.monotonic() - 0.5) for c in cameras))

            wait_for(settled, 90, "every camera claimed once, both workers with a share, every camera heard", procs)
            time.sleep(1.0)
            before = owners()
            assert all(len(before.get(c, ())) == 1 for c in cameras), before  # still one reader each
            shares = [[c for c in cameras if before[c] == [i]] for i in range(2)]
            assert all(shares) and abs(len(shares[0]) - len(shares[1])) <= 1, shares
            victim, survivor = shares
            killed, killed_unix_s = time.monotonic(), time.time()
            workers[0].send_signal(getattr(signal, how))
            if how == "SIGKILL":
                workers[0].wait(10)
            claimed = wait_for(lambda: all(owners().get(c) == [1] for c in cameras), 20,
                               f"the survivor claims {victim}", [fuse, workers[1]])
            resumed = wait_for(lambda: all(bus.heard_since(c, claimed) for c in victim), 20,
                               f"sightings of {victim} resume", [fuse, workers[1]])
            resumed_unix_s = killed_unix_s + resumed - killed
            # until the fusion has a pose from a taken-over camera (once the robot is in its view)
            wait_for(lambda: any(p["time"] > resumed_unix_s and set(p["cameras"]) & set(victim)
                                 for p in fused_poses(tmp_path / "fused" / "robot.jsonl")), 60,
                     f"a fused pose from {victim}", [fuse, workers[1]])
            time.sleep(max(0.0, resumed + 1.5 - time.monotonic()))  # the gaps below look 1 s past `resumed`
            if how == "SIGSTOP":
                workers[0].send_signal(signal.SIGCONT)
                wait_for(lambda: all(len(owners().get(c, ())) == 1 for c in cameras) and len(bus.holders()) == 3,
                         LEASE_S + 10, "one reader per camera after the frozen worker woke up", procs)
                procs.remove(workers[0])
                workers[0].kill()
                workers[0].wait(10)
            for p in (workers[1], fuse):
                p.send_signal(signal.SIGINT)
            outs = [p.communicate(timeout=60) for p in (workers[1], fuse)]
        finally:
            kill_leftovers(procs)
            bus.close()
    assert [p.returncode for p in (workers[1], fuse)] == [0, 0], outs
    window_s = (killed_unix_s - 1.0, killed_unix_s + resumed - killed + 1.0)
    gaps = {c: bus.longest_gap_s(c, *window_s) for c in cameras}
    print(f"{how}: victim {victim}, survivor {survivor}: claimed {claimed - killed:.3f} s and heard "
          f"{resumed - killed:.3f} s after; longest gap in the frames of each camera around it {gaps}")
    assert claimed - killed < TAKEOVER_CLAIM_S[how]
    assert resumed - killed < TAKEOVER_SIGHTING_S[how]
    # the survivor's own cameras went on (a frame every 1/fps; more only if the machine stalls the
    # worker); the victim's lost frames until the take-over, no longer
    assert max(gaps[c] for c in survivor) < 1.5, gaps
    assert max(gaps[c] for c in victim) < TAKEOVER_SIGHTING_S[how], gaps
    # the poses went on: after the kill no longer gap than the take-over plus the longest the
    # robot goes unseen in the offline replay of the recording (the cameras' views, not the bus)
    assert "interrupted" in outs[1][0]
    times_s = np.array([p["time"] for p in fused_poses(tmp_path / "fused" / "robot.jsonl")])
    after = times_s[times_s > killed_unix_s]
    unseen_s = float(np.max(np.diff(read_tum(work / "offline" / "robot.tum").times_s)))
    print(f"longest gap between fused poses after the {how}: {np.max(np.diff(after)):.3f} s "
          f"(offline replay: {unseen_s:.3f} s)")
    assert len(after) > 1 and np.max(np.diff(after)) < max(unseen_s, 0.5) + (resumed - killed) + 0.5


def test_named_and_automatic_workers_share_the_cameras(scene, tmp_path):
    """A worker with --cameras keeps its camera; two automatic workers share the others, one
    each; one stopped with Ctrl-C drops its tokens at once and the other takes its camera.
    (The cameras are unreachable: claiming does not depend on them; the test's peer is the hub.)"""
    work, rec = scene
    port = free_port()
    cameras = [c.name for c in read_tracker_config(rec / "config.toml").cameras]
    config = write_live_config(rec / "config.toml", dict.fromkeys(cameras, "http://127.0.0.1:9/stream"),
                               tmp_path / "lab.toml")
    common = ["--config", str(config), "--extrinsics", str(work / "extrinsics.toml"), "--duration", "120",
              "--bus-connect", f"tcp/127.0.0.1:{port}"]
    bus = Bus(port, hub=True)
    named = cubetrack("worker", *common, "--cameras", cameras[0])
    autos = [cubetrack("worker", *common) for _ in range(2)]
    procs = [named, *autos]
    try:
        def held() -> dict[str, list[str]]:
            return {c: sorted(w.rsplit("-", 1)[1] for w in bus.holders().get(c, ())) for c in cameras}

        def shared() -> bool:
            h = held()
            return (h[cameras[0]] == [str(named.pid)] and all(len(h[c]) == 1 for c in cameras[1:])
                    and {h[c][0] for c in cameras[1:]} == {str(a.pid) for a in autos})

        wait_for(shared, 90, "the named camera kept, the others one per automatic worker", procs)
        gone = next(c for c in cameras[1:] if held()[c] == [str(autos[0].pid)])
        autos[0].send_signal(signal.SIGINT)
        stopped = time.monotonic()
        took = wait_for(lambda: held()[gone] == [str(autos[1].pid)], 20, f"{gone} taken over", [named, autos[1]])
        print(f"Ctrl-C: {gone} claimed by the other worker {took - stopped:.3f} s later")
        assert took - stopped < 5.0  # the stopping worker drops its tokens itself: no lease to wait for
        assert held()[cameras[0]] == [str(named.pid)]
        first = autos[0].communicate(timeout=60)  # one Ctrl-C only: a second one would cut its clean-up
        for p in (named, autos[1]):
            p.send_signal(signal.SIGINT)
        outs = [p.communicate(timeout=60) for p in (named, autos[1])]
        outs.insert(1, first)
    finally:
        kill_leftovers(procs)
        bus.close()
    assert [p.returncode for p in procs] == [0, 0, 0], outs
    assert f"took {gone}" in outs[2][0] and f"gave up {gone}" in outs[1][0]  # the summaries list the claims
