"""Fuzzing campaigns of every parser that faces the network, the serial port or a file.

Python targets (the host's and cubecam's parsers) run under atheris (coverage-guided libFuzzer
for Python; ``pip install atheris``) in a subprocess each; the firmware targets are the
libFuzzer binaries ``make -C firmware fuzz`` builds (every ``fuzz-*`` executable found in the
build folder, so new firmware targets are picked up without changing this script). Each
campaign starts from the saved corpus (``tests/corpus/<target>/`` for Python,
``firmware/fuzz/corpus/<target>/`` for the firmware), runs to a number of executions and
prints, per target: executions, time, coverage (libFuzzer's ``cov``/``ft`` counters, plus
line coverage of the parser code for Python targets and edge coverage of the firmware core
files the target reaches), corpus size and crashes. ``--save`` merges the inputs that found
new coverage, and every crash input, into the saved corpus: CI replays the saved corpora on
every run (``tests/reliability/test_fuzz_corpora.py``), so a crash found once stays a
regression test.

  python benchmarks/fuzz_campaign.py --list
  python benchmarks/fuzz_campaign.py --python-runs 1000000 --firmware-runs 10000000 --save
  python benchmarks/fuzz_campaign.py --only mjpeg,http --python-runs 20000 --firmware-runs 100000
  python benchmarks/fuzz_campaign.py --replay          # the saved corpora once each (what CI does)

Every Python target asserts properties, not just "no crash": only the project's own error
type may escape a file reader; a network parser never raises and keeps its buffers bounded
whatever it is fed; what a parser accepts is well formed (whole JPEGs, finite times, file
names inside their folder) and, where there is a writer, reads back as written.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PY_CORPUS = REPO / "tests" / "corpus"
FIRMWARE_DIR = REPO / "firmware"
FIRMWARE_CORPUS = FIRMWARE_DIR / "fuzz" / "corpus"
FILE_SEPARATOR = b"\xfe\xfe"  # splits one input into several files (never in valid UTF-8)
CRASH_PREFIXES = ("crash-", "timeout-", "oom-", "leak-", "slow-unit-")
# Largest input per firmware target: the console's lines are at most 128 bytes and an Improv frame
# 265, so 1 KB holds several; an HTTP request head may be 2048 bytes (more is 431). Others: 4096.
FIRMWARE_MAX_LEN = {"console": 1024, "improv": 1024}


# --- Python targets: each takes bytes and raises only on a broken property -----------------------


class _Scratch:
    """A per-process folder for the targets that read files (created on first use)."""

    path: Path | None = None

    @classmethod
    def dir(cls) -> Path:
        if cls.path is None:
            shm = Path("/dev/shm")  # memory-backed where there is one: the file targets write every input
            cls.path = Path(tempfile.mkdtemp(prefix="cubetrack-fuzz-", dir=shm if shm.is_dir() else None))
        return cls.path


def _chunks(data: bytes, step: int):
    for i in range(0, len(data), step):
        yield data[i:i + step]


def target_mjpeg(data: bytes) -> None:
    """The MJPEG part reader of the live source (cubetrack.source.mjpeg.MjpegParser).

    Byte 0: bit 0 = boundary unknown (learnt from the stream), bits 1-7 = read size - 1.
    Properties: never raises; every part it returns is a whole JPEG of at most max_part_bytes
    taken from the input, with a finite non-negative time; its buffer stays bounded."""
    from cubetrack.source.mjpeg import MjpegParser

    if not data:
        return
    boundary = None if data[0] & 1 else "cubecam-mjpeg-boundary"
    step = (data[0] >> 1) + 1
    body = data[1:]
    parser = MjpegParser(boundary, max_header_bytes=256, max_part_bytes=2048)
    bound = parser.max_part_bytes + parser.max_header_bytes + step + 256
    for chunk in _chunks(body, step):
        for part in parser.feed(chunk):
            assert part.jpeg.startswith(b"\xff\xd8") and part.jpeg.rstrip(b"\r\n").endswith(b"\xff\xd9")
            assert len(part.jpeg) <= parser.max_part_bytes and part.jpeg in body
            assert math.isfinite(part.device_time_s) and part.device_time_s >= 0
            assert part.seq is None or part.seq >= 0
        assert len(parser._buf) <= bound, f"buffer {len(parser._buf)} > {bound}"
    parser.close()
    assert parser.parts + sum(parser.bad.values()) <= len(body)


def target_time_answer(data: bytes) -> None:
    """The ``/time`` answer parser: a number >= 0 or ValueError; the node's format reads back."""
    from cubecam.mjpeg import format_timestamp
    from cubetrack.source.time_poll import parse_time_answer

    try:
        value = parse_time_answer(data)
    except ValueError:
        pass
    else:
        digits = re.search(rb"\d+(\.\d+)?", data)
        assert math.isfinite(value) and value >= 0 and digits is not None and value == float(digits.group())
    micros = int.from_bytes(data[:6], "little")
    assert abs(parse_time_answer(format_timestamp(micros).encode()) - micros / 1e6) <= 1e-6 * max(1.0, micros / 1e6)


def target_improv(data: bytes) -> None:
    """cubecam's Improv serial splitter and decoders (tools/cubecam/improv.py).

    Byte 0: bits 0-5 = read size - 1, bits 6-7 = how often the 100 ms partial-frame timeout
    fires. Properties: feed never raises; a frame re-encodes to bytes of the input; lines and
    frames stay within their limits; decoders raise only ImprovError."""
    from cubecam import improv

    if not data:
        return
    step = (data[0] & 0x3F) + 1
    timeout_every = data[0] >> 6
    parser = improv.Parser()
    body = data[1:]
    for n, chunk in enumerate(_chunks(body, step)):
        events = parser.feed(chunk)
        if timeout_every and n % (timeout_every + 1) == 0:
            events += parser.timeout()
        for ev in events:
            if isinstance(ev, improv.Frame):
                assert improv.encode_frame(ev.type, ev.data) in body
                for decode in (improv.decode_state, improv.decode_error, improv.decode_rpc, improv.decode_rpc_result):
                    try:
                        decode(ev)
                    except improv.ImprovError:
                        pass
            elif isinstance(ev, improv.Line):
                assert len(ev.text) <= improv.MAX_LINE and "\n" not in ev.text
            else:
                assert len(ev.raw) <= improv.HEADER_LEN + improv.MAX_DATA + 1
        assert len(parser._line) < improv.MAX_LINE and len(parser._frame) <= improv.HEADER_LEN + improv.MAX_DATA + 1


def target_http_request(data: bytes) -> None:
    """The emulator's HTTP request reader (tools/cubecam/request.py, the firmware's rules).

    Byte 0 = read size - 1. Properties: the outcome does not depend on how the bytes are split;
    a head over the limit is never INCOMPLETE; the route is one of the node's answers."""
    from cubecam.mjpeg import MAX_REQUEST_HEAD
    from cubecam.request import ParseStatus, RequestParser, route

    if not data:
        return
    step = data[0] + 1
    whole, split = RequestParser(), RequestParser()
    whole.feed(data[1:])
    for chunk in _chunks(data[1:], step):
        split.feed(chunk)
    assert (whole.status, whole.method, whole.target) == (split.status, split.method, split.target)
    if len(data) - 1 > MAX_REQUEST_HEAD:
        assert whole.status is not ParseStatus.INCOMPLETE
    if whole.status is not ParseStatus.INCOMPLETE:
        decision = route(whole)
        assert decision.status in (200, 400, 404, 405, 431)
        assert decision.fps_cap is None or 0 < decision.fps_cap <= 30


def _write_files(folder: Path, names: tuple[str, ...], data: bytes) -> None:
    pieces = data.split(FILE_SEPARATOR)
    # the pieces, padded with empty files, are longer than the names on purpose: zip stops at the names
    for name, piece in zip(names, pieces + [b""] * len(names), strict=False):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(piece)


def target_recording(data: bytes) -> None:
    """The recording reader (host/cubetrack/io/recording.py): recording.json, index.csv and
    clock.csv of camera ``cam`` (the input split at FILE_SEPARATOR). Properties: only
    RecordingError escapes; rows kept have finite times and file names inside the camera
    folder; clock samples are finite."""
    from cubetrack.core.errors import RecordingError
    from cubetrack.io.recording import Recording

    folder = _Scratch.dir() / "recording"
    shutil.rmtree(folder, ignore_errors=True)
    _write_files(folder, ("recording.json", "cam/index.csv", "cam/clock.csv"), data)
    (folder / "cam" / "00000001.jpg").write_bytes(b"\xff\xd8\xff\xd9")
    try:
        rec = Recording.open(folder)
    except RecordingError:
        return
    for camera in rec.camera_names:
        try:
            rows = rec.index(camera)
            samples = rec.clock_samples(camera)
            frames = list(rec.frames(camera))
        except RecordingError:
            continue
        for row in rows:
            assert math.isfinite(row.device_time_s) and math.isfinite(row.host_time_s)
            assert (folder / camera / row.file).resolve().parent == (folder / camera).resolve()
        assert all(math.isfinite(v) for s in samples for v in (s.host_send_s, s.device_time_s, s.host_recv_s))
        assert len(frames) <= len(rows)


_CONFIG_FILES = ("tracker.toml", "cube.toml", "extrinsics.toml")


@functools.cache
def _valid_config_files() -> dict[str, bytes]:
    import tomli_w

    from cubetrack.core.layout import layout_to_table, paper_cube_layout

    tracker = ('[world]\nmarker_id = 0\nmarker_size = 0.2\n\n[[cameras]]\nname = "cam1"\n'
               'url = "http://127.0.0.1:8080/stream"\n\n[[robots]]\nname = "bot"\nlayout = "cube.toml"\n\n'
               '[source]\nread_timeout_s = 2.0\n')
    extrinsics = ('[cam1]\nposition = [1.0, 2.0, 1.5]\nquaternion_xyzw = [0.0, 0.0, 0.0, 1.0]\nsamples = 40\n'
                  'spread_position_m = 0.001\nspread_rotation_deg = 0.1\nmethod = "world marker"\n')
    cube = tomli_w.dumps(layout_to_table(paper_cube_layout()))
    return {"tracker.toml": tracker.encode(), "cube.toml": cube.encode(), "extrinsics.toml": extrinsics.encode()}


def target_config(data: bytes) -> None:
    """The tracker config, its cube layout and the extrinsics TOML (host/cubetrack/io/config.py,
    core/layout.py, app/config.py). Byte 0 % 3 chooses which file the rest replaces (the others
    stay valid). Property: only ConfigError escapes."""
    from cubetrack.app.config import load_config
    from cubetrack.core.errors import ConfigError
    from cubetrack.io.config import read_extrinsics

    if not data:
        return
    folder = _Scratch.dir() / "config"
    folder.mkdir(exist_ok=True)
    files = dict(_valid_config_files())
    files[_CONFIG_FILES[data[0] % 3]] = data[1:]
    for name, content in files.items():
        (folder / name).write_bytes(content)
    for read in (load_config, read_extrinsics):
        try:
            read(folder / ("extrinsics.toml" if read is read_extrinsics else "tracker.toml"))
        except ConfigError:
            pass


def target_camera_info(data: bytes) -> None:
    """Intrinsics files (host/cubetrack/io/camera_info.py): ROS camera_info YAML and OpenCV
    FileStorage YAML. Properties: only CameraInfoError escapes; what is accepted is a finite
    camera and reads back unchanged from the ROS file the project writes."""
    import numpy as np

    from cubetrack.core.errors import CameraInfoError
    from cubetrack.io.camera_info import read_camera_info, write_camera_info

    path = _Scratch.dir() / "camera.yaml"
    path.write_bytes(data)
    try:
        intr = read_camera_info(path)
    except CameraInfoError:
        return
    assert intr.width > 0 and intr.height > 0 and np.all(np.isfinite(intr.K))
    back_path = _Scratch.dir() / "written.yaml"
    if not np.all(np.isfinite(intr.dist)):
        return
    write_camera_info(intr, back_path)
    back = read_camera_info(back_path)
    assert (back.width, back.height) == (intr.width, intr.height)
    assert np.array_equal(back.K, intr.K) and np.array_equal(back.dist, intr.dist)


@dataclass(frozen=True)
class PythonTarget:
    """A Python fuzz target: the function, the modules atheris instruments (imported inside
    its hook) and the code whose line coverage is reported ("module:qualname", a class
    counts all its methods)."""

    function: Callable[[bytes], None]
    modules: tuple[str, ...]
    measured: tuple[str, ...]
    max_len: int = 4096


PY_TARGETS: dict[str, PythonTarget] = {
    "mjpeg": PythonTarget(target_mjpeg, ("cubetrack.source.mjpeg",),
                          ("cubetrack.source.mjpeg:MjpegParser", "cubetrack.source.mjpeg:boundary_from_content_type")),
    "time_answer": PythonTarget(target_time_answer, ("cubetrack.source.time_poll", "cubecam.mjpeg"),
                                ("cubetrack.source.time_poll:parse_time_answer",), max_len=64),
    "cubecam_improv": PythonTarget(target_improv, ("cubecam.improv",), ("cubecam.improv:Parser",
                           "cubecam.improv:decode_state", "cubecam.improv:decode_error",
                           "cubecam.improv:_decode_command_frame", "cubecam.improv:_split_strings")),
    "http_request": PythonTarget(target_http_request, ("cubecam.request",),
                                 ("cubecam.request:RequestParser", "cubecam.request:route",
                                  "cubecam.request:parse_fps")),
    "recording": PythonTarget(target_recording, ("cubetrack.io.recording",),
                              ("cubetrack.io.recording:Recording", "cubetrack.io.recording:_parse_index_row",
                               "cubetrack.io.recording:check_camera_name")),
    "config": PythonTarget(target_config, ("cubetrack.io.config", "cubetrack.core.layout", "cubetrack.core.params",
                                           "cubetrack.app.config"),
                           ("cubetrack.io.config:read_tracker_config", "cubetrack.io.config:_world",
                            "cubetrack.io.config:read_extrinsics",
                            "cubetrack.core.layout:read_layout", "cubetrack.core.layout:layout_from_table",
                            "cubetrack.core.params:params_from_table", "cubetrack.core.params:_coerce")),
    "camera_info": PythonTarget(target_camera_info, ("cubetrack.io.camera_info",),
                                ("cubetrack.io.camera_info:read_camera_info", "cubetrack.io.camera_info:_matrix",
                                 "cubetrack.io.camera_info:_opencv_matrix", "cubetrack.io.camera_info:_small")),
}


def python_seeds() -> dict[str, list[bytes]]:
    """Well-formed inputs of every Python target, made with the project's own writers."""
    import json

    import cv2
    import numpy as np
    import yaml

    from cubecam import improv, mjpeg
    from cubecam.testdata import synthetic_jpeg
    from cubetrack.core.cameras import CameraIntrinsics
    from cubetrack.io.camera_info import camera_info_to_dict

    jpegs = [synthetic_jpeg(i, 16, 16, quality=30) for i in range(2)]
    stream = mjpeg.PART_DELIMITER + b"".join(
        mjpeg.part_header(len(j), i + 1, 1_000_000 * (i + 1)) + j + mjpeg.PART_DELIMITER for i, j in enumerate(jpegs))
    no_length = (mjpeg.PART_DELIMITER + b"Content-Type: image/jpeg\r\nX-Timestamp: 2.5\r\n\r\n" + jpegs[0]
                 + mjpeg.PART_DELIMITER)
    truncated = (mjpeg.PART_DELIMITER + mjpeg.part_header(len(jpegs[0]) + 50, 3, 7) + jpegs[0]
                 + mjpeg.PART_DELIMITER + mjpeg.part_header(len(jpegs[1]), 4, 8) + jpegs[1])
    wifi = improv.encode_wifi_settings("lab", "correct horse") + b"\n"
    serial = (b"[I] boot: cubecam\n" + improv.encode_current_state(improv.State.READY) + b"\n" + wifi
              + improv.encode_rpc_result(improv.Command.GET_DEVICE_INFO, ["cubecam", "1.0", "Spresense", "cam1"])
              + b"\nset fps 15\nOK\n" + improv.encode_error_state(improv.Error.UNABLE_TO_CONNECT)[:-1] + b"\x00\n")
    meta = json.dumps({"format": "cubetrack.recording", "version": 1, "cameras": [{"name": "cam", "source": "x"}],
                       "created": "2025-01-01T00:00:00+00:00"}).encode()
    index = (b"seq,device_time,host_time,file\n1,100.000000,1700000000.030000,00000001.jpg\n"
             b"2,100.1,1700000000.13,00000002.jpg\n")
    clock = b"host_send,device_time,host_recv\n1699999999.998,100.0,1700000000.002\n"
    K = np.array([[500.0, 0, 319.5], [0, 501.0, 239.5], [0, 0, 1]])
    intr = CameraIntrinsics(640, 480, K, np.array([0.1, -0.2, 0.001, 0.002, 0.05]), "cam1")
    ros = yaml.safe_dump(camera_info_to_dict(intr), sort_keys=False).encode()
    path = _Scratch.dir() / "opencv.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", intr.dist.reshape(1, 5))
    fs.release()
    config = _valid_config_files()
    return {
        "mjpeg": [b"\x00" + stream, b"\x0f" + stream, b"\x01" + stream, b"\x02" + no_length, b"\x07" + truncated],
        "time_answer": [b"12.345678", b"0.000000", b" 5.5\n", b"999999999999.999999999", b"abc"],
        "cubecam_improv": [b"\x00" + serial, b"\x3f" + serial, b"\xc3" + wifi[:20], b"\x05" + wifi],
        "http_request": [b"\x00GET /stream?fps=7.5 HTTP/1.1\r\nHost: cam\r\n\r\n", b"\x03GET /time HTTP/1.0\n\n",
                         b"\xffPOST /status HTTP/1.1\r\nContent-Length: 3\r\n\r\nabc",
                         b"\x01\r\nGET / HTTP/1.1\r\n\r\n"],
        "recording": [FILE_SEPARATOR.join((meta, index, clock)), FILE_SEPARATOR.join((meta, index))],
        "config": [bytes([i]) + config[name] for i, name in enumerate(_CONFIG_FILES)],
        "camera_info": [ros, path.read_bytes()],
    }


def firmware_seeds() -> dict[str, list[bytes]]:
    """Well-formed inputs of the firmware targets (see firmware/fuzz/fuzz_*.cpp for their layout:
    http's first byte sets the read size; improv's 0xFF bytes are 150 ms pauses)."""
    from cubecam import improv

    frames = [improv.encode_rpc(improv.Command.GET_CURRENT_STATE), improv.encode_rpc(improv.Command.GET_DEVICE_INFO),
              improv.encode_wifi_settings("lab", "correct horse battery"),
              improv.encode_rpc(improv.Command.GET_WIFI_NETWORKS),
              improv.encode_rpc(improv.Command.HOSTNAME, ["cam1"])]
    return {
        "http": [b"\x10GET /stream?fps=5 HTTP/1.1\r\nHost: cam\r\n\r\n", b"\x01GET /capture HTTP/1.0\r\n\r\n",
                 b"\x3fPOST /status HTTP/1.1\r\nContent-Length: 3\r\n\r\nabc", b"\x05GET /time HTTP/1.1\nX: y\n\n",
                 b"\x07GET / HTTP/1.1\r\nAccept: */*\r\n\r\nGET /status HTTP/1.1\r\n\r\n"],
        "improv": [b"\n" + f + b"\n" for f in frames] + [b"help\nget\nset fps 30\nstatus\n",
                                                      frames[2][:12] + b"\xff" + frames[0] + b"\n"],
        "console": [b"help\n", b"set ssid My Lab\nget ssid\nsave\n", b"set ip 10.0.0.2/24,10.0.0.1\nget\n",
                    b"set password hunter2hunter2\nget password\nstatus\nreboot\n", b"factory_reset\nset fps 7.5\n"],
    }


# --- line coverage of Python targets (replaying a corpus) ----------------------------------------


def _code_objects(obj) -> list:
    import inspect

    if inspect.isclass(obj):
        out = []
        for value in vars(obj).values():
            value = getattr(value, "fget", value)
            value = getattr(value, "__func__", value)
            if inspect.isfunction(value):
                out += _code_objects(value)
        return out
    codes, todo = [], [obj.__code__]
    while todo:
        code = todo.pop()
        codes.append(code)
        todo += [c for c in code.co_consts if hasattr(c, "co_lines")]
    return codes


def line_coverage(name: str, inputs: list[bytes]) -> tuple[int, int]:
    """(lines run, executable lines) of the target's measured code over ``inputs``."""
    import importlib

    target = PY_TARGETS[name]
    codes = []
    for spec in target.measured:
        module, _, qualname = spec.partition(":")
        obj = importlib.import_module(module)
        try:
            for part in qualname.split("."):
                obj = getattr(obj, part)
        except AttributeError:  # renamed or gone: say so, measure the rest
            print(f"fuzz_campaign: {spec} no longer exists; update PY_TARGETS", file=sys.stderr)
            continue
        codes += _code_objects(obj)
    wanted = set(codes)
    lines = {(c.co_filename, line) for c in codes for _, _, line in c.co_lines()
             if line is not None and line != c.co_firstlineno}
    hit: set[tuple[str, int]] = set()

    def local(frame, event, arg):
        if event == "line":
            hit.add((frame.f_code.co_filename, frame.f_lineno))
        return local

    def tracer(frame, event, arg):
        return local if frame.f_code in wanted else None

    old = sys.gettrace()
    sys.settrace(tracer)
    try:
        for data in inputs:
            try:
                target.function(data)
            except Exception:  # a crash is reported by the replay; coverage counts what ran
                pass
    finally:
        sys.settrace(old)
    return len(lines & hit), len(lines)


# --- corpora -------------------------------------------------------------------------------------


def corpus_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file()) if folder.is_dir() else []


def write_seeds() -> int:
    """Add the seed inputs missing from tests/corpus/<target>/ and firmware/fuzz/corpus/<target>/
    (named by content); returns how many."""
    added = 0
    for folder, seeds in [*((PY_CORPUS / n, s) for n, s in python_seeds().items()),
                          *((FIRMWARE_CORPUS / n, s) for n, s in firmware_seeds().items())]:
        folder.mkdir(parents=True, exist_ok=True)
        for data in seeds:
            path = folder / f"seed-{hashlib.sha1(data).hexdigest()[:16]}"
            if not path.exists():
                path.write_bytes(data)
                added += 1
    return added


@dataclass
class Failure:
    target: str
    input: Path
    error: str


def replay_python(name: str, folder: Path | None = None) -> tuple[int, list[Failure]]:
    """Run a Python target on every file of its saved corpus; (inputs run, failures)."""
    fn = PY_TARGETS[name].function
    failures = []
    files = corpus_files(folder or PY_CORPUS / name)
    for path in files:
        try:
            fn(path.read_bytes())
        except Exception as exc:  # every exception is a finding
            failures.append(Failure(name, path, f"{type(exc).__name__}: {exc}"[:300]))
    return len(files), failures


# --- firmware targets ----------------------------------------------------------------------------


def build_firmware_fuzzers(build_dir: Path, jobs: int) -> dict[str, Path]:
    """``make -C firmware fuzz`` into build_dir; name -> binary for every fuzz-* built there."""
    result = subprocess.run(["make", "-C", str(FIRMWARE_DIR), f"-j{jobs}", f"BUILD={build_dir}", "fuzz"],
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit("fuzz_campaign: make -C firmware fuzz "
                         f"failed:\n{result.stdout[-3000:]}{result.stderr[-3000:]}")
    return firmware_fuzzers(build_dir)


def firmware_fuzzers(build_dir: Path) -> dict[str, Path]:
    return {p.name.removeprefix("fuzz-"): p for p in sorted(build_dir.glob("fuzz-*"))
            if p.is_file() and os.access(p, os.X_OK)}


# --- running libFuzzer (firmware binaries and atheris) --------------------------------------------


@dataclass
class Result:
    target: str
    kind: str
    executions: int = 0
    seconds: float = 0.0
    cov: int = 0
    ft: int = 0
    corpus: int = 0
    coverage: str = ""
    crashes: list[Path] = field(default_factory=list)
    note: str = ""


_STATS = re.compile(r"^#(\d+)\s+\w+\s+cov: (\d+) ft: (\d+)(?: corp: (\d+)/)?", re.M)
_DONE = re.compile(r"^Done (\d+) runs in (\d+) second", re.M)
_FUNC = re.compile(r"^(?:UN)?COVERED_FUNC: hits: \d+ edges: (\d+)/(\d+) .* (/\S+?):\d+$", re.M)


def parse_libfuzzer(log: str, result: Result) -> None:
    stats = _STATS.findall(log)
    if stats:
        last = stats[-1]
        result.cov, result.ft = int(last[1]), int(last[2])
        result.corpus = int(last[3]) if last[3] else result.corpus
        result.executions = max(result.executions, int(last[0]))
    done = _DONE.search(log)
    if done:
        result.executions = int(done.group(1))


def firmware_edge_coverage(log: str) -> str:
    """Edges covered / edges of the firmware core files the target reached (from -print_coverage)."""
    per_file: dict[str, list[int]] = {}
    for covered, total, path in _FUNC.findall(log):
        if "/src/core/" not in path:
            continue
        entry = per_file.setdefault(Path(path).name, [0, 0])
        entry[0] += int(covered)
        entry[1] += int(total)
    reached = {f: e for f, e in per_file.items() if e[0]}
    if not reached:
        return ""
    covered = sum(e[0] for e in reached.values())
    total = sum(e[1] for e in reached.values())
    return f"{covered}/{total} edges ({100 * covered / total:.0f}%) of core/{','.join(sorted(reached))}"


def run_libfuzzer(cmd: list[str], work: Path, saved: Path, runs: int, max_len: int, log_path: Path,
                  extra: list[str], result: Result, max_seconds: int | None) -> str:
    work.mkdir(parents=True, exist_ok=True)
    saved.mkdir(parents=True, exist_ok=True)
    artifacts = work.parent / f"{work.name}-artifacts"
    artifacts.mkdir(exist_ok=True)
    args = [*cmd, f"-runs={runs}", f"-max_len={max_len}", "-timeout=10", "-rss_limit_mb=2048",
            f"-artifact_prefix={artifacts}/", "-print_final_stats=1", *extra]
    if max_seconds:
        args.append(f"-max_total_time={max_seconds}")
    start = time.monotonic()
    with open(log_path, "w") as log:
        subprocess.run([*args, str(work), str(saved)], stdout=log, stderr=subprocess.STDOUT)
    result.seconds = time.monotonic() - start
    text = log_path.read_text(errors="replace")
    parse_libfuzzer(text, result)
    result.crashes = sorted(p for p in artifacts.iterdir() if p.name.startswith(CRASH_PREFIXES))
    return text


def merge_corpus(cmd: list[str], saved: Path, work: Path, crashes: list[Path], log_path: Path) -> None:
    """Keep the inputs of work/ that add coverage to saved/, and every crash input."""
    with open(log_path, "a") as log:
        subprocess.run([*cmd, "-merge=1", str(saved), str(work)], stdout=log, stderr=subprocess.STDOUT)
    for crash in crashes:
        shutil.copy(crash, saved / crash.name)


def atheris_worker(name: str, argv: list[str]) -> None:
    """Runs inside the subprocess: instrument the target's modules, then hand over to libFuzzer."""
    import importlib
    import logging

    import atheris

    logging.disable(logging.CRITICAL)  # the readers log every skipped row: keep the fuzzer's output readable
    target = PY_TARGETS[name]
    with atheris.instrument_imports(include=["cubetrack", "cubecam"]):
        for module in target.modules:
            importlib.import_module(module)
    atheris.Setup([sys.argv[0], *argv], target.function)
    atheris.Fuzz()


def run_python_target(name: str, runs: int, work_root: Path, save: bool, max_seconds: int | None) -> Result:
    result = Result(name, "python")
    try:
        import atheris  # noqa: F401
    except ImportError:
        result.note = "atheris is not installed (pip install atheris): replayed the corpus only"
        inputs, failures = replay_python(name)
        result.executions = inputs
        result.crashes = [f.input for f in failures]
        return result
    cmd = [sys.executable, str(Path(__file__).resolve()), "--atheris-worker", name, "--"]
    work = work_root / name
    log_path = work_root / f"{name}.log"
    run_libfuzzer(cmd, work, PY_CORPUS / name, runs, PY_TARGETS[name].max_len, log_path, [], result, max_seconds)
    inputs = [p.read_bytes() for p in corpus_files(work) + corpus_files(PY_CORPUS / name)]
    hit, total = line_coverage(name, inputs)
    result.coverage = f"{hit}/{total} lines ({100 * hit / max(total, 1):.0f}%)"
    if save:
        merge_corpus(cmd, PY_CORPUS / name, work, result.crashes, log_path)
    return result


def run_firmware_target(name: str, binary: Path, runs: int, work_root: Path, save: bool,
                        max_seconds: int | None) -> Result:
    result = Result(name, "firmware")
    work = work_root / f"fw-{name}"
    log_path = work_root / f"fw-{name}.log"
    text = run_libfuzzer([str(binary)], work, FIRMWARE_CORPUS / name, runs, FIRMWARE_MAX_LEN.get(name, 4096), log_path,
                         ["-print_coverage=1"], result, max_seconds)
    result.coverage = firmware_edge_coverage(text)
    if save:
        merge_corpus([str(binary)], FIRMWARE_CORPUS / name, work, result.crashes, log_path)
    return result


def replay_firmware(name: str, binary: Path, work_root: Path) -> Result:
    """Every saved input of a firmware target once (libFuzzer -runs=0)."""
    result = Result(name, "firmware")
    saved = FIRMWARE_CORPUS / name
    result.corpus = len(corpus_files(saved))
    if not result.corpus:
        result.note = f"no saved corpus in {saved.relative_to(REPO)}"
        return result
    artifacts = work_root / f"fw-{name}-artifacts"
    artifacts.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    proc = subprocess.run([str(binary), "-runs=0", "-timeout=10", "-rss_limit_mb=2048",
                           f"-artifact_prefix={artifacts}/", str(saved)], capture_output=True, text=True)
    result.seconds = time.monotonic() - start
    parse_libfuzzer(proc.stderr, result)
    result.executions = result.corpus
    result.crashes = sorted(p for p in artifacts.iterdir() if p.name.startswith(CRASH_PREFIXES))
    if proc.returncode != 0 and not result.crashes:
        result.note = f"exit status {proc.returncode}: {proc.stderr.strip().splitlines()[-1:]}"
    return result


def replay_python_result(name: str) -> Result:
    """Every saved input of a Python target once, in this process, with its line coverage."""
    start = time.monotonic()
    inputs, failures = replay_python(name)
    result = Result(name, "python", inputs, time.monotonic() - start, corpus=inputs,
                    crashes=[f.input for f in failures])
    hit, total = line_coverage(name, [p.read_bytes() for p in corpus_files(PY_CORPUS / name)])
    result.coverage = f"{hit}/{total} lines ({100 * hit / max(total, 1):.0f}%)"
    for f in failures:
        print(f"    {f.input.name}: {f.error}", file=sys.stderr)
    return result


def print_table(results: list[Result], out=sys.stdout) -> None:
    print(f"{'target':14} {'kind':8} {'executions':>12} {'time s':>8} {'exec/s':>8} {'cov':>6} {'ft':>6} "
          f"{'corpus':>6} {'crashes':>7}  coverage", file=out)
    for r in results:
        rate = r.executions / r.seconds if r.seconds > 0 else 0.0
        print(f"{r.target:14} {r.kind:8} {r.executions:12d} {r.seconds:8.1f} {rate:8.0f} {r.cov:6d} {r.ft:6d} "
              f"{r.corpus:6d} {len(r.crashes):7d}  {r.coverage}{'  ' + r.note if r.note else ''}", file=out)
        for crash in r.crashes:
            print(f"    crash input: {crash}", file=out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--atheris-worker"]:
        atheris_worker(argv[1], argv[3:])
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--only", metavar="LIST", help="comma list of targets (default: all; see --list)")
    p.add_argument("--skip-firmware", action="store_true", help="only the Python targets")
    p.add_argument("--skip-python", action="store_true", help="only the firmware targets")
    p.add_argument("--python-runs", type=int, default=1_000_000, metavar="N",
                   help="executions per Python target (default 1e6)")
    p.add_argument("--firmware-runs", type=int, default=10_000_000, metavar="N",
                   help="executions per firmware target (default 1e7)")
    p.add_argument("--max-seconds", type=int, metavar="S", help="stop each target after S seconds as well")
    p.add_argument("--build-dir", type=Path, default=FIRMWARE_DIR / "build", metavar="DIR",
                   help="where make builds the firmware fuzzers (default firmware/build)")
    p.add_argument("--work", type=Path, metavar="DIR", help="working corpora and logs (default: a new "
                                                            "temporary folder)")
    p.add_argument("--save", action="store_true", help="merge new coverage and crash inputs into the saved corpora")
    p.add_argument("--replay", action="store_true", help="only run every saved input once (what CI does)")
    p.add_argument("--seed", action="store_true", help="add the seed inputs to the saved corpora and exit")
    p.add_argument("--jobs", type=int, default=1, help="make -j (default 1)")
    p.add_argument("--parallel", type=int, default=1, metavar="N", help="run N campaigns at once (default 1)")
    p.add_argument("--list", action="store_true", help="list the targets and exit")
    args = p.parse_args(argv)

    if args.seed:
        print(f"fuzz_campaign: {write_seeds()} seed input(s) added")
        return 0
    firmware: dict[str, Path] = {}
    if not args.skip_firmware:
        if shutil.which("clang++") is None:
            print("fuzz_campaign: clang++ is not installed: firmware targets skipped", file=sys.stderr)
        else:
            print(f"fuzz_campaign: building the firmware fuzzers in {args.build_dir} ...", file=sys.stderr, flush=True)
            firmware = build_firmware_fuzzers(args.build_dir.resolve(), args.jobs)
    python = [] if args.skip_python else list(PY_TARGETS)
    if set(python) & set(firmware):
        raise SystemExit(f"fuzz_campaign: {', '.join(sorted(set(python) & set(firmware)))}: a Python and a firmware "
                         "target of the same name; rename the Python one in PY_TARGETS")
    if args.list:
        print("python:   " + " ".join(python))
        print("firmware: " + " ".join(firmware))
        return 0
    if args.only:
        wanted = set(args.only.split(","))
        unknown = wanted - set(python) - set(firmware)
        if unknown:
            p.error(f"unknown target(s) {', '.join(sorted(unknown))}; --list shows them")
        python = [n for n in python if n in wanted]
        firmware = {n: b for n, b in firmware.items() if n in wanted}
    work_root = args.work or Path(tempfile.mkdtemp(prefix="cubetrack-fuzz-campaign-"))
    work_root.mkdir(parents=True, exist_ok=True)
    print(f"fuzz_campaign: {os.cpu_count()} core(s); logs and working corpora in {work_root}", file=sys.stderr)
    jobs = []
    for name in python:
        if args.replay:
            jobs.append(functools.partial(replay_python_result, name))
        else:
            jobs.append(functools.partial(run_python_target, name, args.python_runs, work_root, args.save,
                                          args.max_seconds))
    for name, binary in firmware.items():
        if args.replay:
            jobs.append(functools.partial(replay_firmware, name, binary, work_root))
        else:
            jobs.append(functools.partial(run_firmware_target, name, binary, args.firmware_runs, work_root, args.save,
                                          args.max_seconds))

    def run(job) -> Result:
        name = job.args[0]
        print(f"fuzz_campaign: {name} ...", file=sys.stderr, flush=True)
        result = job()
        print(f"fuzz_campaign: {name}: {result.executions} executions in {result.seconds:.0f} s, "
              f"{len(result.crashes)} crash(es)", file=sys.stderr, flush=True)
        return result

    with ThreadPoolExecutor(max(1, args.parallel)) as pool:  # each campaign is a subprocess
        results = list(pool.map(run, jobs))
    print_table(results)
    return 1 if any(r.crashes for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
