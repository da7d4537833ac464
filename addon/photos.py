"""Cameras from a user's own photos in Blender: solve them, show them, train on them.

``mlx3d.sfm.solve_capture`` (pycolmap; bundled in the extension zips for
linux-x64, macos-arm64 and windows-x64) turns a folder of photos or a video
into a COLMAP dataset folder, set upright (+Z up, the scene at the origin,
cameras about 4 units away). This module runs it for the operator and the
headless script and shows the result:

- ``PhotoSolve``: one solve. The constructor checks the input (photos or a
  video, pycolmap, an output folder that is new or empty) before anything
  starts; ``run()`` solves in the calling thread, ``start()`` on a worker
  thread (pycolmap releases the GIL, so Blender stays responsive), followed
  with ``running``, ``stage``/``progress`` and ``status()``; ``cancel()``
  stops pycolmap within about a second and ``wait()`` joins the worker. A
  failed or cancelled solve leaves no files (``solve_capture`` works in a
  scratch folder) and touches no Blender data.
- ``add_solved(dataset)``: (main thread) one camera object per solved photo
  (pose and lens from ``camera.set_blender_camera``) and the sparse points as
  a point cloud with their colours (``Color``), all in a new collection;
  nothing is left behind if it fails.
- ``default_dataset_folder``: where a dataset goes when the user names no
  folder: ``<photos>_dataset`` next to the .blend file, or in the temporary
  folder, never an existing non-empty folder.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import bpy
import numpy as np

from mlx3d.datasets import load_dataset
from mlx3d.sfm import MATCHING, VIDEO_SUFFIXES, PosesError, is_video, list_photos, require_pycolmap, solve_capture
from mlx3d.sfm.solve import PHOTO_SUFFIXES

from .camera import set_blender_camera
from .display import attribute_material
from .splat_object import pointcloud_from_positions, srgb_to_linear
from .worker import WorkerJob

#: The stages ``solve_capture`` reports, in order ("frames" for a video only), and what they do.
STAGES = {
    "frames": "taking frames from the video",
    "photos": "reading photos",
    "features": "finding features",
    "matching": "matching photos",
    "mapping": "placing cameras",
}
MATCHING_ITEMS = [
    ("auto", "Auto", "Every pair up to 100 photos; neighbours in name order for more, and for a video"),
    ("exhaustive", "Exhaustive", "Match every pair of photos (slow for many photos)"),
    ("sequential", "Sequential", "Match each photo with its neighbours in name order (a video, a walk)"),
]
assert [item[0] for item in MATCHING_ITEMS] == list(MATCHING)
POINTS_MATERIAL = "MLX3D Sparse Points"
POINTS_COLOR = "Color"
#: Radius of the sparse points shown, in world units (the solved scene has its cameras about 4 units away).
POINTS_RADIUS = 0.01
#: Display size of the camera objects, in world units.
CAMERA_SIZE = 0.25
INFO_KEY = "mlx3d_poses"


def source_kind(path) -> tuple[Path, bool]:
    """(folder or video, is a video) for what the user picked: a folder of photos, a video file,
    or one photo (its folder). A PosesError names what is wrong."""
    if path is None or not os.fspath(path):
        raise PosesError("choose a folder of photos (or one photo in it) or a video file")
    p = Path(os.path.abspath(os.fspath(path)))
    if is_video(p):
        return p, True
    if p.is_file():
        if p.suffix.lower() in PHOTO_SUFFIXES:
            return p.parent, False
        raise PosesError(f"{p}: neither a photo, a video nor a folder of photos")
    if not p.is_dir():
        raise PosesError(f"{p}: not found")
    return p, False


def source_name(source) -> str:
    """A name for the photos: the folder's name, or the video's without its extension."""
    p = Path(os.path.abspath(os.fspath(source)))
    return (p.stem if p.suffix.lower() in VIDEO_SUFFIXES else p.name) or "photos"


def _free(folder: Path) -> bool:
    return not folder.exists() or (folder.is_dir() and not any(folder.iterdir()))


def default_dataset_folder(source, blend_path: str = "") -> Path:
    """``<name>_dataset`` next to the saved .blend file (else in ``<temp>/mlx3d_photos``), numbered
    ``_2``, ``_3``, ... when that folder exists and is not empty: never an existing dataset."""
    base = Path(os.path.dirname(os.path.abspath(blend_path))) if blend_path else Path(tempfile.gettempdir()) / "mlx3d_photos"
    stem = f"{source_name(source)}_dataset"
    candidate, n = base / stem, 1
    while not _free(candidate):
        n += 1
        candidate = base / f"{stem}_{n}"
    return candidate


class PhotoSolve(WorkerJob):
    """One camera solve of photos or a video into the dataset folder ``out`` (see the module doc).

    fps, blur_ratio: a video's frames taken per second and the sharpness kept (None: ``mlx3d.sfm``'s defaults);
    matching, max_image_size, min_registered, seed, verbose: as ``mlx3d.sfm.solve_capture``.
    Bad input raises a ``PosesError`` (a ValueError) here, before anything starts.
    """

    def __init__(self, source, out, *, fps=None, blur_ratio=None, matching="auto", max_image_size=1600, min_registered=None,
                 seed=0, verbose=False):
        self.source, self.video = source_kind(source)
        self.name = source_name(self.source)
        self.out = Path(os.path.abspath(os.fspath(out)))
        if not _free(self.out):
            raise PosesError(f"{self.out}: already exists and is not an empty folder; choose a new or empty dataset folder")
        if matching not in MATCHING:
            raise PosesError(f"matching must be one of {', '.join(MATCHING)}, got {matching!r}")
        require_pycolmap()
        if not self.video:
            list_photos(self.source)  # none: said now (too few: by the solve, at once)
        self._existed = self.out.exists()
        self.options = dict(matching=matching, max_image_size=int(max_image_size), seed=int(seed), verbose=bool(verbose))
        if min_registered is not None:
            self.options["min_registered"] = float(min_registered)
        if self.video:
            self.options.update(fps=fps, blur_ratio=blur_ratio)
        self.stages = [s for s in STAGES if self.video or s != "frames"]
        self.stage, self.progress = None, (0, 1)
        self._fraction = 0.0
        self.result = None
        super().__init__()
        self.thread_name = f"mlx3d solve {self.name}"

    # -- solving (any thread)
    def run(self, progress=None, should_stop=None):
        """Solve in this thread; returns the ``PosesResult``. progress(stage, done, total); should_stop()
        polled about every 0.1 s (as ``cancel()``): a cancel raises KeyboardInterrupt and writes nothing."""

        def report(stage, done, total):
            self.stage, self.progress = stage, (done, total)
            if progress is not None:
                progress(stage, done, total)

        def stop():
            return self._cancel.is_set() or (should_stop is not None and should_stop())

        self.result = solve_capture(self.source, self.out, progress=report, should_stop=stop, **self.options)
        return self.result

    def work(self):
        self.run()

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set() or isinstance(self.error, KeyboardInterrupt)

    def fraction(self) -> float:
        """Overall progress in [0, 1], each stage an equal share; it never goes back (the mapping may
        start again from other image pairs, and its count with it), so a progress bar only moves on."""
        if self.stage in self.stages:
            done, total = self.progress
            now = (self.stages.index(self.stage) + min(done / max(total, 1), 1.0)) / len(self.stages)
            self._fraction = max(self._fraction, now)
        return self._fraction

    def status(self) -> str:
        """The stage and its done/total, e.g. ``finding features 12/24``."""
        if self.stage is None:
            return "starting"
        done, total = self.progress
        return f"{STAGES.get(self.stage, self.stage)} {done:,}/{total:,}"

    def discard(self) -> None:
        """Remove a dataset solved after all (a cancel that came too late): the folder as it was before."""
        if self.result is None or not self.out.is_dir():
            return
        if self._existed:
            for entry in self.out.iterdir():
                shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
        else:
            shutil.rmtree(self.out)
        self.result = None

    def messages(self) -> list[str]:
        """What was solved: the summary, the photos left out, where the dataset is."""
        result = self.result
        lines = [f"solved the cameras of '{self.name}': {result.summary()}"]
        if result.unregistered:
            lines.append(f"not placed, left out of the dataset: {', '.join(result.unregistered[:20])}"
                         + (" ..." if len(result.unregistered) > 20 else ""))
        where = f"wrote the dataset {self.out} ({sum(result.seconds.values()):.1f} s)"
        if Path(tempfile.gettempdir()) in self.out.parents:
            where += " in the temporary folder: set a dataset folder to keep it elsewhere"
        return lines + [where]


def points_material():
    """The emissive material of the sparse points, coloured by their ``Color`` attribute (reused when it exists)."""
    return attribute_material(POINTS_MATERIAL, transparent=False, attribute=POINTS_COLOR)


def _remove(made) -> None:
    """Remove the data-blocks a failed ``add_solved`` made, last made first (objects before their data)."""
    for blocks, block in reversed(made):
        try:
            blocks.remove(block)
        except ReferenceError:
            pass


def add_solved(dataset, *, name=None, parent=None, scene=None, set_resolution=True):
    """Add a solved dataset to the scene: a new collection ``<name> cameras`` in ``parent`` (default:
    the scene's collection) holding a camera object per photo, named after it, and the sparse points
    as a point cloud object ``<name> points`` with their sRGB colours stored linear in the
    ``Color`` attribute (shown by the ``MLX3D Sparse Points`` material; in the viewport only, not in
    renders).

    dataset: the dataset folder (or a loaded ``Dataset``); set_resolution: set the scene's render
    resolution to the photos' size when they share one, so each camera frames its photo. Returns
    (collection, camera objects, point cloud object or None, messages). Nothing is left behind if
    it fails.
    """
    if not hasattr(dataset, "frames"):
        dataset = load_dataset(os.fspath(dataset))
    scene = scene or bpy.context.scene
    parent = parent or scene.collection
    name = name or (dataset.root.name if dataset.root is not None else "photos")
    made, cameras, points, notes = [], [], None, set()
    had_material = bpy.data.materials.get(POINTS_MATERIAL) is not None
    try:
        collection = bpy.data.collections.new(f"{name} cameras")
        made.append((bpy.data.collections, collection))
        for frame in dataset.frames:
            stem = os.path.splitext(os.path.basename(frame.name))[0] or frame.name
            data = bpy.data.cameras.new(stem)
            made.append((bpy.data.cameras, data))
            obj = bpy.data.objects.new(stem, data)
            made.append((bpy.data.objects, obj))
            notes.update(set_blender_camera(obj, frame.camera))
            data.display_size = CAMERA_SIZE
            collection.objects.link(obj)
            cameras.append(obj)
        if dataset.points is not None and len(dataset.points):
            cloud = pointcloud_from_positions(f"{name} points", dataset.points)
            made.append((bpy.data.pointclouds, cloud))
            n = len(dataset.points)
            radius = cloud.attributes.get("radius") or cloud.attributes.new("radius", "FLOAT", "POINT")
            radius.data.foreach_set("value", np.full(n, POINTS_RADIUS, np.float32))
            colours = np.ones((n, 4), np.float32)
            if dataset.point_colors is not None:
                colours[:, :3] = srgb_to_linear(dataset.point_colors / 255.0)
            attr = cloud.attributes.new(POINTS_COLOR, "FLOAT_COLOR", "POINT")
            attr.data.foreach_set("color", colours.ravel())
            material = points_material()
            if not had_material:
                made.append((bpy.data.materials, material))
            cloud.materials.append(material)
            points = bpy.data.objects.new(f"{name} points", cloud)
            made.append((bpy.data.objects, points))
            points.hide_render = True  # a guide in the viewport, not part of the scene's renders
            collection.objects.link(points)
        collection[INFO_KEY] = {"dataset": str(dataset.root) if dataset.root is not None else "", "cameras": len(cameras),
                                "points": 0 if points is None else len(dataset.points)}
        parent.children.link(collection)
    except BaseException:
        _remove(made)
        raise
    messages = [f"added {len(cameras)} cameras" + (f" and {len(dataset.points):,} points" if points is not None else "")
                + f" in the collection '{collection.name}'"]
    sizes = {(f.camera.width, f.camera.height) for f in dataset.frames}
    if set_resolution and len(sizes) == 1:
        width, height = sizes.pop()
        render = scene.render
        if (render.resolution_x, render.resolution_y, render.pixel_aspect_x, render.pixel_aspect_y) != (width, height, 1.0, 1.0):
            render.resolution_x, render.resolution_y = width, height
            render.pixel_aspect_x = render.pixel_aspect_y = 1.0
            messages.append(f"set the render resolution to the photos' {width} x {height}, so each camera frames its photo")
    if scene.camera is None and cameras:
        scene.camera = cameras[0]
    if notes:
        messages.append(f"Blender's cameras leave out the solved {' and '.join(sorted(notes, key=str))}; training uses the full camera model")
    return collection, cameras, points, messages
