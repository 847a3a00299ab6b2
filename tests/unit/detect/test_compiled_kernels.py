"""The edge fit's and the template fit's compiled kernels (numba): compiled when a detector is
built, never on a frame, and per-marker arguments reach each marker."""

from __future__ import annotations

import cv2
import numpy as np
from scenes import render_in_front
from test_detect_markers import INTR, K, facing

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.detect import detector as detector_module
from cubetrack.detect import edge_fit, template_fit
from cubetrack.detect.detector import CornerRefinement, Detector, DetectorParams

# the kernels the fit calls from Python (the ones they call are compiled, or loaded from numba's cache, with them)
TEMPLATE_KERNELS = (template_fit._fitted_offsets, template_fit._region_start, template_fit._region_arrays,
                    template_fit._area_sigmas, template_fit._distorted)


EDGE_KERNELS = (edge_fit._finite_box, edge_fit._fit_buffers, edge_fit._side_samples, edge_fit._fitted_corners,
                edge_fit._fit_result, edge_fit._fitted_loop, edge_fit._profiles, edge_fit._region,
                edge_fit._pinhole_refined, detector_module._quad_kernel)


def _kernel_signatures() -> int:
    return sum(len(kernel.signatures) for kernel in EDGE_KERNELS)


def _template_signatures() -> list[int]:
    return [len(kernel.signatures) for kernel in TEMPLATE_KERNELS]


def _two_marker_frame() -> np.ndarray:
    markers = [(facing(0.8, 25, 10, 15, -0.12, 0.0), "DICT_4X4_50", 3, 0.08, 0.04),
               (facing(1.1, -30, 20, 80, 0.15, 0.05), "DICT_4X4_50", 9, 0.08, 0.04)]
    return render_in_front(INTR, markers, blur_px=0.7, noise_std=2.0, jpeg_quality=85, rng=np.random.default_rng(3))


def test_a_detector_compiles_the_kernel_before_its_first_frame():
    """Every kind of call the detector and calibration make (8-bit and float images, one or
    several markers, one module count or one per marker, with and without a lens model, tent and
    peak focus) runs code compiled when the detector was built: no frame waits for numba."""
    detector = Detector(DetectorParams(corner_refinement=CornerRefinement.EDGE))
    compiled = _kernel_signatures()
    assert compiled >= len(EDGE_KERNELS)
    gray = _two_marker_frame()
    found = detector.detect(gray)
    assert len(found) == 2
    quads = np.array([d.corners_px for d in found])
    dist = np.array([-0.1, 0.02, 0.0, 0.0, 0.0])
    for kwargs in ({}, {"focus": "peak"}, {"K": K, "dist": dist}, {"K": K, "dist": dist, "focus": "peak"}):
        for image in (gray, gray.astype(np.float32)):
            assert np.isfinite(edge_fit.refine_corners_edges(image, quads, np.array([6, 6]), **kwargs)).all()
            assert np.isfinite(edge_fit.refine_corners_edges(image, quads[0], 6, **kwargs)).all()
    assert _kernel_signatures() == compiled


def test_a_module_count_per_marker_reaches_each_marker():
    """``modules`` per marker sets each marker's sampling half-width: a call over several markers
    gives each the corners it gets alone with its own count, and one count for all is the same
    as that count repeated."""
    gray = _two_marker_frame()
    quads = np.array([d.corners_px for d in Detector(DetectorParams(corner_refinement=CornerRefinement.NONE))
                      .detect(gray)])
    together = edge_fit.refine_corners_edges(gray, quads, np.array([6, 9]))
    for i, modules in enumerate((6, 9)):
        np.testing.assert_allclose(together[i], edge_fit.refine_corners_edges(gray, quads[i], modules), atol=1e-9)
    assert not np.allclose(together[1], edge_fit.refine_corners_edges(gray, quads[1], 6), atol=1e-6)
    np.testing.assert_array_equal(edge_fit.refine_corners_edges(gray, quads, 6),
                                  edge_fit.refine_corners_edges(gray, quads, np.array([6, 6])))


def test_the_fit_follows_a_known_edge_to_a_fraction_of_a_pixel():
    """A dark square on a bright ground, blurred: the fitted corners (the detector's ``tent``
    focus) are the square's to 1e-3 px, from initial corners a pixel off."""
    gray = np.full((120, 120), 210.0, np.float32)
    gray[30:90, 40:100] = 30.0
    gray = cv2.GaussianBlur(gray, (0, 0), 1.0)
    truth = np.array([[40.0, 30.0], [100.0, 30.0], [100.0, 90.0], [40.0, 90.0]]) - 0.5   # pixel edges
    start = truth + np.array([[1.0, -0.8], [-0.7, 0.9], [0.8, 1.0], [-1.0, -0.6]])
    assert np.abs(edge_fit.refine_corners_edges(gray, start, 6) - truth).max() < 1e-3


def _sampled(image: np.ndarray, p: np.ndarray) -> np.ndarray:
    """:func:`edge_fit._profiles` of ``image`` at the complex positions ``p``, in ``p``'s shape."""
    out = np.full(p.size, np.nan, np.float32)
    edge_fit._profiles(image, np.ascontiguousarray(p).reshape(-1), np.empty((2, p.size), np.float32), out)
    return out.reshape(p.shape)


def test_the_fit_samples_the_image_as_cv2_remap_does():
    """The compiled sampler gives ``cv2.remap``'s bilinear samples (float32 map, replicated border)
    to the bit, inside the image and beyond its border, of an 8-bit and a float32 image, and
    where every position lies inside (its loop without the border's branch): the corners do not
    depend on which of the two samples them."""
    # Equal to the bit where OpenCV runs its remap in code dispatched to AVX2 (fused multiply-adds; the machines
    # this was measured on). On a CPU without AVX2 OpenCV takes another path: held to float32 rounding there.
    exact = "*AVX2" in cv2.getCPUFeaturesLine()
    rng = np.random.default_rng(11)
    gray = rng.integers(0, 256, (37, 53), dtype=np.uint8)
    for image in (gray, (gray * 0.731).astype(np.float32)):
        for lo, hi, edges in (((0.0, 0.0), (52.0, 36.0), True), ((-6.0, -6.0), (60.0, 44.0), True),
                              ((0.0, 0.0), (51.999, 35.999), False)):   # the last: every position inside
            xy = rng.uniform(lo, hi, (3, 7, 2 * 17 + 1, 2))
            if edges:
                xy[0, 0, :4] = [[0.0, 0.0], [52.0, 36.0], [51.999, 35.5], [-1.0, 36.0]]   # on the edges
            p = xy[..., 0] + 1j * xy[..., 1]
            want = cv2.remap(image.astype(np.float32), xy.reshape(1, -1, 2).astype(np.float32), None,
                             cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(p.shape)
            if exact:
                np.testing.assert_array_equal(_sampled(image, p), want)
            else:
                np.testing.assert_allclose(_sampled(image, p), want, rtol=0, atol=1e-4)


def test_a_marker_stops_after_the_first_fit_that_moves_it_less_than_settled_px():
    """With ``settled_px`` each marker's fits end after the first one that moved none of its
    corners by that much along either axis (the corners then are those of that many fits, to the
    bit); 0 fits ``iterations`` times."""
    gray = _two_marker_frame()
    quads = np.array([d.corners_px for d in Detector(DetectorParams(corner_refinement=CornerRefinement.EDGE))
                      .detect(gray)])
    start = quads + np.array([[[0.05, -0.04]], [[1.5, -1.2]]])      # one a twentieth of a pixel off, one 1.5 px
    fits = [start] + [edge_fit.refine_corners_edges(gray, start, 6, k) for k in range(1, 7)]
    settled_px = 0.01
    stops = []
    for q in range(2):
        moves = [np.abs(fits[k][q] - fits[k - 1][q]).max() for k in range(1, 7)]
        stops.append(next((k for k, move in enumerate(moves, 1) if move < settled_px), 6))
    assert stops[0] < stops[1] < 6, stops                     # the near one stops sooner; both before 6 fits
    settled = edge_fit.refine_corners_edges(gray, start, 6, 6, settled_px=settled_px)
    for q in range(2):
        np.testing.assert_array_equal(settled[q], fits[stops[q]][q])
    np.testing.assert_array_equal(edge_fit.refine_corners_edges(gray, start, 6, 6, settled_px=0.0), fits[6])
    np.testing.assert_array_equal(edge_fit.refine_corners_edges(gray, start, 6, 6, settled_px=100.0), fits[1])


def test_a_template_detector_compiles_the_template_fit_before_its_first_frame():
    """With ``template`` corners the detector also compiles the template fit's kernels when it is
    built; fitting markers through a lens model or without one then compiles nothing more, and
    the fit still moves the corners (it ran)."""
    detector = Detector(DetectorParams(corner_refinement=CornerRefinement.TEMPLATE))
    compiled = _template_signatures()
    assert min(compiled) >= 1
    gray = _two_marker_frame()
    edge = Detector(DetectorParams(corner_refinement=CornerRefinement.EDGE)).detect(gray)
    lensed = CameraIntrinsics(INTR.width, INTR.height, K, np.array([-0.05, 0.01, 0.0, 0.0, 0.0]))
    for lens in (None, lensed):
        found = detector.detect(gray, lens=lens)
        assert len(found) == 2
        moved = max(np.abs(a.corners_px - b.corners_px).max() for a, b in zip(found, edge, strict=True))
        assert 1e-4 < moved < 1.5
    assert _template_signatures() == compiled


def _numba_interrupted() -> None:
    """What numba's dispatcher raises when Ctrl-C lands while it loads a kernel from its cache (seen
    in CI: a SIGHUP during a dashboard's start-up)."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as interrupt:
        raise SystemError("CPUDispatcher(<function _side_samples>) returned a result with an exception set") \
            from interrupt


def test_an_interrupt_while_the_kernels_load_is_an_interrupt(monkeypatch):
    import pytest

    from cubetrack.detect import detector

    monkeypatch.setattr(detector, "compile_edge_fit", _numba_interrupted)
    with pytest.raises(KeyboardInterrupt):
        Detector(DetectorParams(corner_refinement=CornerRefinement.EDGE))

    def broken() -> None:
        raise SystemError("a numba failure of its own")

    monkeypatch.setattr(detector, "compile_edge_fit", broken)
    with pytest.raises(SystemError, match="of its own"):
        Detector(DetectorParams(corner_refinement=CornerRefinement.EDGE))


def _cold_compile() -> None:
    """A kernel numba has never compiled and does not cache: a cold cache's compile."""
    import numba

    @numba.njit
    def plus_one(x):
        return x + 1

    plus_one(1)


COLD_WARNING = ("compiling the test kernels (numba; once after an install or upgrade, a minute or two): run "
                "`cubetrack compile` after installing to do this ahead ...")


def test_a_cold_compile_is_warned_once_as_it_starts_and_a_load_says_nothing(monkeypatch, caplog):
    """The first run after an install compiles for a minute: the user hears why at the default
    verbosity (WARNING), as it starts, not only after, and once; a start from numba's cache is silent."""
    import logging
    import threading

    monkeypatch.setattr(detector_module, "_cold_cache_told", threading.Lock())  # a process that has said nothing
    said_while_compiling = []

    def compile_and_listen():
        _cold_compile()
        said_while_compiling.extend((r.levelno, r.getMessage()) for r in caplog.records)

    with caplog.at_level(logging.INFO, logger=detector_module.log.name):
        detector_module.compile_kernels("test kernels", compile_and_listen)
        assert said_while_compiling == [(logging.WARNING, COLD_WARNING)]
        assert caplog.records[-1].getMessage().startswith("compiled the test kernels in ")
        caplog.clear()
        detector_module.compile_kernels("other kernels", _cold_compile)   # said once per process
        assert [r.levelno for r in caplog.records] == [logging.INFO]
        caplog.clear()
        detector_module.compile_kernels("test kernels", lambda: None)
    assert caplog.records == []


def test_cubetrack_compile_silences_the_cold_cache_warning(monkeypatch, caplog):
    """`cubetrack compile` compiles on purpose: no warning telling the user to run it."""
    import logging
    import threading

    monkeypatch.setattr(detector_module, "_cold_cache_told", threading.Lock())
    detector_module.no_cold_cache_warning()
    with caplog.at_level(logging.WARNING, logger=detector_module.log.name):
        detector_module.compile_kernels("test kernels", _cold_compile)
    assert caplog.records == []


def test_cubetrack_compile_reports_a_failure_in_one_line(monkeypatch, capsys):
    from cubetrack.app import kernels
    from cubetrack.cli.main import main

    def broken() -> None:
        raise RuntimeError("cannot cache function 'f': no locator available for file 'f.py'\nmore detail")

    monkeypatch.setattr(kernels, "KERNEL_GROUPS", (("quad checks", detector_module.compile_quad_checks),
                                                   ("broken kernels", broken)))
    assert main(["compile"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == ("cubetrack compile: error: numba failed: RuntimeError: cannot cache function "
                                    "'f': no locator available for file 'f.py'; numba's cache needs a writable "
                                    "folder: NUMBA_CACHE_DIR, __pycache__ beside the sources or ~/.cache/numba")
    assert "compiling the broken kernels: 1/2" in err
