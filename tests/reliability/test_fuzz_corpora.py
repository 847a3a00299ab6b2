"""CI's share of the fuzzing campaigns (benchmarks/fuzz_campaign.py): every saved input of every
target -- seeds, the inputs that found new coverage, and every crash input ever found -- is run
once on each CI run, and the campaign script itself runs briefly."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import fuzz_campaign  # noqa: E402


@pytest.mark.parametrize("target", sorted(fuzz_campaign.PY_TARGETS))
def test_python_corpus_replays_without_a_failure(target):
    inputs, failures = fuzz_campaign.replay_python(target)
    assert inputs >= 2, f"tests/corpus/{target} holds no saved inputs"
    assert not failures, "\n".join(f"{f.input.name}: {f.error}" for f in failures)


@pytest.fixture(scope="module")
def firmware_fuzzers() -> dict[str, Path]:
    if shutil.which("clang++") is None:
        pytest.skip("clang++ is not installed (tests/install.sh installs it)")
    return fuzz_campaign.build_firmware_fuzzers(fuzz_campaign.FIRMWARE_DIR / "build", 2)


def test_firmware_corpora_replay_without_a_crash(firmware_fuzzers, tmp_path):
    """(tests/firmware/test_fuzz.py checks that every target has a saved corpus.)"""
    for name, binary in firmware_fuzzers.items():
        result = fuzz_campaign.replay_firmware(name, binary, tmp_path)
        assert not result.crashes and not result.note, (name, result.crashes, result.note)
        assert result.cov > 0, name


def test_the_campaign_script_runs_and_reports_every_target(tmp_path):
    pytest.importorskip("atheris")
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "fuzz_campaign.py"), "--only", "cubecam_improv,http_request,console",
         "--python-runs", "300", "--firmware-runs", "3000", "--work", str(tmp_path)],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    rows = {line.split()[0]: line.split() for line in proc.stdout.splitlines()[1:] if line.strip()}
    assert set(rows) == {"cubecam_improv", "http_request", "console"}
    for row in rows.values():
        executions, cov, crashes = int(row[2]), int(row[5]), int(row[8])
        assert executions >= 300 and cov > 0 and crashes == 0, row
    assert "lines (" in " ".join(rows["cubecam_improv"]) and "edges (" in " ".join(rows["console"])
