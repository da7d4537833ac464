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

from mlx3d.cameras import Camera, focal_to_fov, fov_to_focal, look_at, look_at_view_transform

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
    lens = {"focal": 12.0} if model == "orthographic" else {"hfov": 70.0}
    base = Camera.look_at((2.0, -3.0, 1.5), (0.1, 0.2, -0.1), (0.0, 0.0, 1.0), width=W, height=H,
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


def test_look_at_hfov_focal_relation():
    hfov = 63.0
    cam = Camera.look_at((0, 0, 0), (0, 5, 0), (0, 0, 1), width=W, height=H, hfov=hfov)
    assert cam.fx == pytest.approx((W / 2) / math.tan(math.radians(hfov) / 2), rel=1e-12)
    assert cam.fy == cam.fx and (cam.cx, cam.cy) == (W / 2, H / 2)
    assert cam.fov_x == pytest.approx(math.radians(hfov), abs=1e-12)
    # Looking along +y with z up, a direction hfov/2 to the right (+x) is the right image edge.
    half = math.radians(hfov) / 2
    uv, _ = cam.project_points(np.array([math.sin(half), math.cos(half), 0.0]) * 3)
    np.testing.assert_allclose(uv, [W, H / 2], atol=1e-9)
    same = Camera.look_at((0, 0, 0), (0, 5, 0), (0, 0, 1), width=W, height=H, focal=cam.fx)
    assert same == cam
    radians = Camera.look_at((0, 0, 0), (0, 5, 0), (0, 0, 1), width=W, height=H, hfov=math.radians(hfov),
                             degrees=False)
    assert radians.fx == pytest.approx(cam.fx, rel=1e-12)


@pytest.mark.parametrize(
    "args, kw, match",
    [
        (((1, 2, 3), (1, 2, 3)), {"fov": 60}, "eye and at"),
        (((0, 0, 0), (0, 5, 0)), {"fov": 60}, "up"),  # the default up is +y
        (((0, 0, 0), (0, 0, 5), (0, 0, 1)), {"fov": 60}, "up"),
        (((0, 0, 0), (0, 1, 0), (0, 0, 0)), {"fov": 60}, "up"),
        (((0, 0, 0), (0, 0, 1)), {"fov": 60, "focal": 50}, "fov"),
        (((0, 0, 0), (0, 0, 1)), {"fov": 60, "hfov": 50}, "hfov"),
        (((0, 0, 0), (0, 0, 1)), {"hfov": 60, "focal": 50}, "focal"),
        (((0, 0, 0), (0, 0, 1)), {"fov": 180}, "fov"),
        (((0, 0, 0), (0, 0, 1)), {"hfov": 0}, "hfov"),
        (((0, 0, 0), (0, 0, 1)), {"fov": 3.2, "degrees": False}, "radians"),
        (((0, 0, 0), (0, 0, 1)), {"focal": -3}, "focal"),
        (((0, 0, 0), (0, 1)), {"fov": 60}, "at"),
    ],
)
def test_look_at_errors(args, kw, match):
    with pytest.raises(ValueError, match=match):
        Camera.look_at(*args, width=W, height=H, **kw)
    with pytest.raises(TypeError, match="pose"):
        Camera.look_at((0, 0, -4), R=np.eye(3))


# --------------------------------------------------------------------- the original mlx3D API
#
# Oracles: poses and pixels derived by hand below, from the original's documented
# conventions (x_cam = R x_world + t, OpenCV axes, u = fx x/z + cx, v = fy y/z + cy,
# look_at's default up = +y and fov = vertical degrees, 60 by default).

# eye (0, 0, -4) looking at the origin with +y up: forward +z, right = forward x up = -x,
# down = -y. So R = diag(-1, -1, 1) and t = -R eye = (0, 0, 4).
R_BACK = np.diag([-1.0, -1.0, 1.0])
T_BACK = np.array([0.0, 0.0, 4.0])
# eye (3, 0, 0) looking at the origin with +y up: forward -x, right = (-x) x (+y) = -z, down = -y.
R_SIDE = np.array([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]])
T_SIDE = np.array([0.0, 0.0, 3.0])


def test_original_look_at_defaults():
    cam = Camera.look_at(eye=(0, 0, -4), at=(0, 0, 0), width=96, height=64, fov=50)
    f = 32.0 / math.tan(math.radians(25.0))  # vertical: half the height over tan(fov / 2)
    assert cam.fx == pytest.approx(f, rel=1e-12) and cam.fy == pytest.approx(f, rel=1e-12)
    assert (cam.cx, cam.cy, cam.width, cam.height) == (48.0, 32.0, 96, 64)
    assert cam.fov_y == pytest.approx(math.radians(50.0), abs=1e-12)
    assert cam.fov_x == pytest.approx(2 * math.atan(48.0 / f), abs=1e-12)
    np.testing.assert_allclose(cam.R, R_BACK, atol=1e-15)
    np.testing.assert_allclose(cam.t, T_BACK, atol=1e-15)
    np.testing.assert_allclose(np.array(cam.camera_center), [0.0, 0.0, -4.0], atol=1e-6)
    assert (cam.znear, cam.zfar) == (cam.near, cam.far) == (0.01, 1e10)
    assert cam.orthographic is False and cam.fisheye is False and cam.distortion is None

    everything_default = Camera.look_at((0, 0, -4))
    assert (everything_default.width, everything_default.height) == (512, 512)
    assert everything_default.fov_y == pytest.approx(math.radians(60.0), abs=1e-12)
    assert everything_default.fx == pytest.approx(256.0 / math.tan(math.radians(30.0)), rel=1e-12)
    np.testing.assert_allclose(everything_default.R, R_BACK, atol=1e-15)

    positional = Camera.look_at((0, 0, -4), (0, 0, 0), (0, 1, 0), 50, 96, 64)
    assert positional == cam
    radians = Camera.look_at((0, 0, -4), fov=math.radians(50), width=96, height=64, degrees=False)
    assert radians.fy == pytest.approx(cam.fy, rel=1e-12)


def test_original_look_at_projects_known_pixels():
    cam = Camera.look_at(eye=(0, 0, -4), at=(0, 0, 0), width=96, height=64, fov=50)
    f = cam.fy
    pts = np.array([
        [0.0, 0.0, 0.0],  # the target: on the optical axis
        [0.0, 0.0, 3.0],  # farther along the axis
        [0.0, 1.0, 0.0],  # up the world y axis: camera (0, -1, 4)
        [1.0, 0.0, 0.0],  # +x: camera (-1, 0, 4), left in the image
        [0.0, -1.0, 0.0],  # down
    ])
    uv, depth = cam.project_points(pts)
    np.testing.assert_allclose(uv, [[48, 32], [48, 32], [48, 32 - f / 4], [48 - f / 4, 32], [48, 32 + f / 4]],
                               atol=1e-12)
    np.testing.assert_allclose(depth, [4.0, 7.0, 4.0, 4.0, 4.0], atol=1e-12)
    assert uv[2, 1] < 32  # upper half of the image with the y-up default
    # The vertical field of view: a point fov/2 above the axis lands on the top edge.
    half = math.radians(25.0)
    uv_top, _ = cam.project_points(np.array([0.0, 4.0 * math.tan(half), 0.0]))
    np.testing.assert_allclose(uv_top, [48.0, 0.0], atol=1e-9)
    # MLX points in, MLX out (as in the original); eps is accepted.
    uvm, dm = cam.project_points(mx.array(pts.astype(np.float32)), eps=1e-8)
    assert isinstance(uvm, mx.array) and isinstance(dm, mx.array)
    np.testing.assert_allclose(np.array(uvm), uv, atol=1e-4)


def test_original_look_at_off_axis_pose():
    cam = Camera.look_at(eye=(3, 0, 0), at=(0, 0, 0), width=W, height=H, fov=40)
    np.testing.assert_allclose(cam.R, R_SIDE, atol=1e-15)
    np.testing.assert_allclose(cam.t, T_SIDE, atol=1e-15)
    uv, _ = cam.project_points(np.array([[0.0, 0.5, 0.0], [0.0, 0.0, 1.0]]))
    assert uv[0, 1] < H / 2 and uv[0, 0] == pytest.approx(W / 2, abs=1e-12)  # +y is up
    assert uv[1, 0] < W / 2  # +z is to the left when looking along -x with y up


def test_original_constructor_forms_equal_look_at():
    ref = Camera.look_at(eye=(0, 0, -4), at=(0, 0, 0), width=96, height=64, fov=50)
    f = ref.fx
    by_keyword = Camera(R=R_BACK, t=T_BACK, fx=f, fy=f, cx=48.0, cy=32.0, width=96, height=64)
    positional = Camera(R_BACK, T_BACK, f, f, 48.0, 32.0, 96, 64)
    mlx_arrays = Camera(mx.array(R_BACK.astype(np.float32)), mx.array(T_BACK.astype(np.float32)),
                        f, f, 48.0, 32.0, 96, 64, 0.01)
    lists = Camera(R_BACK.tolist(), T_BACK.tolist(), f, f, 48.0, 32.0, 96, 64, znear=0.01, zfar=1e10)
    for cam in (by_keyword, positional, mlx_arrays, lists):
        assert cam == ref
    from_fov = Camera.from_fov(50, 96, 64, R=R_BACK, t=T_BACK)
    assert from_fov.fy == pytest.approx(f, rel=1e-12)
    np.testing.assert_array_equal(from_fov.viewmat, ref.viewmat)
    assert from_fov.fov_y == pytest.approx(math.radians(50), abs=1e-12)
    assert Camera.from_fov(math.radians(50), 96, 64, degrees=False).fy == pytest.approx(f, rel=1e-12)
    np.testing.assert_array_equal(Camera.from_fov(50, 96, 64).viewmat, np.eye(4))


def test_original_constructor_random_pose():
    rng = np.random.default_rng(11)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    t = rng.normal(size=3)
    cam = Camera(R=q, t=t, fx=70.0, fy=65.0, cx=30.0, cy=20.0, width=W, height=H, znear=0.2, zfar=50.0)
    assert (cam.near, cam.far, cam.znear, cam.zfar) == (0.2, 50.0, 0.2, 50.0)
    p = rng.normal(size=(20, 3)) + q.T @ (np.array([0.0, 0.0, 5.0]) - t)  # around 5 units in front
    pc = p @ q.T + t
    uv, depth = cam.project_points(p)
    np.testing.assert_allclose(uv, np.column_stack([70 * pc[:, 0] / pc[:, 2] + 30, 65 * pc[:, 1] / pc[:, 2] + 20]),
                               atol=1e-9)
    np.testing.assert_allclose(depth, pc[:, 2], atol=1e-12)
    np.testing.assert_allclose(np.array(cam.camera_center), -q.T @ t, atol=1e-5)
    m = np.array(cam.world_to_camera_matrix)
    np.testing.assert_allclose(m[:3, :3], q, atol=1e-6)
    np.testing.assert_allclose(m[:3, 3], t, atol=1e-6)
    np.testing.assert_allclose(m[3], [0, 0, 0, 1])
    np.testing.assert_allclose(cam.camera_to_world(cam.world_to_camera(p)), p, atol=1e-12)
    np.testing.assert_allclose(cam.unproject_points(uv, depth), p, atol=1e-9)
    # Rebuilding from the attributes a script would read gives the same camera.
    assert Camera(cam.R, cam.t, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.znear, cam.zfar) == cam


def test_module_look_at_functions():
    r, t = look_at((0, 0, -4), (0, 0, 0), (0, 1, 0))
    assert isinstance(r, mx.array) and isinstance(t, mx.array)
    np.testing.assert_allclose(np.array(r), R_BACK, atol=1e-7)
    np.testing.assert_allclose(np.array(t), T_BACK, atol=1e-6)
    # On a sphere: azim 180 from +z about +y puts the camera at (0, 0, -dist); azim 90 at (+dist, 0, 0).
    r, t = look_at_view_transform(dist=4.0, elev=0.0, azim=180.0)
    np.testing.assert_allclose(np.array(r), R_BACK, atol=1e-6)
    np.testing.assert_allclose(np.array(t), T_BACK, atol=1e-6)
    r, t = look_at_view_transform(dist=3.0, azim=math.pi / 2, degrees=False)
    np.testing.assert_allclose(np.array(r), R_SIDE, atol=1e-6)
    np.testing.assert_allclose(np.array(t), T_SIDE, atol=1e-6)
    # Elevation raises the camera: it then looks down at `at`, which stays at the image centre.
    r, t = look_at_view_transform(dist=5.0, elev=30.0, azim=40.0, at=(1.0, 2.0, 3.0))
    cam = Camera(r, t, 50.0, 50.0, W / 2, H / 2, W, H)
    centre = np.array([1.0, 2.0, 3.0]) + 5.0 * np.array([math.cos(math.radians(30)) * math.sin(math.radians(40)),
                                                         math.sin(math.radians(30)),
                                                         math.cos(math.radians(30)) * math.cos(math.radians(40))])
    np.testing.assert_allclose(cam.center, centre, atol=1e-5)
    uv, depth = cam.project_points(np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(uv, [W / 2, H / 2], atol=1e-4)
    assert depth == pytest.approx(5.0, abs=1e-5)
    assert fov_to_focal(math.pi / 2, 100) == pytest.approx(50.0, rel=1e-12)
    assert focal_to_fov(50.0, 100) == pytest.approx(math.pi / 2, rel=1e-12)
    assert focal_to_fov(fov_to_focal(0.7, 64), 64) == pytest.approx(0.7, rel=1e-12)
    with pytest.raises(ValueError, match="up"):
        look_at((0, 0, 0), (0, 3, 0), (0, 1, 0))


def test_original_orthographic_camera():
    cam = Camera.orthographic_camera(2.0, W, H, R=R_BACK, t=T_BACK)
    assert cam.orthographic and cam.model == "orthographic"
    assert cam.fx == cam.fy == pytest.approx((H / 2) / 2.0)
    # Camera y = -world y; the view spans camera y in [-2, 2] over the image height, at any depth.
    uv, _ = cam.project_points(np.array([[0.0, 2.0, 0.0], [0.0, -2.0, 7.0], [0.5, 0.0, -1.0]]))
    np.testing.assert_allclose(uv, [[W / 2, 0.0], [W / 2, H], [W / 2 - 0.5 * H / 4, H / 2]], atol=1e-12)
    assert Camera(R_BACK, T_BACK, 6.0, 6.0, 32.0, 24.0, W, H, orthographic=True) == dataclasses.replace(
        cam, fx=6.0, fy=6.0)
    ortho = Camera.look_at((0, 0, -4), width=W, height=H, orthographic=True, focal=6.0)
    assert ortho.model == "orthographic" and ortho.fx == 6.0


def test_original_lens_arguments():
    base = dict(R=R_BACK, t=T_BACK, fx=45.0, fy=47.0, cx=31.0, cy=25.0, width=W, height=H)
    bc = Camera(**base, distortion=OPENCV_DIST[:4])
    assert bc.model == "opencv" and bc.dist == OPENCV_DIST[:4] + (0.0,) and bc.distortion == bc.dist
    five = Camera(**base, distortion=OPENCV_DIST)
    assert five == Camera(W, H, 45.0, 47.0, 31.0, 25.0, pose(R_BACK, T_BACK), model="opencv", dist=OPENCV_DIST)
    pc = random_cam_points(np.random.default_rng(9), 20)
    np.testing.assert_allclose(five.camera_to_pixels(pc)[0], opencv_reference(pc, five.K, OPENCV_DIST), atol=1e-9)
    fish = Camera(**base, distortion=FISHEYE_DIST, fisheye=True)
    assert fish.model == "fisheye" and fish.fisheye and fish.distortion == FISHEYE_DIST
    np.testing.assert_allclose(fish.camera_to_pixels(pc)[0], fisheye_reference(pc, fish.K, FISHEYE_DIST), atol=1e-9)
    equidistant = Camera(**base, fisheye=True)
    assert equidistant.model == "fisheye" and equidistant.dist == (0.0,) * 4
    assert Camera(**base, distortion=None).model == "pinhole"
    with pytest.raises(ValueError, match="orthographic"):
        Camera(**base, orthographic=True, fisheye=True)
    with pytest.raises(ValueError, match="dist"):
        Camera(**base, distortion=(0.1, 0.2))


def test_replace_with_original_names():
    cam = Camera.look_at(eye=(0, 0, -4), width=W, height=H)
    moved = dataclasses.replace(cam, t=T_BACK + [0.5, 0.0, 0.0])
    np.testing.assert_array_equal(moved.R, cam.R)
    np.testing.assert_allclose(moved.t, T_BACK + [0.5, 0.0, 0.0])
    turned = dataclasses.replace(cam, R=R_SIDE, t=T_SIDE)
    np.testing.assert_allclose(turned.center, [3.0, 0.0, 0.0], atol=1e-12)
    assert dataclasses.replace(cam, znear=0.5, zfar=9.0).near == 0.5
    assert dataclasses.replace(cam, znear=0.5, zfar=9.0).far == 9.0
    ortho = dataclasses.replace(cam, orthographic=True)
    assert ortho.model == "orthographic"
    assert dataclasses.replace(ortho, orthographic=False).model == "pinhole"
    assert dataclasses.replace(ortho, cx=3.0).model == "orthographic"
    fish = dataclasses.replace(cam, fisheye=True, distortion=FISHEYE_DIST)
    assert dataclasses.replace(fish, cx=3.0).dist == FISHEYE_DIST
    assert dataclasses.replace(fish, distortion=None).dist == (0.0,) * 4  # still fisheye: equidistant


def test_generate_rays_matches_rays():
    cam = camera()
    o, d = cam.generate_rays()
    assert isinstance(o, mx.array) and isinstance(d, mx.array) and o.dtype == mx.float32
    assert tuple(o.shape) == (H, W, 3) and tuple(d.shape) == (H, W, 3)
    o_np, d_np = cam.rays()
    np.testing.assert_allclose(np.array(o), o_np, atol=1e-6)
    np.testing.assert_allclose(np.array(d), d_np, atol=1e-6)
    # A centred camera's pixel grid is symmetric about the optical axis, so the mean ray is
    # the view direction (+z from (0, 0, -4)) and every origin is the eye.
    o, d = Camera.look_at((0, 0, -4), width=4, height=2, fov=40).generate_rays()
    mean = np.array(d).mean(axis=(0, 1))
    np.testing.assert_allclose(mean / np.linalg.norm(mean), [0.0, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(np.array(o), np.broadcast_to([0.0, 0.0, -4.0], (2, 4, 3)), atol=1e-6)


@pytest.mark.parametrize(
    "args, kw, error, match",
    [
        ((), {"width": W}, TypeError, "missing"),
        ((W, H, 50.0, 50.0, 32.0, 24.0), {"fx": 3.0}, TypeError, "multiple"),
        ((), {**dict(width=W, height=H, fx=50.0, fy=50.0, cx=32.0, cy=24.0), "focal": 3.0}, TypeError, "unexpected"),
        ((R_BACK, T_BACK, 50.0, 50.0, 32.0, 24.0, W, H, 0.01, 1.0, False, None, False, 1), {}, TypeError, "at most"),
        ((2.0 * R_BACK, T_BACK, 50.0, 50.0, 32.0, 24.0, W, H), {}, ValueError, "R: "),
        ((np.eye(2), T_BACK, 50.0, 50.0, 32.0, 24.0, W, H), {}, ValueError, "R must have shape"),
        ((R_BACK, (0.0, 1.0), 50.0, 50.0, 32.0, 24.0, W, H), {}, ValueError, "t must"),
        ((R_BACK, (0.0, float("nan"), 1.0), 50.0, 50.0, 32.0, 24.0, W, H), {}, ValueError, "t must be finite"),
        ((R_BACK, T_BACK, 50.0, 50.0, 32.0, 24.0, W, H), {"znear": 0.0}, ValueError, "near"),
    ],
)
def test_original_constructor_errors(args, kw, error, match):
    with pytest.raises(error, match=match):
        Camera(*args, **kw)


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
