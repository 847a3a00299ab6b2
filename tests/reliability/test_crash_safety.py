"""Crash safety (issue 12, item 3): `cubetrack record` and `cubetrack track --live --record`,
reading cameras served by the emulator over real HTTP on 127.0.0.1, are killed with SIGKILL at
random moments (while starting, and at random times after their first frame or pose is on
disk). After every kill the recording folder opens with Recording.open and reads back whole
(every indexed frame is a whole JPEG, no broken row), the trajectory files (TUM and JSONL) hold
whole lines that parse, and at most the frame or pose in flight is missing (a JPEG stored
without its index row, a TUM line without its JSONL line). A full disk (a small tmpfs; the test
skips where mounting is not permitted) ends either command with a one-line error, exit status 1
and readable files."""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cubecam.emulator import Emulator
from cubetrack.app.demo import write_live_config
from cubetrack.cli.main import main
from cubetrack.core.errors import RecordingError
from cubetrack.io.recording import Recording
from cubetrack.io.trajectory import read_tum

pytestmark = pytest.mark.slow

TRIAL_PAIRS = 10  # each: one `record` and one `track --live --record` run at once, killed independently
KILLS_WHILE_STARTING = 2  # of those pairs, killed at a random moment of their start (before any frame)
START_TIMEOUT_S = 60.0  # for the first frame or pose on disk, on a loaded machine
SOI, EOI = b"\xff\xd8", b"\xff\xd9"


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A 3 s, 2-camera simulated session looped by the emulator; a live config reading it and
    the simulation's true camera poses (no calibration needed)."""
    work = tmp_path_factory.mktemp("crash")
    rec = work / "rec"
    assert main(["simulate", "--out", str(rec), "--cameras", "2", "--duration", "3", "--fps", "10",
                 "--calibration-frames", "0", "--seed", "3"]) == 0
    with Emulator(rec, host="127.0.0.1", port=0, loop=True) as emu:
        config = write_live_config(rec / "config.toml", emu.urls, work / "live.toml")
        yield config, rec / "true_extrinsics.toml"


def _cubetrack(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cubetrack.cli.main", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _has_rows(path: Path, rows: int) -> bool:
    try:
        return path.read_bytes().count(b"\n") >= rows
    except FileNotFoundError:
        return False


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)


def _whole_lines(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8")
    assert text == "" or text.endswith("\n"), f"{path}: torn last line {text[-80:]!r}"
    return text.splitlines()


def check_recording(folder: Path) -> tuple[int, int]:
    """The folder a killed recorder left reads back whole; returns the frames it holds and the
    frames that were in flight (a JPEG or its .part on disk, not in the index yet)."""
    jpegs = sorted(folder.rglob("*.jpg")) if folder.exists() else []
    if not (folder / "recording.json").exists():  # killed before the folder was set up: nothing recorded
        assert not jpegs, f"{folder}: frames without recording.json"
        return 0, 0
    recording = Recording.open(folder)
    frames = lost = 0
    for camera in recording.camera_names:
        cam_dir = folder / camera
        _whole_lines(cam_dir / "index.csv")
        try:
            rows = recording.index(camera)
        except RecordingError as exc:  # no frame of this camera yet: at most the one in flight is on disk
            assert "empty index" in str(exc)
            rows = []
        listed = {row.file for row in rows}
        in_flight = [p.name for p in cam_dir.iterdir() if p.suffix in (".jpg", ".part") and p.name not in listed]
        assert len(in_flight) <= 1, f"{cam_dir}: files not in the index: {in_flight}"
        got = list(recording.frames(camera))
        assert len(got) == len(rows)
        assert all(f.jpeg.startswith(SOI) and f.jpeg.endswith(EOI) for f in got)
        assert [f.seq for f in got] == sorted({f.seq for f in got})
        if (cam_dir / "clock.csv").exists():
            _whole_lines(cam_dir / "clock.csv")
            recording.clock_samples(camera)
        frames += len(got)
        lost += len(in_flight)
    assert not recording.skipped, recording.skipped
    return frames, lost


def check_trajectory(out: Path, robot: str = "robot") -> tuple[int, int]:
    """The pose files a killed tracker left hold whole lines that parse, the JSONL at most the
    pose in flight behind the TUM; returns the poses in the JSONL and the poses in flight (0 or 1)."""
    tum_path, jsonl_path = out / f"{robot}.tum", out / f"{robot}.jsonl"
    if not tum_path.exists():
        assert not jsonl_path.exists()
        return 0, 0
    tum = _whole_lines(tum_path)
    jsonl = [json.loads(line) for line in _whole_lines(jsonl_path)] if jsonl_path.exists() else []
    assert len(tum) - len(jsonl) in (0, 1), (len(tum), len(jsonl))
    if tum:
        times = read_tum(tum_path).times_s
        assert len(times) == len(tum)
        assert sorted(float(line.split()[0]) for line in tum[:len(jsonl)]) == pytest.approx(
            sorted(pose["time"] for pose in jsonl), abs=2e-6)
    return len(jsonl), len(tum) - len(jsonl)


def test_sigkill_at_random_moments_leaves_readable_recordings_and_trajectories(served, tmp_path):
    config, extrinsics = served
    rng = random.Random(12)
    frames, poses = [0, 0], [0, 0]  # read back, in flight
    after_first_write = 0
    for trial in range(TRIAL_PAIRS):
        rec_out, live_out, live_rec = tmp_path / f"rec{trial}", tmp_path / f"live{trial}", tmp_path / f"lrec{trial}"
        recorder = _cubetrack("record", "--config", str(config), "--out", str(rec_out))
        tracker = _cubetrack("track", "--config", str(config), "--extrinsics", str(extrinsics), "--live",
                             "--out", str(live_out), "--record", str(live_rec))
        try:
            if trial < KILLS_WHILE_STARTING:  # somewhere in the start: imports, config, folders, connections
                time.sleep(rng.uniform(0.0, 1.5))
                _kill(recorder)
                _kill(tracker)
                continue
            deadline = time.monotonic() + START_TIMEOUT_S
            pending = {"record": (recorder, rec_out / "cam1" / "index.csv", 2),
                       "track": (tracker, live_out / "robot.jsonl", 1)}
            kill_at = {}
            while pending and time.monotonic() < deadline:
                for name, (proc, path, rows) in list(pending.items()):
                    assert proc.poll() is None, f"{name} exited early: {proc.communicate()[1][-2000:]}"
                    if _has_rows(path, rows):  # first frame/pose on disk: kill within the next second
                        kill_at[name] = time.monotonic() + rng.uniform(0.0, 1.0)
                        del pending[name]
                time.sleep(0.02)
            assert not pending, f"no frame or pose on disk within {START_TIMEOUT_S:.0f} s: {sorted(pending)}"
            for name in sorted(kill_at, key=kill_at.get):
                time.sleep(max(0.0, kill_at[name] - time.monotonic()))
                _kill(recorder if name == "record" else tracker)
            after_first_write += 1
        finally:
            for proc in (recorder, tracker):
                if proc.poll() is None:
                    proc.kill()
                    proc.communicate()
        assert recorder.returncode == -signal.SIGKILL and tracker.returncode == -signal.SIGKILL
        for counts, found in ((frames, check_recording(rec_out)), (frames, check_recording(live_rec)),
                              (poses, check_trajectory(live_out))):
            counts[0] += found[0]
            counts[1] += found[1]
    print(f"{2 * TRIAL_PAIRS} kills ({2 * after_first_write} after the first write): {frames[0]} frames "
          f"({frames[1]} in flight) and {poses[0]} poses ({poses[1]} in flight) read back")
    assert after_first_write == TRIAL_PAIRS - KILLS_WHILE_STARTING
    assert frames[0] >= 2 * after_first_write and poses[0] >= after_first_write


@pytest.fixture
def small_disk(tmp_path):
    """A 256 kB tmpfs at tmp_path/disk (we run as root in CI; skipped where mounting is not allowed)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command: cannot make a small file system to fill")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
                          check=False, capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"mounting a tmpfs is not permitted here ({done.stderr.strip() or done.returncode}): "
                    "the full-disk test needs root")
    yield disk
    subprocess.run(["umount", "-l", str(disk)], check=False)


def _fill(disk: Path, leave_bytes: int) -> None:
    """Fill the file system but for about ``leave_bytes``."""
    free = shutil.disk_usage(disk).free
    (disk / "filler").write_bytes(b"\0" * max(0, free - leave_bytes))


def _one_line_disk_full_error(proc: subprocess.Popen, command: str) -> str:
    """Waits for ``proc`` to give up; returns its error line."""
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1, err
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"cubetrack {command}: error: ") and "No space left on device" in last, err
    return last


def test_a_full_disk_ends_record_with_one_line_and_a_readable_recording(served, small_disk):
    config, _ = served
    out = small_disk / "rec"
    proc = _cubetrack("record", "--config", str(config), "--out", str(out), "--duration", "60")
    assert f"{out}{os.sep}cam" in _one_line_disk_full_error(proc, "record")
    assert check_recording(out)[0] >= 2  # 256 kB hold several 22 kB frames


def test_a_full_disk_ends_track_with_one_line_and_whole_pose_lines(served, small_disk):
    config, extrinsics = served
    out = small_disk / "out"
    proc = _cubetrack("track", "--config", str(config), "--extrinsics", str(extrinsics), "--live",
                      "--out", str(out), "--duration", "60")
    deadline = time.monotonic() + START_TIMEOUT_S
    while not (out / "run.json").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    _fill(small_disk, 8 * 1024)  # once the run record is written: a page for each pose file
    assert "robot.tum" in (last := _one_line_disk_full_error(proc, "track")) or "robot.jsonl" in last
    assert check_trajectory(out)[0] >= 1


def test_a_line_the_file_system_cannot_take_whole_is_cut_off_again(tmp_path):
    """A write cut short (here by a file size limit, as a full disk cuts it) leaves no torn line."""
    path = tmp_path / "rows.csv"
    code = ("import resource, signal, sys\n"
            "from cubetrack.io.files import LineFile\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (100, resource.RLIM_INFINITY))\n"
            "f = LineFile(sys.argv[1], 'header')\n"
            "for i in range(10):\n"
            "    try:\n"
            "        f.write_line(f'{i:02d},' + 'x' * 26)\n"
            "    except OSError as exc:\n"
            "        print(i, exc.errno)\n"
            "        break\n")
    done = subprocess.run([sys.executable, "-c", code, str(path)], check=True, capture_output=True, text=True)
    assert done.stdout.split()[0] == "3"  # 7 + 3 x 30 bytes fit in 100, the fourth line only in part
    assert path.read_text() == "header\n" + "".join(f"{i:02d}," + "x" * 26 + "\n" for i in range(3))


def test_an_unfinished_last_index_row_is_skipped_and_counted(tmp_path):
    from cubetrack.io.recording import CameraEntry, RecordingWriter

    with RecordingWriter(tmp_path / "rec", [CameraEntry("cam1")]) as writer:
        for seq in (1, 2):
            writer.add_frame("cam1", seq, seq * 0.1, 1000.0 + seq * 0.1, SOI + b"jpeg" + EOI)
    index = tmp_path / "rec" / "cam1" / "index.csv"
    with index.open("a") as f:
        f.write("3,0.300000,1000.300000,0000")  # cut inside the file name: four fields, no line end
    recording = Recording.open(tmp_path / "rec")
    assert [row.seq for row in recording.index("cam1")] == [1, 2]
    assert recording.skipped == {"unfinished last row": 1}
