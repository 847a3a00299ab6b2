"""``cubetrack make-body``: a body (the paper's cube, any box with markers on its faces, or any
layout file), its printable sheet (:mod:`cubetrack.io.body_sheet`: SVG, and PDF through
cairosvg) and the matching layout file the tracker reads."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubetrack.core.errors import ConfigError
from cubetrack.core.layout import (
    DEFAULT_DICTIONARY,
    FACES,
    CubeLayout,
    LayoutMarker,
    face_T_cube_marker,
    layout_to_table,
)
from cubetrack.detect.detector import aruco_dictionary
from cubetrack.io.body_sheet import Cells, body_svg
from cubetrack.io.config import write_toml
from cubetrack.io.files import atomic_write

_NORMAL_AXIS = {"top": 2, "bottom": 2, "front": 0, "back": 0, "left": 1, "right": 1}
MARKER_FILL = 0.75  # a box face's default marker side: this fraction of its shorter side, whole millimetres


def box_layout(size_m: Sequence[float], marker_size_m: float | None = None, marker_id: int = 1,
               dictionary: str = DEFAULT_DICTIONARY, distinct_ids: bool = False,
               faces: Sequence[str] = FACES) -> CubeLayout:
    """A box of sides ``size_m`` (x forward, y left, z up; origin at its centre) with a marker
    centred on each of ``faces``, turned as on the paper's cube (:func:`cubetrack.core.layout.
    face_T_cube_marker`). Marker sides: ``marker_size_m``, or each face's own (``MARKER_FILL`` of
    its shorter side); ids ``marker_id`` on every face, or counting up with ``distinct_ids``."""
    size = np.asarray(size_m, float)
    if size.shape != (3,) or not np.all(size > 0):
        raise ConfigError(f"a box needs three positive sides (x y z metres), got {list(size_m)}")
    markers = []
    for k, face in enumerate(faces):
        if face not in _NORMAL_AXIS:
            raise ConfigError(f"unknown face {face!r}; faces are {', '.join(_NORMAL_AXIS)}")
        axis = _NORMAL_AXIS[face]
        shorter = float(min(size[a] for a in range(3) if a != axis))
        side = marker_size_m if marker_size_m is not None else math.floor(1000 * MARKER_FILL * shorter) / 1000
        if not 0 < side <= shorter:
            raise ConfigError(f"a {1000 * side:.0f} mm marker does not fit the {face} face ({1000 * shorter:.0f} mm)")
        T = face_T_cube_marker(face, 1.0)
        T[:3, 3] *= size[axis]  # the face's plane: half the box's side along its normal
        markers.append(LayoutMarker(face, marker_id + (k if distinct_ids else 0), side, T))
    return CubeLayout(dictionary, tuple(markers))


def marker_cells(layout: CubeLayout) -> Cells:
    """Each marker's cells (black border included; True = white, row 0 = top) as OpenCV draws it."""
    import cv2

    out = {}
    for key in layout.keys:
        d = aruco_dictionary(key[0])
        n = d.markerSize + 2
        out[key] = cv2.aruco.generateImageMarker(d, key[1], n, borderBits=1) > 127
    return out


@dataclass(frozen=True, slots=True)
class BodyFiles:
    """What :func:`write_body` wrote (None: not asked for)."""

    svg: Path
    layout: Path | None
    pdf: Path | None


def write_body(layout: CubeLayout, out: str | Path, title: str, *, pdf: bool = False, net: bool = True,
               write_layout: bool = True, force: bool = False) -> BodyFiles:
    """Write ``<out>.svg`` (the printable sheet), ``<out>.toml`` (the layout, unless not
    ``write_layout``) and with ``pdf`` ``<out>.pdf`` (the same drawing through cairosvg). An
    existing file is not replaced unless ``force``; nothing is written when a check fails."""
    out = Path(out)
    stem = out.with_suffix("") if out.suffix in (".svg", ".toml", ".pdf") else out
    paths = BodyFiles(stem.with_suffix(".svg"), stem.with_suffix(".toml") if write_layout else None,
                      stem.with_suffix(".pdf") if pdf else None)
    existing = [str(p) for p in (paths.svg, paths.layout, paths.pdf) if p is not None and p.exists()]
    if existing and not force:
        raise ConfigError(f"{', '.join(existing)} already exist(s); choose another --out or pass --force")
    svg = body_svg(layout, title, marker_cells(layout), net)
    pdf_bytes = _pdf(svg) if pdf else None
    if not stem.parent.is_dir():
        raise ConfigError(f"{stem.parent} is not a folder")
    atomic_write(paths.svg, svg)
    if paths.layout is not None:
        write_toml(layout_to_table(layout), paths.layout)
    if paths.pdf is not None and pdf_bytes is not None:  # (both with pdf)
        paths.pdf.write_bytes(pdf_bytes)
    return paths


def _pdf(svg: str) -> bytes:
    try:
        import cairosvg
    except (ImportError, OSError) as exc:  # OSError: the package is there, the cairo library is not
        raise ConfigError(f"--pdf needs cairosvg and the cairo library (pip install cairosvg): {exc}") from None
    return cairosvg.svg2pdf(bytestring=svg.encode("utf-8"))
