"""Helpers shared by the splat file codecs (numpy only).

Conventions every codec follows (written once here):

- In memory a splat file is a :class:`~mlx3d.io.ply.SplatArrays` in the 3DGS
  PLY convention: raw values (``opacity`` a logit, ``scales`` log standard
  deviations, ``quats`` ``w, x, y, z``), ``sh_rest`` coefficient-major
  ``(N, K-1, 3)``, positions in the file's own axes.  A format that stores
  activated values (linear scales, alpha, 8-bit colour) is converted with
  :func:`logit` / :data:`SH_C0` here, in float64, and rounded to float32 once.
- A reader takes the path and returns :class:`SplatArrays`; it raises
  :class:`~mlx3d.errors.SplatFormatError` naming the file and what is wrong
  (truncated, bad magic, unsupported version, inconsistent sizes) and never
  returns part of a file.  :class:`Bytes` does the bounds-checked reading.
- A writer takes ``(path, splats, *, fsync=True)`` with ``splats`` already
  checked by :func:`~mlx3d.io.formats.write_splats` (shapes, float32,
  finite where the format quantises) and writes inside
  :func:`~mlx3d.io.atomic.atomic_write`, so a failed write leaves no partial
  file and an existing file untouched.  Everything that can fail (encoding,
  compression) happens before the first byte is written.
- A sniffer ``(head: bytes, path: str) -> bool`` recognises a file by its
  first bytes (:data:`SNIFF_BYTES` of them), opening ``path`` only where the
  head is not enough (a zip's member list, a header's consistency with the
  file's size).
"""

from __future__ import annotations

import numpy as np

from ..errors import SplatFormatError
from ..sh_basis import C0

__all__ = ["SH_C0", "SNIFF_BYTES", "Bytes", "logit", "sigmoid", "normalized_quats"]

#: Degree-0 SH basis constant: ``rgb = 0.5 + SH_C0 * dc``.
SH_C0 = C0

#: How many leading bytes a sniffer sees.
SNIFF_BYTES = 4096


def sigmoid(x) -> np.ndarray:
    """Logistic function in float64 (opacity logit -> alpha in ``[0, 1]``).

    Accurate to a few ulps in relative terms for every ``x``, also very
    negative ones (``exp(x) / (1 + exp(x))`` there), without overflow.
    """
    x = np.asarray(x, np.float64)
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def logit(alpha, eps: float = 1e-6) -> np.ndarray:
    """Inverse of :func:`sigmoid` in float64, ``alpha`` clamped to ``[eps, 1-eps]``.

    8-bit alphas 0 and 255 map to about -13.8 and 13.8 instead of infinities.
    """
    a = np.clip(np.asarray(alpha, np.float64), eps, 1.0 - eps)
    return np.log(a / (1.0 - a))


def normalized_quats(quats) -> np.ndarray:
    """``(N, 4)`` float64 unit quaternions ``w, x, y, z`` with ``w >= 0``.

    A zero quaternion (no rotation stored) becomes the identity.
    """
    q = np.asarray(quats, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    zero = norm[:, 0] == 0.0
    q = np.where(zero[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q / np.where(norm == 0.0, 1.0, norm))
    return np.where(q[:, :1] < 0.0, -q, q)


class Bytes:
    """Bounds-checked reading of a file's bytes; errors name the file.

    ``data`` is the whole (decompressed) content; ``take(n, what)`` returns the
    next ``n`` bytes as a ``memoryview`` or raises :class:`SplatFormatError`
    saying what was being read and how many bytes were missing.
    """

    def __init__(self, path: str, data: bytes, what: str = "file"):
        self.path = path
        self.data = memoryview(data)
        self.pos = 0
        self.what = what

    def error(self, problem: str) -> SplatFormatError:
        """A :class:`SplatFormatError` for this file."""
        return SplatFormatError(f"{self.path}: {problem}")

    @property
    def left(self) -> int:
        """Bytes after the current position."""
        return len(self.data) - self.pos

    def take(self, n: int, what: str) -> memoryview:
        """The next ``n`` bytes; raise a "truncated" error naming ``what``."""
        n = int(n)
        if n < 0 or n > self.left:
            raise self.error(
                f"truncated {self.what}: {what} needs {n} bytes at byte {self.pos}, "
                f"only {self.left} remain")
        view = self.data[self.pos:self.pos + n]
        self.pos += n
        return view

    def array(self, dtype, count: int, what: str) -> np.ndarray:
        """The next ``count`` items of ``dtype`` (a copy, native byte order)."""
        dt = np.dtype(dtype)
        raw = self.take(dt.itemsize * int(count), what)
        return np.frombuffer(raw, dt).astype(dt.newbyteorder("="), copy=True)

    def seek(self, pos: int, what: str) -> None:
        """Move to byte ``pos``; raise if it is past the end."""
        if pos < 0 or pos > len(self.data):
            raise self.error(f"{what} points at byte {pos}, outside the {len(self.data)}-byte {self.what}")
        self.pos = int(pos)
