"""mlx3d: 3D Gaussian Splatting on MLX, for any CPU and Apple GPUs.

Subpackages are imported on demand so that ``import mlx3d`` stays cheap:

- ``mlx3d.splatting``: ``GaussianModel``, ``merge``, spherical harmonics;
- ``mlx3d.io``: splat files of every format (PLY, SPZ, SOG, ...), mesh PLY, atomic writes;
- ``mlx3d.transforms``: quaternions, Euler angles, affine maps on splats;
- ``mlx3d.neighbors`` / ``mlx3d.floaters``: k-NN search and floater removal;
- ``mlx3d.cli``: the ``mlx3d`` command.

Conventions (quaternion order, SH layout, axes) are written down once in
docs/reference/conventions.md and in the module docstrings they apply to.
"""

__version__ = "0.1.0"
