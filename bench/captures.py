"""Generate the realistic evaluation set: rendered captures whose cameras come from our own SfM, and lund.

    .venv/bin/python bench/captures.py [--out bench_data/captures] [--size 320] [--only NAME,...] [--samples 16]

Every rendered capture is built with ``bpy`` from ``bench/scenes.py``'s scene
builders and rendered with the add-on's capture code (``addon/capture.py``,
Cycles on the CPU, fixed seeds), but only the photos are kept: their cameras
are then solved from the photos alone with ``mlx3d.sfm.solve_poses`` (what
``mlx3d poses`` runs), so training sees what a real capture gives. The true
Blender cameras are written beside, in ``truth.json``, for reference only.

Each capture is a folder ``OUT/NAME/``::

    photos/        the photos, 000.png, 001.png, ... (what a phone would give)
    truth.json     the true cameras (OpenGL camera-to-world, intrinsics, lens distortion)
                   and what was done to each photo (exposure, white balance, blur)
    data/          the dataset solved from photos/ (images/, sparse/0/, poses.json):
                   what bench/real_captures.py trains on
    capture.json   settings, the solve's summary and its error against the truth

Captures (photos are ``--size`` wide, 3:4 high; 320 x 240 by default):

arc
    A handheld arc at arm's length around ``outdoor``'s four objects on their
    textured ground: 40 photos over 160 degrees of azimuth, the distance,
    height, aim and roll jittered like a hand (seeded). Opaque photos, sky and
    ground to the horizon.
walk
    Walking past ``open_points``' plaza and objects: 40 photos along a gently
    curved path with head bob, the camera turning to keep the objects in view
    as the walker passes them (forward and sideways motion at once). Solved
    with sequential matching (``make_walk`` says why); the default solve
    (every pair matched) is kept beside, in ``data_auto/``, and scored too.
distorted_exposure
    ``arc``'s photos as a phone with a wide lens and auto exposure would give
    them: Brown radial distortion ``k1`` = -0.1 on every photo (resampled in
    numpy from a wider render of the same camera, so the solve must estimate
    it), a gain of 0.55-1.6 and a white balance of +-12 % per channel (the
    ranges of ``bench/scenes.py``'s ``exposure`` scene) and on every third
    photo a 3-5 pixel directional motion blur. Photos that training holds out
    (every 8th in name order, indices 0, 8, 16, ...) keep the exposure and
    sharpness of the scene, as in ``exposure``; distortion is on all of them.
object_orbit
    ``object_rgba``'s house on a full orbit: 60 photos (1.5 x ``--size``,
    480 x 360 by default) on a two-turn spiral from 35 degrees below to 65
    degrees above it, 2.1 units away; its materials varied by a noise
    pattern (``weather``: without it the repeating bricks left SIFT only the
    door and the chimney, and fewer than a third of the photos registered) (cameras all around, below
    included), transparent background (RGBA). No points are handed over: the
    dataset holds the sparse points the solve triangulated, and those are
    what training starts from.
lund
    The real handheld street walk in ``shared/data/real/lund`` (29 photos,
    1024 x 768, BSD-2), solved with the ``mlx3d poses`` command. No truth.

``arc`` and ``distorted_exposure`` share one set of renders (``arc/render/``,
rendered a little wider than the photos): ``arc``'s photos are their centre
crops (an exact pinhole camera of the photo size), ``distorted_exposure``'s
are resampled through the lens model. For each capture the script prints the
photos registered, the mean reprojection error and, for the rendered ones, the
solved cameras' largest rotation and position errors against the truth after a
similarity alignment (``tests/photo_capture.py``'s ``similarity_errors``), and
the solved focal length (and ``k1``) against the true one.
"""

from __future__ import annotations

import argparse
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
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))

import scenes  # noqa: E402  bench/scenes.py: the scene builders and the capture helpers
from common import parse_only  # noqa: E402

CAPTURES = ("arc", "walk", "distorted_exposure", "object_orbit", "lund")
LUND = os.path.join(ROOT, "..", "shared", "data", "real", "lund")
FORMAT_VERSION = 1  # bump when a capture changes
SEED = 7

VIEWS = 40
ARC_DEGREES = 160.0
ARC_DISTANCE = 3.0
ARC_ELEVATION = 22.0
K1 = -0.1
BLUR_EVERY = 3  # every third photo (not held out) is blurred
BLUR_PIXELS = (3.0, 5.0)
HELD_OUT_EVERY = 8  # the COLMAP loader's test split: indices 0, 8, 16, ... in name order
OBJECT_ELEVATIONS = (-35.0, 65.0)
OBJECT_TURNS = 2.0
OBJECT_VIEWS = 60  # 12 degrees apart on a turn: at 18 (40 views) only 6 of the house's photos registered
OBJECT_DISTANCE = scenes.OBJECT_DISTANCE  # 2.1: the whole house in every photo (at 1.5 brick walls filled them and 13 of 60 registered)
OBJECT_SCALE = 1.5  # the house's photos are 1.5 x --size (at 320 x 240, 40 photos, 6 of 40 registered)
WALK_MATCHING = "sequential"  # neighbours in order, as for a video: see make_walk


# ------------------------------------------------------------------ handheld camera paths
def _look(eye, target, roll_deg=0.0) -> np.ndarray:
    """OpenGL camera-to-world looking from ``eye`` at ``target`` (world up +Z), rolled about the view axis."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross((0.0, 0.0, 1.0), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    r = math.radians(roll_deg)
    right, up = math.cos(r) * right + math.sin(r) * up, -math.sin(r) * right + math.cos(r) * up
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, eye
    return c2w


def arc_poses(centre, rng) -> list:
    """A handheld arc: azimuth over ARC_DEGREES around ``centre`` (from the front, -Y), jittered distance, height, aim, roll."""
    poses = []
    for i in range(VIEWS):
        a = math.radians(-ARC_DEGREES / 2 + ARC_DEGREES * i / (VIEWS - 1) + rng.normal(0.0, 0.8))
        e = math.radians(ARC_ELEVATION + 3.0 * math.sin(2.1 * i / VIEWS * math.pi) + rng.normal(0.0, 1.5))
        d = ARC_DISTANCE + rng.normal(0.0, 0.08)
        eye = centre + d * np.array([math.cos(e) * math.sin(a), -math.cos(e) * math.cos(a), math.sin(e)])
        aim = centre + rng.normal(0.0, 0.08, 3)
        poses.append(_look(eye, aim, rng.normal(0.0, 1.5)))
    return poses


def walk_poses(rng) -> list:
    """Walking past the open scene's objects (around the origin): x from -3.6 to 1.2 along y = -2.7 + 0.5 sin(pi t),
    eye 1.1 high with a step's bob; looking at a point that moves along the objects from x = -1 to 1 (forward and
    sideways motion, the objects always in view)."""
    poses = []
    for i in range(VIEWS):
        t = i / (VIEWS - 1)
        x = -3.6 + 4.8 * t
        eye = np.array([x, -2.7 + 0.5 * math.sin(math.pi * t), 1.1 + 0.025 * math.sin(math.pi * i)]) + rng.normal(0.0, 0.02, 3)
        target = np.array([-1.0 + 2.0 * t, 0.4, 0.35]) + rng.normal(0.0, 0.06, 3)
        poses.append(_look(eye, target, rng.normal(0.0, 1.5)))
    return poses


def orbit_poses(centre, distance, rng, elevations=OBJECT_ELEVATIONS) -> list:
    """A full orbit: a spiral of OBJECT_TURNS turns from ``elevations[0]`` (below) to ``[1]`` degrees, jittered."""
    poses = []
    lo, hi = elevations
    for i in range(OBJECT_VIEWS):
        t = i / (OBJECT_VIEWS - 1)
        a = 2.0 * math.pi * OBJECT_TURNS * t + math.radians(rng.normal(0.0, 2.0))
        e = math.radians(lo + (hi - lo) * t + rng.normal(0.0, 2.0))
        d = distance * (1.0 + rng.normal(0.0, 0.03))
        eye = centre + d * np.array([math.cos(e) * math.sin(a), -math.cos(e) * math.cos(a), math.sin(e)])
        poses.append(_look(eye, centre + rng.normal(0.0, 0.03, 3), rng.normal(0.0, 2.0)))
    return poses


def weather(bpy, objects, scale=6.0, strength=1.0):
    """Vary each object's procedural colour by a noise pattern (dirt and weathering: a gain of about 0.4-1.6), in place.

    The house's bricks and roof tiles repeat exactly, so apart from the door and the chimney SIFT finds the
    same features everywhere and the solve cannot tell the walls apart; the noise makes every part of a wall
    look different, as on a real house. The roof's two colours have almost the same brightness, so seen from
    above (where the roof fills the photo) only this pattern gives features."""
    for obj in objects:
        for material in obj.data.materials:
            nodes, links = material.node_tree.nodes, material.node_tree.links
            colour = nodes["Principled BSDF"].inputs["Base Color"]
            if not colour.is_linked:
                continue
            source = colour.links[0].from_socket
            coords, noise, mix = nodes.new("ShaderNodeTexCoord"), nodes.new("ShaderNodeTexNoise"), nodes.new("ShaderNodeMix")
            noise.inputs["Scale"].default_value = scale
            noise.inputs["Detail"].default_value = 12.0
            noise.inputs["Roughness"].default_value = 0.7
            links.new(coords.outputs["Object"], noise.inputs["Vector"])
            mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
            mix.inputs["Factor"].default_value = strength
            a, b = (next(x for x in mix.inputs if x.name == n and x.type == "RGBA") for n in ("A", "B"))
            gain = nodes.new("ShaderNodeMath")  # the noise (about 0.2-0.8) as a gain of about 0.4-1.6
            gain.operation = "MULTIPLY"
            gain.inputs[1].default_value = 2.0
            links.new(noise.outputs["Fac"], gain.inputs[0])
            links.new(source, a)
            links.new(gain.outputs[0], b)
            links.new(next(x for x in mix.outputs if x.type == "RGBA"), colour)


def _weathered_object(bpy):
    scene, objects, centre = scenes.build_object(bpy)
    weather(bpy, objects)
    return scene, objects, centre


# ------------------------------------------------------------------ lens distortion, exposure, blur (numpy)
def undistort_radius(r_d, k1, iterations=20):
    """r_u with r_u (1 + k1 r_u^2) = r_d (normalised image coordinates)."""
    r_u = np.array(r_d, dtype=np.float64)
    for _ in range(iterations):
        r_u = r_d / (1.0 + k1 * r_u * r_u)
    return r_u


def distortion_margin(width, height, focal, k1) -> tuple[int, int]:
    """Pixels to add on each side of a render so that the distorted photo's corners still sample inside it."""
    x, y = width / 2.0 / focal, height / 2.0 / focal
    r_d = math.hypot(x, y)
    grow = float(undistort_radius(r_d, k1)) / r_d
    return int(math.ceil((grow - 1.0) * width / 2.0)) + 2, int(math.ceil((grow - 1.0) * height / 2.0)) + 2


def _bilinear(image, u, v):
    """Sample ``image`` (H, W, C) at pixel-centre coordinates (u right, v down; pixel (j, i) centred at j + 0.5, i + 0.5)."""
    h, w = image.shape[:2]
    x, y = np.clip(u - 0.5, 0.0, w - 1.0), np.clip(v - 0.5, 0.0, h - 1.0)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    return ((image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx) * (1 - fy)
            + (image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx) * fy)


def distort(wide, width, height, focal, cx, cy, margin, k1):
    """The photo (height, width) a lens with Brown radial ``k1`` gives, from ``wide``, a pinhole render of the same
    focal length and centre with ``margin`` (mx, my) more pixels on each side."""
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    xd, yd = (j - cx) / focal, (i - cy) / focal
    r_d = np.hypot(xd, yd)
    scale = np.where(r_d > 0, undistort_radius(r_d, k1) / np.maximum(r_d, 1e-12), 1.0)
    return _bilinear(wide, xd * scale * focal + cx + margin[0], yd * scale * focal + cy + margin[1])


def motion_blur(image, length, angle):
    """A directional box blur ``length`` pixels long at ``angle`` radians (the mean of shifted copies)."""
    h, w = image.shape[:2]
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    taps = max(int(math.ceil(length)) * 2, 2)
    out = np.zeros_like(image)
    for s in np.linspace(-length / 2.0, length / 2.0, taps):
        out += _bilinear(image, j + s * math.cos(angle), i + s * math.sin(angle))
    return out / taps


# ------------------------------------------------------------------ rendering
def render(bpy, capture, name, folder, build, poses, lens, size, samples, transparent, margin=(0, 0)):
    """Render ``poses`` of the scene ``build(bpy)`` makes at ``size`` plus ``margin`` pixels each side, the focal length
    in pixels that of ``lens`` mm on a 36 mm sensor ``size[0]`` pixels wide; returns the capture's transforms.json."""
    scene, objects, _ = build(bpy)
    width, height = size[0] + 2 * margin[0], size[1] + 2 * margin[1]
    scenes._add_cameras(bpy, scene, poses, lens * size[0] / width)  # same focal length in pixels as the photo
    scenes._capture(capture, folder, name, objects=objects, use_scene_cameras=True, resolution=(width, height),
                    samples=samples, num_points=1, test_every=0, transparent=transparent, colmap=False, seed=scenes.SEED,
                    scene=scene)
    with open(os.path.join(folder, "transforms.json"), encoding="utf-8") as f:
        return json.load(f)


def _truth_frame(name, frame, meta, margin=(0, 0), k1=0.0, **effects):
    fx = meta["fl_x"]
    return {"file": name, "transform_matrix": frame["transform_matrix"], "fx": fx, "fy": meta["fl_y"],
            "cx": meta["cx"] - margin[0], "cy": meta["cy"] - margin[1], "k1": k1, **effects}


def write_photos(source, meta, photos, margin=(0, 0), size=None, k1=0.0, rng=None):
    """The photos from the renders in ``source``: centre crops (pinhole), or with ``k1`` distorted, re-exposed and
    blurred (``rng`` set). Returns the truth frames."""
    from PIL import Image

    from addon import capture

    os.makedirs(photos)
    frames = []
    for k, frame in enumerate(meta["frames"]):
        name = f"{k:03d}.png"
        pixels = np.asarray(Image.open(os.path.join(source, frame["file_path"])))
        held_out = k % HELD_OUT_EVERY == 0
        effects = {"held_out": held_out}
        if rng is None:
            mx, my = margin
            out = pixels[my:my + size[1], mx:mx + size[0]]
        else:
            linear = scenes.srgb_to_linear(pixels[..., :3] / 255.0)
            gain = float(rng.uniform(*scenes.EXPOSURE_GAIN))
            balance = rng.uniform(1.0 - scenes.WHITE_BALANCE, 1.0 + scenes.WHITE_BALANCE, 3)
            length, angle = float(rng.uniform(*BLUR_PIXELS)), float(rng.uniform(0.0, math.pi))
            if not held_out:
                if k % BLUR_EVERY == 1:
                    linear = motion_blur(linear, length, angle)
                    effects["blur"] = {"pixels": round(length, 3), "angle_deg": round(math.degrees(angle), 2)}
                linear = linear * (gain * balance)
                effects.update(gain=round(gain, 6), white_balance=[round(float(b), 6) for b in balance])
            cx, cy = meta["cx"] - margin[0], meta["cy"] - margin[1]
            linear = distort(linear, size[0], size[1], meta["fl_x"], cx, cy, margin, k1)
            out = capture.srgb8(linear)
        Image.fromarray(np.ascontiguousarray(out)).save(os.path.join(photos, name))
        frames.append(_truth_frame(name, frame, meta, margin, k1, **effects))
    return frames


# ------------------------------------------------------------------ solving and scoring
def solve(photos, data, matching="auto"):
    from mlx3d.sfm import solve_poses

    t0 = time.perf_counter()
    result = solve_poses(photos, data, matching=matching)
    return result, time.perf_counter() - t0


def camera_pairs(data, truth_frames) -> list:
    """(solved camera, truth frame, true camera) for every photo the solve placed."""
    from mlx3d.cameras import Camera
    from mlx3d.datasets import load_dataset

    solved = {f.name: f.camera for f in load_dataset(data).frames}
    return [(solved[t["file"]], t, Camera.from_opengl_c2w(np.array(t["transform_matrix"]), solved[t["file"]].width,
                                                          solved[t["file"]].height, t["fx"], t["fy"], t["cx"], t["cy"]))
            for t in truth_frames if t["file"] in solved]


def score(data, truth_frames) -> dict:
    """The solved cameras against the truth: largest rotation and position errors after a similarity alignment,
    solved focal length and k1 against the true ones."""
    from photo_capture import similarity_errors

    pairs = camera_pairs(data, truth_frames)
    if len(pairs) < 3:
        return {}
    rotation, position = similarity_errors([s for s, _, _ in pairs], [c for _, _, c in pairs])
    first = pairs[0][0]
    dist = [float(d) for d in (first.dist or ())]
    return {"rotation_deg": rotation, "position_pct": 100.0 * position, "focal_true": pairs[0][1]["fx"],
            "focal_solved": float(first.fx), "model": first.model, "k1_true": pairs[0][1]["k1"],
            "k1_solved": dist[0] if dist else 0.0}


# ------------------------------------------------------------------ captures
def _render_arc(bpy, capture, folder, args, margin):
    rng = np.random.default_rng(SEED)
    scene, _, centre = scenes.build_outdoor(bpy)
    poses = arc_poses(centre, rng)
    meta = render(bpy, capture, "arc", os.path.join(folder, "render"), scenes.build_outdoor, poses, scenes.OUTDOOR_LENS,
                  args.dims, args.samples, transparent=False, margin=margin)
    meta["margin"] = list(margin)
    scenes._write_json(os.path.join(folder, "render", "transforms.json"), meta)
    return meta


def _arc_margin(args):
    focal = scenes.OUTDOOR_LENS / 36.0 * args.dims[0]
    return distortion_margin(args.dims[0], args.dims[1], focal, K1)


def _arc_renders(bpy, capture, out, args):
    """The arc's wide renders (``OUT/arc/render``), rendered if missing or made with other settings."""
    folder = os.path.join(out, "arc")
    render_dir = os.path.join(folder, "render")
    try:
        with open(os.path.join(render_dir, "settings.json"), encoding="utf-8") as f:
            if json.load(f) == _settings(args):
                with open(os.path.join(render_dir, "transforms.json"), encoding="utf-8") as g:
                    return json.load(g)
    except (OSError, ValueError):
        pass
    if os.path.isdir(render_dir):
        shutil.rmtree(render_dir)
    meta = _render_arc(bpy, capture, folder, args, _arc_margin(args))
    scenes._write_json(os.path.join(render_dir, "settings.json"), _settings(args))
    return meta


def make_arc(bpy, capture, folder, out, args):
    meta = _arc_renders(bpy, capture, out, args)
    frames = write_photos(os.path.join(folder, "render"), meta, os.path.join(folder, "photos"), tuple(meta["margin"]), args.dims)
    return frames, {"scene": "bench/scenes.py build_outdoor", "path": f"handheld arc over {ARC_DEGREES:g} degrees at "
                    f"{ARC_DISTANCE} units, {ARC_ELEVATION:g} degrees up (+-3 degrees sway), jittered distance, aim and roll",
                    "lens_mm": scenes.OUTDOOR_LENS, "background": "opaque (sky and ground)"}


def make_distorted(bpy, capture, folder, out, args):
    meta = _arc_renders(bpy, capture, out, args)
    rng = np.random.default_rng(SEED + 1)
    frames = write_photos(os.path.join(out, "arc", "render"), meta, os.path.join(folder, "photos"), tuple(meta["margin"]),
                          args.dims, K1, rng)
    return frames, {"scene": "arc's renders", "lens": f"Brown radial k1 = {K1} (normalised coordinates, as COLMAP's "
                    "SIMPLE_RADIAL), resampled bilinearly in linear light from a render wider by "
                    f"{meta['margin'][0]} x {meta['margin'][1]} pixels per side",
                    "exposure": f"gain {scenes.EXPOSURE_GAIN}, white balance 1 +- {scenes.WHITE_BALANCE} per channel, linear light",
                    "blur": f"every {BLUR_EVERY}rd photo: a {BLUR_PIXELS[0]:g}-{BLUR_PIXELS[1]:g} pixel directional box blur",
                    "held_out": f"photos {HELD_OUT_EVERY}k keep exposure and sharpness (distortion on all)",
                    "lens_mm": scenes.OUTDOOR_LENS, "background": "opaque (sky and ground)"}


def make_walk(bpy, capture, folder, out, args):
    """The walk, solved with sequential matching (each photo with its next ones, as ``mlx3d poses --matching
    sequential``), the matching for a walk or a video. With every pair matched (``auto`` below 100 photos) and
    the mapper as it was before commit 0686237, two solves of earlier versions of this walk bent the path
    (rotation errors of 95 and 102 degrees, position errors of 40 % of the path) though every photo registered
    under a pixel; since that commit the default solve of this walk is right too. It is kept in ``data_auto/``
    and reported beside."""
    rng = np.random.default_rng(SEED + 2)
    render_dir = os.path.join(folder, "render")
    meta = render(bpy, capture, "walk", render_dir, scenes.build_open, walk_poses(rng), scenes.OPEN_LENS, args.dims,
                  args.samples, transparent=False)
    frames = write_photos(render_dir, meta, os.path.join(folder, "photos"), size=args.dims)
    shutil.rmtree(render_dir)
    return frames, {"scene": "bench/scenes.py build_open", "path": "walking past the objects: x from -3.6 to 1.2 on a "
                    "gentle curve, eye 1.1 high with a step's bob, turning to keep the objects in view; jittered position, aim, roll",
                    "matching": WALK_MATCHING,
                    "lens_mm": scenes.OPEN_LENS, "background": "opaque (sky and plaza)"}


def make_object(bpy, capture, folder, out, args):
    rng = np.random.default_rng(SEED + 3)
    scene, _, centre = scenes.build_object(bpy)
    render_dir = os.path.join(folder, "render")
    dims = tuple(int(round(d * OBJECT_SCALE / 2)) * 2 for d in args.dims)
    meta = render(bpy, capture, "object_orbit", render_dir, _weathered_object,
                  orbit_poses(centre, OBJECT_DISTANCE, rng), scenes.OUTDOOR_LENS, dims, args.samples, transparent=True)
    frames = write_photos(render_dir, meta, os.path.join(folder, "photos"), size=dims)
    shutil.rmtree(render_dir)
    return frames, {"scene": "bench/scenes.py build_object, weathered (weather())", "path": f"a {OBJECT_TURNS:g}-turn spiral from "
                    f"{OBJECT_ELEVATIONS[0]:g} to {OBJECT_ELEVATIONS[1]:g} degrees elevation at {OBJECT_DISTANCE} units, {OBJECT_VIEWS} photos, jittered",
                    "lens_mm": scenes.OUTDOOR_LENS, "background": "transparent (RGBA, alpha 0)", "photo_size": list(dims),
                    "points": "none handed over: training starts from the sparse points the solve triangulated"}


def make_lund(folder, args):
    """lund through the ``mlx3d poses`` command (a child process, as a user runs it)."""
    data = os.path.join(folder, "data")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "mlx3d", "poses", args.lund, "--out", data], check=True, cwd=ROOT)
    seconds = time.perf_counter() - t0
    with open(os.path.join(data, "poses.json"), encoding="utf-8") as f:
        poses = json.load(f)
    return poses, seconds


def _settings(args):
    return {"size": list(args.dims), "samples": args.samples, "engine": "CYCLES (CPU, no denoiser)", "seed": SEED,
            "version": FORMAT_VERSION}


def _fresh(folder):
    if os.path.isdir(folder) and os.listdir(folder):
        if not os.path.isfile(os.path.join(folder, "capture.json")) and not os.path.isdir(os.path.join(folder, "render")):
            raise SystemExit(f"{folder} exists and has no capture.json: not removing it (choose another --out)")
        for item in os.listdir(folder):
            if item != "render":  # the arc's renders are reused when their settings match
                path = os.path.join(folder, item)
                shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join("bench_data", "captures"), help="output folder (default bench_data/captures)")
    parser.add_argument("--size", type=int, default=320, help="photo width in pixels, height 3/4 of it (default 320)")
    parser.add_argument("--only", help=f"comma-separated captures to make (of {', '.join(CAPTURES)})")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default 16)")
    parser.add_argument("--lund", default=LUND, metavar="DIR", help="the lund photos (default ../shared/data/real/lund)")
    args = parser.parse_args()
    only = parse_only(parser, args.only, CAPTURES, "capture")
    if args.size < 64 or args.samples < 1:
        parser.error("--size must be at least 64 and --samples at least 1")
    args.dims = (args.size, (args.size * 3 // 4) // 2 * 2)

    t_start = time.perf_counter()
    rendered = [c for c in CAPTURES if c in only and c != "lund"]
    bpy = capture = None
    if rendered:
        bpy = scenes._bpy()
        from addon import capture
        print(f"Blender {bpy.app.version_string}, Cycles on the CPU, {args.dims[0]}x{args.dims[1]}, {args.samples} samples, "
              f"into {args.out}", flush=True)
    os.makedirs(args.out, exist_ok=True)
    makers = {"arc": make_arc, "walk": make_walk, "distorted_exposure": make_distorted, "object_orbit": make_object}
    rows = []
    for name in [c for c in CAPTURES if c in only]:
        folder = os.path.join(args.out, name)
        _fresh(folder)
        os.makedirs(folder, exist_ok=True)
        print(f"{name}: ...", flush=True)
        t0 = time.perf_counter()
        meta = {"name": name, "command": "python bench/captures.py " + " ".join(sys.argv[1:]), "settings": _settings(args)}
        if name == "lund":
            poses, solve_seconds = make_lund(folder, args)
            meta.update(source=os.path.abspath(args.lund), photos=poses["photos"], registered=len(poses["registered"]),
                        reprojection_error=poses["reprojection_error"], points=poses["points"], camera_model=poses["camera_model"],
                        focal=poses["focal"], solve_seconds=solve_seconds, render_seconds=0.0)
        else:
            frames, notes = makers[name](bpy, capture, folder, args.out, args)
            size = notes.setdefault("photo_size", list(args.dims))
            matching = notes.get("matching", "auto")
            render_seconds = time.perf_counter() - t0
            scenes._write_json(os.path.join(folder, "truth.json"), {
                "note": "the true Blender cameras, for reference only (training uses the solved ones in data/): OpenGL "
                        "camera-to-world in Blender's world (Z up), intrinsics in pixels of the photo, Brown radial k1",
                "width": size[0], "height": size[1], "frames": frames})
            data = os.path.join(folder, "data")
            from mlx3d.sfm import PosesError

            meta.update(notes, photos=len(frames), render_seconds=render_seconds)
            try:
                result, solve_seconds = solve(os.path.join(folder, "photos"), data, matching)
            except PosesError as exc:
                meta.update(error=str(exc))
                print(f"{name}: the solve failed: {exc}", flush=True)
            else:
                meta.update(registered=len(result.registered), unregistered=result.unregistered,
                            reprojection_error=result.reprojection_error, points=result.points,
                            camera_model=result.camera_model, focal=result.focal, solve_seconds=solve_seconds,
                            against_truth=score(data, frames))
            if matching != "auto":  # the default matching too, for the record (not trained on)
                other = os.path.join(folder, "data_auto")
                try:
                    result, seconds = solve(os.path.join(folder, "photos"), other)
                    meta["auto_matching"] = {"matching": result.matching, "registered": len(result.registered),
                                             "reprojection_error": result.reprojection_error, "points": result.points,
                                             "focal": result.focal, "solve_seconds": seconds, "against_truth": score(other, frames)}
                except PosesError as exc:
                    meta["auto_matching"] = {"error": str(exc)}
                print(f"{name}: with the default matching ({meta['auto_matching'].get('matching', 'auto')}): "
                      f"{_summary({**meta['auto_matching'], 'photos': len(frames)})}", flush=True)
        meta["seconds"] = round(time.perf_counter() - t0, 1)
        scenes._write_json(os.path.join(folder, "capture.json"), meta)
        rows.append(meta)
        print(f"{name}: {_summary(meta)} ({meta['seconds']:.0f} s)", flush=True)

    print()
    print(table(rows))
    print(f"{len(rows)} captures in {time.perf_counter() - t_start:.1f} s, in {os.path.abspath(args.out)}")
    return 0 if all("error" not in r for r in rows) else 1


def _summary(meta) -> str:
    if "error" in meta:
        return f"failed: {meta['error']}"
    s = f"{meta['registered']}/{meta['photos']} registered, {meta['reprojection_error']:.2f} px"
    t = meta.get("against_truth")
    if t:
        s += (f", rotation error max {t['rotation_deg']:.2f} deg, position error max {t['position_pct']:.2f} % of the path's "
              f"diameter, focal {t['focal_solved']:.1f} (true {t['focal_true']:.1f})")
        if t["k1_true"]:
            s += f", k1 {t['k1_solved']:.3f} (true {t['k1_true']:g})"
    return s


def table(rows) -> str:
    """The captures as a markdown table."""
    lines = ["| capture | photos | registered | reprojection error | points | camera | focal solved (true) | k1 solved (true) | "
             "max rotation error | max position error | render | solve |",
             "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['name']} | {r['photos']} | failed: {r['error']} | | | | | | | | | |")
            continue
        t = r.get("against_truth") or {}
        focal = f"{r['focal']:.1f}" + (f" ({t['focal_true']:.1f})" if t else "")
        k1 = f"{t['k1_solved']:.3f} ({t['k1_true']:g})" if t else ""
        rot = f"{t['rotation_deg']:.2f}°" if t else "(no truth)"
        pos = f"{t['position_pct']:.2f} %" if t else "(no truth)"
        lines.append(f"| {r['name']} | {r['photos']} | {r['registered']} | {r['reprojection_error']:.2f} px | {r['points']:,} | "
                     f"{r['camera_model']} | {focal} | {k1} | {rot} | {pos} | {r['render_seconds']:.0f} s | {r['solve_seconds']:.0f} s |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
