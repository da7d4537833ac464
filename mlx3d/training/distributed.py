"""Data-parallel training across processes on MLX's own distributed engine (``mx.distributed``).

Every rank holds the whole model. A step's batch of views is drawn the same
way on every rank (the same seed, the same draws) and dealt out by position:
rank ``r`` of ``W`` renders the views at positions ``r, r + W, ...``. Each
rank sums its views' gradients; one ``all_sum`` adds those sums (with the
losses, and the bilateral-grid gradients of every view of the batch) across
ranks, so every rank applies the same Adam update to the same parameters
and the models stay identical. The densification statistics stay per rank
between events and are summed (``all_sum``; radii ``all_max``) when an event
or a checkpoint reads them. Decisions drawn from random numbers (splits,
relocation, noise) use each rank's copy of one seeded generator, so they
agree too.

Ranks compare a digest of their state (step, parameters, optimizer step) at
every density event and checkpoint, and of their configuration and dataset
at the start; any difference stops every rank with a :class:`DistributedError`
that names the ranks. A rank that dies makes the others' next collective
fail; that too becomes a :class:`DistributedError`. Checkpoints and outputs
are written by rank 0 alone, atomically, so the last checkpoint stays intact.

Launch with ``mlx.launch`` (ring or JACCL backend) or ``mpirun``;
:func:`launched` recognises their environments.
"""

from __future__ import annotations

import hashlib
import os

import mlx.core as mx
import numpy as np

from ..errors import Mlx3dError

#: Environment variables that a launcher sets in each process it starts: mlx.launch (ring, JACCL) and MPI implementations.
LAUNCHER_ENV = ("MLX_RANK", "OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK")


class DistributedError(Mlx3dError, RuntimeError):
    """Ranks cannot go on together (a rank died, or their states differ); the message says which and where."""


def launched() -> bool:
    """Whether this process was started by a distributed launcher (mlx.launch or mpirun)."""
    return any(name in os.environ for name in LAUNCHER_ENV)


def init(backend: str = "any") -> "Ranks":
    """The ranks of this run: ``mx.distributed.init`` with ``backend`` ('any', 'ring', 'jaccl', 'mpi', 'nccl').

    Raises DistributedError when the backend cannot start (e.g. not under a launcher)."""
    try:
        group = mx.distributed.init(strict=True, backend=backend)
    except (RuntimeError, ValueError) as exc:
        raise DistributedError(f"cannot start MLX's distributed backend {backend!r}: {exc} "
                               "(run under mlx.launch or mpirun; see docs/guides/distributed.md)") from exc
    return Ranks(group)


class Ranks:
    """A group of ranks training one model together (``group`` an ``mx.distributed.Group``).

    Collectives are wrapped so that a lost rank becomes a DistributedError; ``bytes_sent``
    and ``seconds`` count this rank's gradient traffic (the payload of each ``sum``).
    """

    def __init__(self, group):
        self.group = group
        self.rank = group.rank()
        self.size = group.size()
        self.bytes_sent = 0
        self.seconds = 0.0

    def __repr__(self) -> str:
        return f"Ranks(rank={self.rank}, size={self.size})"

    def positions(self, batch_size: int) -> list:
        """The positions in a batch of ``batch_size`` views that this rank renders."""
        return list(range(self.rank, batch_size, self.size))

    def _run(self, what: str, fn, *arrays):
        import time

        t0 = time.perf_counter()
        try:
            out = fn(*arrays, group=self.group)
            mx.eval(out)
        except RuntimeError as exc:
            raise DistributedError(f"rank {self.rank} of {self.size}: lost contact with another rank during {what} ({exc})") from exc
        self.seconds += time.perf_counter() - t0
        return out

    def sum(self, flat: mx.array, what: str = "the gradient sum") -> mx.array:
        """``flat`` summed over the ranks (the same array on every rank)."""
        self.bytes_sent += flat.nbytes
        return self._run(what, mx.distributed.all_sum, flat)

    def host_sum(self, values: np.ndarray, what: str) -> np.ndarray:
        """A float64 numpy array summed over the ranks (computed on the CPU)."""
        with mx.stream(mx.cpu):
            return np.array(self._run(what, mx.distributed.all_sum, mx.array(np.asarray(values, np.float64), dtype=mx.float64)))

    def host_max(self, values: np.ndarray, what: str) -> np.ndarray:
        """A float64 numpy array's elementwise maximum over the ranks."""
        with mx.stream(mx.cpu):
            return np.array(self._run(what, mx.distributed.all_max, mx.array(np.asarray(values, np.float64), dtype=mx.float64)))

    def broadcast(self, arrays: dict, what: str) -> dict:
        """Rank 0's ``arrays`` (name -> array) on every rank; other ranks' values are ignored, shapes may differ."""
        shapes = {k: tuple(v.shape) for k, v in arrays.items()}
        sizes = self.host_sum(np.array([np.prod(s) if self.rank == 0 else 0 for s in shapes.values()], np.float64),
                              f"{what} (sizes)")
        out = {}
        for (name, shape), size in zip(shapes.items(), sizes.astype(np.int64)):
            value = arrays[name] if self.rank == 0 else mx.zeros((int(size),), dtype=arrays[name].dtype)
            if self.rank == 0 and value.size != size:
                raise DistributedError(f"{what}: {name} has {value.size} values on rank 0, {size} summed")
            total = self._run(what, mx.distributed.all_sum, value.reshape(-1))
            rows = int(size) // max(int(np.prod(shape[1:])), 1) if len(shape) > 1 else int(size)
            out[name] = total.reshape((rows,) + shape[1:]) if len(shape) > 1 else total
        return out

    def check_same(self, what: str, digest: bytes) -> None:
        """Raise DistributedError on every rank unless every rank's ``digest`` (of ``what``) is the same."""
        mine = np.frombuffer(hashlib.blake2b(digest, digest_size=16).digest(), np.uint8).astype(np.float64)
        with mx.stream(mx.cpu):
            gathered = np.array(self._run(f"the check of {what}", mx.distributed.all_gather, mx.array(mine[None])))
        differ = [r for r in range(self.size) if not np.array_equal(gathered[r], gathered[0])]
        if differ:
            raise DistributedError(f"ranks {differ} hold a different {what} from rank 0; stopping every rank "
                                   "(start them from the same data, version and settings)")


def digest(*parts) -> bytes:
    """Bytes identifying ``parts`` (numpy/MLX arrays, numbers, strings), for :meth:`Ranks.check_same`."""
    h = hashlib.blake2b(digest_size=32)
    for part in parts:
        if isinstance(part, mx.array):
            part = np.array(part)
        if isinstance(part, np.ndarray):
            h.update(str((part.dtype.str, part.shape)).encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(repr(part).encode())
    return h.digest()
