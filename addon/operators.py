"""Operators: thin wrappers that collect options, call ``workflows`` and report.

Each operator validates its input, shows errors with ``self.report`` and
returns CANCELLED without changing the scene; editing operators are undoable.
"""

from __future__ import annotations

import os

import bpy
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, IntVectorProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from mlx3d.io import FORMATS

from . import benchmark, capture, display, photos, scene_render, train, workflows
from .splat_object import is_splat_object

# Folder settings that may start with "//" (relative to the .blend); Blender 5.0 asks for the flag.
BLEND_RELATIVE_PATH = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (5, 0, 0) else set()
SH_ITEMS = [("FILE", "As in file", "Keep every SH coefficient of the file")] + [(str(d), f"Degree {d}", f"Truncate or zero-pad SH to degree {d}") for d in range(4)]
KEEP_SH_ITEMS = [("KEEP", "Keep", "Keep the current SH degree")] + [(str(d), f"Degree {d}", f"Truncate SH to degree {d}") for d in range(4)]


def _degree(value: str):
    return None if value in ("FILE", "KEEP") else int(value)


class _Progress:
    """Window-manager progress (cursor/status bar) usable as ``progress(done, total)``."""

    def __init__(self, context):
        self.wm = context.window_manager

    def __enter__(self):
        self.wm.progress_begin(0, 100)
        return self

    def __call__(self, done, total):
        self.wm.progress_update(int(100 * done / max(total, 1)))

    def __exit__(self, *exc):
        self.wm.progress_end()
        return False


def _report_all(op, messages):
    """The first message is the result (INFO); the rest are caveats (WARNING)."""
    for i, message in enumerate(messages):
        op.report({"INFO"} if i == 0 else {"WARNING"}, message)


#: Every readable splat file, for the file browser and drag and drop.
READ_GLOB = ";".join(f"*{ext}" if ext.startswith(".") else ext for f in FORMATS for ext in f.extensions)
#: The writable formats: (identifier, label, description) and their extensions.
WRITE_ITEMS = [(f.name.upper().replace("-", "_"), f"{f.description} ({f.extensions[0]})", f"Write {f.description} ({', '.join(f.extensions)})")
               for f in FORMATS if f.writer]
WRITE_EXTENSIONS = {f.name.upper().replace("-", "_"): f.extensions[0] for f in FORMATS if f.writer}


class IMPORT_SCENE_OT_gaussian_splat_ply(bpy.types.Operator, ImportHelper):
    """Import Gaussian splat files (PLY, compressed PLY, SPZ, .splat, .ksplat, SOG, glTF) as splat objects"""

    bl_idname = "import_scene.gaussian_splat_ply"
    bl_label = "Import Gaussian Splats"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default=READ_GLOB, options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    sh_degree: EnumProperty(name="SH degree", items=SH_ITEMS, default="FILE", description="Cap the spherical-harmonics degree")
    drop_nonfinite: BoolProperty(name="Drop NaN rows", default=False, description="Drop splats with NaN/Inf values instead of refusing the file")
    at_cursor: BoolProperty(name="Place at 3D cursor", default=False)
    axis: EnumProperty(name="Axes", items=workflows.AXIS_ITEMS, default="NONE", description="Axis convention of the file")

    def paths(self):
        if self.files and self.directory:
            return [os.path.join(self.directory, f.name) for f in self.files if f.name]
        return [self.filepath]

    def execute(self, context):
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        location = tuple(context.scene.cursor.location) if self.at_cursor else None
        imported = []
        with _Progress(context) as progress:
            for i, path in enumerate(self.paths()):
                try:
                    obj, messages = workflows.import_splat_file(
                        path, sh_degree=_degree(self.sh_degree), drop_nonfinite=self.drop_nonfinite, axis=self.axis, location=location
                    )
                except (ValueError, OSError) as exc:
                    self.report({"ERROR"}, str(exc))
                    return {"CANCELLED"} if not imported else {"FINISHED"}
                imported.append(obj)
                _report_all(self, messages)
                progress(i + 1, len(self.paths()))
        for obj in context.selected_objects:
            obj.select_set(False)
        for obj in imported:
            obj.select_set(True)
        context.view_layer.objects.active = imported[-1]
        return {"FINISHED"}


class EXPORT_SCENE_OT_gaussian_splat_ply(bpy.types.Operator, ExportHelper):
    """Export splat objects, with their transforms baked in, to one splat file (PLY, compressed PLY, SPZ, SOG, .splat or glTF)"""

    bl_idname = "export_scene.gaussian_splat_ply"
    bl_label = "Export Gaussian Splats"
    bl_options = {"REGISTER", "PRESET"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default=READ_GLOB, options={"HIDDEN"})
    file_format: EnumProperty(name="Format", items=WRITE_ITEMS, default="PLY", description="File format; PLY keeps every value exactly, the others quantise")
    use_selection: BoolProperty(name="Selected only", default=True, description="Export only selected splat objects (else all in the scene)")
    axis: EnumProperty(name="Axes", items=workflows.AXIS_ITEMS, default="NONE", description="Axis convention to write")
    sh_degree: EnumProperty(name="SH degree", items=SH_ITEMS, default="FILE", description="SH degree of the file (default: highest of the objects)")

    def check(self, context):
        # The file name follows the chosen format's extension (as Blender's glTF exporter does).
        ext = WRITE_EXTENSIONS[self.file_format]
        path = self.filepath
        for other in WRITE_EXTENSIONS.values():
            if path.lower().endswith(other) and other != ext:
                path = path[: -len(other)]
                break
        self.filename_ext = ext
        if not path.lower().endswith(ext):
            path += ext
        changed = path != self.filepath
        self.filepath = path
        return changed

    def invoke(self, context, event):
        self.filename_ext = WRITE_EXTENSIONS[self.file_format]
        return super().invoke(context, event)

    def execute(self, context):
        objects = context.selected_objects if self.use_selection else context.scene.objects
        try:
            _, messages = workflows.export_splat_file(self.filepath, objects, axis=self.axis, sh_degree=_degree(self.sh_degree))
        except (ValueError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _report_all(self, messages)
        return {"FINISHED"}


class _SplatEdit:
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return is_splat_object(context.active_object)

    def run(self, context, func, *args, **kwargs):
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            result = func(*args, **kwargs)
        except (ValueError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        messages = result[1] if isinstance(result, tuple) else result
        _report_all(self, messages)
        return {"FINISHED"}


class MLX3D_OT_merge_selected(_SplatEdit, bpy.types.Operator):
    """Merge the selected splat objects into one new splat object, baking their transforms"""

    bl_idname = "mlx3d.merge_selected"
    bl_label = "Merge Selected Splats"

    @classmethod
    def poll(cls, context):
        return len(workflows.splat_objects(context.selected_objects)) >= 2

    def execute(self, context):
        return self.run(context, workflows.merge_objects, context.selected_objects)


class MLX3D_OT_apply_transform(_SplatEdit, bpy.types.Operator):
    """Bake the active splat object's transform into its splats and reset it (positions, rotations, scales and SH)"""

    bl_idname = "mlx3d.apply_transform"
    bl_label = "Apply Transform to Splats"

    def execute(self, context):
        return self.run(context, workflows.apply_transform, context.active_object)


class MLX3D_OT_crop_to_box(_SplatEdit, bpy.types.Operator):
    """Keep or delete the splats inside the bounds of a mesh or empty"""

    bl_idname = "mlx3d.crop_to_box"
    bl_label = "Crop Splats to Box"

    box: StringProperty(name="Box", description="Mesh or empty whose bounds define the box")
    keep_inside: BoolProperty(name="Keep inside", default=True, description="Keep the splats inside (else delete them)")

    def execute(self, context):
        box = bpy.data.objects.get(self.box)
        if box is None:
            self.report({"ERROR"}, f"crop box object '{self.box}' not found")
            return {"CANCELLED"}
        return self.run(context, workflows.crop_to_box, context.active_object, box, keep_inside=self.keep_inside)


class MLX3D_OT_remove_floaters(_SplatEdit, bpy.types.Operator):
    """Remove isolated splats (statistical or radius outlier removal)"""

    bl_idname = "mlx3d.remove_floaters"
    bl_label = "Remove Floaters"

    method: EnumProperty(
        name="Method",
        items=[("STATISTICAL", "Statistical", "Mean distance to k neighbours above mean + N std"), ("RADIUS", "Radius", "Fewer than M neighbours within R")],
        default="STATISTICAL",
    )
    k: IntProperty(name="Neighbours", default=25, min=1)
    std_ratio: FloatProperty(name="Std ratio", default=10.5, min=0.0)
    radius: FloatProperty(name="Radius", default=0.05, min=0.0, subtype="DISTANCE")
    min_neighbours: IntProperty(name="Min neighbours", default=4, min=1)

    def execute(self, context):
        with _Progress(context) as progress:
            return self.run(
                context, workflows.remove_floaters, context.active_object, method=self.method, k=self.k, std_ratio=self.std_ratio,
                radius=self.radius, min_neighbours=self.min_neighbours, progress=progress,
            )


class MLX3D_OT_compact(_SplatEdit, bpy.types.Operator):
    """Keep the most important splats and/or truncate SH (importance = opacity x max scale²)"""

    bl_idname = "mlx3d.compact"
    bl_label = "Compact Splats"

    max_gaussians: IntProperty(name="Max splats", default=0, min=0, description="Keep at most this many splats (0: no limit)")
    min_opacity: FloatProperty(name="Min opacity", default=0.0, min=0.0, max=1.0)
    sh_degree: EnumProperty(name="SH degree", items=KEEP_SH_ITEMS, default="KEEP")

    def execute(self, context):
        return self.run(
            context, workflows.compact_object, context.active_object, max_gaussians=self.max_gaussians or None,
            min_opacity=self.min_opacity, sh_degree=_degree(self.sh_degree),
        )


class MLX3D_OT_show_ellipsoids(bpy.types.Operator):
    """Show each splat as an ellipsoid (2 standard deviations) for close inspection, or go back to points"""

    bl_idname = "mlx3d.show_ellipsoids"
    bl_label = "Show Ellipsoids"
    bl_options = {"REGISTER", "UNDO"}

    show: BoolProperty(name="Show", default=True)

    @classmethod
    def poll(cls, context):
        return is_splat_object(context.active_object)

    def execute(self, context):
        display.set_ellipsoids(context.active_object, self.show)
        return {"FINISHED"}


def _select_only(context, obj):
    """Make ``obj`` the only selected and the active object."""
    context.view_layer.update()  # a newly linked object has no base in the view layer before this
    for other in context.view_layer.objects:
        if other is not None and other.select_get():
            other.select_set(False)
    if obj.name in context.view_layer.objects:
        obj.select_set(True)
        context.view_layer.objects.active = obj


# Events a running operator lets through to the 3D viewport, so the view can be orbited, panned and zoomed meanwhile.
_VIEW_EVENTS = {
    "MOUSEMOVE", "INBETWEEN_MOUSEMOVE", "MIDDLEMOUSE", "WHEELUPMOUSE", "WHEELDOWNMOUSE", "WHEELINMOUSE", "WHEELOUTMOUSE",
    "TRACKPADPAN", "TRACKPADZOOM", "MOUSEROTATE", "MOUSESMARTZOOM", "LEFT_SHIFT", "RIGHT_SHIFT", "LEFT_CTRL", "RIGHT_CTRL",
    "LEFT_ALT", "RIGHT_ALT", "OSKEY", "NUMPAD_0", "NUMPAD_1", "NUMPAD_2", "NUMPAD_3", "NUMPAD_4", "NUMPAD_5", "NUMPAD_6",
    "NUMPAD_7", "NUMPAD_8", "NUMPAD_9", "NUMPAD_PERIOD", "NUMPAD_PLUS", "NUMPAD_MINUS", "HOME",
}


class _ModalWork:
    """Plumbing of operators that do one unit of work per timer tick: the timer,
    status-bar progress, header text, event routing and handing the session back
    at the end. Subclasses give ``_tick`` (one unit of work) and ``_end``, or
    their own ``_escape``."""

    _session = None
    _timer = None
    _area = None
    # Events other than the timer and Esc that reach the rest of Blender while the work runs:
    # "NONE" (the scene stays still), "VIEW" (viewport navigation) or "ALL".
    PASS_EVENTS = "VIEW"

    def modal(self, context, event):
        if self._session is None:
            return {"CANCELLED"}
        if event.type == "ESC" and event.value == "PRESS":
            return self._escape(context)
        if event.type == "TIMER":
            return self._tick(context)
        if self.PASS_EVENTS == "ALL" or (self.PASS_EVENTS == "VIEW" and (event.type in _VIEW_EVENTS or event.type.startswith("NDOF"))):
            return {"PASS_THROUGH"}
        return {"RUNNING_MODAL"}

    def _escape(self, context):
        return self._end(context, cancelled=True)

    def _start_modal(self, context, total: int, text: str):
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, total)
        self._area = context.area
        self._header(text)
        return {"RUNNING_MODAL"}

    def _header(self, text):
        try:
            if self._area is not None:
                self._area.header_text_set(text)
        except ReferenceError:
            self._area = None

    def _stop(self, context):
        """Remove the timer, progress and header text; returns the session, which the operator lets go of."""
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        self._header(None)
        session, self._session = self._session, None
        return session


class MLX3D_OT_capture_dataset(_ModalWork, bpy.types.Operator):
    """Render the scene's meshes from an orbit of cameras (or the scene cameras) with Cycles into a training dataset: images, transforms.json, a COLMAP model and initial points. Esc cancels and keeps the views rendered so far"""

    bl_idname = "mlx3d.capture_dataset"
    bl_label = "Capture Dataset"
    bl_options = {"REGISTER"}
    PASS_EVENTS = "NONE"  # the scene stays still while it is captured

    directory: StringProperty(name="Folder", subtype="DIR_PATH", default="", description="Output folder of the dataset", options=BLEND_RELATIVE_PATH)
    selected_only: BoolProperty(name="Selected only", default=False, description="Capture the selected meshes (else every visible mesh)")
    use_scene_cameras: BoolProperty(name="Scene cameras", default=False, description="Render from the scene's cameras instead of an orbit")
    num_views: IntProperty(name="Views", default=72, min=1, description="Orbit views, spread over the elevation rings")
    radius: FloatProperty(name="Radius", default=0.0, min=0.0, subtype="DISTANCE", description="Orbit radius (0: 2.2 x the bounding-sphere radius)")
    elevations: StringProperty(name="Elevations", default="-10, 20, 45", description="Elevation rings in degrees, comma separated")
    resolution: IntVectorProperty(name="Resolution", size=2, default=(256, 256), min=4, description="Image width and height in pixels")
    samples: IntProperty(name="Samples", default=32, min=1, description="Cycles samples per pixel")
    num_points: IntProperty(name="Points", default=20000, min=1, description="Initial points sampled on the surfaces")
    test_every: IntProperty(name="Test every", default=8, min=0, description="Hold out every n-th frame for testing (0: none)")
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of the point sampling")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def _session_kwargs(self, context):
        if not self.directory:
            raise capture.CaptureError("choose an output folder for the dataset")
        try:
            elevations = [float(v) for v in self.elevations.replace(";", ",").split(",") if v.strip()]
        except ValueError:
            raise capture.CaptureError(f"elevations must be numbers separated by commas, got '{self.elevations}'") from None
        objects = None
        if self.selected_only:
            objects = [o for o in context.selected_objects if o.type == "MESH"]
            if not objects:
                raise capture.CaptureError("no mesh objects selected")
        return dict(
            objects=objects, use_scene_cameras=self.use_scene_cameras, num_views=self.num_views,
            radius=self.radius or None, elevations_deg=elevations, resolution=tuple(self.resolution), samples=self.samples,
            num_points=self.num_points, test_every=self.test_every, seed=self.seed,
        )

    def execute(self, context):
        try:
            kwargs = self._session_kwargs(context)
            with _Progress(context) as progress:
                _, messages = capture.capture_dataset(bpy.path.abspath(self.directory), scene=context.scene, progress=progress, **kwargs)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _report_all(self, messages)
        return {"FINISHED"}

    def invoke(self, context, event):
        if context.window is None:  # no event loop (background): render everything now
            return self.execute(context)
        try:
            kwargs = self._session_kwargs(context)
            self._session = capture.CaptureSession(bpy.path.abspath(self.directory), scene=context.scene, view_layer=context.view_layer, **kwargs)
            self._session.start()
        except (ValueError, OSError, RuntimeError) as exc:
            if self._session is not None:
                self._session.close()
                self._session = None
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._start_modal(context, self._session.total, f"Capturing dataset: view 0 of {self._session.total} (Esc to cancel)")

    def _end(self, context, cancelled=False, error=None):
        session = self._stop(context)
        messages = []
        try:
            session.close()
            if error is None:
                _, messages = session.finish(cancelled=cancelled)
        except (ValueError, OSError, RuntimeError) as exc:
            error = error or str(exc)
        if error is not None:
            self.report({"ERROR"}, error)
            return {"CANCELLED"}
        _report_all(self, messages)
        return {"CANCELLED"} if cancelled else {"FINISHED"}

    def _tick(self, context):
        try:
            done = self._session.step()
        except (ValueError, OSError, RuntimeError) as exc:
            return self._end(context, error=str(exc))
        context.window_manager.progress_update(done)
        self._header(f"Capturing dataset: view {done} of {self._session.total} (Esc to cancel)")
        if self._session.done:
            return self._end(context)
        return {"RUNNING_MODAL"}

    def cancel(self, context):
        if self._session is not None:
            self._end(context, cancelled=True)


class _TrainOptions:
    """The training options of Train Splats, shared with Train from Photos, which hands them on."""

    method: EnumProperty(name="Method", items=train.METHOD_ITEMS, default="vanilla")
    steps: IntProperty(name="Steps", default=30000, min=1, description="Training steps (the schedules are laid out over them)")
    max_gaussians: IntProperty(name="Max Gaussians", default=0, min=0, description="Cap on the number of Gaussians (0: the method's default: no cap for Vanilla and 2DGS; MCMC grows to one per pixel of a training image, at least twice its start)")
    sh_degree: IntProperty(name="SH degree", default=3, min=0, max=3, description="Spherical-harmonics degree of the view-dependent colour")
    background: EnumProperty(name="Background", items=train.BACKGROUND_ITEMS, default="black")
    update_every: IntProperty(name="Update every", default=100, min=1, description="Training steps between updates of the splat object")

    TRAIN_OPTIONS = ("method", "steps", "max_gaussians", "sh_degree", "background", "update_every")

    def train_options(self) -> dict:
        return {name: getattr(self, name) for name in self.TRAIN_OPTIONS}


class MLX3D_OT_train(_TrainOptions, _ModalWork, bpy.types.Operator):
    """Train 3D Gaussians on a dataset folder (COLMAP, NeRF-synthetic or nerfstudio, e.g. a captured one); the splat object updates while it trains. Esc stops and keeps the result so far"""

    bl_idname = "mlx3d.train"
    bl_label = "Train Splats"
    bl_options = {"UNDO"}  # no redo panel: adjusting a setting there would retrain from scratch, blocking Blender

    directory: StringProperty(name="Dataset", subtype="DIR_PATH", default="", options=BLEND_RELATIVE_PATH,
                              description="Dataset folder (empty: the panel's dataset folder, where Capture Dataset writes)")

    TICK_SECONDS = 0.15  # training time per timer tick, so Blender stays responsive

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def _new_session(self, context):
        folder = self.directory
        if not folder:
            settings = getattr(context.scene, "mlx3d_splats", None)
            folder = settings.capture_dir if settings is not None else ""
        if not folder:
            raise train.TrainError("choose a dataset folder (or capture one with Capture Dataset)")
        with _Progress(context) as progress:  # the initial model's plane sweep can take half a minute
            return train.TrainSession(
                bpy.path.abspath(folder), method=self.method, steps=self.steps, max_gaussians=self.max_gaussians or None,
                sh_degree=self.sh_degree, background=self.background, update_every=self.update_every,
                collection=context.collection, start_progress=progress,
            )


    def _report_end(self, context, obj, messages, error):
        if error is not None:
            self.report({"ERROR"}, messages[0])
            messages = messages[1:]
        _report_all(self, messages)
        _select_only(context, obj)

    def execute(self, context):
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            session = self._new_session(context)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        error = None
        with _Progress(context) as progress:
            try:
                session.run(progress=lambda done, total, status: progress(done, total))
            except (ValueError, OSError, RuntimeError) as exc:
                error = str(exc)
        try:
            obj, messages = session.finish(error=error)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self._report_end(context, obj, messages, error)
        return {"FINISHED"}

    def invoke(self, context, event):
        if context.window is None:  # no event loop (background): train to the end now
            return self.execute(context)
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            self._session = self._new_session(context)
            _select_only(context, self._session.update_object())  # the initial Gaussians, shown at once
        except (ValueError, OSError, RuntimeError) as exc:
            self._session = None
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._start_modal(context, self._session.steps, "Training: starting (Esc to stop and keep the result)")

    def _redraw(self, context):
        for area in context.screen.areas if context.screen else ():
            if area.type == "VIEW_3D":
                area.tag_redraw()

    def _end(self, context, cancelled=False, error=None):
        session = self._stop(context)
        try:
            obj, messages = session.finish(cancelled=cancelled, error=error)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self._report_end(context, obj, messages, error)
        self._redraw(context)
        return {"FINISHED"}  # also after Esc or an error: the object kept in the scene gets its undo step

    def _tick(self, context):
        session = self._session
        updated = session.object_step
        try:
            session.step(session.steps, max_seconds=self.TICK_SECONDS)
        except (ValueError, OSError, RuntimeError) as exc:
            return self._end(context, error=str(exc))
        status = session.status()
        context.window_manager.progress_update(status["step"])
        self._header(f"Training: {train.format_status(status)}  (Esc to stop and keep the result)")
        if session.object_step != updated:
            self._redraw(context)
        if session.done:
            return self._end(context)
        return {"RUNNING_MODAL"}

    def cancel(self, context):
        # Blender ends the operator (a file is loaded, the window closes): stop without touching the scene,
        # whose object holds the last update.
        if self._session is not None:
            self._stop(context)


class MLX3D_OT_train_from_photos(_TrainOptions, _ModalWork, bpy.types.Operator):
    """Solve the cameras of a folder of photos or a video (structure from motion with pycolmap) into a dataset folder, add them as cameras and the sparse points as a point cloud in a new collection, then train splats on them as Train Splats does. Esc cancels the solve and changes nothing"""

    bl_idname = "mlx3d.train_from_photos"
    bl_label = "Train from Photos"
    bl_options = {"UNDO"}  # no redo panel: it would solve and train again

    source: StringProperty(name="Photos", subtype="FILE_PATH", default="", options=BLEND_RELATIVE_PATH,
                           description="A folder of photos (or any photo in it), or a video file")
    directory: StringProperty(name="Dataset folder", subtype="DIR_PATH", default="", options=BLEND_RELATIVE_PATH,
                              description="Where the solved dataset is written: a new or empty folder (empty: <photos>_dataset next to the .blend file, or in the temporary folder)")
    matching: EnumProperty(name="Matching", items=photos.MATCHING_ITEMS, default="auto", description="Which pairs of photos are matched")
    max_image_size: IntProperty(name="Max image size", default=1600, min=64, description="Features are found on photos scaled to at most this many pixels on their longer side")
    fps: FloatProperty(name="Video fps", default=0.0, min=0.0, description="Video: frames taken per second, the sharpest of each interval (0: the default, 2)")
    train: BoolProperty(name="Train", default=True, description="Train splats on the solved cameras (off: only solve them and add them to the scene)")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def _new_job(self):
        if not self.source:
            raise photos.PosesError("choose a folder of photos (or one photo in it) or a video file")
        source = bpy.path.abspath(self.source)
        out = bpy.path.abspath(self.directory) if self.directory else photos.default_dataset_folder(source, bpy.data.filepath)
        return photos.PhotoSolve(source, out, fps=self.fps or None, matching=self.matching, max_image_size=self.max_image_size)

    def _cancelled(self, job):
        self.report({"INFO"}, f"solving the cameras of '{job.name}' was cancelled; nothing was added or written")
        return {"CANCELLED"}

    def _add_and_train(self, context, job, invoke: bool):
        """The solved cameras and points into the scene, then Train Splats on the dataset (its own modal run when invoked)."""
        try:
            _, _, _, messages = photos.add_solved(job.out, name=job.name, parent=context.collection, scene=context.scene)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, f"{exc} (the solved dataset is in {job.out})")
            return {"CANCELLED"}
        _report_all(self, job.messages() + messages)
        if self.train:
            try:
                bpy.ops.mlx3d.train("INVOKE_DEFAULT" if invoke else "EXEC_DEFAULT", directory=str(job.out), **self.train_options())
            except RuntimeError as exc:  # Train Splats reported an error: the cameras stay, the dataset is on disk
                self.report({"ERROR"}, f"training on {job.out} did not start: {exc}")
        return {"FINISHED"}

    def execute(self, context):
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            job = self._new_job()
            with _Progress(context) as progress:
                job.run(progress=lambda stage, done, total: progress(int(1000 * job.fraction()), 1000))
        except KeyboardInterrupt:
            return self._cancelled(job)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._add_and_train(context, job, invoke=False)

    def invoke(self, context, event):
        if context.window is None or bpy.app.background:  # no event loop: solve (and train) to the end now
            return self.execute(context)
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            self._session = self._new_job()
            self._session.start()
        except (ValueError, OSError, RuntimeError) as exc:
            self._session = None
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._start_modal(context, 1000, self._text())

    def _text(self):
        job = self._session
        return f"Solving the cameras of '{job.name}': {job.status()} (Esc to cancel)"

    def _escape(self, context):
        job = self._session
        job.cancel()
        job.wait()  # pycolmap stops within about a second; the solve then removes its scratch folder
        job.discard()  # solved just before Esc: the dataset goes too
        self._stop(context)
        return self._cancelled(job)

    def _tick(self, context):
        job = self._session
        if job.running:
            context.window_manager.progress_update(int(1000 * job.fraction()))
            self._header(self._text())
            return {"RUNNING_MODAL"}
        self._stop(context)
        if job.cancelled:
            return self._cancelled(job)
        if job.error is not None:
            self.report({"ERROR"}, str(job.error))
            return {"CANCELLED"}
        return self._add_and_train(context, job, invoke=True)

    def cancel(self, context):
        # Blender ends the operator (a file is loaded, the window closes): stop the solve, add nothing.
        if self._session is not None:
            job = self._session
            job.cancel()
            job.wait()
            job.discard()
            self._stop(context)


class MLX3D_OT_render(bpy.types.Operator):
    """Render the current frame from the scene camera: Blender's objects with the scene's engine, the splat objects with mlx3d, composited by depth, into the image 'MLX3D Render'"""

    bl_idname = "mlx3d.render"
    bl_label = "Render Image"
    bl_options = {"REGISTER"}

    antialias: BoolProperty(name="Antialias", default=False, description="Mip-Splatting opacity compensation for the 2D blur")
    filepath: StringProperty(name="Save to", subtype="FILE_PATH", default="", description="Also save a PNG here (optional)", options=BLEND_RELATIVE_PATH)

    def execute(self, context):
        try:
            with _Progress(context) as progress:
                progress(0, 1)
                image, messages = scene_render.render_image(
                    context.scene, view_layer=context.view_layer, antialias=self.antialias,
                    filepath=bpy.path.abspath(self.filepath) if self.filepath else None,
                )
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _show_image(context, image)
        _report_all(self, messages)
        return {"FINISHED"}


def _show_image(context, image):
    """Show ``image`` in the open Image Editors."""
    for area in context.screen.areas if context.screen else ():
        if area.type == "IMAGE_EDITOR":
            area.spaces.active.image = image


class MLX3D_OT_render_animation(_ModalWork, bpy.types.Operator):
    """Render the scene's frame range like Render Image, each frame written to the scene's output folder and format as soon as it is done (a movie is encoded at the end). Esc stops after the current frame and keeps the frames written"""

    bl_idname = "mlx3d.render_animation"
    bl_label = "Render Animation"
    bl_options = {"REGISTER"}
    PASS_EVENTS = "NONE"  # the scene changes frame while it renders

    antialias: BoolProperty(name="Antialias", default=False, description="Mip-Splatting opacity compensation for the 2D blur")

    def _new_session(self, context):
        return scene_render.AnimationRender(context.scene, view_layer=context.view_layer, antialias=self.antialias)

    def execute(self, context):
        try:
            session = self._new_session(context)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        try:
            with _Progress(context) as progress:
                while not session.done:
                    session.step()
                    progress(len(session.written), session.total)
        except (ValueError, OSError, RuntimeError) as exc:
            session.close()
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _report_all(self, session.close() + [session.summary()])
        return {"FINISHED"}

    def invoke(self, context, event):
        if context.window is None:  # no event loop (background): render everything now
            return self.execute(context)
        try:
            self._session = self._new_session(context)
        except (ValueError, OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._start_modal(context, self._session.total, self._text())

    def _text(self):
        s = self._session
        return f"Rendering frame {s.frames[min(len(s.written), s.total - 1)]} ({len(s.written)} of {s.total} done; Esc stops after this frame)"

    def _end(self, context, cancelled=False, error=None):
        session = self._stop(context)
        messages = []
        try:
            messages = session.close()
        except (ValueError, OSError, RuntimeError) as exc:
            error = error or str(exc)
        if error is not None:
            self.report({"ERROR"}, error)
            return {"CANCELLED"}
        if getattr(session, "last", None) is not None:
            _show_image(context, scene_render.show_frame(session.last.rgba))
        _report_all(self, messages + [session.summary() + (" (cancelled)" if cancelled else "")])
        return {"CANCELLED"} if cancelled else {"FINISHED"}

    def _tick(self, context):
        try:
            self._session.step()
        except (ValueError, OSError, RuntimeError) as exc:
            return self._end(context, error=str(exc))
        context.window_manager.progress_update(len(self._session.written))
        if self._session.done:
            return self._end(context)
        self._header(self._text())
        return {"RUNNING_MODAL"}

    def cancel(self, context):
        if self._session is not None:
            self._end(context, cancelled=True)


class MLX3D_OT_extract_mesh(_ModalWork, bpy.types.Operator):
    """Extract a triangle mesh of the active splat object's surface as a child of the splat object: by depth fusion (depth and colour rendered from views around the splats or from a collection of cameras, unseen space left empty) or by Poisson reconstruction (a closed surface through the splats as discs). Esc cancels and adds nothing"""

    bl_idname = "mlx3d.extract_mesh"
    bl_label = "Extract Mesh"
    bl_options = {"REGISTER", "UNDO"}

    method: EnumProperty(name="Method", items=workflows.MESH_METHOD_ITEMS, default="FUSION", description="How the surface is found")
    cameras: StringProperty(name="Cameras", default="",
                            search=lambda self, context, text: [c.name for c in bpy.data.collections if any(o.type == "CAMERA" for o in c.all_objects)],
                            description="Name of a collection of cameras to render the depth from (fusion; Poisson turns each splat's normal "
                                        "toward the nearest), each at the scene's output resolution; empty: 60 views around the splats")
    box: StringProperty(name="Box", default="",
                        search=lambda self, context, text: [o.name for o in bpy.data.objects if o.type in {"MESH", "EMPTY"} and not is_splat_object(o)],
                        description="Fusion: name of a mesh or empty whose bounds (as placed) are the volume to mesh, e.g. around an object "
                                    "standing on a floor; empty: the surfaces the views share")
    resolution: IntProperty(name="Resolution", default=128, min=8, max=512,
                            description="Voxels along the longest side of the surface (fusion) or of the grid (Poisson); memory and time grow with its cube")
    cleanup: FloatProperty(name="Cleanup", default=0.01, min=0.0, max=1.0,
                           description="Drop pieces with fewer faces than this fraction of the largest piece's (0: keep every piece)")
    faces: IntProperty(name="Faces", default=0, min=0, description="At most this many triangles, fewer where the mesh is simplified (0: as extracted)")
    min_opacity: FloatProperty(name="Min opacity", default=0.01, min=0.0, max=1.0, description="Poisson: leave out splats less opaque than this")
    max_points: IntProperty(name="Max points", default=200000, min=0, description="Poisson: use at most this many splats as surface samples, the most important first (0: all)")
    trim: FloatProperty(name="Trim", default=workflows.DEFAULT_TRIM, min=0.0, description="Poisson: remove surface farther than this many voxels from any splat (0: off)")

    @classmethod
    def poll(cls, context):
        if is_splat_object(context.active_object):
            return True
        cls.poll_message_set("the active object is not a splat object")
        return False

    def _cameras(self):
        """The camera objects of the collection named by ``cameras`` (sorted by name), or None for views around the splats."""
        if not self.cameras:
            return None
        collection = bpy.data.collections.get(self.cameras)
        if collection is None:
            raise workflows.MeshingError(f"no collection named '{self.cameras}' (choose a collection of cameras, or none for views around the splats)")
        cameras = sorted((o for o in collection.all_objects if o.type == "CAMERA"), key=lambda o: o.name)
        if not cameras:
            raise workflows.MeshingError(f"the collection '{self.cameras}' holds no camera")
        return cameras

    def _bounds(self, context):
        """World bounds of the object named by ``box`` (fusion), or None for the default volume."""
        if not self.box or self.method != "FUSION":
            return None
        box = bpy.data.objects.get(self.box)
        if box is None:
            raise workflows.MeshingError(f"no object named '{self.box}' (choose a mesh or empty as the box, or none)")
        if box == context.active_object:
            raise workflows.MeshingError("the box must be another object than the splat object")
        return workflows.box_world_bounds(box)

    def _job(self, context):
        return workflows.MeshExtraction(context.active_object, method=self.method.lower(), cameras=self._cameras(),
                                        resolution=self.resolution, cleanup=self.cleanup, faces=self.faces, min_opacity=self.min_opacity,
                                        max_points=self.max_points, trim=self.trim, bounds=self._bounds(context))

    def _add(self, context, job):
        try:
            obj, messages = job.add_object()
        except workflows.ExtractionCancelled as exc:
            self.report({"INFO"}, f"{exc}; nothing was added")
            return {"CANCELLED"}
        except (ValueError, OSError, RuntimeError, MemoryError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        _select_only(context, obj)
        _report_all(self, messages)
        return {"FINISHED"}

    def execute(self, context):
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            job = self._job(context)
            with _Progress(context) as progress:
                job.compute(progress)
        except (ValueError, OSError, RuntimeError, MemoryError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._add(context, job)

    def invoke(self, context, event):
        if context.window is None or bpy.app.background:  # no event loop: extract now
            return self.execute(context)
        if context.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        try:
            self._session = self._job(context)
        except (ValueError, OSError, RuntimeError, MemoryError) as exc:
            self._session = None
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        job = self._session
        if not job.views_left:  # Poisson: straight to the worker
            job.start()
        return self._start_modal(context, 100, self._text(job))

    def _text(self, job):
        if job.views_left:
            done, count = len(job.views), len(job.cameras)
            return f"Extracting mesh from '{job.source_name}': rendering view {done + 1}/{count} (Esc to cancel)"
        done, total = job.progress
        return f"Extracting mesh from '{job.source_name}': {int(100 * done / max(total, 1))}% (Esc to cancel)"

    def _escape(self, context):
        job = self._session
        job.cancel()  # the worker stops at its next progress report and its result is dropped
        self._stop(context)
        self.report({"INFO"}, f"mesh extraction from '{job.source_name}' cancelled; nothing was added")
        return {"CANCELLED"}

    def _tick(self, context):
        job = self._session
        if job.views_left:  # one view per tick, on the main thread (MLX), so Blender stays responsive
            try:
                job.render_next()
            except (ValueError, OSError, RuntimeError, MemoryError) as exc:
                self._stop(context)
                self.report({"ERROR"}, str(exc))
                return {"CANCELLED"}
            if not job.views_left:
                job.start()  # fusing needs no MLX: on the worker thread
        elif not job.running:
            self._stop(context)
            return self._add(context, job)
        done, total = job.progress
        context.window_manager.progress_update(int(100 * done / max(total, 1)))
        self._header(self._text(job))
        return {"RUNNING_MODAL"}

    def cancel(self, context):
        # Blender ends the operator (a file is loaded, the window closes): stop the worker, add nothing.
        if self._session is not None:
            self._session.cancel()
            self._stop(context)


class MLX3D_OT_benchmark(_ModalWork, bpy.types.Operator):
    """Measure on this machine what accuracy costs: train and render a fixed set of configurations on a built-in scene and write a markdown report with plots. Runs in a separate process; Esc cancels and writes nothing"""

    bl_idname = "mlx3d.benchmark"
    bl_label = "Benchmark this machine"
    bl_options = {"REGISTER"}
    PASS_EVENTS = "ALL"  # Blender stays usable while the benchmark runs in its own process

    directory: StringProperty(name="Folder", subtype="DIR_PATH", default="", options=BLEND_RELATIVE_PATH,
                              description="Output folder of the report (empty: mlx3d_accuracy next to the .blend file, or in the temporary folder)")
    full: BoolProperty(name="Full run", default=False, description="The full benchmark (under an hour on 2 cores) instead of the quick one (a few minutes)")
    tiny: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"})  # seconds-long sizes, for tests

    def _new_job(self):
        folder = bpy.path.abspath(self.directory) if self.directory else benchmark.default_folder(bpy.data.filepath)
        return benchmark.BenchmarkJob(folder, "tiny" if self.tiny else "full" if self.full else "quick")

    def _show(self, context, path):
        """Open the report in Blender's text editor (in a Text Editor area when there is one) and say where it is."""
        text = bpy.data.texts.load(path)
        for area in context.screen.areas if context.screen else ():
            if area.type == "TEXT_EDITOR":
                area.spaces.active.text = text
        print(f"mlx3d benchmark report: {path}")
        self.report({"INFO"}, f"benchmark report: {path} (open in the Text Editor as '{text.name}'; the PNG plots are next to it)")
        return {"FINISHED"}

    def execute(self, context):
        try:
            job = self._new_job()
        except benchmark.BenchmarkError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        try:
            with _Progress(context) as progress:
                path = job.run(progress=lambda done, total, status: progress(done, total))
        except (benchmark.BenchmarkError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        except KeyboardInterrupt:
            job.cancel()
            self.report({"INFO"}, "the benchmark was cancelled; nothing was written")
            return {"CANCELLED"}
        return self._show(context, path)

    def invoke(self, context, event):
        if context.window is None or bpy.app.background:  # no event loop: run to the end now
            return self.execute(context)
        try:
            self._session = self._new_job()
            self._session.start()
        except (benchmark.BenchmarkError, OSError) as exc:
            self._session = None
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._start_modal(context, 1000, "Benchmarking this machine: starting (Esc to cancel)")

    def _escape(self, context):
        self._session.cancel()
        self._stop(context)
        self.report({"INFO"}, "the benchmark was cancelled; nothing was written")
        return {"CANCELLED"}

    def _tick(self, context):
        job = self._session
        if job.running:
            context.window_manager.progress_update(job.progress)
            self._header(f"Benchmarking this machine: {job.progress / 10:.0f}%, {job.status} (Esc to cancel)")
            return {"RUNNING_MODAL"}
        self._stop(context)
        try:
            path = job.finish()
        except benchmark.BenchmarkError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self._show(context, path)

    def cancel(self, context):
        # Blender ends the operator (a file is loaded, the window closes): stop the benchmark.
        if self._session is not None:
            self._session.cancel()
            self._stop(context)


class MLX3D_FH_gaussian_splat_ply(bpy.types.FileHandler):
    """Drag and drop splat files onto the 3D viewport to import them"""

    bl_idname = "MLX3D_FH_gaussian_splat_ply"
    bl_label = "Gaussian Splats"
    bl_import_operator = IMPORT_SCENE_OT_gaussian_splat_ply.bl_idname
    bl_file_extensions = ";".join(ext for f in FORMATS for ext in f.extensions if ext.startswith("."))

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type == "VIEW_3D"


def menu_import(self, context):
    self.layout.operator(IMPORT_SCENE_OT_gaussian_splat_ply.bl_idname, text="Gaussian Splats (.ply .spz .splat .sog .glb ...)")


def menu_export(self, context):
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat_ply.bl_idname, text="Gaussian Splats (.ply .spz .splat .sog .glb ...)")


CLASSES = (
    IMPORT_SCENE_OT_gaussian_splat_ply,
    EXPORT_SCENE_OT_gaussian_splat_ply,
    MLX3D_OT_merge_selected,
    MLX3D_OT_apply_transform,
    MLX3D_OT_crop_to_box,
    MLX3D_OT_remove_floaters,
    MLX3D_OT_compact,
    MLX3D_OT_show_ellipsoids,
    MLX3D_OT_render,
    MLX3D_OT_render_animation,
    MLX3D_OT_capture_dataset,
    MLX3D_OT_train,
    MLX3D_OT_train_from_photos,
    MLX3D_OT_extract_mesh,
    MLX3D_OT_benchmark,
    MLX3D_FH_gaussian_splat_ply,
)
