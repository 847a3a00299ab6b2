"""benchmarks/accuracy.py --body calibrates the body out of sample: from a copy of the longer
render holding only the frames after the scored session (``later_part``). Here: no frame of the
session survives the cut, every later frame does, byte for byte, with every /time round trip and
the camera_info files."""

import runpy
from pathlib import Path

from cubetrack.core.cameras import ClockSample
from cubetrack.io.recording import CameraEntry, Recording, RecordingWriter

BENCHMARK = Path(__file__).resolve().parents[3] / "benchmarks" / "accuracy.py"
START_S = 1_750_000_000.0


def test_the_drive_after_the_session_keeps_no_frame_of_the_session(tmp_path):
    src = tmp_path / "drive"
    with RecordingWriter(src, [CameraEntry("cam1"), CameraEntry("cam2")]) as w:
        for cam, phase in (("cam1", 0.0), ("cam2", 0.05)):
            for seq in range(40):  # 7.5 fps for 5.3 s; arrival 60 ms after capture
                capture = START_S + phase + seq / 7.5
                w.add_frame(cam, seq, 100.0 + capture - START_S, capture + 0.06, f"{cam}-{seq}".encode())
            for k in range(5):
                w.add_clock_sample(cam, ClockSample(START_S + k, 100.0 + k + 0.004, START_S + k + 0.008))
            w.camera_info_path(cam).write_text(f"{cam} intrinsics", encoding="utf-8")
    session_end = START_S + 3.0

    later_part = runpy.run_path(str(BENCHMARK))["later_part"]
    out = later_part(src, tmp_path / "after", session_end)

    after = Recording.open(out)
    assert after.camera_names == ("cam1", "cam2")
    for cam in after.camera_names:
        kept = list(after.frames(cam))
        want = [f for f in Recording.open(src).frames(cam) if f.host_time_s >= session_end + 1.0]
        assert kept and [(f.seq, f.jpeg) for f in kept] == [(f.seq, f.jpeg) for f in want]
        assert min(f.host_time_s - 0.06 for f in kept) > session_end  # captured after the session
        assert after.clock_samples(cam) == Recording.open(src).clock_samples(cam)
        assert after.camera_info_path(cam).read_text(encoding="utf-8") == f"{cam} intrinsics"
