"""Camera models, poses and constructors, checked against hand values and independent formulas.

Tolerances: float64 numpy math to 1e-9 (pixels or world units; 1e-12 where it is
a single closed-form expression); round trips through iterative undistortion to
1e-9 in float64 (the brief's bound is 1e-5 relative); MLX float32 against numpy
float64 to 1e-5 relative plus 2e-3 px absolute; MLX gradients against
float64 central differences (h = 1e-6) to 1e-3 relative of the largest entry.
"""

import dataclasses
import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera

W, H = 64, 48

OPENCV_DIST = (-0.21, 0.07, 0.0012, -0.0008, -0.011)
FISHEYE_DIST = (0.08, -0.03, 0.006, -0.0015)
MODELS = {
    "pinhole": (),
    "opencv": OPENCV_DIST,
    "fisheye": FISHEYE_DIST,
    "orthographic": (),
}


def rot_x(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], float)


def rot_z(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], float)


def pose(R, t):
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = t
    return m


def camera(model="pinhole", **kw):
    """A camera with a non-trivial pose looking at the world origin from about 4 units."""
    lens = {"focal": 12.0} if model == "orthographic" else {"fov": 70.0}
    base = Camera.look_at((2.0, -3.0, 1.5), (0.1, 0.2, -0.1), width=W, height=H,
                          model=model, dist=MODELS[model], **lens)
    return dataclasses.replace(base, cx=W / 2 + 1.3, cy=H / 2 - 0.7, **kw)


def points_in_view(cam, n, seed=0, margin=0.1):
    """World points that project inside the image (sampled per pixel and depth, then unprojected)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([margin * W, margin * H], [(1 - margin) * W, (1 - margin) * H], size=(n, 2))
    depth = rng.uniform(1.0, 6.0, size=n)
    return cam.unproject(uv, depth), uv, depth


# --------------------------------------------------------------------- pinhole


def test_pinhole_hand_values():
    vm = pose(np.eye(3), [0.5, 0.0, 2.0])
    cam = Camera(640, 480, 500.0, 400.0, 320.0, 240.0, vm)
    uv, depth = cam.project_points(np.array([[-0.5, 0.0, 0.0], [0.5, -1.0, 2.0]]))
    # (-0.5, 0, 0) + t = (0, 0, 2): straight ahead -> (cx, cy), depth 2.
    # (0.5, -1, 2) + t = (1, -1, 4): u = 500 * 1/4 + 320 = 445, v = 400 * -1/4 + 240 = 140.
    np.testing.assert_allclose(uv, [[320.0, 240.0], [445.0, 140.0]], atol=1e-12)
    np.testing.assert_allclose(depth, [2.0, 4.0], atol=1e-12)

    # Rotation about y by +90 degrees: x_cam = -z_w, y_cam = y_w, z_cam = x_w.
    R = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    cam = Camera(640, 480, 500.0, 400.0, 320.0, 240.0, pose(R, [0.0, 0.0, 0.0]))
    uv, depth = cam.project_points(np.array([3.0, 0.5, 1.0]))  # camera (-1, 0.5, 3)
    np.testing.assert_allclose(uv, [500 * (-1 / 3) + 320, 400 * (0.5 / 3) + 240], atol=1e-12)
    assert depth == pytest.approx(3.0, abs=1e-12)
    np.testing.assert_allclose(cam.world_to_camera(np.array([3.0, 0.5, 1.0])), [-1.0, 0.5, 3.0], atol=1e-12)


def test_pose_properties():
    cam = camera()
    np.testing.assert_allclose(cam.camtoworld @ cam.viewmat, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(cam.R @ cam.center + cam.t, 0.0, atol=1e-12)
    np.testing.assert_allclose(cam.K, [[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    p = np.array([0.3, -0.2, 0.4])
    pc = cam.R @ p + cam.t
    uv, depth = cam.project_points(p)
    np.testing.assert_allclose(uv, (cam.K @ (pc / pc[2]))[:2], atol=1e-12)
    assert depth == pytest.approx(pc[2], abs=1e-12)
    uv2, depth2 = cam.camera_to_pixels(cam.world_to_camera(p))
    np.testing.assert_array_equal(uv, uv2)
    vm = cam.viewmat_mx
    assert isinstance(vm, mx.array) and vm.dtype == mx.float32
    np.testing.assert_allclose(np.array(vm), cam.viewmat, atol=1e-6)
    assert cam.viewmat.dtype == np.float64


def test_fov_pinhole_off_centre():
    cam = Camera(100, 50, 80.0, 90.0, 30.0, 20.0)
    assert cam.fov_x == pytest.approx(math.atan(30 / 80) + math.atan(70 / 80), abs=1e-12)
    assert cam.fov_y == pytest.approx(math.atan(20 / 90) + math.atan(30 / 90), abs=1e-12)
    zeros = dataclasses.replace(cam, model="opencv", dist=(0.0,) * 5)
    assert zeros.fov_x == pytest.approx(cam.fov_x, abs=1e-12)
    # Equidistant fisheye (zero coefficients): the angle is the pixel distance over f.
    fish = dataclasses.replace(cam, model="fisheye", dist=(0.0,) * 4)
    assert fish.fov_x == pytest.approx(100 / 80, abs=1e-12)
    assert fish.fov_y == pytest.approx(50 / 90, abs=1e-12)
    with pytest.raises(ValueError, match="orthographic"):
        dataclasses.replace(cam, model="orthographic").fov_x


def test_needs_ut():
    cam = Camera(W, H, 50.0, 50.0, W / 2, H / 2)
    assert cam.needs_ut is False
    assert dataclasses.replace(cam, model="opencv", dist=(0, 0, 0, 0, 0)).needs_ut is False
    assert dataclasses.replace(cam, model="opencv", dist=(0, 0, 0, 1e-3, 0)).needs_ut is True
    assert dataclasses.replace(cam, model="fisheye", dist=(0, 0, 0, 0)).needs_ut is True
    assert dataclasses.replace(cam, model="orthographic").needs_ut is True


def test_frozen_equality_and_readonly_pose():
    cam = camera()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cam.fx = 1.0
    with pytest.raises(ValueError):
        cam.viewmat[0, 3] = 5.0
    same = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.viewmat.astype(np.float64))
    assert same == cam and hash(same) == hash(cam)
    assert dataclasses.replace(cam, cx=cam.cx + 1) != cam


# --------------------------------------------------------------------- look_at


def test_look_at_centre_up_and_eye():
    eye, at, up = np.array([3.0, -4.0, 2.0]), np.array([0.5, 1.0, 0.2]), np.array([0.0, 0.0, 1.0])
    cam = Camera.look_at(eye, at, up, width=W, height=H, fov=55.0)
    uv, depth = cam.project_points(at)
    np.testing.assert_allclose(uv, [W / 2, H / 2], atol=1e-9)
    assert depth == pytest.approx(np.linalg.norm(at - eye), abs=1e-12)
    np.testing.assert_allclose(cam.center, eye, atol=1e-12)
    # A point above `at` lands straight above the image centre (smaller v).
    uv_up, _ = cam.project_points(at + 0.3 * up)
    assert uv_up[0] == pytest.approx(W / 2, abs=1e-9)
    assert uv_up[1] < H / 2 - 1.0
    # The camera's image-down axis points against world up.
    assert cam.R[1] @ up < 0 and abs(cam.R[0] @ up) < 1e-12


def test_look_at_fov_focal_relation():
    fov = 63.0
    cam = Camera.look_at((0, 0, 0), (0, 5, 0), width=W, height=H, fov=fov)
    assert cam.fx == pytest.approx((W / 2) / math.tan(math.radians(fov) / 2), rel=1e-12)
    assert cam.fy == cam.fx and (cam.cx, cam.cy) == (W / 2, H / 2)
    assert cam.fov_x == pytest.approx(math.radians(fov), abs=1e-12)
    # Looking along +y with z up, a direction fov/2 to the right (+x) is the right image edge.
    half = math.radians(fov) / 2
    uv, _ = cam.project_points(np.array([math.sin(half), math.cos(half), 0.0]) * 3)
    np.testing.assert_allclose(uv, [W, H / 2], atol=1e-9)
    same = Camera.look_at((0, 0, 0), (0, 5, 0), width=W, height=H, focal=cam.fx)
    assert same == cam


@pytest.mark.parametrize(
    "args, kw, match",
    [
        (((1, 2, 3), (1, 2, 3)), {"fov": 60}, "eye and at"),
        (((0, 0, 0), (0, 0, 5)), {"fov": 60}, "up"),
        (((0, 0, 0), (0, 1, 0), (0, 0, 0)), {"fov": 60}, "up"),
        (((0, 0, 0), (0, 1, 0)), {}, "fov"),
        (((0, 0, 0), (0, 1, 0)), {"fov": 60, "focal": 50}, "fov"),
        (((0, 0, 0), (0, 1, 0)), {"fov": 180}, "fov"),
        (((0, 0, 0), (0, 1, 0)), {"focal": -3}, "focal"),
        (((0, 0, 0), (0, 1)), {"fov": 60}, "at"),
    ],
)
def test_look_at_errors(args, kw, match):
    with pytest.raises(ValueError, match=match):
        Camera.look_at(*args, width=W, height=H, **kw)


# --------------------------------------------------------------------- OpenGL poses


def test_from_opengl_c2w_identity_rotation():
    c2w = pose(np.eye(3), [0.0, 0.0, 5.0])  # at (0,0,5), looking down -z, y up
    cam = Camera.from_opengl_c2w(c2w, W, H, 40.0)
    assert (cam.fy, cam.cx, cam.cy) == (40.0, W / 2, H / 2)
    uv, depth = cam.project_points(np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=1e-12)
    np.testing.assert_allclose(depth, [5.0, 5.0, 5.0], atol=1e-12)
    assert uv[1, 1] < H / 2 and uv[1, 0] == pytest.approx(W / 2, abs=1e-12)  # +y is up
    assert uv[2, 0] > W / 2 and uv[2, 1] == pytest.approx(H / 2, abs=1e-12)  # +x is right
    np.testing.assert_allclose(cam.to_opengl_c2w(), c2w, atol=1e-12)


def test_from_opengl_c2w_blender_camera():
    # A Blender camera at (0, -5, 0) rotated 90 degrees about X looks along +y with z up.
    c2w = pose(rot_x(90), [0.0, -5.0, 0.0])
    cam = Camera.from_opengl_c2w(c2w[:3], W, H, 40.0, 42.0, 30.0, 25.0)
    uv, depth = cam.project_points(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [30.0, 25.0], atol=1e-12)
    np.testing.assert_allclose(depth, 5.0, atol=1e-12)
    assert uv[1, 1] < 25.0 and uv[2, 0] > 30.0


def test_opengl_round_trip_random():
    rng = np.random.default_rng(3)
    for _ in range(5):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        c2w = pose(q, rng.normal(size=3) * 3)
        cam = Camera.from_opengl_c2w(c2w, W, H, 50.0)
        np.testing.assert_allclose(cam.to_opengl_c2w(), c2w, atol=1e-12)
        np.testing.assert_allclose(cam.center, c2w[:3, 3], atol=1e-12)
        # OpenGL looks down its -z; OpenCV forward (+z) is the same world direction.
        np.testing.assert_allclose(cam.R[2], -c2w[:3, 2], atol=1e-12)
        back = Camera.from_opengl_c2w(cam.to_opengl_c2w(), W, H, 50.0)
        np.testing.assert_allclose(back.viewmat, cam.viewmat, atol=1e-12)


# --------------------------------------------------------------------- lens models


def opencv_reference(points_cam, K, dist):
    """OpenCV projectPoints (k1, k2, p1, p2, k3), point by point, from the documented formulas."""
    k1, k2, p1, p2, k3 = dist
    out = []
    for X, Y, Z in points_cam:
        x1, y1 = X / Z, Y / Z
        r2 = x1**2 + y1**2
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        x2 = x1 * radial + 2 * p1 * x1 * y1 + p2 * (r2 + 2 * x1**2)
        y2 = y1 * radial + p1 * (r2 + 2 * y1**2) + 2 * p2 * x1 * y1
        out.append((K[0][0] * x2 + K[0][2], K[1][1] * y2 + K[1][2]))
    return np.array(out)


def fisheye_reference(points_cam, K, dist):
    """OpenCV fisheye projectPoints (k1..k4, no skew), point by point, from the documented formulas."""
    k1, k2, k3, k4 = dist
    out = []
    for X, Y, Z in points_cam:
        a, b = X / Z, Y / Z
        r = math.hypot(a, b)
        theta = math.atan(r)
        theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
        s = theta_d / r if r > 0 else 1.0
        out.append((K[0][0] * s * a + K[0][2], K[1][1] * s * b + K[1][2]))
    return np.array(out)


def random_cam_points(rng, n, spread=0.8):
    return np.column_stack([rng.uniform(-spread, spread, (n, 2)) * 3.0, rng.uniform(1.0, 4.0, n)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_opencv_matches_reference(seed):
    rng = np.random.default_rng(seed)
    dist = tuple(rng.uniform(-1, 1, 5) * [0.3, 0.1, 0.01, 0.01, 0.05])
    cam = Camera(W, H, 45.0, 47.0, 31.0, 25.0, model="opencv", dist=dist)
    pc = random_cam_points(rng, 50)
    uv, depth = cam.camera_to_pixels(pc)
    np.testing.assert_allclose(uv, opencv_reference(pc, cam.K, dist), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(depth, pc[:, 2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fisheye_matches_reference(seed):
    rng = np.random.default_rng(seed)
    dist = tuple(rng.uniform(-1, 1, 4) * [0.1, 0.05, 0.01, 0.005])
    cam = Camera(W, H, 45.0, 47.0, 31.0, 25.0, model="fisheye", dist=dist)
    pc = random_cam_points(rng, 50, spread=1.5)
    pc[0, :2] = 0.0  # on the optical axis
    uv, depth = cam.camera_to_pixels(pc)
    np.testing.assert_allclose(uv, fisheye_reference(pc, cam.K, dist), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(depth, pc[:, 2])


def test_zero_coefficients():
    """Zero Brown-Conrady coefficients are the pinhole; zero fisheye ones the equidistant model."""
    rng = np.random.default_rng(4)
    pin = camera()
    pts = rng.normal(size=(40, 3))
    uv_pin, d_pin = pin.project_points(pts)
    front = d_pin > 0
    cam = dataclasses.replace(pin, model="opencv", dist=(0.0,) * 5)
    uv, d = cam.project_points(pts[front])
    np.testing.assert_allclose(uv, uv_pin[front], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(d, d_pin[front])

    cam = dataclasses.replace(pin, model="fisheye", dist=(0.0,) * 4)
    pc = pin.world_to_camera(pts[front])
    uv, _ = cam.camera_to_pixels(pc)
    rho = np.linalg.norm(pc[:, :2], axis=-1)
    theta = np.arctan2(rho, pc[:, 2])  # pixel distance from (cx, cy) is f * theta
    want = np.column_stack([cam.fx * theta * pc[:, 0] / rho + cam.cx, cam.fy * theta * pc[:, 1] / rho + cam.cy])
    np.testing.assert_allclose(uv, want, rtol=0, atol=1e-9)


def test_orthographic_is_depth_independent():
    cam = Camera(W, H, 10.0, 12.0, 32.0, 24.0, pose(np.eye(3), [0.0, 0.0, 1.0]), model="orthographic")
    pc = np.array([[0.5, -0.25, z] for z in (0.5, 2.0, 40.0)])
    uv, depth = cam.camera_to_pixels(pc)
    np.testing.assert_allclose(uv, [[10 * 0.5 + 32, 12 * -0.25 + 24]] * 3, atol=1e-12)
    np.testing.assert_array_equal(depth, [0.5, 2.0, 40.0])
    uvw, dw = cam.project_points(pc - [0.0, 0.0, 1.0])
    np.testing.assert_allclose(uvw, uv, atol=1e-12)
    np.testing.assert_allclose(dw, depth, atol=1e-12)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_behind_and_on_camera_plane_stay_finite(model):
    cam = camera(model)
    pc = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 0.0], [0.3, -0.2, -2.0], [0.0, 0.0, -1.0],
                   [1e-9, 0.0, 1e-12], [5.0, 5.0, 1e-7]])
    uv, depth = cam.camera_to_pixels(pc)
    assert np.all(np.isfinite(uv)) and np.all(np.isfinite(depth))
    np.testing.assert_array_equal(depth, pc[:, 2])
    uvm, dm = cam.camera_to_pixels(mx.array(pc.astype(np.float32)))
    assert np.all(np.isfinite(np.array(uvm))) and np.all(np.isfinite(np.array(dm)))
    g = mx.grad(lambda p: cam.camera_to_pixels(p)[0].sum())(mx.array(pc.astype(np.float32)))
    assert np.all(np.isfinite(np.array(g)))


# --------------------------------------------------------------------- round trips


@pytest.mark.parametrize("model", sorted(MODELS))
def test_project_unproject_round_trip(model):
    cam = camera(model)
    rng = np.random.default_rng(5)
    pc = random_cam_points(rng, 200, spread=0.45)
    if model == "orthographic":
        pc[:, :2] *= 1.5
    world = pc @ cam.camtoworld[:3, :3].T + cam.camtoworld[:3, 3]
    uv, depth = cam.project_points(world)
    inside = (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
    assert inside.mean() > 0.5
    back = cam.unproject(uv, depth)
    scale = np.linalg.norm(world, axis=-1, keepdims=True)
    assert np.max(np.abs(back - world) / scale) < 1e-9
    # And pixels -> world -> pixels.
    uv2, depth2 = cam.project_points(cam.unproject(uv, 2.5))
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    np.testing.assert_allclose(depth2, 2.5, atol=1e-12)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_rays_hit_pixel_centres(model):
    cam = camera(model)
    origins, dirs = cam.rays()
    assert origins.shape == (H, W, 3) and dirs.shape == (H, W, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-12)
    uv, depth = cam.project_points(origins + 3.0 * dirs)
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    np.testing.assert_allclose(uv, np.stack([jj, ii], -1), atol=1e-9)
    assert np.all(depth > 0)
    if model == "orthographic":
        np.testing.assert_allclose(dirs, np.broadcast_to(cam.R[2], dirs.shape), atol=1e-12)
        np.testing.assert_allclose(cam.world_to_camera(origins)[..., 2], 0.0, atol=1e-12)
    else:
        np.testing.assert_allclose(origins, np.broadcast_to(cam.center, origins.shape), atol=1e-12)
    o2, d2 = cam.rays(np.array([[cam.cx, cam.cy]]))
    np.testing.assert_allclose(d2[0], cam.R[2], atol=1e-9)  # the principal ray is the optical axis


def test_unproject_broadcasts_scalar_depth():
    cam = camera()
    uv = cam.pixel_centers()
    pts = cam.unproject(uv, 2.0)
    assert pts.shape == (H, W, 3)
    np.testing.assert_allclose(cam.world_to_camera(pts)[..., 2], 2.0, atol=1e-12)


# --------------------------------------------------------------------- scaled


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("size, factor, new_size", [((64, 48), 0.5, (32, 24)), ((101, 75), 0.5, (51, 38)),
                                                    ((101, 75), 2.0, (202, 150))])
def test_scaled(model, size, factor, new_size):
    cam = dataclasses.replace(camera(model), width=size[0], height=size[1])
    small = cam.scaled(factor)
    assert (small.width, small.height) == new_size
    ratio = np.array(new_size, float) / size
    pts, _, _ = points_in_view(cam, 30)
    uv, depth = cam.project_points(pts)
    uv_s, depth_s = small.project_points(pts)
    np.testing.assert_allclose(uv_s, uv * ratio, atol=1e-9)
    np.testing.assert_array_equal(depth_s, depth)
    assert small.dist == cam.dist and small.model == cam.model
    np.testing.assert_array_equal(small.viewmat, cam.viewmat)


def test_scaled_errors():
    with pytest.raises(ValueError, match="factor"):
        camera().scaled(0)
    with pytest.raises(ValueError, match="factor"):
        camera().scaled(1e-4)


# --------------------------------------------------------------------- MLX


@pytest.mark.parametrize("model", sorted(MODELS))
def test_numpy_and_mlx_agree(model):
    cam = camera(model)
    pts, uv_in, depth_in = points_in_view(cam, 100, seed=6)
    uv, depth = cam.project_points(pts)
    uvm, dm = cam.project_points(mx.array(pts.astype(np.float32)))
    assert isinstance(uvm, mx.array) and uvm.dtype == mx.float32 and tuple(uvm.shape) == (100, 2)
    assert isinstance(dm, mx.array) and tuple(dm.shape) == (100,)
    np.testing.assert_allclose(np.array(uvm), uv, rtol=1e-5, atol=2e-3)
    np.testing.assert_allclose(np.array(dm), depth, rtol=1e-5, atol=1e-5)

    back = cam.unproject(mx.array(uv_in.astype(np.float32)), mx.array(depth_in.astype(np.float32)))
    assert isinstance(back, mx.array)
    np.testing.assert_allclose(np.array(back), pts, rtol=1e-5, atol=2e-4)
    o, d = cam.rays(mx.array(uv_in.astype(np.float32)))
    o_np, d_np = cam.rays(uv_in)
    assert isinstance(d, mx.array)
    np.testing.assert_allclose(np.array(o), o_np, atol=2e-5)
    np.testing.assert_allclose(np.array(d), d_np, atol=2e-5)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_mlx_gradient_matches_finite_differences(model):
    cam = camera(model)
    pts, _, _ = points_in_view(cam, 12, seed=7)
    rng = np.random.default_rng(8)
    w_uv, w_d = rng.normal(size=(12, 2)), rng.normal(size=12)

    def loss_np(p):
        uv, depth = cam.project_points(p)
        return float(np.sum(w_uv * uv) + np.sum(w_d * depth))

    def loss_mx(p):
        uv, depth = cam.project_points(p)
        return (mx.array(w_uv, dtype=mx.float32) * uv).sum() + (mx.array(w_d, dtype=mx.float32) * depth).sum()

    g = np.array(mx.grad(loss_mx)(mx.array(pts.astype(np.float32))))
    assert np.all(np.isfinite(g))
    h = 1e-6
    fd = np.zeros_like(pts)
    for idx in np.ndindex(*pts.shape):
        e = np.zeros_like(pts)
        e[idx] = h
        fd[idx] = (loss_np(pts + e) - loss_np(pts - e)) / (2 * h)
    assert np.max(np.abs(g - fd)) <= 1e-3 * np.max(np.abs(fd))


# --------------------------------------------------------------------- validation


GOOD = dict(width=W, height=H, fx=50.0, fy=50.0, cx=32.0, cy=24.0)


@pytest.mark.parametrize(
    "change, match",
    [
        ({"width": 0}, "width"),
        ({"height": -3}, "height"),
        ({"width": 12.5}, "width"),
        ({"fx": 0.0}, "fx"),
        ({"fy": -1.0}, "fy"),
        ({"fx": float("nan")}, "fx"),
        ({"cx": float("inf")}, "cx"),
        ({"viewmat": np.eye(3)}, "viewmat"),
        ({"viewmat": pose(2.0 * np.eye(3), [0, 0, 0])}, "viewmat"),
        ({"viewmat": pose(np.diag([1.0, 1.0, -1.0]), [0, 0, 0])}, "viewmat"),
        ({"viewmat": pose(np.eye(3), [0, float("nan"), 0])}, "viewmat"),
        ({"near": 0.0}, "near"),
        ({"near": 5.0, "far": 5.0}, "near"),
        ({"model": "kb8"}, "model"),
        ({"model": "opencv", "dist": (0.1, 0.0, 0.0, 0.0)}, "dist"),
        ({"model": "fisheye", "dist": (0.1, 0.0, 0.0, 0.0, 0.0)}, "dist"),
        ({"dist": (0.1,)}, "dist"),
        ({"model": "fisheye", "dist": (0.1, float("nan"), 0.0, 0.0)}, "dist"),
    ],
)
def test_validation_names_the_argument(change, match):
    with pytest.raises(ValueError, match=match):
        Camera(**{**GOOD, **change})


def test_valid_variants_accepted():
    cam = Camera(**{**GOOD, "width": np.int64(64), "height": 48.0, "viewmat": np.eye(4, dtype=np.float32)})
    assert cam.width == 64 and isinstance(cam.height, int)
    assert Camera(**GOOD, model="orthographic", near=-1.0).near == -1.0
    assert Camera(**GOOD, viewmat=mx.array(np.eye(4, dtype=np.float32)))


def test_method_argument_errors():
    cam = camera()
    with pytest.raises(ValueError, match="points"):
        cam.project_points(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="uv"):
        cam.unproject(np.zeros((4, 3)), 1.0)
    with pytest.raises(ValueError, match="c2w"):
        Camera.from_opengl_c2w(pose(3.0 * rot_z(10), [0, 0, 0]), W, H, 50.0)
