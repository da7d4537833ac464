"""The attribute layout of splat objects, and the one place that decides it by Blender version.

A splat object is a point cloud whose POINT-domain attributes are those of
Blender 5.3's own Gaussian splats (what ``bpy.ops.wm.ply_import`` makes of a
3DGS PLY), on every Blender version the add-on supports:

=================  ============  =============================================
attribute          type          meaning (3DGS PLY properties)
=================  ============  =============================================
position           FLOAT_VECTOR  x y z (object space)
radiance:base      FLOAT4 [1]_   f_dc_0..2, sigmoid(opacity)
scale              FLOAT_VECTOR  exp(scale_0..2): standard deviations
rotation           QUATERNION    rot_0..3 normalised (w, x, y, z)
radiance:sh_<k>    FLOAT_VECTOR  SH coefficient k+1 (RGB) = f_rest_{k},
                                 f_rest_{K+k}, f_rest_{2K+k}; K = 3, 8 or 15
<name>             FLOAT / INT   any other PLY property; its PLY type in the
                                 data's ``mlx3d_ply_types``
=================  ============  =============================================

.. [1] FLOAT_COLOR where Blender has no FLOAT4 attributes (4.5, 5.0); a file
   saved there is converted when it is opened in 5.3.

These are the source of truth: export reads them, so an edit in the
spreadsheet, a Python script or a Geometry Nodes tree is what the file gets.
Three hidden attributes keep the file's raw values where the native ones
cannot reproduce them bit for bit (a logit above about 16 saturates the
float32 sigmoid; exp/log and normalisation round): ``.mlx3d_opacity``
(logit), ``.mlx3d_log_scale`` and ``.mlx3d_rot`` (as stored). Export uses a
point's raw value only while the native one still equals what was derived
from it, so an edit always wins. PLY properties that are zero for every splat
(``nx ny nz`` in most files) are not stored; their names are kept in
``mlx3d_zero_properties`` and written back as zeros.

Memory per splat at SH degree 3: 236 bytes in Blender's layout, 268 with the
hidden raw values (plus 4 per non-zero extra property).

By version (``layout_for``): from 5.3 the point cloud's ``type`` is
``GAUSSIAN_SPLAT`` and nothing else is added, so Blender draws and renders
our objects exactly as its own. Before 5.3 Blender has no splat drawing, so
a Geometry Nodes modifier (``display``) shows every splat as a point of its
size and colour; it adds nothing to the data-block that export reads.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import bpy

BASE = "radiance:base"
SCALE = "scale"
ROTATION = "rotation"
NATIVE = (BASE, SCALE, ROTATION)
SH_PATTERN = re.compile(r"^radiance:sh_(\d+)$")
RAW_OPACITY = ".mlx3d_opacity"
RAW_LOG_SCALE = ".mlx3d_log_scale"
RAW_ROT = ".mlx3d_rot"
RAW = (RAW_OPACITY, RAW_LOG_SCALE, RAW_ROT)
TYPES_KEY = "mlx3d_ply_types"
ZERO_KEY = "mlx3d_zero_properties"

# The layout of earlier versions of this add-on (raw PLY values as attributes,
# display attributes beside them): read, and converted when a file is opened.
LEGACY_RAW = ("f_dc", "opacity", "log_scale", "rot")
LEGACY_REST = re.compile(r"^f_rest_(\d+)$")
LEGACY_DISPLAY = ("radius", "splat_color")
LEGACY_MATERIAL = "MLX3D Splat"

NATIVE_SPLAT_VERSION = (5, 3, 0)


@dataclass(frozen=True)
class Layout:
    """What a Blender version gets.

    base_type: the data type of ``radiance:base``; splat_type: the point
    cloud ``type`` to set (None where the property does not exist); own_display:
    whether the add-on's Geometry Nodes display is needed to see the splats."""

    base_type: str
    splat_type: str | None
    own_display: bool


def layout_for(version: tuple, has_float4: bool) -> Layout:
    """The layout for Blender ``version`` (a tuple like ``bpy.app.version``),
    whose attributes have a FLOAT4 type or not."""
    native = tuple(version) >= NATIVE_SPLAT_VERSION
    return Layout(
        base_type="FLOAT4" if has_float4 else "FLOAT_COLOR",
        splat_type="GAUSSIAN_SPLAT" if native else None,
        own_display=not native,
    )


def current() -> Layout:
    """The layout of the running Blender."""
    types = {item.identifier for item in bpy.types.Attribute.bl_rna.properties["data_type"].enum_items}
    return layout_for(bpy.app.version, "FLOAT4" in types)


def reserved(name: str) -> bool:
    """Attribute names the layout owns (never an extra PLY property)."""
    return name == "position" or name in NATIVE or name in RAW or bool(SH_PATTERN.match(name)) or name.startswith(".")
