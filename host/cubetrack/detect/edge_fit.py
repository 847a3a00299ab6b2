"""The ``edge`` corner refinement: a line fitted to each side's sub-pixel outer edge.

Used by the detector (``[detector] corner_refinement = "edge"``, and as the start of the
``template`` fit) and by calibration, which fits the world marker's edges through the camera's
lens model (:func:`refine_corners_edges` with ``K`` and ``dist``). A marker is dark on a bright
margin here; the detector hands inverted (white-on-black) markers over in the negated image.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, cast

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from cubetrack.core.geometry import undistort_points
from cubetrack.detect.quads import corners_finite
from cubetrack.detect.template_fit import distort_px

_ROI_MARGIN_PX = 16  # refine_corners_edges: the quads' region plus this is read


_EDGE_SPAN = (0.1, 0.9)       # the detector's edge samples: the middle 80 % of each side
_EDGE_SAMPLES_ACROSS = 17     # profile samples across an edge
_EDGE_FOCUS_PX = 3.0          # focus='tent': half-width of the tent that re-centres each edge point, px
_PEAK_WINDOW_PX = 1.25        # focus='peak': half-width of the window around the gradient's peak, px

# _side_samples' output, per quad and side: (positions (M, 4, m, k), vector, outward normal, length, half-width)
_Sides = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _distort_c(z: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """:func:`cubetrack.detect.template_fit.distort_px` on complex pixel positions x + iy."""
    out = distort_px(np.stack([z.real, z.imag], axis=-1), K, dist)
    return out[..., 0] + 1j * out[..., 1]


def _undistort_c(z: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Where distorted complex pixel positions x + iy lie in the ideal pinhole image of the same
    ``K`` (:func:`cubetrack.core.geometry.undistort_points`, iterated to 1e-12)."""
    out = undistort_points(np.stack([z.real, z.imag], axis=-1), K, dist, K)
    return out[..., 0] + 1j * out[..., 1]


@functools.lru_cache(maxsize=8)
def _edge_sampling(samples_along: int, samples_across: int, span: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """Sample positions of the edge fit: along a side (fractions t), across it (units of the
    half-width), and the midpoints between those (where a profile's differences lie)."""
    t = np.linspace(span[0], span[1], samples_along)
    unit = np.linspace(-1.0, 1.0, samples_across)
    out = (t, unit, 0.5 * (unit[1:] + unit[:-1]))
    for a in out:
        a.setflags(write=False)
    return out


@numba.njit(cache=True, nogil=True)
def _edge_points(prof: np.ndarray, s_mid: np.ndarray, focus: tuple[bool, float, float], g: np.ndarray,
                 sums: np.ndarray, off: np.ndarray, weight: np.ndarray) -> None:
    """One side's edge points from its profiles ``prof`` (m, k; float32: m samples from inside
    to outside at each of k places along the side): ``off`` (k) where along the normal (px, the
    sample midpoints at ``s_mid``) the rising gradient puts the edge (``focus``: peak or not,
    ``focus_px``; see :func:`refine_corners_edges`), ``weight`` (k) the gradient's mass, 0 where
    the profile brightens by ``min_contrast`` or less. ``g`` (m-1, k) and ``sums`` (2, k) are
    scratch. The k profiles go in lockstep (k innermost: independent sums, which the compiler
    vectorises; each profile's sums still run over its own samples in order)."""
    peak, focus_px, min_contrast = focus
    k = prof.shape[1]
    for i in range(k):
        weight[i] = 0.0
    for j in range(g.shape[0]):
        for i in range(k):
            g[j, i] = max(np.float64(prof[j + 1, i]) - np.float64(prof[j, i]), 0.0)
            weight[i] += g[j, i]
    if peak:   # start at the (smoothed) gradient's peak; a hard window of +-focus_px around the edge point
        for i in range(k):
            sums[0, i], off[i] = -1.0, s_mid[1]
        for j in range(g.shape[0] - 2):
            for i in range(k):
                smooth = g[j, i] + 2.0 * g[j + 1, i] + g[j + 2, i]
                if smooth > sums[0, i]:
                    sums[0, i], off[i] = smooth, s_mid[j + 1]
        for _focus in range(3):
            sums[:] = 0.0
            for j in range(g.shape[0]):
                for i in range(k):
                    d = s_mid[j] - off[i]
                    if abs(d) <= focus_px:
                        sums[0, i] += g[j, i] * d
                        sums[1, i] += g[j, i]
            for i in range(k):
                off[i] = off[i] + sums[0, i] / max(sums[1, i], 1e-12)
    else:   # the centroid of the whole profile's gradient, then twice under tent weights focus_px - |d| around the last
        sums[:] = 0.0
        for j in range(g.shape[0]):
            for i in range(k):
                sums[0, i] += g[j, i] * s_mid[j]
                sums[1, i] += g[j, i]
        for i in range(k):
            off[i] = sums[0, i] / max(sums[1, i], 1e-12)
        for _focus in range(2):
            sums[:] = 0.0
            for j in range(g.shape[0]):
                for i in range(k):
                    gf = g[j, i] * max(focus_px - abs(s_mid[j] - off[i]), 0.0)
                    sums[0, i] += gf * s_mid[j]
                    sums[1, i] += gf
            for i in range(k):
                off[i] = sums[0, i] / max(sums[1, i], 1e-12)
    for i in range(k):
        rise = np.float64(prof[-1, i]) - np.float64(prof[0, i])
        weight[i] = weight[i] if weight[i] > 1e-6 and rise > min_contrast else 0.0


@numba.njit(cache=True, nogil=True)
def _line_fit(weight: np.ndarray, off: np.ndarray, t: np.ndarray) -> tuple[float, float, float]:
    """``off = a + b t`` by weighted least squares: ``(a, b, the weights' sum)``; NaN with fewer
    than two usable points."""
    s0 = s1 = s2 = sy = sty = 0.0
    for i in range(t.shape[0]):
        wi, ti = weight[i], t[i]
        s0 += wi
        s1 += wi * ti
        s2 += wi * ti * ti
        sy += wi * off[i]
        sty += wi * ti * off[i]
    den = s0 * s2 - s1 * s1
    if not den > 1e-12:
        return math.nan, math.nan, s0
    b = (s0 * sty - s1 * sy) / den
    return (sy - b * s1) / s0, b, s0


@numba.njit(cache=True, nogil=True)
def _fit_buffers(n_markers: int, k: int, m: int) -> tuple[_Sides, np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """What one fit of ``n_markers`` quads with k samples along and m across each side writes,
    allocated once for all of a call's fits (a fit allocates nothing): ``(sides, prof, xy,
    scratch)``, :func:`_side_samples`' ``(p, v, n, length, w)``, the profiles (M, 4, m, k;
    float32), :func:`_profiles`' and :func:`_fitted_corners`' scratch."""
    sides = (np.empty((n_markers, 4, m, k), np.complex128), np.empty((n_markers, 4), np.complex128),
             np.empty((n_markers, 4), np.complex128), np.empty((n_markers, 4)), np.empty((n_markers, 4)))
    scratch = (np.empty((m - 1, k)), np.empty((2, k)), np.empty(m - 1), np.empty(k), np.empty(k),
               np.empty(4, np.complex128), np.empty(4, np.complex128))
    samples = n_markers * 4 * m * k
    return sides, np.empty((n_markers, 4, m, k), np.float32), np.empty((2, samples), np.float32), scratch


@numba.njit(cache=True, nogil=True)
def _side_samples(z: np.ndarray, width_per_side: np.ndarray, t: np.ndarray, unit: np.ndarray, sides: _Sides) -> None:
    """Where the edge fit samples the quads ``z`` (M, 4; complex x + iy), into ``sides`` = ``(p,
    v, n, length, w)``: the positions (M, 4, m, k) at ``unit`` half-widths across each side and
    fractions ``t`` along it, each side's vector (corner i -> i + 1), outward unit normal
    (clockwise, y down) and length, and its half-width ``w``: ``width_per_side`` (M, 1; or 1, 1
    for all) x the two neighbouring sides, in [1.5, 4] px."""
    p, v, n, length, w = sides
    n_markers, k, m = z.shape[0], t.shape[0], unit.shape[0]
    last = width_per_side.shape[0] - 1
    for q in range(n_markers):
        for side in range(4):
            v[q, side] = z[q, (side + 1) % 4] - z[q, side]
            length[q, side] = abs(v[q, side])
            n[q, side] = v[q, side] * (-1j / max(length[q, side], 1e-9))
        for side in range(4):
            around = length[q, (side + 1) % 4] + length[q, (side + 3) % 4]
            w[q, side] = min(max(around * width_per_side[min(q, last), 0], 1.5), 4.0)
            across = w[q, side] * n[q, side]
            for i in range(k):
                at = z[q, side] + t[i] * v[q, side]
                for j in range(m):   # at + unit[j] * across without the complex product's zero terms
                    p[q, side, j, i] = complex(at.real + unit[j] * across.real, at.imag + unit[j] * across.imag)


def _fma32_typed(typingctx: object, a: object, b: object, c: object) -> tuple[object, Callable[..., object]]:
    """numba's typing and code of :data:`_fma32`."""
    def codegen(context: object, builder: ir.IRBuilder, sig: object, args: list[ir.Value]) -> ir.Value:
        f32 = ir.FloatType()
        return builder.call(builder.module.declare_intrinsic("llvm.fma", [f32], ir.FunctionType(f32, [f32] * 3)),
                            args)
    return types.float32(types.float32, types.float32, types.float32), codegen


# a * b + c of float32 values rounded once (LLVM's fused multiply-add), as OpenCV's vectorised remap computes it
_fma32 = cast(Callable[[np.float32, np.float32, np.float32], np.float32], intrinsic(_fma32_typed))


@numba.njit(cache=True, nogil=True, inline="always")
def _bilinear(img: np.ndarray, x0: np.unsignedinteger[Any], y0: np.unsignedinteger[Any], x1: np.unsignedinteger[Any],
              y1: np.unsignedinteger[Any], ax: np.float32, ay: np.float32) -> np.float32:
    """``cv2.remap``'s bilinear sample of ``img`` between the pixels x0, x1 and y0, y1 (unsigned:
    no wrap-around code) at the fractions ``ax``, ``ay``: two fused multiply-adds along x, one along y."""
    p00, p01 = np.float32(img[y0, x0]), np.float32(img[y0, x1])
    p10, p11 = np.float32(img[y1, x0]), np.float32(img[y1, x1])
    top, bottom = _fma32(ax, p01 - p00, p00), _fma32(ax, p11 - p10, p10)
    return _fma32(ay, bottom - top, top)


@numba.njit(cache=True, nogil=True)
def _profiles(img: np.ndarray, p: np.ndarray, xy: np.ndarray, out: np.ndarray) -> None:
    """``img`` (H, W; 8-bit or float32) sampled at the positions ``p`` (1-D, N; complex x + iy,
    pixels) into ``out`` (float32, N): what ``cv2.remap`` of ``img`` as float32 at ``p`` as a
    float32 map (``INTER_LINEAR``, ``BORDER_REPLICATE``) gives in OpenCV 5, to the bit — its
    arithmetic in its order: the float32 position's fractions, two fused multiply-adds along x
    and one along y (tests/unit/detect/test_compiled_kernels.py compares the two) — without a
    call per fit. ``xy`` (2, N; float32) is scratch: the positions as float32, so that when all
    lie inside the image (a fit's usual case) one loop without the border's branch samples them."""
    height, width = img.shape
    x_inside, y_inside = np.float32(width - 1), np.float32(height - 1)
    outside = 0
    for s in range(p.shape[0]):
        x, y = np.float32(p[s].real), np.float32(p[s].imag)
        xy[0, s], xy[1, s] = x, y
        outside += not (x >= 0.0 and x < x_inside and y >= 0.0 and y < y_inside)
    if outside == 0:
        for s in range(p.shape[0]):
            x, y = xy[0, s], xy[1, s]
            cx, cy = np.int32(x), np.int32(y)   # the pixel cell, as the loop below has it
            out[s] = _bilinear(img, np.uint32(cx), np.uint32(cy), np.uint32(cx + 1), np.uint32(cy + 1),
                               x - np.float32(cx), y - np.float32(cy))
        return
    for s in range(p.shape[0]):
        x, y = xy[0, s], xy[1, s]
        if x >= 0.0 and x < x_inside and y >= 0.0 and y < y_inside:
            ix, iy = int(x), int(y)
            x0, y0, x1, y1 = numba.uint64(ix), numba.uint64(iy), numba.uint64(ix + 1), numba.uint64(iy + 1)
        else:   # the border's pixels replicated (a position beyond -1 or NaN as at -1, beyond the end as at it)
            x = x if x > -1.0 else np.float32(-1.0)
            y = y if y > -1.0 else np.float32(-1.0)
            x, y = min(x, np.float32(width)), min(y, np.float32(height))
            ix, iy = int(math.floor(x)), int(math.floor(y))
            x0, x1 = numba.uint64(min(max(ix, 0), width - 1)), numba.uint64(min(max(ix + 1, 0), width - 1))
            y0, y1 = numba.uint64(min(max(iy, 0), height - 1)), numba.uint64(min(max(iy + 1, 0), height - 1))
        out[s] = _bilinear(img, x0, y0, x1, y1, x - np.float32(ix), y - np.float32(iy))


@numba.njit(cache=True, nogil=True)
def _finite_box(quads: np.ndarray, margin_px: int) -> tuple[np.ndarray, bool, int, int, int, int]:
    """For (M, 4, 2) quads: which have four finite corners, whether all do, and the box (x0, y0,
    x1, y1; pixels, end exclusive) around those quads' corners grown by ``margin_px`` (+ 2 at the
    far end), its start not below 0 (no quad finite: 0, 0, 0, 0)."""
    good = np.empty(quads.shape[0], dtype=np.bool_)
    lo_x, lo_y, hi_x, hi_y = math.inf, math.inf, -math.inf, -math.inf
    for q in range(quads.shape[0]):
        good[q] = corners_finite(quads, q)
        if good[q]:
            for c in range(4):
                lo_x, hi_x = min(lo_x, quads[q, c, 0]), max(hi_x, quads[q, c, 0])
                lo_y, hi_y = min(lo_y, quads[q, c, 1]), max(hi_y, quads[q, c, 1])
    if not good.any():
        return good, False, 0, 0, 0, 0
    return (good, bool(good.all()), max(int(lo_x) - margin_px, 0), max(int(lo_y) - margin_px, 0),
            int(hi_x) + margin_px + 2, int(hi_y) + margin_px + 2)


@numba.njit(cache=True, nogil=True)
def _fit_result(z: np.ndarray, z_in: np.ndarray, inv_modules: np.ndarray, fitted: np.ndarray, good: np.ndarray,
                origin: complex) -> np.ndarray:
    """The fitted corners ``z`` (M, 4; complex, in the region) as (M, 4, 2) pixels of the image
    (+ ``origin``); NaN for a marker whose start ``z_in`` was not finite (``good``), whose fit
    failed on a side or corner (``fitted``), or one of whose corners moved more than two modules
    (at least 3 px) from ``z_in``: more than 0.5 x the start's perimeter x ``inv_modules`` (M, 1;
    or 1, 1 for all)."""
    out = np.empty((z.shape[0], 4, 2))
    last = inv_modules.shape[0] - 1
    for q in range(z.shape[0]):
        perimeter = 0.0
        for c in range(4):
            perimeter += abs(z_in[q, (c + 1) % 4] - z_in[q, c])
        limit = max(0.5 * perimeter * inv_modules[min(q, last), 0], 3.0)
        ok = good[q]
        for c in range(4):
            ok = ok and fitted[q, c] and abs(z[q, c] - z_in[q, c]) <= limit
        for c in range(4):
            corner = z[q, c] + origin if ok else complex(math.nan, math.nan)
            out[q, c, 0], out[q, c, 1] = corner.real, corner.imag
    return out


@numba.njit(cache=True, nogil=True)
def _fitted_corners(prof: np.ndarray, z: np.ndarray, z0: np.ndarray, sides: _Sides, t: np.ndarray,
                    unit_mid: np.ndarray, focus: tuple[bool, float, float], fitted: np.ndarray,
                    scratch: tuple[np.ndarray, ...], out: np.ndarray) -> None:
    """One iteration of the edge fit after sampling, into ``out`` (M, 4): from the profiles
    ``prof`` (M, 4, m, k, float32) across the sides of the quads ``z`` (:func:`_side_samples`'
    ``sides``; ``scratch`` from :func:`_fit_buffers`), each side's edge points
    (:func:`_edge_points`; ``focus``: peak or not, ``focus_px``, ``min_contrast``), its line
    ``off = a + b t`` (px along the normal) fitted to them weighted by their gradient mass, once
    more without points beyond 2.5 sigma, and the corners where neighbouring lines meet.
    ``fitted`` (M, 4) is cleared where a side has fewer than 3 points or is shorter than 4 px or
    a corner is not finite; those markers' corners are ``z0``'s. One compiled pass: as numpy,
    ~40 calls per iteration over a few markers, and the calls were the cost."""
    _p, v, n, length, w = sides
    g, sums, s_mid, off, weight, base, direction = scratch   # side i: base + s direction
    n_markers, m, k = prof.shape[0], prof.shape[2], prof.shape[3]
    for q in range(n_markers):
        for side in range(4):
            for j in range(m - 1):
                s_mid[j] = unit_mid[j] * w[q, side]
            _edge_points(prof[q, side], s_mid, focus, g, sums, off, weight)
            a0, b0, s0 = _line_fit(weight, off, t)
            rms2 = 0.0
            for i in range(k):
                r = off[i] - (a0 + b0 * t[i])
                rms2 += weight[i] * r * r
            limit = max(6.25 * rms2 / max(s0, 1e-12), 0.01)   # no line (NaN): r is NaN, no point kept
            points = 0
            for i in range(k):
                r = off[i] - (a0 + b0 * t[i])
                if r * r <= limit and weight[i] > 0.0:
                    points += 1
                else:
                    weight[i] = 0.0
            a, b, _s0 = _line_fit(weight, off, t)
            base[side], direction[side] = z[q, side] + a * n[q, side], v[q, side] + b * n[q, side]
            if not (length[q, side] > 4.0 and points >= 3):
                fitted[q, side] = False
        for c in range(4):   # corner c: side c - 1 meets side c
            b1, d1 = base[(c + 3) % 4], direction[(c + 3) % 4]
            s = ((base[c] - b1).conjugate() * direction[c]).imag / (d1.conjugate() * direction[c]).imag
            out[q, c] = b1 + s * d1
            if not (math.isfinite(out[q, c].real) and math.isfinite(out[q, c].imag)):
                fitted[q, c] = False
        for c in range(4):
            if not fitted[q, c]:
                out[q, c] = z0[q, c]


@numba.njit(cache=True, nogil=True)
def _fitted_loop(img: np.ndarray, z0: np.ndarray, width_per_side: np.ndarray, t: np.ndarray, unit: np.ndarray,
                 unit_mid: np.ndarray, focus: tuple[bool, float, float], iterations: int, settled_px: float,
                 fitted: np.ndarray) -> np.ndarray:
    """The edge fits of the quads ``z0`` (M, 4) in ``img`` without a lens model, marker by marker:
    up to ``iterations`` fits, each sampling along the previous fit's sides (:func:`_side_samples`,
    :func:`_profiles`, :func:`_fitted_corners`), ending after a fit that moved none of the marker's
    corners by ``settled_px`` or more along either axis (0: never before ``iterations``)."""
    out = np.empty_like(z0)
    last = width_per_side.shape[0] - 1
    sides, prof, xy, scratch = _fit_buffers(1, t.shape[0], unit.shape[0])   # one marker at a time, every fit
    samples, values = sides[0].reshape(-1), prof.reshape(-1)
    z, fit = np.empty((1, 4), np.complex128), np.empty((1, 4), np.complex128)
    for q in range(z0.shape[0]):
        start, held, width = z0[q:q + 1], fitted[q:q + 1], width_per_side[min(q, last):min(q, last) + 1]
        z[:] = start
        for _ in range(iterations):
            _side_samples(z, width, t, unit, sides)
            _profiles(img, samples, xy, values)
            _fitted_corners(prof, z, start, sides, t, unit_mid, focus, held, scratch, fit)
            moved = 0.0
            for c in range(4):
                moved = max(moved, abs(fit[0, c].real - z[0, c].real), abs(fit[0, c].imag - z[0, c].imag))
            z, fit = fit, z
            if moved < settled_px:
                break
        out[q] = z[0]
    return out


@numba.njit(cache=True, nogil=True)
def _region(img: np.ndarray, quads: np.ndarray, crop: bool) -> tuple[np.ndarray, complex, np.ndarray, np.ndarray]:
    """What the fit of the (M, 4, 2) ``quads`` reads of ``img``: ``(region, origin, good, z)``,
    with ``crop`` the box around the finite quads grown by ``_ROI_MARGIN_PX`` (a view; the margin
    covers the sampling half-width and the moves) and its top-left corner (complex x + iy), else
    the whole image and 0; which quads are finite, and their corners in the region (M, 4;
    complex), a quad that is not finite at the image's origin."""
    good, _all_good, x0, y0, x1, y1 = _finite_box(quads, _ROI_MARGIN_PX)
    region, origin = img[:, :], 0j
    if crop and good.any():
        region, origin = img[y0:y1, x0:x1], complex(x0, y0)
    z = np.empty((quads.shape[0], 4), np.complex128)
    for q in range(quads.shape[0]):
        for c in range(4):
            z[q, c] = (complex(quads[q, c, 0], quads[q, c, 1]) if good[q] else 0j) - origin
    return region, origin, good, z


@numba.njit(cache=True, nogil=True)
def _pinhole_refined(img: np.ndarray, quads: np.ndarray, crop: bool, inv_modules: np.ndarray, t: np.ndarray,
                     unit: np.ndarray, unit_mid: np.ndarray, focus: tuple[bool, float, float], iterations: int,
                     settled_px: float) -> np.ndarray:
    """:func:`refine_corners_edges` without a lens model, in one call (at a few markers a frame the
    calls, not the arithmetic, are the cost): :func:`_region`, :func:`_fitted_loop`,
    :func:`_fit_result`."""
    region, origin, good, z_in = _region(img, quads, crop)
    fitted = np.ones(z_in.shape, np.bool_)   # per side and corner: the fit held
    # half-width 0.8 module = 0.4 x (sum of two neighbouring sides) / modules
    z = _fitted_loop(region, z_in, 0.4 * inv_modules, t, unit, unit_mid, focus, iterations, settled_px, fitted)
    return _fit_result(z, z_in, inv_modules, fitted, good, origin)


def compile_edge_fit() -> None:
    """Compile the edge fit's kernels (or load them from numba's on-disk cache, ``__pycache__``)
    for the argument types :func:`refine_corners_edges` passes, by fitting one synthetic marker
    both ways (``tent`` and ``peak``) in an 8-bit and a float32 image, with and without a lens
    model, so that no frame pays it: called at start-up, before the first frame
    (:class:`cubetrack.detect.detector.Detector` does)."""
    gray = np.full((48, 48), 200, dtype=np.uint8)
    gray[12:36, 12:36] = 20
    corners = np.array([[12.0, 12.0], [36.0, 12.0], [36.0, 36.0], [12.0, 36.0]])
    K = np.array([[50.0, 0.0, 24.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])
    for image in (gray, gray.astype(np.float32)):
        for focus in ("tent", "peak"):
            refine_corners_edges(image, corners, 6, focus=focus)
        refine_corners_edges(image, corners, 6, K=K, dist=np.array([-0.01, 0.0, 0.0, 0.0, 0.0]))


def refine_corners_edges(gray: np.ndarray, corners_px: np.ndarray, modules: int | np.ndarray,
                         iterations: int = 2, *, K: np.ndarray | None = None,
                         dist: np.ndarray | None = None, samples_along: int = 12,
                         samples_across: int = _EDGE_SAMPLES_ACROSS, span: tuple[float, float] = _EDGE_SPAN,
                         focus: str = "tent", focus_px: float | None = None,
                         min_contrast: float = 8.0, settled_px: float = 0.0) -> np.ndarray:
    """Refine marker corners by fitting a line to each side's outer edge (the ``edge`` method).

    ``gray``: the image (8-bit: only the quads' region is read, its samples interpolated in
    float32, as ``cv2.remap`` of a float32 image: rounded samples bias an edge by ~0.03 px; or
    float32); ``corners_px``: (4, 2)
    or (M, 4, 2) initial corners (TL, TR, BR, BL, clockwise in the image); ``modules``: cells
    across each marker including its black border (6 for a 4x4 dictionary).

    Along each side, at ``samples_along`` places spread over ``span`` (fractions of its length),
    the image is sampled across the edge at ``samples_across`` points (bilinear; half-width
    0.8 module, clipped to [1.5, 4] px), and the positive (dark inside -> bright outside)
    gradient locates the edge point. ``focus='tent'`` (the detector's): the gradient's centroid
    over the whole profile, re-centred twice with a tent of half-width ``focus_px`` (3 px)
    around it — steady under noise, and a second edge nearby (the outer edge of a narrow white
    margin or of the cube) barely pulls it. ``focus='peak'`` (calibration's): the gradient's
    peak, re-centred three times on the gradient within ``focus_px`` (1.25 px) of it — no pull
    from a margin's outer edge even under blur (marker size bias ~0.001 px against ~0.02 px),
    noisier per frame, so for averaging many frames. A profile is used when it brightens by more
    than ``min_contrast`` grey levels from its inner to its outer end. Each side's edge points
    get a weighted least-squares line (offset across the side against position along it), once
    more without points beyond 2.5 sigma; neighbouring lines intersect in the corners. This
    repeats ``iterations`` times, each sampling along the previous fit's sides; with
    ``settled_px`` above 0 (without a lens model) a marker's fits end sooner, after one that moved
    none of its corners by ``settled_px`` or more along either axis.

    With the camera's lens model (``K`` and plumb_bob ``dist``) the sides are straight lines in
    the undistorted image, not in this one: the sampling runs along them there, each sample is
    looked up at its distorted position, and the corners are mapped back. Without it the sides
    are taken as straight in the image (exact for a pinhole camera; the detector's default).

    Returns corners of the input's shape, in the input image; a marker whose fit fails (low
    contrast, fewer than 3 edge points on a side, a degenerate quad, a corner moving more than
    two modules) gets NaN corners, so the caller can keep its initial ones or drop the marker.
    Compiled over markers and sides (complex x + iy positions); without a lens model all the
    iterations are one compiled call (the calls, not the arithmetic, are the cost at a few markers
    per frame), its corners those of the earlier ``cv2.remap`` sampling to the bit.
    """
    img = np.asarray(gray)
    crop = img.dtype != np.float32   # only the quads' region of an 8-bit image is read
    # samples as float32 (of an 8-bit image, exact: rounded ones bias an edge by ~0.03 px)
    img = np.ascontiguousarray(img if img.dtype in (np.uint8, np.float32) else img.astype(np.float32))
    c_in = np.ascontiguousarray(corners_px, dtype=np.float64)
    single = c_in.ndim == 2
    quads = c_in.reshape(-1, 4, 2)
    inv_modules = 1.0 / np.asarray(modules, dtype=np.float64).reshape(-1, 1)
    if focus not in ("tent", "peak"):
        raise ValueError(f"focus must be 'tent' or 'peak', got {focus!r}")
    peak = focus == "peak"
    if focus_px is None:
        focus_px = _PEAK_WINDOW_PX if peak else _EDGE_FOCUS_PX
    t, unit, unit_mid = _edge_sampling(samples_along, samples_across, tuple(span))
    fit_focus = (peak, float(focus_px), float(min_contrast))
    if K is None or dist is None or not np.any(np.asarray(dist) != 0.0):
        c = _pinhole_refined(img, quads, crop, inv_modules, t, unit, unit_mid, fit_focus, iterations, settled_px)
        return c[0] if single else c
    region, origin, good, z_in = _region(img, quads, crop)
    region = np.ascontiguousarray(region)   # one layout for the kernels, whichever box it is
    K = np.array(K, dtype=np.float64)
    K[0, 2] -= origin.real  # the region's own principal point
    K[1, 2] -= origin.imag
    lens = (K, np.asarray(dist, dtype=np.float64).reshape(-1))
    z0 = _undistort_c(z_in, *lens)                                      # corners in the pinhole image
    fitted = np.ones(z0.shape, dtype=bool)   # per side and corner: the fit held (a failed marker's
    # corners restart from the initial ones, so the next iteration samples finite positions)
    z, fit = z0.copy(), np.empty_like(z0)
    sides, prof, xy, scratch = _fit_buffers(z0.shape[0], t.shape[0], unit.shape[0])
    for _ in range(iterations):   # _fitted_loop's steps, each sample looked up at its distorted position
        _side_samples(z, 0.4 * inv_modules, t, unit, sides)
        _profiles(region, _distort_c(sides[0], *lens).reshape(-1), xy, prof.reshape(-1))
        _fitted_corners(prof, z, z0, sides, t, unit_mid, fit_focus, fitted, scratch, fit)
        z, fit = fit, z
    # a corner moving more than two modules (at least 3 px) is a failed fit
    c = _fit_result(_distort_c(z, *lens), z_in, inv_modules, fitted, good, origin)
    return c[0] if single else c
