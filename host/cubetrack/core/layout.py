"""The cube layout model (contracts §4): which marker sits where on a robot's cube.

Cube frame: origin at the cube's centre, x forward (the "front" face), y left, z up.
Marker frame (OpenCV ArUco): origin at the marker centre, x right, y up, z out of the face.
``T_cube_marker`` maps marker-frame points into the cube frame.

The paper's cube repeats one id on five faces (no bottom). Faces are told apart by which marker
axis points up in the world while the robot stands upright:

========  ==========  ==================================
face      axis up     in-plane rotation of the marker
========  ==========  ==================================
top       +z          —
front     +y          upright
left      +x          turned 90° clockwise
back      -y          upside down
right     -x          turned 90° counter-clockwise
========  ==========  ==================================
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import tomli_w

from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import T_from_position_quat, invert_T, make_T, position_quat_from_T
from cubetrack.core.params import read_toml

FACES = ("top", "front", "left", "back", "right")
DEFAULT_DICTIONARY = "DICT_4X4_50"

# Outward normal of each face (cube frame) and the marker axis that points up (cube +z).
_FACE_NORMAL = {
    "top": (0.0, 0.0, 1.0),
    "front": (1.0, 0.0, 0.0),
    "left": (0.0, 1.0, 0.0),
    "back": (-1.0, 0.0, 0.0),
    "right": (0.0, -1.0, 0.0),
    "bottom": (0.0, 0.0, -1.0),
}
_FACE_UP_AXIS = {"front": "+y", "left": "+x", "back": "-y", "right": "-x"}


@dataclass(frozen=True, slots=True, eq=False)
class LayoutMarker:
    """One marker on the cube: its face name, id, black-square side (metres) and pose; its
    ``dictionary`` when it is not the layout's ("" = the layout's)."""

    face: str
    marker_id: int
    size_m: float
    T_cube_marker: np.ndarray
    dictionary: str = ""

    def corners_cube_m(self) -> np.ndarray:
        """(4, 3) marker corners in the cube frame, in detector order TL, TR, BR, BL."""
        return (marker_corners_m(self.size_m) @ self.T_cube_marker[:3, :3].T) + self.T_cube_marker[:3, 3]


BODY_MOTIONS = ("floor", "free")  # a body on a robot that drives on a floor; a body moved freely (hand-held)


@dataclass(frozen=True, slots=True, eq=False)
class CubeLayout:
    """A dictionary name and the markers on one cube.

    Derived when the layout is made (read-only arrays in the order of ``markers``): the lookup
    tables every stage that matches or projects the cube needs, so none keeps its own cache.

    - ``corners_m`` (M, 4, 3): marker corners in the cube frame (detector order TL, TR, BR, BL);
    - ``normals`` (M, 3): outward face normals in the cube frame;
    - ``T_marker_cube`` (M, 4, 4): the inverse of each marker's ``T_cube_marker``;
    - ``sizes_m`` (M,), ``marker_ids`` (M,);
    - ``ids``: the set of ids; ``has_repeated_ids``: some id is on more than one face;
    - :meth:`indices_of`: the markers carrying an id.

    Markers may come from several dictionaries (a marker's own ``dictionary``):
    ``marker_dictionaries`` (M,) names each marker's, ``dictionaries`` lists them (the layout's
    first), ``keys`` is the set of (dictionary, id); ids repeat only when a (dictionary, id) does.
    """

    dictionary: str
    markers: tuple[LayoutMarker, ...]
    motion: str = "floor"  # how the body moves, one of BODY_MOTIONS (the file's ``motion``; docs/tracking.md)
    corners_m: np.ndarray = field(init=False, repr=False)
    normals: np.ndarray = field(init=False, repr=False)
    T_marker_cube: np.ndarray = field(init=False, repr=False)
    sizes_m: np.ndarray = field(init=False, repr=False)
    marker_ids: np.ndarray = field(init=False, repr=False)
    ids: frozenset[int] = field(init=False, repr=False)
    has_repeated_ids: bool = field(init=False, repr=False)
    marker_dictionaries: tuple[str, ...] = field(init=False, repr=False)
    dictionaries: tuple[str, ...] = field(init=False, repr=False)
    keys: frozenset[tuple[str, int]] = field(init=False, repr=False)
    _indices: dict[int, np.ndarray] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.markers:
            raise ConfigError("a cube layout needs at least one marker")
        if self.motion not in BODY_MOTIONS:
            raise ConfigError(f"a cube layout's motion must be one of {', '.join(BODY_MOTIONS)}, got {self.motion!r}")
        faces = [m.face for m in self.markers]
        if len(set(faces)) != len(faces):
            raise ConfigError(f"cube layout repeats a face name: {faces}")
        derived = {
            "corners_m": np.array([m.corners_cube_m() for m in self.markers]),
            "normals": np.array([m.T_cube_marker[:3, 2] for m in self.markers]),
            "T_marker_cube": np.array([invert_T(m.T_cube_marker) for m in self.markers]),
            "sizes_m": np.array([m.size_m for m in self.markers], dtype=float),
            "marker_ids": np.array([m.marker_id for m in self.markers]),
        }
        indices = {int(i): np.flatnonzero(derived["marker_ids"] == i) for i in dict.fromkeys(derived["marker_ids"])}
        for value in (*derived.values(), *indices.values()):
            value.setflags(write=False)
        for name, value in derived.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_indices", indices)
        object.__setattr__(self, "ids", frozenset(indices))
        names = tuple(m.dictionary or self.dictionary for m in self.markers)
        keys = list(zip(names, (m.marker_id for m in self.markers), strict=True))
        object.__setattr__(self, "marker_dictionaries", names)
        object.__setattr__(self, "dictionaries", tuple(dict.fromkeys((self.dictionary, *names))))
        object.__setattr__(self, "keys", frozenset(keys))
        object.__setattr__(self, "has_repeated_ids", len(set(keys)) < len(self.markers))

    def indices_of(self, marker_id: int, dictionary: str = "") -> np.ndarray:
        """Indices into ``markers`` of the markers with ``marker_id`` (of ``dictionary``; "" =
        any), in layout order (read-only; empty for an id not on the cube)."""
        found = self._indices.get(marker_id, _NO_INDICES)
        if not dictionary or len(self.dictionaries) == 1 and dictionary == self.dictionary:
            return found
        return found[[self.marker_dictionaries[i] == dictionary for i in found]] if len(found) else found


_NO_INDICES = np.zeros(0, dtype=np.intp)
_NO_INDICES.setflags(write=False)


def marker_corners_m(size_m: float) -> np.ndarray:
    """(4, 3) corners of a square marker in its own frame, in detector order TL, TR, BR, BL.

    Matches the object points OpenCV documents for SOLVEPNP_IPPE_SQUARE.
    """
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def face_T_cube_marker(face: str, cube_size_m: float) -> np.ndarray:
    """Pose of a marker centred on ``face`` of a cube of side ``cube_size_m`` (paper's scheme)."""
    if face not in _FACE_NORMAL:
        raise ConfigError(f"unknown face {face!r}; faces are {', '.join(_FACE_NORMAL)}")
    z = np.array(_FACE_NORMAL[face])
    up = np.array([0.0, 0.0, 1.0])
    if face in ("top", "bottom"):
        y = np.array([1.0, 0.0, 0.0])  # the marker's y points to the cube's front
        x = np.cross(y, z)
    else:
        axis = _FACE_UP_AXIS[face]
        sign = 1.0 if axis[0] == "+" else -1.0
        if axis[1] == "y":
            y = sign * up
            x = np.cross(y, z)
        else:
            x = sign * up
            y = np.cross(z, x)
    R = np.column_stack([x, y, z])
    return make_T(R, z * cube_size_m / 2.0)


def paper_cube_layout(
    cube_size_m: float = 0.11,
    marker_size_m: float = 0.08,
    marker_id: int = 1,
    dictionary: str = DEFAULT_DICTIONARY,
    distinct_ids: bool = False,
) -> CubeLayout:
    """The paper's five-face cube; with ``distinct_ids`` faces get ids marker_id .. marker_id+4."""
    if not 0 < marker_size_m <= cube_size_m:
        raise ConfigError(
            f"marker size {marker_size_m} m must be positive and fit the cube side {cube_size_m} m"
        )
    markers = tuple(
        LayoutMarker(
            face=face,
            marker_id=marker_id + (i if distinct_ids else 0),
            size_m=marker_size_m,
            T_cube_marker=face_T_cube_marker(face, cube_size_m),
        )
        for i, face in enumerate(FACES)
    )
    return CubeLayout(dictionary=dictionary, markers=markers)


def _vector(value: object, n: int, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    ):
        raise ConfigError(f"{where}: expected a list of {n} numbers, got {value!r}")
    out = np.array(value, dtype=float)
    if not np.all(np.isfinite(out)):
        raise ConfigError(f"{where}: numbers must be finite, got {value!r}")
    return out


def layout_from_table(table: dict, where: str) -> CubeLayout:
    """Build a layout from its parsed TOML table (contracts §4; a marker may name its own
    ``dictionary``); ``where`` names it in errors."""
    dictionary = table.get("dictionary", DEFAULT_DICTIONARY)
    if not isinstance(dictionary, str):
        raise ConfigError(f"{where}: 'dictionary' must be a name like {DEFAULT_DICTIONARY!r}")
    rows = table.get("markers")
    if not isinstance(rows, list) or not rows:
        raise ConfigError(f"{where}: needs at least one [[markers]] table")
    markers = []
    for i, row in enumerate(rows):
        w = f"{where}: markers[{i}]"
        if not isinstance(row, dict):
            raise ConfigError(f"{w} must be a [[markers]] table")
        missing = {"face", "id", "size", "position", "quaternion_xyzw"} - set(row)
        if missing:
            raise ConfigError(f"{w} lacks {', '.join(sorted(missing))}")
        if not isinstance(row["id"], int) or isinstance(row["id"], bool) or row["id"] < 0:
            raise ConfigError(f"{w}.id must be a non-negative integer, got {row['id']!r}")
        size = row["size"]
        if not isinstance(size, (int, float)) or isinstance(size, bool) or not size > 0:
            raise ConfigError(f"{w}.size must be a positive number of metres, got {size!r}")
        q = _vector(row["quaternion_xyzw"], 4, f"{w}.quaternion_xyzw")
        if np.linalg.norm(q) < 1e-9:
            raise ConfigError(f"{w}.quaternion_xyzw must not be zero")
        T = T_from_position_quat(_vector(row["position"], 3, f"{w}.position"), q)
        own = row.get("dictionary", "")
        if not isinstance(own, str):
            raise ConfigError(f"{w}.dictionary must be a name like {DEFAULT_DICTIONARY!r}")
        markers.append(LayoutMarker(str(row["face"]), int(row["id"]), float(size), T,
                                    "" if own == dictionary else own))
    try:  # the layout's own checks (its motion, its faces), named by the file
        return CubeLayout(dictionary=dictionary, markers=tuple(markers), motion=table.get("motion", "floor"))
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def layout_to_table(layout: CubeLayout) -> dict:
    """The TOML table of a layout (contracts §4)."""
    rows = []
    for m in layout.markers:
        position, q = position_quat_from_T(m.T_cube_marker)
        rows.append(
            {
                "face": m.face,
                "id": m.marker_id,
                "size": m.size_m,
                "position": [round(float(v), 9) for v in position],
                "quaternion_xyzw": [round(float(v), 12) for v in q],
                **({"dictionary": m.dictionary} if m.dictionary and m.dictionary != layout.dictionary else {}),
            }
        )
    return {"dictionary": layout.dictionary, **({"motion": layout.motion} if layout.motion != "floor" else {}),
            "markers": rows}


def read_layout(path: str | Path) -> CubeLayout:
    """Read a cube layout TOML file."""
    return layout_from_table(read_toml(path, "cube layout"), str(path))


def write_layout(layout: CubeLayout, path: str | Path) -> None:
    """Write a cube layout TOML file."""
    Path(path).write_text(tomli_w.dumps(layout_to_table(layout)), encoding="utf-8")


def marker_bits(dictionary: str, marker_id: int) -> np.ndarray:
    """The inner bit pattern (n, n) of marker ``marker_id`` of the OpenCV dictionary named
    ``dictionary`` (1 = white); ConfigError for an unknown name or an id beyond the dictionary."""
    value = getattr(cv2.aruco, dictionary, None) if dictionary.startswith("DICT_") else None
    if not isinstance(value, int):
        raise ConfigError(f"unknown marker dictionary {dictionary!r}")
    d = cv2.aruco.getPredefinedDictionary(value)
    if not 0 <= marker_id < len(d.bytesList):
        raise ConfigError(f"{dictionary} has ids 0..{len(d.bytesList) - 1}, not {marker_id}")
    n = d.markerSize
    image = cv2.aruco.generateImageMarker(d, marker_id, n + 2, borderBits=1)
    return (image[1:-1, 1:-1] > 127).astype(np.uint8)


def pattern_collisions(owners: Mapping[tuple[str, int], str]) -> list[str]:
    """Markers of different dictionaries that a detector could take for one another: for each pair
    of ``owners`` keys ((dictionary, id) -> who uses it) of equal bit-grid size whose patterns, in
    any of the four rotations, differ in no more bits than either dictionary corrects
    (``maxCorrectionBits``), one line naming both. (Within one dictionary distinct ids never collide:
    that is how dictionaries are made; DICT_4X4_50 id 0 and DICT_4X4_1000 id 0 are one pattern.)"""
    keys = sorted(owners)
    bits = {k: marker_bits(*k) for k in keys}
    correct = {name: cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).maxCorrectionBits
               for name in {k[0] for k in keys}}
    out = []
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            if a[0] == b[0] or bits[a].shape != bits[b].shape:
                continue
            distance = min(int(np.count_nonzero(np.rot90(bits[a], r) != bits[b])) for r in range(4))
            if distance <= max(correct[a[0]], correct[b[0]]):
                out.append(f"{owners[a]} ({a[0]} id {a[1]}) and {owners[b]} ({b[0]} id {b[1]}) are "
                           f"{'the same marker' if distance == 0 else f'{distance} bit(s) apart'}: a detector "
                           f"cannot tell them apart; choose other ids or one dictionary")
    return out
