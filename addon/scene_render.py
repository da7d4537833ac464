"""Whole-scene frames: Blender's own objects rendered by Blender, the splat objects by mlx3d, composited per pixel by depth.

One frame (``render_frame``), in the scene's current state:

1. Plan (``FramePlan``): which splat objects and which other drawn objects
   (meshes, curves, text, volumes, ...) are visible to the render, and what
   the world behind them is: transparent (film transparent), a flat colour
   (a world without texture), or rendered (a textured world). Blender's engine
   runs only when another object is visible or the world is textured; without
   splats the frame is Blender's layer alone.
2. Blender's layer: the scene rendered by its own engine and settings (Cycles,
   EEVEE, samples, lights, materials) with the splat objects hidden, the film
   transparent (so edges carry coverage alpha), and the Depth pass (camera z,
   the splats' depth too) and, behind a textured world, the Environment pass
   (the world); read from a multilayer OpenEXR. The compositor is not applied.
3. Display space: 3DGS colours are display-referred sRGB (what the photos
   showed), so the frame is composited in display space. Blender's layer
   (unpremultiplied) and the world go through the scene's view transform:
   exactly in float for 'Standard' and 'Raw' (with no look, exposure 0, gamma 1,
   no curves, sRGB display), through Blender's own colour management (16-bit)
   for the others (AgX, Filmic, ...).
4. Splats: one mlx3d render of every visible splat object (world matrices
   from the depsgraph) with Blender's layer as its surface
   (``mlx3d.render.surface.Surface``): front to back, each pixel's splats up
   to Blender's surface depth, then the surface with the transmittance left,
   then the splats behind it where the surface is not opaque; the world fills
   what stays transparent. No depth test where Blender drew nothing but the
   world.

Frames are (H, W, 4) float32 display-referred RGBA, straight alpha, top row
first. ``AnimationRender`` renders a frame range one frame per ``step``
through the depsgraph (animated cameras, lens and shift, animated and parented
objects) and writes each frame atomically in the scene's output format and
folder (a movie format: frames first, then Blender's own movie writer).
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass

import bpy
import numpy as np

from mlx3d.io.exr import read_exr
from mlx3d.render.surface import Surface
from mlx3d.splatting import GaussianModel, merge_splats, transform_splats

from .camera import camera_from_blender, render_size
from .capture import linear_to_srgb
from .scene_settings import TemporarySettings
from .splat_object import SplatObjectError, is_identity, is_splat_object, read_splats, srgb_to_linear

# Object types a render engine draws (cameras, lights, empties and armatures draw nothing themselves).
DRAWN_TYPES = frozenset({"MESH", "CURVE", "SURFACE", "META", "FONT", "VOLUME", "GPENCIL", "GREASEPENCIL", "CURVES", "POINTCLOUD"})
# Blender writes this depth (or more) where a pixel has no surface.
EMPTY_DEPTH = 1e9
RENDER_IMAGE = "MLX3D Render"


class SceneRenderError(SplatObjectError):
    """A scene that cannot be rendered (no camera, no output folder, a failed Blender render)."""


# ------------------------------------------------------------------ what a frame needs
def _render_visible(view_layer) -> list:
    """(object, instanced) for the objects the render of ``view_layer`` draws: in an included collection
    that renders, not hidden from renders, and (instanced) the objects of collections that visible empties
    instance."""
    found, seen = [], set()

    def add(obj, instanced=False):
        if obj.name_full not in seen and not obj.hide_render:
            seen.add(obj.name_full)
            found.append((obj, instanced))
            if obj.instance_type == "COLLECTION" and obj.instance_collection is not None:
                for inner in obj.instance_collection.all_objects:
                    add(inner, True)

    def walk(layer_collection):
        if layer_collection.exclude or layer_collection.collection.hide_render:
            return
        for obj in layer_collection.collection.objects:
            add(obj)
        for child in layer_collection.children:
            walk(child)

    walk(view_layer.layer_collection)
    return found


def flat_world_colour(scene):
    """The scene-linear RGB of a world without texture (colour × strength of a lone Background node,
    or the world colour without nodes); None for a textured world; black without a world."""
    world = scene.world
    if world is None:
        return np.zeros(3)
    uses_nodes = world.node_tree is not None and (bpy.app.version >= (5, 0, 0) or world.use_nodes)  # 5.x: always nodes
    if not uses_nodes:
        return np.array(world.color[:3], np.float64)
    outputs = [n for n in world.node_tree.nodes if n.type == "OUTPUT_WORLD"]
    output = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    if output is None or not output.inputs["Surface"].is_linked:
        return np.zeros(3)
    node = output.inputs["Surface"].links[0].from_node
    if node.type != "BACKGROUND" or node.inputs["Color"].is_linked or node.inputs["Strength"].is_linked:
        return None
    return np.array(node.inputs["Color"].default_value[:3], np.float64) * node.inputs["Strength"].default_value


@dataclass(frozen=True)
class FramePlan:
    """What one frame runs. ``world``: 'transparent', 'flat' or 'rendered'."""

    width: int
    height: int
    splat_objects: tuple
    blender_objects: tuple  # other objects the render draws
    world: str
    engine: str

    @property
    def blender_render(self) -> bool:
        return bool(self.blender_objects) or self.world == "rendered"


def plan_frame(scene, view_layer=None) -> FramePlan:
    """Decide the stages of a frame of ``scene`` (see the module docstring)."""
    if scene.camera is None or scene.camera.type != "CAMERA":
        raise SceneRenderError(f"scene '{scene.name}' has no active camera to render from")
    view_layer = view_layer or scene.view_layers[0]
    visible = _render_visible(view_layer)
    # splat objects drawn through a collection instance are left out (the instancer's matrix is not applied)
    splats = tuple(o.name for o, instanced in visible if is_splat_object(o) and not instanced)
    others = tuple(o.name for o, _ in visible if o.type in DRAWN_TYPES and not is_splat_object(o))
    if scene.render.film_transparent:
        world = "transparent"
    else:
        world = "flat" if flat_world_colour(scene) is not None else "rendered"
    width, height = render_size(scene)
    return FramePlan(width, height, splats, others, world, scene.render.engine)


# ------------------------------------------------------------------ colour
def exact_view(scene) -> str | None:
    """'Standard' or 'Raw' when the scene's view transform is one we apply exactly in float, else None."""
    view = scene.view_settings
    plain = (view.look in ("None", "") and view.exposure == 0.0 and view.gamma == 1.0 and not view.use_curve_mapping
             and scene.display_settings.display_device == "sRGB")
    return view.view_transform if plain and view.view_transform in ("Standard", "Raw") else None


def to_display(linear, scene) -> np.ndarray:
    """Scene-linear RGB (..., 3) -> display-referred RGB in [0, 1], as the scene's view transform shows it."""
    linear = np.asarray(linear, np.float32)
    view = exact_view(scene)
    if view == "Standard":
        return linear_to_srgb(linear).astype(np.float32)
    if view == "Raw":
        return np.clip(linear, 0.0, 1.0)
    return _display_by_blender(linear, scene)


def _display_by_blender(linear: np.ndarray, scene) -> np.ndarray:
    """``to_display`` through Blender's colour management: a float image saved as a 16-bit PNG with the scene's view settings."""
    flat = linear.reshape(-1, 3)
    n = flat.shape[0]
    width = max(1, min(n, 4096))
    height = max(1, math.ceil(n / width))
    rgba = np.ones((height * width, 4), np.float32)
    rgba[:n, :3] = flat
    rgba[n:, :3] = 0.0
    image = bpy.data.images.new(".mlx3d view transform", width, height, alpha=False, float_buffer=True)
    loaded = None
    with tempfile.TemporaryDirectory() as folder, TemporarySettings() as settings:
        path = os.path.join(folder, "display.png")
        _image_format(settings, scene, "PNG", color_mode="RGB", color_depth="16")
        settings.set(scene.render.image_settings, "color_management", "FOLLOW_SCENE")
        settings.set(scene.render, "dither_intensity", 0.0)
        try:
            image.pixels.foreach_set(rgba.ravel())
            image.save_render(filepath=path, scene=scene)
            loaded = bpy.data.images.load(path)
            loaded.colorspace_settings.name = "Non-Color"
            out = np.empty(width * height * 4, np.float32)
            loaded.pixels.foreach_get(out)
        finally:
            bpy.data.images.remove(image)
            if loaded is not None:
                bpy.data.images.remove(loaded)
    return out.reshape(-1, 4)[:n, :3].reshape(linear.shape)


def _image_format(settings: TemporarySettings, scene, file_format: str, **values) -> None:
    """Switch the scene's output image format for a moment (Blender 5 picks the media type first)."""
    image = scene.render.image_settings
    # Remember everything first: a new media type or format changes the others on its own.
    for attr in ("media_type", "file_format", "color_mode", "color_depth", "exr_codec", "compression", "quality"):
        if hasattr(image, attr):
            settings.keep(image, attr)
    if hasattr(image, "media_type"):
        settings.set(image, "media_type", "MULTI_LAYER_IMAGE" if file_format == "OPEN_EXR_MULTILAYER" else "IMAGE")
    settings.set(image, "file_format", file_format)
    settings.set_all(image, values)


# ------------------------------------------------------------------ Blender's layer
@dataclass
class BlenderLayer:
    """Blender's render of a frame: premultiplied scene-linear ``color`` (H,W,3), coverage ``alpha``
    (H,W), camera-z ``depth`` (H,W) (+inf where nothing is drawn), and the scene-linear ``world``
    (H,W,3) when it was asked for (a textured world behind an opaque film), else None; rows top first."""

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    world: np.ndarray | None


def _channels(channels: dict, layer: str, name: str, components: str) -> np.ndarray:
    keys = [f"{layer}.{name}.{c}" for c in components]
    missing = [k for k in keys if k not in channels]
    if missing:
        raise SceneRenderError(f"Blender's render has no {', '.join(missing)} (channels: {', '.join(sorted(channels))})")
    return np.stack([channels[k] for k in keys], axis=-1)


def render_blender_layer(scene, view_layer, hide, world: bool) -> BlenderLayer:
    """Render ``scene`` with its own engine, ``hide`` (objects) hidden, film transparent, and read the
    passes (the Environment pass only with ``world``)."""
    with tempfile.TemporaryDirectory() as folder, TemporarySettings() as settings:
        for obj in hide:
            settings.set(obj, "hide_render", True)
        # the whole frame, one view: a render border or stereo views would not line up with the splats' frame
        settings.set_all(scene.render, {"film_transparent": True, "use_compositing": False, "use_sequencer": False, "use_border": False,
                                        "use_multiview": False})
        settings.set(view_layer, "use_pass_z", True)
        if world:
            settings.set(view_layer, "use_pass_environment", True)
        path = os.path.join(folder, "layer.exr")
        if bpy.ops.render.render(scene=scene.name, layer=view_layer.name) != {"FINISHED"}:
            raise SceneRenderError(f"Blender's render of scene '{scene.name}' failed")
        _image_format(settings, scene, "OPEN_EXR_MULTILAYER", color_depth="32", exr_codec="ZIP")
        bpy.data.images["Render Result"].save_render(filepath=path, scene=scene)
        channels = read_exr(path)
    rgba = _channels(channels, view_layer.name, "Combined", "RGBA")
    depth = _channels(channels, view_layer.name, "Depth", "Z")[..., 0]
    alpha = np.clip(rgba[..., 3], 0.0, 1.0)
    drawn = (alpha > 0.0) & np.isfinite(depth) & (depth < EMPTY_DEPTH)
    env = None
    if world:  # the Environment pass is "Env" in Blender 4.x files, "Environment" in 5.x
        env = "Environment" if f"{view_layer.name}.Environment.R" in channels else "Env"
        env = np.maximum(_channels(channels, view_layer.name, env, "RGB"), 0.0)
    return BlenderLayer(np.maximum(rgba[..., :3], 0.0), np.where(drawn, alpha, 0.0).astype(np.float32),
                        np.where(drawn, depth, np.inf).astype(np.float32), env)


# ------------------------------------------------------------------ splats
class SplatSource:
    """The splat objects' attributes, read once; ``model`` bakes their world matrices of the current
    frame (the last model is reused while the objects and their matrices stay the same)."""

    def __init__(self):
        self._arrays: dict = {}
        self._last = (None, None)  # (objects and matrices, model)
        self.messages: list = []

    def model(self, objects, depsgraph) -> GaussianModel:
        matrices = [np.array(obj.evaluated_get(depsgraph).matrix_world, np.float64) for obj in objects]
        key = tuple((obj.name_full, m.tobytes()) for obj, m in zip(objects, matrices))
        if self._last[0] == key:
            return self._last[1]
        parts = []
        for obj, matrix in zip(objects, matrices):
            if obj.name_full not in self._arrays:
                arrays, warnings = read_splats(obj)
                self._arrays[obj.name_full] = arrays
                self.messages += warnings
            arrays = self._arrays[obj.name_full]
            parts.append(arrays if is_identity(matrix) else transform_splats(arrays, matrix))
        model = GaussianModel.from_arrays(parts[0] if len(parts) == 1 else merge_splats(parts))
        self._last = (key, model)
        return model


# ------------------------------------------------------------------ a frame
@dataclass
class Frame:
    """A composited frame: ``rgba`` (H,W,4) display-referred, straight alpha, top row first."""

    rgba: np.ndarray
    plan: FramePlan
    stages: tuple  # what ran, Blender's stages and mlx3d's
    seconds: dict  # 'blender', 'splats', 'composite'


def render_frame(scene, *, view_layer=None, antialias: bool = False, source: SplatSource | None = None, backend: str = "auto") -> Frame:
    """Composite the scene's current frame (see the module docstring)."""
    view_layer = view_layer or bpy.context.view_layer
    plan = plan_frame(scene, view_layer)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    seconds = {"blender": 0.0, "splats": 0.0, "composite": 0.0}
    stages = []
    h, w = plan.height, plan.width
    splat_objects = [scene.objects[name] for name in plan.splat_objects]
    t0 = time.perf_counter()
    layer = render_blender_layer(scene, view_layer, splat_objects, plan.world == "rendered") if plan.blender_render else None
    seconds["blender"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if layer is not None:
        stages.append(f"blender_render_{plan.engine.lower()}")
        drawn = layer.alpha > 0  # only these pixels (and a textured world) go through the view transform
        coverage = layer.alpha[drawn][:, None]
        parts = [layer.color[drawn] / coverage] + ([layer.world.reshape(-1, 3)] if layer.world is not None else [])
        shown = to_display(np.concatenate(parts), scene)
        color = np.zeros((h, w, 3), np.float32)
        color[drawn] = shown[: len(coverage)] * coverage
        world = shown[len(coverage):].reshape(h, w, 3) if layer.world is not None else None
        stages.append(f"view_transform_{(exact_view(scene) or 'blender').lower()}")
        alpha = layer.alpha
    else:
        color, alpha, world = np.zeros((h, w, 3), np.float32), np.zeros((h, w), np.float32), None
    if plan.world == "flat":
        world = to_display(flat_world_colour(scene), scene)
    seconds["composite"] += time.perf_counter() - t0
    if splat_objects:
        t0 = time.perf_counter()
        source = source or SplatSource()
        model = source.model(splat_objects, depsgraph)
        camera = camera_from_blender(scene.camera.evaluated_get(depsgraph), scene)
        surface = Surface(color, alpha, layer.depth) if plan.blender_objects else None
        out = model.render(camera, antialias=antialias, backend=backend, surface=surface)
        color, alpha = np.array(out["image"], np.float32), np.array(out["alpha"], np.float32)
        stages += list(out["stages"])
        seconds["splats"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if world is not None:
        color = color + (1.0 - alpha)[..., None] * world
        alpha = np.ones_like(alpha)
        stages.append(f"world_{plan.world}")
    rgba = np.empty((h, w, 4), np.float32)
    rgba[..., :3] = np.clip(np.where(alpha[..., None] > 0, color / np.maximum(alpha, 1e-12)[..., None], 0.0), 0.0, 1.0)
    rgba[..., 3] = np.clip(alpha, 0.0, 1.0)
    seconds["composite"] += time.perf_counter() - t0
    return Frame(rgba, plan, tuple(stages), seconds)


# ------------------------------------------------------------------ writing
def is_movie(scene) -> bool:
    """True when the scene's output is a movie (Blender's FFmpeg writer)."""
    image = scene.render.image_settings
    return getattr(image, "media_type", None) == "VIDEO" or image.file_format == "FFMPEG"


def save_frame(scene, rgba: np.ndarray, path: str, png: bool = False) -> None:
    """Write a frame to ``path`` atomically (temporary file, then rename) in the scene's image format
    (``png``: 8-bit RGBA PNG instead), through Blender's image writer under the 'Standard' view, so
    the display-referred values are written as they are (a float format gets their sRGB-decoded
    linear values)."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise SceneRenderError(f"folder {folder} does not exist")
    h, w = rgba.shape[:2]
    alpha = rgba[..., 3:4]
    linear = np.concatenate([srgb_to_linear(rgba[..., :3]) * alpha, alpha], axis=-1).astype(np.float32)  # Blender's float images are premultiplied
    image = bpy.data.images.new(".mlx3d frame", w, h, alpha=True, float_buffer=True)
    name, ext = os.path.splitext(os.path.basename(path))
    tmp = os.path.join(folder, f".{name}.{os.getpid()}.tmp{ext}")
    try:
        image.pixels.foreach_set(np.ascontiguousarray(linear[::-1]).ravel())
        with TemporarySettings() as settings:
            if png:
                _image_format(settings, scene, "PNG", color_mode="RGBA", color_depth="8")
            image_settings = scene.render.image_settings
            settings.set(image_settings, "color_management", "OVERRIDE")
            settings.set_all(image_settings.view_settings, {"view_transform": "Standard", "look": "None", "exposure": 0.0, "gamma": 1.0, "use_curve_mapping": False})
            settings.set(image_settings.display_settings, "display_device", "sRGB")
            image.save_render(filepath=tmp, scene=scene)
        os.replace(tmp, path)
    finally:
        bpy.data.images.remove(image)
        if os.path.exists(tmp):
            os.remove(tmp)


def show_frame(rgba: np.ndarray):
    """Put a frame into the Blender image ``RENDER_IMAGE`` (display values, as shown) and return it."""
    h, w = rgba.shape[:2]
    image = bpy.data.images.get(RENDER_IMAGE)
    if image is None or tuple(image.size) != (w, h):
        if image is not None:
            bpy.data.images.remove(image)
        image = bpy.data.images.new(RENDER_IMAGE, w, h, alpha=True)
    image.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    image.update()
    return image


# ------------------------------------------------------------------ frames to files
def parse_frames(text: str) -> tuple:
    """'A-B' or 'A' -> (A, B) inclusive; ValueError naming the text otherwise."""
    parts = text.split("-") if not text.startswith("-") else None
    try:
        if parts is None or len(parts) > 2:
            raise ValueError
        start, end = int(parts[0]), int(parts[-1])
    except ValueError:
        raise SceneRenderError(f"frames must be 'A-B' or 'A' with whole numbers A <= B, got {text!r}") from None
    if start > end:
        raise SceneRenderError(f"frames must be 'A-B' with A <= B, got {text!r}")
    return start, end


class AnimationRender:
    """Frames ``start..end`` of ``scene`` (default its frame range and step), one per ``step``.

    Each frame is set through the depsgraph (``scene.frame_set``), composited
    (``render_frame``) and written atomically to ``scene.render.frame_path``
    (in ``out_dir`` when given) in the scene's image format. For a movie
    format, frames go to a temporary folder as PNG and ``close`` encodes the
    ones written with Blender's own movie writer. ``close`` (always call it)
    restores the current frame; after a cancel the frames written are kept.
    """

    def __init__(self, scene, frames: tuple | None = None, *, out_dir=None, antialias: bool = False, view_layer=None, backend: str = "auto"):
        plan_frame(scene, view_layer)  # refuses a scene without a camera before anything is written
        start, end = frames if frames is not None else (scene.frame_start, scene.frame_end)
        if start > end:
            raise SceneRenderError(f"the frame range {start}-{end} is empty")
        self.scene = scene
        self.view_layer = view_layer or bpy.context.view_layer
        self.frames = list(range(start, end + 1, scene.frame_step if frames is None else 1))
        self.antialias, self.backend = antialias, backend
        self.out_dir = os.path.abspath(out_dir) if out_dir else None
        self.movie = is_movie(scene)
        self.written: list = []
        self.stages: tuple = ()
        self.seconds = {"blender": 0.0, "splats": 0.0, "composite": 0.0, "write": 0.0}
        self._source = SplatSource()
        self._original_frame = (scene.frame_current, scene.frame_subframe)
        self._movie_dir = tempfile.mkdtemp(prefix="mlx3d_frames_") if self.movie else None
        folder = os.path.dirname(self.path(self.frames[0]))
        if not self.movie:
            try:
                os.makedirs(folder, exist_ok=True)
            except OSError as exc:
                raise SceneRenderError(f"cannot create the output folder {folder}: {exc}") from None
        self._closed = False

    @property
    def total(self) -> int:
        return len(self.frames)

    @property
    def done(self) -> bool:
        return len(self.written) >= self.total

    def path(self, frame: int) -> str:
        """Where frame ``frame`` is written (the scene's own frame naming)."""
        if self.movie:
            return os.path.join(self._movie_dir, f"{frame:06d}.png")
        path = self.scene.render.frame_path(frame=frame)
        return os.path.join(self.out_dir, os.path.basename(path)) if self.out_dir else path

    def step(self) -> str:
        """Render and write the next frame; returns its path."""
        frame = self.frames[len(self.written)]
        self.scene.frame_set(frame)
        result = render_frame(self.scene, view_layer=self.view_layer, antialias=self.antialias, source=self._source, backend=self.backend)
        t0 = time.perf_counter()
        path = self.path(frame)
        save_frame(self.scene, result.rgba, path, png=self.movie)
        self.seconds["write"] += time.perf_counter() - t0
        for key, value in result.seconds.items():
            self.seconds[key] += value
        self.stages = result.stages
        self.last = result
        self.written.append(path)
        return path

    def close(self) -> list:
        """Restore the current frame and, for a movie, encode the frames written; returns messages."""
        if self._closed:
            return []
        self._closed = True
        self.scene.frame_set(self._original_frame[0], subframe=self._original_frame[1])
        messages = []
        if self.movie and self.written:
            try:
                messages.append(f"wrote {encode_movie(self.scene, self.written, self.frames[0], self.out_dir)}")
            except (SceneRenderError, OSError, RuntimeError) as exc:  # the frames stay where they are
                raise SceneRenderError(f"encoding the movie failed ({exc}); its {len(self.written)} frames are in {self._movie_dir}") from None
        if self._movie_dir:
            for path in self.written:
                os.remove(path)
            os.rmdir(self._movie_dir)
        return messages + self._source.messages

    def summary(self) -> str:
        where = os.path.dirname(self.written[0]) if self.written and not self.movie else "the movie"
        per = {k: v / max(1, len(self.written)) for k, v in self.seconds.items()}
        return (f"rendered {len(self.written)} of {self.total} frames into {where} ({', '.join(self.stages)}); per frame: "
                f"Blender {per['blender']:.2f} s, splats {per['splats']:.2f} s, compositing {per['composite']:.2f} s, writing {per['write']:.2f} s")


def encode_movie(scene, frames: list, first: int, out_dir=None) -> str:
    """Encode PNG ``frames`` into ``scene``'s movie output with Blender's movie writer (the sequencer of
    a temporary scene with the same output settings, under the 'Standard' view so the frames' values
    pass unchanged); the file appears whole. Returns its path."""
    temp = bpy.data.scenes.new(".mlx3d movie")
    try:
        render = temp.render
        for attr in ("resolution_x", "resolution_y", "resolution_percentage", "pixel_aspect_x", "pixel_aspect_y", "fps", "fps_base"):
            setattr(render, attr, getattr(scene.render, attr))
        source, target = scene.render.image_settings, render.image_settings
        if hasattr(target, "media_type"):
            target.media_type = source.media_type
        target.file_format = source.file_format
        for prop in scene.render.ffmpeg.bl_rna.properties:
            if not prop.is_readonly and prop.identifier != "rna_type":
                setattr(render.ffmpeg, prop.identifier, getattr(scene.render.ffmpeg, prop.identifier))
        temp.view_settings.view_transform = "Standard"
        temp.view_settings.look = "None"
        temp.sequencer_colorspace_settings.name = "sRGB"
        temp.frame_start, temp.frame_end = first, first + len(frames) - 1
        editor = temp.sequence_editor_create()
        strips = editor.strips if hasattr(editor, "strips") else editor.sequences
        strip = strips.new_image("frames", frames[0], 1, first)
        for path in frames[1:]:
            strip.elements.append(os.path.basename(path))
        final = scene.render.frame_path(frame=first)
        if out_dir:
            final = os.path.join(out_dir, os.path.basename(final))
        folder = os.path.dirname(final)
        os.makedirs(folder, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder, prefix=".mlx3d_movie_") as tmp:
            render.filepath = os.path.join(tmp, "movie")
            render.use_file_extension = True
            if bpy.ops.render.render(animation=True, scene=temp.name) != {"FINISHED"}:
                raise SceneRenderError("Blender's movie writer failed")
            written = [os.path.join(tmp, f) for f in os.listdir(tmp)]
            if len(written) != 1:
                raise SceneRenderError(f"Blender's movie writer left {len(written)} files")
            os.replace(written[0], final)
        return final
    finally:
        bpy.data.scenes.remove(temp)


def render_image(scene, *, filepath=None, antialias: bool = False, view_layer=None, backend: str = "auto"):
    """Composite the current frame into the image ``RENDER_IMAGE`` (and a PNG at ``filepath``); returns (image, messages)."""
    source = SplatSource()
    result = render_frame(scene, view_layer=view_layer, antialias=antialias, source=source, backend=backend)
    image = show_frame(result.rgba)
    plan = result.plan
    what = ", ".join(plan.splat_objects + plan.blender_objects) or "the world"
    messages = [f"rendered {what} through '{scene.camera.name}' at {plan.width}x{plan.height} ({', '.join(result.stages)}); "
                + ", ".join(f"{k} {v:.2f} s" for k, v in result.seconds.items())] + source.messages
    if filepath:
        save_frame(scene, result.rgba, os.fspath(filepath), png=True)
        messages.append(f"saved {filepath}")
    return image, messages
