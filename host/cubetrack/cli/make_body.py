"""Make a body to track: its printable sheet (SVG, and PDF with --pdf) and its layout file.

A body is any set of markers with sizes and poses. Presets:

  paper   the paper's cube (default): --cube-size 0.11 m, --marker-size 0.08 m, one id
          (--marker-id) on five faces, or ids counting up with --distinct-ids
  box     a cuboid of --size X Y Z metres (x forward, y left, z up) with a marker on each of
          --faces (default: the five faces but the bottom); each marker --marker-size, or 75 %
          of its face's shorter side

or --layout FILE: any layout (markers of any size, pose, id and dictionary) as it is.

A body whose markers lie flat on the faces of a box is drawn as a net to cut out and fold (solid:
cut, dashed: fold; glue tabs close the box), each marker where the layout puts it and turned as
the folded box shows it; any other body (or --tiles) as one cut-out tile per marker, labelled with
its face. Print at 100 % (no "fit to page") and check the 100 mm scale bar with a ruler.

A body on a robot drives on a floor (the default); a body carried or waved by hand is written with
--motion free, so the tracker follows it without a floor's assumptions (no upright prior: give it
--distinct-ids, or faces sharing an id keep it; docs/tracking.md, "A motion switch per body").

Writes OUT.svg, OUT.toml (the layout; not with --layout) and with --pdf OUT.pdf (needs cairosvg).
Point a robot's [[robots]] layout at OUT.toml. Existing files are kept unless --force.

Example:
  cubetrack make-body --out cube                      # the paper's cube: cube.svg, cube.toml
  cubetrack make-body --out crate --preset box --size 0.30 0.20 0.15 --distinct-ids --pdf
  cubetrack make-body --out wand --preset box --size 0.06 0.06 0.06 --distinct-ids --motion free
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

HELP = "write a printable sheet (SVG/PDF: markers at exact size, a cube net) and the layout of a body"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, type=Path, metavar="NAME", help="output name: NAME.svg, NAME.toml, NAME.pdf")
    p.add_argument("--preset", choices=("paper", "box"), default="paper", help="paper (default) or box")
    p.add_argument("--layout", type=Path, metavar="FILE", help="draw this layout instead of a preset")
    p.add_argument("--cube-size", type=float, default=0.11, metavar="M", help="paper: cube side (default 0.11)")
    p.add_argument("--size", type=float, nargs=3, metavar=("X", "Y", "Z"), help="box: sides in metres")
    p.add_argument("--faces", default="top,front,left,back,right", metavar="LIST",
                   help="box: faces with a marker (default top,front,left,back,right; bottom too)")
    p.add_argument("--marker-size", type=float, metavar="M",
                   help="marker side in metres (paper: 0.08; box: 75%% of each face's shorter side)")
    p.add_argument("--marker-id", type=int, default=1, metavar="N", help="(first) marker id (default 1)")
    p.add_argument("--distinct-ids", action="store_true", help="ids counting up from --marker-id, one per face")
    p.add_argument("--dictionary", default="DICT_4X4_50", metavar="NAME", help="ArUco dictionary (default DICT_4X4_50)")
    p.add_argument("--motion", metavar="KIND",
                   help="floor: on a robot (the default); free: hand-held, waved, carried (not with --layout)")
    p.add_argument("--tiles", action="store_true", help="one tile per marker instead of a net")
    p.add_argument("--pdf", action="store_true", help="also write NAME.pdf (through cairosvg)")
    p.add_argument("--force", action="store_true", help="replace existing output files")


def run(args: argparse.Namespace) -> int:
    from cubetrack.app.make_body import box_layout, write_body
    from cubetrack.core.errors import ConfigError
    from cubetrack.core.layout import paper_cube_layout, read_layout
    from cubetrack.detect.detector import aruco_dictionary

    aruco_dictionary(args.dictionary)  # a one-line error naming the valid names
    if args.layout is not None and args.motion is not None:
        raise ConfigError("--motion is for the presets; a --layout file says its own motion (its 'motion' key)")
    if args.layout is not None:
        layout, title = read_layout(args.layout), f"cubetrack body {args.layout.name}"
    elif args.preset == "paper":
        layout = paper_cube_layout(args.cube_size, args.marker_size or 0.08, args.marker_id, args.dictionary,
                                   args.distinct_ids)
        title = f"cubetrack: the paper's cube, {1000 * args.cube_size:.0f} mm"
    else:
        if args.size is None:
            raise ConfigError("--preset box needs --size X Y Z (metres)")
        faces = [f.strip() for f in args.faces.split(",") if f.strip()]
        layout = box_layout(args.size, args.marker_size, args.marker_id, args.dictionary, args.distinct_ids, faces)
        title = "cubetrack: box " + " x ".join(f"{1000 * s:.0f}" for s in args.size) + " mm"
    if args.motion is not None:
        layout = dataclasses.replace(layout, motion=args.motion)  # the layout's own check names the kinds
    ids = ", ".join(f"{m.face} {m.marker_id} ({1000 * m.size_m:.1f} mm)" for m in layout.markers)
    title += f"; {'/'.join(layout.dictionaries)}: {ids}"
    files = write_body(layout, args.out, title, pdf=args.pdf, net=not args.tiles,
                       write_layout=args.layout is None, force=args.force)
    for path in (files.svg, files.layout, files.pdf):
        if path is not None:
            print(f"wrote {path}")
    if layout.motion == "free" and layout.has_repeated_ids:
        print("note: faces share an id, so this free body is still held near upright to tell them apart (tilts "
              "beyond [estimator] upright_tolerance_deg are lost); --distinct-ids lets it tilt freely")
    print("print at 100 % (no fit to page) and check the 100 mm scale bar")
    return 0
