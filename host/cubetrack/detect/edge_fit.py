"""The ``edge`` corner refinement: a line fitted to each side's sub-pixel outer edge.

Used by the detector (``[detector] corner_refinement = "edge"``, and as the start of the
``template`` fit) and by calibration, which fits the world marker's edges through the camera's
lens model (:func:`refine_corners_edges` with ``K`` and ``dist``). A marker is dark on a bright
margin here; the detector hands inverted (white-on-black) markers over in the negated image.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from cubetrack.core.geometry import undistort_points
from cubetrack.detect.template_fit import distort_px

_ROI_MARGIN_PX = 16  # refine_corners_edges: float copy of the quads' region plus this
# side i of a quad runs from corner i to corner i + 1; x.take(NEXT_I, axis=1) is x[:, NEXT_I]
# at a fifth of the cost (no fancy-indexing machinery for a handful of markers)
NEXT_I = np.array([1, 2, 3, 0])
PREV_I = np.array([3, 0, 1, 2])


_EDGE_SPAN = (0.2, 0.8)       # the detector's edge samples: the middle 60 % of each side
_EDGE_SAMPLES_ACROSS = 17     # profile samples across an edge
_EDGE_FOCUS_PX = 3.0          # focus='tent': half-width of the tent that re-centres each edge point, px
_PEAK_WINDOW_PX = 1.25        # focus='peak': half-width of the window around the gradient's peak, px


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
    """Sample positions of the edge fit: along a side (fractions t, and the powers 1, t, t^2
    per row), across it (units of the half-width), the midpoints between those, the matrix
    taking a profile to its differences (m, m-1), and the midpoints beside ones (m-1, 2: a
    profile's moments in one product)."""
    t = np.linspace(span[0], span[1], samples_along)
    unit = np.linspace(-1.0, 1.0, samples_across)
    unit_mid = 0.5 * (unit[1:] + unit[:-1])
    step = np.eye(samples_across, samples_across - 1, -1) - np.eye(samples_across, samples_across - 1)
    out = (t, np.stack([np.ones_like(t), t, t * t], axis=1), unit, unit_mid, step,
           np.stack([unit_mid, np.ones_like(unit_mid)], axis=1))
    for a in out:
        a.setflags(write=False)
    return out


def refine_corners_edges(gray: np.ndarray, corners_px: np.ndarray, modules: int | np.ndarray,
                         iterations: int = 2, *, K: np.ndarray | None = None,
                         dist: np.ndarray | None = None, samples_along: int = 12,
                         samples_across: int = _EDGE_SAMPLES_ACROSS, span: tuple[float, float] = _EDGE_SPAN,
                         focus: str = "tent", focus_px: float | None = None,
                         min_contrast: float = 8.0) -> np.ndarray:
    """Refine marker corners by fitting a line to each side's outer edge (the ``edge`` method).

    ``gray``: the image (8-bit: only the quads' region is converted to float, since an 8-bit
    ``cv2.remap`` rounds its samples, a ~0.03 px edge bias; or float32); ``corners_px``: (4, 2)
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
    repeats ``iterations`` times, each sampling along the previous fit's sides.

    With the camera's lens model (``K`` and plumb_bob ``dist``) the sides are straight lines in
    the undistorted image, not in this one: the sampling runs along them there, each sample is
    looked up at its distorted position, and the corners are mapped back. Without it the sides
    are taken as straight in the image (exact for a pinhole camera; the detector's default).

    Returns corners of the input's shape, in the input image; a marker whose fit fails (low
    contrast, fewer than 3 edge points on a side, a degenerate quad, a corner moving more than
    two modules) gets NaN corners, so the caller can keep its initial ones or drop the marker.
    Vectorised over markers and sides (complex x + iy positions keep the numpy calls few: they,
    not the arithmetic, are the cost at a few markers per frame).
    """
    img = np.asarray(gray)
    c_in = np.ascontiguousarray(corners_px, dtype=np.float64)
    single = c_in.ndim == 2
    z_in = c_in.view(np.complex128).reshape(-1, 4)                     # (M, 4) x + iy (a view)
    # numpy's stubs type .all(axis=1) as a bool or an array; along an axis it is an array
    good: np.ndarray = np.isfinite(z_in).all(axis=1)  # type: ignore[assignment]
    if not good.all():
        z_in = np.where(good[:, None], z_in, 0.0)
    origin: complex = 0.0
    if img.dtype != np.float32:
        # only the region around the quads, as float (cv2.remap of an 8-bit image rounds its
        # samples: a ~0.03 px edge bias); the margin covers the sampling half-width and the moves
        if good.any():
            xy = c_in.reshape(-1, 2) if good.all() else c_in.reshape(-1, 4, 2)[good].reshape(-1, 2)
            (x0, y0), (x1, y1) = xy.min(axis=0).tolist(), xy.max(axis=0).tolist()
            x0, y0 = max(int(x0) - _ROI_MARGIN_PX, 0), max(int(y0) - _ROI_MARGIN_PX, 0)
            x1, y1 = int(x1) + _ROI_MARGIN_PX + 2, int(y1) + _ROI_MARGIN_PX + 2
            img, origin = img[y0:y1, x0:x1], complex(x0, y0)
            z_in = z_in - origin
        img = img.astype(np.float32)
    inv_modules = 1.0 / np.asarray(modules, dtype=np.float64).reshape(-1, 1)
    width_per_side = 0.4 * inv_modules      # half-width 0.8 module = 0.4 x (sum of two neighbouring sides) / modules
    lens = None
    if K is not None and dist is not None and np.any(np.asarray(dist) != 0.0):
        K = np.array(K, dtype=np.float64)
        K[0, 2] -= origin.real  # the region's own principal point
        K[1, 2] -= origin.imag
        lens = (K, np.asarray(dist, dtype=np.float64).reshape(-1))
        z0 = _undistort_c(z_in, *lens)                                  # corners in the pinhole image
    else:
        z0 = z_in
    if focus not in ("tent", "peak"):
        raise ValueError(f"focus must be 'tent' or 'peak', got {focus!r}")
    peak = focus == "peak"
    if focus_px is None:
        focus_px = _PEAK_WINDOW_PX if peak else _EDGE_FOCUS_PX
    t, powers_t, unit, unit_mid, step, across = _edge_sampling(samples_along, samples_across, tuple(span))
    ones_t, k, moments_t = powers_t[:, 0], len(t), powers_t.T
    z = z0
    side_px = np.abs(z.take(NEXT_I, axis=1) - z)  # the initial quad's side lengths (pinhole image)
    fitted = np.ones(z.shape, dtype=bool)   # per side and corner: the fit held (a failed marker's
    # corners restart from the initial ones, so the next iteration samples finite positions)
    # few numpy calls per iteration, each over every marker, side and sample at once: they, not
    # the arithmetic, are the cost; sums over samples are matrix products with constant vectors
    for _ in range(iterations):
        v = z.take(NEXT_I, axis=1) - z                                 # side i: corner i -> i+1
        length = np.abs(v)                                              # (M, 4) px
        n = v * (-1j / np.maximum(length, 1e-9))                        # outward unit normal (clockwise, y down)
        w = np.minimum(np.maximum((length.take(NEXT_I, axis=1) + length.take(PREV_I, axis=1)) * width_per_side,
                                  1.5), 4.0)
        p = (z[..., None] + t * v[..., None])[..., None] + unit * (w * n)[..., None, None]   # (M, 4, k, m)
        if lens is not None:
            p = _distort_c(p, *lens)
        xy = p.view(np.float64).reshape(1, -1, 2).astype(np.float32)  # interleaved x, y: one map
        # map1 holds both coordinates, so map2 is None (OpenCV's stubs do not allow None there)
        prof = cv2.remap(img, xy, None, cv2.INTER_LINEAR,  # type: ignore[call-overload]
                         borderMode=cv2.BORDER_REPLICATE).reshape(p.shape).astype(np.float64)
        # edge point along n from the rising gradient (see focus)
        g = np.maximum(prof @ step, 0.0)                                # (M, 4, k, m-1) differences
        wide = w[..., None]                                             # (M, 4, 1) half-width px
        if peak:   # start at the gradient's peak; a hard window of +-focus_px around the edge point
            mass = g @ across[:, 1]
            smooth = g[..., :-2] + 2.0 * g[..., 1:-1] + g[..., 2:]       # a steadier peak
            off = unit_mid[smooth.argmax(axis=-1) + 1] * wide
            s_mid = (unit_mid * wide[..., None])                        # (M, 4, 1, m-1) px
            for _focus in range(3):
                d = s_mid - off[..., None]
                gf = g * (np.abs(d) <= focus_px)
                off = off + (gf * d) @ across[:, 1] / np.maximum(gf @ across[:, 1], 1e-12)
        else:      # start at the centroid of the whole profile's gradient; a tent of half-width focus_px
            moments = g @ across                                        # (M, 4, k, 2): sum g u, sum g
            mass = moments[..., 1]
            off = wide * moments[..., 0] / np.maximum(mass, 1e-12)      # (M, 4, k) px along n
            s_mid = (unit_mid * wide[..., None])
            for _focus in range(2):
                # the centroid under tent weights focus_px - |d| (the scale cancels) around the last
                gf = g * np.maximum(focus_px - np.abs(s_mid - off[..., None]), 0.0)
                moments = gf @ across
                off = wide * moments[..., 0] / np.maximum(moments[..., 1], 1e-12)
        weight = mass * ((mass > 1e-6) & (prof[..., -1] - prof[..., 0] > min_contrast))
        # each side: off = a + b t by weighted least squares (edge points scatter across the
        # side only), then once more without points beyond 2.5 sigma of that line
        a: np.ndarray  # a, b, s0: bound by the first (robust=False) pass
        b: np.ndarray
        s0: np.ndarray
        for robust in (False, True):
            if robust:
                resid2 = off - (a[..., None] + b[..., None] * t)  # noqa: F821 (see above)
                resid2 *= resid2
                rms2 = (weight * resid2) @ ones_t / np.maximum(s0, 1e-12)  # noqa: F821 (see above)
                weight = weight * (resid2 <= np.maximum(6.25 * rms2, 0.01)[..., None])
            s0, s1, s2 = (moments_t @ weight.reshape(-1, k).T).reshape(3, -1, 4)   # (M, 4) each
            sy, sty = (moments_t[:2] @ (weight * off).reshape(-1, k).T).reshape(2, -1, 4)
            den = s0 * s2 - s1 * s1
            den[den <= 1e-12] = np.nan                                  # < 2 usable points: no line
            b = (s0 * sty - s1 * sy) / den
            a = (sy - b * s1) / s0
        # side i is the line P + s D; corner i = side i-1 meets side i
        P, D = z + a * n, v + b * n
        P1, D1 = P.take(PREV_I, axis=1), D.take(PREV_I, axis=1)
        s = ((P - P1).conj() * D).imag / (D1.conj() * D).imag
        z = P1 + s * D1
        fitted &= (length > 4.0) & (np.sign(weight) @ ones_t >= 3.0) & np.isfinite(z)
        z = np.where(fitted, z, z0)
    good &= fitted.all(axis=1)
    if lens is not None:
        z = _distort_c(z, *lens)
        side_px = np.abs(z_in.take(NEXT_I, axis=1) - z_in)
    # a corner moving more than two modules (at least 3 px) is a failed fit
    moved = np.abs(z - z_in).max(axis=1)
    good &= moved <= np.maximum(0.5 * side_px.sum(axis=1) * inv_modules[:, 0], 3.0)   # 2 x mean side
    z = np.where(good[:, None], z + origin, complex(np.nan, np.nan))
    c = z.view(np.float64).reshape(*z.shape, 2)
    return c[0] if single else c
