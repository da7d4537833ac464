"""Train from Photos: cameras solved from a user's own photos (``addon/photos.py``, the ``mlx3d.train_from_photos``
operator, its panel section and ``blender_splat.py poses`` / ``train PHOTOS``), through the installed extension.

The photos are 24 views at 256 px of a textured scene rendered with known cameras by ``tests/photo_capture.py``.
Oracles: those true cameras (after a similarity alignment: a solve fixes neither the frame nor the scale), the
solved dataset read back with ``load_dataset`` (what the scene's cameras and points must hold), Blender's own
camera model read back with ``camera_from_blender`` (the inverse of the conversion under test), and a snapshot of
every data-block (what a cancel or an error must leave as it was).
"""

import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from modal_state import ESC, MOVE, TIMER, OperatorState
from panel_layout import RecordingLayout

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from photo_capture import photo_orbit, similarity_errors  # noqa: E402

bpy = pytest.importorskip("bpy")
pytest.importorskip("pycolmap", reason="solving cameras needs pycolmap (the poses extra; no wheel for this platform)")

from mlx3d.cameras import Camera  # noqa: E402
from mlx3d.datasets import load_dataset  # noqa: E402
from core_marks import above_kernels  # noqa: E402

pytestmark = above_kernels  # the add-on over the camera solve and the trainer: the pure path runs the same code there

COUNT = 24


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """(folder of photos, their true cameras in name order)."""
    folder = tmp_path_factory.mktemp("capture") / "garden"
    return folder, photo_orbit(folder, COUNT, 256)


def snapshot():
    """Every kind of data-block the operator could add or change, the scene's objects, its camera and resolution."""
    kinds = ("objects", "collections", "cameras", "pointclouds", "meshes", "materials", "images", "node_groups")
    scene = bpy.context.scene
    state = {kind: sorted(block.name for block in getattr(bpy.data, kind)) for kind in kinds}
    state["scene objects"] = sorted(o.name for o in scene.objects)
    state["children"] = sorted(c.name for c in scene.collection.children_recursive)
    state["camera"] = scene.camera.name if scene.camera else None
    state["render"] = (scene.render.resolution_x, scene.render.resolution_y, scene.render.pixel_aspect_x)
    return state


def leftovers(folder):
    """Files and folders the solve may have left beside its output (scratch and frame folders start with '.')."""
    return sorted(p.name for p in Path(folder).iterdir() if p.name.startswith("."))


def check_solved(extension, collection, truth, dataset_dir):
    """The collection holds a camera per photo seeing what the dataset's camera sees, close to the true camera,
    and the sparse points with their colours."""
    dataset = load_dataset(dataset_dir)
    scene = bpy.context.scene
    assert (scene.render.resolution_x, scene.render.resolution_y) == (256, 256)  # set to the photos' size
    bpy.context.view_layer.update()
    cameras = sorted((o for o in collection.objects if o.type == "CAMERA"), key=lambda o: o.name)
    assert [o.name for o in cameras] == [f"{i:03d}" for i in range(COUNT)] == [f.name[:-4] for f in dataset.frames]
    seen = [extension.addon.camera.camera_from_blender(o, scene) for o in cameras]
    for got, frame in zip(seen, dataset.frames):
        want = frame.camera
        assert (got.width, got.height) == (want.width, want.height)
        np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], [want.fx, want.fx, want.cx, want.cy], rtol=1e-5)
        np.testing.assert_allclose(got.viewmat, want.viewmat, atol=1e-5)
    rotation, position = similarity_errors(seen, truth)  # about 0.7 degrees; up to 1.4 seen (pycolmap's threads)
    assert rotation < 1.5 and position < 0.02, (rotation, position)
    (points,) = [o for o in collection.objects if o.type == "POINTCLOUD"]
    assert points.name == "garden points" and not extension.addon.splat_object.is_splat_object(points) and points.hide_render
    n = len(dataset.points)
    assert len(points.data.points) == n > 500
    positions = np.empty(3 * n, np.float32)
    points.data.attributes["position"].data.foreach_get("vector", positions)
    np.testing.assert_array_equal(positions.reshape(n, 3), dataset.points)
    colours = np.empty(4 * n, np.float32)
    points.data.attributes["Color"].data.foreach_get("color", colours)
    want = extension.addon.splat_object.srgb_to_linear(dataset.point_colors / 255.0)
    np.testing.assert_allclose(colours.reshape(n, 4)[:, :3], want, atol=1e-6)
    assert points.data.materials[0].name == "MLX3D Sparse Points"


# ------------------------------------------------------------------ the modal operator
def test_modal_operator_solves_adds_cameras_and_points_then_trains(extension, clean_scene, photos, tmp_path):
    folder, truth = photos
    op = extension.addon.operators.MLX3D_OT_train_from_photos
    out = tmp_path / "garden_dataset"
    job = extension.addon.photos.PhotoSolve(folder, out)
    options = dict(method="vanilla", steps=3, max_gaussians=0, sh_degree=1, background="black", update_every=100)
    state = OperatorState(op, job, train=True, **options)
    job.start()
    seen, result = [], {"RUNNING_MODAL"}
    deadline = time.monotonic() + 60
    while result == {"RUNNING_MODAL"} and time.monotonic() < deadline:
        time.sleep(0.05)
        assert op.modal(state, bpy.context, MOVE) == {"PASS_THROUGH"}  # the view can be navigated meanwhile
        result = op.modal(state, bpy.context, TIMER)
        seen.append((job.stage, job.fraction()))
    assert result == {"FINISHED"} and state._session is None
    stages = [s for s, _ in seen if s is not None]
    assert {"features", "matching"} <= set(stages) and stages == sorted(stages, key=list(extension.addon.photos.STAGES).index)
    assert [f for _, f in seen] == sorted(f for _, f in seen)  # the progress bar only moves forwards

    (collection,) = bpy.context.scene.collection.children
    assert collection.name == "garden cameras" and collection["mlx3d_poses"]["dataset"] == str(out)
    check_solved(extension, collection, truth, out)
    assert bpy.context.scene.camera.name == "000"  # the scene had no camera
    level, message = state.reports[0]
    assert level == {"INFO"} and message.startswith(f"solved the cameras of 'garden': {COUNT} of {COUNT} photos registered")
    messages = [m for _, m in state.reports]
    assert f"wrote the dataset {out} (" in messages[1]
    assert any(m.startswith(f"added {COUNT} cameras and ") and m.endswith("points in the collection 'garden cameras'") for m in messages)

    # then Train Splats on the dataset (invoked; without a window it trains to the end at once)
    (trained,) = [o for o in bpy.context.scene.objects if extension.addon.splat_object.is_splat_object(o)]
    record = trained["mlx3d_training"].to_dict()
    assert trained.name == "Trained splats" and trained.users_collection[0] == bpy.context.scene.collection
    assert record["dataset"] == str(out) and record["step"] == record["steps"] == 3 and record["sh_degree"] == 1
    assert len(trained.data.points) >= len(load_dataset(out).points)  # from the solved points (and a backdrop: opaque photos)


def test_esc_cancels_the_solve_and_leaves_everything_as_it_was(extension, clean_scene, photos, tmp_path):
    folder, _ = photos
    op = extension.addon.operators.MLX3D_OT_train_from_photos
    bpy.data.objects.new("Empty", None)  # something there already
    before = snapshot()
    out = tmp_path / "garden_dataset"
    job = extension.addon.photos.PhotoSolve(folder, out)
    state = OperatorState(op, job, train=True)
    job.start()
    deadline = time.monotonic() + 30
    while job.stage not in ("features", "matching") and time.monotonic() < deadline:
        time.sleep(0.02)
        assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert job.stage in ("features", "matching") and job.running
    t0 = time.perf_counter()
    assert op.modal(state, bpy.context, ESC) == {"CANCELLED"}
    assert time.perf_counter() - t0 < 5 and not job.running and state._session is None
    assert state.reports == [({"INFO"}, "solving the cameras of 'garden' was cancelled; nothing was added or written")]
    assert snapshot() == before
    assert not out.exists() and leftovers(tmp_path) == []


def test_bad_input_is_reported_and_changes_nothing(extension, clean_scene, photos, tmp_path):
    folder, _ = photos
    before = snapshot()
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(RuntimeError, match="empty: no photos found"):
        bpy.ops.mlx3d.train_from_photos(source=str(empty), directory=str(tmp_path / "out"))
    with pytest.raises(RuntimeError, match="choose a folder of photos"):
        bpy.ops.mlx3d.train_from_photos()
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "notes.txt").write_text("mine")
    with pytest.raises(RuntimeError, match="taken: already exists and is not an empty folder"):
        bpy.ops.mlx3d.train_from_photos(source=str(folder / "000.png"), directory=str(tmp_path / "taken"))  # a photo: its folder
    assert snapshot() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "taken"]
    assert [p.name for p in (tmp_path / "taken").iterdir()] == ["notes.txt"]


def test_a_dataset_solved_just_before_a_cancel_is_removed(extension, photos, tmp_path):
    """Esc can come after the solve finished but before the operator saw it: the dataset goes too, and a folder
    that existed (empty) before stays, empty."""
    folder, _ = photos
    for out, existed in ((tmp_path / "new", False), (tmp_path / "was_empty", True)):
        if existed:
            out.mkdir()
        job = extension.addon.photos.PhotoSolve(folder, out)
        (out / "sparse").mkdir(parents=True)
        (out / "poses.json").write_text("{}")
        job.result = object()  # as if run() had returned
        job.discard()
        assert job.result is None and (out.is_dir() and not any(out.iterdir()) if existed else not out.exists())


def test_the_default_dataset_folder_is_new(extension, tmp_path):
    photos_mod = extension.addon.photos
    blend = tmp_path / "scene.blend"
    assert photos_mod.default_dataset_folder(tmp_path / "garden", str(blend)) == tmp_path / "garden_dataset"
    (tmp_path / "garden_dataset").mkdir()  # empty: still free
    assert photos_mod.default_dataset_folder(tmp_path / "garden", str(blend)) == tmp_path / "garden_dataset"
    (tmp_path / "garden_dataset" / "x").write_text("")
    (tmp_path / "garden_dataset_2").mkdir()
    (tmp_path / "garden_dataset_2" / "x").write_text("")
    assert photos_mod.default_dataset_folder(tmp_path / "garden", str(blend)) == tmp_path / "garden_dataset_3"
    video = photos_mod.default_dataset_folder(tmp_path / "walk.mp4", "")  # unsaved .blend: the temporary folder
    assert video.parent.parent == Path(__import__("tempfile").gettempdir()) and video.name.startswith("walk_dataset")


@pytest.mark.parametrize("size, shift", [((300, 200), (140.0, 110.0)), ((200, 300), (96.0, 160.5)), ((256, 256), (128.0, 128.0))])
def test_blender_cameras_see_what_the_solved_cameras_see(extension, clean_scene, size, shift):
    """``set_blender_camera`` is the inverse of ``camera_from_blender`` (landscape, portrait, square; principal point off centre)."""
    camera_mod = extension.addon.camera
    width, height = size
    want = Camera.look_at(eye=(1.0, -3.0, 2.0), at=(0.1, 0.2, 0.3), up=(0, 0, 1), width=width, height=height, fov=55.0)
    want = Camera(width, height, 0.9 * want.fx, 0.9 * want.fx, shift[0], shift[1], want.viewmat, model="opencv", dist=(0.01, 0, 0, 0, 0))
    obj = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    bpy.context.scene.collection.objects.link(obj)
    assert camera_mod.set_blender_camera(obj, want) == ["lens distortion"]
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    bpy.context.view_layer.update()
    got = camera_mod.camera_from_blender(obj, scene)
    np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], [want.fx, want.fy, want.cx, want.cy], rtol=1e-5)
    np.testing.assert_allclose(got.viewmat, want.viewmat, atol=1e-6)


# ------------------------------------------------------------------ panel, docs and headless
def test_panel_section_passes_its_settings_and_the_training_ones(extension, clean_scene):
    settings = clean_scene.mlx3d_splats
    settings.photos_source, settings.photos_dir, settings.photos_matching, settings.photos_fps = "//photos", "//ds", "sequential", 3.0
    settings.train_steps, settings.train_method, settings.train_sh_degree, settings.train_update_every = 7000, "mcmc", 2, 250
    panel = extension.addon.panel.VIEW3D_PT_mlx3d_photos
    assert panel.bl_parent_id == "VIEW3D_PT_mlx3d_splats" and panel.bl_label == "Train from Photos"
    log = []
    panel.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene, active_object=None))
    assert [entry[1] for entry in log if entry[0] == "prop"] == ["photos_source", "photos_dir", "photos_matching", "photos_fps"]
    (_, idname, op), = [entry for entry in log if entry[0] == "operator"]
    assert idname == "mlx3d.train_from_photos"
    assert (op.source, op.directory, op.matching, op.fps) == ("//photos", "//ds", "sequential", 3.0)
    assert (op.steps, op.method, op.sh_degree, op.update_every, op.max_gaussians, op.background) == (7000, "mcmc", 2, 250, 0, "black")


def test_the_guide_lists_every_operator(extension):
    """docs/guides/blender.md's operator table names every operator of the add-on with its label and bpy.ops id."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "guides" / "blender.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| ") and "`" in line]
    for cls in extension.addon.operators.CLASSES:
        if issubclass(cls, bpy.types.Operator):
            assert any(row.startswith(f"| {cls.bl_label} | `{cls.bl_idname}` |") for row in rows), cls.bl_idname


def test_headless_poses_then_train_on_the_photos(extension, photos, tmp_path, capsys):
    """``poses`` solves into --out and adds the cameras and points (saved with --save-blend); ``train PHOTOS`` takes
    its dataset from OUT's name + ``_poses`` beside OUT, reusing the solve found there (each solve costs seconds)."""
    import importlib

    folder, truth = photos
    headless = importlib.import_module(extension.__name__ + ".addon.headless")
    dataset, blend = tmp_path / "garden_poses", tmp_path / "poses.blend"
    assert headless.main(["poses", str(folder), "--out", str(dataset), "--save-blend", str(blend)]) == 0
    out, err = capsys.readouterr()
    assert f"solved the cameras of 'garden': {COUNT} of {COUNT} photos registered" in out and f"wrote the dataset {dataset} (" in out
    stages = [line.split(":")[1].strip() for line in err.splitlines() if line.startswith("poses: ")]
    assert [s for i, s in enumerate(stages) if i == 0 or stages[i - 1] != s] == ["photos", "features", "matching", "mapping"]
    assert blend.is_file()
    check_solved(extension, bpy.data.collections["garden cameras"], truth, dataset)

    ply = tmp_path / "garden.ply"
    assert headless.main(["train", str(folder), "--steps", "2", "--sh-degree", "0", "--out", str(ply)]) == 0
    out, _ = capsys.readouterr()
    assert f"{folder}: photos without poses; using the cameras solved earlier in {dataset}" in out
    assert "trained 2 steps (vanilla)" in out and ply.is_file()
    assert len(bpy.data.collections["garden cameras"].objects) == COUNT + 1  # the cameras and points are in the scene too

    (tmp_path / "nothing").mkdir()
    assert headless.main(["train", str(tmp_path / "nothing"), "--steps", "1", "--out", str(tmp_path / "n.ply")]) == 1
    err = capsys.readouterr().err
    assert "no dataset found" in err and "and it holds no photos to solve cameras from" in err
    parser = headless.build_parser()
    args = parser.parse_args(["train", "v.mp4", "--out", "o.ply", "--poses-out", "d", "--matching", "sequential", "--fps", "3"])
    assert (args.poses_out, args.matching, args.fps, args.max_image_size) == ("d", "sequential", 3.0, 1600)
