"""Geometry operations under mlx3D's names: :func:`poisson_reconstruction`."""

from .geometry import poisson_reconstruction

__all__ = ["poisson_reconstruction"]
