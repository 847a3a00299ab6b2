"""A printable sheet of a body's markers (``cubetrack make-body``): SVG at exact physical size.

User units are millimetres (``width="…mm"`` with a matching ``viewBox``), so a printer at 100 %
(no "fit to page") reproduces every length. Each marker is drawn as OpenCV's ArUco image
(its cells, black border included, as ``cv2.aruco.generateImageMarker`` gives them; the caller
passes them in): one black square of the marker's side and one white path of its white cells, so
no seam shows between neighbouring cells.

A body whose markers all lie flat on the faces of a box centred on the body's origin (the
paper's cube, any cuboid with markers on its faces; :func:`box_half_sizes`) is drawn as a net:
the top in the middle, the four sides hinged on its edges, the bottom on the front's far edge;
solid lines are cut, dashed lines folded, glue tabs close the box. Each marker sits on its face
where the layout puts it, turned as it will be seen once folded (the faces are unfolded about
their hinges, so what is printed is what the folded box shows). Any other body gets its markers
one by one, each on a white tile with a cut line and its face name. A 100 mm scale bar checks
the print.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from xml.sax.saxutils import escape

import numpy as np

from cubetrack.core.geometry import make_T
from cubetrack.core.layout import CubeLayout

_AXES = np.eye(3)
_TAB_MM = 12.0  # glue tab depth
_PAGE_MARGIN_MM = 12.0
_LOOSE_MARGIN_CELLS = 1.5  # white around a loose marker, in marker cells (at least 5 mm)
_LABEL_MM = 3.5  # label font size
_FLAT_TOLERANCE = 1e-6  # how far from an axis a face normal may be (radians, roughly)
_PLANE_TOLERANCE_M = 1e-4  # how far from its face plane a marker may be


def box_half_sizes(layout: CubeLayout) -> np.ndarray | None:
    """Half sides (x, y, z) in metres of the box centred on the body origin whose faces carry all
    the layout's markers flat (each marker's normal along a body axis, its centre on that face's
    plane; opposite faces at the same distance), or None when the markers do not form one. A
    face without a marker takes the opposite face's distance."""
    half = np.full(3, np.nan)
    for m in layout.markers:
        normal = m.T_cube_marker[:3, 2]
        axis = int(np.argmax(np.abs(normal)))
        if abs(abs(normal[axis]) - 1.0) > _FLAT_TOLERANCE:
            return None
        distance = float(m.T_cube_marker[axis, 3] * np.sign(normal[axis]))
        if distance <= 0 or (not np.isnan(half[axis]) and abs(half[axis] - distance) > _PLANE_TOLERANCE_M):
            return None
        half[axis] = distance
    if np.isnan(half).any():
        return None
    for m in layout.markers:  # the marker must lie inside its face
        normal = m.T_cube_marker[:3, 2]
        axis = int(np.argmax(np.abs(normal)))
        others = [a for a in range(3) if a != axis]
        corners = m.corners_cube_m()
        if np.any(np.abs(corners[:, others]) > half[others] + _PLANE_TOLERANCE_M):
            return None
    return half


@dataclass(frozen=True, slots=True)
class _Face:
    name: str
    normal: np.ndarray
    parent: str | None


# the net: the top, the sides hinged on it, the bottom hinged on the front
_NET = (
    _Face("top", np.array([0.0, 0.0, 1.0]), None),
    _Face("front", np.array([1.0, 0.0, 0.0]), "top"),
    _Face("left", np.array([0.0, 1.0, 0.0]), "top"),
    _Face("back", np.array([-1.0, 0.0, 0.0]), "top"),
    _Face("right", np.array([0.0, -1.0, 0.0]), "top"),
    _Face("bottom", np.array([0.0, 0.0, -1.0]), "front"),
)
# glue tabs: (face, the neighbour whose edge it is glued under)
_TABS = (("left", "front"), ("left", "back"), ("right", "front"), ("right", "back"),
         ("bottom", "left"), ("bottom", "right"), ("bottom", "back"))


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def unfold_transforms(half: np.ndarray) -> dict[str, np.ndarray]:
    """Per net face, the rigid transform (4x4, body frame) that lays it flat in the top face's
    plane: each face turns 90° outward about the edge it shares with its parent."""
    out: dict[str, np.ndarray] = {}
    for face in _NET:
        if face.parent is None:
            out[face.name] = np.eye(4)
            continue
        parent = next(f for f in _NET if f.name == face.parent)
        hinge = half @ np.abs(face.normal) * face.normal + half @ np.abs(parent.normal) * parent.normal
        R = _rotation(np.cross(face.normal, parent.normal), np.pi / 2.0)
        about = make_T(np.eye(3), hinge) @ make_T(R, np.zeros(3)) @ make_T(np.eye(3), -hinge)
        out[face.name] = out[face.parent] @ about
    return out


def _face_corners(name: str, half: np.ndarray) -> np.ndarray:
    """(4, 3) corners of a box face in the body frame, in order around it."""
    normal = next(f.normal for f in _NET if f.name == name)
    axis = int(np.argmax(np.abs(normal)))
    u, v = [a for a in range(3) if a != axis]
    out = []
    for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        p = normal * half[axis]
        p = p + _AXES[u] * su * half[u] + _AXES[v] * sv * half[v]
        out.append(p)
    return np.array(out)


class _Svg:
    """SVG elements in millimetres, y down."""

    def __init__(self) -> None:
        self.items: list[str] = []

    def path(self, d: str, **attrs: str) -> None:
        self.items.append(f'<path d="{d}"{_attrs(attrs)}/>')

    def polyline(self, points: np.ndarray, closed: bool, **attrs: str) -> None:
        d = "M " + " L ".join(f"{x:.4f} {y:.4f}" for x, y in points) + (" Z" if closed else "")
        self.path(d, fill="none", **attrs)

    def text(self, x: float, y: float, text: str, size: float = _LABEL_MM, anchor: str = "start") -> None:
        self.items.append(f'<text x="{x:.3f}" y="{y:.3f}" font-family="sans-serif" font-size="{size:.2f}" '
                          f'text-anchor="{anchor}">{escape(text)}</text>')

    def marker(self, bits: np.ndarray, matrix: tuple[float, ...], marker_id: int, dictionary: str) -> None:
        """A marker whose cell (column i, row j) spans [i, i+1] x [j, j+1] before ``matrix`` (the
        SVG matrix(a b c d e f) mapping cells to millimetres)."""
        n = bits.shape[0]
        white = " ".join(f"M{i} {j}h1v1h-1z" for j, i in zip(*np.nonzero(bits), strict=True))
        m = " ".join(f"{v:.6f}" for v in matrix)
        self.items.append(f'<g class="marker" data-id="{marker_id}" data-dictionary="{escape(dictionary)}" '
                          f'data-cells="{n}" transform="matrix({m})">'
                          f'<rect x="0" y="0" width="{n}" height="{n}" fill="#000"/>'
                          + (f'<path d="{white}" fill="#fff"/>' if white else "") + "</g>")

    def document(self, width_mm: float, height_mm: float, title: str) -> str:
        return (f'<?xml version="1.0" encoding="UTF-8"?>\n'
                f'<svg xmlns="http://www.w3.org/2000/svg" width="{width_mm:.3f}mm" height="{height_mm:.3f}mm" '
                f'viewBox="0 0 {width_mm:.3f} {height_mm:.3f}">\n<title>{escape(title)}</title>\n'
                f'<rect x="0" y="0" width="{width_mm:.3f}" height="{height_mm:.3f}" fill="#fff"/>\n'
                + "\n".join(self.items) + "\n</svg>\n")


def _attrs(attrs: dict[str, str]) -> str:
    return "".join(f' {k.replace("_", "-")}="{v}"' for k, v in attrs.items())


CUT = {"stroke": "#000", "stroke_width": "0.25"}
FOLD = {"stroke": "#000", "stroke_width": "0.25", "stroke_dasharray": "2 1.5"}


def _cell_matrix(corners_mm: np.ndarray, cells: int) -> tuple[float, ...]:
    """The affine map (SVG matrix) taking cell coordinates of a marker (TL at (0, 0), BR at
    (cells, cells)) to its corners (4, 2) TL TR BR BL on the sheet."""
    tl, tr, _br, bl = corners_mm
    a, b = (tr - tl) / cells
    c, d = (bl - tl) / cells
    return (a, b, c, d, tl[0], tl[1])


Cells = Mapping[tuple[str, int], np.ndarray]  # (dictionary, id) -> (n, n) bool, True = white, row 0 = top


def body_svg(layout: CubeLayout, title: str, cells: Cells, net: bool = True) -> str:
    """The printable SVG of ``layout`` (``cells``: each marker's cells): a box net when the
    markers sit on a box's faces and ``net``, else each marker on its own tile (see the module
    docstring)."""
    half = box_half_sizes(layout) if net else None
    svg = _Svg()
    if half is not None:
        width, height = _draw_net(svg, layout, half, cells)
    else:
        width, height = _draw_tiles(svg, layout, cells)
    y = height + 6.0
    _scale_bar(svg, _PAGE_MARGIN_MM, y)
    lines = [title, "print at 100 % (no fit to page); the bar must measure 100 mm",
             "cut: solid lines; fold: dashed lines" if half is not None else "cut: solid lines"]
    for k, line in enumerate(lines):
        svg.text(_PAGE_MARGIN_MM, y + 14.0 + 5.0 * k, line)
    width = max(width, _PAGE_MARGIN_MM + 100.0) + _PAGE_MARGIN_MM
    return svg.document(max(width, 2 * _PAGE_MARGIN_MM + 130.0), y + 14.0 + 5.0 * len(lines) + _PAGE_MARGIN_MM,
                        title)


def _scale_bar(svg: _Svg, x: float, y: float) -> None:
    svg.path(f"M{x:.3f} {y:.3f}h100", stroke="#000", stroke_width="0.4", fill="none")
    for k in range(11):
        tick = 4.0 if k % 5 == 0 else 2.5
        svg.path(f"M{x + 10 * k:.3f} {y:.3f}v{tick}", stroke="#000", stroke_width="0.3", fill="none")
    svg.text(x, y + 8.0, "0", anchor="middle")
    svg.text(x + 100.0, y + 8.0, "100 mm", anchor="middle")


def _draw_net(svg: _Svg, layout: CubeLayout, half: np.ndarray, cells: Cells) -> tuple[float, float]:
    U = unfold_transforms(half)
    mm = 1000.0

    def sheet(face: str, points: np.ndarray) -> np.ndarray:
        """Body-frame points of ``face`` -> flat (u, w) in mm: u along body y, w along -x."""
        p = points @ U[face][:3, :3].T + U[face][:3, 3]
        return np.column_stack([p[:, 1], p[:, 0]]) * mm  # SVG y down = body x (front at the bottom)

    outlines = {f.name: sheet(f.name, _face_corners(f.name, half)) for f in _NET}
    tabs = {}
    for face, other in _TABS:
        edge = _shared_edge(outlines[face], sheet(face, _face_corners(other, half)))
        tabs[(face, other)] = _tab(edge, outlines[face])
    everything = np.vstack([*outlines.values(), *tabs.values()])
    offset = _PAGE_MARGIN_MM - everything.min(axis=0) + np.array([0.0, 8.0])
    for outline in outlines.values():
        svg.polyline(outline + offset, True, **FOLD)
    for tab in tabs.values():
        svg.polyline(tab + offset, False, **CUT)
    tab_bases = [tab[[0, 3]] for tab in tabs.values()]
    for edge in _outer_edges(outlines):
        if not any(_same_edge(edge, base) for base in tab_bases):  # a tab's base is folded, not cut
            svg.polyline(edge + offset, False, **CUT)
    for m, dictionary in zip(layout.markers, layout.marker_dictionaries, strict=True):
        corners = sheet(_face_of(m.T_cube_marker[:3, 2]), m.corners_cube_m()) + offset
        bits = cells[(dictionary, m.marker_id)]
        svg.marker(bits, _cell_matrix(corners, bits.shape[0]), m.marker_id, dictionary)
    for name, outline in outlines.items():
        o = outline + offset
        svg.text(o[:, 0].min() + 2.0, o[:, 1].min() + 2.0 + _LABEL_MM, name, size=_LABEL_MM * 0.8)
    svg.text(_PAGE_MARGIN_MM, _PAGE_MARGIN_MM + 2.0,
             f"box {2000 * half[0]:.1f} x {2000 * half[1]:.1f} x {2000 * half[2]:.1f} mm (x front, y left, z up)")
    size = everything.max(axis=0) + offset
    return float(size[0]), float(size[1])


def _face_of(normal: np.ndarray) -> str:
    return max(_NET, key=lambda f: float(f.normal @ normal)).name


def _shared_edge(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The two points of outline ``a`` (4, 2) that lie on outline ``b``'s edge (within 1 µm)."""
    near = [p for p in a if np.min(np.linalg.norm(b - p, axis=1)) < 1e-3]
    return np.array(near[:2])


def _tab(edge: np.ndarray, face: np.ndarray) -> np.ndarray:
    """A glue tab on ``edge`` (2, 2), outside the face outline (4, 2): a trapezoid with 45° sides."""
    p, q = edge
    along = (q - p) / np.linalg.norm(q - p)
    out = np.array([along[1], -along[0]])
    if out @ (p - face.mean(axis=0)) < 0:
        out = -out
    depth = min(_TAB_MM, 0.4 * np.linalg.norm(q - p))
    return np.array([p, p + out * depth + along * depth, q + out * depth - along * depth, q])


def _same_edge(e: np.ndarray, f: np.ndarray) -> bool:
    """Two 2-point edges are one (either direction, within 1 µm)."""
    return bool(np.allclose(e, f, atol=1e-3) or np.allclose(e, f[::-1], atol=1e-3))


def _outer_edges(outlines: dict[str, np.ndarray]) -> list[np.ndarray]:
    """The edges of the net that belong to one face only (its outline), as (2, 2) lines."""
    edges = [np.array([o[k], o[(k + 1) % 4]]) for o in outlines.values() for k in range(4)]
    return [e for e in edges if sum(_same_edge(e, f) for f in edges) == 1]


def _draw_tiles(svg: _Svg, layout: CubeLayout, cells: Cells) -> tuple[float, float]:
    """Each marker on a square white tile with a cut line, in rows no wider than 180 mm."""
    x = y = _PAGE_MARGIN_MM
    row_height = width = 0.0
    y += 8.0
    for m, dictionary in zip(layout.markers, layout.marker_dictionaries, strict=True):
        bits = cells[(dictionary, m.marker_id)]
        side = 1000.0 * m.size_m
        margin = max(5.0, _LOOSE_MARGIN_CELLS * side / bits.shape[0])
        tile = side + 2 * margin
        if x > _PAGE_MARGIN_MM and x + tile > _PAGE_MARGIN_MM + 180.0:
            x, y = _PAGE_MARGIN_MM, y + row_height + 8.0
            row_height = 0.0
        svg.polyline(np.array([[x, y], [x + tile, y], [x + tile, y + tile], [x, y + tile]]), True, **CUT)
        tl = np.array([x + margin, y + margin])
        corners = np.array([tl, tl + [side, 0.0], tl + [side, side], tl + [0.0, side]])
        svg.marker(bits, _cell_matrix(corners, bits.shape[0]), m.marker_id, dictionary)
        svg.text(x, y + tile + _LABEL_MM + 0.5, f"{m.face}: id {m.marker_id}, {side:.1f} mm", size=_LABEL_MM * 0.8)
        x += tile + 8.0
        width = max(width, x)
        row_height = max(row_height, tile + _LABEL_MM + 1.0)
    return width, y + row_height
