"""`mlx3d train` and `mlx3d eval` on a small dataset folder written by the test."""

import json

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from mlx3d.cli import main
from mlx3d.io import read_splat_ply
from test_trainer import small_problem
from core_marks import above_kernels

pytestmark = above_kernels


@pytest.fixture
def dataset_dir(tmp_path):
    from PIL import Image

    model, cams, targets = small_problem(6)
    cams, targets = cams * 2, targets * 2  # 12 views: two held out
    frames = []
    for i, (cam, img) in enumerate(zip(cams, targets)):
        Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).save(tmp_path / f"f{i:02d}.png")
        frames.append({"file_path": f"f{i:02d}.png", "transform_matrix": cam.to_opengl_c2w().tolist()})
    pts = np.asarray(model.means)
    verts = np.zeros(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, axis in enumerate("xyz"):
        verts[axis] = pts[:, i]
    verts["red"] = verts["green"] = verts["blue"] = 128
    PlyData([PlyElement.describe(verts, "vertex")]).write(str(tmp_path / "points.ply"))
    c = cams[0]
    meta = {"camera_model": "PINHOLE", "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height, "frames": frames, "ply_file_path": "points.ply"}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    return tmp_path


# MCMC starts from Gaussians a tenth of the neighbour distance (as gsplat's MCMC preset): more steps to cover the views
@pytest.mark.parametrize("method,steps", [("vanilla", 60), ("mcmc", 240)])
def test_train_then_eval(dataset_dir, tmp_path_factory, capsys, method, steps):
    out = tmp_path_factory.mktemp("out")
    code = main(["train", str(dataset_dir), "--out", str(out / "model.ply"), "--steps", str(steps), "--method", method, "--max-gaussians", "200", "--eval", "--checkpoint-every", "30"])
    assert code == 0
    err = capsys.readouterr().err
    assert "steps/s" in err and "ETA" in err
    model = read_splat_ply(out / "model.ply")
    assert model.count >= 60 and model.sh_degree == 3
    report = json.loads((out / "model_eval" / "metrics.json").read_text())
    assert len(report["views"]) == 2 and report["psnr"] > 10
    assert (out / "checkpoint.npz").exists()
    assert main(["eval", str(out / "model.ply"), "--data", str(dataset_dir), "--out", str(out / "ev")]) == 0
    assert "mean" in capsys.readouterr().out
    assert len(list((out / "ev" / "renders").glob("*.png"))) == 2


def test_resume_and_errors(dataset_dir, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    assert main(["train", str(dataset_dir), "--out", str(out / "m.ply"), "--steps", "20", "--checkpoint-every", "10"]) == 0
    assert main(["train", str(dataset_dir), "--out", str(out / "m2.ply"), "--steps", "30", "--resume", str(out / "checkpoint.npz")]) == 0
    assert "resumed at step 20" in capsys.readouterr().out
    assert main(["train", str(tmp_path / "nothing"), "--out", str(out / "x.ply"), "--steps", "5"]) == 1
    assert "nothing" in capsys.readouterr().err
    assert not (out / "x.ply").exists()
    # transforms.json holds points but no photo's observations of them
    assert main(["train", str(dataset_dir), "--out", str(out / "x.ply"), "--steps", "5", "--sparse-depth", "0.01"]) == 1
    assert "--sparse-depth needs the points a solve placed" in capsys.readouterr().err
    assert not (out / "x.ply").exists()
    with pytest.raises(SystemExit):
        main(["train", str(dataset_dir), "--out", str(out / "x.ply"), "--sparse-depth", "nan"])
    assert "must be a number >= 0" in capsys.readouterr().err


@pytest.mark.parametrize("method", ["vanilla", "mcmc"])
def test_a_resumed_run_writes_the_file_the_whole_run_writes(dataset_dir, tmp_path, method):
    """--resume from the checkpoint a run wrote at step 20 continues with the settings the run resolved when it
    started (MCMC's Gaussian budget, the backdrop seeded behind opaque photos), so the output is byte for byte
    that of the run itself."""
    common = ["train", str(dataset_dir), "--steps", "30", "--method", method, "--sh-degree", "1", "--checkpoint-every", "20"]
    assert main([*common, "--out", str(tmp_path / "whole.ply")]) == 0
    assert main([*common, "--out", str(tmp_path / "resumed.ply"), "--resume", str(tmp_path / "checkpoint.npz")]) == 0
    assert (tmp_path / "resumed.ply").read_bytes() == (tmp_path / "whole.ply").read_bytes()
