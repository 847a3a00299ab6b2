"""ChArUco views picked from a live camera for intrinsic calibration (``cubetrack
calibrate-intrinsics --camera usb:0``): frames come in as the user moves the board; a frame is
kept as a view when the board is found with enough corners and it shows something the kept
views do not (:class:`ViewPicker`), and the guidance says where the board has not been yet.

A view is kept when its ChArUco corners reach a cell of a ``grid`` x ``grid`` division of the
image that no kept view reached (the distortion model needs corners out to the edges and
corners), or when the board's apparent shape differs from every kept view's (its tilt: the
ratio of the board's two side lengths in the image, by ``min_tilt_change``; focal length needs
tilted views), and at least ``min_interval_s`` after the last kept view (the board moved on,
not one pose kept twice).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from cubetrack.calib.intrinsics import IntrinsicsParams, _charuco_detector, make_board
from cubetrack.core.errors import SourceError
from cubetrack.core.records import Frame
from cubetrack.detect.decode import decode_gray
from cubetrack.source.streams import LiveCameras, SourceParams

log = logging.getLogger(__name__)

_ROWS = ("top", "middle", "bottom")
_COLS = ("left", "centre", "right")


@dataclass(frozen=True, slots=True)
class PickedView:
    """What one frame showed: ChArUco corners found and whether it was kept (and why not)."""

    name: str
    corners: int
    kept: bool
    reason: str = ""


@dataclass(slots=True)
class ViewPicker:
    """Keeps views of the board from a stream of grayscale frames (module doc)."""

    params: IntrinsicsParams = IntrinsicsParams()
    target_views: int = 15
    grid: int = 3
    min_tilt_change: float = 0.08
    min_interval_s: float = 0.7
    views: list[tuple[str, np.ndarray]] = field(default_factory=list)
    covered: set[tuple[int, int]] = field(default_factory=set)
    tilts: list[tuple[float, float]] = field(default_factory=list)
    last_kept_s: float = float("-inf")
    _detector: object = None
    _board: object = None

    @property
    def done(self) -> bool:
        return len(self.views) >= self.target_views

    def offer(self, name: str, gray: np.ndarray, time_s: float) -> PickedView:
        """Look at one frame (taken at ``time_s``, seconds); keep it as a view if it adds something."""
        if self._detector is None:
            self._board = make_board(self.params)
            self._detector = _charuco_detector(self._board, self.params)
        corners, ids, _, _ = self._detector.detectBoard(gray)  # type: ignore[attr-defined]
        n = 0 if ids is None else len(ids)
        if n < self.params.min_corners:
            return PickedView(name, n, False, f"{n} corners (< {self.params.min_corners})")
        if time_s - self.last_kept_s < self.min_interval_s:
            return PickedView(name, n, False, "too soon after the last view")
        h, w = gray.shape[:2]
        points = corners.reshape(-1, 2)
        cells = {(min(int(y * self.grid / h), self.grid - 1), min(int(x * self.grid / w), self.grid - 1))
                 for x, y in points}
        tilt = _tilt(points, ids.reshape(-1), self.params.squares_x - 1)
        new_cells = cells - self.covered
        new_tilt = all(max(abs(tilt[0] - a), abs(tilt[1] - b)) >= self.min_tilt_change for a, b in self.tilts)
        if not new_cells and not new_tilt:
            return PickedView(name, n, False, "nothing new: move or tilt the board")
        self.views.append((name, gray))
        self.covered |= cells
        self.tilts.append(tilt)
        self.last_kept_s = time_s
        return PickedView(name, n, True)

    def guidance(self) -> str:
        """One line: views kept, image coverage, and where the board has not been yet."""
        missing = [self.cell_name(r, c) for r in range(self.grid) for c in range(self.grid)
                   if (r, c) not in self.covered]
        text = f"{len(self.views)}/{self.target_views} views, {len(self.covered)}/{self.grid ** 2} of the image covered"
        if missing:
            return f"{text}; move the board to: {', '.join(missing)}"
        if len(self.tilts) < self.target_views:
            return f"{text}; now tilt the board (left/right, up/down) at different distances"
        return text

    def cell_name(self, row: int, col: int) -> str:
        if self.grid == 3:
            return "centre" if (row, col) == (1, 1) else f"{_ROWS[row]} {_COLS[col]}"
        return f"row {row + 1} column {col + 1}"


def _tilt(points: np.ndarray, ids: np.ndarray, per_row: int) -> tuple[float, float]:
    """The board's apparent foreshortening: the spread, relative to their mean, of the image
    lengths of its corner rows (horizontal tilt) and of its corner columns (vertical tilt)."""
    by_id = dict(sorted((int(i), p) for i, p in zip(ids, points, strict=True)))
    rows: dict[int, list[np.ndarray]] = {}
    cols: dict[int, list[np.ndarray]] = {}
    for i, p in by_id.items():
        rows.setdefault(i // per_row, []).append(p)
        cols.setdefault(i % per_row, []).append(p)
    return _spread(rows), _spread(cols)


def _spread(lines: dict[int, list[np.ndarray]]) -> float:
    """(longest - shortest) / mean of the unit spacing along each line of corners with 2 or more."""
    spacings = []
    for pts in lines.values():
        if len(pts) >= 2:
            a = np.array(pts)
            spacings.append(float(np.linalg.norm(a[-1] - a[0])) / (len(a) - 1))
    if len(spacings) < 2:
        return 0.0
    return (max(spacings) - min(spacings)) / float(np.mean(spacings))


def pick_views_live(url: str, picker: ViewPicker, duration_s: float, report: Callable[[PickedView, str], None],
                    source: SourceParams | None = None, stop: Callable[[], bool] = lambda: False) -> None:
    """Read the camera at ``url`` (any camera URL: ``usb:0``, ``http://...``, ``file:...``) and offer
    its frames to ``picker`` until it has its views, ``duration_s`` has passed, ``stop()`` or the
    camera's end (a video file); ``report(view, guidance)`` after each frame looked at. Frames that
    come while one is being looked at are dropped (the newest is looked at next)."""
    deadline = time.monotonic() + duration_s
    with LiveCameras({"camera": url}, source or SourceParams()) as live:
        while not picker.done and not stop() and (left := deadline - time.monotonic()) > 0:
            event = live.get(min(left, 0.5), newest_first=True)
            if not isinstance(event, Frame):
                stats = live.stats()["camera"]
                if event is None and not stats.connected and stats.last_error.startswith("end of the video"):
                    return
                continue
            view = picker.offer(f"frame {event.seq}", decode_gray(event.jpeg, f"{url} frame {event.seq}"),
                                event.host_time_s)
            report(view, picker.guidance())
    if not picker.views:
        raise SourceError(f"{url}: no view of the board with at least {picker.params.min_corners} corners in "
                          f"{duration_s:g} s — is the board in view, and are --board and --dictionary right?")
