"""File > Import / Export of every splat format through the installed extension.

Oracles: ``mlx3d.io.read_splats`` of the same file (what an import must hold,
bit for bit: an unedited object exports to PLY exactly as read), the format the
output's bytes are recognised as, and on Blender 5.3 Blender's own SPZ importer
(``wm.spz_import``), which reads SPZ as Y-up.
"""

from pathlib import Path

import numpy as np
import pytest

from mlx3d.io import detect_format, read_splat_ply, read_splats, write_splats

bpy = pytest.importorskip("bpy")

from test_workflows import export_file, import_file, select_only  # noqa: E402  (tests/blender is on sys.path)

REAL = Path(__file__).resolve().parents[1] / "data" / "formats" / "opensplat_500.ply"
WRITABLE = [".ply", ".compressed.ply", ".spz", ".sog", ".splat", ".ksplat", ".glb"]
FIELDS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def real():
    """The committed real scene without its normals (no format but PLY and glTF stores them)."""
    s = read_splat_ply(REAL)
    s.extra.clear()
    return s


@pytest.mark.parametrize("ext", WRITABLE)
def test_export_and_import_every_format(extension, clean_scene, tmp_path, ext):
    obj = import_file(REAL)
    select_only(obj)
    out = tmp_path / f"scan{ext}"
    export_file(out)  # the extension of the path picks the format, as a script passes it
    assert detect_format(out).extensions[0] == ext
    want = read_splats(out)

    clean_scene_objects = set(bpy.context.scene.objects)
    back = import_file(out)
    assert back not in clean_scene_objects and back.name.startswith("scan") and len(back.data.points) == want.count
    select_only(back)
    export_file(tmp_path / "again.ply")
    got = read_splat_ply(tmp_path / "again.ply")
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=f"{ext}: {field}")


def test_export_format_choice_sets_the_extension(extension, clean_scene, tmp_path):
    op = bpy.ops.export_scene.gaussian_splat_ply
    props = op.get_rna_type().properties
    names = {item.identifier for item in props["file_format"].enum_items}
    assert {"PLY", "SPZ", "COMPRESSED_PLY", "SOG", "SPLAT", "KSPLAT", "GLB"} <= names
    operators = extension.addon.operators
    assert operators.WRITE_EXTENSIONS["COMPRESSED_PLY"] == ".compressed.ply"
    assert "*.spz" in operators.READ_GLOB and "*.ksplat" in operators.READ_GLOB


def test_a_bad_file_is_refused_and_the_scene_is_unchanged(extension, clean_scene, tmp_path):
    good = tmp_path / "good.spz"
    write_splats(good, real())
    bad = tmp_path / "bad.spz"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    before = set(bpy.context.scene.objects)
    with pytest.raises(RuntimeError, match="bad.spz"):
        bpy.ops.import_scene.gaussian_splat_ply(filepath=str(bad))
    assert set(bpy.context.scene.objects) == before
    assert set(bpy.data.pointclouds) == {o.data for o in before if o.type == "POINTCLOUD"}


@pytest.mark.skipif(bpy.app.version < (5, 3, 0), reason="Blender before 5.3 has no SPZ importer")
def test_spz_placed_as_blenders_own_importer_with_y_up(extension, clean_scene, tmp_path):
    spz = tmp_path / "scan.spz"
    write_splats(spz, real())
    assert bpy.ops.wm.spz_import(filepath=str(spz)) == {"FINISHED"}
    theirs = bpy.context.selected_objects[0]
    ours = import_file(spz, axis="Y_UP")
    bpy.context.view_layer.update()

    def world(obj):
        n = len(obj.data.points)
        p = np.empty(n * 3, np.float32)
        obj.data.attributes["position"].data.foreach_get("vector", p)
        m = np.array(obj.matrix_world, np.float64)
        return p.reshape(n, 3) @ m[:3, :3].T + m[:3, 3]

    np.testing.assert_allclose(world(ours), world(theirs), atol=1e-6)
    for name in ("scale", "opacity"):
        if name in theirs.data.attributes and name in ours.data.attributes:
            a, b = (np.empty(len(o.data.points) * (3 if name == "scale" else 1), np.float32) for o in (ours, theirs))
            key = "vector" if name == "scale" else "value"
            ours.data.attributes[name].data.foreach_get(key, a)
            theirs.data.attributes[name].data.foreach_get(key, b)
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7, err_msg=name)
