"""MCMC against vanilla on a small unbounded scene: objects on a ground that runs out of frame under
a sky that must itself be made of Gaussians, opaque photos, held-out views off the training ring.

The failure this guards against: MCMC building the sky out of sky-coloured Gaussians among the
cameras, which fit every ring view and veil the views off the ring (see mlx3d.training.initial).
Measured here (held-out PSNR per view, mean): vanilla 21.8 25.8 24.9 14.5 21.1 24.6 (22.1); MCMC
21.6 (worst 17.1, the closest view); MCMC started as before the backdrop and the reference's initial
opacity and scale: 22.0 with the far view veiled at 15.1 dB, which the haze check rejects."""

import json
import math

import mlx.core as mx
import numpy as np
import pytest
from PIL import Image

from core_marks import long_training
from mlx3d.cameras import Camera
from mlx3d.datasets import load_dataset
from mlx3d.report import scene
from mlx3d.splatting import GaussianModel
from mlx3d.splatting.sh import C0
from mlx3d.training import GaussianTrainer, TrainerConfig
from mlx3d.training.initial import initial_state
from mlx3d.training.metrics import psnr

pytestmark = long_training

SIZE = 40
STEPS = 700
MARGIN_DB = 1.0  # MCMC's held-out mean may trail vanilla's by at most this
HAZE_DB = 6.0  # and no held-out view may fall this far below MCMC's own mean


def _surfels(points, rgb, size, opacity_logit):
    n = len(points)
    return {"means": points, "scales": np.log(np.column_stack([size, size, 0.05 * size])), "quats": np.tile([1.0, 0, 0, 0], (n, 1)),
            "opacities": np.full(n, opacity_logit), "sh_dc": ((np.clip(rgb, 0, 1) - 0.5) / C0)[:, None, :], "sh_rest": np.zeros((n, 3, 3))}


def _truth(rng) -> GaussianModel:
    """The built-in scene's objects, a checker ground out to radius 40 and a sky dome at radius 60."""
    objects = {k: np.array(v) for k, v in scene.ground_truth(0.05, 0).params.items()}
    objects["sh_rest"] = objects["sh_rest"][:, :3]
    n = 20_000
    r = np.exp(rng.uniform(np.log(1.15), np.log(40.0), n))
    theta = rng.uniform(0, 2 * np.pi, n)
    ground = np.column_stack([r * np.cos(theta), r * np.sin(theta), np.zeros(n)])
    outside = (np.abs(ground[:, 0]) > 1.2) | (np.abs(ground[:, 1]) > 1.2)
    ground, r = ground[outside], r[outside]
    cell = (np.floor(ground[:, 0] / 0.6) + np.floor(ground[:, 1] / 0.6)) % 2
    green = np.where(cell[:, None] > 0, [0.45, 0.55, 0.3], [0.3, 0.38, 0.2])
    m = 4000
    i = np.arange(m) + 0.5
    z = 1 - i / m * 1.05
    phi = math.pi * (1 + 5**0.5) * i
    ring = np.sqrt(np.clip(1 - z * z, 0, 1))
    dirs = np.column_stack([ring * np.cos(phi), ring * np.sin(phi), z])
    sky = np.array([0.55, 0.72, 0.92])[None, :] * (1 - 0.3 * np.clip(dirs[:, 2:3], 0, 1))
    parts = [objects, _surfels(ground, green, 0.04 * r, 4.0), _surfels(60.0 * dirs, sky, np.full(m, 3.5), 6.0)]
    parts[2]["scales"][:] = math.log(3.5)  # round sky blobs
    return GaussianModel({k: mx.array(np.concatenate([p[k] for p in parts]).astype(np.float32)) for k in objects})


def _camera(elevation, azimuth, distance):
    el, az = math.radians(elevation), math.radians(azimuth)
    look = np.array(scene.LOOK_AT)
    eye = look + distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    return Camera.look_at(eye, look, up=(0, 0, 1), width=SIZE, height=SIZE, fov=50.0)


@pytest.fixture(scope="module")
def outdoor(tmp_path_factory):
    folder = tmp_path_factory.mktemp("outdoor")
    rng = np.random.default_rng(0)
    truth = _truth(rng)
    train = [_camera(el, 360.0 * k / 16 + (11.25 if el > 20 else 0), 3.2) for el in (15, 35) for k in range(16)]
    # off the rings (between their heights, closer, farther, other azimuths) and seeing what the rings saw:
    # a view below the lower ring would look at sky no training view shows
    test = [_camera(20, 20, 3.2), _camera(30, 80, 3.2), _camera(25, 130, 2.6), _camera(25, 200, 4.0), _camera(30, 300, 3.8), _camera(20, 250, 2.8)]
    frames = []
    for j, cam in enumerate(train + test):
        name = f"f{j:02d}.png"
        Image.fromarray((scene.render_view(truth, cam) * 255).round().astype(np.uint8)).save(folder / name)
        frames.append({"file_path": name, "transform_matrix": cam.to_opengl_c2w().tolist()})
    means, colours = np.asarray(truth.means), np.asarray(truth.colors)
    near = np.flatnonzero(np.linalg.norm(means[:, :2], axis=1) < 4.5)  # the points a capture would find: not the sky
    pick = rng.choice(near, 3000, replace=False)
    scene._write_points_ply(folder / "points.ply", (means[pick] + rng.normal(0, 0.03, (3000, 3))).astype(np.float32),
                            np.clip(np.round(colours[pick] * 255), 0, 255).astype(np.uint8))
    c = train[0]
    names = [f["file_path"] for f in frames]
    meta = {"camera_model": "PINHOLE", "w": SIZE, "h": SIZE, "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "ply_file_path": "points.ply",
            "frames": frames, "train_filenames": names[: len(train)], "test_filenames": names[len(train):]}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return load_dataset(folder)


def _held_out(dataset, method, **overrides):
    # Both methods train over the black these photos show around nothing: this test compares the density
    # methods. The default behind opaque photos, a random colour per step, is ahead for both at the
    # benchmark scenes' 3,000 steps (docs/benchmarks/scenes.md), but after 700 steps here it still costs MCMC's backdrop
    # more (held-out 19.9 vs 21.8 dB) than vanilla (20.8 vs 21.6 dB).
    config = TrainerConfig(method=method, steps=STEPS, sh_increase_every=200, densify_from=100, densify_until=600, densify_every=50,
                           opaque_background=None, **overrides)
    start = initial_state(dataset, config, sh_degree=1)
    trainer = GaussianTrainer(start.model, start.config, scene_extent=dataset.scene_extent())
    trainer.fit(dataset)
    values = []
    for i in dataset.test:
        target, _ = dataset.load_image(i, background="black")
        image = trainer.model.render(dataset.frames[i].camera, background=(0, 0, 0))["image"]
        values.append(float(psnr(mx.clip(image, 0, 1), mx.array(target))))
    return np.array(values), len(trainer.model)


def test_mcmc_holds_up_against_vanilla_off_the_training_ring(outdoor):
    # Against vanilla without its backdrop, as this test was written: with it (the default now) vanilla
    # reaches 29.4 dB here after 700 steps, far ahead of MCMC, whose small, half-opaque start (gsplat's
    # MCMC preset) covers the frame more slowly; at the benchmark scenes' 3,000 steps (docs/benchmarks/scenes.md) vanilla leads too.
    vanilla, n_vanilla = _held_out(outdoor, "vanilla", init_background_points=0)
    mcmc, n_mcmc = _held_out(outdoor, "mcmc", max_gaussians=None)
    print(f"vanilla {vanilla.round(1)} ({n_vanilla}), mcmc {mcmc.round(1)} ({n_mcmc})")
    assert mcmc.mean() >= vanilla.mean() - MARGIN_DB, (mcmc, vanilla)
    assert mcmc.min() >= mcmc.mean() - HAZE_DB, mcmc


def test_vanilla_keeps_its_backdrop_through_the_size_prunes(outdoor):
    # Opacity resets at steps 200 and 400, so that the size prunes (20 px on screen, 0.1 x extent in the
    # world) run from step 250 to 600. The backdrop sphere lies 10 x the extent away: beyond backdrop_distance (5 x)
    # it is exempt and stays; with 3DGS's prunes for every Gaussian it goes, and the sky becomes a veil.
    overrides = dict(opacity_reset_every=200, reset_recovery=300)
    kept, n_kept = _held_out(outdoor, "vanilla", **overrides)
    pruned, n_pruned = _held_out(outdoor, "vanilla", backdrop_distance=None, **overrides)
    print(f"backdrop kept {kept.round(1)} ({n_kept}), pruned {pruned.round(1)} ({n_pruned})")
    # measured: kept 28.0 (worst 25.6), pruned 21.9 (worst 14.2); without a backdrop 21.5 (worst 13.9)
    assert kept.mean() >= pruned.mean() + 2.0, (kept, pruned)
    assert kept.min() >= kept.mean() - HAZE_DB, kept
