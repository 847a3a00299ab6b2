"""Short libFuzzer runs of the HTTP server, the serial port (Improv + console) and the
console. The long run is documented in firmware/README.md."""

from __future__ import annotations

import subprocess
import sys

import pytest
from firmware_tools import BUILD_DIR, make, require_tools

SECONDS = 5

SEEDS = {
    "http": [
        b"\x10GET /stream?fps=5 HTTP/1.1\r\nHost: cam\r\n\r\n",
        b"\x01GET /capture HTTP/1.0\r\n\r\n",
        b"\x3fPOST /status HTTP/1.1\r\nContent-Length: 3\r\n\r\nabc",
        b"\x05GET /time HTTP/1.1\nX: y\n\n",
    ],
    "improv": [
        b"IMPROV\x01\x03\x02\x02\x00\xe0\n",  # get current state (checksum fixed below)
        b"help\nget\nset fps 30\nstatus\n",
        b"IMPROV\x01\x03\x0d\x01\x0b\x03lab\x07pass\xffword\n",
    ],
    "console": [b"help\n", b"set ssid My Lab\nget ssid\nsave\n", b"set ip 10.0.0.2/24,10.0.0.1\nget\n"],
}


def with_checksum(frame: bytes) -> bytes:
    if not frame.startswith(b"IMPROV"):
        return frame
    body = frame[: 9 + frame[8]]
    return body + bytes([sum(body) & 0xFF]) + b"\n"


@pytest.mark.parametrize("target", sorted(SEEDS))
def test_fuzz_target_survives_a_short_run(target, tmp_path):
    require_tools("clang++")
    make("fuzz")
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    for i, seed in enumerate(SEEDS[target]):
        (corpus / f"seed{i}").write_bytes(with_checksum(seed) if target == "improv" else seed)
    result = subprocess.run(
        [str(BUILD_DIR / f"fuzz-{target}"), f"-max_total_time={SECONDS}", "-timeout=10", "-rss_limit_mb=2048",
         f"-artifact_prefix={tmp_path}/", str(corpus)],
        capture_output=True, text=True, timeout=SECONDS + 60,
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
