"""Benchmark this machine from Blender: the ``mlx3d.benchmark`` operator, its panel section and the job behind it
(``addon/benchmark.py``: ``mlx3d bench accuracy`` in a child process), with the tiny sizes so each run takes seconds."""

import os
import re
import time
from types import SimpleNamespace

import pytest
from modal_state import ESC, MOVE, OperatorState, TIMER
from panel_layout import RecordingLayout
from core_marks import above_kernels

pytestmark = above_kernels  # the add-on over mlx3d.report: the pure path runs the same code there

bpy = pytest.importorskip("bpy")

SECTIONS = ("## Training: accuracy against time", "## Rendering: time against accuracy", "## Best configuration for a time budget",
            "## Effects on demand: what skipping a stage saves")


def check_report(folder):
    path = os.path.join(folder, "README.md")
    with open(path) as f:
        text = f.read()
    assert text.startswith("# What accuracy costs on this machine") and "tiny mode" in text
    for section in SECTIONS:
        assert section in text
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
        assert os.path.getsize(os.path.join(folder, link)) > 1000, link
    return path


def test_operator_runs_the_benchmark_headless_and_opens_the_report(extension, clean_scene, tmp_path):
    out = tmp_path / "bench"
    texts = len(bpy.data.texts)
    # Invoked without a window (background), the operator runs to the end at once.
    assert bpy.ops.mlx3d.benchmark("INVOKE_DEFAULT", directory=str(out), tiny=True) == {"FINISHED"}
    path = check_report(str(out))
    assert len(bpy.data.texts) == texts + 1
    (text,) = [t for t in bpy.data.texts if t.filepath and os.path.samefile(bpy.path.abspath(t.filepath), path)]
    assert "## Rendering: time against accuracy" in text.as_string()


def test_default_folder_is_next_to_the_blend_file_or_in_the_temp_folder(extension, clean_scene, tmp_path):
    benchmark = extension.addon.benchmark
    assert benchmark.default_folder("") == os.path.join(__import__("tempfile").gettempdir(), "mlx3d_accuracy")
    assert benchmark.default_folder(str(tmp_path / "scene.blend")) == str(tmp_path / "mlx3d_accuracy")
    op = extension.addon.operators.MLX3D_OT_benchmark
    job = op._new_job(SimpleNamespace(directory="", full=True, tiny=False))
    assert job.mode == "full" and job.out_dir.endswith("mlx3d_accuracy") and "--quick" not in job.command
    job = op._new_job(SimpleNamespace(directory=str(tmp_path), full=False, tiny=False))
    assert job.mode == "quick" and job.command[-1] == "--quick" and job.out_dir == str(tmp_path)
    with pytest.raises(benchmark.BenchmarkError, match="mode"):
        benchmark.BenchmarkJob(str(tmp_path), "huge")


def test_modal_operator_follows_the_child_and_esc_cancels_it(extension, clean_scene, tmp_path):
    benchmark = extension.addon.benchmark
    op = extension.addon.operators.MLX3D_OT_benchmark

    # Esc once the child reports progress: it stops as on Ctrl+C and writes nothing.
    out = tmp_path / "cancelled"
    job = benchmark.BenchmarkJob(str(out), "tiny")
    state = OperatorState(op, job)
    job.start()
    deadline = time.monotonic() + 120
    while job.progress == 0 and job.running and time.monotonic() < deadline:
        time.sleep(0.05)
    assert job.running and job.progress > 0
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert op.modal(state, bpy.context, MOVE) == {"PASS_THROUGH"}  # Blender stays usable meanwhile
    assert op.modal(state, bpy.context, ESC) == {"CANCELLED"}
    assert job.wait(30) and job.returncode == 130
    assert state._session is None and state.reports == [({"INFO"}, "the benchmark was cancelled; nothing was written")]
    assert not out.exists() or not os.listdir(out)
    with pytest.raises(benchmark.BenchmarkError, match="cancelled"):
        job.finish()

    # Run to the end: the timer tick after the child exits reports and opens the report.
    out = tmp_path / "done"
    job = benchmark.BenchmarkJob(str(out), "tiny")
    state = OperatorState(op, job)
    job.start()
    assert op.modal(state, bpy.context, TIMER) == {"RUNNING_MODAL"}
    assert job.wait(300) and job.returncode == 0, job._lines
    assert op.modal(state, bpy.context, TIMER) == {"FINISHED"}
    path = check_report(str(out))
    assert state._session is None and state.reports[0][0] == {"INFO"} and path in state.reports[0][1]
    assert any(t.filepath and os.path.samefile(bpy.path.abspath(t.filepath), path) for t in bpy.data.texts)


def test_a_failing_child_is_reported(extension, tmp_path):
    benchmark = extension.addon.benchmark
    job = benchmark.BenchmarkJob(str(tmp_path / "x"), "tiny")
    job.command = job.command[:1] + ["-c", "import sys; print('mlx3d bench: error: no space left', file=sys.stderr); sys.exit(1)"]
    job.start()
    with pytest.raises(benchmark.BenchmarkError, match="exit code 1.*no space left"):
        job.finish()


def test_panel_benchmark_section_passes_its_settings(extension, clean_scene):
    settings = clean_scene.mlx3d_splats
    settings.bench_dir, settings.bench_full = "/tmp/somewhere", True
    log = []
    extension.addon.panel.VIEW3D_PT_mlx3d_benchmark.draw(SimpleNamespace(layout=RecordingLayout(log)), SimpleNamespace(scene=clean_scene))
    assert [entry[1] for entry in log if entry[0] == "prop"] == ["bench_dir", "bench_full"]
    (_, idname, op), = [entry for entry in log if entry[0] == "operator"]
    assert idname == "mlx3d.benchmark" and (op.directory, op.full) == ("/tmp/somewhere", True)
    assert extension.addon.panel.VIEW3D_PT_mlx3d_benchmark.bl_parent_id == "VIEW3D_PT_mlx3d_splats"
