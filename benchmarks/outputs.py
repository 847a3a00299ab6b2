"""Issue 10's benchmark: the CPU per frame the outputs cost, on both sides of their pipe.

A recorded stream of pipeline items (what the live pipeline hands its outputs: fused poses with
the filter's velocity and covariance, processed camera frames with their JPEG and detections,
camera health once a second per camera) is fed at --fps frames per second (default 16 cameras
x 30 fps = 480) into :class:`cubetrack.sink.base.Outputs` with the outputs running as a session
runs them (:func:`cubetrack.app.outputs.start_outputs`: one child process). Then it prints CPU
per frame of

- the parent (the tracker's side: thinning the views, the pipe's queue, pickling, writing):
  this process's CPU while feeding, minus a baseline run of the same feed with no outputs in
  the same invocation;
- the child (every output, with their native threads), from /proc between the first and the
  last item (its start-up and close are not counted).

The stream is built once (cached in --out): ``cubetrack simulate`` renders --cameras x
--stream-fps for --recording-s seconds, the offline tracker (``track_recording``, true
extrinsics) gives the poses, the detector the markers of each frame. It is replayed in a loop
(times shifted by its length) for --duration seconds. No client is connected to any server, unless
--clients: then a process of consumers (not counted) takes everything as users would: a Zenoh
router (what ``rmw_zenohd`` is) that the Zenoh and ROS 2 outputs connect to, subscribed to
every key; a VRPN client of the robot's tracker; a Foxglove WebSocket client subscribed to every
channel (the test suite's clients, tests/unit/sink); it says how many messages each received.

    .venv/bin/python benchmarks/outputs.py                      # every output on, 480 frames/s, 10 s
    .venv/bin/python benchmarks/outputs.py --each               # and each output alone
    .venv/bin/python benchmarks/outputs.py --only mcap foxglove # just these, together
    .venv/bin/python benchmarks/outputs.py --clients            # with a consumer on every output
    .venv/bin/python benchmarks/outputs.py --quick              # CI smoke: 2 cameras, 60 frames/s, 2 s

Run it under ``nice -n 19`` on a shared machine and compare CPU per frame (not wall time);
the load average is printed with the figures. Exit code 0 for a completed run (a report).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pickle
import socket
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from live import process_cpu_rss  # benchmarks/live.py, next to this script (one /proc reader)

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ("zenoh", "ros2", "vrpn", "foxglove", "mcap")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fps", type=float, default=480.0, help="frames per second fed (default 480 = 16 x 30)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds of feeding per run (default 10)")
    p.add_argument("--only", nargs="+", choices=OUTPUTS, default=list(OUTPUTS), metavar="OUTPUT",
                   help=f"the outputs to run together (default all: {' '.join(OUTPUTS)})")
    p.add_argument("--each", action="store_true", help="also run each of them alone")
    p.add_argument("--clients", action="store_true", help="a consumer on every output (in a process not counted)")
    p.add_argument("--consume", nargs=3, type=int, metavar=("ROUTER", "VRPN", "FOXGLOVE"), help=argparse.SUPPRESS)
    p.add_argument("--cameras", type=int, default=16, help="cameras of the recorded stream (default 16)")
    p.add_argument("--stream-fps", type=float, default=30.0, help="frames/s per camera of the recording (default 30)")
    p.add_argument("--recording-s", type=float, default=3.0, help="seconds of recording, looped (default 3)")
    p.add_argument("--seed", type=int, default=7, help="scene seed (default 7)")
    p.add_argument("--out", type=Path, help="keep the recording, the stream and outputs_report.json here")
    p.add_argument("--quick", action="store_true", help="smoke run: 2 cameras x 30 fps, 60 frames/s, 2 s")
    args = p.parse_args(argv)
    if args.quick:
        args.cameras, args.fps, args.duration, args.recording_s = 2, 60.0, 2.0, 1.0
    for name in ("fps", "duration", "cameras", "stream_fps", "recording_s"):
        if not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')} must be positive")
    return args


# --------------------------------------------------------------------------- the recorded stream


class _Capture:
    """A sink keeping what the offline tracker hands out (poses)."""

    name, in_line, wants_views, view_interval_s, where = "capture", True, False, 0.0, ""

    def __init__(self) -> None:
        self.poses: list = []
        self.session = None

    def open(self, session) -> None:
        self.session = session

    def pose(self, pose) -> None:
        self.poses.append(pose)

    def camera_health(self, health) -> None:
        pass

    def close(self) -> None:
        pass


def build_stream(args: argparse.Namespace, work: Path) -> tuple[object, list[tuple[float, str, object]], float]:
    """(session info, [(output time s, kind, item)] in time order, frames in it) from a simulated
    recording; cached as a pickle next to it."""
    rec = work / f"rec_c{args.cameras}_f{args.stream_fps:g}_d{args.recording_s:g}_s{args.seed}"
    cache = rec.with_suffix(".stream.pickle")
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    from live import cubetrack  # benchmarks/live.py: a cubetrack command in-process

    from cubetrack.app.track import track_recording
    from cubetrack.core.records import CameraHealth, CameraView
    from cubetrack.detect.detector import Detector, decode_gray
    from cubetrack.io.config import read_extrinsics, read_tracker_config
    from cubetrack.io.recording import Recording

    cubetrack("simulate", "--out", str(rec), "--force", "--cameras", str(args.cameras), "--fps",
              str(args.stream_fps), "--duration", str(args.recording_s), "--seed", str(args.seed),
              "--latency-ms", "8", "--latency-jitter-ms", "2", "--spike-rate", "0", "--drop-rate", "0",
              "--calibration-frames", "1")
    config = read_tracker_config(rec / "config.toml")
    recording = Recording.open(rec)
    capture = _Capture()
    print("outputs benchmark: tracking the recording offline for the stream's poses", file=sys.stderr)
    track_recording(config, recording, read_extrinsics(rec / "true_extrinsics.toml"), work / "offline",
                    sinks=[capture])
    detector = Detector(dictionaries=[config.world.dictionary,
                                      *(d for r in config.robots for d in r.layout.dictionaries)])
    items: list[tuple[float, str, object]] = [(p.time_s + p.latency_s, "pose", p) for p in capture.poses]
    frames = 0
    for camera in recording.camera_names:
        count = 0
        for frame in recording.frames(camera):
            found = detector.detect(decode_gray(frame.jpeg))
            items.append((frame.host_time_s, "camera_view",
                          CameraView(camera, frame.seq, frame.host_time_s - 0.008, frame.jpeg, found)))
            count += 1
            if count % round(args.stream_fps) == 0:
                items.append((frame.host_time_s, "camera_health", CameraHealth(
                    camera, frame.host_time_s, True, args.stream_fps, count, 0, 0, 0, 0.01, 3.0, 0.008,
                    len(frame.jpeg))))
        frames += count
    items.sort(key=lambda item: item[0])
    stream = (capture.session, items, frames)
    cache.write_bytes(pickle.dumps(stream))
    return stream


# --------------------------------------------------------------------------- feeding


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def output_specs(names: list[str], work: Path, ports: tuple[int, int, int] | None):
    """The outputs ``names``; ``ports`` (Zenoh router, VRPN, Foxglove) where consumers wait,
    else free ones and the Zenoh outputs' defaults (as benchmarks/live.py runs them)."""
    from cubetrack.app.outputs import OutputSpec

    router, vrpn, foxglove = ports or (None, free_port(), free_port())
    zenoh = {"connect": [f"tcp/127.0.0.1:{router}"]} if router else {}
    tables = {"zenoh": {"type": "zenoh", **zenoh}, "ros2": {"type": "ros2", **zenoh},
              "vrpn": {"type": "vrpn", "address": f"127.0.0.1:{vrpn}"},
              "foxglove": {"type": "foxglove", "address": f"127.0.0.1:{foxglove}"},
              "mcap": {"type": "mcap", "path": "outputs_bench.mcap"}}
    (work / "outputs_bench.mcap").unlink(missing_ok=True)
    return [OutputSpec(tables[name], work, f"--{name}") for name in names]


def consume(router_port: int, vrpn_port: int, foxglove_port: int) -> None:
    """The consumers' process (--clients): until stdin closes, then prints what each received."""
    import threading

    import zenoh

    sys.path.insert(0, str(ROOT / "tests" / "unit" / "sink"))
    from foxglove_client import LiveClient  # the test suite's clients, written from the protocols
    from vrpn_client import TrackerClient

    config = zenoh.Config()
    for key, value in (("mode", '"router"'), ("listen/endpoints", f'["tcp/127.0.0.1:{router_port}"]'),
                       ("scouting/multicast/enabled", "false")):
        config.insert_json5(key, value)
    router = zenoh.open(config)
    counts = {"zenoh": 0, "vrpn": 0, "foxglove": 0}

    def count(sample) -> None:
        counts["zenoh"] += 1

    router.declare_subscriber("**", count)
    stop = threading.Event()

    def retry(make):
        while not stop.is_set():
            try:
                return make()
            except OSError:
                time.sleep(0.2)
        return None

    def foxglove() -> None:
        import websocket

        client = retry(lambda: LiveClient(foxglove_port))
        while client is not None and not stop.is_set():
            try:
                opcode, data = client.ws.recv_data()
            except websocket.WebSocketTimeoutException:
                continue
            except (OSError, websocket.WebSocketException):
                return
            if opcode == websocket.ABNF.OPCODE_TEXT:
                client._text(json.loads(data))  # subscribes to what is advertised
            else:
                counts["foxglove"] += 1

    vrpn = []

    def vrpn_client() -> None:
        client = retry(lambda: TrackerClient(vrpn_port, "robot"))
        if client is not None:
            vrpn.append(client)

    for target in (foxglove, vrpn_client):  # each waits for its server (runs without it have none)
        threading.Thread(target=target, daemon=True).start()
    print("ready", flush=True)
    sys.stdin.read()  # the benchmark closes it at the end of the run
    stop.set()
    for client in vrpn:
        counts["vrpn"] = len(client.reports)
        client.close()
    router.close()
    print(json.dumps(counts), flush=True)


@contextlib.contextmanager
def consumers(enabled: bool):
    """(ports, result) of a consumers' process for one run; ``result`` holds their counts after it."""
    if not enabled:
        yield None, {}
        return
    import subprocess

    ports = (free_port(), free_port(), free_port())
    proc = subprocess.Popen([sys.executable, __file__, "--consume", *map(str, ports)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    result: dict = {}
    try:
        if proc.stdout.readline().strip() != "ready":
            raise SystemExit("the consumers' process did not start")
        yield ports, result
    finally:
        out, _ = proc.communicate("", timeout=60)
        result.update(json.loads(out.strip().splitlines()[-1]) if out.strip() else {})


def feed(args: argparse.Namespace, stream, names: list[str], work: Path) -> dict:
    """One run: the stream at ``args.fps`` frames/s into the outputs ``names`` (none: the baseline)."""
    with consumers(args.clients and bool(names)) as (ports, received):
        result = _feed(args, stream, names, work, ports)
    result["received"] = received
    return result


def _feed(args: argparse.Namespace, stream, names: list[str], work: Path, ports) -> dict:
    from cubetrack.app.outputs import start_outputs
    from cubetrack.sink.base import Outputs

    session, items, frames = stream
    span_s = items[-1][0] - items[0][0] + 1.0 / args.stream_fps
    speed = args.fps / (frames / span_s)  # stream seconds per second of feeding
    sinks = start_outputs(output_specs(names, work, ports)) if names else []
    child = sinks[0]._process.pid if sinks else None
    outputs = Outputs(sinks)
    outputs.open(session)
    sent = fed_frames = 0
    start_s, start_cpu = time.monotonic(), time.process_time()
    start_child = process_cpu_rss(child)[0] if child else 0.0
    t0 = items[0][0]
    loop = 0
    while True:
        for at_s, kind, item in items:
            stream_s = at_s - t0 + loop * span_s
            due_s = start_s + stream_s / speed
            if due_s - start_s > args.duration:
                break
            wait_s = due_s - time.monotonic()
            if wait_s > 0.002:
                time.sleep(wait_s)
            shift_s = loop * span_s
            if shift_s:
                item = replace(item, time_s=item.time_s + shift_s)
            getattr(outputs, kind)(item)
            sent += 1
            fed_frames += kind == "camera_view"
        else:
            loop += 1
            continue
        break
    feed_s = time.monotonic() - start_s
    # the pipe's queue empties, then the child finishes what it holds
    queue = outputs.sinks[0] if sinks else None
    while queue is not None and queue._queue:
        time.sleep(0.05)
    parent_cpu = time.process_time() - start_cpu
    settle_s = 0.5
    time.sleep(settle_s)
    child_cpu = process_cpu_rss(child)[0] - start_child if child else 0.0
    dropped = sum(outputs.dropped().values())
    outputs.close()
    mcap = work / "outputs_bench.mcap"
    mcap_mb = mcap.stat().st_size / 1e6 if mcap.exists() else 0.0
    mcap.unlink(missing_ok=True)
    return {"outputs": names, "frames": fed_frames, "items": sent, "feed_s": feed_s,
            "frames_per_s": fed_frames / feed_s, "parent_cpu_s": parent_cpu, "child_cpu_s": child_cpu,
            "child_cpu_ms_per_frame": child_cpu / max(fed_frames, 1) * 1e3, "dropped_items": dropped,
            "mcap_mb": mcap_mb}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.consume:
        consume(*args.consume)
        return 0
    import logging

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    with contextlib.ExitStack() as stack:
        work = args.out or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="cubetrack-outputs-")))
        work.mkdir(parents=True, exist_ok=True)
        stream = build_stream(args, work)
        runs = [[]] + [list(args.only)] + ([[name] for name in args.only] if args.each and len(args.only) > 1 else [])
        results = []
        for names in runs:
            print(f"outputs benchmark: {' + '.join(names) or 'no outputs (baseline)'} for {args.duration:g} s",
                  file=sys.stderr, flush=True)
            results.append(feed(args, stream, names, work))
        base = results[0]
        base_ms = base["parent_cpu_s"] / max(base["frames"], 1) * 1e3
        for r in results:
            r["parent_cpu_ms_per_frame"] = r["parent_cpu_s"] / max(r["frames"], 1) * 1e3 - base_ms
        report = {"cores": os.cpu_count(), "load_average": os.getloadavg(), "fps": args.fps,
                  "stream_items_per_frame": len(stream[1]) / stream[2], "baseline_parent_ms_per_frame": base_ms,
                  "runs": results[1:]}
        if args.out:
            (work / "outputs_report.json").write_text(json.dumps(report, indent=2))
    print(f"outputs benchmark: {args.fps:g} frames/s fed for {args.duration:g} s per run, {report['cores']} cores, "
          f"load average {' '.join(f'{v:.2f}' for v in report['load_average'])}; the feed alone "
          f"{base_ms:.3f} ms CPU per frame")
    print(f"  {'outputs':<37} {'frames/s':>8} {'parent ms/frame':>15} {'child ms/frame':>14} {'dropped':>7} "
          f"{'MCAP MB':>7}")
    for r in report["runs"]:
        print(f"  {' + '.join(r['outputs']):<37} {r['frames_per_s']:>8.1f} {r['parent_cpu_ms_per_frame']:>15.3f} "
              f"{r['child_cpu_ms_per_frame']:>14.3f} {r['dropped_items']:>7d} {r['mcap_mb']:>7.2f}")
        if r["received"]:
            print(f"    consumers received: {', '.join(f'{k} {v} messages' for k, v in r['received'].items())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
