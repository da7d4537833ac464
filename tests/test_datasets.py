"""Dataset readers (COLMAP binary/text, NeRF-synthetic, nerfstudio), image loading and its cache.

Every dataset is written here, in tmp_path, with small 16x12 PNG images and
model files produced by the writers below (COLMAP's documented byte layout,
little-endian). Expected pixels are computed by hand from the file parameters
(the lens formulas written out again here), so a wrong parameter order, a
half-pixel shift or a wrong axis flip moves a point by far more than the 1e-9 px
tolerance. Pixel values are compared exactly (uint8 / 255 in float32) or to
1e-6 where a resize averages them.
"""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from PIL import Image

from mlx3d.datasets import (
    Dataset,
    DatasetError,
    Frame,
    detect_format,
    load_colmap,
    load_dataset,
    load_nerf_synthetic,
    load_nerfstudio,
)
from mlx3d.errors import Mlx3dError

from core_marks import runs_no_kernel  # noqa: E402

pytestmark = runs_no_kernel  # file formats, datasets and packaging: no kernel of ours runs here

W, H = 16, 12
N_IMAGES = 10

# COLMAP camera models used here: id -> (model id, model name, params).
COLMAP_CAMERAS = {
    1: (0, "SIMPLE_PINHOLE", (14.0, 8.3, 5.9)),
    2: (1, "PINHOLE", (13.0, 15.5, 7.7, 6.2)),
    3: (2, "SIMPLE_RADIAL", (14.5, 8.1, 6.05, -0.08)),
    4: (3, "RADIAL", (14.2, 7.9, 5.8, -0.07, 0.02)),
    5: (4, "OPENCV", (13.4, 14.1, 8.2, 6.1, -0.09, 0.03, 0.004, -0.006)),
    6: (5, "OPENCV_FISHEYE", (9.0, 9.5, 8.05, 5.95, 0.05, -0.02, 0.004, -0.001)),
}
EXPECTED_MODEL = {
    1: ("pinhole", ()),
    2: ("pinhole", ()),
    3: ("opencv", (-0.08, 0.0, 0.0, 0.0, 0.0)),
    4: ("opencv", (-0.07, 0.02, 0.0, 0.0, 0.0)),
    5: ("opencv", (-0.09, 0.03, 0.004, -0.006, 0.0)),
    6: ("fisheye", (0.05, -0.02, 0.004, -0.001)),
}


# -- hand-written reference math


def quat_to_R(q):
    """Hamilton (w, x, y, z) quaternion -> rotation matrix, written out."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def colmap_pixel(model, params, p_cam):
    """The pixel COLMAP's camera model gives a camera-space point (pixel centres at +0.5 in both)."""
    x, y, z = p_cam
    xn, yn = x / z, y / z
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = params
        return f * xn + cx, f * yn + cy
    if model == "PINHOLE":
        fx, fy, cx, cy = params
        return fx * xn + cx, fy * yn + cy
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy, k1, *rest = params
        k2 = rest[0] if rest else 0.0
        r2 = xn * xn + yn * yn
        s = 1 + k1 * r2 + k2 * r2 * r2
        return f * xn * s + cx, f * yn * s + cy
    if model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = params
        r2 = xn * xn + yn * yn
        s = 1 + k1 * r2 + k2 * r2 * r2
        xd = xn * s + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * s + 2 * p2 * xn * yn + p1 * (r2 + 2 * yn * yn)
        return fx * xd + cx, fy * yd + cy
    if model == "OPENCV_FISHEYE":
        fx, fy, cx, cy, k1, k2, k3, k4 = params
        r = math.hypot(xn, yn)
        th = math.atan(r)
        thd = th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
        return fx * xn * thd / r + cx, fy * yn * thd / r + cy
    raise AssertionError(model)


# -- files


def image_pixels(idx, w=W, h=H, channels=3):
    i, j = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    planes = [(idx * 23 + i * 7 + j * 13 + c * 61) % 256 for c in range(channels)]
    return np.stack(planes, axis=-1).astype(np.uint8)


def write_png(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


def colmap_scene(seed=0):
    """Ground truth of a small COLMAP reconstruction: cameras, posed images, coloured points."""
    rng = np.random.default_rng(seed)
    images = []
    for k in range(N_IMAGES):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        if q[0] < 0:
            q = -q
        t = rng.normal(size=3)
        cam_id = 1 + k % len(COLMAP_CAMERAS)
        images.append(dict(id=100 + 7 * ((k * 3) % N_IMAGES), q=tuple(q), t=tuple(t), cam=cam_id,
                           name=f"img_{k:03d}.png", pts2d=[(1.5 + k, 2.25, k - 1)] * (k % 3)))
    points = rng.normal(size=(25, 3))
    colors = rng.integers(0, 256, size=(25, 3), dtype=np.uint8)
    return dict(images=images, points=points, colors=colors)


def write_colmap_binary(sparse, scene, cameras=COLMAP_CAMERAS):
    sparse.mkdir(parents=True, exist_ok=True)
    with open(sparse / "cameras.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(cameras)))
        for cid, (mid, _, params) in cameras.items():
            fh.write(struct.pack("<IiQQ", cid, mid, W, H))
            fh.write(struct.pack(f"<{len(params)}d", *params))
    with open(sparse / "images.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(scene["images"])))
        for im in reversed(scene["images"]):  # file order is not name order
            fh.write(struct.pack("<I7dI", im["id"], *im["q"], *im["t"], im["cam"]))
            fh.write(im["name"].encode() + b"\0")
            fh.write(struct.pack("<Q", len(im["pts2d"])))
            for x, y, pid in im["pts2d"]:
                fh.write(struct.pack("<ddq", x, y, pid))
    with open(sparse / "points3D.bin", "wb") as fh:
        fh.write(struct.pack("<Q", len(scene["points"])))
        for n, (p, c) in enumerate(zip(scene["points"], scene["colors"])):
            fh.write(struct.pack("<Q3d3Bd", 1000 + n, *p, *c, 0.5))
            track = [(100, n), (107, n + 1)][: n % 3]
            fh.write(struct.pack("<Q", len(track)))
            for iid, pidx in track:
                fh.write(struct.pack("<II", iid, pidx))


def text_float(x):
    """A float as COLMAP writes it, exactly (``repr`` of a numpy 2 scalar is ``np.float64(...)``)."""
    return repr(float(x))


def write_colmap_text(sparse, scene, cameras=COLMAP_CAMERAS):
    sparse.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    for cid, (_, name, params) in cameras.items():
        lines.append(" ".join([str(cid), name, str(W), str(H), *map(text_float, params)]))
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for im in scene["images"]:
        lines.append(" ".join([str(im["id"]), *map(text_float, im["q"]), *map(text_float, im["t"]), str(im["cam"]), im["name"]]))
        lines.append(" ".join(f"{text_float(x)} {text_float(y)} {pid}" for x, y, pid in im["pts2d"]))  # may be empty
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:"]
    for n, (p, c) in enumerate(zip(scene["points"], scene["colors"])):
        lines.append(" ".join([str(1000 + n), *map(text_float, p.tolist()), *map(str, c.tolist()), "0.5", "100 0"]))
    (sparse / "points3D.txt").write_text("\n".join(lines) + "\n")


def make_colmap(root, binary=True, scene=None, images=True):
    scene = scene or colmap_scene()
    (write_colmap_binary if binary else write_colmap_text)(root / "sparse" / "0", scene)
    if images:
        for k, im in enumerate(scene["images"]):
            write_png(root / "images" / im["name"], image_pixels(k))
    return scene


def gl_c2w(eye, at, up=(0.0, 0.0, 1.0)):
    """An OpenGL camera-to-world pose (x right, y up, looking down -z) at ``eye`` looking at ``at``."""
    eye, at, up = (np.asarray(v, float) for v in (eye, at, up))
    back = eye - at
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
    return m


def gl_pixel(c2w, fx, fy, cx, cy, point):
    """Hand projection for an OpenGL c2w: camera coordinates, flip y and z, pinhole."""
    xg, yg, zg = c2w[:3, :3].T @ (np.asarray(point, float) - c2w[:3, 3])
    x, y, z = xg, -yg, -zg
    return fx * x / z + cx, fy * y / z + cy


def make_nerf_synthetic(root, n=(3, 2, 2), rgba=True, angle=0.9):
    poses = {}
    for split, count in zip(("train", "val", "test"), n):
        frames = []
        for k in range(count):
            a = 2 * math.pi * (k + 0.3 * len(poses)) / max(count, 1)
            c2w = gl_c2w((4 * math.cos(a), 4 * math.sin(a), 1.0 + 0.2 * k), (0.1, -0.2, 0.3))
            name = f"{split}/r_{k}"
            write_png(root / f"{name}.png", image_pixels(10 * len(poses) + k, channels=4 if rgba else 3))
            frames.append({"file_path": f"./{name}", "rotation": 0.1, "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
        poses[split] = [np.array(f["transform_matrix"]) for f in frames]
    return poses


def write_ply_points(path, xyz, rgb=None):
    import plyfile

    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    v = np.empty(len(xyz), dtype=fields)
    v["x"], v["y"], v["z"] = xyz.T
    if rgb is not None:
        v["red"], v["green"], v["blue"] = rgb.T
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(path))


NS_SHARED = {"camera_model": "OPENCV", "fl_x": 13.5, "fl_y": 14.25, "cx": 7.6, "cy": 6.3, "w": W, "h": H,
             "k1": -0.05, "k2": 0.01, "p1": 0.002, "p2": -0.003}


def make_nerfstudio(root, n=10, names=None, ply=True, masks=False, split_lists=None):
    rng = np.random.default_rng(3)
    frames = []
    for k in range(n):
        c2w = gl_c2w(rng.normal(size=3) * 0.5 + (0, -5, 1), (0, 0, 0))
        name = (names or [f"images/frame_{i:05d}.png" for i in range(n)])[k]
        write_png(root / name, image_pixels(k))
        fr = {"file_path": name, "transform_matrix": c2w.tolist()}
        if masks:
            m = np.zeros((H, W), np.uint8)
            m[2:9, 3 + k % 4:12] = 1  # nonzero = keep, even for tiny values
            write_png(root / f"masks/frame_{k:05d}.png", m)
            fr["mask_path"] = f"masks/frame_{k:05d}.png"
        frames.append(fr)
    # Frame 1 overrides the shared intrinsics; frame 2 is a fisheye.
    frames[1].update({"fl_x": 12.0, "fl_y": 12.5, "cx": 8.25, "cy": 5.75, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                      "camera_model": "PINHOLE"})
    frames[2].update({"camera_model": "OPENCV_FISHEYE", "k1": 0.03, "k2": -0.01, "k3": 0.002, "k4": -0.0005,
                      "p1": 0.0, "p2": 0.0})
    meta = dict(NS_SHARED, applied_transform=np.eye(4)[:3].tolist(), frames=list(reversed(frames)))
    if ply:
        meta["ply_file_path"] = "sparse_pc.ply"
        xyz = np.arange(12, dtype=np.float32).reshape(4, 3) * 0.5
        rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]], np.uint8)
        write_ply_points(root / "sparse_pc.ply", xyz, rgb)
    if split_lists:
        meta.update(split_lists)
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return frames


# -- COLMAP


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_colmap_cameras_project_like_colmap(tmp_path, binary):
    scene = make_colmap(tmp_path, binary)
    ds = load_colmap(tmp_path)
    assert ds.kind == "colmap" and len(ds) == N_IMAGES
    by_name = {im["name"]: im for im in scene["images"]}
    rng = np.random.default_rng(1)
    for fr in ds.frames:
        im = by_name[fr.name]
        _, model, params = COLMAP_CAMERAS[im["cam"]]
        R, t = quat_to_R(im["q"]), np.array(im["t"])
        for _ in range(3):
            p_cam = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.25, 0.25), rng.uniform(2.0, 5.0)])
            world = R.T @ (p_cam - t)
            uv, depth = fr.camera.project_points(world)
            # COLMAP's pixel frame is ours (pixel centres at +0.5): no offset.
            np.testing.assert_allclose(uv, colmap_pixel(model, params, p_cam), rtol=0, atol=1e-9)
            assert depth == pytest.approx(p_cam[2], abs=1e-12)
        np.testing.assert_allclose(fr.camera.center, -R.T @ t, atol=1e-12)
        assert (fr.camera.width, fr.camera.height) == (W, H)


def test_colmap_models_map_to_camera_models(tmp_path):
    scene = make_colmap(tmp_path)
    ds = load_colmap(tmp_path)
    by_name = {im["name"]: im for im in scene["images"]}
    seen = set()
    for fr in ds.frames:
        cam_id = by_name[fr.name]["cam"]
        model, dist = EXPECTED_MODEL[cam_id]
        assert fr.camera.model == model
        np.testing.assert_allclose(fr.camera.dist, dist, atol=0)
        seen.add(cam_id)
    assert seen == set(COLMAP_CAMERAS)


def test_colmap_binary_and_text_agree(tmp_path):
    scene = colmap_scene()
    make_colmap(tmp_path / "b", True, scene)
    make_colmap(tmp_path / "t", False, scene)
    a, b = load_colmap(tmp_path / "b"), load_colmap(tmp_path / "t")
    assert [f.name for f in a] == [f.name for f in b]
    for fa, fb in zip(a, b):
        assert fa.camera == fb.camera
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.point_colors, b.point_colors)


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_colmap_points_and_colours(tmp_path, binary):
    scene = make_colmap(tmp_path, binary)
    ds = load_colmap(tmp_path)
    assert ds.points.dtype == np.float32 and ds.points.shape == (25, 3)
    assert ds.point_colors.dtype == np.uint8
    np.testing.assert_array_equal(ds.points, scene["points"].astype(np.float32))
    np.testing.assert_array_equal(ds.point_colors, scene["colors"])


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_colmap_tracks_say_where_each_photo_sees_its_points(tmp_path, binary):
    """Each image's 2D points that name a 3D point become the dataset's observations, in the
    frame camera's pixels (scaled with the factor); unobserved keypoints (-1) and ids the model
    lacks are dropped."""
    scene = colmap_scene()
    for k, im in enumerate(scene["images"]):
        im["pts2d"] = [(1.5 + k, 2.25, 1000 + k), (3.0, 4.0, -1), (7.75, 0.5 + k, 1000 + 2 * k), (2.0, 2.0, 999)]
    make_colmap(tmp_path, binary, scene)
    for factor in (1, 2):
        ds = load_colmap(tmp_path, factor=factor)
        assert len(ds.observations) == len(ds.frames)
        for frame, (xy, index) in zip(ds.frames, ds.observations):
            k = int(frame.name[4:7])
            np.testing.assert_array_equal(index, [k, 2 * k])
            np.testing.assert_allclose(xy, np.array([[1.5 + k, 2.25], [7.75, 0.5 + k]]) / factor, rtol=1e-6)
    make_colmap(tmp_path / "none", binary, colmap_scene(), images=True)
    (tmp_path / "none" / "sparse" / "0" / f"points3D.{'bin' if binary else 'txt'}").unlink()
    assert load_colmap(tmp_path / "none").observations is None


@pytest.mark.parametrize("line, says", [("1.5 2.5", "as X Y POINT3D_ID triples, got 2 values"),
                                         ("1.5 2.5 seven", "malformed 2D points of image")])
def test_colmap_text_2d_points_that_are_not_triples_of_numbers_are_named(tmp_path, line, says):
    scene = colmap_scene()
    make_colmap(tmp_path, False, scene)
    images = tmp_path / "sparse" / "0" / "images.txt"
    lines = images.read_text().splitlines()
    first = next(i for i, text in enumerate(lines) if text and not text.startswith("#"))
    lines[first + 1] = line
    images.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=f"images.txt:{first + 2}: .*{says}"):
        load_colmap(tmp_path)


def test_colmap_without_points3d_has_no_points(tmp_path):
    make_colmap(tmp_path)
    (tmp_path / "sparse" / "0" / "points3D.bin").unlink()
    ds = load_colmap(tmp_path)
    assert ds.points is None and ds.point_colors is None


def test_colmap_split_holds_out_every_eighth_by_name(tmp_path):
    make_colmap(tmp_path)
    ds = load_colmap(tmp_path)
    assert [f.name for f in ds] == sorted(f"img_{k:03d}.png" for k in range(N_IMAGES))
    assert ds.test == [0, 8] and ds.split("test") == [0, 8]
    assert ds.train == [1, 2, 3, 4, 5, 6, 7, 9]
    assert load_colmap(tmp_path, test_every=4).test == [0, 4, 8]
    everything = load_colmap(tmp_path, test_every=None)
    assert everything.test == [] and everything.train == list(range(N_IMAGES))
    with pytest.raises(ValueError, match="no split 'val'"):
        ds.split("val")


def test_colmap_images_load_as_stored(tmp_path):
    make_colmap(tmp_path)
    ds = load_colmap(tmp_path)
    for i in (0, 3, 9):
        rgb, weight = ds.load_image(i)
        k = int(ds[i].name[4:7])
        assert rgb.dtype == np.float32 and rgb.shape == (H, W, 3) and weight is None
        np.testing.assert_array_equal(rgb, image_pixels(k).astype(np.float32) / np.float32(255))


def test_colmap_sparse_without_zero_and_detect(tmp_path):
    scene = colmap_scene()
    write_colmap_binary(tmp_path / "sparse", scene)
    for k, im in enumerate(scene["images"]):
        write_png(tmp_path / "images" / im["name"], image_pixels(k))
    assert detect_format(tmp_path) == "colmap"
    assert len(load_dataset(tmp_path)) == N_IMAGES


def test_colmap_masks_dir(tmp_path):
    scene = make_colmap(tmp_path)
    for k, im in enumerate(scene["images"]):
        m = np.zeros((H // 2, W // 2), np.uint8)  # half size: resized to the camera
        m[: 1 + k % 5] = 255
        write_png(tmp_path / "masks" / (im["name"] + ".png"), m)
    ds = load_colmap(tmp_path, masks_dir="masks")
    for i in (0, 6):
        k = int(ds[i].name[4:7])
        expect = np.zeros((H, W), np.float32)
        expect[: 2 * (1 + k % 5)] = 1
        np.testing.assert_array_equal(ds.load_image(i)[1], expect)
    (tmp_path / "masks" / "img_003.png.png").unlink()
    with pytest.raises(DatasetError, match=r"masks/img_003\.png: mask not found"):
        load_colmap(tmp_path, masks_dir="masks")


# -- downscaling


def test_downscale_uses_images_folder(tmp_path):
    scene = make_colmap(tmp_path)
    for k, im in enumerate(scene["images"]):
        write_png(tmp_path / "images_2" / im["name"], np.full((H // 2, W // 2, 3), 40 + k, np.uint8))
    ds = load_colmap(tmp_path, factor=2)
    full = load_colmap(tmp_path)
    for fr, ref in zip(ds, full):
        assert fr.image_path.parent.name == "images_2"
        assert (fr.camera.width, fr.camera.height) == (W // 2, H // 2)
        pts = np.array([[0.1, -0.2, 0.3], [-0.4, 0.25, 0.1]])
        uv_full, _ = ref.camera.project_points(pts)
        uv, _ = fr.camera.project_points(pts)
        np.testing.assert_allclose(uv, uv_full / 2, atol=1e-9)
    rgb, _ = ds.load_image(0)
    np.testing.assert_array_equal(rgb, np.full((H // 2, W // 2, 3), 40 / 255, np.float32))


@pytest.mark.parametrize("factor", [2, 4, 3, 2.5])
def test_downscale_resizes_and_scales_camera(tmp_path, factor):
    make_colmap(tmp_path)
    full = load_colmap(tmp_path)
    ds = load_colmap(tmp_path, factor=factor, resample="box")
    w, h = math.floor(W / factor + 0.5), math.floor(H / factor + 0.5)
    pts = np.array([[0.1, -0.2, 0.3], [-0.4, 0.25, 0.1], [0.0, 0.0, 0.0]])
    for fr, ref in zip(ds, full):
        assert fr.image_path == ref.image_path  # no images_N folder: the full image, resized
        assert (fr.camera.width, fr.camera.height) == (w, h)
        uv_full, _ = ref.camera.project_points(pts)
        uv, _ = fr.camera.project_points(pts)
        np.testing.assert_allclose(uv, uv_full * [w / W, h / H], atol=1e-9)
    rgb, _ = ds.load_image(1)
    assert rgb.shape == (h, w, 3) and rgb.dtype == np.float32
    if factor in (2, 4):  # BOX over whole blocks is the block mean
        src = full.load_image(1)[0].astype(np.float64)
        f = int(factor)
        expect = src.reshape(h, f, w, f, 3).mean(axis=(1, 3))
        np.testing.assert_allclose(rgb, expect, atol=1e-6)
    lz = load_colmap(tmp_path, factor=factor).load_image(1)[0]  # default Lanczos
    assert lz.shape == (h, w, 3) and lz.min() >= 0 and lz.max() <= 1


def test_downscaled_folder_of_wrong_size_is_an_error(tmp_path):
    scene = make_colmap(tmp_path)
    for im in scene["images"]:
        write_png(tmp_path / "images_4" / im["name"], np.zeros((H // 2, W // 2, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"images_4.*img_000\.png.*8x6.*factor 4"):
        load_colmap(tmp_path, factor=4)


def test_rgba_downscale_is_premultiplied(tmp_path):
    make_nerf_synthetic(tmp_path)
    full = load_nerf_synthetic(tmp_path)
    ds = load_nerf_synthetic(tmp_path, factor=2, resample="box")
    small, _ = ds.load_image(0, background="black")
    big, _ = full.load_image(0, background="black")
    expect = big.astype(np.float64).reshape(H // 2, 2, W // 2, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(small, expect, atol=1e-6)
    _, a_small = ds.load_image(0)
    _, a_big = full.load_image(0)
    np.testing.assert_allclose(a_small, a_big.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3)), atol=1e-6)


# -- NeRF-synthetic


def test_nerf_synthetic_cameras_flip_opengl(tmp_path):
    angle = 0.9
    poses = make_nerf_synthetic(tmp_path, angle=angle)
    ds = load_nerf_synthetic(tmp_path)
    assert ds.kind == "nerf_synthetic"
    fx = 0.5 * W / math.tan(0.5 * angle)
    c2ws = poses["train"] + poses["val"] + poses["test"]
    assert len(ds) == len(c2ws)
    pts = [(0.1, -0.2, 0.3), (0.5, 0.4, -0.2), (-0.3, 0.2, 0.8)]
    for fr, c2w in zip(ds, c2ws):
        assert (fr.camera.fx, fr.camera.fy, fr.camera.cx, fr.camera.cy) == (fx, fx, W / 2, H / 2)
        for p in pts:
            uv, depth = fr.camera.project_points(np.array(p))
            np.testing.assert_allclose(uv, gl_pixel(c2w, fx, fx, W / 2, H / 2, p), atol=1e-9)
            assert depth > 0
    assert ds[0].name == "train/r_0.png" and ds[0].image_path.name == "r_0.png"


def test_nerf_synthetic_files_with_nerfstudio_intrinsics(tmp_path):
    """Blender's NeRF exporters and capture apps write fl_x/camera_model (with or without camera_angle_x):
    those decide the camera; a frame's own values override the file's."""
    poses = make_nerf_synthetic(tmp_path, n=(2, 0, 1), rgba=False)
    for split, extra in (("train", {"camera_model": "PINHOLE", "fl_x": 40.0, "fl_y": 42.0, "cx": 7.5, "cy": 5.0}),
                         ("test", {"camera_angle_x": 0.9, "fl_x": 30.0})):
        path = tmp_path / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        meta.pop("camera_angle_x")
        meta.update(extra)
        if split == "train":
            meta["frames"][1]["fl_x"] = 50.0
        path.write_text(json.dumps(meta))
    ds = load_nerf_synthetic(tmp_path)
    cams = [fr.camera for fr in ds]
    assert [(c.fx, c.fy, c.cx, c.cy, c.model) for c in cams] == [
        (40.0, 42.0, 7.5, 5.0, "pinhole"), (50.0, 42.0, 7.5, 5.0, "pinhole"), (30.0, 30.0, W / 2, H / 2, "pinhole")]
    p = (0.1, -0.2, 0.3)
    np.testing.assert_allclose(cams[0].project_points(np.array(p))[0], gl_pixel(poses["train"][0], 40.0, 42.0, 7.5, 5.0, p),
                               atol=1e-9)


def test_nerf_synthetic_named_splits(tmp_path):
    make_nerf_synthetic(tmp_path, n=(3, 2, 2))
    ds = load_nerf_synthetic(tmp_path)
    assert ds.train == [0, 1, 2] and ds.split("val") == [3, 4] and ds.test == [5, 6]
    assert [ds[i].name.split("/")[0] for i in ds.test] == ["test", "test"]
    assert load_nerf_synthetic(tmp_path, val_in_train=True).train == [0, 1, 2, 3, 4]
    (tmp_path / "transforms_val.json").unlink()
    ds = load_nerf_synthetic(tmp_path)
    assert ds.train == [0, 1, 2] and ds.test == [3, 4] and "val" not in ds.splits
    assert detect_format(tmp_path) == "nerf_synthetic"
    assert load_dataset(tmp_path).test == [3, 4]


def test_rgba_composited_on_white_black_and_colour(tmp_path):
    make_nerf_synthetic(tmp_path)
    ds = load_nerf_synthetic(tmp_path)
    px = image_pixels(0, channels=4).astype(np.float32) / np.float32(255)
    rgb, a = px[..., :3], px[..., 3:]
    assert np.any((a > 0) & (a < 1)) and np.any(a == 0)  # partial and empty coverage
    for bg, col in (("white", (1, 1, 1)), ("black", (0, 0, 0)), ((0.2, 0.5, 0.9), (0.2, 0.5, 0.9))):
        out, weight = ds.load_image(0, background=bg)
        assert weight is None and out.dtype == np.float32
        np.testing.assert_allclose(out, rgb * a + np.float32(col) * (1 - a), atol=1e-6)


def test_rgba_random_background_is_fresh_each_call(tmp_path):
    make_nerf_synthetic(tmp_path)
    ds = load_nerf_synthetic(tmp_path)
    px = image_pixels(0, channels=4).astype(np.float32) / np.float32(255)
    rgb, a = px[..., :3], px[..., 3:]
    rng = np.random.default_rng(5)
    expect = np.random.default_rng(5)
    seen = []
    for _ in range(3):
        out, weight, bg = ds.load_image(0, background="random", rng=rng, return_background=True)
        col = expect.random(3).astype(np.float32)
        np.testing.assert_array_equal(bg, col)
        np.testing.assert_allclose(out, rgb * a + col * (1 - a), atol=1e-6)
        assert weight is None
        seen.append(tuple(bg))
    assert len(set(seen)) == 3
    a1 = ds.load_image(0, background="random")[0]  # the dataset's own generator
    a2 = ds.load_image(0, background="random")[0]
    assert not np.array_equal(a1, a2)


def test_rgba_alpha_as_weight_without_background(tmp_path):
    make_nerf_synthetic(tmp_path)
    ds = load_nerf_synthetic(tmp_path)
    px = image_pixels(0, channels=4).astype(np.float32) / np.float32(255)
    rgb, weight = ds.load_image(0)
    np.testing.assert_array_equal(rgb, px[..., :3])  # straight colour, untouched
    np.testing.assert_array_equal(weight, px[..., 3])
    out, bg = ds.load_image(0)  # two-tuple without return_background
    assert bg is not None and out.shape == (H, W, 3)
    assert ds.load_image(0, return_background=True)[2] is None


def test_rgb_images_ignore_background(tmp_path):
    make_nerf_synthetic(tmp_path, rgba=False)
    ds = load_nerf_synthetic(tmp_path)
    a, wa = ds.load_image(1)
    b, wb = ds.load_image(1, background="white")
    assert wa is None and wb is None
    np.testing.assert_array_equal(a, b)


def test_opaque_alpha_counts_as_none(tmp_path):
    make_nerf_synthetic(tmp_path, n=(1, 0, 0))
    px = image_pixels(0, channels=4)
    px[..., 3] = 255
    write_png(tmp_path / "train" / "r_0.png", px)
    rgb, weight = load_nerf_synthetic(tmp_path).load_image(0)
    assert weight is None
    np.testing.assert_array_equal(rgb, px[..., :3].astype(np.float32) / np.float32(255))


# -- nerfstudio


def test_nerfstudio_shared_and_per_frame_intrinsics(tmp_path):
    frames = make_nerfstudio(tmp_path)
    ds = load_nerfstudio(tmp_path)
    assert ds.kind == "nerfstudio" and len(ds) == 10
    assert [f.name for f in ds] == [f"images/frame_{k:05d}.png" for k in range(10)]  # sorted by file_path
    s = NS_SHARED
    p = np.array([0.2, -0.1, 0.3])
    for k, fr in enumerate(ds):
        c2w = np.array(frames[k]["transform_matrix"])
        cam = fr.camera
        if k == 1:
            assert cam.model == "pinhole" and cam.dist == ()
            intr = (12.0, 12.5, 8.25, 5.75)
        elif k == 2:
            assert cam.model == "fisheye" and cam.dist == (0.03, -0.01, 0.002, -0.0005)
            intr = (s["fl_x"], s["fl_y"], s["cx"], s["cy"])
        else:
            assert cam.model == "opencv" and cam.dist == (s["k1"], s["k2"], s["p1"], s["p2"], 0.0)
            intr = (s["fl_x"], s["fl_y"], s["cx"], s["cy"])
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == intr
        if k == 1:
            uv, _ = cam.project_points(p)
            np.testing.assert_allclose(uv, gl_pixel(c2w, *intr, p), atol=1e-9)
        else:  # the distorted models: hand projection of the flipped camera-space point
            xg, yg, zg = c2w[:3, :3].T @ (p - c2w[:3, 3])
            model = "OPENCV_FISHEYE" if k == 2 else "OPENCV"
            params = (*intr, *cam.dist[:4])
            np.testing.assert_allclose(cam.project_points(p)[0], colmap_pixel(model, params, (xg, -yg, -zg)),
                                       atol=1e-9)


def test_nerfstudio_points_masks_and_split(tmp_path):
    make_nerfstudio(tmp_path, masks=True)
    ds = load_nerfstudio(tmp_path / "transforms.json")
    np.testing.assert_array_equal(ds.points, np.arange(12, dtype=np.float32).reshape(4, 3) * 0.5)
    np.testing.assert_array_equal(ds.point_colors, [[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]])
    assert ds.test == [0, 8] and ds.train == [1, 2, 3, 4, 5, 6, 7, 9]
    for k in (0, 5):
        expect = np.zeros((H, W), np.float32)
        expect[2:9, 3 + k % 4:12] = 1
        rgb, weight = ds.load_image(k)
        np.testing.assert_array_equal(weight, expect)
        np.testing.assert_array_equal(rgb, image_pixels(k).astype(np.float32) / np.float32(255))
        out, weight = ds.load_image(k, background="white")  # the mask as coverage
        assert weight is None
        np.testing.assert_array_equal(out[expect == 0], 1.0)
        np.testing.assert_array_equal(out[expect == 1], rgb[expect == 1])


def test_mask_times_alpha(tmp_path):
    make_nerfstudio(tmp_path, n=9, masks=True, ply=False)
    px = image_pixels(4, channels=4)
    write_png(tmp_path / "images/frame_00004.png", px)
    ds = load_nerfstudio(tmp_path)
    assert ds.points is None
    _, weight = ds.load_image(4)
    mask = np.zeros((H, W), np.float32)
    mask[2:9, 3:12] = 1
    np.testing.assert_allclose(weight, mask * px[..., 3].astype(np.float32) / 255, atol=1e-7)


def test_colour_mask_keeps_any_nonzero_channel(tmp_path):
    make_nerfstudio(tmp_path, n=9, masks=True, ply=False)
    m = np.zeros((H, W, 3), np.uint8)
    m[1, 2] = (0, 0, 2)
    m[5, 7:10] = (1, 0, 0)
    write_png(tmp_path / "masks/frame_00006.png", m)
    _, weight = load_nerfstudio(tmp_path).load_image(6)
    np.testing.assert_array_equal(weight, np.any(m != 0, axis=-1).astype(np.float32))
    assert weight.sum() == 4


def test_nerfstudio_named_splits(tmp_path):
    names = [f"images/frame_{i:05d}.png" for i in range(10)]
    make_nerfstudio(tmp_path, split_lists={"train_filenames": names[3:], "test_filenames": ["./" + names[1], names[0]]})
    ds = load_nerfstudio(tmp_path)
    assert ds.train == list(range(3, 10)) and ds.test == [0, 1]
    assert detect_format(tmp_path) == "nerfstudio" and load_dataset(tmp_path).test == [0, 1]
    assert load_dataset(tmp_path / "transforms.json", kind="nerfstudio").train == list(range(3, 10))


def test_nerfstudio_downscale_folder(tmp_path):
    make_nerfstudio(tmp_path, n=4, ply=False)
    for k in range(4):
        write_png(tmp_path / f"images_2/frame_{k:05d}.png", np.full((H // 2, W // 2, 3), 7 * k, np.uint8))
    ds, full = load_nerfstudio(tmp_path, factor=2), load_nerfstudio(tmp_path)
    assert ds[3].image_path == tmp_path / "images_2" / "frame_00003.png"
    np.testing.assert_array_equal(ds.load_image(3)[0], np.full((H // 2, W // 2, 3), 21 / 255, np.float32))
    assert ds[3].camera.fx == full[3].camera.fx / 2 and ds[3].camera.cy == full[3].camera.cy / 2


# -- dataset behaviour


def test_lru_cache_stays_bounded(tmp_path):
    make_colmap(tmp_path)
    per_image = H * W * 3 * 4
    ds = load_colmap(tmp_path, cache_images=3)
    for i in range(N_IMAGES):
        ds.load_image(i)
    info = ds.cache_info()
    assert (info.items, info.bytes, info.misses, info.hits) == (3, 3 * per_image, N_IMAGES, 0)
    ds.load_image(9)  # most recent: a hit
    ds.load_image(0)  # evicted long ago: a miss
    info = ds.cache_info()
    assert (info.hits, info.misses, info.items) == (1, N_IMAGES + 1, 3)

    ds = load_colmap(tmp_path, cache_bytes=int(2.5 * per_image))
    for _ in range(2):
        for i in range(N_IMAGES):
            ds.load_image(i)
            assert ds.cache_info().bytes <= 2.5 * per_image
    assert ds.cache_info().items == 2 and ds.cache_info().max_bytes == int(2.5 * per_image)

    ds = load_colmap(tmp_path, cache_images=0)
    ds.load_image(0)
    ds.load_image(0)
    assert ds.cache_info().items == 0 and ds.cache_info().misses == 2
    default = load_colmap(tmp_path).cache_info()
    assert default.max_bytes == 1 << 30


def test_cached_images_are_read_only(tmp_path):
    make_colmap(tmp_path)
    ds = load_colmap(tmp_path)
    rgb, _ = ds.load_image(2)
    with pytest.raises(ValueError):
        rgb[0, 0, 0] = 1.0
    assert ds.load_image(2)[0] is rgb


def test_scene_extent_uses_training_cameras(tmp_path):
    scene = colmap_scene()
    # Put the first image by name (a test frame) far away: it must not count.
    scene["images"][0]["t"] = (0.0, 0.0, 500.0)
    make_colmap(tmp_path, scene=scene)
    ds = load_colmap(tmp_path)
    by_name = {im["name"]: im for im in scene["images"]}
    centres = np.array([-quat_to_R(by_name[ds[i].name]["q"]).T @ np.array(by_name[ds[i].name]["t"])
                        for i in ds.train])
    expect = 1.1 * np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1))
    assert ds.scene_extent() == pytest.approx(expect, rel=1e-12)
    everything = np.array([f.camera.center for f in ds])
    assert ds.scene_extent(range(len(ds))) == pytest.approx(
        1.1 * np.max(np.linalg.norm(everything - everything.mean(axis=0), axis=1)), rel=1e-12)
    assert ds.scene_extent(range(len(ds))) > 100 > ds.scene_extent()


def test_dataset_from_frames(tmp_path):
    write_png(tmp_path / "a.png", image_pixels(0))
    from mlx3d.cameras import Camera

    cam = Camera.look_at((0, -3, 0), (0, 0, 0), (0, 0, 1), width=W, height=H, hfov=60)
    ds = Dataset([Frame(cam, tmp_path / "a.png", "a")] * 9, cache_images=1)
    assert ds.test == [0, 8] and ds.scene_extent() == 0.0
    assert ds.load_image(-1)[0].shape == (H, W, 3)
    with pytest.raises(IndexError):
        ds.load_image(9)
    with pytest.raises(ValueError, match="background"):
        ds.load_image(0, background="grey")


# -- errors name the file


def test_error_type():
    assert issubclass(DatasetError, Mlx3dError) and issubclass(DatasetError, ValueError)


def test_missing_images_folder(tmp_path):
    make_colmap(tmp_path, images=False)
    with pytest.raises(DatasetError, match=r"images: images folder not found"):
        load_colmap(tmp_path)


def test_missing_image(tmp_path):
    make_colmap(tmp_path)
    (tmp_path / "images" / "img_004.png").unlink()
    with pytest.raises(DatasetError, match=r"images/img_004\.png: image not found"):
        load_colmap(tmp_path)


def test_missing_nerf_image_and_mask(tmp_path):
    make_nerf_synthetic(tmp_path)
    (tmp_path / "test" / "r_1.png").unlink()
    with pytest.raises(DatasetError, match=r"test/r_1\.png: image not found.*transforms_test\.json"):
        load_nerf_synthetic(tmp_path)
    make_nerfstudio(tmp_path / "ns", masks=True)
    (tmp_path / "ns" / "masks" / "frame_00003.png").unlink()
    with pytest.raises(DatasetError, match=r"frame_00003\.png: mask not found"):
        load_nerfstudio(tmp_path / "ns")


@pytest.mark.parametrize("cut", [8 + 24 + 3 * 8 + 5, 8 + 10, 4])
def test_truncated_cameras_bin(tmp_path, cut):
    make_colmap(tmp_path)
    p = tmp_path / "sparse" / "0" / "cameras.bin"
    p.write_bytes(p.read_bytes()[:cut])
    with pytest.raises(DatasetError, match=r"cameras\.bin: truncated file") as info:
        load_colmap(tmp_path)
    if cut > 8:
        assert "camera record" in str(info.value)


@pytest.mark.parametrize("name,cut", [("images.bin", -30), ("points3D.bin", -5), ("images.bin", 20)])
def test_truncated_images_and_points_bin(tmp_path, name, cut):
    make_colmap(tmp_path)
    p = tmp_path / "sparse" / "0" / name
    p.write_bytes(p.read_bytes()[:cut])
    with pytest.raises(DatasetError, match=rf"{name.replace('.', r'[.]')}: truncated file: .*record"):
        load_colmap(tmp_path)


def test_trailing_bytes_are_reported(tmp_path):
    make_colmap(tmp_path)
    p = tmp_path / "sparse" / "0" / "points3D.bin"
    p.write_bytes(p.read_bytes() + b"\0\0\0")
    with pytest.raises(DatasetError, match=r"points3D\.bin: 3 unexpected bytes after the 25 points"):
        load_colmap(tmp_path)


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_unsupported_camera_model(tmp_path, binary):
    cams = dict(COLMAP_CAMERAS)
    cams[3] = (7, "FOV", (14.0, 14.0, 8.0, 6.0, 0.9))
    scene = colmap_scene()
    (write_colmap_binary if binary else write_colmap_text)(tmp_path / "sparse" / "0", scene, cams)
    for k, im in enumerate(scene["images"]):
        write_png(tmp_path / "images" / im["name"], image_pixels(k))
    ext = "bin" if binary else "txt"
    with pytest.raises(DatasetError, match=rf"cameras\.{ext}: camera 3: unsupported camera model FOV"):
        load_colmap(tmp_path)


def test_unknown_model_id_and_camera_id(tmp_path):
    cams = {1: (42, "X", (1.0, 2.0))}
    scene = colmap_scene()
    write_colmap_binary(tmp_path / "a" / "sparse" / "0", scene, cams)
    msg = r"cameras\.bin: camera record 1 of 1 \(camera 1\): unknown camera model id 42"
    with pytest.raises(DatasetError, match=msg):
        load_colmap(tmp_path / "a")
    write_colmap_text(tmp_path / "b" / "sparse" / "0", scene, {1: COLMAP_CAMERAS[1]})
    (tmp_path / "b" / "images").mkdir()
    with pytest.raises(DatasetError, match=r"images\.txt: image \d+ \(img_\d+\.png\) uses camera [2-6]"):
        load_colmap(tmp_path / "b")


def test_malformed_text_lines_name_the_line(tmp_path):
    make_colmap(tmp_path, binary=False)
    p = tmp_path / "sparse" / "0" / "images.txt"
    lines = p.read_text().splitlines()
    lines[5] = lines[5].replace(" 0.", " zero.", 1)  # second image record (line 6)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"images\.txt:6: malformed image line"):
        load_colmap(tmp_path)
    lines = p.read_text().splitlines()
    del lines[4]  # drop the first image's (empty) 2D point line
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"images\.txt:5: expected the 2D points of image"):
        load_colmap(tmp_path)
    c = tmp_path / "sparse" / "0" / "cameras.txt"
    c.write_text(c.read_text().replace("SIMPLE_PINHOLE 16 12 14.0", "SIMPLE_PINHOLE 16 12"))
    with pytest.raises(DatasetError, match=r"cameras\.txt:3: camera 1: model SIMPLE_PINHOLE has 3 parameters, got 2"):
        load_colmap(tmp_path)


def test_malformed_json(tmp_path):
    make_nerf_synthetic(tmp_path)
    p = tmp_path / "transforms_test.json"
    p.write_text('{"camera_angle_x": 0.5,\n "frames": [\n  {"file_path": "./test/r_0",}\n ]\n}')
    with pytest.raises(DatasetError, match=r"transforms_test\.json:3:\d+: malformed JSON"):
        load_nerf_synthetic(tmp_path)
    p.write_text(json.dumps({"camera_angle_x": 0.5, "frames": [{"file_path": "./test/r_0"}]}))
    msg = r"transforms_test\.json: frames\[0\] \(\./test/r_0\) has no 'transform_matrix'"
    with pytest.raises(DatasetError, match=msg):
        load_nerf_synthetic(tmp_path)
    make_nerfstudio(tmp_path / "ns", ply=False)
    q = tmp_path / "ns" / "transforms.json"
    meta = json.loads(q.read_text())
    meta["frames"][0]["transform_matrix"][0][0] = 3.0
    q.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[0\].*not a rotation"):
        load_nerfstudio(tmp_path / "ns")
    meta["frames"][0]["transform_matrix"][0][0] = 1.0
    meta["frames"][0]["camera_model"] = "EQUIRECTANGULAR"
    q.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[0\].*unsupported camera_model EQUIRECTANGULAR"):
        load_nerfstudio(tmp_path / "ns")


def test_corrupt_image_and_unknown_dataset(tmp_path):
    make_colmap(tmp_path)
    (tmp_path / "images" / "img_002.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"img_002\.png: cannot read image"):
        load_colmap(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"empty: no dataset found"):
        load_dataset(tmp_path / "empty")
