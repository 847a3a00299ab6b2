"""Short libFuzzer runs of every firmware fuzz target (HTTP server, serial port, console,
settings record, GS2200M text), each from its saved corpus in firmware/fuzz/corpus/. The long
campaigns: benchmarks/fuzz_campaign.py (numbers in docs/reliability.md); every saved input is
replayed on each CI run by tests/reliability/test_fuzz_corpora.py."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
from firmware_tools import BUILD_DIR, FIRMWARE_DIR, make, require_tools

SECONDS = 4
TARGETS = sorted(p.stem.removeprefix("fuzz_") for p in (FIRMWARE_DIR / "fuzz").glob("fuzz_*.cpp"))


def test_every_target_is_built_and_has_a_saved_corpus():
    assert set(TARGETS) >= {"http", "improv", "console", "settings", "gs2200m"}
    for target in TARGETS:
        assert len(list((FIRMWARE_DIR / "fuzz" / "corpus" / target).iterdir())) >= 2, target


@pytest.mark.parametrize("target", TARGETS)
def test_fuzz_target_survives_a_short_run(target, tmp_path):
    require_tools("clang++")
    make("fuzz")
    corpus = tmp_path / "corpus"
    shutil.copytree(FIRMWARE_DIR / "fuzz" / "corpus" / target, corpus)
    result = subprocess.run(
        [str(BUILD_DIR / f"fuzz-{target}"), f"-max_total_time={SECONDS}", "-timeout=10", "-rss_limit_mb=2048",
         "-max_len=4096", f"-artifact_prefix={tmp_path}/", str(corpus)],
        capture_output=True, text=True, timeout=SECONDS + 60, check=False,
    )
    assert result.returncode == 0, result.stderr[-6000:]
    assert "Done" in result.stderr
    assert not list(tmp_path.glob("crash-*"))


def test_benchmark_script_prints_ratios(capsys):
    require_tools("g++", "make")
    sys.path.insert(0, str(BUILD_DIR.parents[1] / "benchmarks"))
    import firmware_stream

    assert firmware_stream.main(["--frames", "200"]) == 0
    out = capsys.readouterr().out
    assert "x memcpy" in out and "RAM per client slot" in out
    r = firmware_stream.run(45000, 200)
    assert r["max_write_bytes"] <= 1400
    assert r["writes_per_frame"] == pytest.approx(45000 / 1400, abs=1.5)  # chunks are filled
    assert r["ratio_1_client"] < 50  # the core's cost stays of the order of copying the frame
