"""``python -m mlx3d``: the ``mlx3d`` command line (see ``mlx3d.cli``)."""

from .cli import main

if __name__ == "__main__":
    raise SystemExit(main())
