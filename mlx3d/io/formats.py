"""Every splat file format behind one pair of functions.

``read_splats(path)`` recognises the format by the file's content (its magic
bytes; the extension only decides where the content says nothing, as for
``.splat``) and ``write_splats(path, splats)`` picks it from the output's
extension.  Both go through :class:`SplatArrays`, the PLY convention described
in :mod:`mlx3d.io.codec`.

==================  ==============================  ======  =====  =============
format              extensions                      read    write  exact
==================  ==============================  ======  =====  =============
``ply``             ``.ply``                        yes     yes    yes
``compressed-ply``  ``.compressed.ply``             yes     yes    quantised
``spz``             ``.spz``                        yes     yes    quantised
``splat``           ``.splat``                      yes     yes    no SH, 8-bit
``ksplat``          ``.ksplat``                     yes     yes    quantised
``sog``             ``.sog``, ``meta.json``         yes     yes    quantised
``glb``             ``.glb``, ``.gltf``             yes     yes    yes [#]_
==================  ==============================  ======  =====  =============

.. [#] glTF stores scales and opacities activated (linear, alpha): float32 round
   trips within about 1e-7; extras of dtype int32, uint32 and float64 have no
   glTF type and are left out with a warning.

Each codec module states its quantisation bounds; :data:`FORMATS` holds what
the CLI and the Blender add-on list.
"""

from __future__ import annotations

import importlib
import inspect
import os
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import NonFiniteError, SplatFormatError
from .codec import SNIFF_BYTES
from .ply import NONFINITE_MODES, SplatArrays, _validated, read_splat_ply, write_splat_ply

__all__ = [
    "FORMATS",
    "SplatFormat",
    "detect_format",
    "format_for_path",
    "read_splats",
    "with_sh_degree",
    "write_splats",
]


@dataclass(frozen=True)
class SplatFormat:
    """One file format: its name, extensions and codec entry points.

    ``module`` is the :mod:`mlx3d.io` submodule holding ``reader`` /
    ``writer`` / ``sniffer`` (names of functions there; ``writer`` is ``None``
    for a read-only format).  ``exact`` formats keep every float32 value and
    the extra properties; the others quantise and drop extras (with a
    warning naming them).  ``max_sh_degree`` is the highest SH degree the
    format stores (higher ones are cut with a warning).
    """

    name: str
    description: str
    extensions: tuple[str, ...]
    module: str
    reader: str
    writer: str | None
    sniffer: str | None
    exact: bool
    max_sh_degree: int = 3

    def _function(self, attr: str):
        return getattr(importlib.import_module(f"mlx3d.io.{self.module}"), attr)

    def read(self, path: str) -> SplatArrays:
        """Read ``path`` with this format's codec."""
        return self._function(self.reader)(path)

    def options(self) -> tuple[str, ...]:
        """The keyword options of this format's writer besides ``fsync`` (e.g. SPZ's ``version``)."""
        if self.writer is None:
            return ()
        params = inspect.signature(self._function(self.writer)).parameters.values()
        return tuple(p.name for p in params if p.kind is p.KEYWORD_ONLY and p.name != "fsync")

    def write(self, path: str, splats: SplatArrays, *, fsync: bool = True, **options) -> None:
        """Write ``splats`` to ``path`` with this format's codec and its writer's ``options``."""
        if self.writer is None:
            raise SplatFormatError(f"{path}: {self.description} files can be read but not written")
        self.check_options(path, options)
        self._function(self.writer)(path, splats, fsync=fsync, **options)

    def check_options(self, path: str, options: dict) -> None:
        """Raise ``ValueError`` naming any of ``options`` this format's writer does not take."""
        unknown = sorted(set(options) - set(self.options()))
        if unknown:
            raise ValueError(
                f"{path}: {self.description} has no writing option {', '.join(map(repr, unknown))}"
                + (f"; its options are {', '.join(self.options())}" if self.options() else "; it takes none"))

    def sniff(self, head: bytes, path: str) -> bool:
        """Whether ``head`` (the first bytes of ``path``) is this format."""
        return self.sniffer is not None and bool(self._function(self.sniffer)(head, path))


#: The formats, in detection order (the most specific magic first).
FORMATS: tuple[SplatFormat, ...] = (
    SplatFormat("compressed-ply", "PlayCanvas compressed PLY", (".compressed.ply",),
                "compressed_ply", "read_compressed_ply", "write_compressed_ply", "sniff_compressed_ply", False),
    SplatFormat("ply", "3DGS PLY", (".ply",),
                "ply", "read_splat_ply", "write_splat_ply", "sniff_ply", True),
    SplatFormat("spz", "Niantic SPZ", (".spz",),
                "spz", "read_spz", "write_spz", "sniff_spz", False),
    SplatFormat("glb", "glTF KHR_gaussian_splatting", (".glb", ".gltf"),
                "gltf", "read_gltf", "write_gltf", "sniff_gltf", True),
    SplatFormat("sog", "PlayCanvas SOG", (".sog", "meta.json"),
                "sog", "read_sog", "write_sog", "sniff_sog", False),
    SplatFormat("ksplat", "GaussianSplats3D .ksplat", (".ksplat",),
                "ksplat", "read_ksplat", "write_ksplat", "sniff_ksplat", False, max_sh_degree=2),
    SplatFormat("splat", "antimatter15 .splat", (".splat",),
                "splat", "read_splat", "write_splat", None, False, max_sh_degree=0),
)

_BY_NAME = {f.name: f for f in FORMATS}


def _get(name: str) -> SplatFormat:
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(
            f"unknown splat format {name!r}; expected one of {', '.join(_BY_NAME)}") from None


def _by_extension(path: str) -> SplatFormat | None:
    lower = os.path.basename(path).lower()
    best = None
    for f in FORMATS:
        for ext in f.extensions:
            if lower.endswith(ext) and (best is None or len(ext) > best[0]):
                best = (len(ext), f)
    return best[1] if best else None


def _extension_list(writable: bool = False) -> str:
    return ", ".join(ext for f in FORMATS if f.writer or not writable for ext in f.extensions)


def format_for_path(path: str | os.PathLike, *, writable: bool = False) -> SplatFormat:
    """The format an output path's extension names (``.compressed.ply`` before ``.ply``).

    Raises :class:`SplatFormatError` for an unknown extension, or a read-only
    format when ``writable``.
    """
    path = os.fspath(path)
    fmt = _by_extension(path)
    if fmt is None:
        raise SplatFormatError(
            f"{path}: unknown splat file extension; expected one of {_extension_list(writable)}")
    if writable and fmt.writer is None:
        raise SplatFormatError(
            f"{path}: {fmt.description} files can be read but not written; "
            f"write one of {_extension_list(True)}")
    return fmt


def detect_format(path: str | os.PathLike) -> SplatFormat:
    """The format of an existing file, from its content, else its extension.

    Raises :class:`SplatFormatError` if the file is empty or neither its
    content nor its extension names a format; ``OSError`` if it cannot be read.
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise SplatFormatError(f"{path}: is a directory, not a splat file")
    with open(path, "rb") as f:
        head = f.read(SNIFF_BYTES)
    if not head:
        raise SplatFormatError(f"{path}: empty file (0 bytes)")
    for fmt in FORMATS:
        if fmt.sniff(head, path):
            return fmt
    fmt = _by_extension(path)
    if fmt is not None and fmt.sniffer is None:
        return fmt
    if fmt is not None:
        raise SplatFormatError(
            f"{path}: not a {fmt.description} file (its first bytes {head[:8]!r} are not that format's)")
    raise SplatFormatError(
        f"{path}: not a splat file this program reads (first bytes {head[:8]!r}); "
        f"readable: {_extension_list()}")


def _check_degree(degree):
    if degree is not None and (
            isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or not 0 <= degree <= 3):
        raise ValueError(f"sh_degree must be None or an integer 0-3; got {degree!r}")
    return degree


def with_sh_degree(splats: SplatArrays, degree: int | None) -> SplatArrays:
    """``splats`` with ``sh_rest`` cut to or zero-padded up to SH ``degree`` (0-3).

    ``None`` or the current degree returns ``splats`` itself.
    """
    if _check_degree(degree) is None:
        return splats
    k1 = (int(degree) + 1) ** 2 - 1
    rest = np.asarray(splats.sh_rest)
    if rest.shape[1] == k1:
        return splats
    out = np.zeros((rest.shape[0], k1, 3), np.float32)
    keep = min(k1, rest.shape[1])
    out[:, :keep] = rest[:, :keep]
    return SplatArrays(
        means=splats.means, scales=splats.scales, quats=splats.quats, opacities=splats.opacities,
        sh_dc=splats.sh_dc, sh_rest=out, extra=dict(splats.extra), comments=list(splats.comments),
        nonfinite_rows=splats.nonfinite_rows, dropped_rows=splats.dropped_rows)


_STANDARD = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def _nonfinite_rows(splats: SplatArrays) -> np.ndarray:
    n = splats.count
    bad = np.zeros(n, bool)
    if not n:
        return bad
    for key in _STANDARD:
        a = np.asarray(getattr(splats, key)).reshape(n, -1)
        if a.shape[1]:
            bad |= ~np.isfinite(a).all(axis=1)
    return bad


def _apply_nonfinite(path: str, splats: SplatArrays, mode: str) -> SplatArrays:
    """``read_splat_ply``'s ``nonfinite`` rule for the other formats."""
    bad = _nonfinite_rows(splats)
    count = int(bad.sum())
    if not count:
        return splats
    what = f"{count} of {splats.count} splat(s) contain NaN or Inf values (first: splat {int(np.argmax(bad))})"
    if mode == "error":
        raise SplatFormatError(
            f"{path}: {what}; pass nonfinite='drop' to discard them or nonfinite='keep' to load them as they are")
    splats.nonfinite_rows = count
    if mode == "keep":
        warnings.warn(f"{path}: kept {what}", UserWarning, stacklevel=3)
        return splats
    keep = ~bad
    warnings.warn(f"{path}: dropped {what}", UserWarning, stacklevel=3)
    return SplatArrays(
        **{k: np.asarray(getattr(splats, k))[keep] for k in _STANDARD},
        extra={k: np.asarray(v)[keep] for k, v in splats.extra.items()},
        comments=list(splats.comments), nonfinite_rows=count, dropped_rows=count)


def read_splats(
    path: str | os.PathLike,
    *,
    format: str | None = None,
    sh_degree: int | None = None,
    nonfinite: str = "error",
) -> SplatArrays:
    """Read a splat file of any supported format into :class:`SplatArrays`.

    Args:
        path: the file (for SOG also an unbundled ``meta.json``).
        format: a name from :data:`FORMATS` to skip detection; ``None``
            detects it from the content (:func:`detect_format`).
        sh_degree: SH degree of the result (``None`` keeps the file's; lower
            cuts, higher pads with zeros).
        nonfinite: NaN/Inf rule of :func:`~mlx3d.io.read_splat_ply`
            (``"error"``, ``"drop"`` or ``"keep"``), for every format.

    Raises:
        SplatFormatError: unknown, malformed or truncated file (the message
            names the file and the problem); no partial result is returned.
        ValueError: bad ``format``, ``sh_degree`` or ``nonfinite``.
        OSError: the file cannot be opened.
    """
    if nonfinite not in NONFINITE_MODES:
        raise ValueError(
            f"nonfinite must be one of {', '.join(map(repr, NONFINITE_MODES))}; got {nonfinite!r}")
    _check_degree(sh_degree)
    path = os.fspath(path)
    fmt = detect_format(path) if format is None else _get(format)
    if fmt.name == "ply":
        return read_splat_ply(path, sh_degree=sh_degree, nonfinite=nonfinite)
    splats = fmt.read(path)
    return with_sh_degree(_apply_nonfinite(path, splats, nonfinite), sh_degree)


def write_splats(
    path: str | os.PathLike,
    splats: SplatArrays,
    *,
    format: str | None = None,
    sh_degree: int | None = None,
    fsync: bool = True,
    **options,
) -> SplatFormat:
    """Write ``splats`` in the format the extension of ``path`` names, atomically.

    Args:
        path: output file; its extension picks the format unless ``format``
            is given.
        splats: what to write (checked first: a wrong shape or dtype raises
            ``ValueError`` naming the field before the disk is touched).
        format: a name from :data:`FORMATS`, overriding the extension.
        sh_degree: write this SH degree (cut or zero-padded); ``None`` keeps it.
        fsync: flush the file to disk before renaming it into place.
        options: the format's own writing options (``SplatFormat.options``:
            SPZ ``version``, ``.ksplat`` ``level``, ...); one the format does
            not have raises ``ValueError`` before anything is written.

    Returns the :class:`SplatFormat` written.  Quantising formats refuse
    NaN/Inf (:class:`~mlx3d.errors.NonFiniteError` naming the field) and warn
    naming the extra properties they cannot store.  On any error no file is
    written and an existing one is left as it was.
    """
    path = os.fspath(path)
    fmt = format_for_path(path, writable=True) if format is None else _get(format)
    if fmt.writer is None:
        raise SplatFormatError(f"{path}: {fmt.description} files can be read but not written")
    splats = with_sh_degree(splats, sh_degree)
    if splats.sh_degree > fmt.max_sh_degree:
        warnings.warn(
            f"{path}: {fmt.description} stores SH up to degree {fmt.max_sh_degree}; "
            f"degree {splats.sh_degree} is cut to {fmt.max_sh_degree}", UserWarning, stacklevel=2)
        splats = with_sh_degree(splats, fmt.max_sh_degree)
    fmt.check_options(path, options)
    if fmt.name == "ply":
        write_splat_ply(path, splats, fsync=fsync, **options)
        return fmt
    arrays = _validated(splats)
    if not fmt.exact:
        for key in _STANDARD:
            a = arrays[key]
            if a.size and not np.isfinite(a).all():
                row = int(np.argmax(~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)))
                raise NonFiniteError(
                    f"{path}: {key} has NaN or Inf (first at splat {row}); "
                    f"{fmt.description} cannot store them")
        if arrays["extra"]:
            warnings.warn(
                f"{path}: {fmt.description} cannot store the extra properties "
                f"{', '.join(arrays['extra'])}; they are not written", UserWarning, stacklevel=2)
    clean = SplatArrays(
        **{k: arrays[k] for k in _STANDARD}, extra=arrays["extra"] if fmt.exact else {},
        comments=list(splats.comments))
    fmt.write(path, clean, fsync=fsync, **options)
    return fmt

