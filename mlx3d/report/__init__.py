"""Measured reports: what accuracy costs on this machine (``mlx3d bench accuracy``).

- ``scene``: the built-in benchmark scene (ground-truth Gaussians rendered into a dataset);
- ``accuracy``: the measurements and the markdown report (``run_accuracy``);
- ``plot``: line and scatter plots drawn with Pillow;
- ``stats``: medians and spreads of repeated timings, Pareto choices.
"""
