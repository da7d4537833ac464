"""antimatter15 ``.splat`` files (the web viewers' 32-byte splats; numpy only).

No header: ``N`` records of 32 bytes, little-endian::

    position  3 x float32           x, y, z (the file's axes, as PLY)
    scale     3 x float32           linear standard deviations, exp(scale_i)
    colour    4 x uint8             r, g, b = 255 * (0.5 + SH_C0 * f_dc), clamped;
                                    a = 255 * sigmoid(opacity)
    rotation  4 x uint8             w, x, y, z of the unit quaternion, 128 * q + 128

No SH beyond degree 0 and no extra properties.  Quantisation bounds, for a
value inside the format's range (a colour in [0, 1], any unit quaternion):

- positions: exact (float32); log scales: float32 ``log(exp(s))``, within 1e-6;
- ``f_dc``: ``0.5 / 255 / SH_C0 = 0.00695`` (half an 8-bit step);
- opacity: the alpha within ``0.5 / 255``; a logit beyond +-13.8 is clamped;
- rotation: each unit-quaternion component within ``0.5 / 128`` before
  renormalisation; the rotation matrix within about 0.02.

A colour outside [0, 1] (``f_dc`` beyond about +-1.77) is clamped: the format
cannot hold it.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import SplatFormatError
from .atomic import atomic_write
from .codec import SH_C0, logit, normalized_quats, sigmoid
from .ply import SplatArrays

__all__ = ["RECORD", "read_splat", "write_splat"]

#: One splat's record.
RECORD = np.dtype([
    ("position", "<f4", 3), ("scale", "<f4", 3), ("color", "u1", 4), ("rotation", "u1", 4)])
assert RECORD.itemsize == 32


def _u8(x) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def read_splat(path: str | os.PathLike) -> SplatArrays:
    """Read a ``.splat`` file into :class:`SplatArrays` (SH degree 0).

    Raises :class:`SplatFormatError` for an empty file or one whose size is not
    a multiple of 32 bytes.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        data = f.read()
    if not data or len(data) % RECORD.itemsize:
        raise SplatFormatError(
            f"{path}: not a .splat file: {len(data)} bytes is not a positive multiple of the "
            f"{RECORD.itemsize}-byte splat record"
            + (f" ({len(data) // RECORD.itemsize} whole records and {len(data) % RECORD.itemsize} "
               "bytes over: truncated?)" if data else ""))
    rec = np.frombuffer(data, RECORD)
    n = len(rec)
    with np.errstate(divide="ignore", invalid="ignore"):
        scales = np.log(rec["scale"].astype(np.float64))
    rgba = rec["color"].astype(np.float64) / 255.0
    quats = normalized_quats((rec["rotation"].astype(np.float64) - 128.0) / 128.0)
    return SplatArrays(
        means=rec["position"].astype(np.float32),
        scales=scales.astype(np.float32),
        quats=quats.astype(np.float32),
        opacities=logit(rgba[:, 3]).astype(np.float32),
        sh_dc=((rgba[:, :3] - 0.5) / SH_C0).astype(np.float32).reshape(n, 1, 3),
        sh_rest=np.zeros((n, 0, 3), np.float32),
    )


def write_splat(path: str | os.PathLike, splats: SplatArrays, *, fsync: bool = True) -> None:
    """Write ``splats`` as a ``.splat`` file (drops SH above degree 0), atomically.

    Splats are written in their order (viewers sort them for drawing).
    """
    n = splats.count
    rec = np.empty(n, RECORD)
    rec["position"] = splats.means
    rec["scale"] = np.exp(np.asarray(splats.scales, np.float64))
    rgb = 0.5 + SH_C0 * np.asarray(splats.sh_dc, np.float64).reshape(n, 3)
    rec["color"] = _u8(np.concatenate([rgb, sigmoid(splats.opacities)[:, None]], axis=1) * 255.0)
    rec["rotation"] = _u8(normalized_quats(splats.quats) * 128.0 + 128.0)
    with atomic_write(path, "wb", fsync=fsync) as f:
        f.write(rec.tobytes())
