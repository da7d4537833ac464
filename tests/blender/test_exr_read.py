"""``mlx3d.io.exr.read_exr`` against the OpenEXR files Blender writes.

Oracles: the pixels put into a Blender float image before Blender saves it
(every codec the reader supports, 32-bit and half), and a tiny Cycles render
of a plane at a known distance whose depth, coverage and background follow
from the camera's geometry.  Files crafted byte by byte here cover the data
window offset, short channel names in a multi-part file and the errors.

Facts recorded here (the add-on's pass reading relies on them):

- Blender 5.x (5.0, 5.3) writes a multi-layer EXR as a *multi-part* file,
  one part per pass named ``"<view layer>.<pass>"``, whose channels already
  carry full names (``"ViewLayer.Depth.Z"``); Blender 4.5 writes one
  single-part file holding every pass.  Plain EXRs are single-part ``R G B A``.
- The environment pass is ``"<layer>.Environment.RGB"`` from Blender 5.0 on
  and ``"<layer>.Env.RGB"`` in 4.5.
- The Z pass is the camera-space depth along the view axis (a plane facing the
  camera has the same Z at every pixel), not the ray length; pixels without a
  surface hold Z = 1e10, alpha 0 (film transparent) and the world colour in
  the environment pass (0 where a surface was hit).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from mlx3d.io.exr import ExrError, read_exr

bpy = pytest.importorskip("bpy")

BLENDER_5 = bpy.app.version >= (5, 0, 0)
WORLD_RGB = (0.2, 0.4, 0.6)
EMPTY_Z = 1e10  # Z where no surface was hit


@pytest.fixture
def blank_scene():
    """Blender reset to an empty scene (the reader needs no add-on, so this skips installing one)."""
    assert bpy.ops.wm.read_homefile(use_empty=True) == {"FINISHED"}
    return bpy.context.scene


def set_format(settings, multilayer: bool, codec: str = "ZIP", depth: str = "32") -> None:
    if hasattr(settings, "media_type"):  # Blender 5.x
        settings.media_type = "MULTI_LAYER_IMAGE" if multilayer else "IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER" if multilayer else "OPEN_EXR"
    settings.exr_codec = codec
    settings.color_depth = depth


# ------------------------------------------------------------ Blender images
@pytest.fixture
def saved_image(blank_scene, tmp_path):
    """A 64x48 float image of known pixels.

    Returns ``(save, pixels)``: ``save(codec, depth) -> path`` writes it as an
    EXR; ``pixels`` is ``(H, W, 4)`` float32, top row first.
    """
    h, w = 48, 64
    rng = np.random.default_rng(7)
    # A ramp over [-1, 3) plus noise, in steps of 2**-12: signs, many exponents, mantissas
    # finer than half's (so float16 rounds them), smooth enough for ZIP/ZIPS to shrink the chunks.
    ramp = np.linspace(-1, 3, w * h * 4, endpoint=False).reshape(h, w, 4)
    noise = rng.integers(-64, 64, (h, w, 4)) / 4096
    pixels = (np.round(ramp * 4096) / 4096 + noise).astype(np.float32)
    image = bpy.data.images.new("exr_oracle", w, h, alpha=True, float_buffer=True)
    image.pixels.foreach_set(pixels[::-1].ravel())  # Blender stores the bottom row first

    def save(codec: str, depth: str):
        set_format(blank_scene.render.image_settings, multilayer=False, codec=codec, depth=depth)
        path = tmp_path / f"image_{codec}_{depth}.exr"
        image.save_render(str(path), scene=blank_scene)
        return path

    return save, pixels


@pytest.mark.parametrize("depth", ["32", "16"])
@pytest.mark.parametrize("codec", ["NONE", "ZIPS", "ZIP"])
def test_float_image_round_trip(saved_image, codec, depth):
    save, pixels = saved_image
    path = save(codec, depth)
    channels = read_exr(path)
    assert sorted(channels) == ["A", "B", "G", "R"]
    got = np.stack([channels[c] for c in "RGBA"], axis=-1)
    assert got.dtype == np.float32 and got.shape == pixels.shape
    want = pixels if depth == "32" else pixels.astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(got, want)  # row 0 is the image's top row
    if codec != "NONE":  # the zlib path ran: the chunks are smaller than the raw pixels
        assert path.stat().st_size < save("NONE", depth).stat().st_size


# ------------------------------------------------------------ Cycles render
W, H = 16, 12
PLANE_Z = -3.0
PLANE_CENTRE = (0.3, 0.5)  # camera-space x, y: right of centre, top half
PLANE_HALF = 0.6
SENSOR_MM, LENS_MM = 36.0, 50.0  # Blender's default camera, sensor fit AUTO (width)


@pytest.fixture
def render_exr(blank_scene, tmp_path):
    """A 1-sample Cycles render of a plane 3 units in front of the camera, saved as a multi-layer ZIP EXR."""
    scene = blank_scene
    world = bpy.data.worlds.new("exr_world")
    if world.node_tree is None:  # 4.x: a new world has no nodes
        world.use_nodes = True
    background = next(n for n in world.node_tree.nodes if n.type == "BACKGROUND")
    background.inputs["Color"].default_value = (*WORLD_RGB, 1.0)
    background.inputs["Strength"].default_value = 1.0
    scene.world = world

    bpy.ops.object.camera_add(location=(0, 0, 0), rotation=(0, 0, 0))  # looks down -Z, +Y up
    scene.camera = bpy.context.object
    scene.camera.data.lens = LENS_MM
    scene.camera.data.sensor_width = SENSOR_MM
    scene.camera.data.sensor_fit = "AUTO"
    bpy.ops.mesh.primitive_plane_add(size=2 * PLANE_HALF, location=(*PLANE_CENTRE, PLANE_Z))

    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    scene.cycles.use_denoising = False
    render.resolution_x, render.resolution_y, render.resolution_percentage = W, H, 100
    render.film_transparent = True
    layer = scene.view_layers[0]
    layer.use_pass_z = True
    layer.use_pass_environment = True
    bpy.ops.render.render()

    set_format(render.image_settings, multilayer=True, codec="ZIP", depth="32")
    path = tmp_path / "render.exr"
    bpy.data.images["Render Result"].save_render(str(path), scene=scene)
    return path, layer.name


def pixel_rays():
    """Camera-space ``(x, y)`` at depth 1 of every pixel centre, each ``(H, W)``, row 0 at the top."""
    pitch = SENSOR_MM / LENS_MM / W
    x = (np.arange(W) + 0.5 - W / 2) * pitch
    y = (H / 2 - np.arange(H) - 0.5) * pitch
    return np.meshgrid(x, y), pitch


def test_render_passes(render_exr):
    path, layer = render_exr
    channels = read_exr(path)
    env = f"{layer}.Environment" if BLENDER_5 else f"{layer}.Env"
    for name in [f"{layer}.Combined.{c}" for c in "RGBA"] + [f"{layer}.Depth.Z"] + [f"{env}.{c}" for c in "RGB"]:
        assert name in channels, f"{name} missing from {sorted(channels)}"
        assert channels[name].shape == (H, W) and channels[name].dtype == np.float32

    # Pixels 1.5 px or more inside or outside the plane's edge: beyond the pixel filter's reach.
    (x, y), pitch = pixel_rays()
    depth = -PLANE_Z
    inset = np.minimum(PLANE_HALF - np.abs(x * depth - PLANE_CENTRE[0]),
                       PLANE_HALF - np.abs(y * depth - PLANE_CENTRE[1]))
    hit = inset > 1.5 * pitch * depth
    miss = inset < -1.5 * pitch * depth
    assert hit.sum() >= 10 and miss.sum() >= 10
    assert hit[0].any() and not hit[-1].any()  # the plane is in the top half: rows run top to bottom

    z = channels[f"{layer}.Depth.Z"]
    np.testing.assert_allclose(z[hit], depth, rtol=1e-5)  # planar depth along the view axis ...
    ray_length = depth * np.sqrt(1 + x**2 + y**2)
    assert (ray_length[hit] - depth).max() > 0.1  # ... not the ray length, which this render would tell apart
    np.testing.assert_array_equal(z[miss], np.float32(EMPTY_Z))
    assert np.all((z == np.float32(EMPTY_Z)) | np.isclose(z, depth, rtol=1e-5))

    alpha = channels[f"{layer}.Combined.A"]
    np.testing.assert_allclose(alpha[hit], 1.0, atol=1e-6)
    np.testing.assert_allclose(alpha[miss], 0.0, atol=1e-6)
    assert np.all(channels[f"{layer}.Combined.R"][hit] > 0.0)
    for c, value in zip("RGB", WORLD_RGB):
        np.testing.assert_allclose(channels[f"{env}.{c}"][miss], value, rtol=1e-5)
        np.testing.assert_allclose(channels[f"{env}.{c}"][hit], 0.0, atol=1e-6)


# ------------------------------------------------------------ crafted files
def attribute(name: str, type_name: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + type_name.encode() + b"\0" + struct.pack("<i", len(value)) + value


def header(channels: dict, window, compression: int = 0, extra: bytes = b"", display=None) -> bytes:
    """Header attributes of FLOAT channels (sorted) over ``window = (x0, y0, x1, y1)``, unterminated."""
    entry = struct.pack("<iB3xii", 2, 0, 1, 1)  # FLOAT, not linear, sampling 1x1
    chlist = b"".join(name.encode() + b"\0" + entry for name in sorted(channels)) + b"\0"
    return (
        attribute("channels", "chlist", chlist)
        + attribute("compression", "compression", bytes([compression]))
        + attribute("dataWindow", "box2i", struct.pack("<4i", *window))
        + attribute("displayWindow", "box2i", struct.pack("<4i", *(display or window)))
        + attribute("lineOrder", "lineOrder", b"\0")
        + attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0))
        + attribute("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
        + attribute("screenWindowWidth", "float", struct.pack("<f", 1.0))
        + extra
    )


def scanlines(channels: dict, y0: int) -> list[bytes]:
    """Uncompressed one-line chunks (y, size, data) of ``(H, W)`` float32 planes."""
    names = sorted(channels)
    h = channels[names[0]].shape[0]
    chunks = []
    for row in range(h):
        data = b"".join(channels[n][row].astype("<f4").tobytes() for n in names)
        chunks.append(struct.pack("<ii", y0 + row, len(data)) + data)
    return chunks


def single_part(channels: dict, window=None, display=None, compression: int = 0,
                extra: bytes = b"", flags: int = 0) -> bytes:
    """A single-part file of ``{channel: (H, W) float32}``, one-line uncompressed chunks."""
    h, w = next(iter(channels.values())).shape
    window = window or (0, 0, w - 1, h - 1)
    head = struct.pack("<iI", 20000630, 2 | flags) + header(channels, window, compression, extra, display) + b"\0"
    chunks = scanlines(channels, window[1])
    table_end = len(head) + 8 * len(chunks)
    offsets = np.cumsum([table_end] + [len(c) for c in chunks[:-1]]).astype("<u8")
    return head + offsets.tobytes() + b"".join(chunks)


def multi_part(parts: dict, part_type: str = "scanlineimage") -> bytes:
    """A multi-part file of ``{part name: {channel: (H, W) float32}}``, one-line uncompressed chunks."""
    heads, bodies = b"", []
    for name, channels in parts.items():
        h, w = next(iter(channels.values())).shape
        extra = (attribute("name", "string", name.encode()) + attribute("type", "string", part_type.encode())
                 + attribute("chunkCount", "int", struct.pack("<i", h)))
        heads += header(channels, (0, 0, w - 1, h - 1), extra=extra) + b"\0"
        bodies.append(scanlines(channels, 0))
    head = struct.pack("<iI", 20000630, 2 | 0x1000) + heads + b"\0"
    pos = len(head) + 8 * sum(len(b) for b in bodies)
    tables, data = [], b""
    for index, chunks in enumerate(bodies):
        for chunk in chunks:
            tables.append(pos)
            chunk = struct.pack("<i", index) + chunk
            data += chunk
            pos += len(chunk)
    return head + np.array(tables, dtype="<u8").tobytes() + data


def planes(*names, shape=(3, 5), seed=0):
    rng = np.random.default_rng(seed)
    return {n: rng.standard_normal(shape).astype(np.float32) for n in names}


def test_crafted_single_part_matches(tmp_path):
    channels = planes("R", "G", "B")
    path = tmp_path / "plain.exr"
    path.write_bytes(single_part(channels))
    got = read_exr(path)
    assert sorted(got) == ["B", "G", "R"]
    for name, plane in channels.items():
        np.testing.assert_array_equal(got[name], plane)


def test_data_window_pixels_are_returned_uncropped_and_unpadded(tmp_path):
    """A data window that is offset from, and sticks out of, the display window comes back as stored."""
    channels = planes("Y", shape=(4, 6))
    path = tmp_path / "window.exr"
    path.write_bytes(single_part(channels, window=(-2, 3, 3, 6), display=(0, 0, 9, 9)))
    got = read_exr(path)
    np.testing.assert_array_equal(got["Y"], channels["Y"])


def test_multi_part_short_names_get_the_part_prefix(tmp_path):
    full = planes("ViewLayer.Depth.Z", seed=1)
    short = planes("R", "G", seed=2)
    path = tmp_path / "multi.exr"
    path.write_bytes(multi_part({"ViewLayer.Depth": full, "beauty": short}))
    got = read_exr(path)
    assert sorted(got) == ["ViewLayer.Depth.Z", "beauty.G", "beauty.R"]
    np.testing.assert_array_equal(got["ViewLayer.Depth.Z"], full["ViewLayer.Depth.Z"])
    np.testing.assert_array_equal(got["beauty.G"], short["G"])


def test_zip_predictor_and_interleave(tmp_path):
    """A ZIP chunk built by the spec's forward filter (interleave halves, then byte deltas + 128)."""
    channels = {n: np.round(p * 8) / 8 for n, p in planes("R", "G", shape=(16, 7)).items()}
    raw = b"".join(channels[n][row].astype("<f4").tobytes() for row in range(16) for n in sorted(channels))
    split = np.frombuffer(raw, dtype=np.uint8)
    interleaved = np.concatenate([split[0::2], split[1::2]]).astype(np.int64)
    filtered = interleaved.copy()
    filtered[1:] = (np.diff(interleaved) + 128) & 0xFF
    packed = zlib.compress(filtered.astype(np.uint8).tobytes())
    assert len(packed) < len(raw)
    head = struct.pack("<iI", 20000630, 2) + header(channels, (0, 0, 6, 15), compression=3) + b"\0"
    chunk = struct.pack("<ii", 0, len(packed)) + packed
    path = tmp_path / "zip.exr"
    path.write_bytes(head + struct.pack("<Q", len(head) + 8) + chunk)
    got = read_exr(path)
    for name, plane in channels.items():
        np.testing.assert_array_equal(got[name], plane)


def expect_error(path, *words):
    with pytest.raises(ValueError) as info:
        read_exr(path)
    assert isinstance(info.value, ExrError)
    message = str(info.value)
    assert str(path) in message
    for word in words:
        assert word in message, message


def test_truncated_files(tmp_path, saved_image):
    save, _ = saved_image
    data = save("ZIP", "32").read_bytes()
    for cut in (4, 20, 200, len(data) // 2, len(data) - 1):
        path = tmp_path / f"cut_{cut}.exr"
        path.write_bytes(data[:cut])
        expect_error(path, "truncated")


def test_not_an_exr(tmp_path):
    for name, data in {"empty.exr": b"", "png.exr": b"\x89PNG\r\n\x1a\n" + bytes(64)}.items():
        path = tmp_path / name
        path.write_bytes(data)
        expect_error(path, "not an OpenEXR")


@pytest.mark.parametrize(
    "kind, words",
    [
        ("piz", ("PIZ", "compression")),
        ("tiled_flag", ("tiled",)),
        ("tiled_part", ("tiledimage",)),
        ("deep", ("deep",)),
        ("half_sampled", ("subsampled",)),
        ("no_channels", ("channels",)),
        ("bad_chunk_y", ("y=",)),
        ("bad_zip", ("corrupt",)),
    ],
)
def test_unsupported_or_malformed(tmp_path, kind, words):
    channels = planes("R")
    if kind == "piz":
        data = single_part(channels, compression=4)
    elif kind == "tiled_flag":
        tiles = attribute("tiles", "tiledesc", struct.pack("<IIB", 32, 32, 0))
        data = single_part(channels, extra=tiles, flags=0x200)
    elif kind == "tiled_part":
        data = multi_part({"part": channels}, part_type="tiledimage")
    elif kind == "deep":
        data = single_part(channels, flags=0x800)
    elif kind == "half_sampled":
        data = single_part(channels).replace(struct.pack("<iB3xii", 2, 0, 1, 1), struct.pack("<iB3xii", 2, 0, 2, 2))
    elif kind == "no_channels":
        data = single_part(channels).replace(b"channels\0", b"chAnnels\0")
    elif kind == "bad_chunk_y":
        good = single_part(channels)
        first = good.index(struct.pack("<ii", 0, 20))  # chunk y=0, 5 floats
        data = good[:first] + struct.pack("<i", 7) + good[first + 4:]
    else:
        head = struct.pack("<iI", 20000630, 2) + header(channels, (0, 0, 4, 2), compression=3) + b"\0"
        junk = b"not zlib data"
        data = head + struct.pack("<Q", len(head) + 8) + struct.pack("<ii", 0, len(junk)) + junk
    path = tmp_path / f"{kind}.exr"
    path.write_bytes(data)
    expect_error(path, *words)
