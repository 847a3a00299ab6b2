"""An exact, anti-aliased renderer of planar textured rectangles seen by a pinhole camera
(with optional plumb_bob lens distortion), for simulated camera frames.

Exactness. A final-image pixel ``u`` covers ``[u - 0.5, u + 0.5]`` (OpenCV's pixel-centre
convention: ``(0, 0)`` is the centre of the top-left pixel, the principal point of a centred
camera is ``((w - 1) / 2, (h - 1) / 2)``). The scene is rendered at ``s`` samples per pixel and
axis; supersampled pixel ``j`` has its centre at ``u = (j + 0.5) / s - 0.5``, so supersampled
index ``j = s * u + (s - 1) / 2``. Each rectangle is drawn with ``cv2.warpPerspective`` through a
homography that contains that transform and the texture's own convention (texel ``i`` covers
``[i, i + 1]`` of the texture, its centre ``i`` is where OpenCV samples). Bilinear sampling of a
texture whose texels are at least one supersampled pixel wide gives a coverage ramp centred on
every true edge (alpha 0.5 exactly on the edge), and ``cv2.resize(..., INTER_AREA)`` by an
integer factor is an exact box filter. Marker textures come from ``cv2.aruco.generateImageMarker``
at one pixel per cell, enlarged by an integer factor chosen per view so that a texel covers
one to two supersampled pixels. Lens distortion is applied by ``cv2.remap`` of the supersampled
ideal (pinhole) image through the exactly inverted distortion (``cv2.undistortPoints`` iterated to 1e-12).

Composition. A :class:`Solid` is a convex object: its faces (rectangles that never overlap,
drawn after back-face culling, coverage added so shared edges leave no seam) and decals (markers
printed on a face, drawn over it). Solids are composited over the background in the order
given (painter's order: the caller lists them far to near). A face reaching behind the camera
is drawn where its plane is met in front of the camera.

Time. :meth:`Renderer.render` averages the scene at given instants (a global shutter's motion
blur); :meth:`Renderer.render_exposure` renders a rolling shutter: each row of the (distorted,
sensor) image averages the scene over its own exposure window (:class:`Exposure`), the scene
between rendered instants taken as their linear blend (:func:`exposure_weights`).

Everything is greyscale albedo (0 black .. 1 white) until :func:`form_image` applies lighting,
blur, noise and quantisation.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import SimulationError
from cubetrack.core.geometry import invert_T

WHITE_ALBEDO = 0.85  # printed paper
BLACK_ALBEDO = 0.05  # printed ink
_MAX_TEXTURE = 4096
_MAX_PLAIN_TEXTURE = 1024
_CACHED_ONES = 1 << 18  # plain coverage textures up to this many texels are cached


@lru_cache(maxsize=64)
def _marker_bits(dictionary: str, marker_id: int) -> np.ndarray:
    """The marker image at one pixel per cell (black border included), 0 or 255."""
    try:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    except (AttributeError, cv2.error, TypeError):
        raise SimulationError(f"unknown ArUco dictionary {dictionary!r}; use a name like 'DICT_4X4_50'") from None
    n = d.markerSize + 2
    if not 0 <= marker_id < d.bytesList.shape[0]:
        raise SimulationError(f"marker id {marker_id} is not in {dictionary} (ids 0..{d.bytesList.shape[0] - 1})")
    return cv2.aruco.generateImageMarker(d, marker_id, n, borderBits=1)


@dataclass(frozen=True, slots=True)
class MarkerTexture:
    """An ArUco marker's black square (its black border cells included) as a texture."""

    dictionary: str
    marker_id: int
    inverted: bool = False  # printed white-on-black: every cell and the border swap albedos

    @property
    def cells(self) -> int:
        return _marker_bits(self.dictionary, self.marker_id).shape[0]

    def image(self, per_cell_x: int, per_cell_y: int) -> np.ndarray:
        """The albedo texture with ``per_cell_*`` texels per cell (float32, row 0 = marker top)."""
        return _marker_texture(self.dictionary, self.marker_id, per_cell_x, per_cell_y, self.inverted)


@lru_cache(maxsize=256)
def _marker_texture(dictionary: str, marker_id: int, cx: int, cy: int, inverted: bool = False) -> np.ndarray:
    bits = _marker_bits(dictionary, marker_id)
    tex = np.where((bits > 127) != inverted, np.float32(WHITE_ALBEDO), np.float32(BLACK_ALBEDO))
    return np.ascontiguousarray(np.repeat(np.repeat(tex, cy, axis=0), cx, axis=1))


@lru_cache(maxsize=256)
def _ones(h: int, w: int) -> np.ndarray:
    return np.ones((h, w), np.float32)


@dataclass(frozen=True, slots=True, eq=False)
class Quad:
    """A planar rectangle: its frame (origin at the centre, x right, y up, z out of the visible
    side — the marker frame convention), its size along x and y (metres), and either a uniform
    ``albedo`` or a ``texture`` covering the whole rectangle (row 0 along its +y edge).
    ``shade`` scales its brightness (how much light falls on it)."""

    T_world_quad: np.ndarray
    size_m: tuple[float, float]
    albedo: float = WHITE_ALBEDO
    texture: MarkerTexture | None = None
    shade: float = 1.0

    def corners_world(self) -> np.ndarray:
        """(4, 3) corners TL, TR, BR, BL (marker order) in the world frame."""
        w, h = self.size_m[0] / 2.0, self.size_m[1] / 2.0
        local = np.array([[-w, h, 0.0], [w, h, 0.0], [w, -h, 0.0], [-w, -h, 0.0]])
        return local @ self.T_world_quad[:3, :3].T + self.T_world_quad[:3, 3]


@dataclass(frozen=True, slots=True, eq=False)
class Solid:
    """A convex object: non-overlapping ``faces`` and ``decals`` printed on them."""

    faces: tuple[Quad, ...]
    decals: tuple[Quad, ...] = ()

    def corners_world(self) -> np.ndarray:
        return np.concatenate([q.corners_world() for q in self.faces])

    def outline_world(self, per_edge: int) -> np.ndarray:
        """Points along every face edge (``per_edge`` per edge, corners included), world frame."""
        corners = self.corners_world().reshape(-1, 4, 3)
        u = (np.arange(per_edge) / per_edge)[None, None, :, None]
        edges = corners[:, :, None, :] + u * (np.roll(corners, -1, axis=1) - corners)[:, :, None, :]
        return edges.reshape(-1, 3)


def box_faces(T_world_box: np.ndarray, size_m: tuple[float, float, float], albedo: float,
              bottom: bool = False) -> tuple[Quad, ...]:
    """The faces of a box centred at ``T_world_box`` with sides ``size_m`` (x, y, z), outward."""
    return tuple(Quad(T_world_box @ T, wh, albedo) for T, wh in _box_templates(tuple(size_m), bottom))


@lru_cache(maxsize=64)
def _box_templates(size_m: tuple[float, float, float], bottom: bool) -> tuple[tuple[np.ndarray, tuple], ...]:
    """Each face's frame in the box frame (z = outward normal) and its size."""
    hx, hy, hz = (v / 2.0 for v in size_m)
    # (outward normal, in-plane "up", half-extent along the normal, width, height)
    specs = [
        ((1, 0, 0), (0, 0, 1), hx, 2 * hy, 2 * hz),
        ((-1, 0, 0), (0, 0, 1), hx, 2 * hy, 2 * hz),
        ((0, 1, 0), (0, 0, 1), hy, 2 * hx, 2 * hz),
        ((0, -1, 0), (0, 0, 1), hy, 2 * hx, 2 * hz),
        ((0, 0, 1), (1, 0, 0), hz, 2 * hy, 2 * hx),
    ]
    if bottom:
        specs.append(((0, 0, -1), (1, 0, 0), hz, 2 * hy, 2 * hx))
    out = []
    for normal, up, half, width, height in specs:
        z = np.array(normal, float)
        y = np.array(up, float)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([np.cross(y, z), y, z])
        T[:3, 3] = z * half
        T.setflags(write=False)
        out.append((T, (width, height)))
    return tuple(out)


def project_points(intrinsics: CameraIntrinsics, T_world_cam: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(N, 2) pixel positions (OpenCV convention, lens distortion applied) of (N, 3) world points."""
    pts = np.asarray(points_world, float).reshape(-1, 3)
    T_cam_world = invert_T(np.asarray(T_world_cam, float))
    rvec, _ = cv2.Rodrigues(T_cam_world[:3, :3])
    out, _ = cv2.projectPoints(pts, rvec, T_cam_world[:3, 3], np.asarray(intrinsics.K, float),
                               np.asarray(intrinsics.dist, float).reshape(-1))
    return out.reshape(-1, 2)


class View:
    """One camera's geometry for rendering: intrinsics, pose, supersampling, distortion maps."""

    def __init__(self, intrinsics: CameraIntrinsics, T_world_cam: np.ndarray, supersample: int):
        self.intrinsics = intrinsics
        self.K = np.asarray(intrinsics.K, float)
        self.dist = np.asarray(intrinsics.dist, float).reshape(-1)
        self.T_world_cam = np.asarray(T_world_cam, float)
        self.T_cam_world = invert_T(self.T_world_cam)
        self.position_world = self.T_world_cam[:3, 3].copy()
        self.s = int(supersample)
        self.width, self.height = intrinsics.width, intrinsics.height
        self.distorted = bool(np.any(self.dist != 0))
        s = self.s
        if not self.distorted:
            self.canvas_origin = (0, 0)
            self.canvas_size = (self.width * s, self.height * s)
            self.map_x = self.map_y = None
        else:
            self._build_maps()

    def _build_maps(self) -> None:
        """For every supersampled pixel of the distorted image, where it looks in the ideal one."""
        s = self.s
        W, H = self.width * s, self.height * s
        # exact inversion on the pixel grid (and one pixel beyond), bilinear in between: the
        # map is smooth, interpolation errors stay below 1e-3 px for plausible lenses
        gx = np.arange(-1, self.width + 1, dtype=np.float64)
        gy = np.arange(-1, self.height + 1, dtype=np.float64)
        grid = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        coarse = cv2.undistortPoints(grid, self.K, self.dist, None, None, self.K, criteria)
        coarse = coarse.reshape(len(gy), len(gx), 2)
        # bilinear upsampling: output index j' of the enlarged grid samples coarse index
        # (j' + 0.5) / s - 0.5, i.e. pixel (j' - s + 0.5) / s - 0.5: crop s samples each side
        big = cv2.resize(coarse, (len(gx) * s, len(gy) * s), interpolation=cv2.INTER_LINEAR)
        ideal = big[s:s + H, s:s + W]
        ideal_s = s * ideal + (s - 1) / 2.0
        lo = np.floor(ideal_s.reshape(-1, 2).min(axis=0)).astype(int) - 2
        hi = np.ceil(ideal_s.reshape(-1, 2).max(axis=0)).astype(int) + 3
        if np.any(hi - lo > 4 * np.array([W, H])):
            raise SimulationError(f"lens distortion {self.dist.tolist()} is too strong to render")
        self.canvas_origin = (int(lo[0]), int(lo[1]))
        self.canvas_size = (int(hi[0] - lo[0]), int(hi[1] - lo[1]))
        self.map_x = (ideal_s[..., 0] - lo[0]).astype(np.float32)
        self.map_y = (ideal_s[..., 1] - lo[1]).astype(np.float32)

    def moved(self, T_world_cam: np.ndarray) -> View:
        """The same camera at another pose (the distortion maps, which depend on the lens only, are shared)."""
        view = copy.copy(self)
        view.T_world_cam = np.asarray(T_world_cam, float)
        view.T_cam_world = invert_T(view.T_world_cam)
        view.position_world = view.T_world_cam[:3, 3].copy()
        return view

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 2) pixel positions (with distortion) of world points; points must be in front."""
        return project_points(self.intrinsics, self.T_world_cam, points_world)

    def image_box(self, solids: tuple[Solid, ...] | list[Solid], pad: int = 4) -> tuple[int, int, int, int] | None:
        """The final-image box ``(x0, y0, x1, y1)`` (``pad`` pixels wider) that holds the solids'
        image; the whole image when one of them reaches behind the camera, None when nothing is
        in front. Distorted edges bow, so they are sampled along their length."""
        if not solids:
            return None
        distorted = self.distorted
        pts = np.concatenate([s.outline_world(8) if distorted else s.corners_world() for s in solids])
        depth = self.depth(pts)
        if np.all(depth <= 0.0):
            return None
        uv = self._near_outline(solids) if np.any(depth <= 1e-3) else self.project(pts)
        if uv is None:
            return None
        x0 = max(int(math.floor(uv[:, 0].min())) - pad, 0)
        y0 = max(int(math.floor(uv[:, 1].min())) - pad, 0)
        x1 = min(int(math.ceil(uv[:, 0].max())) + pad + 1, self.width)
        y1 = min(int(math.ceil(uv[:, 1].max())) + pad + 1, self.height)
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1, y1

    def _near_outline(self, solids) -> np.ndarray | None:
        """Image points around solids reaching behind the camera: each face clipped 1 mm in
        front of it, the box of their undistorted images, that box's outline distorted."""
        boxes = []
        for solid in solids:
            for q in solid.faces:
                c = q.corners_world() @ self.T_cam_world[:3, :3].T + self.T_cam_world[:3, 3]
                if np.all(c[:, 2] < 1e-3):
                    continue
                xy = _clip_in_front(np.column_stack([c[:, :2], c[:, 2]]), 1e-3) if np.any(c[:, 2] < 1e-3) \
                    else c[:, :2] / c[:, 2:3]
                boxes.append(np.r_[xy.min(axis=0), xy.max(axis=0)])  # normalised image coordinates
        if not boxes:
            return None
        b = np.array(boxes)
        lo, hi = b[:, :2].min(axis=0), b[:, 2:].max(axis=0)
        # the box's corners and edge points, distorted where they lie near the image
        edge = np.linspace(0.0, 1.0, 33)
        ring = np.concatenate([np.column_stack([lo[0] + edge * (hi[0] - lo[0]), np.full(33, y)])
                               for y in (lo[1], hi[1])]
                              + [np.column_stack([np.full(33, x), lo[1] + edge * (hi[1] - lo[1])])
                                 for x in (lo[0], hi[0])])
        limit = 2.0 * max(self.width, self.height) / min(self.K[0, 0], self.K[1, 1])
        ring = np.clip(ring, -limit, limit)
        uv, _ = cv2.projectPoints(np.column_stack([ring, np.ones(len(ring))]), np.zeros(3), np.zeros(3), self.K,
                                  self.dist)
        return uv.reshape(-1, 2)

    def depth(self, points_world: np.ndarray) -> np.ndarray:
        pts = np.asarray(points_world, float).reshape(-1, 3)
        return pts @ self.T_cam_world[2, :3] + self.T_cam_world[2, 3]

    def plane_to_ideal(self, T_world_plane: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
        """Homography from plane coordinates (x, y) metres to a patch's supersampled pixel indices;
        ``origin`` is the patch's top-left in ideal supersampled indices."""
        T = self.T_cam_world @ T_world_plane
        M = np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
        s = self.s
        A = np.array([[s, 0.0, (s - 1) / 2.0 - origin[0]], [0.0, s, (s - 1) / 2.0 - origin[1]], [0, 0, 1.0]])
        return A @ self.K @ M


def _texel_to_plane(size_m: tuple[float, float], tw: int, th: int) -> np.ndarray:
    """Texture pixel index -> rectangle coordinates (metres); texel i covers [i, i+1]."""
    w, h = size_m
    return np.array([[w / tw, 0.0, -w / 2 + 0.5 * w / tw],
                     [0.0, -h / th, h / 2 - 0.5 * h / th],
                     [0.0, 0.0, 1.0]])


def _warp(texture: np.ndarray, H_tex_to_dst: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return cv2.warpPerspective(texture, np.linalg.inv(H_tex_to_dst), size,
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def _clip_in_front(p: np.ndarray, near: float) -> np.ndarray:
    """Image points (x, y) of a polygon given as homogeneous rows (x z, y z, z), clipped to
    depth ``z >= near``."""
    out = []
    for a, b in zip(p, np.roll(p, -1, axis=0), strict=True):
        if a[2] >= near:
            out.append(a)
        if (a[2] >= near) != (b[2] >= near):
            out.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    q = np.array(out)
    return q[:, :2] / q[:, 2:3]


def _quad_layer(view: View, quad: Quad, origin: tuple[int, int], shape: tuple[int, int]):
    """The coverage and premultiplied albedo of one rectangle in a patch, restricted to its
    bounding box: ``(y0, y1, x0, x1, alpha, value)`` or None when it is not visible."""
    T = quad.T_world_quad
    # back-face culling: the camera must be on the quad's +z side
    if float(np.dot(view.position_world - T[:3, 3], T[:3, 2])) <= 1e-9:
        return None
    Hp = view.plane_to_ideal(T, origin)
    w, h = quad.size_m
    local = np.array([[-w / 2, h / 2, 1.0], [w / 2, h / 2, 1.0], [w / 2, -h / 2, 1.0], [-w / 2, -h / 2, 1.0]])
    p = local @ Hp.T  # the third coordinate is the depth in the camera (metres)
    front = p[:, 2] > 1e-3
    if not front.any():
        return None
    # a quad reaching behind the camera can cover any part of the patch; each pixel's ray meets
    # its plane once, in front or behind: the pixels that meet it behind are masked below
    partial = not front.all()
    xy = p[front, :2] / p[front, 2:3]
    # the box of its image: of the part at least 1 mm in front of the camera when it reaches
    # behind (p is linear in the plane coordinates, so the outline is clipped in p)
    outline = _clip_in_front(p, 1e-3) if partial else xy
    x0 = max(int(math.floor(outline[:, 0].min())) - 2, 0)
    y0 = max(int(math.floor(outline[:, 1].min())) - 2, 0)
    x1 = min(int(math.ceil(outline[:, 0].max())) + 3, shape[1])
    y1 = min(int(math.ceil(outline[:, 1].max())) + 3, shape[0])
    if x1 <= x0 or y1 <= y0:
        return None
    # Jacobian of the projective map at the corners: supersampled pixels per metre along x, y
    J = (Hp[:2, :2][None] - xy[:, :, None] * Hp[2, :2][None, None, :]) / p[front, 2][:, None, None]
    px_per_m_x = float(np.linalg.norm(J[:, :, 0], axis=1).min())
    px_per_m_y = float(np.linalg.norm(J[:, :, 1], axis=1).min())
    if quad.texture is None:
        # plain quads only need texels small enough for a sharp edge; one reaching behind the
        # camera (a passer-by) gets at most _MAX_PLAIN_TEXTURE texels, so a softer edge
        most = _MAX_PLAIN_TEXTURE if partial else _MAX_TEXTURE
        tw = int(np.clip(math.floor(w * px_per_m_x), 1, most))
        th = int(np.clip(math.floor(h * px_per_m_y), 1, most))
        tex = None
    else:
        n = quad.texture.cells
        cx = int(np.clip(math.floor(w / n * px_per_m_x), 1, _MAX_TEXTURE // n))
        cy = int(np.clip(math.floor(h / n * px_per_m_y), 1, _MAX_TEXTURE // n))
        tex = quad.texture.image(cx, cy)
        th, tw = tex.shape
    shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
    H = shift @ Hp @ _texel_to_plane(quad.size_m, tw, th)
    size = (x1 - x0, y1 - y0)
    alpha = _warp(_ones(th, tw) if th * tw <= _CACHED_ONES else np.ones((th, tw), np.float32), H, size)
    value = alpha * np.float32(quad.albedo * quad.shade) if tex is None else _warp(tex, H, size)
    if tex is not None and quad.shade != 1.0:
        value *= np.float32(quad.shade)
    if partial:
        # the third coordinate of H^-1 (pixel, 1) is 1 / depth of the plane point on that ray
        Hi = np.linalg.inv(H)
        third = (Hi[2, 0] * np.arange(size[0], dtype=np.float64)[None, :]
                 + Hi[2, 1] * np.arange(size[1], dtype=np.float64)[:, None] + Hi[2, 2])
        behind = third <= 0
        alpha[behind] = 0.0
        value[behind] = 0.0
    return y0, y1, x0, x1, alpha, value


def draw_solid(canvas: np.ndarray, origin: tuple[int, int], view: View, solid: Solid) -> None:
    """Composite a solid over a float32 patch in place (``origin``: the patch's top-left in
    ideal supersampled indices)."""
    layers = [lay for q in solid.faces if (lay := _quad_layer(view, q, origin, canvas.shape)) is not None]
    if not layers:
        return
    y0 = min(lay[0] for lay in layers)
    y1 = max(lay[1] for lay in layers)
    x0 = min(lay[2] for lay in layers)
    x1 = max(lay[3] for lay in layers)
    A = np.zeros((y1 - y0, x1 - x0), np.float32)
    P = np.zeros_like(A)
    for ly0, ly1, lx0, lx1, alpha, value in layers:
        A[ly0 - y0:ly1 - y0, lx0 - x0:lx1 - x0] += alpha
        P[ly0 - y0:ly1 - y0, lx0 - x0:lx1 - x0] += value
    for q in solid.decals:
        lay = _quad_layer(view, q, origin, canvas.shape)
        if lay is None:
            continue
        ly0, ly1, lx0, lx1, alpha, value = lay
        ly0, ly1, lx0, lx1 = max(ly0, y0), min(ly1, y1), max(lx0, x0), min(lx1, x1)
        if ly1 <= ly0 or lx1 <= lx0:
            continue
        a = alpha[ly0 - lay[0]:ly1 - lay[0], lx0 - lay[2]:lx1 - lay[2]]
        v = value[ly0 - lay[0]:ly1 - lay[0], lx0 - lay[2]:lx1 - lay[2]]
        sub = P[ly0 - y0:ly1 - y0, lx0 - x0:lx1 - x0]
        sub *= 1.0 - a
        sub += v
    np.minimum(A, 1.0, out=A)
    region = canvas[y0:y1, x0:x1]
    region *= 1.0 - A
    region += P


@dataclass(frozen=True, slots=True, eq=False)
class Floor:
    """The floor plane z = 0 with a square albedo texture centred on the world origin, and a
    uniform wall albedo above the horizon."""

    texture: np.ndarray
    half_size_m: float
    wall_albedo: float = 0.6

    @property
    def mean_albedo(self) -> float:
        return float(self.texture.mean())


def draw_floor(canvas: np.ndarray, origin: tuple[int, int], view: View, floor: Floor) -> None:
    """Fill a patch with the floor (and the wall above the horizon), overwriting it."""
    Hp = view.plane_to_ideal(np.eye(4), origin)
    n = floor.texture.shape[0]
    side = 2.0 * floor.half_size_m
    H = Hp @ _texel_to_plane((side, side), n, n)
    Hinv = np.linalg.inv(Hp)
    h, w = canvas.shape
    canvas[:] = cv2.warpPerspective(floor.texture, np.linalg.inv(H), (w, h),
                                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=floor.mean_albedo)
    # above the horizon the ray meets the floor behind the camera: the third coordinate is <= 0
    third = (Hinv[2, 0] * np.arange(w, dtype=np.float64)[None, :]
             + Hinv[2, 1] * np.arange(h, dtype=np.float64)[:, None] + Hinv[2, 2])
    canvas[third <= 0] = floor.wall_albedo


@dataclass(frozen=True, slots=True)
class Exposure:
    """When the rows of one image are exposed. Row ``v`` integrates the scene over
    ``[t_v - exposure_s / 2, t_v + exposure_s / 2]`` with ``t_v = time_s + (v - ref_row) * row_s``
    (scene seconds): ``row_s`` 0 is a global shutter, otherwise a rolling shutter whose rows are
    ``row_s`` apart; ``time_s`` is the mid-exposure instant of row ``ref_row``."""

    time_s: float
    exposure_s: float
    row_s: float = 0.0
    ref_row: float = 0.0

    def row_times(self, rows: np.ndarray) -> np.ndarray:
        return self.time_s + (np.asarray(rows, float) - self.ref_row) * self.row_s


def exposure_weights(row_times_s: np.ndarray, exposure_s: float, sample_times_s: np.ndarray) -> np.ndarray:
    """(rows, samples) weights that average the scene over each row's exposure window, the scene
    between two rendered instants (``sample_times_s``, evenly spaced) taken as their linear
    blend: the integral of each sample's hat function over the window (its value at the row's
    instant for a zero exposure). Each row's weights sum to 1 when the samples span its window."""
    step = float(sample_times_s[1] - sample_times_s[0]) if len(sample_times_s) > 1 else 1.0
    u = (np.asarray(row_times_s, float)[:, None] - np.asarray(sample_times_s, float)[None, :]) / step
    if exposure_s <= 0:
        return np.maximum(0.0, 1.0 - np.abs(u))
    half = 0.5 * exposure_s / step

    def integral(x: np.ndarray) -> np.ndarray:  # of the unit hat from -inf to x
        x = np.clip(x, -1.0, 1.0)
        return np.where(x <= 0.0, 0.5 * (x + 1.0) ** 2, 1.0 - 0.5 * (1.0 - x) ** 2)

    return (integral(u + half) - integral(u - half)) / (2.0 * half)


class Renderer:
    """Renders one camera's frames: a static background (floor, wall, static solids) computed
    once, and moving solids drawn only in the region of the image they can touch."""

    def __init__(self, view: View, floor: Floor, static: tuple[Solid, ...] = ()):
        self.view = view
        cw, ch = view.canvas_size
        canvas = np.empty((ch, cw), np.float32)
        draw_floor(canvas, view.canvas_origin, view, floor)
        for solid in static:
            draw_solid(canvas, view.canvas_origin, view, solid)
        self._canvas = canvas
        self.background = self._final_region(0, 0, view.width, view.height, [()])

    def _final_region(self, fx0: int, fy0: int, fx1: int, fy1: int,
                      solids_per_sample: list[tuple[Solid, ...]], row_weights: np.ndarray | None = None
                      ) -> np.ndarray:
        """The final image in a box, the solids drawn at each sample and the samples averaged:
        equally, or per final row with ``row_weights`` (rows, samples)."""
        v, s = self.view, self.view.s
        sx0, sy0, sx1, sy1 = fx0 * s, fy0 * s, fx1 * s, fy1 * s
        if v.map_x is None or v.map_y is None:  # not distorted
            base = self._canvas[sy0:sy1, sx0:sx1]
            origin = (v.canvas_origin[0] + sx0, v.canvas_origin[1] + sy0)
            mx = my = None
        else:
            mx = v.map_x[sy0:sy1, sx0:sx1]
            my = v.map_y[sy0:sy1, sx0:sx1]
            ch, cw = self._canvas.shape
            bx0 = max(int(math.floor(float(mx.min()))) - 2, 0)
            by0 = max(int(math.floor(float(my.min()))) - 2, 0)
            bx1 = min(int(math.ceil(float(mx.max()))) + 3, cw)
            by1 = min(int(math.ceil(float(my.max()))) + 3, ch)
            base = self._canvas[by0:by1, bx0:bx1]
            origin = (v.canvas_origin[0] + bx0, v.canvas_origin[1] + by0)
            mx, my = mx - np.float32(bx0), my - np.float32(by0)
        acc: np.ndarray | None = None
        for k, solids in enumerate(solids_per_sample):
            patch: np.ndarray = base.copy()
            for solid in solids:
                draw_solid(patch, origin, v, solid)
            if mx is not None and my is not None:
                patch = cv2.remap(patch, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            if row_weights is not None:
                patch *= np.repeat(row_weights[:, k].astype(np.float32), s)[:, None]
            acc = patch if acc is None else acc + patch
        assert acc is not None  # at least one sample
        if row_weights is None:
            acc /= np.float32(len(solids_per_sample))
        if s == 1:
            return acc
        return cv2.resize(acc, (fx1 - fx0, fy1 - fy0), interpolation=cv2.INTER_AREA)

    def render(self, solids_per_sample: list[tuple[Solid, ...]]) -> np.ndarray:
        """The albedo image (float32, final size) with the moving solids drawn; several entries
        in ``solids_per_sample`` (the scene at instants within the exposure) are averaged."""
        if not solids_per_sample or not any(solids_per_sample):
            return self.background.copy()
        box = self.view.image_box([solid for solids in solids_per_sample for solid in solids])
        out = self.background.copy()
        if box is None:
            return out
        fx0, fy0, fx1, fy1 = box
        out[fy0:fy1, fx0:fx1] = self._final_region(fx0, fy0, fx1, fy1, solids_per_sample)
        return out

    def render_exposure(self, solids_at, exposure: Exposure, step_s: float, band_rows: int = 32) -> np.ndarray:
        """The albedo image of moving solids seen through ``exposure`` (a rolling shutter, motion
        blur): ``solids_at(t)`` gives the solids at scene time t; the scene is rendered at
        instants ``step_s`` apart (choose it so nothing moves more than a fraction of a pixel
        between two) and each row averages the instants of its own exposure window
        (:func:`exposure_weights`). Rows are done in bands of ``band_rows``, each with the
        instants its rows need, so the cost grows with the exposure, not with the readout."""
        v = self.view
        out = self.background.copy()
        cache: dict[int, list[tuple[Solid, tuple[int, int, int, int]]]] = {}

        def at(k: int) -> list[tuple[Solid, tuple[int, int, int, int]]]:
            """The solids in view at instant k, each with its image box."""
            if k not in cache:
                solids = solids_at(exposure.time_s + k * step_s)
                cache[k] = [(solid, box) for solid in solids if (box := v.image_box((solid,))) is not None]
            return cache[k]

        half = 0.5 * exposure.exposure_s
        for b0 in range(0, v.height, band_rows):
            b1 = min(b0 + band_rows, v.height)
            times = exposure.row_times(np.arange(b0, b1)) - exposure.time_s  # relative to the reference row
            k0 = math.floor((float(times.min()) - half) / step_s - 1e-9)
            k1 = math.ceil((float(times.max()) + half) / step_s + 1e-9)
            ks = np.arange(k0, max(k1, k0 + 1) + 1)
            weights = exposure_weights(times, exposure.exposure_s, ks * step_s)
            used = np.flatnonzero(weights.sum(axis=0) > 0)
            # only the solids whose image reaches into the band's rows
            samples = [[(solid, box) for solid, box in at(int(ks[i])) if box[1] < b1 and box[3] > b0] for i in used]
            boxes = [box for sample in samples for _, box in sample]
            if not boxes:
                continue
            x0 = min(b[0] for b in boxes)
            x1 = max(b[2] for b in boxes)
            out[b0:b1, x0:x1] = self._final_region(x0, b0, x1, b1, [tuple(s for s, _ in sample) for sample in samples],
                                                   weights[:, used])
        return out


def lighting_gain(width: int, height: int, gradient: float, direction_rad: float, vignetting: float) -> np.ndarray:
    """Per-pixel illumination factor: a linear gradient across the image and radial vignetting."""
    x = np.arange(width, dtype=np.float32) - (width - 1) / 2.0
    y = np.arange(height, dtype=np.float32) - (height - 1) / 2.0
    half_diag = math.hypot(width, height) / 2.0
    proj = (math.cos(direction_rad) * x[None, :] + math.sin(direction_rad) * y[:, None]) / (2.0 * half_diag)
    r2 = (x[None, :] ** 2 + y[:, None] ** 2) / half_diag**2
    return ((1.0 + gradient * proj) * (1.0 - vignetting * r2)).astype(np.float32)


def form_image(albedo: np.ndarray, gain: np.ndarray, blur_px: float, noise_std: float,
               rng: np.random.Generator) -> np.ndarray:
    """Albedo -> 8-bit sensor image: illumination, optical blur, noise, rounding."""
    img = albedo * gain * np.float32(255.0)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px, borderType=cv2.BORDER_REFLECT)
    if noise_std > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_std)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise SimulationError("OpenCV could not encode a JPEG frame")
    return buf.tobytes()
