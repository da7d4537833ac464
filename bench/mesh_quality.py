"""Benchmark mesh extraction quality: train, extract, compare with the ground-truth mesh.

    python bench/mesh_quality.py DATA_DIR [--gt MESH.ply] [--methods 2dgs,vanilla] [--steps 3000]
                                 [--resolution 128] [--extract fusion,poisson] [--max-gaussians 60000]
                                 [--model PLY] [--out DIR] [--markdown PATH]

DATA_DIR is a captured dataset (``make demo`` writes ``demo_out/dataset``;
its ``mesh.ply`` holds the captured surfaces, the ground truth). For each
method: train in a fresh process (white background, as the demo), extract a
mesh at ``--resolution`` by each of ``--extract`` (depth fusion from the
training views; Poisson with normals oriented towards the training cameras),
then report

- Chamfer distance: the mean of both directions' mean nearest-neighbour
  distance between 200k area-uniform samples on each mesh, in scene units and
  as a fraction of the ground truth's bounding-box diagonal;
- F-score at 0.5 % and 1 % of the diagonal: the harmonic mean of precision
  (the share of the mesh's samples that close to the truth) and recall (the
  share of the truth's samples that close to the mesh);
- normal consistency: the mean |cos| between each sample's face normal and
  the normal at its nearest sample on the other mesh (1 = perfect);
- train and extraction time.

``--out`` keeps the trained PLYs, the meshes and ``meshes.png`` (ground truth
| each method, Blender Workbench renders from one held-out camera).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import numpy as np

from common import emit, peak_rss_mb  # bench/ is on sys.path when run as a script

SAMPLES = 200_000


def _train_child(data: str, method: str, steps: int, max_gaussians: int, out_ply: str) -> None:
    from mlx3d.datasets import load_dataset
    from mlx3d.splatting import GaussianModel
    from mlx3d.training import GaussianTrainer, TrainerConfig
    from mlx3d.training.evaluate import BACKGROUNDS, evaluate

    dataset = load_dataset(data)
    model = GaussianModel.from_points(dataset.points, dataset.point_colors, sh_degree=3)
    config = TrainerConfig(method=method, steps=steps, max_gaussians=max_gaussians, background=BACKGROUNDS["white"])
    trainer = GaussianTrainer(model, config, scene_extent=dataset.scene_extent())
    t0 = time.perf_counter()
    trainer.fit(dataset)
    seconds = time.perf_counter() - t0
    trainer.model.save_ply(out_ply)
    report = evaluate(trainer.model, dataset, "test", BACKGROUNDS["white"])
    print(json.dumps({"train_s": seconds, "psnr": report["psnr"], "gaussians": len(trainer.model), "train_peak_mb": peak_rss_mb()}))


def sample_surface(mesh, count: int, seed: int = 0):
    """``count`` area-uniform points on the mesh and their face normals: ((count,3), (count,3)) float64."""
    tri = mesh.vertices.astype(np.float64)[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(area), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    fold = u + v > 1
    u[fold], v[fold] = 1 - u[fold], 1 - v[fold]
    t = tri[face]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    normals = cross[face] / np.maximum(np.linalg.norm(cross[face], axis=1, keepdims=True), 1e-30)
    return points, normals


def compare(mesh, truth, observed=None, ground=None) -> dict:
    """Chamfer distance, accuracy, completeness, F-scores at 0.5 % and 1 % of the truth's bounding-box diagonal
    (``f_0.5``, ``f_1``) and normal consistency of ``mesh`` against ``truth`` (see the module docstring).

    With ``observed`` ((SAMPLES,) bool: which of the truth's samples, ``sample_surface(truth, SAMPLES, 2)``, a
    photo sees) and ``ground`` (the height z of a ground plane under the truth), also ``observed_chamfer``,
    ``observed_f_0.5`` and ``observed_f_1``: the mesh's distances are to the truth or the ground, whichever is
    nearer (the ground is true surface too), and the truth's only from its observed samples, as DTU's
    evaluation counts what its cameras see."""
    from mlx3d.neighbors import knn

    p, pn = sample_surface(mesh, SAMPLES, 1)
    q, qn = sample_surface(truth, SAMPLES, 2)
    to_truth_idx, to_truth = knn(q, 1, queries=p)
    to_mesh_idx, to_mesh = knn(p, 1, queries=q)
    to_truth, to_mesh = to_truth[:, 0].astype(np.float64), to_mesh[:, 0].astype(np.float64)
    chamfer = 0.5 * (float(to_truth.mean()) + float(to_mesh.mean()))
    nc = 0.5 * (np.abs(np.sum(pn * qn[to_truth_idx[:, 0]], axis=1)).mean() + np.abs(np.sum(qn * pn[to_mesh_idx[:, 0]], axis=1)).mean())
    diagonal = float(np.linalg.norm(truth.vertices.max(0) - truth.vertices.min(0)))
    out = {"chamfer": chamfer, "chamfer_frac": chamfer / diagonal, "normal_consistency": float(nc), "diagonal": diagonal,
           "accuracy": float(to_truth.mean()), "completeness": float(to_mesh.mean())}
    out.update(_f_scores(to_truth, to_mesh, diagonal))
    if observed is not None:
        to_surface = np.minimum(to_truth, np.abs(p[:, 2] - ground))
        out["observed_chamfer"] = 0.5 * (float(to_surface.mean()) + float(to_mesh[observed].mean()))
        out.update({f"observed_{k}": v for k, v in _f_scores(to_surface, to_mesh[observed], diagonal).items()})
    return out


def _f_scores(to_truth, to_mesh, diagonal) -> dict:
    """F-scores at 0.5 % and 1 % of ``diagonal``: precision, the share of the mesh's samples that close to the
    truth (``to_truth``); recall, the share of the truth's samples that close to the mesh (``to_mesh``)."""
    out = {}
    for percent in (0.5, 1):
        precision, recall = float((to_truth <= percent / 100 * diagonal).mean()), float((to_mesh <= percent / 100 * diagonal).mean())
        out[f"f_{percent:g}"] = 2 * precision * recall / max(precision + recall, 1e-12)
    return out


def render_meshes(paths: list, labels: list, camera, out_png: str) -> None:
    """Workbench renders of the mesh PLYs from ``camera`` (an mlx3d Camera), side by side in one PNG."""
    import bpy
    from PIL import Image, ImageDraw

    from mlx3d.io.mesh_ply import read_mesh_ply

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "SINGLE"
    scene.render.resolution_x, scene.render.resolution_y = camera.width * 2, camera.height * 2
    scene.render.film_transparent = False
    cam_data = bpy.data.cameras.new("bench")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.lens_unit = "FOV"
    cam_data.angle = 2 * np.arctan(camera.width / (2 * camera.fx))
    cam_obj = bpy.data.objects.new("bench", cam_data)
    from mathutils import Matrix

    cam_obj.matrix_world = Matrix(camera.to_opengl_c2w().tolist())
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    tiles = []
    for path in paths:
        mesh = read_mesh_ply(path)
        data = bpy.data.meshes.new("m")
        data.vertices.add(len(mesh.vertices))
        data.vertices.foreach_set("co", mesh.vertices.ravel())
        data.loops.add(mesh.faces.size)
        data.loops.foreach_set("vertex_index", mesh.faces.ravel())
        data.polygons.add(len(mesh.faces))
        data.polygons.foreach_set("loop_start", np.arange(0, mesh.faces.size, 3))
        data.update()
        obj = bpy.data.objects.new("m", data)
        scene.collection.objects.link(obj)
        target = out_png + f".{len(tiles)}.png"
        scene.render.filepath = target
        bpy.ops.render.render(write_still=True)
        bpy.data.objects.remove(obj)
        tiles.append(Image.open(target).convert("RGB"))
        os.remove(target)
    w, h = tiles[0].size
    sheet = Image.new("RGB", (w * len(tiles), h + 24), "white")
    draw = ImageDraw.Draw(sheet)
    for i, (tile, label) in enumerate(zip(tiles, labels)):
        sheet.paste(tile, (i * w, 24))
        draw.text((i * w + 6, 6), label, fill="black")
    sheet.save(out_png)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", metavar="DATA_DIR")
    parser.add_argument("--gt", metavar="MESH.ply", help="ground-truth mesh (default DATA_DIR/mesh.ply)")
    parser.add_argument("--methods", default="2dgs,vanilla")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--extract", default="fusion,poisson", help="extraction methods, comma-separated (default fusion,poisson)")
    parser.add_argument("--max-gaussians", type=int, default=60_000)
    parser.add_argument("--model", metavar="PLY", help="mesh this trained model instead of training (e.g. demo_out/trained.ply)")
    parser.add_argument("--out", default="bench/out/mesh_quality")
    parser.add_argument("--markdown", metavar="PATH")
    parser.add_argument("--child", metavar="METHOD", help=argparse.SUPPRESS)
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    if args.child:
        _train_child(args.data, args.child, args.steps, args.max_gaussians, os.path.join(args.out, f"{args.child}.ply"))
        return

    from mlx3d.datasets import load_dataset
    from mlx3d.io.mesh_ply import read_mesh_ply
    from mlx3d.splatting import GaussianModel

    dataset = load_dataset(args.data)
    centres = np.array([f.camera.center for f in dataset.frames])
    truth = read_mesh_ply(args.gt or os.path.join(args.data, "mesh.ply"))
    rows, meshes = [], []
    for method in ["given"] if args.model else args.methods.split(","):
        if args.model:
            ply, trained = args.model, {"train_s": float("nan"), "psnr": float("nan")}
        else:
            ply = os.path.join(args.out, f"{method}.ply")
            cmd = [sys.executable, __file__, args.data, "--child", method, "--steps", str(args.steps), "--max-gaussians", str(args.max_gaussians), "--out", args.out]
            trained = json.loads(subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=True).stdout.strip().splitlines()[-1])
        model = GaussianModel.load_ply(ply)
        trained["gaussians"] = len(model)
        for extraction in args.extract.split(","):
            t0 = time.perf_counter()
            if extraction == "fusion":
                mesh = model.fused_mesh([dataset.frames[i].camera for i in dataset.train], resolution=args.resolution)
            else:
                mesh = model.surface_mesh(resolution=args.resolution, orient_towards=centres)
            extract_s = time.perf_counter() - t0
            mesh_path = os.path.join(args.out, f"{method}_{extraction}_mesh.ply")
            mesh.save_ply(mesh_path)
            meshes.append((f"{method}, {extraction}", mesh_path))
            rows.append({"method": method, "extraction": extraction, **trained, "extract_s": extract_s, "faces": len(mesh.faces),
                         **compare(mesh, truth)})
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    diagonal = rows[0]["diagonal"]
    lines = [
        f"Mesh extraction on {os.path.basename(os.path.abspath(args.data))} ({platform.machine()}, {os.cpu_count()} cores): "
        + (f"the model {args.model}, " if args.model else f"{args.steps:,} training steps, ") +
        f"resolution {args.resolution}, ground-truth bounding-box diagonal {diagonal:.3f}",
        "",
        "| method | extraction | train (s) | held-out PSNR (dB) | Gaussians | extract (s) | faces | Chamfer | Chamfer / diagonal | accuracy | completeness | F-score 0.5 % | F-score 1 % | normal consistency |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['extraction']} | {r['train_s']:.0f} | {r['psnr']:.2f} | {r['gaussians']:,} | {r['extract_s']:.1f} | {r['faces']:,} | {r['chamfer']:.4f} | "
            f"{100 * r['chamfer_frac']:.2f}% | {r['accuracy']:.4f} | {r['completeness']:.4f} | {r['f_0.5']:.3f} | {r['f_1']:.3f} | {r['normal_consistency']:.3f} |"
        )
    emit("\n".join(lines) + "\n", args.markdown)
    test = dataset.test[len(dataset.test) // 2] if dataset.test else 0
    png = os.path.join(args.out, "meshes.png")
    render_meshes([args.gt or os.path.join(args.data, "mesh.ply")] + [p for _, p in meshes], ["ground truth"] + [m for m, _ in meshes], dataset.frames[test].camera, png)
    print(f"wrote {png}")


if __name__ == "__main__":
    main()
