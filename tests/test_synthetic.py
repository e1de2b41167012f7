"""Synthetic scenes against independent truths: closed-form depths of planes, boxes, spheres and
cylinders; re-projection between frames with the ground-truth poses; the noise model's statistics;
the written TUM folder read back by other code; the ground-truth mesh against analytic surfaces.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics, axial_noise, load_intrinsics_json
from kintinuous_ref.datasets import synthetic, tum
from kintinuous_ref.datasets.synthetic import SensorModel
from kintinuous_ref.datasets.synthetic.scene import Scene
from kintinuous_ref.datasets.synthetic.solids import Box, Cylinder, Rectangle, Sphere
from kintinuous_ref.datasets.synthetic.textures import random_material
from kintinuous_ref.errors import ConfigError, DatasetError, KintinuousError
from kintinuous_ref.program.cli import main

CAMERA = Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
NAMES = ("desk", "corridor", "dark", "floor", "loop")


def _scenario(solids, noise=False, camera=CAMERA, seed=0) -> synthetic.Scenario:
    """A one-frame scenario around hand-made solids (camera at the world origin)."""
    rng = np.random.default_rng(seed)
    scene = Scene(solids, [[random_material(rng, "object")] for _ in solids], seed=seed)
    trajectory = tum.Trajectory(np.array([0.0]), np.eye(4)[None])
    sensor = SensorModel() if noise else SensorModel.exact()
    return synthetic.Scenario("test", scene, camera, trajectory, np.ones(1), sensor, seed)


def _pose(rotation_vector=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Rotation (axis-angle) then translation: X -> R X + t."""
    return _translation(translation) @ se3.exp(np.r_[rotation_vector, 0.0, 0.0, 0.0])


def _translation(t) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = t
    return pose


def _pixel_rays(camera=CAMERA):
    """Camera-frame rays (x, y, 1) of every pixel centre, from the pinhole model directly."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    return (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy


# --- exact geometry -------------------------------------------------------------------------


def test_plane_depth_equals_closed_form():
    # A tilted plane n . X = n . centre (world). Seen from a camera at pose (R, t), its points
    # R p + t satisfy (R^T n) . p = n . (centre - t), so pixel ray (x, y, 1) meets it at depth
    # z = n . (centre - t) / ((R^T n) . (x, y, 1)).
    # Tolerance 1e-6 relative: float64 ray casting, float32 output (6e-8 relative).
    normal = np.array([0.2, -0.3, -1.0])
    normal /= np.linalg.norm(normal)
    centre = np.array([0.1, 0.05, 2.0])
    z_axis = normal  # the rectangle's local z axis is its normal
    x_axis = np.cross([0.0, 1.0, 0.0], z_axis)
    x_axis /= np.linalg.norm(x_axis)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
    pose[:3, 3] = centre
    scenario = _scenario([Rectangle(pose, (20.0, 20.0))])
    camera_pose = _pose((0.05, -0.1, 0.2), (0.3, -0.2, 0.1))
    n_cam = camera_pose[:3, :3].T @ normal
    c_cam = normal @ (centre - camera_pose[:3, 3])
    x, y = _pixel_rays()
    expected = c_cam / (n_cam[0] * x + n_cam[1] * y + n_cam[2])
    _, depth = scenario.render_at(camera_pose)
    assert np.all(depth > 0)
    np.testing.assert_allclose(depth, expected, rtol=1e-6)


def test_axis_aligned_box_shows_its_front_face_only():
    # Camera on the box's axis: only the front face z = zc - hz is visible, inside the projection
    # of its rectangle; everything else is background (depth 0).
    hx, hy, hz, zc = 0.3, 0.2, 0.25, 2.0
    scenario = _scenario([Box(_translation((0.0, 0.0, zc)), (hx, hy, hz))])
    _, depth = scenario.render_at(np.eye(4))
    x, y = _pixel_rays()
    front = zc - hz
    inside = (np.abs(x * front) < hx - 1e-9) & (np.abs(y * front) < hy - 1e-9)
    np.testing.assert_allclose(depth[inside], front, rtol=1e-6)
    assert np.all(depth[~inside] == 0)
    assert inside.sum() > 1000  # the test is about something


def test_rotated_box_matches_face_by_face_intersection():
    # Independent algorithm: intersect each of the 6 face rectangles separately, keep the nearest
    # (the renderer uses the slab method). Agreement to 1e-6 relative away from silhouette edges.
    half = np.array([0.3, 0.2, 0.25])
    box_pose = _pose((0.3, 0.5, -0.2), (0.1, -0.05, 1.8))
    scenario = _scenario([Box(box_pose, tuple(half))])
    _, depth = scenario.render_at(np.eye(4))
    x, y = _pixel_rays()
    rays = np.stack([x, y, np.ones_like(x)], -1)
    best = np.full(x.shape, np.inf)
    rotation, centre = box_pose[:3, :3], box_pose[:3, 3]
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = rotation[:, axis]
            point = centre + sign * half[axis] * n
            t = (n @ point) / (rays @ n)
            hit_local = (rays * t[..., None] - centre) @ rotation
            others = [a for a in range(3) if a != axis]
            ok = (t > 0) & np.all(np.abs(hit_local[..., others]) <= half[others], axis=-1)
            best = np.where(ok & (t < best), t, best)
    hit = np.isfinite(best)
    # silhouette pixels can go either way by rounding; compare where both agree on a hit
    both = hit & (depth > 0)
    assert (hit != (depth > 0)).sum() <= 2
    np.testing.assert_allclose(depth[both], best[both], rtol=1e-6)
    assert both.sum() > 1000


def test_sphere_and_cylinder_depths_equal_closed_forms():
    # Sphere at (0, 0, D) radius r: along ray (x, y, 1) with s = x^2 + y^2,
    # z = (D - sqrt(r^2 (1 + s) - D^2 s)) / (1 + s).
    d, r = 2.0, 0.4
    _, depth = _scenario([Sphere(_translation((0.0, 0.0, d)), r)]).render_at(np.eye(4))
    x, y = _pixel_rays()
    s = x * x + y * y
    disc = r * r * (1 + s) - d * d * s
    inside = disc > 1e-4  # away from the silhouette
    expected = (d - np.sqrt(np.where(inside, disc, 0.0))) / (1 + s)
    np.testing.assert_allclose(depth[inside], expected[inside], rtol=1e-6)
    assert np.all(depth[disc < -1e-4] == 0)

    # Cylinder with its axis along the camera's y (vertical in the image), at distance D:
    # in the x-z plane (x t)^2 + (t - D)^2 = r^2, so
    # z = (D - sqrt(r^2 (1 + x^2) - D^2 x^2)) / (1 + x^2) for rays between the caps, whatever y.
    axis_along_y = _pose((np.pi / 2, 0.0, 0.0), (0.0, 0.0, d))
    scenario = _scenario([Cylinder(axis_along_y, r, 0.3)])
    _, depth = scenario.render_at(np.eye(4))
    disc = r * r * (1 + x * x) - d * d * x * x
    z_side = (d - np.sqrt(np.maximum(disc, 0.0))) / (1 + x * x)
    on_side = (disc > 1e-4) & (np.abs(y * z_side) < 0.3 - 1e-3)
    np.testing.assert_allclose(depth[on_side], z_side[on_side], rtol=1e-6)
    assert on_side.sum() > 500


# --- consistency of poses and renderer ------------------------------------------------------


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples at (u, v) and whether all four neighbours exist (non-zero)."""
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 < image.shape[1] - 1) & (v0 < image.shape[0] - 1)
    u0, v0 = np.where(inside, u0, 0), np.where(inside, v0, 0)
    a, b = (u - u0)[..., None], (v - v0)[..., None]
    img = image.reshape(image.shape[0], image.shape[1], -1).astype(np.float64)
    corners = [img[v0, u0], img[v0, u0 + 1], img[v0 + 1, u0], img[v0 + 1, u0 + 1]]
    value = (1 - a) * (1 - b) * corners[0] + a * (1 - b) * corners[1]
    value += (1 - a) * b * corners[2] + a * b * corners[3]
    valid = inside & np.all([np.all(c > 0, axis=-1) for c in corners], axis=0)
    return value, valid


@pytest.mark.parametrize("name", ["desk", "loop"])
def test_frames_reproject_onto_each_other_with_ground_truth_poses(name):
    # Back-project frame i with its pose, project into frame j with its pose: the inverse depth
    # there (bilinear in 1/z, exact on planes) matches frame j's rendered depth, and the colour
    # matches (textures are world-anchored, shading is view-independent).
    scenario = synthetic.make_scenario(name, frames=12, width=160, height=120, noise=False)
    camera = scenario.camera
    i, j = 0, 11
    colour_i, depth_i = scenario.render(i)
    colour_j, depth_j = scenario.render(j)
    points = camera.backproject(depth_i.astype(np.float64))[depth_i > 0]
    relative = se3.inverse(scenario.trajectory.poses[j]) @ scenario.trajectory.poses[i]
    in_j = se3.transform_points(relative, points)
    uv = camera.project(in_j)
    inverse_j = np.where(depth_j > 0, 1.0 / np.maximum(depth_j, 1e-9), 0.0)
    sampled, valid = _bilinear(inverse_j, uv[:, 0], uv[:, 1])
    predicted = 1.0 / in_j[:, 2]
    # Points landing inside frame j: the predicted inverse depth agrees to 1e-3 relative except
    # where occluded in j or where the 4 neighbours straddle two surfaces (about 10 % in desk).
    assert valid.mean() > 0.7
    agree = valid & (np.abs(sampled[:, 0] - predicted) < 1e-3 * predicted)
    assert agree.sum() > 0.85 * valid.sum(), f"{agree.sum() / valid.sum():.3f} re-project"
    depth_error = np.abs(1.0 / sampled[agree, 0] - in_j[agree, 2])
    # planar pieces interpolate exactly in 1/z (float32 depth: ~1e-7 m); curved ones nearly
    assert np.median(depth_error) < 1e-6
    assert np.percentile(depth_error, 95) < 1e-5

    colour_sampled, _ = _bilinear(colour_j, uv[:, 0], uv[:, 1])
    colour_diff = np.abs(colour_sampled[agree] - colour_i[depth_i > 0][agree]).max(axis=1)
    # texture detail between pixel centres makes bilinear colour differ a few levels at most
    assert np.median(colour_diff) < 4
    assert np.mean(colour_diff < 15) > 0.9


def test_render_matches_render_at_and_is_deterministic():
    scenario = synthetic.make_scenario("desk", frames=5, width=80, height=60, noise=False)
    colour, depth = scenario.render(3)
    colour2, depth2 = scenario.render_at(scenario.trajectory.poses[3])
    np.testing.assert_array_equal(colour, colour2)
    np.testing.assert_array_equal(depth, depth2)
    noisy = synthetic.make_scenario("desk", frames=5, width=80, height=60, noise=True)
    first, again = noisy.render(3), noisy.render(3)
    np.testing.assert_array_equal(first[1], again[1])
    assert np.any(first[1] != depth)  # the noise is there


def test_trajectory_prefix_does_not_depend_on_length_and_seed_changes_it():
    short = synthetic.make_scenario("floor", frames=10, width=64, height=48)
    long = synthetic.make_scenario("floor", frames=300, width=64, height=48)
    np.testing.assert_array_equal(short.trajectory.poses, long.trajectory.poses[:10])
    other = synthetic.make_scenario("floor", frames=10, width=64, height=48, seed=1)
    assert np.abs(other.trajectory.poses - short.trajectory.poses).max() > 1e-4


# --- the sensor model ------------------------------------------------------------------------


def _frontal_plane(distance: float) -> Rectangle:
    return Rectangle(_translation((0.0, 0.0, distance)), (50.0, 50.0))


@pytest.mark.parametrize("distance", [1.0, 2.5, 3.8])
def test_axial_noise_std_matches_nguyen_model(distance):
    # sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 (Nguyen et al. 2012), checked on 19200 samples of a
    # frontal plane: the standard error of a std estimate is sigma / sqrt(2N) = 0.5 %, quantisation
    # (0.2 mm steps) adds variance step^2 / 12, far below; tolerance 3 %.
    scenario = _scenario([_frontal_plane(distance)], noise=True)
    _, depth = scenario.render_at(np.eye(4))
    measured = depth[depth > 0].astype(np.float64)
    assert measured.size > 0.95 * depth.size
    expected = 0.0012 + 0.0019 * (distance - 0.4) ** 2
    assert axial_noise(distance) == pytest.approx(expected)
    assert np.std(measured - distance) == pytest.approx(expected, rel=0.03)
    assert abs(np.mean(measured - distance)) < 4 * expected / np.sqrt(measured.size)


def test_depth_is_quantised_to_depth_units_only_with_noise():
    scenario = _scenario([_frontal_plane(1.7123), Sphere(_translation((0.1, 0.0, 1.2)), 0.2)])
    _, exact = scenario.render_at(np.eye(4), noise=False)
    _, noisy = scenario.render_at(np.eye(4), noise=True)
    units = noisy[noisy > 0].astype(np.float64) * 5000.0
    # float32 holds k / 5000 to 1e-7 relative: 1e-3 units at these depths
    np.testing.assert_allclose(units, np.round(units), atol=1e-3)
    steps = np.diff(np.unique(np.round(units)))
    assert steps.min() == 1.0  # the finest step is one unit, 1/5000 m
    exact_units = exact[exact > 0].astype(np.float64) * 5000.0
    assert np.mean(np.abs(exact_units - np.round(exact_units)) > 0.01) > 0.5


def test_range_and_grazing_angle_limits():
    # Camera 0.3 m above a floor, looking level: pixel ray (x, y, 1) is (x, 1, -y) in the world,
    # so the floor is at depth 0.3 / y and the angle between ray and floor normal has
    # cos = y / |(x, y, 1)|. Beyond 80 degrees or beyond 4 m there is no depth; below, there is.
    height = 0.3
    look_level = np.eye(4)
    look_level[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]  # y down -> -z
    look_level[2, 3] = height
    scenario = _scenario([Rectangle(np.eye(4), (50.0, 50.0))], noise=True)
    _, depth = scenario.render_at(look_level)
    _, exact = scenario.render_at(look_level, noise=False)
    x, y = _pixel_rays()
    cos_angle = y / np.sqrt(x * x + y * y + 1.0)
    z = np.where(y > 0, height / np.maximum(y, 1e-9), np.inf)
    within = z < 3.99
    np.testing.assert_allclose(exact[within], z[within], rtol=1e-6)  # exact: all angles
    steep = cos_angle > np.cos(np.radians(79.0))
    grazing = (cos_angle < np.cos(np.radians(81.0))) & within
    assert grazing.sum() > 500 and steep.sum() > 1000
    assert np.all(depth[grazing] == 0)
    assert np.all(depth[z > 4.0] == 0) and np.all(exact[z > 4.0] == 0)
    assert np.mean(depth[steep] > 0) > 0.97  # a few dropouts where rows jump > 6 % at most
    # nothing closer than 0.4 m either
    _, too_close = _scenario([_frontal_plane(0.35)]).render_at(np.eye(4))
    assert np.all(too_close == 0)


def test_dropouts_along_depth_discontinuities():
    # A sphere in front of a wall: every pixel whose 4-neighbour lies on the other surface
    # (a jump of 1 m) loses its depth with the noise model, and keeps it without.
    scenario = _scenario([_frontal_plane(2.5), Sphere(_translation((0.0, 0.0, 1.5)), 0.3)])
    _, exact = scenario.render_at(np.eye(4), noise=False)
    _, noisy = scenario.render_at(np.eye(4), noise=True)
    jump = np.zeros(exact.shape, bool)
    vertical = np.abs(np.diff(exact, axis=0)) > 0.5
    horizontal = np.abs(np.diff(exact, axis=1)) > 0.5
    jump[1:] |= vertical
    jump[:-1] |= vertical
    jump[:, 1:] |= horizontal
    jump[:, :-1] |= horizontal
    assert jump.sum() > 50
    assert np.all(noisy[jump] == 0)
    assert np.all(exact[jump] > 0)


def test_colour_noise_and_exact_colour():
    scenario = _scenario([_frontal_plane(1.5)])
    exact, _ = scenario.render_at(np.eye(4), noise=False)
    noisy, _ = scenario.render_at(np.eye(4), noise=True)
    diff = noisy.astype(float) - exact.astype(float)
    # read noise 1.5 levels plus shot noise 0.01 per level: std between 1.5 and 2.5 at these levels
    assert 1.5 < diff.std() < 2.5
    assert abs(diff.mean()) < 0.1


def test_dark_scenario_dims_the_middle_third():
    scenario = synthetic.make_scenario("dark", frames=30, width=80, height=60, noise=False)
    assert np.all(scenario.brightness[:10] == 1.0) and np.all(scenario.brightness[20:] == 1.0)
    assert np.all(scenario.brightness[10:20] == pytest.approx(0.02))
    dark, _ = scenario.render(15)
    lit, _ = scenario.render_at(scenario.trajectory.poses[15], noise=False)
    ratio = dark.astype(float).mean() / lit.astype(float).mean()
    assert ratio == pytest.approx(0.02, abs=0.004)  # uint8 rounding of ~2-level values


# --- scenarios and their motion ---------------------------------------------------------------


def test_list_scenarios_has_the_five():
    scenarios = synthetic.list_scenarios()
    assert set(NAMES) <= set(scenarios)
    assert all(isinstance(s, str) and s for s in scenarios.values())


@pytest.mark.parametrize("name", NAMES)
def test_hand_held_motion_and_scene_coverage(name):
    scenario = synthetic.make_scenario(name, frames=300, width=64, height=48, noise=False)
    trajectory = scenario.trajectory
    np.testing.assert_allclose(np.diff(trajectory.timestamps), 1 / 30, atol=1e-12)
    increments = [
        se3.inverse(a) @ b for a, b in zip(trajectory.poses[:-1], trajectory.poses[1:], strict=True)
    ]
    speed = np.array([np.linalg.norm(m[:3, 3]) for m in increments]) * 30
    turn = np.degrees([se3.rotation_angle(m) for m in increments])
    assert 0.1 < speed.mean() < 0.5 and speed.max() < 0.6  # m/s, hand-held
    assert turn.max() < 3.0  # degrees per frame
    # smooth: no velocity jumps (acceleration below 2 m/s^2)
    positions = trajectory.positions
    assert np.linalg.norm(np.diff(positions, 2, axis=0), axis=1).max() * 900 < 2.0
    # the sensor sees the scene all along: most pixels have depth in frames 0, 150 and 299
    for index in (0, 150, 299):
        _, depth = scenario.render(index)
        assert (depth > 0).mean() > 0.6, f"{name} frame {index}"


def test_loop_is_a_closed_lap_of_more_than_ten_metres():
    lap = 840
    scenario = synthetic.make_scenario("loop", frames=lap + 1, width=32, height=24)
    positions = scenario.trajectory.positions
    length = np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()
    assert length > 10.0
    assert np.linalg.norm(positions[lap] - positions[0]) < 0.03  # tremor only
    extent = positions.max(axis=0) - positions.min(axis=0)
    assert extent[0] > 4.0 and extent[1] > 3.0


def test_corridor_camera_moves_along_walls_parallel_to_its_motion():
    # ICP's degenerate case: every surface in view is parallel to the direction of motion (x).
    scenario = synthetic.make_scenario("corridor", frames=300, width=32, height=24)
    motion = scenario.trajectory.positions[-1] - scenario.trajectory.positions[0]
    assert motion[0] > 3.0 and abs(motion[1]) < 0.5
    room = scenario.scene.solids[0]
    assert len(scenario.scene.solids) == 1 and isinstance(room, Box) and room.inside
    # the end walls stay out of range (> 4 m) from every pose of the sequence
    ends = room.pose[0, 3] + np.array([-1.0, 1.0]) * room.half_size[0]
    gaps = np.abs(scenario.trajectory.positions[:, 0, None] - ends[None, :])
    assert gaps.min() > 2.9  # and the camera looks 30 degrees sideways, so depth > 4 m


def test_textures_have_gradients_at_every_pyramid_level():
    # Photometric odometry needs intensity gradients at each level (paper IV-A; thresholds
    # 12/5/3/1 intensity units per pixel after Sobel / 8); a flat colour would give none.
    scenario = synthetic.make_scenario("desk", frames=1, width=320, height=240, noise=False)
    colour, _ = scenario.render(0)
    intensity = colour.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    fractions = []
    for threshold in (12.0, 5.0, 3.0, 1.0):
        blurred = cv2.GaussianBlur(intensity, (3, 3), 0.8)
        dx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3) / 8
        dy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3) / 8
        fractions.append(np.mean(dx * dx + dy * dy >= threshold**2))
        intensity = cv2.pyrDown(intensity)
    assert min(fractions) > 0.03, fractions


# --- files on disk ---------------------------------------------------------------------------


def test_written_folder_round_trips(tmp_path):
    out = synthetic.write_scenario("desk", tmp_path / "desk", frames=3, width=80, height=60)
    scenario = synthetic.make_scenario("desk", frames=3, width=80, height=60)
    for name in ("rgb.txt", "depth.txt", "associations.txt", "groundtruth.txt", "scene.ply"):
        assert (out / name).is_file()
    groundtruth = tum.read_trajectory(out / "groundtruth.txt")
    np.testing.assert_allclose(groundtruth.timestamps, scenario.trajectory.timestamps, atol=1e-6)
    np.testing.assert_allclose(groundtruth.poses, scenario.trajectory.poses, atol=1e-8)
    assert load_intrinsics_json(out / "intrinsics.json") == scenario.camera
    assert json.loads((out / "scenario.json").read_text())["scenario"] == "desk"

    lines = [line.split() for line in (out / "associations.txt").read_text().splitlines()]
    for index, (_, rgb_name, _, depth_name) in enumerate(lines):
        colour, depth = scenario.render(index)
        bgr = cv2.imread(str(out / rgb_name), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(bgr[..., ::-1], colour)
        raw = cv2.imread(str(out / depth_name), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16
        np.testing.assert_allclose(raw / 5000.0, depth, atol=1e-6)  # already quantised

    sequence = tum.open_sequence(out)
    assert len(sequence) == 3 and sequence.camera == scenario.camera
    frame = sequence[2]
    np.testing.assert_array_equal(frame.colour, scenario.render(2)[0])
    np.testing.assert_allclose(frame.depth, scenario.render(2)[1], atol=1e-6)
    np.testing.assert_allclose(sequence.groundtruth.poses, scenario.trajectory.poses, atol=1e-8)

    # rewriting into our own folder is fine; a foreign non-empty folder is refused
    synthetic.write_scenario("floor", out, frames=1, width=32, height=24)
    assert len(list((out / "rgb").iterdir())) == 1
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty"):
        synthetic.write_scenario("floor", foreign, frames=1, width=32, height=24)


def _box_distance(points, half):
    q = np.abs(points) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def _surface_distance(solid, world_points) -> np.ndarray:
    """Unsigned distance to the solid's surface, closed forms written here independently."""
    local = (world_points - solid.pose[:3, 3]) @ solid.pose[:3, :3]
    if isinstance(solid, Sphere):
        return np.abs(np.linalg.norm(local, axis=1) - solid.radius)
    if isinstance(solid, Box):
        return np.abs(_box_distance(local, np.asarray(solid.half_size)))
    if isinstance(solid, Cylinder):
        radial = np.linalg.norm(local[:, :2], axis=1) - solid.radius
        axial = np.abs(local[:, 2]) - solid.half_height
        outside = np.hypot(np.maximum(radial, 0), np.maximum(axial, 0))
        return np.abs(outside + np.minimum(np.maximum(radial, axial), 0.0))
    if isinstance(solid, Rectangle):
        excess = np.maximum(np.abs(local[:, :2]) - solid.half_size, 0.0)
        return np.hypot(np.abs(local[:, 2]), np.linalg.norm(excess, axis=1))
    raise TypeError(type(solid))


def _analytic_area(solid) -> float:
    if isinstance(solid, Sphere):
        return 4 * np.pi * solid.radius**2
    if isinstance(solid, Box):
        a, b, c = 2 * np.asarray(solid.half_size)
        return 2 * (a * b + b * c + a * c)
    if isinstance(solid, Cylinder):
        r, h = solid.radius, 2 * solid.half_height
        return 2 * np.pi * r * h + 2 * np.pi * r * r
    return 4 * solid.half_size[0] * solid.half_size[1]


@pytest.mark.parametrize(("name", "spacing"), [("desk", 0.05), ("loop", 0.15)])
def test_scene_mesh_lies_on_the_surfaces_and_covers_them(tmp_path, name, spacing):
    import pyvista

    scenario = synthetic.make_scenario(name, frames=1, width=32, height=24)
    path = tmp_path / "scene.ply"
    scenario.surface_mesh(spacing).save(str(path), binary=True, texture="rgb")
    mesh = pyvista.read(path)
    assert mesh.is_all_triangles
    colours = mesh.point_data["RGB"]
    assert colours.dtype == np.uint8 and colours.shape == (mesh.n_points, 3)
    assert colours.std() > 10  # textured, not one flat colour
    points = np.asarray(mesh.points, dtype=np.float64)
    distance = np.min([_surface_distance(s, points) for s in scenario.scene.solids], axis=0)
    assert distance.max() < 1e-5  # float32 coordinates of a few metres: 1e-6 m
    # total area: tessellated spheres and cylinders are slightly smaller than the true surfaces
    expected = sum(_analytic_area(s) for s in scenario.scene.solids)
    assert mesh.area == pytest.approx(expected, rel=0.01)
    assert mesh.area < expected


# --- command line ----------------------------------------------------------------------------


def test_cli_lists_and_writes(tmp_path, capsys):
    assert main(["synth", "--list"]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert set(NAMES) <= set(listed)
    out = tmp_path / "floor"
    args = ["synth", "floor", "--out", str(out), "--frames", "2", "--width", "48", "--height", "36"]
    assert main([*args, "--no-noise", "--seed", "3"]) == 0
    groundtruth = tum.read_trajectory(out / "groundtruth.txt")
    expected = synthetic.make_scenario("floor", frames=2, width=48, height=36, seed=3)
    np.testing.assert_allclose(groundtruth.poses, expected.trajectory.poses, atol=1e-8)
    raw = cv2.imread(str(out / "depth" / "1.000000.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(raw.shape, (36, 48))
    assert main(["synth", "nowhere", "--out", str(tmp_path / "x")]) == 2
    assert "unknown scenario 'nowhere'" in capsys.readouterr().err


def test_bad_input_is_reported():
    with pytest.raises(ConfigError, match="unknown scenario"):
        synthetic.make_scenario("attic")
    with pytest.raises(ConfigError, match="frames"):
        synthetic.make_scenario("desk", frames=0)
    with pytest.raises(ConfigError, match="seed"):
        synthetic.make_scenario("desk", seed=-1)
    scenario = synthetic.make_scenario("desk", frames=2, width=32, height=24)
    with pytest.raises(KintinuousError, match="frames 0..1"):
        scenario.render(2)
    with pytest.raises(KintinuousError, match="rigid motion"):
        scenario.render_at(np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(ConfigError, match="spacing"):
        scenario.surface_mesh(0.0)


def test_tiny_desk_fixture_is_what_the_generator_makes():
    # data/tiny_desk (see data/README.md) = synth desk, 10 frames, 160x120, --no-noise.
    from pathlib import Path

    folder = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"
    if not folder.is_dir():
        pytest.skip("data/tiny_desk not present")
    sequence = tum.open_sequence(folder)
    scenario = synthetic.make_scenario("desk", frames=10, width=160, height=120, noise=False)
    assert len(sequence) == 10 and sequence.camera == scenario.camera
    np.testing.assert_allclose(sequence.groundtruth.poses, scenario.trajectory.poses, atol=1e-8)
    for index in (0, 9):
        colour, depth = scenario.render(index)
        frame = sequence[index]
        # other numpy / OpenCV builds may round a texel differently: 1 level, 0.2 mm (1 unit)
        assert np.abs(frame.colour.astype(int) - colour).max() <= 1
        assert np.abs(frame.depth - depth).max() <= 2.1e-4


def test_a_scenario_renders_the_frames_asked_for_and_extends_later(tmp_path):
    # The first N frames of a longer scenario, the same images as a full render; a second call
    # asking for more keeps the frames there and adds the rest.
    size = {"frames": 12, "width": 32, "height": 24}
    out = synthetic.write_scenario("desk", tmp_path / "part", render=4, **size)
    assert len((out / "associations.txt").read_text().splitlines()) == 4
    first = {p.name: p.stat().st_mtime_ns for p in (out / "rgb").iterdir()}
    assert len(first) == 4
    synthetic.write_scenario("desk", out, render=7, **size)
    after = {p.name: p.stat().st_mtime_ns for p in (out / "rgb").iterdir()}
    assert len(after) == 7 and all(after[name] == stamp for name, stamp in first.items())
    full = synthetic.write_scenario("desk", tmp_path / "full", **size)
    assert len((full / "associations.txt").read_text().splitlines()) == 12
    for kind in ("rgb", "depth"):
        for path in sorted((out / kind).iterdir()):
            ours = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            np.testing.assert_array_equal(ours, cv2.imread(str(full / kind / path.name), -1))
    with pytest.raises(ConfigError, match="1..12 frames"):
        synthetic.write_scenario("desk", out, render=13, **size)


def test_open_dataset_renders_a_scenario_only_as_far_as_needed(tmp_path, monkeypatch):
    from kintinuous_ref.program import reconstruct

    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path))
    monkeypatch.setattr(reconstruct, "SCENARIO_FRAMES", 10)
    assert len(reconstruct.open_dataset("floor", frames_needed=2)) == 2
    assert len(reconstruct.open_dataset("floor", frames_needed=3)) == 3
    assert len(reconstruct.open_dataset("floor", frames_needed=1)) == 3  # never fewer than it has
    assert len(reconstruct.open_dataset("floor")) == 10
