"""Smoke run of benchmarks/detect_speed.py --stages (issue 9's per-stage CPU benchmark) on a short
simulated recording: every stage and the estimate/ functions the fusion calls are reported, the
replay is bit-identical across rounds, every stage's timer counted its stage, and the timing hooks
are gone afterwards. How fast each stage is stays the benchmark's business, never asserted here."""

import re

import pytest

import cubetrack.app.tracker as tracker_module
import cubetrack.detect.detector as detector_module
import cubetrack.fuse.corner_filter as corner_filter_module
from tests.helpers.benchmarks import load_benchmark

pytestmark = pytest.mark.slow


def test_stages_report_every_stage_and_a_bit_identical_replay(capsys):
    originals = (tracker_module.decode_gray, detector_module.refine_corners_edges,
                 corner_filter_module.solve_update)
    bench = load_benchmark("detect_speed")
    assert bench.main(["--stages", "--duration", "3", "--rounds", "2", "--micro-frames", "20"]) == 0
    text = capsys.readouterr().out

    def ms(label: str) -> float:
        match = re.search(rf"^{re.escape(label)}\s+([0-9.]+)", text, re.MULTILINE)
        assert match, f"no line {label!r} in:\n{text}"
        return float(match.group(1))

    labels = ("decode (JPEG -> gray)", "detect (OpenCV search, quads)", "edge refinement", "per-camera estimate",
              "planning (regions)", "fusion")
    stages = [ms(label) for label in labels]
    # every stage ran on this scene (the filter plans regions, refines edges and asks for estimates), so
    # each stage's timer counted something: a hook that timed nothing (a stage renamed or skipped) reports 0
    assert all(value > 0.0 for value in stages), dict(zip(labels, stages, strict=True))
    for label in labels:  # each share is the stage's part of the total, as printed
        share = re.search(rf"^{re.escape(label)}\s+[0-9.]+\s+([0-9.]+)%", text, re.MULTILINE)
        assert share and abs(float(share.group(1)) - 100 * ms(label) / ms("total (ours, one thread)")) < 0.2, label
    assert abs(sum(stages) - ms("total (ours, one thread)")) <= 0.1 * ms("total (ours, one thread)") + 0.01
    assert ms("naive loop (same frames)") > 0.0
    empty = re.search(r"^frames whose regions are empty .*: (\d+) of (\d+); decoding them costs ([0-9.]+) ms/frame",
                      text, re.MULTILINE)
    assert empty, text
    assert int(empty.group(1)) <= int(empty.group(2)) and float(empty.group(3)) <= ms("decode (JPEG -> gray)")
    # the tracked cube's markers were found at their predictions (no region search) in some region frames
    predicted = re.search(r"^frames with regions: (\d+) of (\d+); of them found at their predicted markers, "
                          r"verified, without OpenCV's search: (\d+)$", text, re.MULTILINE)
    assert predicted and 0 < int(predicted.group(3)) <= int(predicted.group(1)) <= int(predicted.group(2)), text
    # the frames before the track started were searched whole (and timed), so some but not all were
    whole = re.search(r"^frames searched whole .*: (\d+) of (\d+); their decode \+ detect \+ estimate "
                      r"([0-9.]+) ms each against ([0-9.]+) for the other frames: ([0-9.]+) ms/frame", text,
                      re.MULTILINE)
    assert whole and 0 < int(whole.group(1)) < int(whole.group(2)), text
    assert float(whole.group(3)) > 0.0 and float(whole.group(5)) <= ms("total (ours, one thread)"), text
    # the fusion ran (a track started) and its estimate/ calls were timed alone
    for name in ("fusion.match_faces", "corner_filter.solve_update", "corner_filter.packed_sets"):
        assert re.search(rf"^  {re.escape(name)}\s+[0-9.]+ calls/frame\s+[0-9.]+ us/call", text, re.MULTILINE), name
    assert re.search(r"^poses: [1-9][0-9]*; replay bit-identical across rounds", text, re.MULTILINE), text
    # the decode levers on the same frames, each against the full gray decode (its own ratio 1)
    decodes = {label: (float(value), float(ratio)) for label, value, ratio in
               re.findall(r"^  (colour.*?|gray.*?|the tracker's.*?)\s+([0-9.]+) ms\s+([0-9.]+)$", text, re.MULTILINE)}
    assert len(decodes) == 10, decodes
    assert decodes["gray, full size (simplejpeg)"][1] == 1.0
    assert all(value > 0.0 and abs(ratio - value / decodes["gray, full size (simplejpeg)"][0]) < 0.02
               for value, ratio in decodes.values()), decodes
    # the region searches those frames made, as configured and with the levers (each costs CPU; as configured
    # keeps markers: the tracker searched regions where its robot was predicted)
    regions = {label: (float(ms_), int(kept)) for label, ms_, kept in
               re.findall(r"^  (as configured|threshold windows .*?|the image at half size.*?)\s+([0-9.]+) ms\s+(\d+) "
                          r"markers$", text, re.MULTILINE)}
    assert len(regions) == 4 and all(value > 0.0 for value, _ in regions.values()), regions
    assert regions["as configured"][1] > 0, regions
    gc = re.search(r"^garbage collections in a round \(median of rounds\): (\d+), of which (\d+) of the oldest "
                   r"generation; ([0-9.]+) ms in all \(([0-9.]+) ms per frame\), the longest ([0-9.]+) ms", text, re.M)
    assert gc and int(gc.group(2)) <= int(gc.group(1)), text   # per round, so in the medians too
    full = re.search(r"^a full collection here: (\d+) tracked objects, ([0-9.]+) ms CPU; after gc.freeze\(\) (\d+) "
                     r"objects, ([0-9.]+) ms$", text, re.M)
    assert full and int(full.group(3)) < int(full.group(1)), text   # frozen objects are out of the collection
    assert (tracker_module.decode_gray, detector_module.refine_corners_edges,
            corner_filter_module.solve_update) == originals
