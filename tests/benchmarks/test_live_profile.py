"""benchmarks/live_profile.py's reading of py-spy's samples (the run itself needs py-spy, not a
dependency): each process's stacks by part, waits left out, and a system call at the leaf counted
where it belongs, not in the module that made it."""

from tests.helpers.benchmarks import load_benchmark

MAIN = 'process 10:"python -m cubetrack.cli.main track"'
WORKER = 'process 11:"python -c spawn_main"'


def stack(*frames: str) -> str:
    return ";".join(frames)


def test_samples_are_counted_by_process_and_part(tmp_path):
    profile = load_benchmark("live_profile")
    raw = tmp_path / "raw.txt"
    raw.write_text("\n".join([
        stack(MAIN, "thread (10): MainThread", "Session.run (cubetrack/app/session.py:152)",
              "CameraProcesses.take (cubetrack/app/camera_workers.py:154)",
              "PipePoll.ready (cubetrack/core/pipes.py:65)")
        + " 40",
        stack(MAIN, "thread (10): MainThread", "FilterFusion.add (cubetrack/fuse/fusion.py:408)",
              "PoseFilter._solve (cubetrack/fuse/corner_filter.py:342)") + " 7",
        stack(MAIN, WORKER, "thread (11): MainThread", "work_cameras (cubetrack/app/camera_workers.py:340)",
              "send_plain (cubetrack/app/camera_workers.py:354)",
              "Connection._send (multiprocessing/connection.py:384)")
        + " 3",
        stack(MAIN, WORKER, "thread (11): MainThread", "Detector.find (cubetrack/detect/detector.py:472)",
              "decode_gray (cubetrack/detect/decode.py:60)", "_turbo_gray (cubetrack/detect/decode.py:76)") + " 5",
    ]) + "\n")
    counts = profile.samples(raw)
    assert counts[10] == {"waiting": 40, "fusion": 7}
    assert counts[11] == {"pipes: send (syscall)": 3, "decode": 5}
