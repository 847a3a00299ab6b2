"""The dashboard end to end: `cubetrack dashboard` and `track --live --dashboard` as their own
processes, reading emulated cameras (`cubecam emulate`, the firmware's HTTP API) over real
sockets, one camera nobody listens on and one whose stream stalls; the page driven in headless
Chromium over the DevTools protocol (a real browser running the page's JavaScript): the tiles,
the red cameras and their reasons, the top view, every calibration step (check, collect, results
with advice, save, drive, refine, save), recording a session and downloading its trajectory.

Screenshots are taken at each step (into the test's folder; with CUBETRACK_SCREENSHOTS=DIR also
into DIR: docs/img holds the ones docs/dashboard.md shows)."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import requests

from cubetrack.app.demo import write_live_config
from cubetrack.calib.extrinsics import extrinsics_errors
from cubetrack.cli.main import main
from cubetrack.io.config import read_extrinsics
from cubetrack.io.recording import Recording
from cubetrack.io.trajectory import read_tum

pytestmark = pytest.mark.slow

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
if CHROMIUM is None:
    pytest.skip("Chromium is not installed (Debian package chromium)", allow_module_level=True)
websocket = pytest.importorskip("websocket", reason="websocket-client is a test extra")

# One lap of the robot's path takes the whole recording (3.0 m at 0.4 m/s); the rectangle keeps
# the robot off the world marker. The looping emulator's period is a little longer than the
# recording (the last frame's interval and the cameras' phases: 7.53 s), so the lab fixture
# slows the robot until a lap takes exactly that period: otherwise the robot jumps 2 cm at each
# loop, and a drive across that seam makes the bundle adjustment move correct cameras by cm.
DURATION_S, SPEED_M_S = 7.48, 0.4


def simulation(speed_m_s: float) -> list[str]:
    return ["--duration", str(DURATION_S), "--speed", f"{speed_m_s:.6f}", "--path", "rectangle", "--path-size",
            "0.5", "0.35", "--calibration-frames", "1", "--seed", "3", "--force"]

REFUSED_URL = "http://127.0.0.1:9/stream"  # the discard port: nobody listens
SAMPLES = 12


class Browser:
    """Headless Chromium driven over the Chrome DevTools protocol (a WebSocket)."""

    def __init__(self, profile: Path, width: int = 1400, height: int = 1000):
        profile.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-dev-shm-usage", f"--user-data-dir={profile}", "--remote-debugging-port=0",
             "--remote-debugging-address=127.0.0.1", f"--window-size={width},{height}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port_file = profile / "DevToolsActivePort"
            deadline = time.monotonic() + 60
            while not (port_file.exists() and port_file.read_text().strip()):
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("Chromium did not start its DevTools server")
                time.sleep(0.05)
            port = int(port_file.read_text().split()[0])
            pages = requests.get(f"http://127.0.0.1:{port}/json/list", timeout=10).json()
            page = next(t for t in pages if t["type"] == "page")
            self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=60, suppress_origin=True)
        except BaseException:
            self.proc.kill()
            self.proc.wait()
            raise
        self.next_id = 0
        self.errors: list[str] = []
        self.serving: subprocess.Popen | None = None  # the server the page talks to: a wait ends if it exits
        self.call("Runtime.enable")
        self.call("Page.enable")
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def call(self, method: str, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("method") == "Runtime.exceptionThrown":  # an error in the page's JavaScript
                details = msg["params"]["exceptionDetails"]
                self.errors.append(details.get("exception", {}).get("description") or details.get("text", ""))
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def goto(self, url: str) -> None:
        self.call("Page.navigate", url=url)
        self.wait_for("document.readyState === 'complete'")

    def eval(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0):
        deadline = time.monotonic() + timeout_s
        while not (value := self.eval(expression)):
            if self.serving is not None and self.serving.poll() is not None:
                raise AssertionError(f"the server exited ({self.serving.returncode}) while waiting for {expression}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"waited {timeout_s:.0f} s for {expression}")
            time.sleep(0.1)
        return value

    def click(self, selector: str) -> None:
        self.wait_for(f"(b => b && !b.disabled)(document.querySelector({selector!r}))")
        self.eval(f"document.querySelector({selector!r}).click()")

    def screenshot(self, path: Path) -> None:
        """The page as it is once every streaming camera's tile shows its frame (the shots in
        docs/ show the tiles as a user sees them a moment after opening the page). Not "every
        image complete": a tile asks for its next frame as soon as one has loaded, so on a busy
        machine some tile is always loading its next one, while showing the last. A hang guard,
        not a speed check: at a load of 26 on two cores a tile took over 15 s."""
        try:
            self.wait_for("[...document.querySelectorAll('.tile[data-status=ok] .frame img')]"
                          ".every(i => !i.hidden && i.naturalWidth > 0)", 60)
        except TimeoutError as exc:  # say which tile, and in what state, so a failure can be traced
            tiles = self.eval("[...document.querySelectorAll('.tile')].map(t => { const i = t.querySelector('img'); "
                              "return [t.dataset.camera, t.dataset.status, i.hidden, i.naturalWidth, i.complete, "
                              "i.dataset.loading, i.dataset.src, t.dataset.frame]; })")
            raise TimeoutError(f"{exc}; tiles (camera, status, hidden, naturalWidth, complete, loading, src, "
                               f"newest): {tiles}") from None
        data = self.call("Page.captureScreenshot", format="png", captureBeyondViewport=True)["data"]
        path.write_bytes(base64.b64decode(data))
        if os.environ.get("CUBETRACK_SCREENSHOTS"):
            shutil.copyfile(path, Path(os.environ["CUBETRACK_SCREENSHOTS"]) / path.name)

    def close(self) -> None:
        with contextlib.suppress(OSError, RuntimeError, websocket.WebSocketException):
            self.call("Browser.close")  # the browser may close the socket before it answers
        self.ws.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


class Process:
    """A command in its own process; stderr collected by a thread (it never blocks on a full pipe)."""

    def __init__(self, args: list[str], cwd: Path):
        self.proc = subprocess.Popen(args, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self.reader.start()

    def wait_line(self, pattern: str, timeout_s: float = 60.0) -> re.Match:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for line in list(self.lines):
                if m := re.search(pattern, line):
                    return m
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f"no line matching {pattern!r}:\n{''.join(self.lines)[-3000:]}")

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        code = self.proc.wait()
        self.reader.join(5)
        return code


def emulator(work: Path, *source: str) -> tuple[Process, dict]:
    """`cubecam emulate ... --loop` on 127.0.0.1 (ephemeral ports): the process and what it
    serves (its ready file: urls, period_s, clock_shift_s)."""
    ready = work / f"ready-{len(list(work.glob('ready-*')))}.json"
    proc = Process([sys.executable, "-m", "cubecam", "emulate", *source, "--bind", "127.0.0.1", "--port", "0",
                    "--loop", "--ready-file", str(ready)], work)
    deadline = time.monotonic() + 60
    while not ready.exists():
        assert proc.proc.poll() is None and time.monotonic() < deadline, "".join(proc.lines)
        time.sleep(0.05)
    time.sleep(0.1)  # the file is written whole, but give the writer its close
    return proc, json.loads(ready.read_text())


def cubetrack(*args: str, cwd: Path) -> Process:
    return Process([sys.executable, "-m", "cubetrack.cli.main", *args], cwd)


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A simulated lab: three emulated cameras replaying a lap of the robot (looping), a fourth
    camera nobody listens on; the tracker config for it."""
    work = tmp_path_factory.mktemp("dashboard")
    rec = work / "rec"
    assert main(["simulate", "--out", str(rec), *simulation(SPEED_M_S)]) == 0
    emu, served = emulator(work, "--recording", str(rec))
    # the same frames at the same times, the robot slowed to one lap per period of the replay
    period_s = served["period_s"]
    emu.stop()
    assert main(["simulate", "--out", str(rec), *simulation(SPEED_M_S * DURATION_S / period_s)]) == 0
    emu, served = emulator(work, "--recording", str(rec))
    assert served["period_s"] == pytest.approx(period_s, abs=1e-6)
    urls = served["urls"]
    config = write_live_config(rec / "config.toml", urls, work / "lab.toml")
    with config.open("a", encoding="utf-8") as f:
        f.write(f'\n[[cameras]]\nname = "cam4"\nurl = "{REFUSED_URL}"\n'
                f'camera_info = "{(rec / "camera_info" / "cam1.yaml").as_posix()}"\n'
                f"\n[calibration]\nsamples = {SAMPLES}\n\n[bundle_adjustment]\nmax_instants = 30\nworld_samples = 12\n"
                "rounds = 1\n")  # a short CI run; the defaults are for a lab
    yield {"work": work, "rec": rec, "config": config, "urls": urls}
    emu.stop()


def api(url: str, path: str):
    r = requests.get(url.rstrip("/") + path, timeout=10)
    r.raise_for_status()
    return r.json()


def test_the_dashboard_guides_a_calibration_in_the_browser(lab, tmp_path):
    work, shots = lab["work"], tmp_path
    out, extrinsics = work / "dash", work / "extrinsics.toml"
    dash = cubetrack("-v", "dashboard", "--config", str(lab["config"]), "--extrinsics", str(extrinsics),
                     "--out", str(out),
                     "--port", "0", cwd=work)  # runs until the test stops it (no --duration to outlast)
    browser = None
    try:
        url = dash.wait_line(r"dashboard: (http://127\.0\.0\.1:\d+/) \(4 cameras, not calibrated yet").group(1)
        browser = Browser(tmp_path / "profile")
        browser.serving = dash.proc
        browser.goto(url)

        # tiles: one per camera of the config; the unreachable one red, saying why
        browser.wait_for("document.querySelectorAll('.tile').length === 4")
        browser.wait_for("document.querySelectorAll('.tile .frame img[src]:not([hidden])').length === 3")
        browser.wait_for("document.querySelector('.tile[data-camera=cam4]').dataset.status === 'down'")
        reason = browser.eval("document.querySelector('.tile[data-camera=cam4] .reason').textContent")
        assert reason == "connection refused by 127.0.0.1:9 — is the node on and on this network?", reason
        assert browser.eval("getComputedStyle(document.querySelector('.tile[data-camera=cam4]')).borderTopColor") \
            == "rgb(229, 72, 77)"  # red
        for cam in ("cam1", "cam2", "cam3"):  # health under the frame: frames/s, clock, JPEG size
            tile = f".tile[data-camera={cam}]"
            browser.wait_for(f"parseFloat(document.querySelector('{tile} [data-stat=fps]').textContent) > 3", 15)
            browser.wait_for(f"document.querySelector('{tile} [data-stat=drift]').textContent.endsWith('ppm')", 15)
            assert browser.eval(f"document.querySelector('{tile} [data-stat=jpeg]').textContent").endswith(" KB")
            assert browser.eval(f"document.querySelector('{tile} [data-stat=offset]').textContent").startswith("booted")

        # 1: every camera sees the world marker (the unreachable one: "camera down")
        browser.wait_for("document.querySelectorAll('#calibration-cameras td.marker .good').length === 3")
        assert "camera down" in browser.eval("document.querySelector('#calibration-cameras tr[data-camera=cam4]"
                                             " td.marker').textContent")
        browser.screenshot(shots / "dashboard-check.png")

        # 2: collect samples: progress bars, then the calibration runs by itself
        browser.click("#calibration-collect")
        browser.wait_for("document.querySelectorAll('#calibration-cameras progress').length === 4")
        time.sleep(1.0)
        browser.screenshot(shots / "dashboard-collect.png")
        browser.wait_for("document.querySelector('li.current[data-step=result]') !== null", 120)

        # 3: results: spread and reprojection error per camera, cam4 flagged with advice
        panel = api(url, "/api/calibration")
        results = {c["name"]: c["result"] for c in panel["cameras"]}
        assert browser.eval("document.querySelectorAll('#calibration-cameras tr.advice-row').length") == 1
        for cam in ("cam1", "cam2", "cam3"):
            r = results[cam]
            assert r["calibrated"] and not r["poor"], r
            assert r["samples"] >= SAMPLES // 2 and 0 < r["spread_cm"] < 1.0 and 0 < r["reprojection_px"] < 0.5
            row = f"#calibration-cameras tr[data-camera={cam}]"
            assert browser.eval(f"document.querySelector('{row} td.verdict').textContent") == "good"
            # the page shows what the API says
            assert browser.eval(f"document.querySelector('{row} td.spread').textContent").startswith(
                f"{r['spread_cm']:.2f} cm")
            assert browser.eval(f"document.querySelector('{row} td.reprojection').textContent") == \
                f"{r['reprojection_px']:.2f} px"
        assert not results["cam4"]["calibrated"] and results["cam4"]["poor"]
        advice = browser.eval("document.querySelector('#calibration-cameras tr[data-advice-for=cam4] .advice')"
                              ".textContent")
        assert advice.startswith("the camera sent no usable frames: check its power, its Wi-Fi and its url")
        browser.screenshot(shots / "dashboard-calibration.png")

        # 4: save: the extrinsics file, as `cubetrack calibrate` writes it, with its run record
        browser.click("#calibration-save")
        browser.wait_for("document.querySelector('#calibration-message').textContent.startsWith('Saved to')")
        saved = read_extrinsics(extrinsics)
        assert set(saved) == {"cam1", "cam2", "cam3"}
        errors = extrinsics_errors(saved, read_extrinsics(lab["rec"] / "true_extrinsics.toml"))
        assert all(pos_m < 0.02 and rot_deg < 0.5 for pos_m, rot_deg in errors.values()), errors
        assert json.loads((work / "extrinsics.run.json").read_text())["command"] == "calibrate"

        # the top view now has the calibrated cameras with their fields of view, and the robot
        browser.wait_for("document.querySelectorAll('#topview g.camera polygon.fov').length === 3", 20)
        browser.wait_for("(g => g && g.dataset.seenBy.split(',').length >= 2)"
                         "(document.querySelector('#topview g.robot'))", 30)
        assert browser.eval("document.querySelectorAll('#topview polyline.trail').length") == 1
        time.sleep(1.0)
        browser.screenshot(shots / "dashboard.png")

        # 5: drive the robot around, refine: how far each camera moved
        browser.click("#calibration-drive")
        browser.wait_for("document.querySelector('#drive-progress progress') !== null")
        # as many instants as the adjustment uses ([bundle_adjustment] max_instants): about a lap of the path
        browser.wait_for("document.querySelector('#drive-progress progress').value >= 30", 120)
        browser.click("#calibration-refine")
        # a hang guard, not a speed check: the refinement detects every drive frame and adjusts, beside live
        # tracking, and CI's other test worker may be busy (206 s once there; over 240 s once, when the dashboard's
        # --duration 240 ended it first)
        message = browser.wait_for("(m => /^Refine(d|ment) /.test(m) && m)"   # done: refined, refused or failed
                                   "(document.querySelector('#calibration-message').textContent)", 600)
        assert message.startswith("Refined"), message
        assert browser.eval("document.querySelector('li.current[data-step=refine]') !== null")
        panel = api(url, "/api/calibration")
        refined = {c["name"]: c["refined"] for c in panel["cameras"] if c["refined"]}
        assert set(refined) == {"cam1", "cam2", "cam3"}
        for cam, r in refined.items():
            assert r["instants"] >= 10 and r["shift_cm"] < 2.0, r
            moved = browser.eval(f"document.querySelector('#calibration-cameras tr[data-camera={cam}] td.moved')"
                                 ".textContent")
            assert moved.startswith(f"{r['shift_cm']:.2f} cm")
        browser.screenshot(shots / "dashboard-refined.png")
        browser.click("#calibration-save")
        browser.wait_for("document.querySelector('#calibration-message').textContent.startsWith('Saved to')")
        assert {e.method for e in read_extrinsics(extrinsics).values()} == {"refined"}
        assert len(list(work.glob("extrinsics.*.toml"))) == 1  # the first save kept beside

        # session: record, stop, download the trajectory
        browser.click("#recording-start")
        browser.wait_for("document.querySelector('#recording-state').dataset.recording === 'true'")
        time.sleep(2.0)
        browser.click("#recording-stop")
        browser.wait_for("[...document.querySelectorAll('#files a')].some(a => a.textContent.startsWith('robot.tum'))",
                         20)
        link = browser.eval("[...document.querySelectorAll('#files a')].find(a => a.textContent.startsWith("
                            "'robot.tum')).href")
        tum = requests.get(link, timeout=10)
        assert tum.status_code == 200 and "attachment" in tum.headers["Content-Disposition"]
        rows = [line.split() for line in tum.text.splitlines()]
        assert len(rows) >= 5 and all(len(r) == 8 for r in rows)
        session = next(p for p in (out / "sessions").iterdir())
        assert read_tum(session / "robot.tum").times_s.size == len(rows)
        assert set(Recording.open(session / "recording").camera_names) == {"cam1", "cam2", "cam3", "cam4"}
        assert browser.errors == []
    except BaseException:
        print("".join(dash.lines)[-5000:])  # the dashboard's log, for the report
        if browser is not None:
            print(browser.eval("document.querySelector('#calibration').innerText"))
        raise
    finally:
        if browser is not None:
            browser.close()
        code = dash.stop()
    assert code == 0, "".join(dash.lines)[-3000:]  # SIGTERM stops it as Ctrl-C does (test_dashboard_exit.py)


def test_track_live_shows_its_session_and_a_stalled_camera_turns_red_within_two_seconds(lab, tmp_path):
    """`track --live --dashboard`: a camera whose stream goes silent (the emulator's stall) turns
    red with the reason within 2 s of its last frame; one nobody listens on is red too."""
    work = lab["work"]
    frames = tmp_path / "frames"
    frames.mkdir()
    for f in sorted((lab["rec"] / "cam1").glob("*.jpg"))[:10]:
        shutil.copyfile(f, frames / f.name)
    stall, stall_served = emulator(tmp_path, "--images", str(frames), "--name", "cam5", "--fps", "10",
                                 "--stall-after", "2.5")
    config = tmp_path / "lab.toml"
    text = lab["config"].read_text(encoding="utf-8")
    info = (lab["rec"] / "camera_info" / "cam1.yaml").as_posix()
    config.write_text(text + '\n[[cameras]]\nname = "cam5"\nurl = '
                             f'"{stall_served["urls"]["cam5"]}"\ncamera_info = "{info}"\n',
                      encoding="utf-8")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    track = cubetrack("track", "--config", str(config), "--uncalibrated", "--live", "--out", str(tmp_path / "out"),
                      "--duration", "600", "--dashboard", f"127.0.0.1:{port}", cwd=work)  # a hang guard: Ctrl-C ends it
    browser = None
    try:
        url = track.wait_line(r"output: dashboard: (http://127\.0\.0\.1:\d+/)").group(1)
        assert url == f"http://127.0.0.1:{port}/"
        # Waits are on the camera's state, with time limits only against a hang: each answer says
        # the status as of that moment (not as of the dashboard's last tick), so the checks below
        # hold however loaded the machine is. The emulator stalls each connection 2.5 s after it
        # starts; the tracker reconnects 3 s into a stall ([source] read_timeout_s), and cam5 is ok again.
        deadline = time.monotonic() + 90
        while (cam := api(url, "/api/cameras/cam5"))["status"] != "ok":
            assert time.monotonic() < deadline, f"cam5 never streamed: {cam}"
            time.sleep(0.05)
        ages = []
        while (cam := api(url, "/api/cameras/cam5"))["status"] == "ok":  # until the stream stalls
            ages.append(cam["frame_age_s"])
            assert time.monotonic() < deadline, f"cam5 never stalled: {cam}"
            time.sleep(0.05)
        assert cam["status"] == "stale" and cam["reason"].startswith("no frame for"), cam
        assert cam["frame_age_s"] <= 2.0 and max(ages) <= 2.0, (cam, max(ages))
        browser = Browser(tmp_path / "profile")
        browser.goto(url)
        browser.wait_for("(t => t && ['stale', 'down'].includes(t.dataset.status))"
                         "(document.querySelector('.tile[data-camera=cam5]'))", 10)
        browser.wait_for("document.querySelector('.tile[data-camera=cam4]').dataset.status === 'down'", 10)
        browser.wait_for("document.querySelectorAll('#robots tbody tr').length === 1")
        assert browser.eval("document.querySelector('#recording-state').textContent") == "track"
        browser.screenshot(tmp_path / "dashboard-track.png")
        assert browser.errors == []
        state = api(url, "/api/state")
        assert {c["name"] for c in state["cameras"]} == {"cam1", "cam2", "cam3", "cam4", "cam5"}
        assert state["session"]["calibrated"] is False and state["actions"] == {}
    finally:
        if browser is not None:
            browser.close()
        track.proc.send_signal(signal.SIGINT)  # Ctrl-C: the session ends, what it tracked is kept
        code = track.proc.wait(30)
        stall.stop()
    assert code == 0 and "interrupted; tracked live for" in "".join(track.lines), "".join(track.lines)[-3000:]
    with pytest.raises(requests.ConnectionError):  # the command ended: so did its dashboard
        requests.get(url, timeout=2)
    assert np.isfinite(read_tum(tmp_path / "out" / "robot.tum").times_s).all()
