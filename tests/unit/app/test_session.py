"""The session runtime (cubetrack.app.session.Session): the loop, its ticks and per-turn actions,
the deadline, the end of input, the stop path that Ctrl-C, SIGTERM and SIGHUP take, and run.json.

Signals are real (sent to this process from another thread while the loop runs in the main
thread); ticks run on a clock the test's step moves, so nothing here depends on timing."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from cubetrack.app.session import RunSpec, Session, _Tick
from cubetrack.io.run import read_run_record


class Steps:
    """A loop's step that moves a fake clock by ``dt_s`` per call and records its timeouts."""

    def __init__(self, dt_s: float = 0.1):
        self.now_s, self.dt_s, self.timeouts = 0.0, dt_s, []

    def clock(self) -> float:
        return self.now_s

    def __call__(self, timeout_s: float) -> None:
        self.timeouts.append(timeout_s)
        self.now_s += self.dt_s


def test_ticks_run_on_their_clocks_grid_and_turn_actions_after_every_step():
    steps, ticks, turns = Steps(0.125), [], []
    session = Session()
    session.every(0.25, lambda: ticks.append(steps.now_s), clock=steps.clock, grid=True)
    session.each_turn(lambda: turns.append(steps.now_s))

    def step(timeout_s: float) -> None:
        steps(timeout_s)
        if len(steps.timeouts) == 10:
            session.complete()

    session.run(step, idle_s=1.0)
    assert turns == [0.125 * k for k in range(1, 11)]
    # first at once (the first turn), then at the first turn at or after each multiple of 0.25
    assert ticks == [0.125, 0.25, 0.5, 0.75, 1.0, 1.25]
    assert max(steps.timeouts) <= 0.25 and session.completed and not session.interrupted


def test_the_deadline_ends_the_loop_then_it_drains():
    session = Session(duration_s=0.0)
    drained, stepped = [], []
    pending = [3]

    def draining() -> bool:
        pending[0] -= 1
        return pending[0] >= 0

    session.run(stepped.append, drained=lambda: drained.append(True), draining=draining)
    assert drained == [True] and stepped == [0.05, 0.05, 0.05]  # no turn of the loop, three of the draining


@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP], ids=lambda n: n.name)
def test_a_stop_signal_ends_the_session_like_its_end_and_is_recorded(tmp_path, number):
    before = signal.getsignal(number)
    session = Session(record=RunSpec(tmp_path / "run.json", "track", {}, {}, {"cameras": {}}))
    assert read_run_record(tmp_path)["command"] == "track" and "session" not in read_run_record(tmp_path)
    started, drained = threading.Event(), []

    def step(timeout_s: float) -> None:
        if not started.is_set():
            started.set()
            threading.Thread(target=os.kill, args=(os.getpid(), number)).start()
        session.stop_event.wait(timeout_s)

    session.run(step, drained=lambda: drained.append(True))
    session.finish({"frames": 7})
    assert session.interrupted and session.ended_by == number.name and drained == [True]
    record = read_run_record(tmp_path)
    assert record["session"]["ended"] == number.name and record["session"]["frames"] == 7
    assert record["cameras"] == {} and signal.getsignal(number) == before  # the handler is given back


def test_a_second_signal_gives_up_the_draining():
    session = Session()
    sent = []

    def step(timeout_s: float) -> None:
        if len(sent) < 2:  # one while running, one while draining
            sent.append(True)
            os.kill(os.getpid(), signal.SIGTERM)
        session.stop_event.wait(timeout_s)

    drained = []
    session.run(step, draining=lambda: not drained.append(True), drained=lambda: None)
    assert session.ended_by == "SIGTERM" and len(sent) == 2 and len(drained) == 1


def test_run_json_says_how_each_session_ended(tmp_path):
    for name, make, act in (("duration", lambda r: Session(duration_s=0.0, record=r), lambda s: None),
                            ("stopped", lambda r: Session(record=r), lambda s: s.stop_event.set()),
                            ("end of input", lambda r: Session(record=r), lambda s: s.complete())):
        session = make(RunSpec(tmp_path / name / "run.json", "fuse", {}, {}))
        act(session)
        session.run(lambda t: None)
        session.finish({})
        assert read_run_record(tmp_path / name)["session"]["ended"] == name


def test_an_ignored_signal_stays_ignored():
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        session = Session()
        seen = []

        def step(timeout_s: float) -> None:
            seen.append(signal.getsignal(signal.SIGHUP))
            session.complete()

        session.run(step)
        assert seen == [signal.SIG_IGN] and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)


def test_track_live_resolves_its_config_once(tmp_path, capsys, caplog):
    """`track --live --dashboard` reads the config's sections once: a config warning is logged once
    (the live loop and the dashboard were each resolving the config again: the warning came three
    times). Cameras at an address nobody serves, for a second."""
    import logging

    from cubetrack.app.demo import write_live_config
    from cubetrack.cli.main import main
    from tests.helpers.scene import simulated_recording

    rec = simulated_recording(tmp_path / "rec", 0.3)
    config = write_live_config(rec / "config.toml", {c: "http://127.0.0.1:9/stream" for c in ("cam1", "cam2", "cam3")},
                               tmp_path / "lab.toml")
    config.write_text(config.read_text() + "\n[filter]\ncorner_noise_px = 0.05\n")  # trusts the edge fit too much
    caplog.set_level(logging.WARNING, logger="cubetrack.app.config")
    assert main(["track", "--config", str(config), "--extrinsics", str(rec / "true_extrinsics.toml"), "--live",
                 "--duration", "1", "--out", str(tmp_path / "out"), "--dashboard", "127.0.0.1:0"]) == 0
    warnings = [r for r in caplog.records if "corner_noise_px = 0.05 trusts" in r.getMessage()]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert read_run_record(tmp_path / "out")["session"]["ended"] == "duration"


def test_a_grid_tick_whose_action_reads_the_clock_late_runs_once_in_that_cell():
    now, stamps = [0.96], []

    def action():  # a loaded machine: the action reads the clock after the next multiple has passed
        now[0] += 0.06
        stamps.append(now[0])

    tick = _Tick(0.5, action, lambda: now[0], 0.5, grid=True)
    tick.run_if_due()          # due at 0.5 (clock 0.96): the action's clock says 1.02, in the cell from 1.0
    now[0] = 1.2
    tick.run_if_due()          # the same cell as the action's stamp: not again
    now[0] = 1.5
    tick.run_if_due()
    assert [int(s // 0.5) for s in stamps] == [2, 3]
