"""`cubetrack compile` (run after installing) leaves numba's cache so that a tracker compiles
nothing: a replay in a fresh process, with either corner refinement the live path uses, loads every
kernel from the cache the command wrote (numba's own cache log: loads, no saves) and gives no
cold-cache warning. The cache goes to a fresh NUMBA_CACHE_DIR: the command compiles for a minute or
more here."""

import os
import subprocess
import sys

import pytest

from tests.helpers.scene import simulated_recording

pytestmark = pytest.mark.slow

TEMPLATE = '\n[detector]\ncorner_refinement = "template"\n'


def cubetrack(args: list[str], cache) -> subprocess.CompletedProcess:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "NUMBA_DEBUG_CACHE": "1"}
    return subprocess.run([sys.executable, "-m", "cubetrack.cli.main", *args], env=env, capture_output=True,
                          text=True, timeout=900)


def test_after_cubetrack_compile_a_replay_loads_every_kernel_from_the_cache(tmp_path):
    cache = tmp_path / "numba"
    rec = simulated_recording(tmp_path / "rec", duration_s=1, cameras=2)
    done = cubetrack(["compile"], cache)
    assert done.returncode == 0, done.stderr
    assert "compiling the template fit: 3/5" in done.stderr and "cubetrack compile`" not in done.stderr
    assert "[cache] data saved to" in done.stdout and f"numba's cache: {cache}" in done.stdout
    assert "template fit: 0 compiled" not in done.stdout   # a cold cache: compiled, not loaded
    for name, section in (("edge", ""), ("template", TEMPLATE)):
        config = rec / f"config_{name}.toml"
        config.write_text((rec / "config.toml").read_text() + section)
        tracked = cubetrack(["track", "--config", str(config), "--extrinsics", str(rec / "true_extrinsics.toml"),
                             "--recording", str(rec), "--out", str(tmp_path / name)], cache)
        assert tracked.returncode == 0, tracked.stderr
        assert "[cache] data loaded from" in tracked.stdout and "saved to" not in tracked.stdout, name
        assert "compiling" not in tracked.stderr, name
