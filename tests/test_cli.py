"""The ``mlx3d`` command line: each subcommand's output files and exit codes."""

import json
import os
import shutil
import subprocess
import sys

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.cli import main
from mlx3d.splatting import GaussianModel, eval_sh
from mlx3d.transforms import euler_to_matrix
from core_marks import above_kernels

pytestmark = above_kernels

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")
OPENSPLAT = os.path.join(DATA, "opensplat_trained.ply")


def make_file(path, n=400, degree=3, seed=0, floaters=0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, (n, 3))
    pts[:, 2] = rng.normal(0, 0.01, n)  # a thin slab
    if floaters:
        d = rng.normal(size=(floaters, 3))
        pts[-floaters:] = 20 * d / np.linalg.norm(d, axis=1, keepdims=True)
    m = GaussianModel.from_points(pts.astype(np.float32), rng.uniform(0, 1, (n, 3)), sh_degree=degree)
    m.params["sh_rest"] = mx.array(rng.normal(0, 0.1, tuple(m.params["sh_rest"].shape)).astype(np.float32))
    m.params["opacities"] = mx.array(rng.normal(0, 2, n).astype(np.float32))
    m.save_ply(path)
    return m


def test_info_json(tmp_path, capsys):
    m = make_file(tmp_path / "a.ply", degree=2)
    assert main(["info", "--json", str(tmp_path / "a.ply")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["splats"] == 400 and info["sh_degree"] == 2
    np.testing.assert_allclose(info["bounds_min"], np.array(m.means).min(0), rtol=1e-6)
    np.testing.assert_allclose(info["opacity"]["max"], float(np.array(m.opacities).max()), rtol=1e-5)
    assert info["nonfinite_rows"] == 0


@pytest.mark.skipif(not os.path.exists(OPENSPLAT), reason="shared/data/opensplat_trained.ply not present")
def test_info_table_on_real_file(capsys):
    assert main(["info", OPENSPLAT]) == 0
    out = capsys.readouterr().out
    assert "31,995" in out and "SH degree" in out


def test_compact(tmp_path):
    make_file(tmp_path / "a.ply")
    assert main(["compact", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--max-gaussians", "100", "--sh-degree", "1", "--min-opacity", "0.1"]) == 0
    out = GaussianModel.load_ply(tmp_path / "b.ply", sh_degree=None)
    assert len(out) == 100 and out.sh_degree == 1
    assert (np.array(out.opacities) >= 0.1).all()


def test_outputs_go_into_new_folders(tmp_path):
    # the folder is made before the work, so a long run (training) never ends unable to write its result
    make_file(tmp_path / "a.ply")
    assert main(["compact", str(tmp_path / "a.ply"), str(tmp_path / "new" / "deeper" / "b.ply"), "--max-gaussians", "10"]) == 0
    assert len(GaussianModel.load_ply(tmp_path / "new" / "deeper" / "b.ply", sh_degree=None)) == 10


def test_clean_statistical_and_radius(tmp_path, capsys):
    make_file(tmp_path / "a.ply", n=2000, floaters=10)
    assert main(["clean", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--stat-k", "10", "--stat-std", "3"]) == 0
    assert "removed 10 of 2,000" in capsys.readouterr().out
    kept = np.array(GaussianModel.load_ply(tmp_path / "b.ply").means)
    assert len(kept) == 1990 and np.abs(kept).max() < 2
    assert main(["clean", str(tmp_path / "a.ply"), str(tmp_path / "c.ply"), "--radius", "0.5", "--min-neighbours", "3"]) == 0
    assert len(GaussianModel.load_ply(tmp_path / "c.ply")) == 1990


def test_transform_rotates_positions_and_colour(tmp_path):
    m = make_file(tmp_path / "a.ply")
    args = ["transform", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "--scale", "2", "--rotate-deg", "10", "20", "30", "--translate", "1", "2", "3"]
    assert main(args) == 0
    out = GaussianModel.load_ply(tmp_path / "b.ply")
    rot = euler_to_matrix((10, 20, 30))
    np.testing.assert_allclose(np.array(out.means), 2 * np.array(m.means) @ rot.T + [1, 2, 3], rtol=1e-5, atol=1e-5)
    d = np.random.default_rng(0).normal(size=(8, 3))
    np.testing.assert_allclose(
        eval_sh(3, np.array(out.sh)[:, None].astype(np.float64), (d @ rot.T)[None]),
        eval_sh(3, np.array(m.sh)[:, None].astype(np.float64), d[None]),
        atol=1e-5,
    )


def test_merge_mixed_degrees(tmp_path):
    make_file(tmp_path / "a.ply", n=50, degree=0)
    make_file(tmp_path / "b.ply", n=60, degree=3, seed=1)
    assert main(["merge", str(tmp_path / "m.ply"), str(tmp_path / "a.ply"), str(tmp_path / "b.ply")]) == 0
    out = GaussianModel.load_ply(tmp_path / "m.ply", sh_degree=None)
    assert len(out) == 110 and out.sh_degree == 3


def test_bad_file_gives_message_and_exit_1_and_keeps_output(tmp_path, capsys):
    (tmp_path / "bad.ply").write_bytes(b"not a ply at all")
    (tmp_path / "out.ply").write_bytes(b"keep me")
    assert main(["compact", str(tmp_path / "bad.ply"), str(tmp_path / "out.ply")]) == 1
    err = capsys.readouterr().err
    assert "bad.ply" in err and "error" in err
    assert (tmp_path / "out.ply").read_bytes() == b"keep me"
    assert main(["info", str(tmp_path / "missing.ply")]) == 1


def test_usage_errors_exit_2(tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["clean", "a.ply", "b.ply", "--radius", "1"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main(["transform", "a.ply", "b.ply", "--rotate-deg", "1", "2"])
    assert exc.value.code == 2


@pytest.mark.parametrize("command", ["info", "compact", "clean", "transform", "merge", "demo"])
def test_console_script_help(command):
    exe = shutil.which("mlx3d", path=os.path.dirname(sys.executable))
    cmd = [exe] if exe else [sys.executable, "-m", "mlx3d.cli"]
    result = subprocess.run(cmd + [command, "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "usage: mlx3d " + command in result.stdout


def test_python_dash_m_runs_the_cli(tmp_path):
    """``python -m mlx3d`` is the same command line, exit codes included."""
    ok = subprocess.run([sys.executable, "-m", "mlx3d", "info", "--help"], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0 and "usage: mlx3d info" in ok.stdout
    missing = subprocess.run([sys.executable, "-m", "mlx3d", "info", str(tmp_path / "missing.ply")], capture_output=True, text=True, timeout=60)
    assert missing.returncode == 1 and "missing.ply" in missing.stderr + missing.stdout


def test_mesh_writes_a_coloured_mesh_and_refuses_transparent_models(tmp_path, capsys, monkeypatch):
    from mlx3d.io.mesh_ply import read_mesh_ply

    rng = np.random.default_rng(0)
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    m = GaussianModel.from_points(d.astype(np.float32), np.tile([0.9, 0.2, 0.1], (6000, 1)), sh_degree=0, initial_opacity=0.9)
    # discs tangent to the sphere: rotate local z onto the radius (half-angle quaternion from +z)
    q = np.concatenate([1.0 + d[:, 2:3], -d[:, 1:2], d[:, 0:1], np.zeros((6000, 1))], axis=1)
    m.params["quats"] = mx.array(q.astype(np.float32))
    m.params["scales"] = mx.array(np.log(np.tile([0.04, 0.04, 1e-3], (6000, 1))).astype(np.float32))
    m.save_ply(tmp_path / "ball.ply")
    # the training cameras fusion renders: a NeRF-synthetic folder of 12 views around the ball
    from PIL import Image

    (tmp_path / "data" / "train").mkdir(parents=True)
    frames = []
    for i, (a, z) in enumerate((a, z) for a in np.linspace(0, 2 * np.pi, 6, endpoint=False) for z in (-1.5, 1.5)):
        camera = Camera.look_at((3.5 * np.cos(a), 3.5 * np.sin(a), z), up=(0, 0, 1), fov=50, width=96, height=96)
        Image.new("RGB", (96, 96)).save(tmp_path / "data" / "train" / f"r_{i}.png")
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": camera.to_opengl_c2w().tolist()})
    (tmp_path / "data" / "transforms_train.json").write_text(json.dumps({"camera_angle_x": np.radians(50), "frames": frames}))
    opaque = m.params["opacities"]
    for method, error in (("fusion", "the splats cover no pixel"), ("poisson", "no Gaussian has opacity")):
        out = tmp_path / f"ball_{method}.ply"
        assert main(["mesh", str(tmp_path / "ball.ply"), "--out", str(out), "--method", method, "--resolution", "48",
                     "--data", str(tmp_path / "data")]) == 0
        assert "faces" in capsys.readouterr().out
        mesh = read_mesh_ply(out)
        assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 1.0).max() < 2 * 2.4 / 48
        np.testing.assert_allclose(mesh.colors.mean(0), [0.9, 0.2, 0.1], atol=2 / 255)
        if method == "poisson":  # --faces: at most that many, on the same ball, in the same colour
            assert main(["mesh", str(tmp_path / "ball.ply"), "--out", str(out), "--method", method, "--resolution", "48",
                         "--data", str(tmp_path / "data"), "--faces", "600"]) == 0
            assert "faces to at most 600" in capsys.readouterr().err
            small = read_mesh_ply(out)
            assert 480 <= len(small.faces) <= 600 < len(mesh.faces)
            assert np.abs(np.linalg.norm(small.vertices, axis=1) - 1.0).max() < 2 * 2.4 / 48
            np.testing.assert_allclose(small.colors.mean(0), [0.9, 0.2, 0.1], atol=2 / 255)
        if method == "fusion":  # a box given by hand: the ball's cap inside it, cut at its wall
            assert main(["mesh", str(tmp_path / "ball.ply"), "--out", str(out), "--resolution", "48",
                         "--data", str(tmp_path / "data"), "--bounds", "-1.2", "-1.2", "0.3", "1.2", "1.2", "1.2"]) == 0
            z = read_mesh_ply(out).vertices[:, 2]
            assert z.min() >= 0.3 - 1e-6 and z.min() < 0.3 + 2.4 / 48 and z.max() > 0.95
            # the cameras read at half size, as trained with --factor 2: the same ball, rendered at 48 x 48
            widths = []
            fused_mesh = GaussianModel.fused_mesh
            monkeypatch.setattr(GaussianModel, "fused_mesh", lambda self, cameras, **kw: (
                widths.extend(c.width for c in cameras), fused_mesh(self, cameras, **kw))[1])
            assert main(["mesh", str(tmp_path / "ball.ply"), "--out", str(out), "--resolution", "48",
                         "--data", str(tmp_path / "data"), "--factor", "2"]) == 0
            monkeypatch.undo()
            assert set(widths) == {48}
            assert np.abs(np.linalg.norm(read_mesh_ply(out).vertices, axis=1) - 1.0).max() < 2 * 2.4 / 48
        m.params["opacities"] = mx.full((6000,), -9.0)
        m.save_ply(tmp_path / "clear.ply")
        assert main(["mesh", str(tmp_path / "clear.ply"), "--out", str(tmp_path / "clear_mesh.ply"), "--method", method,
                     "--data", str(tmp_path / "data")]) == 1
        assert error in capsys.readouterr().err and not (tmp_path / "clear_mesh.ply").exists()
        m.params["opacities"] = opaque


WRITABLE = [".ply", ".compressed.ply", ".spz", ".sog", ".splat", ".ksplat", ".glb"]


@pytest.mark.parametrize("ext", WRITABLE)
def test_convert_writes_the_extensions_format_and_every_command_reads_it(tmp_path, capsys, ext):
    from mlx3d.io import detect_format, read_splats

    m = make_file(tmp_path / "a.ply", degree=2)
    out = tmp_path / f"b{ext}"
    assert main(["convert", str(tmp_path / "a.ply"), str(out), "--sh-degree", "1"]) == 0
    fmt = detect_format(out)
    assert fmt.extensions[0] == ext
    back = read_splats(out)
    assert back.count == len(m) and back.sh_degree == (0 if ext == ".splat" else 1)
    capsys.readouterr()
    # info, compact and transform take it as input and write any format.
    assert main(["info", "--json", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["format"] == fmt.name
    assert main(["compact", str(out), str(tmp_path / "c.spz"), "--max-gaussians", "50"]) == 0
    assert read_splats(tmp_path / "c.spz").count == 50


def test_convert_refuses_unknown_outputs_before_reading(tmp_path, capsys):
    make_file(tmp_path / "a.ply", n=20)
    for bad in ("b.xyz", "b.png"):
        assert main(["convert", str(tmp_path / "a.ply"), str(tmp_path / bad)]) == 1
        err = capsys.readouterr().err
        assert bad in err and "unknown splat file extension" in err
        assert "reading" not in err  # refused before any work
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply"]


def test_what_a_format_cannot_store_is_said_in_one_line(tmp_path, capsys):
    from mlx3d.io import SplatArrays, read_splat_ply, write_splat_ply

    make_file(tmp_path / "a.ply", n=30)
    s = read_splat_ply(tmp_path / "a.ply")
    write_splat_ply(tmp_path / "b.ply", SplatArrays(s.means, s.scales, s.quats, s.opacities, s.sh_dc, s.sh_rest,
                                                    extra={"confidence": np.ones(30, np.float32)}))
    assert main(["convert", str(tmp_path / "b.ply"), str(tmp_path / "c.spz")]) == 0
    err = capsys.readouterr().err
    assert "mlx3d convert: warning:" in err and "confidence" in err and "c.spz" in err


def test_convert_passes_a_formats_own_options(tmp_path, capsys):
    from mlx3d.io import read_splats

    make_file(tmp_path / "a.ply", n=40)
    assert main(["convert", str(tmp_path / "a.ply"), str(tmp_path / "v3.spz"), "--spz-version", "3"]) == 0
    assert (tmp_path / "v3.spz").read_bytes()[:2] == b"\x1f\x8b"  # versions 2-3 are one gzip stream
    assert main(["convert", str(tmp_path / "a.ply"), str(tmp_path / "l1.ksplat"), "--ksplat-level", "1"]) == 0
    assert read_splats(tmp_path / "l1.ksplat").count == 40
    capsys.readouterr()
    assert main(["convert", str(tmp_path / "a.ply"), str(tmp_path / "b.sog"), "--spz-version", "3"]) == 1
    err = capsys.readouterr().err
    assert "b.sog" in err and "no writing option 'version'" in err and not (tmp_path / "b.sog").exists()
