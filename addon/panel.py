"""The N-panel ("Splats" tab in the 3D viewport sidebar) and its scene settings."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty

from . import display, operators, photos, train, workflows
from .splat_object import is_splat_object


class MLX3D_PG_settings(bpy.types.PropertyGroup):
    """Panel parameters, stored with the scene."""

    crop_box: PointerProperty(name="Box", type=bpy.types.Object, poll=lambda self, obj: obj.type in {"MESH", "EMPTY"})
    crop_keep_inside: BoolProperty(name="Keep inside", default=True)
    floater_method: EnumProperty(name="Method", items=[("STATISTICAL", "Statistical", ""), ("RADIUS", "Radius", "")], default="STATISTICAL")
    floater_k: IntProperty(name="Neighbours", default=25, min=1)
    floater_std: FloatProperty(name="Std ratio", default=10.5, min=0.0)
    floater_radius: FloatProperty(name="Radius", default=0.05, min=0.0, subtype="DISTANCE")
    floater_min_neighbours: IntProperty(name="Min neighbours", default=4, min=1)
    compact_max: IntProperty(name="Max splats", default=0, min=0, description="0: no limit")
    compact_min_opacity: FloatProperty(name="Min opacity", default=0.0, min=0.0, max=1.0)
    compact_sh: EnumProperty(name="SH degree", items=operators.KEEP_SH_ITEMS, default="KEEP")
    mesh_method: EnumProperty(name="Method", items=workflows.MESH_METHOD_ITEMS, default="FUSION", description="How the surface is found")
    mesh_cameras: PointerProperty(name="Cameras", type=bpy.types.Collection, poll=lambda self, coll: any(o.type == "CAMERA" for o in coll.all_objects),
                                  description="A collection of cameras to render the depth from (fusion; Poisson turns each splat's normal toward "
                                              "the nearest), each at the scene's output resolution; none: 60 views around the splats")
    mesh_box: PointerProperty(name="Box", type=bpy.types.Object, poll=lambda self, obj: obj.type in {"MESH", "EMPTY"},
                              description="Fusion: a mesh or empty whose bounds (as placed) are the volume to mesh, e.g. around an object "
                                          "standing on a floor; none: the surfaces the views share")
    mesh_resolution: IntProperty(name="Resolution", default=128, min=8, max=512, description="Voxels along the longest side of the surface (fusion) or of the grid (Poisson)")
    mesh_cleanup: FloatProperty(name="Cleanup", default=0.01, min=0.0, max=1.0, description="Drop pieces with fewer faces than this fraction of the largest piece's (0: keep every piece)")
    mesh_faces: IntProperty(name="Faces", default=0, min=0, description="At most this many triangles (0: as extracted)")
    mesh_min_opacity: FloatProperty(name="Min opacity", default=0.01, min=0.0, max=1.0, description="Poisson: leave out splats less opaque than this")
    mesh_max_points: IntProperty(name="Max points", default=200000, min=0, description="Poisson: surface samples used at most (0: all)")
    mesh_trim: FloatProperty(name="Trim", default=workflows.DEFAULT_TRIM, min=0.0, description="Poisson: remove surface farther than this many voxels from any splat (0: off)")
    render_antialias: BoolProperty(name="Antialias", default=False)
    render_path: bpy.props.StringProperty(name="Save to", subtype="FILE_PATH", default="", options=operators.BLEND_RELATIVE_PATH)
    capture_dir: bpy.props.StringProperty(name="Folder", subtype="DIR_PATH", default="", description="Output folder of the dataset", options=operators.BLEND_RELATIVE_PATH)
    capture_views: IntProperty(name="Views", default=72, min=1, description="Orbit views, spread over the elevation rings")
    capture_radius: FloatProperty(name="Radius", default=0.0, min=0.0, subtype="DISTANCE", description="Orbit radius (0: 2.2 x the bounding-sphere radius)")
    capture_resolution: bpy.props.IntVectorProperty(name="Resolution", size=2, default=(256, 256), min=4)
    capture_samples: IntProperty(name="Samples", default=32, min=1, description="Cycles samples per pixel")
    capture_points: IntProperty(name="Points", default=20000, min=1, description="Initial points sampled on the surfaces")
    capture_scene_cameras: BoolProperty(name="Scene cameras", default=False, description="Render from the scene's cameras instead of an orbit")
    capture_selected_only: BoolProperty(name="Selected only", default=False, description="Capture the selected meshes (else every visible mesh)")
    train_method: EnumProperty(name="Method", items=train.METHOD_ITEMS, default="vanilla")
    train_steps: IntProperty(name="Steps", default=30000, min=1, description="Training steps")
    train_max_gaussians: IntProperty(name="Max Gaussians", default=0, min=0, description="Cap on the number of Gaussians (0: the method's default: no cap for Vanilla and 2DGS; MCMC grows to one per pixel of a training image, at least twice its start)")
    train_sh_degree: IntProperty(name="SH degree", default=3, min=0, max=3, description="Spherical-harmonics degree of the view-dependent colour")
    train_background: EnumProperty(name="Background", items=train.BACKGROUND_ITEMS, default="black")
    train_update_every: IntProperty(name="Update every", default=100, min=1, description="Training steps between updates of the splat object")
    photos_source: bpy.props.StringProperty(name="Photos", subtype="FILE_PATH", default="", options=operators.BLEND_RELATIVE_PATH,
                                            description="A folder of photos (or any photo in it), or a video file")
    photos_dir: bpy.props.StringProperty(name="Dataset folder", subtype="DIR_PATH", default="", options=operators.BLEND_RELATIVE_PATH,
                                         description="Where the solved dataset is written: a new or empty folder (empty: <photos>_dataset next to the .blend file, or in the temporary folder)")
    photos_matching: EnumProperty(name="Matching", items=photos.MATCHING_ITEMS, default="auto", description="Which pairs of photos are matched")
    photos_fps: FloatProperty(name="Video fps", default=0.0, min=0.0, description="Video: frames taken per second, the sharpest of each interval (0: the default, 2)")
    bench_dir: bpy.props.StringProperty(name="Folder", subtype="DIR_PATH", default="", options=operators.BLEND_RELATIVE_PATH,
                                        description="Output folder of the benchmark report (empty: mlx3d_accuracy next to the .blend file, or in the temporary folder)")
    bench_full: BoolProperty(name="Full run", default=False, description="The full benchmark (under an hour on 2 cores) instead of the quick one (a few minutes)")


_info_cache: dict = {}


def _cached_info(obj) -> dict:
    key = (obj.name, obj.data.name, len(obj.data.points), tuple(map(tuple, obj.matrix_world)))
    if key not in _info_cache:
        _info_cache.clear()
        _info_cache[key] = workflows.splat_info(obj)
    return _info_cache[key]


def _section(layout, title: str, settings, operator, icon: str, fields: dict):
    """A titled column showing ``fields`` (operator property -> setting) and a button passing them on."""
    col = layout.column(align=True)
    col.label(text=title)
    for setting in fields.values():
        col.prop(settings, setting)
    op = col.operator(operator.bl_idname, icon=icon)
    for prop, setting in fields.items():
        setattr(op, prop, getattr(settings, setting))
    return col


class _SplatsTab:
    """Where the panels live: the 3D viewport's sidebar (N-panel), tab "Splats"."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Splats"


class _SplatsSubpanel(_SplatsTab):
    bl_parent_id = "VIEW3D_PT_mlx3d_splats"


class VIEW3D_PT_mlx3d_splats(_SplatsTab, bpy.types.Panel):
    bl_label = "Gaussian Splats"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.mlx3d_splats
        row = layout.row(align=True)
        row.operator(operators.IMPORT_SCENE_OT_gaussian_splat_ply.bl_idname, text="Import", icon="IMPORT")
        row.operator(operators.EXPORT_SCENE_OT_gaussian_splat_ply.bl_idname, text="Export", icon="EXPORT")

        obj = context.active_object
        box = layout.box()
        if is_splat_object(obj):
            info = _cached_info(obj)
            box.label(text=obj.name, icon="POINTCLOUD_DATA")
            box.label(text=f"Splats: {info['count']:,}   SH degree: {info['sh_degree']}")
            box.label(text=f"Memory: {info['memory_bytes'] / 1e6:.1f} MB")
            lo, hi = info["bounds_min"], info["bounds_max"]
            if lo is not None:
                box.label(text="Min: " + "  ".join(f"{v:.3g}" for v in lo))
                box.label(text="Max: " + "  ".join(f"{v:.3g}" for v in hi))
            shown = display.has_ellipsoids(obj)
            op = box.operator(operators.MLX3D_OT_show_ellipsoids.bl_idname, text="Ellipsoids", icon="MESH_UVSPHERE", depress=shown)
            op.show = not shown
        else:
            box.label(text="No splat object active")

        col = layout.column(align=True)
        col.label(text="Compose")
        col.operator(operators.MLX3D_OT_merge_selected.bl_idname, icon="AUTOMERGE_ON")
        col.operator(operators.MLX3D_OT_apply_transform.bl_idname, icon="OBJECT_ORIGIN")
        col.prop(settings, "crop_box")
        col.prop(settings, "crop_keep_inside")
        sub = col.row()
        sub.enabled = settings.crop_box is not None
        op = sub.operator(operators.MLX3D_OT_crop_to_box.bl_idname, icon="MOD_BOOLEAN")
        op.box = settings.crop_box.name if settings.crop_box else ""
        op.keep_inside = settings.crop_keep_inside

        col = layout.column(align=True)
        col.label(text="Clean")
        col.prop(settings, "floater_method", text="")
        if settings.floater_method == "STATISTICAL":
            col.prop(settings, "floater_k")
            col.prop(settings, "floater_std")
        else:
            col.prop(settings, "floater_radius")
            col.prop(settings, "floater_min_neighbours")
        op = col.operator(operators.MLX3D_OT_remove_floaters.bl_idname, icon="BRUSH_DATA")
        op.method, op.k, op.std_ratio = settings.floater_method, settings.floater_k, settings.floater_std
        op.radius, op.min_neighbours = settings.floater_radius, settings.floater_min_neighbours

        _section(layout, "Compact", settings, operators.MLX3D_OT_compact, "MOD_DECIM",
                 {"max_gaussians": "compact_max", "min_opacity": "compact_min_opacity", "sh_degree": "compact_sh"})
        fields = {"method": "mesh_method", "resolution": "mesh_resolution", "cleanup": "mesh_cleanup", "faces": "mesh_faces"}
        if settings.mesh_method == "POISSON":
            fields.update(min_opacity="mesh_min_opacity", max_points="mesh_max_points", trim="mesh_trim")
        col = layout.column(align=True)
        col.label(text="Surface mesh")
        col.prop(settings, "mesh_method", text="")
        col.prop(settings, "mesh_cameras")
        if settings.mesh_method == "FUSION":
            col.prop(settings, "mesh_box")
        for setting in list(fields.values())[1:]:
            col.prop(settings, setting)
        op = col.operator(operators.MLX3D_OT_extract_mesh.bl_idname, icon="OUTLINER_OB_MESH")
        for prop, setting in fields.items():
            setattr(op, prop, getattr(settings, setting))
        op.cameras = settings.mesh_cameras.name if settings.mesh_cameras else ""  # the operator takes the collection's name
        op.box = settings.mesh_box.name if settings.mesh_box and settings.mesh_method == "FUSION" else ""
        col = _section(layout, "Render (scene camera)", settings, operators.MLX3D_OT_render, "RENDER_STILL",
                       {"antialias": "render_antialias", "filepath": "render_path"})
        op = col.operator(operators.MLX3D_OT_render_animation.bl_idname, icon="RENDER_ANIMATION")
        op.antialias = settings.render_antialias

        col = layout.column(align=True)
        col.label(text="Capture dataset")
        col.prop(settings, "capture_dir")
        col.prop(settings, "capture_scene_cameras")
        sub = col.column(align=True)
        sub.enabled = not settings.capture_scene_cameras
        sub.prop(settings, "capture_views")
        sub.prop(settings, "capture_radius")
        col.prop(settings, "capture_resolution")
        col.prop(settings, "capture_samples")
        col.prop(settings, "capture_points")
        col.prop(settings, "capture_selected_only")
        row = col.row()
        row.enabled = bool(settings.capture_dir)
        op = row.operator(operators.MLX3D_OT_capture_dataset.bl_idname, icon="RENDER_ANIMATION")
        op.directory, op.use_scene_cameras, op.num_views = settings.capture_dir, settings.capture_scene_cameras, settings.capture_views
        op.radius, op.resolution, op.samples = settings.capture_radius, settings.capture_resolution, settings.capture_samples
        op.num_points, op.selected_only = settings.capture_points, settings.capture_selected_only


class VIEW3D_PT_mlx3d_train(_SplatsSubpanel, bpy.types.Panel):
    """Train Gaussians on a dataset folder (by default the capture folder)"""

    bl_label = "Train"

    def draw(self, context):
        settings = context.scene.mlx3d_splats
        col = self.layout.column(align=True)
        col.prop(settings, "capture_dir", text="Dataset")
        col.prop(settings, "train_method")
        col.prop(settings, "train_steps")
        col.prop(settings, "train_max_gaussians")
        col.prop(settings, "train_sh_degree")
        col.prop(settings, "train_background")
        col.prop(settings, "train_update_every")
        row = col.row()
        row.enabled = bool(settings.capture_dir)
        op = row.operator(operators.MLX3D_OT_train.bl_idname, icon="PLAY")
        op.directory, op.method, op.steps = settings.capture_dir, settings.train_method, settings.train_steps
        op.max_gaussians, op.sh_degree, op.background = settings.train_max_gaussians, settings.train_sh_degree, settings.train_background
        op.update_every = settings.train_update_every
        stages, skipped, step = _planned_stages(context.scene, settings)
        box = self.layout.box()
        box.label(text=f"A step ({step:,}) runs:", icon="SEQ_STRIP_DUPLICATE")
        col = box.column(align=True)
        col.scale_y = 0.8
        for name in stages:
            col.label(text=name)
        box.label(text="Skipped: " + (", ".join(skipped) or "nothing"))


_plan_cache: dict = {}


def _planned_stages(scene, settings) -> tuple:
    """(stages, skipped, step) of a training step with the panel's settings (``mlx3d.training.plan``):
    the first step with every scheduled effect on, seen from the scene camera (a pinhole one without it)."""
    from mlx3d.cameras import Camera
    from mlx3d.training import TrainerConfig
    from mlx3d.training.plan import active_sh_degree, step_plan

    from .camera import camera_from_blender

    key = (settings.train_method, settings.train_steps, settings.train_sh_degree, scene.camera.name if scene.camera else None,
           scene.camera.data.type if scene.camera else None)
    if key not in _plan_cache:
        config = TrainerConfig(method=settings.train_method, steps=settings.train_steps)
        camera = camera_from_blender(scene.camera, scene) if scene.camera else Camera.look_at(eye=(0, -3, 1), at=(0, 0, 0), up=(0, 0, 1), width=64, height=64, fov=50.0)
        step = min(settings.train_steps - 1, max(config.geometry_from, config.densify_from, config.sh_increase_every * settings.train_sh_degree))
        plan = step_plan(config, camera, active_sh_degree(config, step, settings.train_sh_degree), step)
        _plan_cache.clear()
        _plan_cache[key] = (plan.stages, plan.skipped, step + 1)
    return _plan_cache[key]


class VIEW3D_PT_mlx3d_photos(_SplatsSubpanel, bpy.types.Panel):
    """Solve the cameras of your own photos (or a video), then train on them"""

    bl_label = "Train from Photos"

    def draw(self, context):
        settings = context.scene.mlx3d_splats
        col = self.layout.column(align=True)
        col.prop(settings, "photos_source")
        col.prop(settings, "photos_dir")
        col.prop(settings, "photos_matching")
        col.prop(settings, "photos_fps")
        col.label(text="Trains with the Train panel's settings")
        row = col.row()
        row.enabled = bool(settings.photos_source)
        op = row.operator(operators.MLX3D_OT_train_from_photos.bl_idname, icon="OUTLINER_OB_CAMERA")
        op.source, op.directory, op.matching, op.fps = settings.photos_source, settings.photos_dir, settings.photos_matching, settings.photos_fps
        op.method, op.steps, op.max_gaussians = settings.train_method, settings.train_steps, settings.train_max_gaussians
        op.sh_degree, op.background, op.update_every = settings.train_sh_degree, settings.train_background, settings.train_update_every


class VIEW3D_PT_mlx3d_benchmark(_SplatsSubpanel, bpy.types.Panel):
    """Measure what accuracy costs in time and memory on this machine"""

    bl_label = "Benchmark"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        _section(self.layout, "What accuracy costs here", context.scene.mlx3d_splats, operators.MLX3D_OT_benchmark, "TIME",
                 {"directory": "bench_dir", "full": "bench_full"})


CLASSES = (MLX3D_PG_settings, VIEW3D_PT_mlx3d_splats, VIEW3D_PT_mlx3d_train, VIEW3D_PT_mlx3d_photos, VIEW3D_PT_mlx3d_benchmark)
