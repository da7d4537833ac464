"""Project exception types: one family per kind of bad input.

Each is a ``ValueError`` (or ``RuntimeError``) so callers that already catch
those keep working; messages name the offending file, field or value.
"""


class Mlx3dError(Exception):
    """Base class of every error raised on purpose by mlx3d."""


class SplatFormatError(Mlx3dError, ValueError):
    """A splat file (any format) is not readable as splats (the message names
    the file and says why); also raised for an unknown or unwritable format."""


class PlyFormatError(SplatFormatError):
    """A PLY file is not a readable 3DGS splat file (the message says why)."""


class NonFiniteError(Mlx3dError, ValueError):
    """Splat parameters contain NaN or Inf where finite values are required."""


class TransformError(Mlx3dError, ValueError):
    """A transform cannot be applied (singular, non-finite, wrong shape)."""


class ExtensionBuildError(Mlx3dError, ImportError):
    """The compiled extension ``mlx3d._core`` is missing or failed to load."""
