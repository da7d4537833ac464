"""Run a computation once per thread count of the CPU kernels, restoring the setting afterwards."""

from mlx3d.render.raster_cpu import get_num_threads, set_num_threads


def per_thread_count(fn, counts=(1, 2, 3)) -> list:
    """[fn() with the CPU kernels on n threads, for n in counts]."""
    before = get_num_threads()
    try:
        results = []
        for n in counts:
            set_num_threads(n)
            results.append(fn())
        return results
    finally:
        set_num_threads(before)
