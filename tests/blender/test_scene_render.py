"""Whole-scene frames (addon/scene_render.py) through the installed extension:
Blender's objects rendered by Cycles, splat objects by mlx3d, composited by depth.

Oracles: the float64 loop renderer of tests/render_oracle.py with an analytic
surface (a frame-filling emission plane facing the camera at a known camera z:
constant z, while the ray length varies across the frame, so the depth
convention is checked too); Blender's own render where there are no splats;
``world_to_camera_view`` for where an animated, parented object lands; a
single-frame render for every frame of an animation. Renders are tiny (64x48 or
less, 2 Cycles samples): an emission plane seen directly has the same value for
every sample.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/ (render_oracle)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # tests/blender (modal_state)

import render_oracle  # noqa: E402
from modal_state import ESC, TIMER, OperatorState  # noqa: E402

from mlx3d.io import SplatArrays  # noqa: E402

W, H = 48, 36
C0 = 0.28209479177387814


@pytest.fixture
def sr(extension):
    return extension.addon.scene_render


def _cloud(n=40, seed=0):
    """Splats in a box 3..5 m in front of a camera at the origin looking down -Y (Blender z up)."""
    rng = np.random.default_rng(seed)
    means = np.stack([rng.uniform(-1.0, 1.0, n), rng.uniform(3.0, 5.0, n), rng.uniform(-0.7, 0.7, n)], axis=1)
    colors = rng.uniform(0.1, 0.9, (n, 3))
    return SplatArrays(
        means=means.astype(np.float32),
        scales=np.log(rng.uniform(0.08, 0.25, (n, 3))).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=rng.uniform(-1.0, 2.5, n).astype(np.float32),
        sh_dc=((colors - 0.5) / C0).astype(np.float32)[:, None, :],
        sh_rest=np.zeros((n, 0, 3), np.float32),
    ), colors


def _scene(extension, *, view="Standard", engine="CYCLES"):
    scene = bpy.context.scene
    scene.render.engine = engine
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = W, H, 100
    scene.cycles.samples = 2
    scene.cycles.use_denoising = False
    scene.render.dither_intensity = 0.0
    scene.view_settings.view_transform = view
    scene.world = bpy.data.worlds.new("world")
    _world_colour(scene, (0.0, 0.0, 0.0))
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.rotation_euler = (math.radians(90.0), 0.0, 0.0)  # looks down +Y
    scene.camera = cam
    return scene, cam


def _world_colour(scene, rgb):
    """A flat world colour: the Background node's (Blender 5 worlds have nodes), else the world colour."""
    world = scene.world
    world.color = rgb
    if world.node_tree is not None:
        background = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
        background.inputs["Color"].default_value = (*rgb, 1.0)
        background.inputs["Strength"].default_value = 1.0


def _splats(extension, arrays, name="splats"):
    obj, _ = extension.addon.splat_object.create_splat_object(name, arrays)
    return obj


def _emission_plane(y, colour, size=40.0, name="plane"):
    """A square facing the camera at camera z = ``y``, large enough to fill the frame."""
    mesh = bpy.data.meshes.new(name)
    s = size / 2
    mesh.from_pydata([(-s, y, -s), (s, y, -s), (s, y, s), (-s, y, s)], [], [(0, 1, 2, 3)])
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender 4.x; 5.x materials always have nodes
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    for node in list(nodes):
        nodes.remove(node)
    out = nodes.new("ShaderNodeOutputMaterial")
    emit = nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (*colour, 1.0)
    emit.inputs["Strength"].default_value = 1.0
    mat.node_tree.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    mesh.materials.append(mat)
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _oracle(extension, scene, arrays, colors, surface=None):
    cam = extension.addon.camera.camera_from_blender(scene.camera, scene)
    q = arrays.quats.astype(np.float64)
    image, alpha = render_oracle.render(
        cam, arrays.means.astype(np.float64), q, np.exp(arrays.scales.astype(np.float64)),
        1.0 / (1.0 + np.exp(-arrays.opacities.astype(np.float64))), colors, surface=surface,
    )
    return image, alpha


def _srgb(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


EEVEE = pytest.param("EEVEE", marks=pytest.mark.skipif(
    not os.environ.get("MLX3D_TEST_EEVEE"), reason="EEVEE needs a GPU context; set MLX3D_TEST_EEVEE=1 to run it (minutes per frame in software GL)"))


@pytest.mark.parametrize("engine", ["CYCLES", EEVEE])
@pytest.mark.parametrize("plane_y, case", [(2.0, "in front of every splat"), (7.0, "behind every splat"), (4.0, "through the cloud")])
def test_splats_and_an_opaque_plane_match_the_float64_oracle(extension, clean_scene, sr, plane_y, case, engine):
    import importlib

    scene, _ = _scene(extension)
    importlib.import_module(extension.__name__ + ".addon.headless")._set_engine(scene, engine)
    arrays, colors = _cloud()
    _splats(extension, arrays)
    plane_colour = (0.2, 0.5, 0.3)
    _emission_plane(plane_y, plane_colour)
    frame = sr.render_frame(scene)
    assert frame.plan.blender_objects == ("plane",) and frame.plan.splat_objects == ("splats",)
    assert any(s.startswith("blender_render") for s in frame.stages)
    shown = _srgb(plane_colour)
    surface = (np.broadcast_to(shown, (H, W, 3)), np.ones((H, W)), np.full((H, W), plane_y))
    want, _ = _oracle(extension, scene, arrays, colors, surface)
    got = frame.rgba.astype(np.float64)
    np.testing.assert_allclose(got[..., 3], 1.0)
    # float32 kernels and Blender's float emission against float64; the tile binning may drop
    # rims with alpha < 1/255 that the oracle keeps only where its tile rule differs (it does not).
    # EEVEE renders into half floats (~2.4e-4 steps at 0.5).
    np.testing.assert_allclose(got[..., :3], np.clip(want, 0, 1), atol=2e-4 if engine == "CYCLES" else 4e-4, err_msg=case)
    if case == "in front of every splat":
        np.testing.assert_allclose(got[..., :3], np.broadcast_to(shown, (H, W, 3)), atol=1e-4 if engine == "CYCLES" else 4e-4)
    else:
        assert np.abs(got[..., :3] - shown).max() > 0.1  # splats are seen


def test_orthographic_camera_hides_and_shows_by_camera_z(extension, clean_scene, sr):
    scene, cam = _scene(extension)
    cam.data.type, cam.data.ortho_scale = "ORTHO", 3.0
    arrays, colors = _cloud(seed=2)
    _splats(extension, arrays)
    plane = _emission_plane(7.0, (0.2, 0.5, 0.3))
    behind = sr.render_frame(scene).rgba
    plane.location.y = 2.0 - 7.0  # now in front of every splat
    front = sr.render_frame(scene).rgba
    np.testing.assert_allclose(front[..., :3], np.broadcast_to(_srgb((0.2, 0.5, 0.3)), (H, W, 3)), atol=1e-4)
    plane.hide_render = True
    _world_colour(scene, (0.2, 0.5, 0.3))  # the same colour as a world behind everything: no depth test
    over_world = sr.render_frame(scene)
    assert not over_world.plan.blender_render
    np.testing.assert_allclose(behind, over_world.rgba, atol=1e-5)


def test_without_meshes_blender_does_not_render(extension, clean_scene, sr):
    scene, _ = _scene(extension)
    arrays, colors = _cloud(seed=1)
    _splats(extension, arrays)
    _world_colour(scene, (0.05, 0.1, 0.2))
    frame = sr.render_frame(scene)
    assert not frame.plan.blender_render and not any(s.startswith("blender_render") for s in frame.stages)
    assert "world_flat" in frame.stages and not any("surface" in s for s in frame.stages)
    want, _ = _oracle(extension, scene, arrays, colors)
    want = want + (1 - _oracle(extension, scene, arrays, colors)[1])[..., None] * _srgb((0.05, 0.1, 0.2))
    np.testing.assert_allclose(frame.rgba[..., :3], np.clip(want, 0, 1), atol=2e-4)


@pytest.mark.parametrize("view", ["Standard", "AgX"])
def test_without_splats_the_frame_is_blenders_own_render(extension, clean_scene, sr, tmp_path, view):
    scene, _ = _scene(extension, view=view)
    _world_colour(scene, (0.3, 0.1, 0.05))
    plane = _emission_plane(4.0, (0.9, 0.4, 0.1), size=2.0)  # part of the frame; the world around it
    plane.rotation_euler = (0.0, 0.0, math.radians(20.0))
    scene.cycles.samples = 1  # coverage 0 or 1 per pixel: edges are no blend
    scene.cycles.pixel_filter_type = "BOX"
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_depth = "16"
    scene.render.filepath = str(tmp_path / "blender.png")
    bpy.ops.render.render(write_still=True)
    own = bpy.data.images.load(str(tmp_path / "blender.png"))
    own.colorspace_settings.name = "Non-Color"
    px = np.empty(W * H * 4, np.float32)
    own.pixels.foreach_get(px)
    own_rgb = px.reshape(H, W, 4)[::-1, :, :3]
    frame = sr.render_frame(scene)
    assert f"view_transform_{'standard' if view == 'Standard' else 'blender'}" in frame.stages
    np.testing.assert_allclose(frame.rgba[..., :3], own_rgb, atol=2e-3)
    np.testing.assert_allclose(frame.rgba[..., 3], 1.0)


def _animated_scene(extension):
    """Frames 1..5: the camera moves and zooms; a splat parented to a keyframed empty."""
    scene, cam = _scene(extension)
    scene.frame_start, scene.frame_end = 1, 5
    for f, (x, lens) in zip((1, 5), ((-0.3, 40.0), (0.3, 60.0))):
        cam.location.x, cam.data.lens = x, lens
        cam.keyframe_insert("location", frame=f)
        cam.data.keyframe_insert("lens", frame=f)
    one = SplatArrays(means=np.zeros((1, 3), np.float32), scales=np.full((1, 3), math.log(0.05), np.float32),
                      quats=np.array([[1, 0, 0, 0]], np.float32), opacities=np.array([4.0], np.float32),
                      sh_dc=np.full((1, 1, 3), (1.0 - 0.5) / C0, np.float32), sh_rest=np.zeros((1, 0, 3), np.float32))
    splat = _splats(extension, one, "dot")
    parent = bpy.data.objects.new("mover", None)
    scene.collection.objects.link(parent)
    splat.parent = parent
    splat.location = (0.0, 0.0, 0.2)
    for f, (x, y) in zip((1, 5), ((-0.5, 4.0), (0.6, 5.0))):
        parent.location = (x, y, 0.0)
        parent.keyframe_insert("location", frame=f)
    _emission_plane(8.0, (0.1, 0.1, 0.4))
    scene.frame_set(1)
    return scene, splat


def _read(path):
    image = bpy.data.images.load(str(path))
    image.colorspace_settings.name = "Non-Color"
    px = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(px)
    bpy.data.images.remove(image)
    return px.reshape(H, W, 4)[::-1]


def test_animation_frames_equal_single_frame_renders_and_follow_the_depsgraph(extension, clean_scene, sr, tmp_path):
    from bpy_extras.object_utils import world_to_camera_view

    scene, splat = _animated_scene(extension)
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(tmp_path / "anim" / "f_")
    job = sr.AnimationRender(scene)
    try:
        while not job.done:
            job.step()
    finally:
        job.close()
    assert scene.frame_current == 1  # restored
    files = sorted(os.listdir(tmp_path / "anim"))
    assert files == [f"f_{f:04d}.png" for f in range(1, 6)]
    for k in (2, 4):
        scene.frame_set(k)
        single = tmp_path / f"single_{k}.png"
        sr.render_image(scene, filepath=str(single))
        np.testing.assert_array_equal(_read(tmp_path / "anim" / f"f_{k:04d}.png"), _read(single))
        # the white dot lands where Blender's depsgraph puts the parented object
        rgb = sr.render_frame(scene).rgba[..., :3]
        weight = np.clip(rgb.min(-1) - 0.5, 0, None)  # the blue plane (red and green 0.35 shown) drops out
        ys, xs = np.mgrid[0:H, 0:W]
        centre = np.array([(weight * (xs + 0.5)).sum(), (weight * (ys + 0.5)).sum()]) / weight.sum()
        ndc = world_to_camera_view(scene, scene.camera, splat.matrix_world.translation)
        np.testing.assert_allclose(centre, [ndc.x * W, (1 - ndc.y) * H], atol=0.25)
    scene.frame_set(1)


def test_escape_after_two_of_five_frames_keeps_exactly_two(extension, clean_scene, sr, tmp_path):
    scene, _ = _animated_scene(extension)
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(tmp_path / "out") + os.sep
    op = extension.addon.operators.MLX3D_OT_render_animation
    session = sr.AnimationRender(scene)
    state = OperatorState(op, session)
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert op.modal(state, bpy.context, ESC) == {"CANCELLED"}
    assert sorted(os.listdir(tmp_path / "out")) == ["0001.png", "0002.png"]  # whole files, no temporaries
    for name in ("0001.png", "0002.png"):
        assert _read(tmp_path / "out" / name).shape == (H, W, 4)
    assert scene.frame_current == 1


def test_render_leaves_the_scene_as_it_was(extension, clean_scene, sr, tmp_path):
    scene, _ = _scene(extension)
    arrays, _ = _cloud()
    splats = _splats(extension, arrays)
    _emission_plane(4.0, (0.2, 0.5, 0.3))
    layer = bpy.context.view_layer
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_depth = "8"
    scene.render.image_settings.color_mode = "RGB"
    image = scene.render.image_settings

    def state():
        return (scene.render.film_transparent, layer.use_pass_z, layer.use_pass_environment, splats.hide_render,
                image.file_format, image.color_depth, image.color_mode, image.color_management, scene.render.use_compositing,
                scene.render.dither_intensity, scene.view_settings.view_transform, getattr(image, "media_type", None))

    scene.render.use_border, scene.render.use_crop_to_border = True, True  # a border crop is not used for the layer
    scene.render.border_min_x = 0.5
    before = state() + (scene.render.use_border,)
    assert sr.render_frame(scene).rgba.shape == (H, W, 4)
    sr.save_frame(scene, np.ones((H, W, 4), np.float32), str(tmp_path / "x.png"))
    assert state() + (scene.render.use_border,) == before


def test_headless_render_frames_exit_codes_and_ctrl_c(extension, clean_scene, sr, tmp_path, monkeypatch, capsys):
    import importlib

    scene, _ = _animated_scene(extension)
    scene.render.image_settings.file_format = "PNG"
    blend = tmp_path / "anim.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    headless = importlib.import_module(extension.__name__ + ".addon.headless")
    assert headless.main(["render", "--blend", str(blend), "--frames", "2-4", "--out", str(tmp_path / "frames")]) == 0
    assert sorted(os.listdir(tmp_path / "frames")) == ["0002.png", "0003.png", "0004.png"]
    assert headless.main(["render", "--blend", str(blend), "--out", str(tmp_path / "one.png")]) == 0
    assert (tmp_path / "one.png").exists()
    assert headless.main(["render", "--blend", str(blend), "--frames", "4-2", "--out", str(tmp_path / "x")]) == 1
    assert "A <= B" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        headless.main(["render", "--blend", str(blend), "--engine", "NOPE", "--out", str(tmp_path / "x")])
    assert exit_.value.code == 2
    steps = []
    real_step = sr.AnimationRender.step

    def interrupted(self):
        if len(steps) == 2:
            raise KeyboardInterrupt
        steps.append(1)
        return real_step(self)

    monkeypatch.setattr(sr.AnimationRender, "step", interrupted)
    with pytest.raises(SystemExit) as exit_:
        headless.main(["render", "--blend", str(blend), "--frames", "1-5", "--out", str(tmp_path / "cut")])
    assert exit_.value.code == 130
    assert sorted(os.listdir(tmp_path / "cut")) == ["0001.png", "0002.png"]


def test_movie_output_goes_through_blenders_movie_writer(extension, clean_scene, sr, tmp_path):
    scene, _ = _animated_scene(extension)
    scene.frame_end = 3
    image = scene.render.image_settings
    if hasattr(image, "media_type"):
        image.media_type = "VIDEO"
    image.file_format = "FFMPEG"
    scene.render.ffmpeg.format = "MPEG4"
    scene.render.ffmpeg.codec = "H264"
    scene.render.filepath = str(tmp_path / "movie_")
    job = sr.AnimationRender(scene)
    while not job.done:
        job.step()
    messages = job.close()
    files = os.listdir(tmp_path)
    assert len(files) == 1 and files[0].startswith("movie_") and files[0].endswith(".mp4"), files
    assert messages and files[0] in messages[0]
    clip = bpy.data.movieclips.load(str(tmp_path / files[0]))
    assert clip.frame_duration == 3 and tuple(clip.size) == (W, H)


def test_operators_render_image_and_animation(extension, clean_scene, sr, tmp_path):
    scene, _ = _animated_scene(extension)
    scene.frame_end = 2
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(tmp_path / "ops") + os.sep
    assert bpy.ops.mlx3d.render(filepath=str(tmp_path / "still.png")) == {"FINISHED"}
    image = bpy.data.images[sr.RENDER_IMAGE]
    assert tuple(image.size) == (W, H) and (tmp_path / "still.png").exists()
    assert bpy.ops.mlx3d.render_animation() == {"FINISHED"}
    assert sorted(os.listdir(tmp_path / "ops")) == ["0001.png", "0002.png"]
    scene.camera = None
    with pytest.raises(RuntimeError, match="no active camera"):
        bpy.ops.mlx3d.render_animation()
