"""Each effect of the realistic preset does what it must: a wide-angle lens rendered exactly,
rolling shutter and motion blur, calibration-like camera_info errors, a hand-built cube, a
tilting robot on sharp turns, auto-exposure steps, people walking through. Rendering-level
tests use the renderer directly; the recording-level ones share one short realistic session."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import make_T
from cubetrack.core.layout import paper_cube_layout
from cubetrack.simulate import SimulationParams
from cubetrack.simulate.imperfections import auto_exposure_gains, built_layout, calibrated_intrinsics
from cubetrack.simulate.motion import PERSON_BODY_M
from cubetrack.simulate.render import Exposure, Floor, Quad, Renderer, Solid, View, exposure_weights, project_points
from cubetrack.simulate.scenario import build_scene

# a camera 10 m above the floor looking straight up sees only the uniform "wall": scenes given in
# the camera frame are placed in front of it
T_WORLD_CAM = make_T(np.eye(3), [0.0, 0.0, 10.0])
BLACK = Floor(np.zeros((8, 8), np.float32), 4.0, 0.0)
WIDE = CameraIntrinsics(640, 480, np.array([[525.0, 0.0, 323.0], [0.0, 525.0, 236.0], [0.0, 0.0, 1.0]]),
                        np.array([-0.3, 0.1, 0.0, 0.0, 0.0]))
PINHOLE = CameraIntrinsics(640, 480, np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]]),
                           np.zeros(5))


def _square_at(centre_cam: np.ndarray, side_m: float) -> Solid:
    """A white square facing the camera (its +z towards the camera), centre in camera coordinates."""
    R = np.diag([1.0, -1.0, -1.0])
    return Solid((Quad(T_WORLD_CAM @ make_T(R, centre_cam), (side_m, side_m), 1.0),))


def _centroid(img: np.ndarray, near: np.ndarray, half: int = 5) -> np.ndarray:
    x0, y0 = round(near[0]) - half, round(near[1]) - half
    win = img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1]
    ys, xs = np.mgrid[0:win.shape[0], 0:win.shape[1]]
    return np.array([(win * xs).sum(), (win * ys).sum()]) / win.sum() + [x0, y0]


def test_wide_angle_lens_puts_rendered_points_where_projectpoints_does():
    """k1 -0.3 (about 14 % barrel at the corners), principal point off centre: small squares
    (about 3 px) over the whole image, corners included, sit within 0.05 px of cv2.projectPoints."""
    view = View(WIDE, T_WORLD_CAM, 4)
    # normalised directions across the image, out to the distorted corners
    targets = [(u, v) for u in np.linspace(12, 628, 6) for v in np.linspace(12, 468, 5)]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    rays = cv2.undistortPoints(np.array(targets, float).reshape(-1, 1, 2), WIDE.K, WIDE.dist, None, None, None,
                               criteria).reshape(-1, 2)
    depth = 1.0
    centres = np.column_stack([rays * depth, np.full(len(rays), depth)])
    side = 3.0 / 525.0 * depth
    image = Renderer(view, BLACK, tuple(_square_at(c, side) for c in centres)).background
    truth = project_points(WIDE, T_WORLD_CAM, centres + T_WORLD_CAM[:3, 3])
    errors = [np.linalg.norm(_centroid(image, t) - t) for t in truth]
    assert max(errors) <= 0.05, max(errors)
    assert np.linalg.norm(truth[0] - targets[0]) < 1e-6  # the grid reaches the distorted corner


def _moving_bar(velocity_m_s: np.ndarray, width_m: float = 0.02, height_m: float = 0.3):
    """solids_at(t) of a white bar 1 m in front of the camera, moving in its plane."""
    def at(t: float) -> tuple[Solid, ...]:
        centre = np.array([0.0, 0.0, 1.0]) + t * velocity_m_s
        R = np.diag([1.0, -1.0, -1.0])
        return (Solid((Quad(T_WORLD_CAM @ make_T(R, centre), (width_m, height_m), 1.0),)),)
    return at


def _row_centroids(img: np.ndarray, rows: range) -> np.ndarray:
    xs = np.arange(img.shape[1])
    return np.array([(img[r] * xs).sum() / img[r].sum() for r in rows])


@pytest.mark.parametrize("exposure_s", [0.0, 0.005])
def test_rolling_shutter_displaces_each_row_by_velocity_times_its_time(exposure_s):
    view = View(PINHOLE, T_WORLD_CAM, 4)
    renderer = Renderer(view, BLACK)
    velocity = np.array([0.5, 0.0, 0.0])  # 260 px/s sideways in the image
    px_per_s = 0.5 * 520.0
    row_s = 0.030 / 480
    t_ref = 0.123
    exposure = Exposure(t_ref, exposure_s, row_s, 239.5)
    image = renderer.render_exposure(_moving_bar(velocity), exposure, step_s=0.5 / px_per_s, band_rows=40)
    rows = range(170, 310)  # inside the bar (its image spans rows 161..318)
    centroids = _row_centroids(image, rows)
    slope, at_ref = np.polyfit(np.array(rows) - 239.5, centroids, 1)
    assert slope == pytest.approx(px_per_s * row_s, rel=0.01)       # 0.01625 px per row
    expected = 319.5 + px_per_s * t_ref  # where the bar's centre is at the reference row's instant
    assert abs(at_ref - expected) < 0.01
    assert np.abs(centroids - (expected + slope * (np.array(rows) - 239.5))).max() < 0.02
    # a global shutter keeps the bar upright
    upright = renderer.render_exposure(_moving_bar(velocity), Exposure(t_ref, exposure_s, 0.0, 239.5),
                                       step_s=0.5 / px_per_s)
    assert np.ptp(_row_centroids(upright, rows)) < 0.01


def test_motion_blur_spreads_a_moving_edge_over_its_path_during_the_exposure():
    view = View(PINHOLE, T_WORLD_CAM, 4)
    renderer = Renderer(view, BLACK)
    px_per_s = 2.0 * 520.0
    exposure_s = 0.01  # 10.4 px of travel
    at = _moving_bar(np.array([2.0, 0.0, 0.0]), width_m=0.06)
    sharp = renderer.render_exposure(at, Exposure(0.0, 0.0), step_s=0.5 / px_per_s)[240]
    blurred = renderer.render_exposure(at, Exposure(0.0, exposure_s), step_s=0.5 / px_per_s)[240]
    assert blurred.sum() == pytest.approx(sharp.sum(), rel=1e-4)      # the same light, spread out
    xs = np.arange(640)
    assert (blurred * xs).sum() / blurred.sum() == pytest.approx((sharp * xs).sum() / sharp.sum(), abs=0.01)
    ramp = np.count_nonzero((blurred > 0.02) & (blurred < 0.98) & (xs < 320))
    assert abs(ramp - px_per_s * exposure_s) <= 2  # the leading edge ramps over the travel
    # the global-shutter sampler of the recordings (equal instants) agrees with it
    offsets = exposure_s * (np.arange(12) / 11 - 0.5)
    sampled = renderer.render([at(dt)[0:1] for dt in offsets])[240]
    assert (sampled * xs).sum() / sampled.sum() == pytest.approx((sharp * xs).sum() / sharp.sum(), abs=0.01)


def test_exposure_weights_average_each_row_over_its_window():
    samples = np.arange(-3, 4) * 0.002
    w = exposure_weights(np.array([0.0, 0.0013, -0.0034]), 0.005, samples)
    assert np.allclose(w.sum(axis=1), 1.0)
    assert np.allclose(w @ samples, [0.0, 0.0013, -0.0034])  # the window's mean time
    point = exposure_weights(np.array([0.0013]), 0.0, samples)
    assert np.allclose(point[0, 3:5], [0.35, 0.65])


def test_a_quad_reaching_behind_the_camera_renders_its_visible_part():
    """A passer-by beside a camera: a floor-like quad from 1 m behind to 3 m in front of the
    camera looks the same as its part in front (whose near edge projects far outside)."""
    view = View(PINHOLE, T_WORLD_CAM, 4)
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # normal -y (up, towards the camera)

    def quad(z0: float, z1: float) -> Solid:
        centre = np.array([0.0, 0.3, (z0 + z1) / 2])
        return Solid((Quad(T_WORLD_CAM @ make_T(R, centre), (20.0, z1 - z0), 1.0),))

    whole = Renderer(view, BLACK).render([(quad(-1.0, 3.0),)])
    front = Renderer(view, BLACK).render([(quad(0.05, 3.0),)])
    assert whole[293:].min() > 0.99 and whole[:290].max() == 0.0  # far edge at row 291.5
    assert np.abs(whole - front).sum() < 0.5 * 640 * 0.05


def test_camera_info_errors_look_like_a_calibration():
    truth = WIDE
    p = SimulationParams.realistic()
    rng = np.random.default_rng(1)
    infos = [calibrated_intrinsics(truth, p, rng) for _ in range(3000)]
    df = np.array([[i.K[0, 0] / truth.K[0, 0] - 1, i.K[1, 1] / truth.K[1, 1] - 1] for i in infos])
    dc = np.array([i.K[:2, 2] - truth.K[:2, 2] for i in infos])
    dk = np.array([i.dist[:2] - truth.dist[:2] for i in infos])
    assert 0.8 * p.info_focal_error < df.std(axis=0).min() and df.std(axis=0).max() < 1.3 * p.info_focal_error
    assert np.corrcoef(df.T)[0, 1] > 0.8                 # fx and fy share most of their error
    assert dc.std(axis=0) == pytest.approx([p.info_principal_error_px] * 2, rel=0.1)
    assert dk[:, 0].std() == pytest.approx(p.info_k1_error, rel=0.1)
    assert np.corrcoef(dk.T)[0, 1] < -0.9                # k2 trades against k1
    assert calibrated_intrinsics(truth, SimulationParams(), rng) is truth


def test_built_cube_is_off_by_millimetres_and_a_degree():
    nominal = paper_cube_layout()
    p = SimulationParams.realistic()
    shifts, turns, tilts, scales = [], [], [], []
    for seed in range(40):
        built = built_layout(nominal, p, np.random.default_rng(seed))
        for m, b in zip(nominal.markers, built.markers, strict=True):
            T = np.linalg.inv(m.T_cube_marker) @ b.T_cube_marker  # the built marker in the nominal one's frame
            shifts.append(np.linalg.norm(T[:2, 3]) * 1e3)
            turns.append(math.degrees(math.atan2(T[1, 0], T[0, 0])))
            tilts.append(math.degrees(math.acos(np.clip(T[2, 2], -1, 1))))
            scales.append(b.size_m / m.size_m)
            assert (b.face, b.marker_id) == (m.face, m.marker_id)
    assert 1.0 < np.mean(shifts) < 1.6 and np.percentile(shifts, 90) < 2.6   # 1-2 mm
    assert np.std(turns) == pytest.approx(1.0, rel=0.2)
    assert 0.4 < np.mean(tilts) < 1.0                                        # about 0.5 deg per axis
    assert 0.985 < min(scales) and max(scales) < 0.995                       # printed ~1 % small
    assert built_layout(nominal, SimulationParams(), np.random.default_rng(0)) is nominal


def test_robot_tilts_and_bounces_and_drives_sharp_turns():
    p = SimulationParams.realistic(duration_s=30.0, people=0)
    scene = build_scene(p)
    dt = 0.004
    times = np.arange(0.0, 30.0, dt)
    robot = np.array([scene.T_world_robot(t) for t in times])
    T = robot @ scene.T_robot_cube()
    assert np.allclose(T[1234], scene.T_world_cube(times[1234]))
    tilt = np.degrees(np.arccos(np.clip(T[:, 2, 2], -1, 1)))
    assert 0.3 < math.sqrt(np.mean(tilt**2)) < 3.0
    assert 0.5e-3 < np.std(T[:, 2, 3]) < 6e-3
    ground = robot[:, :2, 3]
    speed = np.linalg.norm(np.diff(ground, axis=0), axis=1) / dt
    assert speed.max() <= p.speed_m_s * 1.01 and speed.max() > 0.9 * p.speed_m_s
    heading = np.unwrap(np.arctan2(robot[:, 1, 0], robot[:, 0, 0]))
    yaw_rate = np.degrees(np.abs(np.diff(heading))) / dt
    assert yaw_rate.max() <= p.turn_rate_deg_s * 1.05
    # sharp turns: the heading swings by 90 degrees or more within 1.5 s
    window = int(1.5 / dt)
    assert np.degrees(np.abs(heading[window:] - heading[:-window])).max() >= 90.0
    accel = np.abs(np.diff(speed[::5])) / (5 * dt)
    assert np.percentile(accel, 99) <= 1.2 * p.accel_m_s2
    # the cube rides on the robot: it stays above the tilted robot's ground point
    assert np.abs(T[:, :2, 3] - ground).max() < p.cube_centre_height_m * math.sin(math.radians(tilt.max())) + 1e-6


def test_auto_exposure_steps_and_settles():
    p = SimulationParams(exposure_steps_per_s=0.5, exposure_step=0.3)
    times = np.arange(0.0, 200.0, 0.05)
    g = auto_exposure_gains(p, times, 0.0, 200.0, np.random.default_rng(3))
    jumps = np.flatnonzero(np.abs(np.diff(g)) > 1e-9)
    assert 60 < len(jumps) / 5 < 140                       # each step settles over 5 frames of 50 ms
    assert g.min() >= 0.6 and g.max() <= 1.6 and np.ptp(g) > 0.5
    assert np.array_equal(auto_exposure_gains(SimulationParams(), times, 0.0, 200.0, np.random.default_rng(3)),
                          np.ones(len(times)))


def test_people_walk_through_the_view_and_hide_what_is_behind_them():
    p = SimulationParams.realistic(duration_s=30.0)
    scene = build_scene(p)
    assert len(scene.people) == 2 and all(person.crossings for person in scene.people)
    found = False
    for person in scene.people:
        for t in np.arange(0.0, 30.0, 0.1):
            T = person.T_world_person(t)
            if T is None:
                continue
            for cam in scene.cameras:
                assert np.linalg.norm(T[:2, 3] - cam.T_world_cam[:2, 3]) > 0.6 - 1e-9
            assert np.linalg.norm(T[:2, 3] - scene.T_world_robot(t)[:2, 3]) > 0.5 - 1e-9
            if found:
                continue
            hip = T[:3, 3] + [0.0, 0.0, 0.3 * PERSON_BODY_M[2]]
            cam = scene.cameras[0]
            if (np.linalg.inv(cam.T_world_cam) @ np.r_[hip, 1.0])[2] < 0.5:
                continue
            uv = project_points(cam.intrinsics, cam.T_world_cam, hip[None])[0]
            if not (50 < uv[0] < 590 and 50 < uv[1] < 430):
                continue
            renderer = Renderer(View(cam.intrinsics, cam.T_world_cam, 2), scene.floor, (scene.world_marker,))
            image = renderer.render([scene.moving_solids(t, cam.T_world_cam[:3, 3])])
            u, v = np.round(uv).astype(int)
            # the person's clothes, shaded by up to face_shading
            assert (1.0 - p.face_shading) * person.albedo - 0.01 < image[v, u] < person.albedo + 0.01
            found = True
    assert found


def test_an_inverted_marker_renders_white_on_black_where_the_detector_finds_it():
    """inverted_markers: the marker texture's cells and border swap albedos on a black face; the
    detector finds it (with detect_inverted_marker only) at its projected corners."""
    from cubetrack.detect.detector import Detector, DetectorParams
    from cubetrack.simulate.render import BLACK_ALBEDO, MarkerTexture, form_image

    R = np.diag([1.0, -1.0, -1.0])
    T_marker = T_WORLD_CAM @ make_T(R @ cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0], [0.02, -0.01, 0.6])
    face = Quad(T_marker @ make_T(np.eye(3), [0.0, 0.0, -1e-4]), (0.11, 0.11), BLACK_ALBEDO)
    decal = Quad(T_marker, (0.08, 0.08), texture=MarkerTexture("DICT_4X4_50", 5, inverted=True))
    albedo = Renderer(View(PINHOLE, T_WORLD_CAM, 4), Floor(np.full((8, 8), 0.5, np.float32), 4.0, 0.0),
                      (Solid((face,), (decal,)),)).background
    gray = form_image(albedo, np.ones_like(albedo), 0.6, 1.0, np.random.default_rng(0))
    assert MarkerTexture("DICT_4X4_50", 5, inverted=True).image(1, 1)[0, 0] > 0.5   # the border is white
    assert Detector(DetectorParams()).detect(gray) == ()
    (found,) = Detector(DetectorParams(detect_inverted_marker=True)).detect(gray)
    truth = project_points(PINHOLE, T_WORLD_CAM, (T_marker @ np.array(
        [[-0.04, 0.04, 0, 1], [0.04, 0.04, 0, 1], [0.04, -0.04, 0, 1], [-0.04, -0.04, 0, 1]]).T).T[:, :3])
    assert found.marker_id == 5 and np.abs(found.corners_px - truth).max() < 0.3
