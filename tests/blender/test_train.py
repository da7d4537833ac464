"""Training splats on a dataset inside Blender (``addon/train.py``, the ``mlx3d.train`` operator, the panel and
``blender_splat.py train``), through the installed extension.

The dataset is captured once per module from a small Blender scene (8 views of a cube and a sphere, 32x32 pixels,
2000 surface points). Oracles: the number of points in the dataset's point file (the Gaussian count before any
densification, and the cap's subsample), the model's own arrays (what the scene object must hold, bit for bit), the
densification schedule of the trainer (which steps change the count), and the PLY read back with ``read_splat_ply``.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest
from node_trees import node_tree
from modal_state import ESC, KEY, MOVE, OperatorState, TIMER
from panel_layout import RecordingLayout

from mlx3d.io import read_splat_ply
from core_marks import above_kernels

pytestmark = above_kernels  # the add-on over the trainer: the pure path runs the same code there

bpy = pytest.importorskip("bpy")
pytest.importorskip("PIL", reason="mlx3d.datasets decodes images with Pillow")

NUM_POINTS = 2000
# Densification fires in a short run: every 20 steps from step 20 on, with any screen-space gradient.
DENSIFY_SOON = dict(densify_from=10, densify_every=20, densify_grad_threshold=1e-7)


def build_scene():
    """A white world, a blue cube at the origin and a red sphere above it."""
    scene = bpy.context.scene
    world = bpy.data.worlds.new("World")
    scene.world = world
    node_tree(world).nodes["Background"].inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    for add, kwargs, rgb in [(bpy.ops.mesh.primitive_cube_add, dict(size=1.0, location=(0, 0, 0)), (0.05, 0.05, 0.8)),
                             (bpy.ops.mesh.primitive_uv_sphere_add, dict(radius=0.4, location=(0, 0, 1), segments=24, ring_count=12), (0.8, 0.05, 0.05))]:
        add(**kwargs)
        material = bpy.data.materials.new("m")
        node_tree(material).nodes["Principled BSDF"].inputs["Base Color"].default_value = (*rgb, 1.0)
        bpy.context.active_object.data.materials.append(material)
    return scene


@pytest.fixture(scope="module")
def dataset(extension, tmp_path_factory):
    assert bpy.ops.wm.read_homefile(use_empty=True) == {"FINISHED"}
    build_scene()
    out = tmp_path_factory.mktemp("train") / "dataset"
    info, _ = extension.addon.capture.capture_dataset(out, num_views=8, elevations_deg=(10, 40), resolution=(32, 32), samples=4,
                                                      num_points=NUM_POINTS)
    assert info["frames"] == 8 and info["num_points"] == NUM_POINTS
    return out


def splat_objects():
    return [o for o in bpy.context.scene.objects if o.type == "POINTCLOUD"]


def assert_holds_model(extension, obj, model):
    """The object's splats are the model's raw parameters, bit for bit, with an identity transform."""
    arrays, _ = extension.addon.splat_object.read_splats(obj)
    expected = model.to_arrays()
    assert arrays.count == len(model)
    for key in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        assert np.array_equal(getattr(arrays, key), getattr(expected, key)), key
    assert np.array_equal(np.array(obj.matrix_world), np.eye(4))


# ------------------------------------------------------------------ the operator
def test_operator_trains_into_a_splat_object_and_the_loss_goes_down(extension, clean_scene, dataset):
    train = extension.addon.train
    clean_scene.mlx3d_splats.capture_dir = str(dataset)  # no directory given: the panel's dataset folder
    t0 = time.perf_counter()
    assert bpy.ops.mlx3d.train(steps=60, update_every=1000) == {"FINISHED"}
    seconds = time.perf_counter() - t0
    (obj,) = splat_objects()
    assert obj.name == "Trained splats" and bpy.context.active_object == obj and obj.select_get()
    assert np.array_equal(np.array(obj.matrix_world), np.eye(4))
    record = obj[train.INFO_KEY].to_dict()
    # No densification before step 500: one Gaussian per dataset point.
    assert len(obj.data.points) == record["num_gaussians"] == NUM_POINTS
    assert record["step"] == record["steps"] == 60 and record["method"] == "vanilla" and record["dataset"] == str(dataset)
    assert record["loss"] < 0.8 * record["initial_loss"], record
    assert 10 < record["psnr"] < 60
    assert seconds < 30
    arrays, _ = extension.addon.splat_object.read_splats(obj)
    assert arrays.sh_degree == 3

    # Without a window (background), invoking trains to the end at once; a second run makes a second object.
    assert bpy.ops.mlx3d.train("INVOKE_DEFAULT", directory=str(dataset), steps=3, sh_degree=1, max_gaussians=500) == {"FINISHED"}
    second = bpy.context.active_object
    assert second != obj and second.name == "Trained splats.001" and len(second.data.points) == 500
    assert second[train.INFO_KEY]["step"] == 3 and extension.addon.splat_object.read_splats(second)[0].sh_degree == 1


def test_session_updates_the_object_every_update_every_steps(extension, clean_scene, dataset):
    train = extension.addon.train
    session = train.TrainSession(dataset, steps=60, update_every=20, sh_degree=1, **DENSIFY_SOON)
    assert session.object is None and not splat_objects()  # nothing in the scene until the first update
    snapshots = {}  # step -> the model's arrays when the object was updated
    update_object = session.update_object

    def recording_update():
        snapshots[session.step_count] = session.model.to_arrays()
        return update_object()

    session.update_object = recording_update
    seen = []
    while not session.done:
        assert session.step(7) <= 7
        obj = session.object
        seen.append((session.step_count, session.object_step, None if obj is None else len(obj.data.points), len(session.model)))
        if session.step_count == 42:  # densified and updated at 40, two plain steps since: the object still holds step 40
            arrays, _ = extension.addon.splat_object.read_splats(obj)
            assert np.array_equal(arrays.means, snapshots[40].means) and np.array_equal(arrays.sh_rest, snapshots[40].sh_rest)
            assert not np.array_equal(arrays.means, session.model.to_arrays().means)
    assert sorted(snapshots) == [20, 40, 60]
    assert [s[0] for s in seen] == [7, 14, 21, 28, 35, 42, 49, 56, 60]
    assert [s[1] for s in seen] == [None, None, 20, 20, 20, 40, 40, 40, 60]
    counts = {s[1]: s[2] for s in seen if s[1] is not None}
    assert NUM_POINTS < counts[20] < counts[40] < counts[60], counts  # densification at 20, 40 and 60 grew the model
    assert [s[2] == s[3] for s in seen][2:] == [True] * 7  # densification only on multiples of 20, where the object updates
    (obj,) = splat_objects()
    assert obj.name == "Trained splats" and obj[train.INFO_KEY]["step"] == 60
    status = session.status()
    assert status["step"] == 60 and status["num_gaussians"] == counts[60] and status["eta_seconds"] == 0.0
    assert status["steps_per_second"] > 0 and status["loss"] < status["initial_loss"]
    line = train.format_status(status)
    assert line.startswith("step 60/60  loss ") and f"{counts[60]:,} Gaussians" in line and "steps/s  ETA 0:00" in line
    result, messages = session.finish()
    assert result == obj and messages[0].startswith("trained 60 steps (vanilla) on 7 views of ")
    assert_holds_model(extension, obj, session.model)


def test_modal_trains_per_tick_and_esc_keeps_the_partial_result(extension, clean_scene, dataset):
    train = extension.addon.train
    op = extension.addon.operators.MLX3D_OT_train
    session = train.TrainSession(dataset, steps=10_000, update_every=1000, sh_degree=0)
    session.update_object()  # as invoke does: the initial Gaussians at once
    state = OperatorState(op, session)
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    first = session.step_count
    assert 1 <= first < 10_000
    assert op.modal(state, bpy.context, MOVE) == {"PASS_THROUGH"}  # the view can be navigated meanwhile
    assert op.modal(state, bpy.context, KEY) == {"RUNNING_MODAL"}  # other input is held back
    assert session.step_count == first
    t0 = time.perf_counter()
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert time.perf_counter() - t0 < 1.0 and session.step_count > first
    steps = session.step_count
    assert op.modal(state, bpy.context, ESC) == {"FINISHED"}  # the kept object gets its undo step
    assert state._session is None
    (obj,) = splat_objects()
    assert obj[train.INFO_KEY]["step"] == steps and bpy.context.active_object == obj
    assert_holds_model(extension, obj, session.model)
    level, message = state.reports[0]
    assert level == {"INFO"} and message.startswith(f"trained {steps:,} of 10,000 steps (cancelled)") and "result in 'Trained splats'" in message


def test_blender_ending_the_operator_leaves_the_scene_alone(extension, clean_scene, dataset):
    op = extension.addon.operators.MLX3D_OT_train
    session = extension.addon.train.TrainSession(dataset, steps=100, update_every=1000, sh_degree=0)
    state = OperatorState(op, session)
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    op.cancel(state, bpy.context)  # e.g. another file is opened: no object is made or changed then
    assert state._session is None and not splat_objects() and not state.reports


def test_modal_runs_to_the_end(extension, clean_scene, dataset):
    op = extension.addon.operators.MLX3D_OT_train
    session = extension.addon.train.TrainSession(dataset, steps=4, update_every=2, sh_degree=0)
    state = OperatorState(op, session, TICK_SECONDS=0.0)  # one step per tick
    results = [op.modal(state, bpy.context, TIMER) for _ in range(4)]
    assert results == [{"RUNNING_MODAL"}] * 3 + [{"FINISHED"}]
    assert state.reports[0][1].startswith("trained 4 steps") and state._session is None


def test_a_training_error_keeps_the_last_good_state(extension, clean_scene, dataset):
    train = extension.addon.train
    from mlx3d.training import TrainingError

    op = extension.addon.operators.MLX3D_OT_train
    session = train.TrainSession(dataset, steps=50, update_every=2, sh_degree=0)
    good_step = session.trainer.step_batch  # what fit calls each step

    def failing_step(*args, **kwargs):
        if session.trainer.step_count == 3:
            raise TrainingError("step 4: the loss or a gradient is not finite (loss nan); parameters left at the last good step")
        return good_step(*args, **kwargs)

    session.trainer.step_batch = failing_step
    state = OperatorState(op, session, TICK_SECONDS=60.0)  # the error comes within the first tick
    assert op.modal(state, bpy.context, TIMER) == {"FINISHED"}
    assert state._session is None
    (obj,) = splat_objects()
    assert obj[train.INFO_KEY]["step"] == 3
    assert_holds_model(extension, obj, session.model)
    level, message = state.reports[0]
    assert level == {"ERROR"} and "training stopped at step 4 of 50: step 4: the loss" in message and "(step 3) in 'Trained splats'" in message


def test_bad_input_is_a_clear_error_and_leaves_the_scene_alone(extension, clean_scene, dataset, tmp_path):
    train = extension.addon.train
    with pytest.raises(RuntimeError, match="nope: dataset not found"):
        bpy.ops.mlx3d.train(directory=str(tmp_path / "nope"), steps=2)
    (tmp_path / "empty").mkdir()
    with pytest.raises(RuntimeError, match="empty: no dataset found"):
        bpy.ops.mlx3d.train(directory=str(tmp_path / "empty"), steps=2)
    with pytest.raises(RuntimeError, match="choose a dataset folder"):
        bpy.ops.mlx3d.train(steps=2)  # no folder, none in the panel either
    with pytest.raises(train.TrainError, match="not available"):
        train.TrainSession(dataset, steps=2, method="3dgs-fast")
    with pytest.raises(train.TrainError, match="TrainerConfig fields"):
        train.TrainSession(dataset, steps=2, densify_sometimes=True)
    with pytest.raises(train.TrainError, match="folder .* does not exist"):
        train.train_dataset(dataset, steps=2, out_ply=tmp_path / "missing" / "x.ply")
    assert not splat_objects() and not bpy.data.pointclouds


def test_a_dataset_without_points_starts_from_random_points(extension, clean_scene, dataset, tmp_path):
    train = extension.addon.train
    bare = tmp_path / "bare"  # a nerfstudio dataset without a point file
    shutil.copytree(dataset / "images", bare / "images")
    meta = json.loads((dataset / "transforms.json").read_text())
    del meta["ply_file_path"]
    (bare / "transforms.json").write_text(json.dumps(meta))
    obj, messages = train.train_dataset(bare, steps=2, sh_degree=0, init_random_points=500)
    assert len(obj.data.points) == 500
    assert any("500 random points" in m and "the dataset has none" in m for m in messages)


def test_train_dataset_stops_early_and_writes_the_result(extension, clean_scene, dataset, tmp_path):
    train = extension.addon.train
    seen = []
    obj, messages = train.train_dataset(dataset, steps=100, sh_degree=0, out_ply=tmp_path / "out.ply",
                                        progress=lambda done, total, status: seen.append((done, total, status["step"])),
                                        should_stop=lambda: len(seen) >= 5)
    assert seen == [(i, 100, i) for i in range(1, 6)]
    assert messages[0].startswith("trained 5 of 100 steps (cancelled)")
    assert any(m.startswith("test PSNR ") and m.endswith("on 1 held-out view") for m in messages)
    arrays = read_splat_ply(tmp_path / "out.ply")
    assert arrays.count == len(obj.data.points) == NUM_POINTS and arrays.sh_degree == 0
    assert messages[-1] == f"wrote {NUM_POINTS:,} Gaussians (SH degree 0) to {tmp_path / 'out.ply'}"


def test_status_printer_prints_every_five_percent(extension):
    import io

    train = extension.addon.train
    stream = io.StringIO()
    printer = train.StatusPrinter(stream)
    status = dict(step=0, steps=200, loss=0.1, psnr=20.0, num_gaussians=1234, steps_per_second=10.0, eta_seconds=95.0)
    for done in range(1, 201):
        printer(done, 200, {**status, "step": done})
    lines = stream.getvalue().splitlines()
    assert len(lines) == 20
    assert lines[0] == "train:   5.0%  step 10/200  loss 0.1000  PSNR 20.00 dB  1,234 Gaussians  10.0 steps/s  ETA 1:35"
    assert lines[-1].startswith("train: 100.0%  step 200/200")


# ------------------------------------------------------------------ headless and panel
def test_headless_train(extension, extension_env, dataset, tmp_path):
    script = os.path.join(os.path.dirname(extension.__file__), "addon", "blender_splat.py")
    out, blend = tmp_path / "out.ply", tmp_path / "trained.blend"
    args = ["train", str(dataset), "--method", "vanilla", "--steps", "20", "--out", str(out), "--max-gaussians", "1500",
            "--sh-degree", "1", "--background", "white", "--save-blend", str(blend)]
    result = subprocess.run([sys.executable, script, *args], env=extension_env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    arrays = read_splat_ply(out)
    assert arrays.count == 1500 and arrays.sh_degree == 1 and np.isfinite(arrays.means).all()
    assert "trained 20 steps (vanilla) on 7 views" in result.stdout and "started from 1,500 of the dataset's 2,000 points" in result.stdout
    assert f"wrote 1,500 Gaussians (SH degree 1) to {out}" in result.stdout and blend.is_file()
    progress = [line for line in result.stderr.splitlines() if line.startswith("train:")]
    assert len(progress) == 20 and progress[-1].startswith("train: 100.0%  step 20/20  loss ") and "PSNR" in progress[-1]
    assert "1,500 Gaussians" in progress[-1] and "steps/s  ETA 0:00" in progress[-1]

    bad = subprocess.run([sys.executable, script, "train", str(tmp_path / "nope"), "--steps", "5", "--out", str(tmp_path / "x.ply")],
                         env=extension_env, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 1 and "blender_splat train: error: " in bad.stderr and "nope: dataset not found" in bad.stderr
    assert not (tmp_path / "x.ply").exists()


def test_panel_train_section_passes_its_settings(extension, clean_scene):
    settings = clean_scene.mlx3d_splats
    settings.capture_dir, settings.train_steps, settings.train_max_gaussians = "//dataset", 7000, 50_000
    settings.train_sh_degree, settings.train_background, settings.train_update_every = 2, "random", 250
    panel = extension.addon.panel.VIEW3D_PT_mlx3d_train
    assert panel.bl_parent_id == "VIEW3D_PT_mlx3d_splats" and panel.bl_label == "Train"  # a section below the main panel
    log = []
    panel.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene, active_object=None))
    props = [entry[1] for entry in log if entry[0] == "prop"]
    assert props == ["capture_dir", "train_method", "train_steps", "train_max_gaussians", "train_sh_degree", "train_background", "train_update_every"]
    (_, idname, op), = [entry for entry in log if entry[0] == "operator"]
    assert idname == "mlx3d.train"
    assert (op.directory, op.method, op.steps, op.max_gaussians, op.sh_degree, op.background, op.update_every) == (
        "//dataset", "vanilla", 7000, 50_000, 2, "random", 250)


def test_mcmc_is_offered_and_trains(extension, clean_scene, dataset):
    train = extension.addon.train
    assert "mcmc" in train.METHODS and "mcmc" in [item[0] for item in train.METHOD_ITEMS]
    session = train.TrainSession(dataset, steps=30, method="mcmc", max_gaussians=2500, densify_from=5, densify_every=10)
    session.run()
    obj, _ = session.finish()
    assert 2000 < len(obj.data.points) <= 2500  # grew towards the cap


def test_2dgs_is_offered_and_trains_flat_discs(extension, clean_scene, dataset):
    train = extension.addon.train
    assert "2dgs" in [item[0] for item in train.METHOD_ITEMS]
    session = train.TrainSession(dataset, steps=20, method="2dgs", geometry_from=5)
    session.run()
    obj, _ = session.finish()
    arrays, _ = extension.addon.splat_object.read_splats(obj)
    limit = session.trainer.max_thickness
    assert np.exp(arrays.scales[:, 2]).max() <= limit * (1 + 1e-5)  # every splat a disc
    assert obj["mlx3d_training"]["method"] == "2dgs"


def test_panel_train_section_shows_the_stages_a_step_runs(extension, clean_scene):
    from mlx3d.cameras import Camera
    from mlx3d.training import TrainerConfig
    from mlx3d.training.plan import step_plan

    settings = clean_scene.mlx3d_splats
    panel = extension.addon.panel.VIEW3D_PT_mlx3d_train
    labels = {}
    for method in ("vanilla", "2dgs"):
        settings.train_method, settings.train_steps = method, 7000
        log = []
        panel.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene, active_object=None))
        labels[method] = [entry[1] for entry in log if entry[0] == "label"]
    # the first step with every scheduled effect on: SH degree 3 from step 3,001 (no scene camera: a pinhole one)
    assert labels["vanilla"][0] == "A step (3,001) runs:"
    pinhole = Camera.look_at(eye=(0, -3, 1), at=(0, 0, 0), up=(0, 0, 1), width=64, height=64, fov=50.0)
    assert labels["2dgs"][1:-1] == list(step_plan(TrainerConfig(method="2dgs", steps=7000), pinhole, 3, 3000).stages)
    assert "loss_normal_consistency" in labels["2dgs"] and "thickness_clamp" in labels["2dgs"]
    assert "loss_normal_consistency" not in labels["vanilla"] and "thickness_clamp" not in labels["vanilla"]
    assert labels["vanilla"][-1].startswith("Skipped: antialias_compensation, gaussian_normals")
