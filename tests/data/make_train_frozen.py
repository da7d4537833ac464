"""Writes train_frozen.npz: the parameters after short seeded training runs, used by
tests/test_train_batches.py::test_batch_size_one_is_bitwise_the_frozen_runs.

Each run trains a small seeded scene through ``GaussianTrainer.fit`` on a
folder dataset (view draws, random backgrounds behind opaque photos), with a
densification round, an opacity reset, MCMC relocation and growth, SGLD
noise, a bilateral grid and 2DGS surfels with their geometry losses between
them. The file was written before
batches of views existed; the test checks that batch size 1 on one process
still reproduces it bit for bit. Rerunning this script overwrites it with the
current trainer's results, so only do that on purpose; naming runs rewrites only those, keeping the others:

    .venv/bin/python tests/data/make_train_frozen.py [RUN ...]

The surfels run was rewritten when the 2DGS depth variance became that of inverse depth (weight 3).
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: name -> TrainerConfig keywords of each frozen run (the test imports this).
RUNS = {
    "vanilla": dict(steps=48, densify_from=5, densify_every=10, densify_until=40, opacity_reset_every=20, reset_recovery=5,
                    densify_grad_threshold=1e-6, sh_increase_every=10, max_gaussians=150),
    "mcmc": dict(method="mcmc", steps=48, densify_from=5, densify_every=10, densify_until=40, max_gaussians=120,
                 sh_increase_every=10, init_background_points=0),
    "grid": dict(steps=30, densify_from=5, densify_every=10, densify_until=25, densify_grad_threshold=1e-6,
                 bilateral_grid=True, bilateral_grid_shape=(4, 4, 2), bilateral_grid_warmup=5),
    "surfels": dict(method="2dgs", steps=30, densify_from=5, densify_every=10, densify_until=25, densify_grad_threshold=1e-6,
                    geometry_from=10),
}


def scene(folder: Path):
    """(start model, folder dataset) of a seeded 60-Gaussian scene photographed by 6 cameras (40x32 px)."""
    from PIL import Image

    from mlx3d.cameras import Camera
    from mlx3d.datasets import load_dataset
    from mlx3d.splatting import GaussianModel

    rng = np.random.default_rng(7)
    truth = GaussianModel.from_points(rng.uniform(-0.6, 0.6, (60, 3)).astype(np.float32), rng.uniform(0, 1, (60, 3)), sh_degree=1,
                                      initial_opacity=0.8)
    cams = [Camera.look_at(eye=(3 * math.cos(a), 3 * math.sin(a), 0.5), at=(0, 0, 0), up=(0, 0, 1), width=40, height=32, hfov=45.0)
            for a in np.linspace(0, 2 * math.pi, 6, endpoint=False)]
    frames = []
    for i, cam in enumerate(cams):
        image = np.array(truth.render(cam, background=(0.2, 0.3, 0.4))["image"])
        Image.fromarray((np.clip(image, 0, 1) * 255).round().astype(np.uint8)).save(folder / f"f{i}.png")
        frames.append({"file_path": f"f{i}.png", "transform_matrix": cam.to_opengl_c2w().tolist()})
    c = cams[0]
    meta = {"camera_model": "PINHOLE", "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height,
            "frames": frames, "train_filenames": [f["file_path"] for f in frames[1:]], "test_filenames": [frames[0]["file_path"]]}
    (folder / "transforms.json").write_text(json.dumps(meta))
    start = GaussianModel.from_points(np.asarray(truth.means) + rng.normal(0, 0.05, (60, 3)).astype(np.float32), sh_degree=1,
                                      initial_opacity=0.3)
    return start, load_dataset(folder)


def run(name: str, folder: Path, ranks=None, progress=None, **overrides) -> dict:
    """Parameters (numpy) after frozen run ``name`` (``overrides`` change its config; ``ranks``: trained
    together with other processes, see mlx3d.training.distributed; ``progress`` as ``fit``'s), and the trainer."""
    from mlx3d.splatting import GaussianModel
    from mlx3d.training import GaussianTrainer, TrainerConfig

    start, dataset = scene(folder)
    config = TrainerConfig(seed=3, **{**RUNS[name], **overrides})
    trainer = GaussianTrainer(GaussianModel(dict(start.params)), config, scene_extent=dataset.scene_extent(),
                              **({} if ranks is None else {"ranks": ranks}))
    trainer.fit(dataset, progress=progress)
    return {k: np.array(v) for k, v in trainer.model.params.items()}, trainer


def main(names) -> int:
    from mlx3d import native

    unknown = sorted(set(names) - set(RUNS))
    if unknown:
        print(f"no frozen run named {', '.join(unknown)} (the runs: {', '.join(RUNS)})", file=sys.stderr)
        return 2
    lanes = np.int32(native.core().rasterizer_simd_lanes())
    data = {"lanes": lanes}
    if names:  # the other runs as written
        kept = np.load(HERE / "train_frozen.npz")
        if int(kept["lanes"]) != lanes:
            print("the file was written with another SIMD width: rewrite every run", file=sys.stderr)
            return 2
        data.update({k: kept[k] for k in kept.files if k.split("/")[0] not in names})
    for name in names or RUNS:
        with tempfile.TemporaryDirectory() as tmp:
            params, _ = run(name, Path(tmp))
        for k, v in params.items():
            data[f"{name}/{k}"] = v
        print(name, {k: v.shape for k, v in params.items()})
    np.savez_compressed(HERE / "train_frozen.npz", **data)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parent.parent))
    sys.exit(main(sys.argv[1:]))
