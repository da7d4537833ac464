"""Headless workflows: ``blender -b -P blender_splat.py -- COMMAND ...`` or ``python blender_splat.py COMMAND ...``.

Subcommands go through Blender objects exactly as the UI does (compose sets
the inserted object's location, rotation and scale on the object and lets
export bake them). Exit code 0 on success, 1 with a message on bad input,
2 on bad usage.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

import bpy

from mlx3d.cli import add_solving_arguments
from mlx3d.errors import Mlx3dError
from mlx3d.io.mesh_ply import write_mesh_ply
from mlx3d.progress import StageProgressLine
from mlx3d.sfm import needs_solve, poses_folder

from . import capture, demo, photos, scene_render, train, workflows


def _print(messages) -> None:
    for message in messages:
        print(message)


def _reset_scene() -> None:
    bpy.ops.wm.read_homefile(use_empty=True)


def _import(path, args):
    obj, messages = workflows.import_splat_file(path, sh_degree=args.sh_degree, drop_nonfinite=args.drop_nonfinite, axis=args.axis)
    _print(messages)
    return obj


def _save_blend(args) -> None:
    if getattr(args, "save_blend", None):
        bpy.ops.wm.save_as_mainfile(filepath=args.save_blend, check_existing=False)
        print(f"saved {args.save_blend}")


def cmd_import(args) -> None:
    _reset_scene()
    for path in args.files:
        _import(path, args)
    _save_blend(args)


def cmd_export(args) -> None:
    bpy.ops.wm.open_mainfile(filepath=args.blend)
    objects = [bpy.data.objects[name] for name in args.objects] if args.objects else list(bpy.context.scene.objects)
    _print(workflows.export_splat_file(args.out, objects, axis=args.axis)[1])


def cmd_compose(args) -> None:
    _reset_scene()
    scene_obj = _import(args.scene, args)
    inserted = _import(args.insert, args)
    inserted.location = args.location
    inserted.rotation_mode = "XYZ"
    inserted.rotation_euler = [math.radians(a) for a in args.rotation_deg]
    inserted.scale = args.scale if len(args.scale) == 3 else args.scale * 3
    _print(workflows.export_splat_file(args.out, [scene_obj, inserted], axis=args.axis)[1])
    _save_blend(args)


def cmd_clean(args) -> None:
    _reset_scene()
    obj = _import(args.input, args)
    method = "RADIUS" if args.radius is not None else "STATISTICAL"
    _print(workflows.remove_floaters(obj, method=method, k=args.stat_k, std_ratio=args.stat_std, radius=args.radius or 0.0, min_neighbours=args.min_neighbours or 1)[1])
    _print(workflows.export_splat_file(args.out, [obj], axis=args.axis)[1])


def cmd_compact(args) -> None:
    _reset_scene()
    obj = _import(args.input, args)
    _print(workflows.compact_object(obj, max_gaussians=args.max_gaussians, min_opacity=args.min_opacity, sh_degree=args.target_sh_degree))
    _print(workflows.export_splat_file(args.out, [obj], axis=args.axis)[1])


def _dataset_cameras(path, splats) -> list:
    """The training cameras of the dataset folder ``path`` (``mlx3d.datasets.load_dataset``), in world space:
    the dataset's frame is the splat file's, placed by the splat object's transform (the --axis preset)."""
    from dataclasses import replace

    import numpy as np

    from mlx3d.datasets import load_dataset

    dataset = load_dataset(path)
    cameras = [dataset.frames[i].camera for i in dataset.train]
    if not cameras:
        raise ValueError(f"{path}: the dataset has no training cameras")
    to_file = np.linalg.inv(np.array(splats.matrix_world, dtype=np.float64))
    if np.allclose(to_file, np.eye(4), rtol=0.0, atol=1e-12):
        return cameras
    return [replace(camera, viewmat=camera.viewmat @ to_file) for camera in cameras]


def cmd_extract_mesh(args) -> None:
    from mlx3d.progress import ProgressLine

    _reset_scene()
    splats = _import(args.input, args)
    bpy.context.view_layer.update()
    cameras = _dataset_cameras(args.cameras_from, splats) if args.cameras_from else None
    bounds = None
    if args.bounds is not None:  # the file's frame -> world: the box around the corners as the splat object places them
        bounds = workflows.placed_bounds(args.bounds[:3], args.bounds[3:], workflows.object_matrix(splats))
    job = workflows.MeshExtraction(splats, method=args.method, cameras=cameras, resolution=args.resolution, cleanup=args.cleanup,
                                   faces=args.faces, min_opacity=args.min_opacity, max_points=args.max_points, trim=args.trim, bounds=bounds)
    try:
        job.compute(ProgressLine("extract mesh"))
    except KeyboardInterrupt:
        print(f"blender_splat {args.command}: cancelled; nothing written", file=sys.stderr)
        raise SystemExit(130) from None
    _, messages = job.add_object()
    _print(messages)
    write_mesh_ply(args.out, job.mesh.vertices, job.mesh.faces, job.mesh.colors)  # the object's frame: the file's
    print(f"wrote {args.out}")
    _save_blend(args)


ENGINES = {"CYCLES": ("CYCLES",), "EEVEE": ("BLENDER_EEVEE", "BLENDER_EEVEE_NEXT"), "WORKBENCH": ("BLENDER_WORKBENCH",)}


def _set_engine(scene, name: str) -> None:
    """Set the scene's render engine by its short name (the identifier differs between Blender versions)."""
    for identifier in ENGINES[name]:
        try:
            scene.render.engine = identifier
            return
        except TypeError:
            continue
    raise ValueError(f"this Blender has no {name} render engine")


def cmd_render(args) -> None:
    from mlx3d.progress import ProgressLine

    bpy.ops.wm.open_mainfile(filepath=args.blend)
    scene = bpy.context.scene
    if args.engine:
        _set_engine(scene, args.engine)
    if args.samples is not None:
        scene.cycles.samples = args.samples
        if hasattr(scene, "eevee"):
            scene.eevee.taa_render_samples = args.samples
    if args.frames is None:
        if not args.out.lower().endswith(".png"):
            raise ValueError(f"--out must be a .png file for one frame (or pass --frames A-B and a folder), got {args.out}")
        _print(scene_render.render_image(scene, filepath=args.out, antialias=args.antialias)[1])
        return
    job = scene_render.AnimationRender(scene, scene_render.parse_frames(args.frames), out_dir=args.out, antialias=args.antialias)
    progress = ProgressLine("render")
    try:
        while not job.done:
            job.step()
            progress(len(job.written), job.total)
    except KeyboardInterrupt:
        messages = job.close()
        _print(messages)
        print(f"blender_splat render: cancelled; the {len(job.written)} frames written are kept", file=sys.stderr)
        raise SystemExit(130) from None
    except BaseException:
        job.close()
        raise
    _print(job.close() + [job.summary()])


def cmd_capture(args) -> None:
    from mlx3d.progress import ProgressLine

    bpy.ops.wm.open_mainfile(filepath=args.blend)
    _, messages = capture.capture_dataset(
        args.out, objects=args.objects or None, use_scene_cameras=args.scene_cameras, num_views=args.views,
        radius=args.radius, elevations_deg=args.elevations, resolution=tuple(args.resolution), samples=args.samples,
        num_points=args.points, test_every=args.test_every, seed=args.seed, progress=ProgressLine("capture"),
    )
    _print(messages)


def _solve(source, out, args) -> None:
    """Solve the cameras of photos or a video into the dataset ``out`` and add them to the scene (as *Train from Photos*)."""
    job = photos.PhotoSolve(source, out, fps=args.fps, blur_ratio=args.blur_ratio, matching=args.matching,
                            max_image_size=args.max_image_size, min_registered=args.min_registered, verbose=args.verbose_sfm)
    job.run(progress=StageProgressLine("poses"))  # a progress line per stage, as `mlx3d poses` prints
    _print(job.messages())
    _print(photos.add_solved(job.out, name=job.name)[3])


def cmd_poses(args) -> None:
    _reset_scene()
    try:
        _solve(args.photos, args.out, args)
    except KeyboardInterrupt:
        print("blender_splat poses: cancelled; nothing written", file=sys.stderr)
        raise SystemExit(130) from None
    _save_blend(args)


def _train_data(args) -> str:
    """The dataset to train on: ``args.data``, or for photos without poses or a video, the dataset solved from
    them into ``--poses-out`` (default: OUT's name + ``_poses``, beside OUT; an earlier solve there is reused)."""
    if not needs_solve(args.data):
        return args.data
    out = poses_folder(args.out, args.poses_out)
    if os.path.isdir(out) and any(os.scandir(out)):
        print(f"{args.data}: photos without poses; using the cameras solved earlier in {out}")
        _print(photos.add_solved(out, name=photos.source_name(args.data))[3])  # a clear error when it holds something else
        return out
    print(f"{args.data}: photos without poses; solving the cameras into {out}")
    _solve(args.data, out, args)
    return out


def cmd_train(args) -> None:
    _reset_scene()
    try:
        data = _train_data(args)
        _, messages = train.train_dataset(
            data, steps=args.steps, method=args.method, out_ply=args.out, max_gaussians=args.max_gaussians,
            sh_degree=args.sh_degree, background=args.background, seed=args.seed, progress=train.StatusPrinter(),
        )
    except KeyboardInterrupt:
        print("blender_splat train: cancelled; nothing written", file=sys.stderr)
        raise SystemExit(130) from None
    _print(messages)
    _save_blend(args)


def cmd_demo(args) -> None:
    try:
        demo.run_demo(args.out, quick=args.quick)
    except KeyboardInterrupt:
        print("blender_splat demo: cancelled", file=sys.stderr)
        raise SystemExit(130) from None


def _positive_int(text) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="blender_splat", description="Gaussian splat workflows in Blender, headless.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name, func, text, reads_splats=True, axis=True, aliases=()):
        """A subcommand; the options of importing splat files only where it reads them, --axis where it reads or writes them."""
        p = sub.add_parser(name, help=text, description=text, aliases=list(aliases))
        p.set_defaults(func=func)
        if axis:
            p.add_argument("--axis", choices=sorted(workflows.AXIS_PRESETS), default="NONE", help="axis convention of the files (default NONE)")
        if reads_splats:
            p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), default=None, help="cap the SH degree on import")
            p.add_argument("--drop-nonfinite", action="store_true", help="drop rows with NaN/Inf instead of refusing the file")
        return p

    p = add("import", cmd_import, "Import splat files (PLY, SPZ, compressed PLY, .splat, .ksplat, SOG, glTF) as splat objects (and save a .blend).")
    p.add_argument("files", nargs="+", metavar="FILE")
    p.add_argument("--save-blend", metavar="OUT.blend")

    p = add("export", cmd_export, "Export splat objects of a .blend, transforms baked, into one splat file (the extension picks the format).",
            reads_splats=False)
    p.add_argument("--blend", required=True, metavar="IN.blend")
    p.add_argument("--objects", nargs="*", metavar="NAME", help="object names (default: every splat object)")
    p.add_argument("--out", required=True, metavar="OUT")

    p = add("compose", cmd_compose, "Insert an object splat into a scene splat with a Blender transform and export both.")
    p.add_argument("--scene", required=True, metavar="SCENE")
    p.add_argument("--insert", required=True, metavar="OBJECT")
    p.add_argument("--location", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"))
    p.add_argument("--rotation-deg", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("RX", "RY", "RZ"), help="Euler XYZ, degrees")
    p.add_argument("--scale", type=float, nargs="+", default=[1.0], metavar="S", help="uniform S or SX SY SZ")
    p.add_argument("--out", required=True, metavar="OUT")
    p.add_argument("--save-blend", metavar="OUT.blend")

    p = add("clean", cmd_clean, "Remove floaters from a splat file (statistical by default, or --radius/--min-neighbours).")
    p.add_argument("input", metavar="IN")
    p.add_argument("out", metavar="OUT")
    p.add_argument("--stat-k", type=int, default=25)
    p.add_argument("--stat-std", type=float, default=10.5)
    p.add_argument("--radius", type=float, default=None)
    p.add_argument("--min-neighbours", type=int, default=None)

    text = ("Extract a triangle mesh of the splats' surface and write it as a PLY (in the file's frame): by depth fusion "
            "(depth rendered from views of the splats, fused into a signed distance volume; unseen space left empty) or "
            "Poisson reconstruction (a closed surface through the splats as discs). `mesh` is the same command.")
    p = add("extract-mesh", cmd_extract_mesh, text, aliases=["mesh"])
    p.add_argument("input", metavar="IN")
    p.add_argument("--out", required=True, metavar="MESH.ply")
    p.add_argument("--method", choices=workflows.MESH_METHODS, default="fusion",
                   help="fusion: depth maps into a signed distance volume, unseen space left empty (default); "
                        "poisson: a closed surface through the splats as discs")
    p.add_argument("--cameras-from", metavar="DATA_DIR",
                   help="a dataset folder (COLMAP, NeRF-synthetic or nerfstudio) in the splat file's frame: fusion renders its "
                        "training cameras, Poisson turns each splat's normal toward the nearest (default: 60 views around the splats)")
    p.add_argument("--resolution", type=int, default=128, help="voxels along the longest side of the surface (fusion) or grid (Poisson) (default 128)")
    p.add_argument("--bounds", type=float, nargs=6, default=None, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="fusion: the box to mesh, in the file's frame (default: the surfaces the views share)")
    p.add_argument("--cleanup", type=float, default=0.01, metavar="F",
                   help="drop pieces with fewer faces than this fraction of the largest piece's, 0 keeps all (default 0.01)")
    p.add_argument("--faces", type=int, default=0, metavar="N", help="at most N triangles, by quadric vertex clustering (default 0: as extracted)")
    p.add_argument("--min-opacity", type=float, default=0.01, help="poisson: leave out splats less opaque than this (default 0.01)")
    p.add_argument("--max-points", type=int, default=200000, help="poisson: surface samples used at most, 0 for all (default 200000)")
    p.add_argument("--trim", type=float, default=None, help=f"poisson: remove surface farther than this many voxels from any splat, 0 for off (default {workflows.DEFAULT_TRIM:g})")
    p.add_argument("--save-blend", metavar="OUT.blend", help="also save the scene with the splat object and the mesh object")

    text = ("Render a .blend's scene from its camera: Blender's objects with the scene's engine, the splat objects with "
            "mlx3d, composited by depth; one frame to a PNG, or a frame range into a folder in the scene's output format.")
    p = add("render", cmd_render, text, reads_splats=False, axis=False)
    p.add_argument("--blend", required=True, metavar="IN.blend")
    p.add_argument("--out", required=True, metavar="OUT", help="a .png for one frame; with --frames, the output folder (default naming and format: the scene's)")
    p.add_argument("--frames", metavar="A-B", help="render frames A to B (inclusive) instead of the current frame")
    p.add_argument("--engine", choices=sorted(ENGINES), help="render engine for Blender's objects (default: the scene's)")
    p.add_argument("--samples", type=_positive_int, help="render samples (default: the scene's)")
    p.add_argument("--antialias", action="store_true", help="Mip-Splatting opacity compensation for the splats")

    p = add("compact", cmd_compact, "Compact a splat file: keep the most important splats, truncate SH.")
    p.add_argument("input", metavar="IN")
    p.add_argument("out", metavar="OUT")
    p.add_argument("--max-gaussians", type=int, default=None)
    p.add_argument("--min-opacity", type=float, default=0.0)
    p.add_argument("--target-sh-degree", type=int, choices=(0, 1, 2, 3), default=None)

    text = "Render the meshes of a .blend with Cycles into a training dataset (images, transforms.json, COLMAP model, points)."
    p = sub.add_parser("capture", help=text, description=text)
    p.set_defaults(func=cmd_capture)
    p.add_argument("--blend", required=True, metavar="IN.blend")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--objects", nargs="*", metavar="NAME", help="mesh objects to capture (default: every visible mesh)")
    p.add_argument("--scene-cameras", action="store_true", help="render from the scene's cameras instead of an orbit")
    p.add_argument("--views", type=int, default=72, help="orbit views (default 72)")
    p.add_argument("--radius", type=float, default=None, help="orbit radius (default 2.2 x the bounding-sphere radius)")
    p.add_argument("--elevations", type=float, nargs="+", default=[-10.0, 20.0, 45.0], metavar="DEG", help="elevation rings (default -10 20 45)")
    p.add_argument("--resolution", type=int, nargs=2, default=(256, 256), metavar=("W", "H"))
    p.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel (default 32)")
    p.add_argument("--points", type=int, default=20000, help="initial points sampled on the surfaces (default 20000)")
    p.add_argument("--test-every", type=int, default=8, help="hold out every n-th frame (0: none; default 8)")
    p.add_argument("--seed", type=int, default=0)

    text = ("Solve the cameras of a folder of photos (or a video) with COLMAP (pycolmap) into a dataset folder, set upright "
            "(+Z up, the scene at the origin), and add them to the scene as cameras and a point cloud (as Train from Photos).")
    p = sub.add_parser("poses", help=text, description=text)
    p.set_defaults(func=cmd_poses)
    p.add_argument("photos", metavar="PHOTOS", help="a folder of photos, or a video file")
    p.add_argument("--out", required=True, metavar="DIR", help="the dataset folder to write (new, or empty)")
    add_solving_arguments(p)
    p.add_argument("--save-blend", metavar="OUT.blend", help="also save the scene with the cameras and the points")

    text = ("Train Gaussians on a dataset folder (COLMAP, NeRF-synthetic or nerfstudio), or on a folder of photos or a video "
            "whose cameras are solved first (as `poses`), and write them as a 3DGS PLY.")
    p = sub.add_parser("train", help=text, description=text)
    p.set_defaults(func=cmd_train)
    p.add_argument("data", metavar="DATA", help="dataset folder (or its transforms*.json), or photos without poses, or a video")
    p.add_argument("--poses-out", metavar="DIR", help="where cameras solved from photos go (default: OUT's name + _poses, "
                   "beside OUT; an earlier solve there is reused)")
    add_solving_arguments(p)
    p.add_argument("--out", required=True, metavar="OUT")
    p.add_argument("--method", choices=train.METHODS, default="vanilla", help="training method (default vanilla)")
    p.add_argument("--steps", type=_positive_int, default=30000, help="training steps (default 30000)")
    p.add_argument("--max-gaussians", type=_positive_int, default=None, metavar="M", help="cap on the number of Gaussians (default: none for vanilla and 2dgs; mcmc grows to one per pixel of a training image, at least twice its start)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), default=3, help="SH degree of the model (default 3)")
    p.add_argument("--background", choices=train.BACKGROUNDS, default="black", help="background of renders and targets (default black)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save-blend", metavar="OUT.blend", help="also save the scene with the trained splat object")

    text = ("Build a textured scene, capture it, train splats on it, evaluate them on held-out views, and export, "
            "re-import and save the result (the main job end to end; replaces the open Blender file).")
    p = sub.add_parser("demo", help=text, description=text)
    p.set_defaults(func=cmd_demo)
    p.add_argument("--out", default="demo_out", metavar="DIR", help="output folder (default demo_out)")
    p.add_argument("--quick", action="store_true", help="toy sizes (8 views at 32x32, 100 steps), for tests")
    return parser


def main(argv) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "compose" and len(args.scale) not in (1, 3):
        parser.error(f"--scale takes 1 or 3 values, got {len(args.scale)}")
    if args.command == "clean" and (args.radius is None) != (args.min_neighbours is None):
        parser.error("clean: --radius and --min-neighbours go together")
    try:
        args.func(args)
    except (Mlx3dError, ValueError, OSError, KeyError, RuntimeError) as exc:
        print(f"blender_splat {args.command}: error: {exc}", file=sys.stderr)
        return 1
    return 0
