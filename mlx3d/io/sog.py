"""PlayCanvas SOG (Spatially Ordered Gaussians; numpy, Pillow's WebP, ``zipfile``).

A SOG is a ``meta.json`` plus 8-bit RGBA images, either side by side in a
directory (``path`` is the ``meta.json``) or stored in a zip archive (``.sog``,
the same files at the archive's root; any compression ``zipfile`` reads).
Images are lossless WebP (any 8-bit image Pillow decodes is accepted).  Splat
``i`` is pixel ``i`` in row-major order of every per-splat image, all of one
size ``W x H`` with ``W * H >= count``; trailing pixels are ignored.
Positions are in the PLY axes.

Version 2 (``"version": 2``; what :func:`write_sog` writes)::

    count                       number of splats
    means   mins, maxs (3 each) per-axis range of l = sign(x) * ln(|x| + 1)
            means_l, means_u    RGB = low / high byte of the 16-bit
                                u = round(65535 * (l - min) / (max - min));
                                x = sign(v) * (exp(|v|) - 1), v = min + (max - min) * u / 65535
                                (a zero range decodes as min)
    quats   quats               RGB = the three components other than the largest
                                (w, x, y, z order; the largest made positive),
                                each b = round(255 * (c * sqrt(2) / 2 + 0.5));
                                A = 252 + index of the largest; it is
                                sqrt(1 - sum of the other three squared)
    scales  codebook (256)      log scales; scales RGB = codebook index per axis
    sh0     codebook (256)      f_dc; sh0 RGB = codebook index per channel,
                                A = round(255 * sigmoid(opacity))
    shN     count, bands (1-3), codebook (256)
            shN_centroids       the palette: width 64 * (K-1), entry e at
                                pixels e * (K-1) + j (j = SH coefficient),
                                RGB = codebook index per channel
            shN_labels          R + 256 * G = palette entry of the splat

Version 1 (no ``version``; splat-transform still reads it): ``count`` is
``means.shape[0]``; ``scales`` and ``sh0`` have per-channel ``mins``/``maxs``
instead of codebooks (``v = min + (max - min) * b / 255``, ``sh0``'s alpha
the opacity logit on the same ramp); ``shN`` has scalar ``mins``/``maxs`` for
every palette byte and no ``count``/``bands`` (the band count follows from the
palette's width, 192 / 512 / 960).  Means and quats are as in version 2.

Writing (version 2) keeps the splats' order (a spatially sorted input gives
smaller images), needs ``W, H <= 16383`` (about 268M splats), and fits:

- scales and ``f_dc``: one 256-entry codebook for all three axes / channels,
  the weighted 1-D k-means of :func:`_codebook` (exact where a field has at
  most 256 distinct values, e.g. a file read back);
- SH rest: a palette of ``k = min(65536, 2 ** floor(log2 N))`` entries (the
  size splat-transform picks), k-means over the ``3 (K-1)`` coefficients of
  each splat (:func:`_palette`, seeded, so a write is deterministic): 10
  Lloyd iterations; above 2^24 point-centroid pairs in two levels,
  ``2^ceil(log2(k) / 2)`` coarse clusters (10 iterations on 64 sampled
  splats per cluster), each split into its share of the palette (10
  iterations); then one 256-entry codebook for every palette value.  About
  1 s for 32k splats and 15 s for 1M on two CPU cores.

Quantisation bounds:

- positions: half a 16-bit step in ``l``: ``|dx| <= (|x| + 1) * (exp(d) - 1)``,
  ``d = (max - min) / 131070`` per axis, plus float32 rounding;
- rotations: each stored component within ``1 / (255 sqrt 2) = 0.0028``;
  rotation matrix entries within 0.015 (0.0124 the most seen in 400k random
  rotations);
- opacity: the alpha within ``0.5 / 255``; a logit beyond +-13.8 is clamped;
- scales, ``f_dc``, SH rest: data dependent (a codebook, a palette).  On the
  500 splats of ``tests/data/formats/opensplat_500.ply`` (a 256-entry
  palette): scales within 0.017 (log units, RMS 0.0053), ``f_dc`` within
  0.015 (RMS 0.0037), SH rest within 0.045 / 0.052 / 0.035 at SH degree
  1 / 2 / 3 (RMS 0.0068 / 0.0042 / 0.0029).  splat-transform's file of that
  scene: scales 0.015 (RMS 0.0048), ``f_dc`` 0.011 (RMS 0.0033), SH rest
  0.047 (RMS 0.0031).
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile

import numpy as np
from PIL import Image

from ..errors import SplatFormatError
from .atomic import atomic_write
from .codec import logit, normalized_quats, sigmoid
from .ply import SplatArrays

__all__ = ["CODEBOOK_SIZE", "KMEANS_ITERATIONS", "palette_size", "read_sog", "sniff_sog", "write_sog"]

#: Entries of the scale, colour and SH codebooks.
CODEBOOK_SIZE = 256
#: Lloyd iterations of the SH palette's k-means (per level).
KMEANS_ITERATIONS = 10
#: Largest image side WebP allows.
MAX_SIDE = 16383

_ZIP_MAGIC = b"PK\x03\x04"
_META = "meta.json"
_REST_PER_CHANNEL = (0, 3, 8, 15)
_V1_BANDS_OF_WIDTH = {192: 1, 512: 2, 960: 3}
_MAX_META_BYTES = 4 << 20
_FLAT_KMEANS_PAIRS = 1 << 24   # point-centroid pairs above which the palette is fitted in two levels
_CHUNK_PAIRS = 1 << 20         # point-centroid distances computed at once (4 MiB of float32)
_SEED = 0x50C


# ---------------------------------------------------------------------------
# reading

class _Files:
    """``meta.json`` and the images beside it, from a zip archive or a directory."""

    def __init__(self, path: str):
        self.path = path
        self.zip = None
        with open(path, "rb") as f:
            head = f.read(4)
        if head == _ZIP_MAGIC:
            try:
                self.zip = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError, ValueError) as e:
                raise self.error(f"not a readable zip archive (truncated or damaged): {e}") from None
            self.names = set(self.zip.namelist())
            if _META not in self.names:
                shown = ", ".join(sorted(self.names)[:8]) or "none"
                raise self.error(f"the archive has no {_META} at its root (members: {shown})")
            self.where = "the archive"
        else:
            self.where = f"{os.path.dirname(os.path.abspath(path))}"

    def error(self, problem: str) -> SplatFormatError:
        return SplatFormatError(f"{self.path}: {problem}")

    def close(self) -> None:
        if self.zip is not None:
            self.zip.close()

    def meta_bytes(self) -> bytes:
        if self.zip is None:
            with open(self.path, "rb") as f:
                return f.read()
        return self._member(_META)

    def _member(self, name: str) -> bytes:
        try:
            return self.zip.read(name)
        except (zipfile.BadZipFile, OSError, EOFError, ValueError, RuntimeError) as e:
            raise self.error(f"cannot read {name} from the archive (truncated or damaged): {e}") from None
        except Exception as e:  # zlib/bz2/lzma errors of a damaged member
            raise self.error(f"cannot read {name} from the archive: {type(e).__name__}: {e}") from None

    def image(self, name, what: str) -> np.ndarray:
        """The image ``name`` as ``(H, W, 4)`` uint8 RGBA."""
        if not isinstance(name, str) or not name:
            raise self.error(f"{_META}: {what} names no image file ({name!r})")
        if self.zip is not None:
            if name not in self.names:
                raise self.error(f"{_META} names {name!r} ({what}), which is not in {self.where}")
            data = self._member(name)
        else:
            if os.path.isabs(name):
                raise self.error(f"{_META} names {name!r} ({what}): an absolute path, not a file beside it")
            full = os.path.join(self.where, name)
            if not os.path.isfile(full):
                raise self.error(f"{_META} names {name!r} ({what}), which does not exist in {self.where}")
            with open(full, "rb") as f:
                data = f.read()
        try:
            with Image.open(io.BytesIO(data)) as im:
                im.load()
                rgba = np.asarray(im.convert("RGBA"))
        except Exception as e:
            raise self.error(f"{name} ({what}) is not a readable image: {type(e).__name__}: {e}") from None
        return rgba


class _Meta:
    """Typed access to ``meta.json`` with errors naming the file and the key."""

    def __init__(self, files: _Files, data: bytes):
        self.files = files
        try:
            self.root = json.loads(data.decode("utf-8-sig"))
        except (UnicodeDecodeError, ValueError) as e:
            raise files.error(f"{_META} is not valid JSON: {e}") from None
        if not isinstance(self.root, dict):
            raise files.error(f"{_META} is not a JSON object (got {type(self.root).__name__})")

    def error(self, problem: str) -> SplatFormatError:
        return self.files.error(f"{_META}: {problem}")

    def section(self, key: str, optional: bool = False) -> dict | None:
        value = self.root.get(key)
        if value is None and optional:
            return None
        if not isinstance(value, dict):
            raise self.error(f"'{key}' must be an object, got {_json_kind(value)}")
        return value

    def count(self, value, where: str) -> int:
        if not _is_number(value) or value != int(value) or value < 0:
            raise self.error(f"'{where}' must be a non-negative integer, got {value!r}")
        return int(value)

    def numbers(self, section: dict, key: str, where: str, length: int | None) -> np.ndarray:
        """``section[key]``: a number (``length`` None) or a list of ``length`` numbers."""
        value = section.get(key)
        if length is None:
            ok = _is_number(value)
        else:
            ok = isinstance(value, list) and len(value) == length and all(map(_is_number, value))
        if not ok:
            want = "a number" if length is None else f"a list of {length} numbers"
            raise self.error(f"'{where}.{key}' must be {want}, got {_json_kind(value)}")
        return np.asarray(value, np.float64)

    def codebook(self, section: dict, where: str) -> np.ndarray:
        """A 256-entry codebook as float32; a leading ``null`` (an -Infinity
        written by old encoders) is extrapolated as PlayCanvas' viewer does."""
        value = section.get("codebook")
        if isinstance(value, list) and len(value) == CODEBOOK_SIZE and value[0] is None \
                and all(map(_is_number, value[1:])):
            value = [value[1] + (value[1] - value[-1]) / (CODEBOOK_SIZE - 1)] + value[1:]
        section = {"codebook": value}
        return self.numbers(section, "codebook", where, CODEBOOK_SIZE).astype(np.float32)

    def file_names(self, section: dict, where: str, count: int) -> list:
        value = section.get("files")
        if not isinstance(value, list) or len(value) < count or not all(isinstance(v, str) for v in value[:count]):
            raise self.error(f"'{where}.files' must list {count} image file name(s), got {_json_kind(value)}")
        return value[:count]


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _json_kind(v) -> str:
    if isinstance(v, (list, dict)):
        return f"{type(v).__name__} of {len(v)}"
    return repr(v) if not isinstance(v, str) or len(v) < 40 else "a string"


class _Texels:
    """The per-splat images of one file: the first ``count`` pixels of each,
    checking that they all have one size holding ``count`` splats."""

    def __init__(self, files: _Files, count: int):
        self.files = files
        self.count = count
        self.size = None
        self.first = None

    def __call__(self, name, what: str) -> np.ndarray:
        img = self.files.image(name, what)
        h, w = img.shape[:2]
        if self.size is None:
            if w * h < self.count:
                raise self.files.error(
                    f"{name} ({what}) is {w}x{h} = {w * h} pixels, fewer than the {self.count} splats of {_META}")
            self.size, self.first = (w, h), name
        elif (w, h) != self.size:
            raise self.files.error(
                f"{name} ({what}) is {w}x{h} but {self.first} is {self.size[0]}x{self.size[1]}; "
                "every per-splat image must have the same size")
        return img.reshape(-1, 4)[:self.count]


def _decode_means(lo: np.ndarray, hi: np.ndarray, mins: np.ndarray, maxs: np.ndarray) -> np.ndarray:
    u = lo[:, :3].astype(np.float64) + 256.0 * hi[:, :3]
    span = maxs - mins
    v = mins + np.where(span != 0.0, span, 1.0) * (u / 65535.0)
    with np.errstate(over="ignore"):  # an absurd range gives Inf, which read_splats reports
        return (np.sign(v) * np.expm1(np.abs(v))).astype(np.float32)


def _decode_quats(files: _Files, q: np.ndarray, name: str) -> np.ndarray:
    tag = q[:, 3].astype(np.int64) - 252
    bad = (tag < 0) | (tag > 3)
    if bad.any():
        i = int(np.argmax(bad))
        raise files.error(
            f"{name} (quats): splat {i} has mode byte {int(q[i, 3])} (alpha); expected 252-255, "
            f"the index of the largest component ({int(bad.sum())} splat(s) affected)")
    small = (q[:, :3].astype(np.float64) / 255.0 * 2.0 - 1.0) / math.sqrt(2.0)
    n = len(q)
    out = np.zeros((n, 4), np.float64)
    # column of the c-th stored component when component `tag` is the largest
    cols = np.arange(3)[None, :] + (np.arange(3)[None, :] >= tag[:, None])
    out[np.arange(n)[:, None], cols] = small
    out[np.arange(n), tag] = np.sqrt(np.maximum(0.0, 1.0 - (small * small).sum(axis=1)))
    return out.astype(np.float32)


def _sh_rest(files: _Files, meta: _Meta, texels: _Texels, shn: dict, count: int, v2: bool) -> np.ndarray:
    """``(count, K-1, 3)`` SH rest from the palette and the labels."""
    if v2:
        bands = meta.count(shn.get("bands"), "shN.bands")
        if bands > 3:
            raise meta.error(f"'shN.bands' must be 0-3, got {bands}")
        if bands == 0:
            return np.zeros((count, 0, 3), np.float32)
    names = meta.file_names(shn, "shN", 2)
    cen = files.image(names[0], "shN centroids")
    ch, cw = cen.shape[:2]
    if v2:
        k1 = _REST_PER_CHANNEL[bands]
        if cw != 64 * k1:
            raise files.error(
                f"{names[0]} (shN centroids) is {cw} pixels wide; {bands} SH band(s) need 64 x {k1} = {64 * k1}")
        entries = min(meta.count(shn.get("count"), "shN.count"), 64 * ch)
        table = meta.codebook(shn, "shN")
    else:
        if cw not in _V1_BANDS_OF_WIDTH:
            raise files.error(
                f"{names[0]} (shN centroids) is {cw} pixels wide; expected 192, 512 or 960 (1, 2 or 3 SH bands)")
        k1 = _REST_PER_CHANNEL[_V1_BANDS_OF_WIDTH[cw]]
        entries = 64 * ch
        lo = meta.numbers(shn, "mins", "shN", None)
        hi = meta.numbers(shn, "maxs", "shN", None)
        table = (lo + (hi - lo) * np.arange(256) / 255.0).astype(np.float32)
    labels_rgba = texels(names[1], "shN labels")
    labels = labels_rgba[:, 0].astype(np.int64) + 256 * labels_rgba[:, 1].astype(np.int64)
    bad = labels >= entries
    if bad.any():
        i = int(np.argmax(bad))
        raise files.error(
            f"{names[1]} (shN labels): splat {i} names palette entry {int(labels[i])}, "
            f"but the palette has {entries} entries")
    palette = cen.reshape(-1, 4)[:entries * k1, :3].reshape(entries, k1, 3)
    return table[palette[labels]]


def read_sog(path: str | os.PathLike) -> SplatArrays:
    """Read a SOG (``.sog`` archive or ``meta.json``; version 1 or 2).

    Raises :class:`SplatFormatError` naming the file and the problem: a
    damaged archive, invalid or incomplete ``meta.json``, an unsupported
    version, a missing or unreadable image, images too small or of different
    sizes, an invalid quaternion mode or a palette label out of range.
    """
    path = os.fspath(path)
    files = _Files(path)
    try:
        return _read(files)
    finally:
        files.close()


def _read(files: _Files) -> SplatArrays:
    meta = _Meta(files, files.meta_bytes())
    version = meta.root.get("version")
    if version is not None and (version != 2 or isinstance(version, bool)):
        raise meta.error(f"unsupported SOG version {version!r} (readable: 2, and 1 without a 'version')")
    v2 = version == 2
    means = meta.section("means")
    if v2:
        count = meta.count(meta.root.get("count"), "count")
    else:
        shape = means.get("shape")
        if not isinstance(shape, list) or not shape:
            raise meta.error(f"'means.shape' must be a list starting with the splat count, got {_json_kind(shape)}")
        count = meta.count(shape[0], "means.shape[0]")
    texels = _Texels(files, count)

    names = meta.file_names(means, "means", 2)
    mins = meta.numbers(means, "mins", "means", 3)
    maxs = meta.numbers(means, "maxs", "means", 3)
    xyz = _decode_means(texels(names[0], "means low bytes"), texels(names[1], "means high bytes"), mins, maxs)

    quats_meta = meta.section("quats")
    qname = meta.file_names(quats_meta, "quats", 1)[0]
    quats = _decode_quats(files, texels(qname, "quats"), qname)

    scales_meta = meta.section("scales")
    s = texels(meta.file_names(scales_meta, "scales", 1)[0], "scales")[:, :3]
    sh0_meta = meta.section("sh0")
    c = texels(meta.file_names(sh0_meta, "sh0", 1)[0], "sh0")
    if v2:
        scales = meta.codebook(scales_meta, "scales")[s]
        sh_dc = meta.codebook(sh0_meta, "sh0")[c[:, :3]]
        opacities = logit(c[:, 3] / 255.0).astype(np.float32)
    else:
        lo = meta.numbers(scales_meta, "mins", "scales", 3)
        hi = meta.numbers(scales_meta, "maxs", "scales", 3)
        scales = (lo + (hi - lo) * (s / 255.0)).astype(np.float32)
        lo = meta.numbers(sh0_meta, "mins", "sh0", 4)
        hi = meta.numbers(sh0_meta, "maxs", "sh0", 4)
        lerped = lo + (hi - lo) * (c / 255.0)
        sh_dc = lerped[:, :3].astype(np.float32)
        opacities = lerped[:, 3].astype(np.float32)

    shn = meta.section("shN", optional=True)
    if shn is None:
        rest = np.zeros((count, 0, 3), np.float32)
    else:
        rest = _sh_rest(files, meta, texels, shn, count, v2)
    return SplatArrays(
        means=xyz, scales=scales, quats=quats, opacities=opacities,
        sh_dc=sh_dc.reshape(count, 1, 3), sh_rest=rest)


def sniff_sog(head: bytes, path: str) -> bool:
    """A zip archive named ``.sog`` or holding a ``meta.json``; a JSON object
    named ``*meta.json`` or holding SOG's ``means``, ``quats``, ``scales``
    and ``sh0`` sections."""
    name = os.path.basename(os.fspath(path)).lower()
    if head.startswith(_ZIP_MAGIC):
        if name.endswith(".sog"):
            return True
        try:
            with zipfile.ZipFile(path) as z:
                return _META in z.namelist()
        except Exception:
            return False
    if not head.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(b"{"):
        return False
    if name.endswith(_META):
        return True
    try:
        if os.path.getsize(path) > _MAX_META_BYTES:
            return False
        with open(path, "rb") as f:
            root = json.loads(f.read().decode("utf-8-sig"))
    except Exception:
        return False
    return isinstance(root, dict) and all(isinstance(root.get(k), dict) for k in ("means", "quats", "scales", "sh0"))


# ---------------------------------------------------------------------------
# writing

def palette_size(n: int) -> int:
    """SH palette entries for ``n`` splats: ``min(65536, 2 ** floor(log2 n))``
    (splat-transform's choice, ``min(64, 2 ** floor(log2(n / 1024))) * 1024``)."""
    return 0 if n < 1 else min(65536, 1 << (int(n).bit_length() - 1))


def _texture_size(n: int) -> tuple[int, int]:
    """Image ``(width, height)`` for ``n`` splats: multiples of 4, near square."""
    w = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    return w, max(4, math.ceil(n / w / 4) * 4)


def _lloyd_1d(s: np.ndarray, cw: np.ndarray, cwx: np.ndarray, centres: np.ndarray,
              iterations: int) -> np.ndarray:
    """Weighted 1-D Lloyd on sorted values ``s`` (``cw``/``cwx``: prefix sums
    of the weights and weighted values); a cluster is a run of ``s``."""
    n = len(s)
    for _ in range(iterations):
        bounds = np.concatenate([[0], np.searchsorted(s, 0.5 * (centres[1:] + centres[:-1]), "right"), [n]])
        wsum = cw[bounds[1:]] - cw[bounds[:-1]]
        moved = np.where(wsum > 0, (cwx[bounds[1:]] - cwx[bounds[:-1]]) / np.where(wsum > 0, wsum, 1.0), centres)
        if np.array_equal(moved, centres):
            break
        centres = moved
    return centres


def _nearest(book: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Index of the nearest entry of the ascending ``book`` for each of ``v``."""
    return np.searchsorted(0.5 * (book[1:] + book[:-1]), v, "right")


def _codebook(values: np.ndarray, k: int = CODEBOOK_SIZE, iterations: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """A ``k``-entry float32 codebook for ``values`` and each value's index.

    Values with at most ``k`` distinct entries are kept exactly.  Otherwise a
    weighted 1-D k-means: each value weighs ``sqrt`` of the spacing of the
    sorted values around it (``N / 512`` ranks wide), i.e. ``density^-1/2``,
    so sparse tails keep entries; entries start at equal steps of cumulative
    weight, Lloyd runs to convergence (at most ``iterations``), entries left
    unused move to the worst-fitted values and Lloyd runs again.
    Returns ``(codebook (k,) float32 ascending, labels uint8 shaped like values)``.
    """
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0:
        return np.zeros(k, np.float32), np.zeros(np.shape(values), np.uint8)
    s = np.sort(v)
    distinct = s[np.concatenate([[True], s[1:] != s[:-1]])]
    if len(distinct) <= k:
        centres = distinct
    else:
        n = len(s)
        h = max(1, n // 1024)
        idx = np.arange(n)
        gap = s[np.minimum(idx + h, n - 1)] - s[np.maximum(idx - h, 0)]
        w = np.sqrt(np.maximum(gap, (s[-1] - s[0]) * 1e-9))
        cw = np.concatenate([[0.0], np.cumsum(w)])
        cwx = np.concatenate([[0.0], np.cumsum(w * s)])
        steps = (np.arange(k) + 0.5) / k * cw[-1]
        centres = np.unique(s[np.minimum(np.searchsorted(cw[1:], steps), n - 1)])
        centres = _lloyd_1d(s, cw, cwx, centres, iterations)
        if len(centres) < k:
            err = np.abs(distinct - centres[_nearest(centres, distinct)])
            worst = distinct[np.argsort(-err, kind="stable")[:k - len(centres)]]
            centres = _lloyd_1d(s, cw, cwx, np.unique(np.concatenate([centres, worst])), iterations)
    book = np.concatenate([centres, np.full(k - len(centres), centres[-1])]).astype(np.float32)
    labels = _nearest(book.astype(np.float64), v)
    return book, labels.astype(np.uint8).reshape(np.shape(values))


def _assign(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Index of the nearest row of ``c`` for each row of ``x`` (chunked)."""
    half = 0.5 * (c * c).sum(axis=1)
    labels = np.empty(len(x), np.int64)
    step = max(1, _CHUNK_PAIRS // len(c))
    for a in range(0, len(x), step):
        g = x[a:a + step] @ c.T
        np.subtract(half, g, out=g)  # |c|^2 / 2 - x.c: same order as |x - c|^2
        labels[a:a + step] = g.argmin(axis=1)
    return labels


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator,
            iterations: int = KMEANS_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's k-means of the rows of ``x`` (float32 ``(n, d)``) from ``k``
    distinct random rows; an emptied cluster moves to the farthest point.
    Returns ``(centroids (k, d) float32, labels (n,))``; ``n <= k`` keeps every row."""
    n = len(x)
    if n <= k:
        return x.copy(), np.arange(n)
    columns = np.ascontiguousarray(x.T)
    c = x[np.sort(rng.choice(n, k, replace=False))]
    for _ in range(iterations):
        labels = _assign(x, c)
        counts = np.bincount(labels, minlength=k)
        sums = np.stack([np.bincount(labels, weights=col, minlength=k) for col in columns], axis=1)
        used = counts > 0
        c = np.where(used[:, None], sums / np.maximum(counts, 1)[:, None], c).astype(np.float32)
        empty = np.flatnonzero(~used)
        if len(empty):
            dist = ((x - c[labels]) ** 2).sum(axis=1)
            c[empty] = x[np.argpartition(-dist, len(empty) - 1)[:len(empty)]]
    return c, _assign(x, c)


def _split_sizes(counts: np.ndarray, k: int) -> np.ndarray:
    """Shares of ``k`` palette entries for clusters of ``counts`` points
    (proportional, at least 1 and at most the count of each non-empty one,
    sum ``k``; needs ``k`` between the number of non-empty clusters and ``counts.sum()``)."""
    n = counts.sum()
    raw = k * counts / n
    sizes = np.minimum(np.maximum(np.floor(raw).astype(np.int64), counts > 0), counts)
    while sizes.sum() > k:
        spare = np.flatnonzero(sizes > 1)
        sizes[spare[np.argsort(-sizes[spare], kind="stable")][:int(sizes.sum() - k)]] -= 1
    while sizes.sum() < k:
        room = np.where(sizes < counts, raw - sizes, -np.inf)
        take = np.argsort(-room, kind="stable")[:int(k - sizes.sum())]
        sizes[take[np.isfinite(room[take])]] += 1
    return sizes


def _palette(x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The SH palette: ``(entries (m, d) float32, labels (n,))`` with ``m <= k``.

    Rows with at most ``k`` distinct values are kept exactly.  Otherwise
    :func:`_kmeans`, flat when ``n * k <= 2^24``, else in two levels (coarse
    clusters split by their share of ``k``) so the cost grows as
    ``n * sqrt(k)`` rather than ``n * k``.
    """
    n = len(x)
    rng = np.random.default_rng(_SEED)
    if n <= k:
        return x.copy(), np.arange(n)
    key = x.astype(np.float64) @ rng.uniform(0.5, 1.5, x.shape[1])
    if len(np.unique(key)) <= k:
        rows, labels = np.unique(x, axis=0, return_inverse=True)
        if len(rows) <= k:
            return rows, labels.ravel()
    if n * k <= _FLAT_KMEANS_PAIRS:
        return _kmeans(x, k, rng)
    coarse = 1 << math.ceil(math.log2(k) / 2)
    sample = x[np.sort(rng.choice(n, min(n, 64 * coarse), replace=False))]
    top = _assign(x, _kmeans(sample, coarse, rng)[0])
    counts = np.bincount(top, minlength=coarse)
    sizes = _split_sizes(counts, k)
    order = np.argsort(top, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(counts)])
    entries, labels, offset = [], np.empty(n, np.int64), 0
    for g in np.flatnonzero(counts):
        rows = order[bounds[g]:bounds[g + 1]]
        c, lab = _kmeans(x[rows], int(sizes[g]), rng)
        entries.append(c)
        labels[rows] = lab + offset
        offset += len(c)
    return np.concatenate(entries), labels


def _image(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(height, width, 4)`` uint8 with ``pixels`` (``(m, 4)``) first, zeros after."""
    out = np.zeros((height * width, 4), np.uint8)
    out[:len(pixels)] = pixels
    return out.reshape(height, width, 4)


def _webp(rgba: np.ndarray) -> bytes:
    """Lossless WebP of ``(H, W, 4)`` uint8 RGBA, keeping RGB under zero alpha."""
    buf = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buf, "WEBP", lossless=True, exact=True)
    return buf.getvalue()


def _u8(x) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _encode_quats(quats: np.ndarray) -> np.ndarray:
    q = normalized_quats(quats)
    n = len(q)
    big = np.abs(q).argmax(axis=1)
    q = q * np.where(q[np.arange(n), big] < 0, -1.0, 1.0)[:, None]
    cols = np.arange(3)[None, :] + (np.arange(3)[None, :] >= big[:, None])
    small = q[np.arange(n)[:, None], cols]
    out = np.empty((n, 4), np.uint8)
    out[:, :3] = _u8(255.0 * (small * (math.sqrt(2.0) / 2.0) + 0.5))
    out[:, 3] = 252 + big
    return out


def _encode(splats: SplatArrays) -> tuple[dict, dict]:
    """``(meta, {file name: WebP bytes})`` of a version 2 SOG."""
    n = splats.count
    width, height = _texture_size(n)
    if width > MAX_SIDE or height > MAX_SIDE:
        raise SplatFormatError(
            f"{n} splats need {width}x{height} images; SOG images are at most {MAX_SIDE} pixels a side")

    def image(pixels, w=width, h=height):
        return _webp(_image(pixels, w, h))

    opaque = np.full((n, 1), 255, np.uint8)
    images = {}

    l = np.asarray(splats.means, np.float64)
    l = np.sign(l) * np.log1p(np.abs(l))
    mins = l.min(axis=0) if n else np.zeros(3)
    maxs = l.max(axis=0) if n else np.zeros(3)
    span = maxs - mins
    u = np.rint((l - mins) / np.where(span > 0, span, 1.0) * 65535.0).astype(np.uint16)
    images["means_l.webp"] = image(np.concatenate([(u & 255).astype(np.uint8), opaque], axis=1))
    images["means_u.webp"] = image(np.concatenate([(u >> 8).astype(np.uint8), opaque], axis=1))

    images["quats.webp"] = image(_encode_quats(splats.quats))

    scale_book, scale_labels = _codebook(splats.scales)
    images["scales.webp"] = image(np.concatenate([scale_labels, opaque], axis=1))

    colour_book, colour_labels = _codebook(np.asarray(splats.sh_dc).reshape(n, 3))
    alpha = _u8(255.0 * sigmoid(splats.opacities))[:, None]
    images["sh0.webp"] = image(np.concatenate([colour_labels, alpha], axis=1))

    meta = {
        "version": 2,
        "asset": {"generator": "mlx3d"},
        "count": n,
        "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": colour_book.tolist(), "files": ["sh0.webp"]},
    }

    rest = np.asarray(splats.sh_rest, np.float32)
    k1 = rest.shape[1]
    if k1:
        entries, labels = _palette(np.ascontiguousarray(rest.reshape(n, 3 * k1)), palette_size(n))
        m = len(entries)
        rest_book, entry_bytes = _codebook(entries)
        pixels = np.concatenate(
            [entry_bytes.reshape(m * k1, 3), np.full((m * k1, 1), 255, np.uint8)], axis=1)
        images["shN_centroids.webp"] = image(pixels, 64 * k1, max(1, math.ceil(m / 64)))
        label_px = np.zeros((n, 4), np.uint8)
        label_px[:, 0] = labels & 255
        label_px[:, 1] = labels >> 8
        label_px[:, 3] = 255
        images["shN_labels.webp"] = image(label_px)
        meta["shN"] = {
            "count": m, "bands": _REST_PER_CHANNEL.index(k1), "codebook": rest_book.tolist(),
            "files": ["shN_centroids.webp", "shN_labels.webp"]}
    return meta, images


def write_sog(path: str | os.PathLike, splats: SplatArrays, *, fsync: bool = True) -> None:
    """Write ``splats`` as a version 2 SOG, atomically.

    A path ending in ``meta.json`` writes the unbundled layout: the images
    beside it under their standard names (``means_l.webp`` ...), each
    replaced atomically, ``meta.json`` last.  Any other path is a zip archive
    (stored, fixed timestamps: writing the same splats again gives the same
    bytes).  Everything is encoded before the first byte is written.
    """
    path = os.fspath(path)
    meta, images = _encode(splats)
    meta_bytes = json.dumps(meta, separators=(",", ":")).encode()
    if os.path.basename(path).lower().endswith(_META):
        directory = os.path.dirname(path)
        for name, data in images.items():
            with atomic_write(os.path.join(directory, name), "wb", fsync=fsync) as f:
                f.write(data)
        with atomic_write(path, "wb", fsync=fsync) as f:
            f.write(meta_bytes)
        return
    with atomic_write(path, "wb", fsync=fsync) as f:
        with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED) as z:
            for name, data in [(_META, meta_bytes), *images.items()]:
                info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
                info.external_attr = 0o644 << 16
                z.writestr(info, data)
