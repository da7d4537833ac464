"""Held-out evaluation: colour-corrected metrics, the worst view, `mlx3d eval` output."""

import json

import numpy as np
import pytest

from mlx3d.cli import main
from mlx3d.datasets import load_dataset
from mlx3d.splatting import GaussianModel
from mlx3d.training.evaluate import METRICS, evaluate, worst_view
from test_trainer import small_problem

# The held-out photo f00 was taken at another exposure and white balance: gain, offset and channel mixing.
COLOUR_MAP = np.array([[0.70, 0.10, 0.00, 0.08], [0.05, 0.60, 0.10, 0.12], [0.00, 0.10, 0.65, 0.15]])


@pytest.fixture
def scene(tmp_path):
    """A dataset folder of the ground-truth model's own renders (12 views, f00 and f08 held out) and the model itself."""
    from PIL import Image

    _, cams, _ = small_problem(3)
    rng = np.random.default_rng(3)
    truth = GaussianModel.from_points(rng.uniform(-0.6, 0.6, (60, 3)).astype(np.float32), rng.uniform(0, 1, (60, 3)), sh_degree=1, initial_opacity=0.8)
    cams = cams * 2
    frames = []
    for i, cam in enumerate(cams):
        img = np.array(truth.render(cam, background=(0, 0, 0))["image"], dtype=np.float64)
        if i == 0:
            img = img @ COLOUR_MAP[:, :3].T + COLOUR_MAP[:, 3]
        Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).save(tmp_path / f"f{i:02d}.png")
        frames.append({"file_path": f"f{i:02d}.png", "transform_matrix": cam.to_opengl_c2w().tolist()})
    c = cams[0]
    meta = {"camera_model": "PINHOLE", "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    truth.save_ply(tmp_path / "truth.ply")
    return tmp_path, truth


def test_worst_view_is_the_true_minimum():
    rng = np.random.default_rng(0)
    for _ in range(20):
        views = [{"name": f"v{i}", **{k: float(x) for k, x in zip(METRICS, rng.normal(25, 5, 4))}} for i in range(int(rng.integers(1, 12)))]
        for key in METRICS:
            assert worst_view(views, key)["name"] == views[int(np.argmin([v[key] for v in views]))]["name"]
    ties = [{"name": "a", "psnr": 20.0}, {"name": "b", "psnr": 20.0}, {"name": "c", "psnr": 30.0}]
    assert worst_view(ties)["name"] == "a"
    with pytest.raises(ValueError):
        worst_view([])


def test_evaluate_reports_colour_corrected_metrics_and_the_worst_view(scene, tmp_path_factory):
    folder, truth = scene
    dataset = load_dataset(folder)
    assert [dataset.frames[i].name for i in dataset.test] == ["f00.png", "f08.png"]
    out = tmp_path_factory.mktemp("eval")
    report = evaluate(truth, dataset, "test", out_dir=out)
    views = {v["name"]: v for v in report["views"]}
    assert set(views["f00.png"]) == {"name", *METRICS}
    # f00: the right content at another exposure. Plain PSNR counts the colour change as error, CC-PSNR
    # sees through it (up to 8-bit rounding of the photo).
    assert views["f00.png"]["psnr"] < 25 and views["f00.png"]["cc_psnr"] > 45, views
    assert views["f08.png"]["psnr"] > 45 and views["f08.png"]["cc_psnr"] >= views["f08.png"]["psnr"] - 1e-6
    assert views["f00.png"]["cc_ssim"] > 0.99 > views["f00.png"]["ssim"]
    for key in METRICS:
        assert report[key] == pytest.approx(np.mean([v[key] for v in report["views"]]))
    assert report["worst"] == views["f00.png"]
    assert report["cc_worst"] == min(report["views"], key=lambda v: v["cc_psnr"])
    assert report["split"] == "test" and report["num_gaussians"] == len(truth) and report["seconds_per_view"] > 0
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["worst"]["name"] == "f00.png" and on_disk["cc_psnr"] == pytest.approx(report["cc_psnr"])
    assert sorted(p.name for p in (out / "renders").glob("*.png")) == ["f00.png", "f08.png"]


def test_eval_command_prints_colour_corrected_columns_and_the_worst_view(scene, capsys):
    folder, _ = scene
    assert main(["eval", str(folder / "truth.ply"), "--data", str(folder)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith("f00.png") and "CC-PSNR" in lines[0] and "CC-SSIM" in lines[0]
    assert any(line.startswith("mean") and "CC-PSNR" in line for line in lines)
    worst = [line for line in lines if line.startswith("worst view: ")]
    assert len(worst) == 1 and "f00.png" in worst[0] and "colour-corrected" in worst[0]
