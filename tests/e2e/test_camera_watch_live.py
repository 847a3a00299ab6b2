"""The camera watching live (issue 27), end to end: four emulated cameras replaying a simulated
lap over real sockets and real JPEGs, `cubetrack track --live --dashboard` as its own process with
`[camera_watch] enabled`, the page in headless Chromium. Once every camera is watched (it has a
settled pose), the emulator knocks cam2 on its tripod (`cubecam.bump`: a 1.5 degree pan, its frames
resampled from then on); cam2's tile goes moved -> re-calibrating -> rejoined, no other tile
leaves watched, and the session keeps the event and the new pose (camera_watch.jsonl,
extrinsics.watch-1.toml), the new pose within 0.3 degrees of the bump. A short CI run (issue 27's
seventh session: 27.2 -> 17.0 s at load 3, 35 -> 28 s at load 11): every sighting checked (`samples_per_s` above the
cameras' rate), a 1 s window checked every 0.25 s, settled poses refitted every half second, and
the re-calibration asks less than a lab's defaults (150 corners; its fit known to 5 mm / 0.15 deg at
the corner noise assumed, its sightings' spread the default 5 mm / 0.15 deg); the scene renders on
both cores while Chromium starts."""

from __future__ import annotations

import json
import signal
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from cubecam.bump import Bump
from cubecam.emulator import Emulator
from cubetrack.app.demo import write_live_config
from cubetrack.core.geometry import rotation_angle
from cubetrack.io.config import read_extrinsics
from tests.e2e.test_dashboard import Browser, api, cubetrack
from tests.helpers.scene import simulated_recording

pytestmark = pytest.mark.slow

BUMP_DEG = 1.5
WATCH = """
[camera_watch]
enabled = true
samples_per_s = 15.0
window_s = 1.0
check_every_s = 0.25
min_points = 20
baseline_every_s = 0.5
settle_span_s = 2.0
rejoin_points = 150
rejoin_sigma_m = 0.005
rejoin_sigma_deg = 0.15
"""
# every change of a tile's data-watch, as the page saw it (a state shown for one event is kept too)
TRAIL = """window.watchTrail = {};
new MutationObserver((changes) => {
  for (const c of changes) {
    const cam = c.target.dataset.camera, now = c.target.dataset.watch;
    const trail = (window.watchTrail[cam] = window.watchTrail[cam] || []);
    if (now && trail[trail.length - 1] !== now) trail.push(now);
  }
}).observe(document, { subtree: true, attributes: true, attributeFilter: ["data-watch"] });"""


def test_a_bumped_camera_goes_moved_recalibrating_rejoined_on_its_tile(tmp_path):
    took = {"start": time.monotonic()}
    browser = Browser(tmp_path / "profile")  # Chromium starts while the scene renders
    try:
        trail, shown, camera, track, out, rec = _bumped_live_session(tmp_path, browser, took)
    finally:
        browser.close()  # (again: a second close does nothing)
    lines = "".join(track.lines)
    print("tile trails:", trail, "| re-calibrating tile said:", shown, "| s since start:",
          {k: round(v - took["start"], 1) for k, v in took.items()})
    cam2 = trail["cam2"]
    moved = cam2.index("moved")  # suspect (out of the fusion) first, as a rule: the first checks after the bump
    assert cam2[:2] == ["settling", "watched"] and set(cam2[2:moved]) <= {"suspect", "watched"}, cam2
    assert cam2[moved + 1] == "re-calibrating", cam2
    assert cam2.index("rejoined") > moved + 1 and "corners gathered" in shown, (cam2, shown)
    # never judged moved; suspect for a moment while cam2 was off is allowed, also when the trails are read (at
    # cam2's rejoin: a spell begun while cam2 was away can still be on; seen at load 10-14, cam2 rejoined at 1.45 deg)
    for other in ("cam1", "cam3", "cam4"):
        assert "moved" not in trail[other] and trail[other][-1] in ("watched", "suspect"), trail
    assert camera["watch"]["state"] in ("rejoined", "watched")
    events = [json.loads(x) for x in (out / "camera_watch.jsonl").read_text().splitlines()]
    assert [(e["event"], e["camera"]) for e in events] == [("moved", "cam2"), ("rejoined", "cam2")], events
    # the new pose is the old one turned by the bump (the emulator turns the camera about its optical centre)
    old = read_extrinsics(rec / "true_extrinsics.toml")["cam2"].T_world_cam
    new = read_extrinsics(out / events[1]["extrinsics"])["cam2"].T_world_cam
    turn = rotation_angle(old[:3, :3], new[:3, :3], unit="deg")
    assert abs(turn - BUMP_DEG) < 0.3 and np.linalg.norm(new[:3, 3] - old[:3, 3]) < 0.02, (turn, new, old)
    assert "cam2 moved" in lines and "re-calibrated from" in lines


def _bumped_live_session(tmp_path: Path, browser: Browser, took: dict[str, float]) -> tuple:
    """Render the scene, serve it from the emulator, track it live with the dashboard open in
    ``browser``; once every tile says watched, bump cam2 and wait for its tile to say rejoined;
    end the session by Ctrl-C. Returns the tiles' trails, what the re-calibrating tile said,
    cam2 from /api/cameras, the track process, its output folder and the recording."""
    rec = simulated_recording(tmp_path / "rec", 10.0, seed=5, cameras=4, workers=2)  # both cores: CI time
    took["simulated"] = time.monotonic()
    with Emulator(rec, loop=True) as emu:
        config = write_live_config(rec / "config.toml", emu.urls, tmp_path / "lab.toml")
        with config.open("a", encoding="utf-8") as f:
            f.write(WATCH)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        out = tmp_path / "out"
        track = cubetrack("track", "--config", str(config), "--extrinsics", str(rec / "true_extrinsics.toml"),
                          "--live", "--out", str(out), "--duration", "600", "--dashboard", f"127.0.0.1:{port}",
                          cwd=tmp_path)  # --duration: a hang guard; Ctrl-C ends it
        try:
            url = track.wait_line(r"output: dashboard: (http://127\.0\.0\.1:\d+/)").group(1)
            browser.serving = track.proc
            browser.call("Page.addScriptToEvaluateOnNewDocument", source=TRAIL)
            browser.goto(url)
            took["page"] = time.monotonic()
            # limits only against a hang: each wait is on what the page shows
            browser.wait_for("['cam1', 'cam2', 'cam3', 'cam4'].every(c => (t => t && t.dataset.watch === 'watched')"
                             "(document.querySelector(`.tile[data-camera=${c}]`)))", 60)
            took["watched"] = time.monotonic()
            emu.bump(Bump("cam2", BUMP_DEG))
            browser.wait_for("document.querySelector('.tile[data-camera=cam2]').dataset.watch === 're-calibrating'", 30)
            shown = browser.eval("document.querySelector('.tile[data-camera=cam2] .watch').textContent")
            browser.wait_for("['rejoined', 'watched'].includes(document.querySelector('.tile[data-camera=cam2]')"
                             ".dataset.watch) && window.watchTrail.cam2.includes('rejoined')", 60)
            took["rejoined"] = time.monotonic()
            trail = browser.eval("window.watchTrail")
            browser.screenshot(tmp_path / "dashboard-camera-watch.png")
            assert browser.errors == []
            camera = api(url, "/api/cameras/cam2")
        finally:
            browser.close()  # before Ctrl-C, as a user closes the page (track has exited -6 with the page open)
            track.proc.send_signal(signal.SIGINT)  # Ctrl-C: the session ends, what it learnt is kept
            code = track.proc.wait(60)
    took["ended"] = time.monotonic()
    assert code == 0, "".join(track.lines)[-3000:]
    return trail, shown, camera, track, out, rec
