"""The demo's cameras: ``cubecam emulate`` in its own process, found through its ready file."""

import json

import pytest
import requests

from cubecam.testdata import CameraSpec, write_recording
from cubetrack.app.emulated import EmulatedCameras
from cubetrack.core.errors import SourceError


def test_serves_a_recording_and_reports_urls_and_clock(tmp_path):
    rec = write_recording(tmp_path / "rec", [CameraSpec("cam1")], frames=20, fps=10.0)
    with EmulatedCameras(rec) as emu:
        assert set(emu.urls) == {"cam1"}
        assert emu.urls["cam1"].startswith("http://127.0.0.1:")
        status = requests.get(emu.urls["cam1"].removesuffix("stream") + "status", timeout=5)
        assert status.status_code == 200 and "frames" in json.dumps(status.json())
        assert 1.5 < emu.period_s < 2.5
        assert emu.wait_finished(10.0)


def test_an_emulator_that_cannot_start_is_a_one_line_error(tmp_path):
    with pytest.raises(SourceError, match=r"exited \(1\) before serving: .*"):
        with EmulatedCameras(tmp_path / "no-such-recording"):
            pass
