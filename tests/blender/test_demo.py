"""The Blender demo (``addon/demo.py``, ``blender_splat.py demo``) through the installed extension.

The quick demo runs once per module as the headless command, in a subprocess
that sees the same installed extension. Oracles: the dataset it captured
(image size and the held-out frames), the PLY it exported read back with
``read_splat_ply`` (the .blend must hold exactly those splats), and an
independent render of that PLY at the held-out camera (the right half of
``side_by_side.png``, whose left half is the ground truth composited on white).
"""

import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from mlx3d.io import read_splat_ply
from core_marks import above_kernels

pytestmark = above_kernels  # the add-on's demo over the trainer: the pure path runs the same code there

bpy = pytest.importorskip("bpy")
pytest.importorskip("PIL", reason="mlx3d.datasets decodes images with Pillow")

RESOLUTION = 32  # the quick demo's capture size
VIEWS = 8


def _script(extension):
    return os.path.join(os.path.dirname(extension.__file__), "addon", "blender_splat.py")


@pytest.fixture(scope="module")
def quick_demo(extension, extension_env, tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo_out"
    t0 = time.perf_counter()
    result = subprocess.run([sys.executable, _script(extension), "demo", "--out", str(out), "--quick"],
                            env=extension_env, capture_output=True, text=True, timeout=300)
    seconds = time.perf_counter() - t0
    assert result.returncode == 0, result.stdout + result.stderr
    return out, result.stdout, seconds


def test_quick_demo_reports_each_stage(quick_demo):
    out, stdout, seconds = quick_demo
    lines = stdout.splitlines()
    for prefix in ("scene: ", "capture: captured 8 views", "train: step 100/100", "train: trained 100 steps", "evaluate: 1 held-out view",
                   "export: exported", "import: imported", "saved demo.blend", "demo finished in"):
        assert any(line.startswith(prefix) for line in lines), (prefix, stdout)
    assert seconds < 60


def test_quick_demo_writes_valid_artifacts(extension, quick_demo):
    from PIL import Image

    from mlx3d.cameras import Camera
    from mlx3d.splatting import GaussianModel

    out, _, _ = quick_demo
    for name in ("scene.blend", "demo.blend", "trained.ply", "side_by_side.png", "metrics.json", "dataset/transforms.json"):
        assert (out / name).is_file(), name

    # The dataset: 8 views at 32x32, every 8th held out.
    meta = json.loads((out / "dataset" / "transforms.json").read_text())
    assert (meta["w"], meta["h"]) == (RESOLUTION, RESOLUTION) and len(meta["frames"]) == VIEWS
    assert meta["test_filenames"] == ["images/frame_00000.png"]

    # The PLY loads and is finite.
    arrays = read_splat_ply(out / "trained.ply")
    assert arrays.count > 0
    for key in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        assert np.isfinite(getattr(arrays, key)).all(), key

    # metrics.json: finite PSNR/SSIM above a low sanity bar, counts and stage times.
    metrics = json.loads((out / "metrics.json").read_text())
    assert math.isfinite(metrics["psnr"]) and math.isfinite(metrics["ssim"]) and math.isfinite(metrics["psnr_foreground"])
    assert metrics["psnr"] > 15.0 and 0.3 < metrics["ssim"] <= 1.0, metrics
    assert metrics["num_gaussians"] == arrays.count
    assert (metrics["train_views"], metrics["test_views"]) == (VIEWS - 1, 1) and len(metrics["views"]) == 1
    assert metrics["demo"]["quick"] is True and metrics["demo"]["resolution"] == RESOLUTION
    assert set(metrics["seconds"]) == {"scene", "capture", "train", "evaluate", "export_import", "total"}
    assert metrics["side_by_side"]["view"] == metrics["views"][0]["name"] == "frame_00000.png"

    # side_by_side.png: ground truth | render, each at the capture's size.
    pair = np.asarray(Image.open(out / "side_by_side.png").convert("RGB"), dtype=np.float64) / 255.0
    assert pair.shape == (RESOLUTION, 2 * RESOLUTION, 3)
    truth, render = pair[:, :RESOLUTION], pair[:, RESOLUTION:]
    rgba = np.asarray(Image.open(out / "dataset" / "images" / "frame_00000.png"), dtype=np.float64) / 255.0
    on_white = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
    assert np.abs(truth - on_white).max() <= 1.5 / 255
    frame = meta["frames"][0]
    camera = Camera.from_opengl_c2w(np.array(frame["transform_matrix"]), meta["w"], meta["h"], meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    image = np.clip(np.array(GaussianModel.from_arrays(arrays).render(camera, background=(1.0, 1.0, 1.0))["image"]), 0.0, 1.0)
    assert np.abs(render - image).max() <= 1.5 / 255
    psnr = -10.0 * math.log10(np.mean((render - truth) ** 2))
    assert abs(psnr - metrics["side_by_side"]["psnr"]) < 0.5


def test_demo_blend_holds_the_exported_splats(extension, quick_demo):
    out, _, _ = quick_demo
    arrays = read_splat_ply(out / "trained.ply")
    try:
        assert bpy.ops.wm.open_mainfile(filepath=str(out / "demo.blend")) == {"FINISHED"}
        splat_object = extension.addon.splat_object
        objects = [o for o in bpy.context.scene.objects if splat_object.is_splat_object(o)]
        assert [o.name for o in objects] == ["trained"]
        held, _ = splat_object.read_splats(objects[0])
        assert held.count == arrays.count
        assert np.array_equal(held.means, arrays.means) and np.array_equal(held.sh_dc, arrays.sh_dc)
        camera = bpy.context.scene.camera
        assert camera is not None and camera.type == "CAMERA"
    finally:
        bpy.ops.wm.read_homefile(use_empty=True)


def test_demo_refuses_an_output_path_that_is_a_file(extension, extension_env, tmp_path):
    target = tmp_path / "taken"
    target.write_text("")
    result = subprocess.run([sys.executable, _script(extension), "demo", "--out", str(target), "--quick"],
                            env=extension_env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 1 and "blender_splat demo: error: " in result.stderr, result.stdout + result.stderr
    assert target.read_text() == ""
