"""Training stays finite on adversarial data, for every method.

Short versions (160 steps at 48x40, the density-control schedule shortened so
that densification, an opacity reset, MCMC relocation/growth and the 2DGS
geometry losses all happen inside the run) of:

1. a dataset with one all-black and one all-white training image;
2. a training camera inside the scene's bounding box, among the Gaussians
   (some of them behind it or straddling its image plane);
3. images with exposure differences of up to 20%, with and without the
   bilateral grid;
4. an initial point cloud with 1% far outliers (10^3-10^4 scene radii away).

The scene is a ball of coloured Gaussians rendered by mlx3d itself; every
case writes a nerfstudio ``transforms.json`` folder (PNGs and a point PLY)
and trains through ``load_dataset`` and ``GaussianTrainer.fit``. After each
run: every parameter, optimizer moment and per-step loss is finite, the
Gaussian count stays within bounds, every camera renders a finite image, and
the render error on the clean views went down.

A last, step-level case puts Gaussians exactly on a camera's image plane
(depth 0, or small enough that x/z overflows float32).
"""

import json
import math

import mlx.core as mx
import numpy as np
import pytest
from PIL import Image

from mlx3d.cameras import Camera
from mlx3d.datasets import load_dataset
from mlx3d.splatting import GaussianModel
from mlx3d.training.trainer import GaussianTrainer, TrainerConfig

W, H = 48, 40
N_VIEWS = 12  # frames 0 and 8 are held out (every 8th)
N_POINTS = 200
SCENE_RADIUS = 0.8
CAMERA_RADIUS = 3.0
STEPS = 160
RESET = 80  # the opacity reset (vanilla, 2dgs); density control runs every 20 steps from 20 to 150
MAX_GAUSSIANS = 320
METHODS = ("vanilla", "mcmc", "2dgs")


# ------------------------------------------------------------------ scene and dataset
def ring_cameras():
    cams = []
    for k in range(N_VIEWS):
        a = 2 * math.pi * k / N_VIEWS
        el = (0.15, 0.6)[k % 2]
        eye = (CAMERA_RADIUS * math.cos(a) * math.cos(el), CAMERA_RADIUS * math.sin(a) * math.cos(el), CAMERA_RADIUS * math.sin(el))
        cams.append(Camera.look_at(eye=eye, at=(0, 0, 0), up=(0, 0, 1), width=W, height=H, hfov=50.0))
    return cams


# a camera inside the ball of Gaussians, looking outwards
INSIDE = Camera.look_at(eye=(0.1, -0.05, 0.05), at=(1.0, 0.3, 0.2), up=(0, 0, 1), width=W, height=H, hfov=60.0)


def make_scene():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(N_POINTS, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = (d * SCENE_RADIUS * rng.uniform(0, 1, (N_POINTS, 1)) ** (1 / 3)).astype(np.float32)
    colours = rng.uniform(0.05, 0.95, (N_POINTS, 3))
    truth = GaussianModel.from_points(means, colours, sh_degree=0, initial_opacity=0.8)
    cams = ring_cameras()
    images = [render_np(truth, c) for c in cams]
    # the initial points: the truth's centres, jittered, with their colours
    points = means + rng.normal(0, 0.05, means.shape).astype(np.float32)
    return {"truth": truth, "cameras": cams, "images": images, "points": points, "colours": (colours * 255).round().astype(np.uint8)}


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def render_np(model, camera):
    return np.array(model.render(camera, background=(0.0, 0.0, 0.0))["image"])


def write_dataset(root, cameras, images, points, colours):
    """A nerfstudio folder: one PNG per view (named so that frame order is view order),
    per-frame pinhole intrinsics, and the initial points as ``points.ply``."""
    import plyfile

    frames = []
    for i, (cam, img) in enumerate(zip(cameras, images)):
        name = f"view_{i:02d}.png"
        Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).save(root / name)
        frames.append({"file_path": name, "transform_matrix": cam.to_opengl_c2w().tolist(), "camera_model": "PINHOLE",
                       "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height})
    v = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = np.asarray(points, np.float32).T
    v["red"], v["green"], v["blue"] = np.asarray(colours, np.uint8).T
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(root / "points.ply"))
    (root / "transforms.json").write_text(json.dumps({"frames": frames, "ply_file_path": "points.ply"}))
    dataset = load_dataset(root)
    assert len(dataset) == len(cameras) and dataset.test == [0, 8]
    return dataset


def config(method, **kw):
    base = dict(
        method=method, steps=STEPS, seed=0, sh_increase_every=50,
        densify_from=20, densify_every=20, densify_until=150, opacity_reset_every=RESET, reset_recovery=0, geometry_from=20,
        densify_grad_threshold=1e-4, max_gaussians=MAX_GAUSSIANS,
    )
    base.update(kw)
    return TrainerConfig(**base)


def initial_model(dataset):
    return GaussianModel.from_points(dataset.points, dataset.point_colors, sh_degree=1, initial_opacity=0.1)


# ------------------------------------------------------------------ checks after a run
def mean_l1(model, cameras, targets):
    return float(np.mean([np.abs(render_np(model, c) - t).mean() for c, t in zip(cameras, targets)]))


def assert_healthy(trainer, history, dataset, steps=STEPS, min_gaussians=1):
    """Finite parameters and losses, a bounded count with matching optimizer state, and a
    finite render from every camera of the dataset."""
    model = trainer.model
    assert len(history) == steps
    losses = np.array([h["loss"] for h in history])
    assert np.isfinite(losses).all(), np.flatnonzero(~np.isfinite(losses))
    assert all(np.isfinite(h["psnr"]) for h in history)
    for name, value in model.params.items():
        assert bool(mx.all(mx.isfinite(value))), f"{name} is not finite"
        assert trainer.optimizer.m[name].shape == value.shape and bool(mx.all(mx.isfinite(trainer.optimizer.v[name])))
    cap = trainer.config.max_gaussians
    assert min_gaussians <= len(model) <= cap, (len(model), min_gaussians, cap)
    assert all(min_gaussians <= h["num_gaussians"] <= cap for h in history)
    if trainer.bilateral is not None:
        assert bool(mx.all(mx.isfinite(trainer.bilateral.params)))
    for frame in dataset.frames:
        out = model.render(frame.camera, background=(0.0, 0.0, 0.0))
        assert bool(mx.all(mx.isfinite(out["image"]))) and bool(mx.all(mx.isfinite(out["alpha"]))), frame.name
    return losses


def fired(history, event):
    return [h["step"] for h in history if event in h]


def assert_schedule_fired(history, method):
    if method == "mcmc":
        assert fired(history, "relocate") and fired(history, "grow")
    else:
        assert fired(history, "densify") and fired(history, "reset_opacity") == [RESET]
    if method == "2dgs":  # the geometry losses were on
        assert any(h.get("depth_variance_loss", 0) > 0 for h in history)


def train(dataset, cfg, eval_cameras, eval_targets, model=None):
    """Train with ``fit``; returns (trainer, history, {step: mean L1 on the eval views}) with the
    L1 taken before the first step, just before the opacity reset and at the end."""
    model = initial_model(dataset) if model is None else model
    trainer = GaussianTrainer(model, cfg, scene_extent=dataset.scene_extent())
    l1s = {0: mean_l1(model, eval_cameras, eval_targets)}

    def progress(done, total, info):
        if done in (RESET - 1, total):
            l1s[done] = mean_l1(trainer.model, eval_cameras, eval_targets)

    history = trainer.fit(dataset, progress=progress)
    return trainer, history, l1s


def assert_loss_decreased(l1s, method):
    """The render error on the clean views fell by the step before the opacity reset (every
    method) and by the end (vanilla, 80 steps after the reset, and mcmc, which has none). A '2dgs'
    model of this volumetric ball learns slowly under its geometry losses (on from step 20) and is
    still recovering from the reset at the end. Measured over seeds 0-2 and the four cases: step 79
    at 0.32-0.46 (vanilla), 0.16-0.25 (mcmc), 0.54-0.83 (2dgs) of the start; the end at 0.25-0.53
    (vanilla) and 0.10-0.23 (mcmc)."""
    assert l1s[RESET - 1] < (0.9 if method == "2dgs" else 0.6) * l1s[0], l1s
    if method != "2dgs":
        assert l1s[STEPS] < 0.75 * l1s[0], l1s


# ------------------------------------------------------------------ 1. black and white images
@pytest.mark.parametrize("method", METHODS)
def test_all_black_and_all_white_images(scene, tmp_path, method):
    images = list(scene["images"])
    images[3] = np.zeros_like(images[3])
    images[6] = np.ones_like(images[6])
    dataset = write_dataset(tmp_path, scene["cameras"], images, scene["points"], scene["colours"])
    loaded = [dataset.load_image(i)[0] for i in (3, 6)]
    assert loaded[0].max() == 0 and loaded[1].min() == 1  # really black and white on disk
    normal = [i for i in range(N_VIEWS) if i not in (3, 6)]
    trainer, history, l1s = train(dataset, config(method), [scene["cameras"][i] for i in normal], [scene["images"][i] for i in normal])
    assert_healthy(trainer, history, dataset)
    assert_schedule_fired(history, method)
    assert_loss_decreased(l1s, method)


# ------------------------------------------------------------------ 2. a camera inside the scene
def inside_points(camera):
    """Points straddling the camera's image plane near its optical axis: behind it, on it,
    between it and the near plane, and just in front."""
    z = np.array([-0.05, -0.01, 0.0, 0.005, 0.01, 0.02, 0.04])
    xy = np.array([[0.0, 0.0], [0.01, -0.01], [-0.02, 0.01], [0.0, 0.02], [0.015, 0.0], [-0.01, -0.02], [0.02, 0.02]])
    cam_pts = np.concatenate([xy, z[:, None]], axis=1)
    return ((cam_pts - camera.viewmat[:3, 3]) @ camera.viewmat[:3, :3]).astype(np.float32)  # camera -> world


@pytest.mark.parametrize("method", METHODS)
def test_camera_inside_the_scene(scene, tmp_path, method):
    truth = scene["truth"]
    means = np.array(truth.means)
    lo, hi = means.min(axis=0), means.max(axis=0)
    assert ((INSIDE.center > lo) & (INSIDE.center < hi)).all()  # inside the bounding box
    depth = (means @ INSIDE.viewmat[:3, :3].T + INSIDE.viewmat[:3, 3])[:, 2]
    assert (depth < 0).sum() > 50 and (np.abs(depth) < 0.1).sum() > 3  # Gaussians behind it and beside its plane
    cameras = scene["cameras"] + [INSIDE]
    images = scene["images"] + [render_np(truth, INSIDE)]
    extra = inside_points(INSIDE)
    points = np.concatenate([scene["points"], extra])
    colours = np.concatenate([scene["colours"], np.full((len(extra), 3), 200, np.uint8)])
    dataset = write_dataset(tmp_path, cameras, images, points, colours)
    assert N_VIEWS in dataset.train
    seen = []
    load = dataset.load_image
    dataset.load_image = lambda i, *a, **k: (seen.append(i), load(i, *a, **k))[1]
    # the error is measured on the ring views: vanilla prunes Gaussians larger than 20 pixels on
    # screen after its opacity reset (3DGS's max_screen_size), which at 48x40 removes most of what
    # the inside view sees up close, so that view ends up worse than it started (by design)
    ring = [i for i in dataset.train if i != N_VIEWS]
    trainer, history, l1s = train(dataset, config(method), [cameras[i] for i in ring], [images[i] for i in ring])
    assert seen.count(N_VIEWS) >= 5  # the inside view was trained on
    assert_healthy(trainer, history, dataset)  # its render included
    assert_schedule_fired(history, method)
    assert_loss_decreased(l1s, method)


# ------------------------------------------------------------------ 3. exposure differences
EXPOSURE = (-0.2, 0.2, -0.15, 0.15, -0.1, 0.1, -0.05, 0.05, 0.2, -0.2)  # of the 10 training views
GRID_SHAPE = (4, 4, 4)  # a coarse grid: the default 16x16x8 has a cell per 3x2.5 pixels at 48x40 and fits the scene itself
# gsplat's rate for every method: MCMC's default of 1e-3 is set for full-length runs (docs/benchmarks/scenes.md, "The bilateral grid on
# the exposure scene"); in 160 steps a grid at that rate moves too little to follow the exposures
GRID_LR = 2e-3


def grid_gain(trainer, camera, index):
    """The least-squares gain the trained grid of image ``index`` applies to the model's render."""
    r = mx.array(render_np(trainer.model, camera))
    out = np.array(trainer.bilateral.apply(r, index))
    r = np.array(r)
    return float((out * r).sum() / (r * r).sum())


@pytest.mark.parametrize("method", METHODS)
def test_exposure_differences_with_and_without_the_bilateral_grid(scene, tmp_path, method):
    from mlx3d.training.metrics import psnr

    factors = np.ones(N_VIEWS)
    train_views = [i for i in range(N_VIEWS) if i % 8]
    factors[train_views] = 1.0 + np.array(EXPOSURE)
    images = [np.clip(img * f, 0, 1) for img, f in zip(scene["images"], factors)]
    dataset = write_dataset(tmp_path, scene["cameras"], images, scene["points"], scene["colours"])
    held = dataset.test  # unscaled: their truth is the scene's own exposure
    held_cams = [scene["cameras"][i] for i in held]
    held_truth = [scene["images"][i] for i in held]
    results = {}
    for use_grid in (False, True):
        cfg = config(method, bilateral_grid=use_grid, bilateral_grid_shape=GRID_SHAPE, bilateral_grid_lr=GRID_LR)
        trainer, history, l1s = train(dataset, cfg, held_cams, held_truth)
        assert_healthy(trainer, history, dataset)
        assert_schedule_fired(history, method)
        assert_loss_decreased(l1s, method)
        held_psnr = np.mean([float(psnr(mx.array(render_np(trainer.model, c)), mx.array(t))) for c, t in zip(held_cams, held_truth)])
        results[use_grid] = (trainer, held_psnr)
    trainer = results[True][0]
    assert trainer.bilateral.num_images == N_VIEWS
    gains = np.array([grid_gain(trainer, scene["cameras"][i], i) for i in train_views])
    f = factors[train_views]
    # the grids moved towards the exposures: up to the free overall scale the grid and the
    # scene share, brighter photos got larger gains (measured correlation 0.92-0.999 over seeds)
    assert np.corrcoef(gains, f)[0, 1] > 0.85
    relative = gains / gains.mean()
    strong = np.abs(f - 1) >= 0.1
    assert (np.sign(relative[strong] - 1) == np.sign(f[strong] - 1)).all(), (relative, f)
    # held-out PSNR against the unscaled truth: the grid helps clearly without an opacity reset
    # in the run (mcmc: +1.9 to +2.3 dB over seeds 0-2 over a fixed background, +1.0 dB at seed 0
    # over the random one it now trains over, with its backdrop seeded); with one, 80 steps before the
    # end, both runs are still recovering and differ by less (vanilla -0.3 to +1.3 dB, 2dgs
    # within 0.1 dB)
    if method == "mcmc":
        assert results[True][1] > results[False][1] + 0.5, results
    else:
        assert results[True][1] > results[False][1] - 1.0, results


# ------------------------------------------------------------------ 4. far outliers in the point cloud
def with_outliers(points, colours, fraction=0.01, seed=3):
    """The points plus ``fraction`` of their count placed 10^3-10^4 scene radii away."""
    rng = np.random.default_rng(seed)
    k = max(1, int(round(fraction * len(points))))
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    far = d * SCENE_RADIUS * 10.0 ** rng.uniform(3, 4, (k, 1))
    return np.concatenate([points, far]).astype(np.float32), np.concatenate([colours, np.full((k, 3), 128, np.uint8)])


@pytest.mark.parametrize("method", METHODS)
def test_far_outliers_in_the_initial_points(scene, tmp_path, method):
    points, colours = with_outliers(scene["points"], scene["colours"])
    n = len(scene["points"])
    dataset = write_dataset(tmp_path, scene["cameras"], scene["images"], points, colours)
    model = initial_model(dataset)
    # from_points: the inliers' kNN scales are those of the clean cloud, the outliers' are large
    clean = GaussianModel.from_points(scene["points"], scene["colours"], sh_degree=1, initial_opacity=0.1)
    scales = np.exp(np.array(model.params["scales"]))
    np.testing.assert_allclose(scales[:n], np.exp(np.array(clean.params["scales"])), rtol=1e-5)
    assert np.isfinite(scales).all() and (scales[n:] > 100 * SCENE_RADIUS).all()
    # the scene extent comes from the cameras, so the learning rates and thresholds are untouched
    extent = dataset.scene_extent()
    centres = np.array([scene["cameras"][i].center for i in dataset.train])
    assert extent == pytest.approx(1.1 * np.linalg.norm(centres - centres.mean(axis=0), axis=1).max(), rel=1e-6)
    # 3DGS's size prunes for every Gaussian (by default, Gaussians this far out are the backdrop and
    # only go when transparent, as with MCMC below)
    cfg = config(method, backdrop_distance=None)
    assert GaussianTrainer(model.copy(), cfg, extent).learning_rates() == GaussianTrainer(clean, cfg, extent).learning_rates()
    trainer, history, l1s = train(dataset, cfg, scene["cameras"], scene["images"], model=model)
    means = np.array(trainer.model.means)
    far = np.linalg.norm(means, axis=1) > 10 * CAMERA_RADIUS
    assert_healthy(trainer, history, dataset)
    assert_schedule_fired(history, method)
    assert_loss_decreased(l1s, method)
    if method != "mcmc":
        # pruned as too large in the world once the opacity reset has happened
        assert not far.any()
    # mcmc never prunes by size: the outliers stay (unless relocated when transparent) and, as
    # the SGLD noise is N(0, Σ) with their huge Σ, wander further out (~1e8 here), still finite
    assert (~far).sum() >= 0.9 * n  # the scene itself is kept


# ------------------------------------------------------------------ 5. Gaussians on a camera's plane
@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize("method", METHODS)
def test_gaussians_on_the_camera_plane(method, antialias):
    """A camera at the origin with axis-aligned axes (camera z = world z exactly) and Gaussians
    at depth exactly 0 (on the image plane, and at the camera centre), at 1e-30 (x/z overflows),
    between the plane and the near plane, and behind it: all culled, and their gradients
    (the 2DGS planar depth divides by the depth) must stay finite."""
    cam = Camera(W, H, 40.0, 40.0, W / 2, H / 2, np.eye(4))
    rng = np.random.default_rng(0)
    visible = rng.uniform(-0.5, 0.5, (40, 3)) + [0.0, 0.0, 2.0]
    plane = np.array([[0.3, 0.1, 0.0], [0.0, 0.0, 0.0], [-0.2, 0.25, 1e-30], [0.2, -0.1, 0.005], [0.1, 0.1, -0.2]])
    model = GaussianModel.from_points(np.concatenate([visible, plane]).astype(np.float32), sh_degree=1, initial_opacity=0.5)
    depths = np.array(model.render(cam)["depths"])
    assert (depths[40:42] == 0).all() and 0 < depths[42] < 1e-20
    cfg = TrainerConfig(method=method, steps=10, geometry_from=0, antialias=antialias, lambda_2d_depth_variance=100.0, lambda_2d_normal_consistency=0.05)
    trainer = GaussianTrainer(model, cfg, scene_extent=2.0)
    target = np.full((H, W, 3), 0.3, np.float32)
    losses = [trainer.step(cam, target)["loss"] for _ in range(3)]  # TrainingError on a NaN/Inf gradient
    assert np.isfinite(losses).all() and losses[-1] < losses[0]
    for name, value in trainer.model.params.items():
        assert bool(mx.all(mx.isfinite(value))), name
