"""The accuracy report (``mlx3d bench accuracy``): plots, statistics, Pareto choices, the scene and a tiny run end to end."""

import itertools
import json
import math
import os
import re

import numpy as np
import pytest
from PIL import Image

from mlx3d.cli import main
from mlx3d.datasets import load_dataset
from mlx3d.report import plot as plt
from mlx3d.report import scene
from mlx3d.report.accuracy import MODES, Cancelled, run_accuracy, schedule, train_cases
from mlx3d.report.stats import best_within, budget_table, format_spread, pareto_front, summary
from core_marks import above_kernels

pytestmark = above_kernels  # the report over the trainer and renderer: the pure path runs the same code there


# ------------------------------------------------------------------ plots
def colour_mask(a, colour, tol=40):
    return (np.abs(a.astype(int) - np.array(colour)).sum(axis=-1) < tol)


def test_line_plot_draws_title_axes_legend_and_both_lines(tmp_path):
    x = [1, 2, 5, 10, 20, 50]
    series = [plt.Series("first", x, [20, 22, 24, 25, 26, 26.5]), plt.Series("second", x, [18, 21, 23, 25.5, 27, 28])]
    image = plt.plot(series, title="A title", xlabel="wall time (s)", ylabel="PSNR (dB)", log_x=True, size=(800, 500))
    plt.save_png(image, tmp_path / "p.png")
    with Image.open(tmp_path / "p.png") as im:
        assert im.format == "PNG" and im.size == (800, 500)
        a = np.asarray(im.convert("RGB"))
    ink = (a < 150).all(axis=-1)  # dark pixels: text, frame, ticks
    assert ink[:45, 200:600].any(), "the title"
    assert ink[:, :60].sum() > 100, "the y label and tick numbers on the left"
    assert ink[440:, 100:600].sum() > 100, "the x label and tick numbers at the bottom"
    blue, orange = colour_mask(a, plt.PALETTE[0]), colour_mask(a, plt.PALETTE[1])
    assert blue[60:420, 80:600].sum() > 300 and orange[60:420, 80:600].sum() > 300, "both lines in the plot area"
    assert blue[:, 640:].sum() > 20 and orange[:, 640:].sum() > 20, "both legend entries on the right"
    assert ink[:, 650:].sum() > 100, "legend text"
    # The two lines are where their data puts them: 'second' ends higher (smaller row) than 'first' at the right edge.
    cols = slice(560, 600)
    assert np.nonzero(orange[:, cols])[0].mean() < np.nonzero(blue[:, cols])[0].mean()


def test_scatter_with_error_bars_and_labels_and_bars():
    series = [plt.Series("points", [1.0, 2.0, 3.0], [3, 1, 2], line=False, xerr=[(0.8, 1.2), (1.5, 2.5), (2.9, 3.1)], labels=["a", "b", "c"])]
    image = plt.plot(series, title="t", xlabel="x (ms)", ylabel="y (dB)", legend=False, size=(600, 400))
    a = np.asarray(image)
    assert image.size == (600, 400)
    assert colour_mask(a, plt.PALETTE[0]).sum() > 100
    assert not colour_mask(a, plt.PALETTE[0])[:, 560:].any(), "no legend"
    bars = plt.barh(["one", "two"], {"on": [3.0, 5.0], "off": [1.0, 2.0]}, title="bars", xlabel="time (ms)", size=(600, 300))
    b = np.asarray(bars)
    assert bars.size == (600, 300)
    assert colour_mask(b, plt.PALETTE[0]).sum() > colour_mask(b, plt.PALETTE[1]).sum() > 200  # 'on' bars are longer
    with pytest.raises(ValueError, match="one value per category|2 values"):
        plt.barh(["one"], {"on": [1.0, 2.0]}, title="t", xlabel="x")
    with pytest.raises(ValueError, match="y values"):
        plt.Series("bad", [1, 2], [1])


def test_ticks_are_round_and_cover_the_range():
    for lo, hi in [(0.0, 1.0), (17.3, 33.9), (-5.0, 12.0), (0.001, 0.0037), (1000.0, 98000.0)]:
        ticks = plt.nice_ticks(lo, hi)
        assert 3 <= len(ticks) <= 12
        assert ticks[0] <= lo + (ticks[1] - ticks[0]) and ticks[-1] >= hi - (ticks[1] - ticks[0])
        steps = np.diff(ticks)
        np.testing.assert_allclose(steps, steps[0], rtol=1e-9)
        mantissa = steps[0] / 10 ** math.floor(math.log10(steps[0]))
        assert any(math.isclose(mantissa, m) for m in (1, 2, 2.5, 5))
    assert plt.log_ticks(0.7, 300) == [1, 2, 5, 10, 20, 50, 100, 200]
    assert plt.log_ticks(0.01, 1e5) == [0.01, 0.1, 1, 10, 100, 1000, 1e4, 1e5]
    assert plt.format_tick(2.5, 2.5) == "2.5" and plt.format_tick(20000.0, 5000.0) == "20,000" and plt.format_tick(0.25, 0.05) == "0.25"


# ------------------------------------------------------------------ statistics and Pareto choices
def test_summary_and_spread():
    s = summary([5.0, 1.0, 3.0, 2.0, 4.0, math.nan])
    assert s == {"median": 3.0, "p25": 2.0, "p75": 4.0, "min": 1.0, "max": 5.0, "n": 5}
    assert format_spread(s, scale=10, digits=0) == "30 (20-40)"
    assert format_spread(summary([-2.0, 1.0, 3.0]), digits=1) == "1.0 (-0.5 to 2.0)"
    assert summary([])["n"] == 0 and math.isnan(summary([])["median"]) and format_spread(summary([])) == "-"


def brute_best(rows, budget, tie=0.0):
    fitting = [r for r in rows if r["seconds"] <= budget]
    if not fitting:
        return None
    top = max(r["psnr"] for r in fitting)
    return min((r for r in fitting if r["psnr"] >= top - tie), key=lambda r: (r["seconds"], rows.index(r)))


def brute_front(rows):
    """Rows no other row dominates; of equal rows the first."""
    def dominated(i, r):
        return any((o["seconds"] <= r["seconds"] and o["psnr"] > r["psnr"]) or (o["seconds"] < r["seconds"] and o["psnr"] >= r["psnr"])
                   or (j < i and (o["seconds"], o["psnr"]) == (r["seconds"], r["psnr"])) for j, o in enumerate(rows) if o is not r)
    return sorted((r for i, r in enumerate(rows) if not dominated(i, r)), key=lambda r: r["seconds"])


@pytest.mark.parametrize("seed", range(6))
def test_pareto_choices_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 40))
    # Coarse values so ties in time and in PSNR occur.
    rows = [{"name": f"c{i}", "seconds": float(rng.integers(1, 15)), "psnr": float(rng.integers(20, 30))} for i in range(n)]
    budgets = [0.5, 1.0, 3.0, 7.5, 14.0, 100.0]
    for tie in (0.0, 1.0, 2.5):
        for budget, best in budget_table(rows, budgets, tie=tie):
            assert best is brute_best(rows, budget, tie)
    assert budget_table(rows, [0.5])[0][1] is None
    front = pareto_front(rows)
    oracle = brute_front(rows)
    assert front == oracle and all(a is b for a, b in zip(front, oracle))
    # Along the front, more time buys more PSNR.
    assert all(a["seconds"] < b["seconds"] and a["psnr"] < b["psnr"] for a, b in itertools.pairwise(front))


def test_best_within_uses_the_given_keys_and_skips_missing_values():
    rows = [{"ms": 2.0, "db": 30.0}, {"ms": 1.0, "db": math.nan}, {"ms": 1.5, "db": 29.0}]
    assert best_within(rows, 1.9, "ms", "db") is rows[2]
    assert best_within(rows, 5.0, "ms", "db") is rows[0]


def test_schedule_reaches_each_budget_and_cases_change_one_factor():
    for steps, initial, budget in [(300, 1000, 10000), (800, 5000, 100000), (16, 300, 900), (800, 5000, 10000)]:
        s = schedule(steps, initial, budget)
        events = sum(1 for k in range(s["densify_from"] + 1, s["densify_until"] + 1) if k % s["densify_every"] == 0)
        assert events >= 1 and initial * (1 + s["mcmc_growth"]) ** events >= budget * 0.99
        assert s["sh_increase_every"] * 3 <= steps and s["opacity_reset_every"] == 0
    cases = train_cases(MODES["full"])
    base = cases[0]
    assert (base.method, base.budget, base.sh_degree, base.projection, base.antialias, base.scale) == ("mcmc", 30000, 3, "ewa", False, 1.0)
    fields = ("method", "budget", "sh_degree", "projection", "antialias", "scale")
    for case in cases[1:]:
        assert sum(getattr(case, f) != getattr(base, f) for f in fields) == 1, case
    assert {c.budget for c in cases} == {10000, 30000, 100000} and {c.sh_degree for c in cases} == {0, 1, 3}


# ------------------------------------------------------------------ the scene
def test_scene_is_deterministic_and_loads_as_a_dataset(tmp_path):
    a, b = scene.ground_truth(spacing=0.05, seed=3), scene.ground_truth(spacing=0.05, seed=3)
    for k in a.params:
        np.testing.assert_array_equal(np.array(a.params[k]), np.array(b.params[k]))
    assert a.sh_degree == 3 and float(np.abs(np.array(a.params["sh_rest"])).max()) > 0.1  # view-dependent colour
    c = scene.ground_truth(spacing=0.05, seed=4)
    assert not np.array_equal(np.array(a.params["scales"]), np.array(c.params["scales"]))

    spec = scene.SceneSpec(image_size=24, num_views=9, num_points=200, spacing=0.05, seed=3)
    scene.write_dataset(tmp_path / "one", spec)
    scene.write_dataset(tmp_path / "two", spec)
    names = sorted(os.listdir(tmp_path / "one" / "images"))
    assert names == [f"frame_{i:05d}.png" for i in range(9)]
    for name in ["transforms.json", "points.ply", "scene.json"] + [f"images/{n}" for n in names]:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name
    data = load_dataset(tmp_path / "one")
    assert data.kind == "nerfstudio" and data.test == [0, 8] and len(data.train) == 7
    assert data.points.shape == (200, 3) and data.point_colors.dtype == np.uint8
    assert data.frames[0].camera.width == 24 and data.frames[0].camera.model == "pinhole"
    # The images are the ground truth rendered from the dataset's own cameras.
    image, _ = data.load_image(5)
    np.testing.assert_allclose(image, scene.render_view(scene.ground_truth(0.05, 3), data.frames[5].camera), atol=1 / 255 + 1e-6)
    # The initial points are the ground truth's centres with noise, near but not on them.
    means = np.array(a.means)
    nearest = np.min(np.linalg.norm(data.points[:50, None, :] - means[None], axis=-1), axis=1)
    assert 0.0 < np.median(nearest) < 4 * spec.point_noise * scene.scene_radius()
    # Asking again with the same spec reuses the folder; another spec replaces it.
    stamp = os.path.getmtime(tmp_path / "one" / "transforms.json")
    scene.write_dataset(tmp_path / "one", spec)
    assert os.path.getmtime(tmp_path / "one" / "transforms.json") == stamp
    scene.write_dataset(tmp_path / "one", scene.SceneSpec(image_size=16, num_views=4, num_points=50, spacing=0.05))
    assert len(os.listdir(tmp_path / "one" / "images")) == 4 and not (tmp_path / "one.partial").exists()


# ------------------------------------------------------------------ a tiny run end to end
SECTIONS = ["# What accuracy costs on this machine", "## Training: accuracy against time", "## Rendering: time against accuracy",
            "## Best configuration for a time budget", "## Effects on demand: what skipping a stage saves", "## What each configuration runs"]


def test_tiny_run_writes_the_report_with_every_section_and_plot(tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["bench", "accuracy", "--tiny", "--out", str(out), "--seed", "1"]) == 0
    captured = capsys.readouterr()
    assert "bench accuracy: finished in" in captured.out and str(out / "README.md") in captured.out
    assert re.search(r"bench accuracy \[effects: .*\]: 100\.0%", captured.err), "the progress line"
    text = (out / "README.md").read_text()
    for section in SECTIONS:
        assert section in text
    for needle in ("**Machine:**", "cores", "MLX 0.32", "**Load:**", "tiny mode", "seed 1", "| baseline | mcmc, 600 Gaussians, SH 3, EWA",
                   "| images x0.5 |", "| 25%, SH 0, EWA |", "| ground truth scene |", "loss_dssim", "project_ut (instead of project_ewa)",
                   "| 100% ("):
        assert needle in text, needle
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert len(links) == 5
    for link in links:
        with Image.open(out / link) as im:
            assert im.format == "PNG" and im.size[0] >= 400
    results = json.loads((out / "results.json").read_text())
    assert results["mode"] == "tiny" and results["seed"] == 1
    assert [r["name"] for r in results["train"]] == [c.name for c in train_cases(MODES["tiny"])]
    for row in results["train"]:
        assert row["steps"] == MODES["tiny"].steps and len(row["curve"]) == MODES["tiny"].checkpoints
        assert row["seconds"] > 0 and 5 < row["psnr"] < 60 and 0 < row["ssim"] <= 1
        assert [p["seconds"] for p in row["curve"]] == sorted(p["seconds"] for p in row["curve"])
    timed = MODES["tiny"].render_repeats * results["scene"]["heldout_views"]
    assert len(results["render"]) == 13 and all(r["ms"]["n"] == timed for r in results["render"])
    assert results["render"][-1]["psnr"] > 40  # the ground truth against its own 8-bit images
    assert len(results["effects"]) == 7 and all(e["train_on_ms"]["n"] == e["train_saved_ms"]["n"] == 2 for e in results["effects"])
    assert [e["render_saved_ms"] is not None for e in results["effects"]] == [False, True, True, True, True, False, False]
    assert not [p for p in os.listdir(out) if p.endswith(".tmp")]


def test_a_cancelled_run_writes_nothing(tmp_path):
    out = tmp_path / "report"
    calls = []

    def should_stop():
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(Cancelled):
        run_accuracy(out, "tiny", should_stop=should_stop)
    assert not out.exists() or not os.listdir(out)
    assert issubclass(Cancelled, KeyboardInterrupt)  # the CLI's Ctrl+C path: exit code 130
