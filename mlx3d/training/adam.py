"""Adam with one learning rate per parameter and row-editable state.

Density control adds, removes and resets Gaussians; their Adam moments must
follow (3DGS zeroes the moments of new and reset rows). ``select``,
``append`` and ``reset_rows`` edit parameters and moments together, so there
is one place that keeps them aligned.
"""

from __future__ import annotations

import mlx.core as mx
import numpy as np


def all_finite(arrays, backend: str = "auto") -> mx.array:
    """A lazy bool scalar: True when no element of any array is NaN or infinite.

    On the CPU a threaded primitive reads each array once (its exponent bits).
    Elsewhere x * 0 is exactly 0 where x is finite and NaN where x is NaN or
    infinite, so the sum of those products is 0 exactly when everything is finite.
    """
    from ..render.rasterize import resolve_backend

    arrays = list(arrays)
    if not arrays:
        return mx.array(True)
    if resolve_backend(backend) == "cpu":
        from mlx3d import native

        from ..render.raster_cpu import get_num_threads

        return native.core().all_finite(arrays, get_num_threads())
    return mx.sum(mx.stack([mx.sum(a * 0) for a in arrays])) == 0


class Adam:
    """Adam (Kingma & Ba) over a dict of (N, ...) arrays, learning rate per name.

    betas and eps as in 3DGS (0.9, 0.999, 1e-15). ``lrs`` maps each parameter
    name to its learning rate; a name missing from ``lrs`` (or with lr 0) is
    not updated.

    On the CPU, ``update`` writes the new moments over the old ones' memory,
    and each new parameter over the old one's, where nothing else holds the
    old array (MLX's donation): an array you keep keeps its values.
    """

    def __init__(self, lrs: dict, betas=(0.9, 0.999), eps: float = 1e-15, backend: str = "auto"):
        from ..render.rasterize import resolve_backend

        self.lrs = dict(lrs)
        self.b1, self.b2 = betas
        self.eps = eps
        self.step_count = 0
        self.m: dict = {}
        self.v: dict = {}
        # 'cpu': one threaded pass per parameter (mlx3d._core.adam_step); else the MLX expression below
        self.backend = resolve_backend(backend)

    def update(self, params: dict, grads: dict) -> dict:
        """New params after one step (moments are created on first use).

        Drop your references to ``params`` before evaluating the result, as the
        trainer does, so that the new parameters can take over their memory.
        """
        self.step_count += 1
        c1 = 1.0 - self.b1**self.step_count
        c2 = 1.0 - self.b2**self.step_count
        out = dict(params)
        for name, g in grads.items():
            lr = self.lrs.get(name, 0.0)
            if not lr:
                continue
            p = params[name]
            m = self.m.get(name, mx.zeros_like(g))
            v = self.v.get(name, mx.zeros_like(g))
            if self.backend == "cpu" and p.dtype == g.dtype == m.dtype == mx.float32:
                from mlx3d import native

                from ..render.raster_cpu import get_num_threads

                out[name], m, v = native.core().adam_step(p, g, m, v, lr, self.b1, self.b2, self.eps, c1, c2, get_num_threads())
            else:
                m = self.b1 * m + (1 - self.b1) * g
                v = self.b2 * v + (1 - self.b2) * g * g
                out[name] = p - lr * (m / c1) / (mx.sqrt(v / c2) + self.eps)
            self.m[name], self.v[name] = m, v
        return out

    def select(self, keep: np.ndarray) -> None:
        """Keep moment rows ``keep`` (indices) for every parameter."""
        idx = mx.array(np.asarray(keep, dtype=np.int64))
        self.m = {k: v[idx] for k, v in self.m.items()}
        self.v = {k: v[idx] for k, v in self.v.items()}

    def append(self, count: int) -> None:
        """Append ``count`` zero moment rows (new Gaussians start with fresh state)."""
        for state in (self.m, self.v):
            for k, v in state.items():
                state[k] = mx.concatenate([v, mx.zeros((count,) + tuple(v.shape[1:]), dtype=v.dtype)], axis=0)

    def reset_rows(self, name: str, rows: np.ndarray) -> None:
        """Zero the moments of ``rows`` of parameter ``name`` (e.g. after an opacity reset)."""
        if name not in self.m:
            return
        mask = np.zeros(self.m[name].shape[0], bool)
        mask[np.asarray(rows, dtype=np.int64)] = True
        shape = (-1,) + (1,) * (self.m[name].ndim - 1)
        keep = mx.array(~mask).reshape(shape)
        self.m[name] = mx.where(keep, self.m[name], 0.0)
        self.v[name] = mx.where(keep, self.v[name], 0.0)

    def state_dict(self) -> dict:
        """numpy copy of the state (for checkpoints)."""
        out = {"step_count": np.array(self.step_count)}
        for prefix, state in (("m", self.m), ("v", self.v)):
            for k, v in state.items():
                out[f"{prefix}/{k}"] = np.array(v)
        return out

    def load_state_dict(self, state: dict) -> None:
        self.step_count = int(state["step_count"])
        self.m = {k[2:]: mx.array(v) for k, v in state.items() if k.startswith("m/")}
        self.v = {k[2:]: mx.array(v) for k, v in state.items() if k.startswith("v/")}
