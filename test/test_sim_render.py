"""Renderer geometry is exact: depth, camera models, rolling shutter; routes and textures."""

import numpy as np
import pytest

from cusfm_ros.core.cameras import FisheyeCamera, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import Rigid3, se3_exp
from cusfm_ros.sim.render import CameraRays, Lighting, Renderer
from cusfm_ros.sim.route import Motion, Route
from cusfm_ros.sim.textures import TextureLibrary
from cusfm_ros.sim.world import World, build_street

CAMERAS = [PinholeCamera(80, 60, fx=40, fy=40, cx=39.5, cy=29.5),
           OpenCVCamera(80, 60, fx=40, fy=41, cx=40, cy=30, k1=-0.1, k2=0.01, p1=1e-3, p2=0),
           FisheyeCamera(80, 60, fx=30, fy=30, cx=39.5, cy=29.5, k1=0.02)]


def constant_textures(value: float = 0.5) -> TextureLibrary:
    levels = [np.full((1, 8 >> i, 8 >> i, 3), value, np.float32) for i in range(3)]
    return TextureLibrary(["flat"], levels)


def wall_world(distance_m: float) -> World:
    """A huge wall at y = distance (world), facing -y."""
    world = World(sky=True)
    world.add_quad([500.0, distance_m, -500.0], [-1, 0, 0], [0, 0, 1], 1000, 1000, 0, 0.1,
                   np.random.default_rng(0))
    return world.finalize()


def looking_along_y(position) -> np.ndarray:
    """world_from_cam for an optical frame looking along +y (x right = +x... z forward = +y)."""
    rotation = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # columns: cam x, y, z in world
    return Rigid3(rotation, np.asarray(position, float)).matrix()


@pytest.mark.parametrize("camera", CAMERAS, ids=lambda c: c.model_name)
def test_range_is_exact_for_every_camera_model(camera):
    renderer = Renderer(wall_world(7.0), constant_textures())
    rays = CameraRays.for_camera(camera)
    pose = looking_along_y([0.3, 2.0, 1.0])
    image, range_m = renderer.render(camera, rays, pose, Lighting(), rng=None)
    ray_z = rays.rays[:, 2].reshape(camera.height, camera.width)
    hits = ray_z > 0.05
    np.testing.assert_allclose(range_m[hits], (5.0 / ray_z)[hits], rtol=1e-9)
    assert image.shape == (camera.height, camera.width, 3) and image.dtype == np.uint8


def test_rolling_shutter_rows_use_their_own_pose():
    camera = CAMERAS[0]
    renderer = Renderer(wall_world(10.0), constant_textures())
    rays = CameraRays.for_camera(camera)
    # the camera backs away from the wall by 2 cm per row
    rows = np.stack([looking_along_y([0.0, -0.02 * r, 0.0]) for r in range(camera.height)])
    _, range_m = renderer.render(camera, rays, rows, Lighting(), rng=None)
    ray_z = rays.rays[:, 2].reshape(camera.height, camera.width)
    expected = (10.0 + 0.02 * np.arange(camera.height))[:, None] / ray_z
    np.testing.assert_allclose(range_m, expected, rtol=1e-9)


def test_sensor_noise_is_seeded():
    camera = CAMERAS[0]
    renderer = Renderer(wall_world(5.0), constant_textures())
    rays = CameraRays.for_camera(camera)
    pose = looking_along_y([0, 0, 0])
    a, _ = renderer.render(camera, rays, pose, Lighting(), np.random.default_rng(3))
    b, _ = renderer.render(camera, rays, pose, Lighting(), np.random.default_rng(3))
    clean, _ = renderer.render(camera, rays, pose, Lighting(), None)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - clean.astype(int)).mean() > 0.5
    assert np.ptp(clean) == 0  # a flat wall under uniform light is flat


def test_trilinear_sampling_of_constant_texture_is_constant(rng):
    lib = constant_textures(0.25)
    out = lib.sample(np.zeros(100, int), rng.uniform(-50, 50, 100), rng.uniform(-50, 50, 100),
                     rng.uniform(0, 5, 100))
    np.testing.assert_allclose(out, 0.25, atol=1e-6)


def test_route_centerline_is_continuous_and_arc_length_parametrized():
    route = Route.for_perimeter(120.0, 8.0)
    assert route.perimeter_m == pytest.approx(120.0)
    s = np.linspace(0, route.perimeter_m, 20001)
    xy, heading = route.centerline(s)
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    np.testing.assert_allclose(steps, s[1] - s[0], rtol=1e-3)
    np.testing.assert_allclose(xy[0], xy[-1], atol=1e-9)  # closed
    direction = np.diff(xy, axis=0) / steps[:, None]
    tangent = np.stack([np.cos(heading[:-1]), np.sin(heading[:-1])], axis=1)
    assert np.einsum("ij,ij->i", direction, tangent).min() > 0.9999


def test_motion_faces_its_direction_of_travel():
    motion = Motion(Route.for_perimeter(100.0, 8.0), speed_mps=5.0)
    times = np.linspace(0.0, 20.0, 50)
    poses = motion.world_from_body(times)
    ahead = motion.world_from_body(times + 1e-3)
    velocity = (ahead[:, :3, 3] - poses[:, :3, 3]) / 1e-3
    forward = poses[:, :3, 0]
    cos = np.einsum("ij,ij->i", forward, velocity) / np.linalg.norm(velocity, axis=1)
    assert cos.min() > 0.999
    np.testing.assert_allclose(np.linalg.det(poses[:, :3, :3]), 1.0, atol=1e-9)
    # exact at any stamp: halfway between two samples equals direct evaluation
    mid = motion.world_from_body(np.array([0.55]))[0]
    assert not np.allclose(mid, motion.world_from_body(np.array([0.5]))[0])
    assert np.allclose(se3_exp(np.zeros(6)), np.eye(4))


def _segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, S) distance of each 2D point to each segment a-b."""
    ab = b - a
    t = np.einsum("psk,sk->ps", points[:, None] - a[None], ab) / np.sum(ab * ab, axis=1)
    closest = a[None] + np.clip(t, 0, 1)[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - closest, axis=2)


@pytest.mark.parametrize("perimeter_m", [120.0, 250.0, 400.0])
def test_street_route_keeps_clear_of_every_facade(perimeter_m):
    """The car never drives through a building: on the 400 m street (1000 frames at 8 m/s and
    10 Hz) a facade inside the block used to reach across the road after a corner."""
    names = ["asphalt_0", "facade_0", "facade_1", "poster_0", "marking_0", "car_0", "pole_0"]
    levels = [np.full((len(names), 8 >> i, 8 >> i, 3), 0.5, np.float32) for i in range(3)]
    route = Route.for_perimeter(perimeter_m, 8.0)
    centre, _ = route.centerline(np.linspace(0.0, route.perimeter_m, 4001))
    for seed in range(4):
        world = build_street(route, TextureLibrary(names, levels), seed)
        facade = np.array([kind == "facade" for kind in world.kinds])
        corners = world.arrays["corners"][facade]
        a, b = corners[:, 0, :2], corners[:, 1, :2]  # the footprint: origin to origin + u
        clearance = _segment_distances(centre, a, b).min()
        assert clearance > 7.5, (seed, clearance)
