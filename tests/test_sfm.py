"""Cameras solved from photos (``mlx3d.sfm``, ``mlx3d poses``): against the cameras the photos were rendered with."""

from __future__ import annotations

import builtins
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from core_marks import runs_no_kernel
from mlx3d.cameras import Camera
from mlx3d.datasets import load_dataset
from mlx3d.sfm import PosesError, choose_matching, extract_frames, solve_capture, solve_poses, upright
from mlx3d.sfm.solve import EXHAUSTIVE_MAX, _copy_photos
from mlx3d.sfm.video import sharpness
from mlx3d.training import TrainerConfig
from mlx3d.training.exposure import EXPOSURE_SPREAD, exposure_spread, photo_gains
from mlx3d.training.initial import initial_state
from photo_capture import photo_orbit, similarity_errors

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the poses extra) is not installed")
pytestmark = runs_no_kernel

COUNT = 24


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    """24 photos of the test scene on two rings, their true cameras, and the dataset solved from them."""
    root = tmp_path_factory.mktemp("orbit")
    cameras = photo_orbit(root / "photos", COUNT, 256)
    reports = []
    result = solve_poses(root / "photos", root / "data", progress=lambda *report: reports.append(report))
    result.reports = reports
    return root, cameras, result


def _solved(data: Path, names):
    by_name = {f.name: f.camera for f in load_dataset(data).frames}
    return [by_name[n] for n in names]


def test_solve_places_every_photo_of_an_orbit_where_it_was_taken(orbit):
    root, truth, result = orbit
    names = [f"{i:03d}.png" for i in range(COUNT)]
    assert result.registered == names and result.unregistered == [] and result.photos == COUNT
    assert result.reprojection_error < 1.0 and result.points > 300
    rotation, position = similarity_errors(_solved(root / "data", names), truth)
    # 1 px is 0.21 degrees at this size; bench/poses.py measures 480-px orbits (within 0.5 degrees there)
    assert rotation < 2.0 and position < 0.015
    # the true focal length (256 px wide, 50 degrees) within 2%
    assert result.focal == pytest.approx(128 / math.tan(math.radians(25)), rel=0.02)
    assert json.loads((root / "data" / "poses.json").read_text())["registered"] == names
    assert sorted(p.name for p in (root / "data" / "images").iterdir()) == names


def test_exposure_spread_reads_each_photos_gain_from_the_solve(orbit, tmp_path):
    """Photos of one exposure measure below the threshold, so 'auto' leaves the colour grid off;
    re-exposing some of the solved photos (gain and white balance) is read back from the tracks,
    at any loading factor, and turns the grid on."""
    data = tmp_path / "data"
    shutil.copytree(orbit[0] / "data", data)
    plain = load_dataset(data)
    assert exposure_spread(plain) < EXPOSURE_SPREAD / 3
    assert initial_state(plain, TrainerConfig(), sh_degree=0).config.bilateral_grid is False
    gains = {1: (0.6, 0.6, 0.6), 5: (1.25, 1.1, 0.9), 10: (0.8, 0.9, 1.0), 19: (0.7, 0.75, 0.8)}
    for i, gain in gains.items():
        path = data / "images" / plain.frames[i].name
        rgb = np.asarray(Image.open(path).convert("RGB"), np.float64)
        Image.fromarray(np.clip(np.round(rgb * gain), 0, 255).astype(np.uint8)).save(path)
    for factor in (1, 2):
        dataset = load_dataset(data, factor=factor)
        measured = photo_gains(dataset)
        assert sorted(measured) == dataset.train  # every training photo sees enough points
        base = np.median([g for i, g in measured.items() if i not in gains], axis=0)
        for i, gain in gains.items():
            np.testing.assert_allclose(measured[i] - base, np.log(gain), atol=0.03, err_msg=f"photo {i}")
        assert exposure_spread(dataset) > EXPOSURE_SPREAD
    start = initial_state(dataset, TrainerConfig(), sh_degree=0)
    assert start.config.bilateral_grid is True
    assert any(note.startswith("bilateral grid: 16x16x8") and "exposure spread" in note for note in start.notes)
    assert initial_state(dataset, TrainerConfig(bilateral_grid=False), sh_degree=0).config.bilateral_grid is False


def test_progress_goes_forward_through_each_stage_to_its_end(orbit):
    reports = orbit[2].reports
    assert [stage for stage, _, _ in reports if stage != "mapping"] == sorted(
        (stage for stage, _, _ in reports if stage != "mapping"), key=["photos", "features", "matching"].index)
    for stage, total in (("photos", COUNT), ("features", COUNT), ("matching", COUNT * (COUNT - 1) // 2), ("mapping", COUNT)):
        done = [d for s, d, t in reports if s == stage and t == total]
        assert done and done[-1] == total and len(done) == len([r for r in reports if r[0] == stage])
        if stage != "mapping":  # the mapper runs three times (its three starts), each from the beginning
            assert done == sorted(done) and len(set(done)) >= 5


def test_solved_capture_is_upright_centred_and_scaled(orbit):
    root, truth, _ = orbit
    solved = load_dataset(root / "data")
    centres = np.array([f.camera.center for f in solved.frames])
    ups = np.array([-f.camera.R[1] for f in solved.frames])
    # the photos were taken with +Z up, looking at one point 4 units away on two level rings
    assert np.degrees(np.arccos(ups.mean(0)[2] / np.linalg.norm(ups.mean(0)))) < 1.0
    for ring, elevation in ((0, 20.0), (1, 40.0)):  # level, at their heights above what the cameras look at
        assert np.ptp(centres[ring::2, 2]) < 0.04 * 4.0
        assert centres[ring::2, 2].mean() == pytest.approx(4.0 * math.sin(math.radians(elevation)), abs=0.04 * 4.0)
    assert np.median(np.linalg.norm(centres, axis=1)) == pytest.approx(4.0, rel=0.02)
    # the solved points sit on the scene: the ground plane is level (z spread of its points)
    pts = solved.points
    assert pts is not None and len(pts) > 300


def test_upright_recovers_a_ring_moved_by_any_similarity():
    ring = [Camera.look_at(eye=(3 * math.cos(a), 3 * math.sin(a), 1.0), at=(0, 0, 0.2), up=(0, 0, 1), fov=50)
            for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)]
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    moved = []
    for c in ring:  # x' = s q x + t: the camera's world-to-camera pose becomes [R q^T | ...] with centre s q C + t
        centre = 0.37 * q @ c.center + np.array([5.0, -2.0, 9.0])
        view = np.eye(4)
        view[:3, :3] = c.R @ q.T
        view[:3, 3] = -view[:3, :3] @ centre
        moved.append(Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, view))
    m = upright(moved)
    centres = np.array([m[:3, :3] @ c.center + m[:3, 3] for c in moved])
    assert np.ptp(centres[:, 2]) < 1e-6  # the ring is level again
    # what they look at is the origin (within look_at_centre's small pull towards their centroid), 4 units away
    assert np.allclose(np.linalg.norm(centres[:, :2], axis=1), 4.0 * 3 / math.hypot(3, 0.8), rtol=1e-3)
    assert centres[:, 2].mean() == pytest.approx(4.0 * 0.8 / math.hypot(3, 0.8), rel=1e-3)
    new_up = (m[:3, :3] @ q @ np.array([0, 0, 1.0]))
    assert new_up / np.linalg.norm(new_up) == pytest.approx([0, 0, 1], abs=1e-9)


def test_cancel_leaves_nothing(orbit, tmp_path):
    root, _, _ = orbit
    seen = []

    def stop():
        return "features" in seen

    with pytest.raises(KeyboardInterrupt):
        solve_poses(root / "photos", tmp_path / "data", progress=lambda stage, done, total: seen.append(stage),
                    should_stop=stop)
    assert list(tmp_path.iterdir()) == []


def test_unrelated_photos_are_refused_and_nothing_is_written(tmp_path):
    from PIL import Image

    photos = tmp_path / "noise"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):  # smooth random blobs: features, but no two photos show the same thing
        small = rng.integers(0, 255, (8, 8, 3), dtype=np.uint8)
        Image.fromarray(small).resize((160, 160), Image.BICUBIC).save(photos / f"{i}.png")
    with pytest.raises(PosesError, match=r"only \d of 4 photos could be placed"):
        solve_poses(photos, tmp_path / "data")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise"]


def test_bad_inputs_are_named(tmp_path):
    with pytest.raises(PosesError, match="not a folder of photos"):
        solve_poses(tmp_path / "missing", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(PosesError, match="no photos found"):
        solve_poses(tmp_path / "empty", tmp_path / "out")
    two = tmp_path / "two"
    photo_orbit(two, 2, 64)
    with pytest.raises(PosesError, match="needs at least 3"):
        solve_poses(two, tmp_path / "out")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "keep.txt").write_text("mine")
    photo_orbit(tmp_path / "three", 3, 64)
    with pytest.raises(PosesError, match="not an empty folder"):
        solve_poses(tmp_path / "three", tmp_path / "taken")
    assert (tmp_path / "taken" / "keep.txt").read_text() == "mine"
    with pytest.raises(PosesError, match="matching must be one of"):
        choose_matching("vocab", 10, False)


def test_matching_follows_the_capture():
    assert choose_matching("auto", EXHAUSTIVE_MAX, False) == "exhaustive"
    assert choose_matching("auto", EXHAUSTIVE_MAX + 1, False) == "sequential"
    assert choose_matching("auto", 10, True) == "sequential"
    assert choose_matching("exhaustive", 500, True) == "exhaustive"


def test_exif_rotation_is_applied_to_the_copies_and_webp_becomes_png(tmp_path):
    from PIL import Image

    src = tmp_path / "src"
    src.mkdir()
    pixels = np.zeros((20, 40, 3), np.uint8)
    pixels[:, :5] = 255  # a white band on the left of the stored pixels
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 degrees clockwise to display"
    exif[0xA405] = 28  # focal length in 35 mm film: kept in the rotated copy
    Image.fromarray(pixels).save(src / "a.jpg", exif=exif.tobytes(), quality=100)
    Image.fromarray(pixels).save(src / "b.jpg", quality=100)
    Image.fromarray(pixels).save(src / "c d.webp", lossless=True)  # pycolmap reads no WebP: copied as PNG
    copied = _copy_photos(src, ["a.jpg", "b.jpg", "c d.webp"], tmp_path / "images", None, None)
    assert copied == [("a.jpg", (20, 40)), ("b.jpg", (40, 20)), ("c_d.webp.png", (40, 20))]
    with Image.open(tmp_path / "images" / "c_d.webp.png") as im:
        assert im.format == "PNG" and (np.asarray(im) == pixels).all()
    with Image.open(tmp_path / "images" / "a.jpg") as im:
        shown = np.asarray(im)
        assert im.getexif().get(0x0112, 1) == 1
        assert im.getexif().get_ifd(0x8769).get(0xA405, im.getexif().get(0xA405)) == 28
    assert shown.shape == (40, 20, 3) and shown[:5].mean() > 200 and shown[-5:].mean() < 50  # the band is on top
    assert (tmp_path / "images" / "b.jpg").read_bytes() == (src / "b.jpg").read_bytes()


def test_without_pycolmap_the_error_says_how_to_get_it(monkeypatch, tmp_path):
    real_import = builtins.__import__

    def no_pycolmap(name, *args, **kw):
        if name == "pycolmap":
            raise ImportError("No module named 'pycolmap'")
        return real_import(name, *args, **kw)

    monkeypatch.delitem(sys.modules, "pycolmap")
    monkeypatch.setattr(builtins, "__import__", no_pycolmap)
    with pytest.raises(PosesError, match=r"mlx3d-splat\[poses\].*COLMAP"):
        solve_poses(tmp_path, tmp_path / "out")


@pytest.fixture
def av():
    return pytest.importorskip("av", reason="PyAV (the poses extra) is not installed")


def _write_video(av, path: Path, frames, rate: int):
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=rate)
        stream.width, stream.height = frames[0].shape[1], frames[0].shape[0]
        stream.pix_fmt = "yuv420p"
        stream.bit_rate = 4_000_000
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def test_video_keeps_the_sharpest_frame_of_each_window(av, orbit, tmp_path):
    from PIL import Image, ImageFilter

    root, _, _ = orbit
    photos = sorted((root / "photos").iterdir())[:8]
    frames = []
    for i, p in enumerate(photos):  # four frames per photo at 8 fps (2 fps kept): one sharp, three blurred
        with Image.open(p) as im:
            for k in range(4):
                frames.append(np.asarray(im.filter(ImageFilter.GaussianBlur(3)) if k != i % 4 else im.convert("RGB")))
    _write_video(av, tmp_path / "walk.mp4", frames, 8)
    names = extract_frames(tmp_path / "walk.mp4", tmp_path / "frames", fps=2.0)
    assert names == [f"frame_{n:05d}.jpg" for n in range(8)]
    for name, p in zip(names, photos):
        with Image.open(tmp_path / "frames" / name) as got, Image.open(p) as sharp:
            a, b = np.asarray(got, np.float32), np.asarray(sharp.convert("RGB"), np.float32)
            assert np.abs(a - b).mean() < 8  # the sharp frame, not a blurred one
            assert sharpness(a.mean(2)) > 0.5 * sharpness(b.mean(2))


def test_video_solves_like_its_photos(av, orbit, tmp_path):
    root, truth, _ = orbit
    photos = sorted((root / "photos").iterdir())
    from PIL import Image

    frames = [np.asarray(Image.open(p).convert("RGB")) for p in photos]
    _write_video(av, tmp_path / "orbit.mp4", frames, 4)
    stages = set()
    result = solve_capture(tmp_path / "orbit.mp4", tmp_path / "data", fps=4.0, blur_ratio=0.0,
                           progress=lambda stage, done, total: stages.add(stage))
    assert result.matching == "sequential" and len(result.registered) == COUNT
    assert stages == {"frames", "photos", "features", "matching", "mapping"}
    names = [f"frame_{n:05d}.jpg" for n in range(COUNT)]
    rotation, position = similarity_errors(_solved(tmp_path / "data", names), truth)
    assert rotation < 1.5 and position < 0.02
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "orbit.mp4"]


def test_cli_trains_on_photos_by_solving_their_cameras_first(orbit, tmp_path, capsys):
    from mlx3d.cli import main
    from mlx3d.splatting import GaussianModel

    root, _, _ = orbit
    out = tmp_path / "model.ply"
    assert main(["train", str(root / "photos"), "--out", str(out), "--steps", "10", "--sh-degree", "0"]) == 0
    text = capsys.readouterr()
    assert f"solving the cameras into {tmp_path / 'model_poses'}" in text.out
    assert f"{COUNT} of {COUNT} photos registered" in text.out and "poses: features" in text.err
    assert len(GaussianModel.load(str(out))) > 0
    assert len(load_dataset(tmp_path / "model_poses")) == COUNT
    # a second run reuses the solved cameras
    assert main(["train", str(root / "photos"), "--out", str(out), "--steps", "5", "--sh-degree", "0"]) == 0
    assert "using the cameras solved earlier" in capsys.readouterr().out
    # mlx3d poses refuses to overwrite, and names what is wrong
    assert main(["poses", str(root / "photos"), "--out", str(tmp_path / "model_poses")]) == 1
    assert "already exists and is not an empty folder" in capsys.readouterr().err
    assert main(["poses", str(tmp_path / "nothing"), "--out", str(tmp_path / "p")]) == 1
    assert "not a folder of photos" in capsys.readouterr().err
