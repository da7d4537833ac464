"""Batches of views per training step, and data-parallel training over ranks (mx.distributed, ring backend on localhost).

The distributed tests start real processes: ``mlx.launch --backend ring`` (as users do), or the
two ranks by hand with the ring backend's environment (MLX_RANK, MLX_HOSTFILE) where a test needs
a rank to die without the launcher stopping the others first.
"""

import json
import math
import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.training import GaussianTrainer, TrainerConfig
from mlx3d.training.adam import Adam
from mlx3d.training.bilateral_grid import BilateralGrid, GridAdam
from mlx3d.training.trainer import TrainingView, batch_adam

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "data"))
import make_train_frozen as frozen  # noqa: E402

WORKER = HERE / "distributed_worker.py"
LAUNCH = Path(sys.executable).parent / "mlx.launch"
needs_launcher = pytest.mark.skipif(not LAUNCH.exists(), reason=f"mlx.launch is not beside {sys.executable}")
# Process orchestration (the CLI on ranks, Ctrl+C) is the same code whichever kernels render; the entry without
# the compiled module (make test-pure, where every step is several times slower) leaves it to the others.
orchestration = pytest.mark.skipif(bool(os.environ.get("MLX3D_NO_CORE")),
                                   reason="orchestration only: run by the entries with the compiled module")


def _free_ports(count: int) -> list:
    """``count`` consecutive free TCP ports on localhost (the ring backend listens on port + rank)."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + count > 65535:
            continue
        try:
            socks = []
            for p in range(base, base + count):
                t = socket.socket()
                socks.append(t)
                t.bind(("127.0.0.1", p))
            return list(range(base, base + count))
        except OSError:
            continue
        finally:
            for t in socks:
                t.close()
    raise RuntimeError("no free ports")


def _launch(args, cwd, timeout=300):
    """``mlx.launch --backend ring -n 2`` on localhost running ``python ARGS``; (returncode, output)."""
    port = _free_ports(2)[0]
    cmd = [str(LAUNCH), "--backend", "ring", "-n", "2", "--hosts", "127.0.0.1", "--starting-port", str(port), "--", sys.executable, *args]
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    return done.returncode, done.stdout + done.stderr


# ------------------------------------------------------------------ one process
def test_batch_size_one_is_bitwise_the_frozen_runs(tmp_path):
    """Batch size 1 on one process reproduces, bit for bit, the parameters the trainer reached before
    batches existed (tests/data/train_frozen.npz: densification and an opacity reset, MCMC relocation,
    growth and noise, a bilateral grid)."""
    from mlx3d import native

    data = np.load(HERE / "data" / "train_frozen.npz")
    if not native.available():
        pytest.skip("the frozen runs are the compiled CPU kernels' results (mlx3d._core is off)")
    if int(data["lanes"]) != native.core().rasterizer_simd_lanes():
        pytest.skip("the frozen runs were written with another SIMD width (gradients are lane sums)")
    for name in frozen.RUNS:
        folder = tmp_path / name
        folder.mkdir()
        params, trainer = frozen.run(name, folder)
        for k, v in params.items():
            assert v.tobytes() == data[f"{name}/{k}"].tobytes(), (name, k)


def test_batch_constants_follow_gsplat():
    assert batch_adam(1) == {"lr_factor": 1.0, "betas": (0.9, 0.999), "eps": 1e-15}
    b4 = batch_adam(4)
    assert b4["lr_factor"] == 2.0 and b4["eps"] == pytest.approx(0.5e-15)
    assert b4["betas"] == pytest.approx((0.6, 0.996))
    assert batch_adam(10)["betas"][0] == 0.0 and batch_adam(12)["betas"][0] == 0.0  # held at 0, not negative
    one = GaussianTrainer(*_problem()[:1], TrainerConfig(steps=100), scene_extent=2.0)
    four = GaussianTrainer(*_problem()[:1], TrainerConfig(steps=100, batch_size=4), scene_extent=2.0)
    for k, v in one.learning_rates().items():
        assert four.learning_rates()[k] == pytest.approx(2 * v)
    assert (four.optimizer.b1, four.optimizer.b2) == pytest.approx((0.6, 0.996))
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="batch_size"):
            TrainerConfig(batch_size=bad)


def test_scale_steps_scales_every_schedule():
    config = TrainerConfig(steps=30_000, checkpoint_every=1000, bilateral_grid_warmup=900)
    quarter = config.scale_steps(0.25)
    assert (quarter.steps, quarter.densify_from, quarter.densify_until, quarter.densify_every) == (7500, 125, 3750, 25)
    assert (quarter.opacity_reset_every, quarter.sh_increase_every, quarter.checkpoint_every, quarter.bilateral_grid_warmup) == (750, 250, 250, 225)
    assert quarter.lr_means_max_steps is None and quarter.batch_size == 1  # None (= steps) stays None
    assert config.scale_steps(1e-4).densify_every == 1  # intervals stay >= 1
    assert TrainerConfig(checkpoint_every=0).scale_steps(0.5).checkpoint_every == 0  # off stays off
    with pytest.raises(ValueError, match="scaler"):
        config.scale_steps(0)


def _problem(seed=0):
    from mlx3d.cameras import Camera
    from mlx3d.splatting import GaussianModel

    rng = np.random.default_rng(seed)
    truth = GaussianModel.from_points(rng.uniform(-0.6, 0.6, (40, 3)).astype(np.float32), rng.uniform(0, 1, (40, 3)), sh_degree=1, initial_opacity=0.8)
    cams = [Camera.look_at(eye=(3 * math.cos(a), 3 * math.sin(a), 0.5), at=(0, 0, 0), up=(0, 0, 1), width=32, height=24, hfov=45.0)
            for a in (0.0, 2.0, 4.0)]
    targets = [np.array(truth.render(c, background=(0, 0, 0))["image"]) for c in cams]
    start = GaussianModel.from_points(np.asarray(truth.means) + rng.normal(0, 0.05, (40, 3)).astype(np.float32), sh_degree=1, initial_opacity=0.3)
    return start, cams, targets


def test_a_batch_step_is_adam_on_the_mean_of_the_views_gradients():
    """Oracle: each view's gradient from its own one-view loss (mx.grad of the trainer's loss), averaged,
    through Adam with gsplat's batch constants, against one step of a batch of those views."""
    from mlx3d.splatting import GaussianModel
    from mlx3d.training.plan import step_plan

    start, cams, targets = _problem()
    config = TrainerConfig(steps=10, batch_size=3, densify_from=100)
    trainer = GaussianTrainer(GaussianModel(dict(start.params)), config, scene_extent=2.0)
    params = dict(trainer.model.params)
    grads = []
    for cam, target in zip(cams, targets):
        plan = step_plan(config, cam, 0, 0)
        fn = lambda p: trainer._loss(p, None, None, cam, mx.array(target), None, (0.0, 0.0, 0.0), plan, 0)[0]  # noqa: E731
        grads.append(mx.grad(fn)(params))
    mean = {k: sum(g[k] for g in grads) / 3 for k in params}
    b = batch_adam(3)
    oracle = Adam(trainer.learning_rates(), betas=b["betas"], eps=b["eps"], backend="mlx").update(params, mean)
    info = trainer.step_batch([TrainingView(c, t, background=(0.0, 0.0, 0.0)) for c, t in zip(cams, targets)])
    assert info["batch_size"] == 3
    for k in params:
        np.testing.assert_allclose(np.array(trainer.model.params[k]), np.array(oracle[k]), rtol=1e-5, atol=1e-7, err_msg=k)


def test_every_view_of_a_batch_adds_to_the_densification_statistics():
    from mlx3d.splatting import GaussianModel

    start, cams, targets = _problem(1)
    config = TrainerConfig(steps=10, densify_from=0, densify_every=100, densify_until=200)
    one = GaussianTrainer(GaussianModel(dict(start.params)), config, scene_extent=2.0)
    batch = GaussianTrainer(GaussianModel(dict(start.params)), TrainerConfig(**{**config.__dict__, "batch_size": 3}), scene_extent=2.0)
    counts = []
    for cam, target in zip(cams, targets):  # each view alone, from the same parameters
        fresh = GaussianTrainer(GaussianModel(dict(start.params)), config, scene_extent=2.0)
        fresh.step(cam, target, background=(0, 0, 0))
        counts.append(fresh.grad_count)
    batch.step_batch([TrainingView(c, t, background=(0, 0, 0)) for c, t in zip(cams, targets)])
    np.testing.assert_array_equal(batch.grad_count, sum(counts))
    assert one.grad_count.sum() == 0 and batch.grad_count.max() <= 3


def test_grid_adam_steps_several_grids_as_adam_on_the_whole_stack():
    """Oracle: Adam over the whole (num_images, ...) stack with zero gradients for the other grids."""
    bg = BilateralGrid(5, (4, 4, 2))
    rng = np.random.default_rng(0)
    stack = mx.array(np.array(bg.params))
    opt, ref = GridAdam(1e-2), Adam({"grid": 1e-2}, backend="mlx")
    for indices in ([1, 3], [0], [4, 1, 2]):
        g = rng.normal(0, 1, (len(indices),) + tuple(bg.params.shape[1:])).astype(np.float32)
        opt.update(bg, indices if len(indices) > 1 else indices[0], mx.array(g if len(indices) > 1 else g[0]))
        full = np.zeros(bg.params.shape, np.float32)
        full[indices] = g
        stack = ref.update({"grid": stack}, {"grid": mx.array(full)})["grid"]
    opt.sync(bg)
    np.testing.assert_allclose(np.array(bg.params), np.array(stack), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="distinct"):
        opt.update(bg, [2, 2], mx.zeros((2,) + tuple(bg.params.shape[1:])))


# ------------------------------------------------------------------ ranks
@needs_launcher
def test_two_ranks_at_batch_two_train_exactly_as_one_process_at_batch_two(tmp_path):
    """2 ranks x batch 2 against 1 process x batch 2, through densification and an opacity reset,
    MCMC relocation and growth, and a bilateral grid: the ranks' parameters are bitwise equal to each
    other and to the one process's (with two views per batch, the sum over ranks adds the same two
    gradients the one process adds; with more views per rank the order of the sums differs)."""
    # Without the compiled module every step is several times slower: there the two runs the equivalence is
    # about (densification and an opacity reset; MCMC relocation and growth), all four elsewhere.
    runs = ["vanilla", "mcmc"] if os.environ.get("MLX3D_NO_CORE") else list(frozen.RUNS)
    code, out = _launch([str(WORKER), "train", str(tmp_path), *runs], tmp_path)
    assert (tmp_path / "rank0.npz").exists() and (tmp_path / "rank1.npz").exists(), out
    a, b = np.load(tmp_path / "rank0.npz"), np.load(tmp_path / "rank1.npz")
    for key in a.files:
        assert a[key].tobytes() == b[key].tobytes(), key
    for name in runs:
        folder = tmp_path / f"one_{name}"
        folder.mkdir()
        params, trainer = frozen.run(name, folder, batch_size=2)
        for k, v in params.items():
            assert v.tobytes() == a[f"{name}/{k}"].tobytes(), (name, k)
        assert int(a[f"{name}/bytes"]) > 0
    assert a["vanilla/means"].shape[0] != 60  # densified
    assert a["mcmc/means"].shape[0] > 60  # grown (relocation ran on the same schedule)


def _start_ranks(args, cwd, extra_env=None):
    """The two ranks started by hand with the ring backend's environment (no launcher to stop the survivor)."""
    ports = _free_ports(2)
    hostfile = Path(cwd) / "hosts.json"
    hostfile.write_text(json.dumps([[f"127.0.0.1:{ports[0]}"], [f"127.0.0.1:{ports[1]}"]]))
    procs = []
    for rank in range(2):
        env = dict(os.environ, MLX_RANK=str(rank), MLX_HOSTFILE=str(hostfile), **(extra_env or {}))
        procs.append(subprocess.Popen([sys.executable, *args], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    outputs = [p.communicate(timeout=300)[0] for p in procs]
    return [p.returncode for p in procs], outputs


def test_a_rank_that_dies_stops_the_others_and_the_last_checkpoint_stays_intact(tmp_path):
    codes, outputs = _start_ranks([str(WORKER), "die", str(tmp_path)], tmp_path)
    assert codes[1] == 3, outputs
    assert codes[0] != 0, outputs[0]
    err = (tmp_path / "rank0.err").read_text()
    assert err.startswith("DistributedError") and "rank 0 of 2: lost contact with another rank" in err, err
    trainer = GaussianTrainer.load_checkpoint(tmp_path / "checkpoint.npz")  # written at step 5 by rank 0 alone
    assert trainer.step_count == 5
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp") or ".tmp" in f]


@needs_launcher
def test_ranks_with_different_settings_refuse_to_start(tmp_path):
    code, out = _launch([str(WORKER), "mismatch", str(tmp_path)], tmp_path)
    for rank in (0, 1):
        err = (tmp_path / f"rank{rank}.err").read_text()
        assert "ranks [1] hold a different configuration and dataset from rank 0" in err, (rank, err, out)


@needs_launcher
@orchestration
def test_mlx3d_train_on_two_ranks_writes_what_one_process_writes(tmp_path):
    """``mlx.launch ... mlx3d train --batch-size 2``: rank 0 alone reports and writes the output and
    checkpoints; the file is byte for byte the one a single process writes with --batch-size 2."""
    data = tmp_path / "data"
    data.mkdir()
    frozen.scene(data)
    common = ["train", "data", "--batch-size", "2", "--steps", "24", "--random-points", "300", "--checkpoint-every", "10", "--sh-degree", "1"]
    code, out = _launch(["-m", "mlx3d", *common, "--out", "two.ply"], tmp_path)
    assert (tmp_path / "two.ply").exists(), out
    assert out.count("training on 2 ranks, 2 views per step") == 1 and out.count("data: 5 training and 1 test views") == 1, out  # rank 0 alone reports
    one = subprocess.run([sys.executable, "-m", "mlx3d", *common, "--out", "one.ply"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert one.returncode == 0, one.stderr
    assert (tmp_path / "one.ply").read_bytes() == (tmp_path / "two.ply").read_bytes()
    assert GaussianTrainer.load_checkpoint(tmp_path / "checkpoint.npz").step_count == 20
    # resumed on 2 ranks from the step-20 checkpoint: the same file as the run that went through
    code, out = _launch(["-m", "mlx3d", *common, "--out", "resumed.ply", "--resume", "checkpoint.npz"], tmp_path)
    assert "resumed at step 20" in out, out
    assert (tmp_path / "resumed.ply").read_bytes() == (tmp_path / "two.ply").read_bytes()
    bad = subprocess.run([sys.executable, "-m", "mlx3d", "train", "data", "--out", "x.ply", "--distributed", "--backend", "ring"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and "cannot start MLX's distributed backend 'ring'" in bad.stderr, bad.stderr
    assert not (tmp_path / "x.ply").exists()


@orchestration
def test_ctrl_c_stops_every_rank_after_the_same_step_and_rank_0_saves(tmp_path):
    """SIGINT to both ranks (what Ctrl+C in a terminal sends to its foreground processes) at different moments:
    both stop after the same step, exit with 130, and rank 0 writes the model and a checkpoint of that step."""
    import re
    import signal
    import time

    frozen.scene(tmp_path)
    ports = _free_ports(2)
    hostfile = tmp_path / "hosts.json"
    hostfile.write_text(json.dumps([[f"127.0.0.1:{p}"] for p in ports]))
    cmd = [sys.executable, "-m", "mlx3d", "train", ".", "--out", "cut.ply", "--batch-size", "2", "--steps", "1000", "--random-points", "300"]
    logs = [open(tmp_path / f"log{r}.txt", "w+") for r in range(2)]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, env=dict(os.environ, MLX_RANK=str(r), MLX_HOSTFILE=str(hostfile)), stdout=logs[r],
                              stderr=subprocess.STDOUT) for r in range(2)]
    try:
        deadline = time.time() + 120
        while not re.search(r"step +\d+ \(", (tmp_path / "log0.txt").read_text()) and time.time() < deadline:  # training
            time.sleep(0.2)
        procs[1].send_signal(signal.SIGINT)
        time.sleep(0.3)
        procs[0].send_signal(signal.SIGINT)
        codes = [p.wait(timeout=120) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    text = (tmp_path / "log0.txt").read_text()
    assert codes == [130, 130], (codes, text[-2000:])
    step = int(text.split("cancelled at step ")[1].split(":")[0])
    assert 0 < step < 1000
    assert GaussianTrainer.load_checkpoint(tmp_path / "checkpoint.npz").step_count == step
    assert (tmp_path / "cut.ply").exists()


def test_statistics_reduced_over_ranks_stay_float64_and_take_the_next_views():
    """The densification statistics summed over the ranks come back as float64 numpy arrays at full precision
    (MLX makes float64 numpy input float32 unless told), so the next view's statistics are added into them (a
    float32 array was silently copied by the compiled kernel's binding and the view lost)."""
    from mlx3d.cameras import Camera
    from mlx3d.render import resolve_backend
    from mlx3d.training.distributed import Ranks
    from mlx3d.training.statistics import ScreenStatistics

    ranks = Ranks(mx.distributed.init())
    fine = np.array([1.0 + 2.0 ** -40, 3.0])
    assert ranks.host_sum(fine, "a sum").dtype == np.float64 and np.array_equal(ranks.host_sum(fine, "a sum"), fine * ranks.size)
    stats = ScreenStatistics(3)
    camera = Camera.look_at(eye=(0, -3, 0), at=(0, 0, 0), up=(0, 0, 1), fov=60, width=64, height=48)
    view = (mx.array([True, False, True]), mx.array([[0.5, 0.0], [1.0, 1.0], [0.0, 0.25]]), mx.array([3, 9, 5]))
    stats.add(camera, *view, resolve_backend("auto"))
    stats.reduce(ranks)
    stats.add(camera, *view, resolve_backend("auto"))
    accum, count, max_radii = stats.arrays()
    assert all(a.dtype == np.float64 for a in (accum, count, max_radii))
    np.testing.assert_allclose(accum, [2 * 0.5 * 32, 0.0, 2 * 0.25 * 24])
    assert count.tolist() == [2.0, 0.0, 2.0] and max_radii.tolist() == [3.0, 9.0, 5.0]
