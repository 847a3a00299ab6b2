"""Issue 15 item 4: `cubetrack make-body` — the printable sheet of any body (the paper's cube, a
box with per-face marker sizes, a body of two dictionaries that is no box) and its layout file.
The SVG is parsed (every marker square has its exact physical size), rasterised at a known DPI by
an independent renderer (cairosvg) and decoded by OpenCV (every marker found where and as large as
it should be), and the layout written beside it reads back as the body."""

import re
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from cubetrack.app.make_body import box_layout, marker_cells
from cubetrack.cli import main as cli_main
from cubetrack.core.geometry import R_from_rotvec, make_T
from cubetrack.core.layout import CubeLayout, LayoutMarker, paper_cube_layout, read_layout
from cubetrack.io.body_sheet import body_svg, box_half_sizes, unfold_transforms

cairosvg = pytest.importorskip("cairosvg", reason="rasterising the SVG needs cairosvg (a test extra)")

SVG = "{http://www.w3.org/2000/svg}"
DPI = 100  # 0.254 mm per pixel: a 1 % error of an 80 mm marker is 3 pixels


def markers_in(svg: str) -> list[dict]:
    """Each marker group of the SVG: id, dictionary, cells and its four corners in millimetres
    (cell square (0,0)-(n,n) through its transform), TL TR BR BL."""
    out = []
    for g in ET.fromstring(svg).iter(f"{SVG}g"):
        if g.get("class") != "marker":
            continue
        a, b, c, d, e, f = (float(v) for v in re.fullmatch(r"matrix\(([^)]*)\)", g.get("transform")).group(1).split())
        n = int(g.get("data-cells"))
        cells = np.array([[0, 0], [n, 0], [n, n], [0, n]], float)
        corners = np.column_stack([a * cells[:, 0] + c * cells[:, 1] + e, b * cells[:, 0] + d * cells[:, 1] + f])
        rect = g.find(f"{SVG}rect")
        assert (rect.get("x"), rect.get("y"), rect.get("width"), rect.get("height")) == ("0", "0", str(n), str(n))
        out.append({"id": int(g.get("data-id")), "dictionary": g.get("data-dictionary"), "cells": n, "mm": corners})
    return out


def page_mm(svg: str) -> tuple[float, float]:
    root = ET.fromstring(svg)
    width, height = float(root.get("width").removesuffix("mm")), float(root.get("height").removesuffix("mm"))
    assert [float(v) for v in root.get("viewBox").split()] == [0.0, 0.0, width, height]  # 1 unit = 1 mm
    return width, height


def decoded(svg: str, dictionaries) -> dict[tuple[str, int], np.ndarray]:
    """OpenCV's detections in the SVG rasterised at DPI: (dictionary, id) -> corners in mm."""
    png = cairosvg.svg2png(bytestring=svg.encode(), dpi=DPI, background_color="white")
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert image.shape[1] == pytest.approx(page_mm(svg)[0] / 25.4 * DPI, abs=1.0)
    out = {}
    for name in dictionaries:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), params)
        corners, ids, _ = detector.detectMarkers(image)
        for c, i in zip(corners, [] if ids is None else ids.ravel(), strict=True):
            out[(name, int(i))] = c.reshape(4, 2) * 25.4 / DPI  # pixel centres -> mm (offset below)
    return out


def sheet(layout: CubeLayout, title: str = "body") -> str:
    return body_svg(layout, title, marker_cells(layout))


def check_sheet(svg: str, layout: CubeLayout) -> None:
    """Every marker of the layout is on the sheet once, its black square exactly its size, and
    OpenCV decodes it in the raster, corner for corner where the SVG put it."""
    drawn = markers_in(svg)
    assert sorted((d["dictionary"], d["id"]) for d in drawn) == sorted(
        (name, m.marker_id) for name, m in zip(layout.marker_dictionaries, layout.markers, strict=True))
    for d, m in zip(drawn, layout.markers, strict=True):
        sides = np.linalg.norm(np.roll(d["mm"], -1, axis=0) - d["mm"], axis=1)
        assert np.allclose(sides, 1000 * m.size_m, atol=1e-6), (m.face, sides)
        diagonals = np.linalg.norm(d["mm"][2] - d["mm"][0]), np.linalg.norm(d["mm"][3] - d["mm"][1])
        assert np.allclose(diagonals, 1000 * m.size_m * np.sqrt(2), atol=1e-6)  # a square, not a rhombus
    found = decoded(svg, set(layout.marker_dictionaries))
    for d in drawn:
        key = (d["dictionary"], d["id"])
        if key not in found:
            continue  # repeated ids: checked below by count
        # OpenCV's corners are pixel centres: pixel k covers [k, k + 1] in the raster
        error = found[key] + 0.5 * 25.4 / DPI - d["mm"]
        if np.abs(error).max() < 0.2:  # within a pixel's 0.254 mm: this is the one
            d["decoded"] = True
    assert all(d.get("decoded") for d in drawn) or layout.has_repeated_ids
    assert len({(d["dictionary"], d["id"]) for d in drawn if d.get("decoded")}) == len(layout.keys)


def test_the_papers_cube_is_a_net_of_five_markers_at_exact_size(tmp_path):
    layout = paper_cube_layout(distinct_ids=True)
    svg = sheet(layout, "paper cube")
    check_sheet(svg, layout)
    # the net: six 110 mm faces (dashed: folds), the scale bar 100 mm
    root = ET.fromstring(svg)
    faces = [p for p in root.iter(f"{SVG}path") if p.get("stroke-dasharray") and p.get("d").endswith("Z")]
    assert len(faces) == 6
    for p in faces:
        xy = np.array([[float(v) for v in pt.split()] for pt in p.get("d")[2:-2].split(" L ")])
        assert np.allclose(np.linalg.norm(np.roll(xy, -1, axis=0) - xy, axis=1), 110.0, atol=1e-6)
    assert any(re.fullmatch(r"M[\d.]+ [\d.]+h100", p.get("d")) for p in root.iter(f"{SVG}path"))


def test_a_repeated_id_cube_decodes_five_times():
    layout = paper_cube_layout()  # one id on five faces: every face still decodes
    svg = sheet(layout, "paper cube")
    drawn = markers_in(svg)
    assert [d["id"] for d in drawn] == [1] * 5
    png = cairosvg.svg2png(bytestring=svg.encode(), dpi=DPI, background_color="white")
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    _c, ids, _ = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)).detectMarkers(image)
    assert sorted(ids.ravel().tolist()) == [1] * 5


def test_folding_the_net_puts_every_marker_back_on_its_face():
    """The net is the box unfolded: each face's unfold transform is rigid and lays the face in the
    top's plane, outside side up; a marker's printed corners, folded back, are its layout corners."""
    layout = box_layout((0.30, 0.20, 0.15), distinct_ids=True,
                        faces=("top", "front", "left", "back", "right", "bottom"))
    half = box_half_sizes(layout)
    assert np.allclose(half, [0.15, 0.10, 0.075])
    U = unfold_transforms(half)
    for m in layout.markers:
        face = m.face
        T = U[face]
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.isclose(np.linalg.det(T[:3, :3]), 1.0)
        flat = m.corners_cube_m() @ T[:3, :3].T + T[:3, 3]
        assert np.allclose(flat[:, 2], half[2])  # in the top's plane
        assert np.allclose(T[:3, :3] @ m.T_cube_marker[:3, 2], [0, 0, 1])  # printed side up
    check_sheet(sheet(layout, "crate"), layout)


def test_per_face_sizes_and_two_dictionaries_on_tiles():
    """A body that is no box (one marker tilted), markers of two dictionaries and three sizes:
    one tile each, every one decoded at its exact size."""
    layout = CubeLayout("DICT_4X4_50", (
        LayoutMarker("a", 3, 0.05, make_T(np.eye(3), [0.0, 0.0, 0.1])),
        LayoutMarker("b", 3, 0.07, make_T(R_from_rotvec([0.3, 0.0, 0.0]), [0.1, 0.0, 0.0]), "DICT_5X5_100"),
        LayoutMarker("c", 7, 0.035, make_T(R_from_rotvec([0.0, 1.0, 0.0]), [0.0, 0.1, 0.0])),
    ))
    assert box_half_sizes(layout) is None and layout.dictionaries == ("DICT_4X4_50", "DICT_5X5_100")
    check_sheet(sheet(layout, "odd body"), layout)


def test_make_body_cli_writes_the_sheet_and_a_layout_that_reads_back(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli_main, "COMMANDS", {"make-body": "make_body"})
    out = tmp_path / "crate"
    args = ["make-body", "--out", str(out), "--preset", "box", "--size", "0.3", "0.2", "0.15", "--distinct-ids",
            "--marker-id", "4", "--dictionary", "DICT_5X5_100", "--pdf"]
    assert cli_main.main(args) == 0
    assert "wrote" in capsys.readouterr().out
    layout = read_layout(out.with_suffix(".toml"))
    assert layout.motion == "floor"  # a body on a robot unless told (--motion free: below)
    expected = box_layout((0.3, 0.2, 0.15), None, 4, "DICT_5X5_100", True)
    assert [(m.face, m.marker_id, m.size_m) for m in layout.markers] == [
        (m.face, m.marker_id, m.size_m) for m in expected.markers]
    assert [m.size_m for m in layout.markers] == [0.15, 0.112, 0.112, 0.112, 0.112]
    for a, b in zip(layout.markers, expected.markers, strict=True):
        assert np.allclose(a.T_cube_marker, b.T_cube_marker, atol=1e-9)
    check_sheet(out.with_suffix(".svg").read_text(), layout)
    assert out.with_suffix(".pdf").read_bytes().startswith(b"%PDF")
    # nothing is overwritten without --force; bad input is one line
    before = out.with_suffix(".toml").read_bytes()
    assert cli_main.main(args) == 1
    assert "already exist" in capsys.readouterr().err
    assert out.with_suffix(".toml").read_bytes() == before
    for bad, message in ((["--preset", "box"], "needs --size"),
                         (["--preset", "box", "--size", "0.1", "0.1", "0.1", "--marker-size", "0.2"], "does not fit"),
                         (["--marker-size", "0.2"], "must be positive and fit the cube side"),
                         (["--dictionary", "DICT_NOPE"], "DICT_NOPE"),
                         (["--motion", "hand"], "motion must be one of floor, free, got 'hand'"),
                         (["--layout", str(out.with_suffix(".toml")), "--motion", "free"], "says its own motion")):
        assert cli_main.main(["make-body", "--out", str(tmp_path / "x")] + bad) == 1
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.toml").exists()
    assert cli_main.main(["make-body", "--out", str(tmp_path / "wand"), "--motion", "free"]) == 0
    assert read_layout(tmp_path / "wand.toml").motion == "free"
    assert "held near upright" in capsys.readouterr().out  # one id on five faces: the prior stays
    assert cli_main.main(["make-body", "--out", str(tmp_path / "wand2"), "--motion", "free", "--distinct-ids"]) == 0
    assert "upright" not in capsys.readouterr().out
