"""The recording folder (contracts §3): one reader and one writer, shared by ``cubetrack
simulate``, the live recorder, the emulator and offline tracking.

Layout::

    <dir>/recording.json
    <dir>/<camera>/index.csv          seq,device_time,host_time,file
    <dir>/<camera>/<file>.jpg
    <dir>/<camera>/clock.csv          host_send,device_time,host_recv   (optional)
    <dir>/camera_info/<camera>.yaml   (optional)
    <dir>/ground_truth.tum            (optional)

Times are seconds: ``device_time`` on the node's clock since boot, host times Unix time.
A broken index row or a missing JPEG is skipped and counted (``Recording.skipped``), never
fatal; a recording with no usable frame at all is an error.
"""

from __future__ import annotations

import csv
import heapq
import io
import json
import logging
import math
import re
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cubetrack.core.cameras import ClockSample
from cubetrack.core.errors import RecordingError
from cubetrack.core.records import Frame
from cubetrack.io.files import LineFile, atomic_write, os_errors_as

log = logging.getLogger(__name__)

FORMAT = "cubetrack.recording"
VERSION = 1
INDEX_HEADER = ("seq", "device_time", "host_time", "file")
CLOCK_HEADER = ("host_send", "device_time", "host_recv")
_CAMERA_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


@dataclass(frozen=True, slots=True)
class CameraEntry:
    """A camera of a recording: its name (also its folder) and where its frames came from."""

    name: str
    source: str = ""


@dataclass(frozen=True, slots=True)
class IndexRow:
    """One frame of ``index.csv``: X-Frame, X-Timestamp (s), host arrival time (Unix s), file."""

    seq: int
    device_time_s: float
    host_time_s: float
    file: str


def check_camera_name(name: str) -> str:
    """Refuse camera names that cannot be a folder name (they become ``<dir>/<camera>/``)."""
    if not isinstance(name, str) or not _CAMERA_NAME.match(name) or name in (".", ".."):
        raise RecordingError(
            f"camera name {name!r} is not usable as a folder name: use letters, digits, '_', '-', '.'"
        )
    return name


def _fmt(t: float) -> str:
    return f"{t:.6f}"


class Recording:
    """Read-only view of a recording folder. Open with :meth:`Recording.open`."""

    def __init__(self, path: Path, cameras: tuple[CameraEntry, ...], created: str):
        self.path = path
        self.cameras = cameras
        self.created = created
        self.skipped: Counter[str] = Counter()  # reason -> count, filled while reading
        self._index: dict[str, list[IndexRow]] = {}  # camera -> valid rows (read once)
        self._clock: dict[str, list[ClockSample]] = {}  # camera -> round trips (read once)
        self._missing: set[tuple[str, str]] = set()  # (camera, file) already counted as missing

    @classmethod
    def open(cls, path: str | Path) -> Recording:
        """Open a recording folder, checking ``recording.json``."""
        path = Path(path)
        meta_path = path / "recording.json"
        if not path.is_dir():
            raise RecordingError(f"{path}: recording folder not found")
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise RecordingError(f"{meta_path}: missing; {path} is not a recording folder") from None
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise RecordingError(f"{meta_path}: not valid JSON: {exc}") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise RecordingError(f'{meta_path}: "format" must be "{FORMAT}"')
        if meta.get("version") != VERSION:
            raise RecordingError(f"{meta_path}: version {meta.get('version')!r} is not supported ({VERSION})")
        rows = meta.get("cameras")
        if not isinstance(rows, list) or not rows:
            raise RecordingError(f'{meta_path}: "cameras" must list at least one camera')
        try:
            cameras = tuple(
                CameraEntry(check_camera_name(row["name"]), str(row.get("source", ""))) for row in rows
            )
        except (TypeError, KeyError):
            raise RecordingError(f'{meta_path}: each camera needs a "name"') from None
        except RecordingError as exc:
            raise RecordingError(f"{meta_path}: {exc}") from None
        return cls(path, cameras, str(meta.get("created", "")))

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    def camera_dir(self, camera: str) -> Path:
        if camera not in self.camera_names:
            raise RecordingError(f"{self.path}: no camera {camera!r} (has {', '.join(self.camera_names)})")
        return self.path / camera

    def index(self, camera: str) -> list[IndexRow]:
        """The valid rows of a camera's ``index.csv``; broken rows are skipped and counted (once:
        the file is read on the first call)."""
        if camera not in self._index:
            self._index[camera] = self._read_index(camera)
        return list(self._index[camera])

    def with_frames(self) -> tuple[Recording, dict[str, str]]:
        """This recording restricted to the cameras that recorded frames (a camera that was down
        while recording has an empty index), and why each other camera was left out. RecordingError
        when no camera recorded a frame."""
        kept, empty = [], {}
        for camera in self.cameras:
            try:
                self.index(camera.name)
                kept.append(camera)
            except RecordingError as exc:
                empty[camera.name] = str(exc)
        if not kept:
            raise RecordingError(f"{self.path}: no camera recorded a frame")
        return Recording(self.path, tuple(kept), self.created), empty

    def _read_index(self, camera: str) -> list[IndexRow]:
        index_path = self.camera_dir(camera) / "index.csv"
        rows = self._read_rows(index_path, INDEX_HEADER, _parse_index_row, "bad index row")
        if not rows:
            raise RecordingError(f"{index_path}: empty index (no frames recorded for {camera})")
        return rows

    def _read_rows(self, path: Path, header: tuple[str, ...], parse: Callable[[list[str]], Any],
                   reason: str) -> list:
        """The rows of a CSV file that must start with ``header``, each through ``parse`` (None:
        a broken row, skipped and counted under ``reason``)."""
        rows = []
        try:
            with path.open(newline="", encoding="utf-8") as f:
                text = f.read()
            if text and not text.endswith(("\n", "\r")):  # the row being written when its writer died
                text = text[:text.rfind("\n") + 1]
                self.skipped["unfinished last row"] += 1
                log.warning("%s: the last row has no line end (its writer stopped in it); skipped", path)
            reader = csv.reader(io.StringIO(text, newline=""))
            first = next(reader, None)
            if first is None or tuple(h.strip() for h in first) != header:
                raise RecordingError(f"{path}: header must be {','.join(header)}")
            for line_no, fields in enumerate(reader, start=2):
                row = parse(fields)
                if row is None:
                    self.skipped[reason] += 1
                    log.warning("%s:%d: skipping malformed row %r", path, line_no, fields)
                    continue
                rows.append(row)
        except FileNotFoundError:
            raise RecordingError(f"{path}: missing") from None
        except (UnicodeDecodeError, csv.Error) as exc:
            raise RecordingError(f"{path}: unreadable: {exc}") from None
        return rows

    def frames(self, camera: str) -> Iterator[Frame]:
        """A camera's frames in index order; missing or unreadable JPEG files are skipped and counted."""
        folder = self.camera_dir(camera)
        for row in self.index(camera):
            try:
                jpeg = (folder / row.file).read_bytes()
            except OSError:
                if (camera, row.file) not in self._missing:
                    self._missing.add((camera, row.file))
                    self.skipped["missing frame file"] += 1
                    log.warning("%s: frame file %s is missing; skipped", folder, row.file)
                continue
            yield Frame(camera, row.seq, row.device_time_s, row.host_time_s, jpeg)

    def merged_frames(self, cameras: Iterable[str] | None = None) -> Iterator[Frame]:
        """Frames of all (or the given) cameras in host arrival order, as a live run would see them."""
        names = tuple(cameras) if cameras is not None else self.camera_names
        return heapq.merge(*(self.frames(c) for c in names), key=lambda f: (f.host_time_s, f.camera))

    def clock_samples(self, camera: str) -> list[ClockSample]:
        """The camera's ``/time`` round trips (empty when the recording has none); broken rows
        are skipped and counted (once: the file is read on the first call)."""
        if camera not in self._clock:
            self._clock[camera] = self._read_clock(camera)
        return list(self._clock[camera])

    def _read_clock(self, camera: str) -> list[ClockSample]:
        path = self.camera_dir(camera) / "clock.csv"
        if not path.exists():
            return []
        return self._read_rows(path, CLOCK_HEADER, _parse_clock_row, "bad clock row")

    def camera_info_path(self, camera: str) -> Path | None:
        path = self.path / "camera_info" / f"{camera}.yaml"
        return path if path.exists() else None

    @property
    def ground_truth_path(self) -> Path | None:
        path = self.path / "ground_truth.tum"
        return path if path.exists() else None


def _parse_clock_row(fields: list[str]) -> ClockSample | None:
    try:
        sample = ClockSample(*(float(v) for v in fields))
    except (TypeError, ValueError):
        return None
    times = (sample.host_send_s, sample.device_time_s, sample.host_recv_s)
    return sample if all(map(math.isfinite, times)) else None


def _parse_index_row(fields: list[str]) -> IndexRow | None:
    if len(fields) != 4:
        return None
    try:
        row = IndexRow(int(fields[0]), float(fields[1]), float(fields[2]), fields[3].strip())
    except ValueError:
        return None
    if not (math.isfinite(row.device_time_s) and math.isfinite(row.host_time_s)):
        return None
    name = row.file
    if not name or "/" in name or "\\" in name or name in (".", ".."):
        return None  # a file name must stay inside the camera folder
    return row


class RecordingWriter:
    """Writes a recording folder incrementally, so that a recording cut short (a killed process,
    Ctrl-C, a full disk) stays readable up to its last whole frame: ``recording.json`` is written
    last of the folder's skeleton (a folder that has it has every camera's ``index.csv`` with its
    header), a frame's JPEG is stored whole before its index row, and rows are whole lines
    written one at a time (:class:`cubetrack.io.files.LineFile`). A write the disk refuses is a
    :class:`RecordingError` naming the file; what was recorded before it stays readable.

    Refuses to write into a folder that already holds a recording unless ``overwrite``.
    """

    def __init__(self, path: str | Path, cameras: Iterable[CameraEntry], overwrite: bool = False):
        self.path = Path(path)
        self.cameras = tuple(cameras)
        if not self.cameras:
            raise RecordingError("a recording needs at least one camera")
        for c in self.cameras:
            check_camera_name(c.name)
        if (self.path / "recording.json").exists() and not overwrite:
            raise RecordingError(f"{self.path}: already holds a recording; choose another folder")
        if self.path.exists() and not self.path.is_dir():
            raise RecordingError(f"{self.path}: exists and is not a folder")
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "cameras": [{"name": c.name, "source": c.source} for c in self.cameras],
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
        }
        self._index: dict[str, LineFile] = {}
        self._clock: dict[str, LineFile] = {}
        try:
            with os_errors_as(RecordingError, self.path):
                self.path.mkdir(parents=True, exist_ok=True)
                for c in self.cameras:
                    (self.path / c.name).mkdir(exist_ok=True)
                    self._index[c.name] = LineFile(self.path / c.name / "index.csv", ",".join(INDEX_HEADER))
                atomic_write(self.path / "recording.json", json.dumps(meta, indent=2) + "\n")
        except BaseException:
            self.close()
            raise

    def add_frame(self, camera: str, seq: int, device_time_s: float, host_time_s: float,
                  jpeg: bytes) -> str:
        """Store one frame; returns its file name (relative to the camera folder)."""
        if camera not in self._index:
            raise RecordingError(f"{self.path}: no camera {camera!r} in this recording")
        name = f"{seq:08d}.jpg"
        index = self._index[camera]
        with os_errors_as(RecordingError, self.path / camera / name):
            atomic_write(self.path / camera / name, jpeg)
        with os_errors_as(RecordingError, index.path):
            index.write_line(f"{int(seq)},{_fmt(device_time_s)},{_fmt(host_time_s)},{name}")
        return name

    def add_clock_sample(self, camera: str, sample: ClockSample) -> None:
        """Store one ``/time`` round trip of ``camera``."""
        if camera not in self._index:
            raise RecordingError(f"{self.path}: no camera {camera!r} in this recording")
        path = self.path / camera / "clock.csv"
        with os_errors_as(RecordingError, path):
            f = self._clock.get(camera)
            if f is None:
                f = self._clock[camera] = LineFile(path, ",".join(CLOCK_HEADER))
            f.write_line(f"{_fmt(sample.host_send_s)},{_fmt(sample.device_time_s)},{_fmt(sample.host_recv_s)}")

    def camera_info_path(self, camera: str) -> Path:
        """Where this camera's intrinsics belong; the folder is created."""
        folder = self.path / "camera_info"
        folder.mkdir(exist_ok=True)
        return folder / f"{camera}.yaml"

    @property
    def ground_truth_path(self) -> Path:
        return self.path / "ground_truth.tum"

    def close(self) -> None:
        for f in (*self._index.values(), *self._clock.values()):
            f.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
