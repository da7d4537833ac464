"""Meshes against surfaces known exactly: objects built with bpy, photographed on a full orbit, cameras solved here.

    python bench/mesh_objects.py [--objects suzanne,bumpy_sphere,torus_knot] [--methods vanilla,2dgs]
                                 [--extract fusion,poisson] [--steps 7000] [--size 640] [--factor 2]
                                 [--resolution 128] [--sparse-depth 0] [--background-points N] [--faces N]
                                 [--data bench_data/mesh_objects] [--markdown docs/benchmarks/mesh_objects.md]

Each object (a subdivided Suzanne, a sphere displaced by a noise texture, a
(2, 3) torus knot), textured with a weathered procedural material, is
rendered with Cycles from 60 cameras on a two-turn spiral from 35 degrees
below to 65 above it, with a transparent background (RGBA), at ``--size`` x
3/4 pixels (the solve needs them: from 320 x 240 photos it placed the torus
knot's cameras up to 5.4 degrees off, from 640 x 480 within 0.14), while
training and fusion read them ``--factor`` times smaller (320 x 240 by
default, as ``mlx3d train --factor 2`` reads a camera's photos);
``suzanne_ground`` is the same Suzanne 0.1 above a textured ground running
to the horizon, in opaque photos from 8 to 65 degrees above
(what a capture of a statue on a floor looks like; its extracted meshes are
cropped to the true mesh's bounding box grown by 2 % of its diagonal before
they are measured, as DTU's observation masks do, so the ground is left
out); its cameras are solved from the photos by ``mlx3d poses``
(``mlx3d.sfm.solve_poses``: no Blender pose and no points are handed over).
Training starts from the sparse points of the solve (every 8th photo held
out), black background, as ``mlx3d train DATA`` does, for ``--steps`` steps
per method (``--sparse-depth W``: with the solve's points as depth,
``TrainerConfig.lambda_sparse_depth``, its rows and files named 'METHOD+depthW';
``--background-points N``: a backdrop of N points, 'METHOD+backdropN'). Each model is meshed by each extraction method at
``--resolution`` (fusion from the training cameras, of their median depth,
or with ``fusion-expected`` of their expected depth; Poisson with normals
towards them; with ``--faces N`` each mesh is also simplified to at most N
faces, ``mlx3d.meshing.simplify``, rows 'EXTRACTION+facesN'), the mesh is taken into Blender's frame by the similarity that
best maps the solved cameras onto the true ones, and compared with the
object's own triangles by ``bench/mesh_quality.py``'s measures (Chamfer and
its two directions as percentages of the true mesh's bounding-box diagonal,
F-scores at 0.5 % and 1 % of it, normal consistency), with the train and
extraction time and the extraction's peak memory (its own process). The
cameras fix the mesh's frame only as well as the solve found them: an error
in the solved focal length scales the object against its cameras, which no
camera alignment undoes. So the Chamfer distance and F-score at 1 % are also
given after ``ICP``: the solve's own sparse points (the features it
triangulated on the object), taken by the camera alignment, are fitted onto
the true surface by a similarity (scale, rotation, shift; iterative closest
points, as Tanks and Temples refines its trajectory alignment), and every
mesh of that capture is moved by the same similarity, with the scale it
found. It corrects the solve's frame, which all extractions share, and
leaves each extraction's own bias (a surface inside or outside the true
one) in its numbers: the first numbers are what a user gets, the second
the meshing alone. An object on a ground is also measured as DTU's
evaluation counts (``observed_...``, the measure the page judges it by):
the ground is true surface too, and only the truth a training photo sees
(``observed_samples``) is to be covered.

Captures, trained models and meshes stay in ``--data`` (git-ignored); a
capture is rebuilt only when its settings changed, and a model is trained
(a mesh extracted) again only when it is missing or ``--retrain`` is given
(the training and extraction figures are kept beside each file, ``.json``). Every row (with
its date, commit, machine and load) is merged into
``docs/benchmarks/mesh_objects/results.json``, replacing an earlier one of
the same object, training, steps, extraction and resolution; the page is
written from all the rows: the tables, its hand-written notes (kept between
``<!-- notes:results -->`` and ``<!-- /notes:results -->``) and one picture
per object (the true mesh and each extraction from a held-out camera,
Blender Workbench).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import shutil
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))  # photo_capture: the similarity alignment

import captures  # noqa: E402  (bench/ is on sys.path when run as a script)
import scenes  # noqa: E402
from common import LoadSampler, commit_info, load_results, machine_line, page_notes, parse_only, peak_rss_mb  # noqa: E402
from mesh_quality import compare, render_meshes, sample_surface  # noqa: E402

OBJECTS = ("suzanne", "bumpy_sphere", "torus_knot", "suzanne_ground")
ON_GROUND = {"suzanne_ground": (8.0, 65.0)}  # opaque photos over a ground plane: the orbit's elevations (degrees)
CROP = 0.02  # meshes of objects on the ground are cropped to the truth's box grown by this fraction of its diagonal
GROUND_GAP = 0.1  # the ground lies this far under the object's lowest point
METHODS = ("vanilla", "2dgs")
EXTRACTIONS = ("fusion", "poisson", "fusion-expected")
DEFAULT_EXTRACTIONS = ("fusion", "poisson")
FORMAT_VERSION = 1
DOCS = os.path.join(ROOT, "docs", "benchmarks")
PICTURES = "mesh_objects"
RESULTS = os.path.join(DOCS, PICTURES, "results.json")
KEY = ("object", "method", "steps", "extraction", "resolution")


# ------------------------------------------------------------------ the objects (bpy)
def _finish(bpy, obj, material):
    """Apply ``obj``'s modifiers, give it ``material`` and weather it (features for the solve)."""
    bpy.context.view_layer.objects.active = obj
    for modifier in list(obj.modifiers):
        bpy.ops.object.modifier_apply(modifier=modifier.name)
    obj.data.materials.clear()
    obj.data.materials.append(material)
    obj.data.shade_smooth()
    captures.weather(bpy, [obj], scale=9.0)
    bpy.context.view_layer.update()
    return obj


def _blotches(bpy, name):
    """A high-contrast noise of five colours (dark to light): features everywhere for the camera solve."""
    colours = [(0.02, 0.02, 0.03), (0.55, 0.12, 0.05), (0.85, 0.80, 0.70), (0.10, 0.35, 0.12), (0.95, 0.95, 0.95)]
    return scenes._material(bpy, name, "NOISE", colours, scale=7.0, Detail=12.0, Roughness=0.65)


def _scene(bpy):
    return scenes._new_scene(bpy, sky_rgb=(0.6, 0.6, 0.6), sky_strength=1.0, sun_strength=3.0, sun_elevation=55.0, sun_azimuth=-40.0)


def build_suzanne(bpy):
    """Blender's monkey, subdivided twice (Catmull-Clark), about 1.1 units across."""
    scene = _scene(bpy)
    bpy.ops.mesh.primitive_monkey_add(size=1.1, location=(0.0, 0.0, 0.0))
    obj = bpy.context.active_object
    obj.name = "Suzanne"
    obj.modifiers.new("subdivide", "SUBSURF").levels = 2
    material = _blotches(bpy, "Suzanne")
    return scene, [_finish(bpy, obj, material)], np.zeros(3)


def build_bumpy_sphere(bpy):
    """A sphere of radius 0.5 displaced along its normals by a clouds texture (up to about 0.05): fine detail."""
    scene = _scene(bpy)
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=6, radius=0.5, location=(0.0, 0.0, 0.0))
    obj = bpy.context.active_object
    obj.name = "Bumpy sphere"
    texture = bpy.data.textures.new("bumps", "CLOUDS")
    texture.noise_scale = 0.12
    displace = obj.modifiers.new("displace", "DISPLACE")
    displace.texture, displace.texture_coords, displace.strength, displace.mid_level = texture, "LOCAL", 0.05, 0.5
    material = _blotches(bpy, "Bumpy")
    return scene, [_finish(bpy, obj, material)], np.zeros(3)


def torus_knot(p=2, q=3, big=0.42, small=0.16, tube=0.09, segments=384, sides=20):
    """(vertices, quads) of a tube of radius ``tube`` around the (p, q) torus knot of radii ``big``, ``small``."""
    t = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    r = big + small * np.cos(q * t)
    curve = np.stack([r * np.cos(p * t), r * np.sin(p * t), small * np.sin(q * t)], axis=1)
    tangent = np.roll(curve, -1, axis=0) - np.roll(curve, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.cross(tangent, [0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    a = np.linspace(0.0, 2.0 * math.pi, sides, endpoint=False)
    ring = np.cos(a)[None, :, None] * normal[:, None] + np.sin(a)[None, :, None] * binormal[:, None]
    vertices = (curve[:, None] + tube * ring).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(segments), np.arange(sides), indexing="ij")
    ni, nj = (i + 1) % segments, (j + 1) % sides
    quads = np.stack([i * sides + j, ni * sides + j, ni * sides + nj, i * sides + nj], axis=-1).reshape(-1, 4)
    return vertices, quads


def build_torus_knot(bpy):
    """A (2, 3) torus knot tube: thin parts close to each other."""
    scene = _scene(bpy)
    vertices, quads = torus_knot()
    material = _blotches(bpy, "Knot")
    obj = scenes._mesh(bpy, scene, "Torus knot", vertices, quads, material)
    return scene, [_finish(bpy, obj, material)], np.zeros(3)


def build_suzanne_on_ground(bpy):
    """Suzanne (as ``build_suzanne``) 0.1 above a textured ground out to the horizon; the ground is not measured."""
    scene, objects, centre = build_suzanne(bpy)
    ground = scenes._material(bpy, "Gravel", "NOISE", [(0.05, 0.05, 0.04), (0.30, 0.26, 0.20), (0.55, 0.50, 0.42), (0.15, 0.18, 0.10)],
                              scale=4.0, roughness=0.9, Detail=10.0, Roughness=0.7)
    bottom = min((o.matrix_world @ v.co).z for o in objects for v in o.data.vertices)
    for part in scenes._ground(bpy, scene, ground, 2.5, scenes.GROUND_SIZE):
        part.location.z = bottom - GROUND_GAP
    bpy.context.view_layer.update()
    return scene, objects, centre


BUILDERS = {"suzanne": build_suzanne, "bumpy_sphere": build_bumpy_sphere, "torus_knot": build_torus_knot,
            "suzanne_ground": build_suzanne_on_ground}


# ------------------------------------------------------------------ capture and solve
def _settings(args) -> dict:
    return {"size": list(args.dims), "samples": args.samples, "views": captures.OBJECT_VIEWS, "version": FORMAT_VERSION}


def make_capture(bpy, capture, name, folder, args) -> dict:
    """Photos, the true mesh and the truth frames of ``name`` in ``folder``, its cameras solved into ``folder/data``."""
    if os.path.isdir(folder):
        shutil.rmtree(folder)
    os.makedirs(folder)
    rng = np.random.default_rng(captures.SEED + OBJECTS.index(name))
    render_dir = os.path.join(folder, "render")
    poses = captures.orbit_poses(np.zeros(3), captures.OBJECT_DISTANCE, rng, ON_GROUND.get(name, captures.OBJECT_ELEVATIONS))
    t0 = time.perf_counter()
    meta = captures.render(bpy, capture, name, render_dir, BUILDERS[name], poses, scenes.OUTDOOR_LENS, args.dims,
                           args.samples, transparent=name not in ON_GROUND)
    shutil.copy(os.path.join(render_dir, capture.MESH_NAME), os.path.join(folder, "truth.ply"))
    frames = captures.write_photos(render_dir, meta, os.path.join(folder, "photos"), size=args.dims)
    shutil.rmtree(render_dir)
    render_s = time.perf_counter() - t0
    result, solve_s = captures.solve(os.path.join(folder, "photos"), os.path.join(folder, "data"))
    info = {"settings": _settings(args), "frames": frames, "render_s": render_s, "solve_s": solve_s,
            "registered": len(result.registered), "photos": result.photos, "reprojection_error": result.reprojection_error,
            **captures.score(os.path.join(folder, "data"), frames)}
    with open(os.path.join(folder, "capture.json"), "w", encoding="utf-8") as f:
        json.dump(info, f, indent=1)
    return info


def to_truth(folder, frames):
    """(4, 4) the similarity from the solved frame to Blender's, fitted to the placed cameras."""
    from photo_capture import similarity

    pairs = captures.camera_pairs(os.path.join(folder, "data"), frames)
    scale, rot, shift = similarity([s for s, _, _ in pairs], [c for _, _, c in pairs])
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = scale * rot, shift
    return matrix


def observed_samples(folder, truth, frames) -> np.ndarray:
    """(SAMPLES,) bool: which of ``compare``'s samples of the truth a training photo sees (inside its picture, in
    front of it, not hidden by the object), cached in ``folder/observed.npy`` (a new capture clears the folder)."""
    from mesh_quality import SAMPLES

    path = os.path.join(folder, "observed.npy")
    if os.path.isfile(path):
        return np.load(path)
    scenes._bpy()
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    q, qn = sample_surface(truth, SAMPLES, 2)
    tree = BVHTree.FromPolygons([tuple(map(float, v)) for v in truth.vertices], [tuple(map(int, f)) for f in truth.faces])
    seen = np.zeros(len(q), bool)
    for _, frame, cam in captures.camera_pairs(os.path.join(folder, "data"), frames):
        if frame.get("held_out"):
            continue
        uv, depth = cam.project_points(q)
        towards = q - cam.center
        candidates = (depth > 0) & np.all((uv >= 0) & (uv < [cam.width, cam.height]), axis=1) & ~seen
        candidates &= np.sum(qn * towards, axis=1) < 0  # a closed surface hides its back faces
        for i in np.flatnonzero(candidates):
            length = float(np.linalg.norm(towards[i]))
            hit = tree.ray_cast(Vector(cam.center), Vector(towards[i] / length), length)
            seen[i] = hit[0] is None or hit[3] >= length * (1 - 1e-4)
    np.save(path, seen)
    return seen


# ------------------------------------------------------------------ children: training and extraction
def _train_child(args) -> None:
    from mlx3d.datasets import load_dataset
    from mlx3d.training import GaussianTrainer, TrainerConfig
    from mlx3d.training.evaluate import BACKGROUNDS, evaluate
    from mlx3d.training.initial import initial_state

    dataset = load_dataset(args.data_dir, factor=args.factor)
    config = TrainerConfig(method=args.child_train.split("+")[0], steps=args.steps, background=BACKGROUNDS["black"], opaque_background="auto",
                           lambda_sparse_depth=args.sparse_depth, init_background_points=args.background_points)
    start = initial_state(dataset, config)
    trainer = GaussianTrainer(start.model, start.config, scene_extent=dataset.scene_extent())
    t0 = time.perf_counter()
    trainer.fit(dataset)
    seconds = time.perf_counter() - t0
    trainer.model.save_ply(args.model)
    report = evaluate(trainer.model, dataset, "test", BACKGROUNDS["black"])
    print(json.dumps({"train_s": seconds, "psnr": report["psnr"], "gaussians": len(trainer.model), "train_peak_mb": peak_rss_mb()}))


def _extract_child(args) -> None:
    from mlx3d.datasets import load_dataset
    from mlx3d.splatting import GaussianModel

    dataset = load_dataset(args.data_dir, factor=args.factor)
    cameras = [dataset.frames[i].camera for i in dataset.train]
    model = GaussianModel.load(args.model)
    t0 = time.perf_counter()
    if args.child_extract.startswith("fusion"):
        mesh = model.fused_mesh(cameras, resolution=args.resolution, depth="expected" if args.child_extract == "fusion-expected" else "median")
    else:
        mesh = model.surface_mesh(resolution=args.resolution, orient_towards=[c.center for c in cameras])
    seconds = time.perf_counter() - t0
    mesh.save_ply(args.mesh)
    print(json.dumps({"extract_s": seconds, "extract_peak_mb": peak_rss_mb(), "faces": len(mesh.faces)}))


def trained_model(method: str, args, data: str, model: str) -> dict:
    """Train ``method`` into ``model`` unless it is there with its figures, trained at ``--factor`` (``--retrain``
    trains again)."""
    figures = model[:-4] + ".json"
    if not args.retrain and os.path.isfile(model) and os.path.isfile(figures):
        with open(figures, encoding="utf-8") as f:
            kept = json.load(f)
        if kept.get("factor", 1) == args.factor:
            return kept
    trained = {**_child("train", method, args, data_dir=data, model=model), **commit_info(ROOT),
               "train_date": datetime.date.today().isoformat(), "factor": args.factor}
    with open(figures, "w", encoding="utf-8") as f:
        json.dump(trained, f, indent=1)
    return trained


def extracted_mesh(extraction: str, args, data: str, model: str, mesh: str) -> dict:
    """Mesh ``model`` into ``mesh`` by ``extraction`` unless that mesh is there, newer than the model, with its
    figures (``--retrain`` extracts again)."""
    figures = mesh[:-4] + ".json"
    if (not args.retrain and os.path.isfile(figures) and os.path.isfile(mesh)
            and os.path.getmtime(mesh) >= os.path.getmtime(model)):
        with open(figures, encoding="utf-8") as f:
            return json.load(f)
    extracted = _child("extract", extraction, args, data_dir=data, model=model, mesh=mesh)
    with open(figures, "w", encoding="utf-8") as f:
        json.dump(extracted, f, indent=1)
    return extracted


def simplified_mesh(mesh: str, faces: int, extracted: dict) -> tuple:
    """(path, figures) of ``mesh`` simplified to at most ``faces`` (``mlx3d.meshing.simplify``), its extraction
    figures with the simplification's time added."""
    from mlx3d.io.mesh_ply import read_mesh_ply
    from mlx3d.meshing import simplify

    source = read_mesh_ply(mesh)
    t0 = time.perf_counter()
    small = simplify(source, faces)
    seconds = time.perf_counter() - t0
    path = mesh[:-4] + f"_faces{faces}.ply"
    small.save_ply(path)
    return path, {**extracted, "extract_s": extracted["extract_s"] + seconds, "simplify_s": seconds, "faces": len(small.faces)}


def _child(kind: str, value: str, args, **extra) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), f"--child-{kind}", value, "--data-dir", extra["data_dir"],
           "--model", extra["model"], "--steps", str(args.steps), "--resolution", str(args.resolution),
           "--factor", str(args.factor), "--sparse-depth", str(args.sparse_depth)]
    if args.background_points is not None:
        cmd += ["--background-points", str(args.background_points)]
    if "mesh" in extra:
        cmd += ["--mesh", extra["mesh"]]
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"{kind} {value} failed (exit code {proc.returncode})")
    return json.loads(lines[-1])


# ------------------------------------------------------------------ measures
ICP_ITERATIONS = 30
ICP_SAMPLES = 50_000


def icp_similarity(points: np.ndarray, target: np.ndarray) -> tuple:
    """``(scale, rotation (3, 3), shift (3,))`` that takes ``points`` (N, 3) onto the surface sampled by ``target``
    (M, 3): iterative closest points with a least-squares similarity per step (Umeyama), pairs farther than three
    times their median distance left out. Starts from the identity."""
    from photo_capture import umeyama

    from mlx3d.neighbors import knn

    scale, rot, shift = 1.0, np.eye(3), np.zeros(3)
    for _ in range(ICP_ITERATIONS):
        moved = scale * points @ rot.T + shift
        index, dist = knn(target, 1, queries=moved)
        dist = dist[:, 0].astype(np.float64)
        near = dist <= 3.0 * np.median(dist)
        scale, rot, shift = umeyama(points[near], target[index[near, 0]])
    return scale, rot, shift


def solve_refinement(folder, matrix, truth) -> np.ndarray:
    """(4, 4) the similarity that fits the solve's sparse points, in the truth's frame by ``matrix``, onto the true
    surface (``icp_similarity``; points farther than 5 % of the diagonal from the truth's box, a backdrop's, left out)."""
    from mlx3d.datasets import load_dataset

    points = load_dataset(os.path.join(folder, "data")).points.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
    lo, hi = truth.vertices.min(axis=0), truth.vertices.max(axis=0)
    margin = 0.05 * float(np.linalg.norm(hi - lo))
    points = points[np.all((points >= lo - margin) & (points <= hi + margin), axis=1)]
    scale, rot, shift = icp_similarity(points, sample_surface(truth, ICP_SAMPLES, 4)[0])
    refine = np.eye(4)
    refine[:3, :3], refine[:3, 3] = scale * rot, shift
    return refine


def measure(row_dir, name, mesh_path, matrix, truth, crop=False, refine=None, observed=None):
    """The measures of the mesh at ``mesh_path`` taken into the truth's frame by ``matrix``, and (``icp_...``) by
    ``refine`` (4, 4) after it; with ``crop``, only its faces inside the truth's bounding box grown by CROP of its
    diagonal; with ``observed`` (``observed_samples``), also ``observed_...``: the ground, GROUND_GAP under the
    truth, counted as true surface and only the observed truth to be covered (``compare``)."""
    from mlx3d.io.mesh_ply import read_mesh_ply
    from mlx3d.meshing import SurfaceMesh
    from mlx3d.meshing.mesh import compact_faces

    mesh = read_mesh_ply(mesh_path)
    vertices, faces, colors = mesh.vertices @ matrix[:3, :3].T + matrix[:3, 3], mesh.faces, mesh.colors
    if crop:
        lo, hi = truth.vertices.min(axis=0), truth.vertices.max(axis=0)
        margin = CROP * float(np.linalg.norm(hi - lo))
        inside = np.all((vertices >= lo - margin) & (vertices <= hi + margin), axis=1)
        vertices, faces, kept = compact_faces(vertices, faces, inside[faces].all(axis=1))
        colors = None if colors is None else colors[kept]
    if len(faces) == 0:  # e.g. Poisson over a box that a backdrop stretched: nothing left near the object
        nan = float("nan")
        return {"chamfer_pct": nan, "accuracy_pct": nan, "completeness_pct": nan, "normal_consistency": nan, "f_0.5": 0.0,
                "f_1": 0.0, "empty": True}
    aligned = SurfaceMesh(vertices, faces, colors)
    aligned.save_ply(os.path.join(row_dir, f"{name}_aligned.ply"))
    ground = None if observed is None else float(truth.vertices[:, 2].min()) - GROUND_GAP
    scores = compare(aligned, truth, observed, ground)
    out = {**scores, **{f"{k}_pct": 100.0 * scores[k] / scores["diagonal"] for k in ("chamfer", "accuracy", "completeness", "observed_chamfer")
                        if k in scores}}
    if observed is not None:
        out["observed_share"] = float(observed.mean())
    if refine is not None:
        refined = compare(SurfaceMesh(vertices @ refine[:3, :3].T + refine[:3, 3], faces, colors), truth)
        out.update(icp_scale=float(np.cbrt(np.linalg.det(refine[:3, :3]))), icp_f_1=refined["f_1"],
                   icp_chamfer_pct=100.0 * refined["chamfer"] / refined["diagonal"])
    return out


# ------------------------------------------------------------------ the page
def _icp(row) -> str:
    if "icp_scale" not in row:
        return " | | "
    return f"{row['icp_chamfer_pct']:.3f} | {row['icp_f_1']:.3f} | {row['icp_scale']:.4f}"


def _photos(row) -> str:
    """The photos a row's capture was solved from, and the factor training and fusion read them smaller by."""
    (width, height), factor = row["photo_size"], row["factor"]
    return f"{width} × {height}" + (f" ÷ {factor}" if factor != 1 else "")


def table(rows) -> str:
    head = ("| object | photos | training | extraction | Chamfer (% of diagonal) | F-score 0.5 % | F-score 1 % | normal consistency | "
            "accuracy (%) | completeness (%) | after ICP: Chamfer (%) | F-score 1 % | scale | faces | held-out PSNR (dB) | "
            "train (s) | extract (s) | extract peak (MB) |")
    out = [head, "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        out.append(f"| {r['object']} | {_photos(r)} | {r['method']} {r['steps']:,} | {r['extraction']} {r['resolution']} | {r['chamfer_pct']:.3f} | "
                   f"{r['f_0.5']:.3f} | {r['f_1']:.3f} | {r['normal_consistency']:.3f} | {r['accuracy_pct']:.3f} | "
                   f"{r['completeness_pct']:.3f} | {_icp(r)} | {r['faces']:,} | {r['psnr']:.2f} | {r['train_s']:.0f} | {r['extract_s']:.1f} | "
                   f"{r['extract_peak_mb']:.0f} |")
    return "\n".join(out)


def observed_table(rows) -> str:
    """The ``observed_...`` measures of the rows that have them (objects on the ground), as DTU counts."""
    rows = [r for r in rows if "observed_chamfer_pct" in r]
    if not rows:
        return ""
    out = ["| object | training | extraction | truth seen by a training photo | Chamfer (% of diagonal) | F-score 0.5 % | F-score 1 % |",
           "|---|---|---|---:|---:|---:|---:|"]
    for r in rows:
        out.append(f"| {r['object']} | {r['method']} {r['steps']:,} | {r['extraction']} {r['resolution']} | {100 * r['observed_share']:.1f} % | "
                   f"{r['observed_chamfer_pct']:.3f} | {r['observed_f_0.5']:.3f} | {r['observed_f_1']:.3f} |")
    return "\n".join(out)


def save_results(results, rows, captured) -> None:
    """Merge ``rows`` (replacing those of the same KEY) and the captures into RESULTS as it is on disk now (another
    run may have added rows since ``results`` was read); ``results`` becomes that."""
    results.update(load_results(RESULTS))
    keys = {tuple(r[k] for k in KEY) for r in rows}
    results["rows"] = [r for r in results["rows"] if tuple(r[k] for k in KEY) not in keys] + rows
    results["rows"].sort(key=lambda r: (OBJECTS.index(r["object"]) if r["object"] in OBJECTS else 99,
                                        METHODS.index(r["method"]) if r["method"] in METHODS else 99, r["extraction"]))
    results.setdefault("captures", {}).update({name: {k: v for k, v in info.items() if k != "frames"} for name, info in captured.items()})
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    with open(RESULTS, "w", encoding="utf-8") as f:
        json.dump(results, f, indent=1)
        f.write("\n")


def write_page(path, results) -> None:
    rows, captured = results["rows"], results["captures"]
    runs = {}
    for r in rows:
        runs.setdefault((r.get("date", "?"), r.get("machine", "?"), r.get("commit", "?")), []).append(r.get("load_median", float("nan")))
    lines = ["# Meshes of objects with known surfaces", "",
             "Each object is built with `bpy`, photographed with Cycles on a full orbit (60 photos, transparent background; "
             "`suzanne_ground`: on a textured ground, opaque photos from 8° to 65° above, meshes cropped to the true mesh's "
             "box grown by 2 % of its diagonal before measuring), "
             "its cameras solved from the photos by `mlx3d poses`, trained without points and meshed from the photos "
             "read smaller by the factor in the table (`--factor`); the meshes are "
             "compared with the object's own triangles after the similarity that maps the solved cameras onto Blender's "
             "(`python bench/mesh_objects.py`; how each measure is defined is in its docstring). The route for meshes "
             "([Surface meshes](../guides/meshes.md); in Blender *Train Splats* with 2DGS, then *Extract Mesh*) is "
             "`mlx3d train --method 2dgs`, then `mlx3d mesh --data`, which fuses the rendered depth.", "",
             "Measured on:", ""]
    lines += [f"- {date}, commit `{commit}`: {machine}; 1-minute load average during the runs: median {min(loads):.1f} "
              f"to {max(loads):.1f} on {os.cpu_count()} cores" for (date, machine, commit), loads in sorted(runs.items())]
    lines += ["", "| object | photos | photos placed | max rotation error | max position error | focal length solved (true) |",
              "|---|---|---:|---:|---:|---:|"]
    for name in sorted(captured, key=lambda n: OBJECTS.index(n) if n in OBJECTS else 99):
        info = captured[name]
        width, height = info["settings"]["size"]
        lines.append(f"| {name} | {width} × {height} | {info['registered']} of {info['photos']} | "
                     f"{info.get('rotation_deg', float('nan')):.2f}° | {info.get('position_pct', float('nan')):.2f} % | "
                     f"{info.get('focal_solved', float('nan')):.1f} px ({info.get('focal_true', float('nan')):.1f}) |")
    lines += ["", table(rows), ""]
    observed = observed_table(rows)
    if observed:
        lines += ["Objects on a ground, measured as DTU's evaluation counts, which is how this page judges them: the ground "
                  "(true surface too) is as near as the truth for the mesh's accuracy, and completeness covers only the truth a "
                  "training photo sees. The rest (here the object's underside, facing the ground) no photo shows, and fusion "
                  "leaves what no view saw empty by design, so counting it would charge every mesh for it alike:", "",
                  observed, ""]
    lines += ["<!-- notes:results -->", page_notes(path, ["results"])["results"], "<!-- /notes:results -->", ""]
    for name in sorted(captured, key=lambda n: OBJECTS.index(n) if n in OBJECTS else 99):
        picture = os.path.join(PICTURES, f"{name}.png")
        if os.path.isfile(os.path.join(os.path.dirname(path), picture)):
            lines += [f"**{name}** (truth, then each training and extraction, from a held-out camera):", "",
                      f"![{name}: the true mesh and the extracted ones]({picture})", ""]
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", default=",".join(OBJECTS))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--extract", default=",".join(DEFAULT_EXTRACTIONS), help=f"comma-separated, of {', '.join(EXTRACTIONS)}")
    parser.add_argument("--steps", type=int, default=7000)
    parser.add_argument("--size", type=int, default=640, help="photo width in pixels, height 3/4 of it (default 640)")
    parser.add_argument("--factor", type=int, default=2, help="training and fusion read the photos this many times "
                        "smaller (default 2)")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default 16)")
    parser.add_argument("--resolution", type=int, default=128, help="extraction resolution (default 128)")
    parser.add_argument("--data", default=os.path.join(ROOT, "bench_data", "mesh_objects"))
    parser.add_argument("--markdown", default=None, help="write the page here (e.g. docs/benchmarks/mesh_objects.md)")
    parser.add_argument("--sparse-depth", type=float, default=0.0, metavar="WEIGHT",
                        help="TrainerConfig.lambda_sparse_depth: the solve's points as depth (default 0: off)")
    parser.add_argument("--background-points", type=int, default=None, metavar="N",
                        help="TrainerConfig.init_background_points: a backdrop of N points (default: the method's)")
    parser.add_argument("--faces", type=int, default=0, metavar="N",
                        help="also measure each mesh simplified to at most N faces (rows 'EXTRACTION+facesN')")
    parser.add_argument("--retrain", action="store_true", help="train and mesh every model again, even where that was done")
    parser.add_argument("--child-train", help=argparse.SUPPRESS)
    parser.add_argument("--child-extract", help=argparse.SUPPRESS)
    parser.add_argument("--data-dir", help=argparse.SUPPRESS)
    parser.add_argument("--model", help=argparse.SUPPRESS)
    parser.add_argument("--mesh", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child_train:
        _train_child(args)
        return 0
    if args.child_extract:
        _extract_child(args)
        return 0
    objects = parse_only(parser, args.objects, OBJECTS, "object")
    methods = parse_only(parser, args.methods, METHODS, "method")
    extractions = parse_only(parser, args.extract, EXTRACTIONS, "extraction")
    if args.size < 64 or args.steps < 1 or args.resolution < 8 or args.factor < 1:
        parser.error("--size must be at least 64, --steps and --factor at least 1 and --resolution at least 8")
    args.dims = (args.size, (args.size * 3 // 4) // 2 * 2)

    from mlx3d.io.mesh_ply import read_mesh_ply

    load = LoadSampler()
    load.start()
    bpy = capture = None
    rows, captured = [], {}
    results, code = load_results(RESULTS), commit_info(ROOT)
    for name in objects:
        folder = os.path.join(args.data, name)
        info_path = os.path.join(folder, "capture.json")
        info = json.load(open(info_path, encoding="utf-8")) if os.path.isfile(info_path) else None
        if info is None or info["settings"] != _settings(args):
            if bpy is None:
                bpy = scenes._bpy()
                from addon import capture
            print(f"{name}: rendering {captures.OBJECT_VIEWS} photos and solving their cameras", file=sys.stderr, flush=True)
            info = make_capture(bpy, capture, name, folder, args)
        captured[name] = info
        print(f"{name}: {info['registered']} of {info['photos']} photos placed", file=sys.stderr, flush=True)
        matrix, truth = to_truth(folder, info["frames"]), read_mesh_ply(os.path.join(folder, "truth.ply"))
        refine = solve_refinement(folder, matrix, truth)
        observed = observed_samples(folder, truth, info["frames"]) if name in ON_GROUND else None
        data = os.path.join(folder, "data")
        for method in methods:
            if args.sparse_depth:  # its own files and rows: 'vanilla+depth0.01'
                method = f"{method}+depth{args.sparse_depth:g}"
            if args.background_points is not None:  # '2dgs+backdrop5000'
                method = f"{method}+backdrop{args.background_points}"
            model = os.path.join(folder, f"{method}_{args.steps}.ply")
            trained = trained_model(method, args, data, model)
            for extraction in extractions:
                mesh = os.path.join(folder, f"{method}_{args.steps}_{extraction}_{args.resolution}.ply")
                extracted = extracted_mesh(extraction, args, data, model, mesh)
                meshes = [(extraction, mesh, extracted)]
                if args.faces:  # 'fusion+faces30000': the same mesh simplified
                    meshes.append((f"{extraction}+faces{args.faces}", *simplified_mesh(mesh, args.faces, extracted)))
                for label, path, figures in meshes:
                    row = {"object": name, "method": method, "steps": args.steps, "extraction": label,
                           "resolution": args.resolution, "photo_size": list(args.dims), **trained, **figures,
                           **measure(folder, os.path.basename(path)[:-4], path, matrix, truth, crop=name in ON_GROUND, refine=refine,
                                     observed=observed),
                           **code,
                           "date": datetime.date.today().isoformat(), "machine": machine_line(),
                           "load_median": load.summary().get("median", float("nan"))}
                    rows.append(row)
                    print(table([row]).splitlines()[-1], file=sys.stderr, flush=True)
        save_results(results, [r for r in rows if r["object"] == name], {name: info})  # after every object: a run stopped early keeps it
        if args.markdown:
            # the picture shows every extraction measured for the object, this run's and earlier ones
            meshes = [os.path.join(folder, "truth.ply")] + [
                os.path.join(folder, f"{r['method']}_{r['steps']}_{r['extraction']}_{r['resolution']}_aligned.ply")
                for r in results["rows"] if r["object"] == name]
            meshes = [m for m in meshes if os.path.isfile(m)]
            if len(meshes) > 1:
                os.makedirs(os.path.join(DOCS, PICTURES), exist_ok=True)
                held_out = next(c for s, t, c in captures.camera_pairs(data, info["frames"]) if t.get("held_out"))
                labels = ["truth"] + [os.path.basename(m)[:-len("_aligned.ply")] for m in meshes[1:]]
                render_meshes(meshes, labels, held_out.scaled(1.0 / args.factor), os.path.join(os.path.dirname(os.path.abspath(args.markdown)), PICTURES, f"{name}.png"))
            write_page(args.markdown, results)
    load.stop.set()
    load.join()
    print(table(rows))
    if args.markdown:
        print(f"wrote {args.markdown} and {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
