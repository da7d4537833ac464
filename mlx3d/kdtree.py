"""Exact k-d tree for k-nearest-neighbour queries on 3D points, in numpy alone.

The pure-numpy counterpart of the compiled ``mlx3d._core.KDTree``, with the
same methods and results: squared distances are evaluated in float64 from the
float32 coordinates as ``(dx*dx + dy*dy) + dz*dz`` (as ``csrc/kernels/knn.cpp``
does), each query keeps the k smallest (distance, index) pairs, skipping its
own point (``self_index``, -1 = none), and the mean sums the k distances in
float64 in increasing order.

Design (each step is vectorised over all points or a block of queries):

* Build: a complete binary tree of ``levels`` levels below the root. Each
  level splits every node at its median position along the widest axis of
  its tight bounding box (one partition of all points per level). Leaves
  are contiguous ranges of the tree-order points, of
  ``ceil(N / 2**levels) <= leaf_size`` points or one fewer. Runs of more
  than ``leaf_size`` identical points enter the tree as one point that
  stands for its members (the k + 1 of smallest index are read back in its
  place), so large duplicate clusters cost no more than a single point.
* Query, per block of queries: (1) a bound on each query's k-th squared
  distance from the points of the nearest node holding enough of them;
  (2) a walk down the tree over (query, node) pairs, keeping the nodes whose
  box lies within the bound; (3) per query, the few leaves nearest by box
  distance give a tight bound, then the other leaves within it are read
  (queries with similar leaf counts are padded into one 2D array) and the
  k smallest (distance, index) pairs of each row are kept.

Inputs are trusted (:mod:`mlx3d.neighbors` validates them): finite float32
(N, 3) points, 1 <= k <= the available neighbours, ``self_index`` entries in
[-1, N).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Iterator

import numpy as np

__all__ = ["KDTree"]

_BLOCK_QUERIES = 4096  # queries walked through the tree together
_MAX_PAIRS = 1 << 22  # (query, node) pairs of a walk beyond which its block is halved
_BLOCK_CANDIDATES = 1 << 18  # most padded candidate points evaluated at once
_INF = np.inf
_NO_INDEX = np.iinfo(np.int64).max


class KDTree:
    """k-d tree over (N, 3) float32 points; numpy counterpart of ``_core.KDTree``.

    Args:
        points: (N, 3) float32 (other dtypes are converted), finite, N >= 1.
        leaf_size: most points per leaf, >= 1.
    """

    def __init__(self, points: np.ndarray, leaf_size: int = 16) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
            raise ValueError(f"points must have shape (N, 3) with N >= 1, got shape {pts.shape}")
        if leaf_size < 1:
            raise ValueError(f"leaf_size must be >= 1, got leaf_size={leaf_size}")
        self._n = pts.shape[0]
        self._leaf_size = int(leaf_size)
        slots, self._dups = _duplicate_runs(pts, self._leaf_size)
        if slots is not None:
            pts = np.take(pts, slots, axis=0)
        self._counts = _level_counts(pts.shape[0], _tree_levels(pts.shape[0], self._leaf_size))
        order = _tree_order(pts, self._counts)
        self._perm = order if slots is None else slots.take(order)  # original index per tree position
        tree_pts = np.take(pts, order, axis=0)
        self._xyz = tree_pts.astype(np.float64).T.copy()  # (3, U) in tree order
        self._begin = np.concatenate([_starts(c) for c in self._counts])
        self._end = self._begin + np.concatenate(self._counts)
        self._lo, self._hi = _node_boxes(tree_pts, self._counts)
        self._split_axis, self._split_at = _splits(self._lo, self._hi, self._counts[-1].size - 1)
        self._leaf_xyz, self._leaf_index = _padded_leaves(self._xyz, self._perm, self._counts[-1], self._n)
        self._pad_leaf = self._leaf_index.shape[0] - 1  # the empty leaf that pads rows of leaves
        self._leaf_node0 = self._counts[-1].size - 1  # node id of leaf 0

    # ------------------------------------------------------------------ #
    # properties mirroring the compiled tree
    # ------------------------------------------------------------------ #
    @property
    def size(self) -> int:
        """Number of points N."""
        return self._n

    @property
    def leaf_size(self) -> int:
        return self._leaf_size

    @property
    def depth(self) -> int:
        """Number of tree levels."""
        return len(self._counts)

    @property
    def node_count(self) -> int:
        return int(self._begin.size)

    def order(self) -> np.ndarray:
        """Original point indices in tree (spatially coherent) order, int64 (N,)."""
        if self._dups is None:
            return self._perm.copy()
        return self._dups.expand(self._perm)

    # ------------------------------------------------------------------ #
    # queries
    # ------------------------------------------------------------------ #
    def query(
        self, queries: np.ndarray, k: int, self_index: np.ndarray | None = None, num_threads: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """k nearest points of each query.

        Args:
            queries: (M, 3) float32.
            k: neighbours per query.
            self_index: (M,) int64 point index skipped per query, -1 = none.
            num_threads: worker threads over blocks of queries, 0 = all CPUs
                (numpy releases the GIL inside its kernels).

        Returns:
            (indices int64 (M, k), squared distances float32 (M, k)), each row
            sorted by increasing distance, ties by index.
        """
        m = len(queries)
        idx = np.empty((m, k), dtype=np.int64)
        d2 = np.empty((m, k), dtype=np.float32)

        def write(rows: np.ndarray, kd2: np.ndarray, kidx: np.ndarray) -> None:
            order = np.lexsort((kidx, kd2), axis=1)
            idx[rows] = np.take_along_axis(kidx, order, axis=1)
            with np.errstate(over="ignore"):
                d2[rows] = np.take_along_axis(kd2, order, axis=1)

        self._run(queries, k, self_index, num_threads, True, write)
        return idx, d2

    def query_mean(
        self, queries: np.ndarray, k: int, self_index: np.ndarray | None = None, num_threads: int = 0
    ) -> np.ndarray:
        """Mean Euclidean distance to the k nearest points, float32 (M,).

        The k distances are summed in float64 in increasing order, then
        divided by k. Arguments as :meth:`query`.
        """
        out = np.empty(len(queries), dtype=np.float32)

        def write(rows: np.ndarray, kd2: np.ndarray, _: None) -> None:
            total = np.cumsum(np.sqrt(np.sort(kd2, axis=1)), axis=1)[:, -1]  # sequential sum, as knn.cpp
            with np.errstate(over="ignore"):
                out[rows] = total / k

        self._run(queries, k, self_index, num_threads, False, write)
        return out

    def query_kth(
        self, queries: np.ndarray, k: int, self_index: np.ndarray | None = None, num_threads: int = 0
    ) -> np.ndarray:
        """Euclidean distance to the k-th nearest point, float32 (M,). Arguments as :meth:`query`."""
        out = np.empty(len(queries), dtype=np.float32)

        def write(rows: np.ndarray, kd2: np.ndarray, _: None) -> None:
            with np.errstate(over="ignore"):
                out[rows] = np.sqrt(kd2.max(axis=1))

        self._run(queries, k, self_index, num_threads, False, write)
        return out

    # ------------------------------------------------------------------ #
    # blocks of queries
    # ------------------------------------------------------------------ #
    def _run(self, queries, k, self_index, num_threads, with_index, write) -> None:
        """Calls ``write(rows, d2 float64 (G, k), indices int64 (G, k) or None)``
        for every group of queries (rows unsorted within a group), from
        ``num_threads`` threads (0 = all CPUs) over blocks of queries."""
        q = np.asarray(queries, dtype=np.float32)
        own = None if self_index is None else np.asarray(self_index, dtype=np.int64)
        need = min(k + (own is not None), self._n)
        first = _first_leaves(need, self._counts[0][0] / self._counts[-1].size)

        def block(a: int) -> None:
            ob = None if own is None else own[a : a + _BLOCK_QUERIES]
            for rows, kd2, kidx in self._block(q[a : a + _BLOCK_QUERIES], k, ob, need, first, with_index):
                write(a + rows, kd2, kidx)

        starts = range(0, q.shape[0], _BLOCK_QUERIES)
        threads = min(len(starts), num_threads if num_threads > 0 else os.cpu_count() or 1)
        if threads <= 1:
            for a in starts:
                block(a)
            return
        pool = ThreadPoolExecutor(threads)
        try:
            for done in [pool.submit(block, a) for a in starts]:
                done.result()
        finally:
            pool.shutdown(wait=True, cancel_futures=True)  # on Ctrl-C: only the running blocks finish

    def _block(self, q, k, own, need, first, with_index):
        """Yields (rows, d2, indices) per group of one block of queries q (B, 3).

        A block whose walk would hold more than ``_MAX_PAIRS`` pairs (queries
        far from all points, with wide bounds) is run as two halves.
        """
        qb = q.astype(np.float64).T.copy()  # (3, B)
        bound = self._initial_bound(qb, k, own, need)
        walked = self._walk(qb, bound, _MAX_PAIRS if q.shape[0] > 1 else None)
        if walked is None:
            half = q.shape[0] // 2
            for a, b in ((0, half), (half, q.shape[0])):
                sub = None if own is None else own[a:b]
                for rows, kd2, kidx in self._block(q[a:b], k, sub, need, first, with_index):
                    yield a + rows, kd2, kidx
            return
        qi, leaf, box = walked
        count = np.bincount(qi, minlength=qb.shape[1])
        start = np.cumsum(count) - count
        by_count = np.argsort(count, kind="stable")
        for s, e in _groups(count[by_count], self._leaf_index.shape[1]):
            rows = by_count[s:e]
            cols = np.arange(int(count[rows[-1]]))
            src = np.minimum(start[rows][:, None] + cols, leaf.size - 1)
            real = cols < count[rows][:, None]
            leaves = np.where(real, leaf[src], self._pad_leaf)
            boxes = np.where(real, box[src], _INF)
            sub = None if own is None else own[rows]
            kd2, kidx = self._group_topk(qb[:, rows], k, sub, leaves, boxes, bound[rows], first, with_index)
            yield rows, kd2, kidx

    def _initial_bound(self, q: np.ndarray, k: int, own: np.ndarray | None, need: int) -> np.ndarray:
        """Upper bound (float64 (B,)) on each query's k-th squared distance.

        The k-th smallest distance to the points of the node reached by
        descending from the root, on the query's side of each split, down to
        the deepest level whose nodes all hold >= ``need`` points.
        """
        level = _bound_level(self._counts, need)
        cols = np.arange(q.shape[1])
        node = np.zeros_like(cols)
        flat = q.ravel()
        for _ in range(level):
            side = flat.take(self._split_axis.take(node) * q.shape[1] + cols) > self._split_at.take(node)
            node = 2 * node + 1 + side
        width = int(self._counts[level].max())
        pos = self._begin[node][:, None] + np.arange(width)
        valid = pos < self._end[node][:, None]
        pos = np.where(valid, pos, 0)
        xyz = (np.where(valid, c.take(pos), _INF) for c in self._xyz)
        index = np.where(valid, self._perm.take(pos), self._n)
        d2, _ = self._candidates(q, own, *xyz, index, k, with_index=False)
        return np.partition(d2, k - 1, axis=1)[:, k - 1]

    def _walk(self, q: np.ndarray, bound: np.ndarray, max_pairs: int | None):
        """(query, leaf) pairs whose leaf box lies within the query's bound.

        Returns query columns of q int64 (P,) (sorted), leaf numbers int64
        (P,) and the squared box distances float64 (P,); None as soon as
        there are more than ``max_pairs`` pairs (None: no limit).
        """
        qi = np.arange(q.shape[1])
        node = np.zeros_like(qi)
        box = np.zeros(qi.size)
        for _ in range(len(self._counts) - 1):
            qi = np.repeat(qi, 2)
            node = (2 * node[:, None] + np.array([1, 2])).ravel()
            box = self._box_d2(node, q, qi)
            keep = box <= bound.take(qi)
            qi, node, box = qi[keep], node[keep], box[keep]
            if max_pairs is not None and qi.size > max_pairs:
                return None
        return qi, node - self._leaf_node0, box

    def _box_d2(self, node: np.ndarray, q: np.ndarray, qi: np.ndarray) -> np.ndarray:
        """Squared float64 distances (P,) from queries ``qi`` (P,), columns of q
        (3, B), to the boxes of ``node`` (P,)."""
        total = np.zeros(node.shape, dtype=np.float64)
        for a in range(3):
            qa = q[a].take(qi)
            t = np.maximum(self._lo[a].take(node) - qa, qa - self._hi[a].take(node))
            np.maximum(t, 0.0, out=t)
            t *= t
            total += t
        return total

    def _group_topk(self, q, k, own, leaves, box, bound, first, with_index):
        """k smallest (d2, index) per query over the points of its ``leaves`` (G, W).

        Two stages: the ``first`` leaves nearest by (squared) ``box`` distance
        (G, W) give a tight bound, then only the other leaves within it are read.
        """
        if leaves.shape[1] <= first:
            return _topk(*self._leaf_d2(q, own, leaves, k, with_index), k)
        near = np.argsort(box, axis=1, kind="stable")
        leaves = np.take_along_axis(leaves, near, axis=1)
        box = np.take_along_axis(box, near, axis=1)
        kd2, kidx = _topk(*self._leaf_d2(q, own, leaves[:, :first], k, with_index), k)
        tight = np.minimum(kd2.max(axis=1), bound)
        rest = np.count_nonzero(box[:, first:] <= tight[:, None], axis=1)
        width = int(rest.max())
        if width == 0:
            return kd2, kidx
        more = np.where(np.arange(width) < rest[:, None], leaves[:, first : first + width], self._pad_leaf)
        d2, index = self._leaf_d2(q, own, more, k, with_index)
        d2 = np.concatenate([kd2, d2], axis=1)
        index = None if index is None else np.concatenate([kidx, index], axis=1)
        return _topk(d2, index, k)

    def _leaf_d2(self, q, own, leaves, k, with_index):
        """Candidates from the points of ``leaves`` (G, W) per query q (3, G); see
        :meth:`_candidates`."""
        g = leaves.shape[0]
        xyz = (c.take(leaves, axis=0).reshape(g, -1) for c in self._leaf_xyz)
        index = None
        if with_index or own is not None or self._dups is not None:
            index = self._leaf_index.take(leaves, axis=0).reshape(g, -1)
        return self._candidates(q, own, *xyz, index, k, with_index)

    def _candidates(self, q, own, px, py, pz, index, k, with_index):
        """Squared distances float64 (G, C') from queries q (3, G) to tree points
        given per axis (G, C), and their indices int64 (G, C') if ``with_index``.

        A point standing for a run of duplicates is replaced by the run's
        first k + 1 members (C' >= C); the query's own point gets +inf.
        """
        d2 = _dist2(px, py, pz, q)
        if self._dups is not None:
            d2, index = self._dups.expand_rows(d2, index, k + 1, self._n)
        if own is not None:
            d2[index == own[:, None]] = _INF
        return d2, index if with_index else None


# --------------------------------------------------------------------------- #
# selection
# --------------------------------------------------------------------------- #
def _dist2(px: np.ndarray, py: np.ndarray, pz: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Squared distances (G, C) from queries q (3, G) to points given per axis (G, C), as knn.cpp."""
    d2 = px - q[0][:, None]
    d2 *= d2
    t = py - q[1][:, None]
    t *= t
    d2 += t
    t = np.subtract(pz, q[2][:, None], out=t)
    t *= t
    d2 += t
    return d2


def _topk(d2: np.ndarray, index: np.ndarray | None, k: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Per row, the k smallest (d2, index) pairs, unsorted: (float64 (G, k), int64 (G, k) or None).

    Without ``index`` only the distances are kept (their values do not depend
    on how ties are broken). With it, a row whose k-th distance is shared by
    entries left out takes the tied entries of smallest index.
    """
    if index is None:
        return np.partition(d2, k - 1, axis=1)[:, :k], None
    part = np.argpartition(d2, k - 1, axis=1)[:, :k]
    kth = np.take_along_axis(d2, part[:, -1:], axis=1)
    tied = np.flatnonzero(np.count_nonzero(d2 <= kth, axis=1) > k)
    if tied.size:
        sub, at = d2[tied], kth[tied]
        key = np.where(sub < at, -1, np.where(sub == at, index[tied], _NO_INDEX))
        part[tied] = np.argpartition(key, k - 1, axis=1)[:, :k]
    return np.take_along_axis(d2, part, axis=1), np.take_along_axis(index, part, axis=1)


def _first_leaves(need: int, mean_leaf: float) -> int:
    """Leaves read in the first stage: about twice the ``need`` points, plus one."""
    return int(np.ceil(2 * need / mean_leaf)) + 1


def _groups(counts: np.ndarray, per_leaf: int) -> Iterator[tuple[int, int]]:
    """(start, stop) runs of sorted leaf ``counts`` (B,) to pad into one array.

    A run spans counts up to 25% above its first one and at most
    ``_BLOCK_CANDIDATES`` padded points.
    """
    a = 0
    while a < counts.size:
        c0 = int(counts[a])
        e = int(np.searchsorted(counts, c0 + c0 // 4, side="right"))
        e = min(e, a + max(1, _BLOCK_CANDIDATES // max(1, int(counts[e - 1]) * per_leaf)))
        yield a, e
        a = e


# --------------------------------------------------------------------------- #
# build
# --------------------------------------------------------------------------- #
_HASH = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9], dtype=np.uint64)


class _Duplicates:
    """Runs of identical points, each kept in the tree as its first member.

    Args:
        run_of: int64 (N + 1,), run number of each run's first member, else -1.
        start: int64 (R + 1,), offsets of each run in ``members``.
        members: int64, the members of each run in increasing index order.
    """

    def __init__(self, run_of: np.ndarray, start: np.ndarray, members: np.ndarray) -> None:
        self.run_of = run_of
        self.start = start
        self.members = members

    def expand(self, index: np.ndarray) -> np.ndarray:
        """``index`` (U,) with each run's first member replaced by all its members, int64 (N,)."""
        run = self.run_of.take(index)
        length = np.where(run >= 0, self.start.take(run + 1) - self.start.take(run), 1)
        source = np.concatenate([index, self.members])
        offset = np.where(run >= 0, index.size + self.start.take(run), np.arange(index.size))
        at = np.repeat(offset - (np.cumsum(length) - length), length) + np.arange(int(length.sum()))
        return source.take(at)

    def expand_rows(self, d2: np.ndarray, index: np.ndarray, cap: int, n: int):
        """Candidates (G, C) with each run's first member replaced by the run's
        first ``cap`` members at the same distance: (d2 float64 (G, C'), index int64 (G, C'))."""
        run = self.run_of.take(index)
        rows, cols = np.nonzero(run >= 0)
        if rows.size == 0:
            return d2, index
        run = run[rows, cols]
        per_row = np.bincount(rows, minlength=d2.shape[0])
        slot = np.arange(rows.size) - (np.cumsum(per_row) - per_row).take(rows)
        pos = self.start.take(run)[:, None] + np.arange(cap)
        valid = pos < self.start.take(run + 1)[:, None]
        extra_d2 = np.full((d2.shape[0], int(per_row.max()), cap), _INF)
        extra_index = np.full(extra_d2.shape, n, dtype=np.int64)
        extra_d2[rows, slot] = np.where(valid, d2[rows, cols][:, None], _INF)
        extra_index[rows, slot] = np.where(valid, self.members.take(np.minimum(pos, self.members.size - 1)), n)
        d2[rows, cols] = _INF  # the first member is among the expanded ones
        g = d2.shape[0]
        return (
            np.concatenate([d2, extra_d2.reshape(g, -1)], axis=1),
            np.concatenate([index, extra_index.reshape(g, -1)], axis=1),
        )


def _duplicate_runs(pts: np.ndarray, limit: int) -> tuple[np.ndarray | None, _Duplicates | None]:
    """Runs of more than ``limit`` identical points (found by hashing the coordinates).

    Returns (original indices int64 (U,) of the points the tree keeps, the
    runs), or (None, None) when there is no such run.
    """
    n = pts.shape[0]
    if n <= limit:
        return None, None
    same = pts + np.float32(0)  # -0.0 as +0.0
    bits = same.view(np.uint32).astype(np.uint64) * _HASH
    h = bits[:, 0] ^ bits[:, 1] ^ bits[:, 2]
    h ^= h >> np.uint64(29)
    order = np.argsort(h, kind="stable")  # equal hashes in increasing index order
    hs = h.take(order)
    first = np.flatnonzero(np.concatenate([[True], hs[1:] != hs[:-1]]))
    size = np.diff(np.append(first, n))
    big = size > limit
    if not big.any():
        return None, None
    run_at = np.repeat(np.arange(first.size), size)  # run of each sorted position
    p = np.take(same, order, axis=0)
    equal = (p == np.take(p, first.take(run_at), axis=0)).all(axis=1)
    big &= np.logical_and.reduceat(equal, first)  # a hash collision is not a run
    if not big.any():
        return None, None
    members = order[big.take(run_at)]
    heads = order.take(first[big])
    run_of = np.full(n + 1, -1, dtype=np.int64)
    run_of[heads] = np.arange(heads.size)
    start = np.concatenate([[0], np.cumsum(size[big])]).astype(np.int64)
    keep = np.ones(n, dtype=bool)
    keep[members] = False
    keep[heads] = True
    return np.flatnonzero(keep), _Duplicates(run_of, start, members)


def _tree_levels(n: int, leaf_size: int) -> int:
    """Levels below the root so that every leaf holds <= leaf_size points, and >= 1."""
    levels = 0
    while -(-n // (1 << levels)) > leaf_size and (2 << levels) <= n:
        levels += 1
    return levels


def _level_counts(n: int, levels: int) -> list[np.ndarray]:
    """Points per node, int64 (2**level,) per level; a left child gets the floor half."""
    counts = [np.array([n], dtype=np.int64)]
    for _ in range(levels):
        c = counts[-1]
        counts.append(np.stack([c // 2, c - c // 2], axis=1).ravel())
    return counts


def _bound_level(counts: list[np.ndarray], need: int) -> int:
    """Deepest level whose every node holds >= need points."""
    level = 0
    while level + 1 < len(counts) and counts[level + 1].min() >= need:
        level += 1
    return level


def _starts(c: np.ndarray) -> np.ndarray:
    """First tree-order position of each node of one level, int64."""
    return np.concatenate([[0], np.cumsum(c)[:-1]]).astype(np.int64)


def _tree_order(pts: np.ndarray, counts: list[np.ndarray]) -> np.ndarray:
    """Tree order of the points, int64 (N,): median splits on each node's widest axis.

    Level by level, each node's points are partitioned at its median
    position by the key ``node + 0.5 * (coordinate - lo) / extent`` (float64,
    non-decreasing in the coordinate within a node, below the next node's);
    the points are kept in tree order, so the gathers stay mostly local.
    """
    n = pts.shape[0]
    p = pts.copy()
    perm = np.arange(n, dtype=np.int64)
    flat3 = 3 * np.arange(n, dtype=np.int64)
    for level, c in enumerate(counts[:-1]):
        starts = _starts(c)
        lo = np.minimum.reduceat(p, starts, axis=0).astype(np.float64)
        ext = np.maximum.reduceat(p, starts, axis=0) - lo
        axis = np.argmax(ext, axis=1)  # the first widest axis, as knn.cpp
        nodes = np.arange(c.size)
        width = ext[nodes, axis]
        scale = np.divide(0.5, width, out=np.zeros_like(width), where=width > 0)
        base = nodes - lo[nodes, axis] * scale
        key = p.ravel().take(flat3 + np.repeat(axis, c)) * np.repeat(scale, c)
        key += np.repeat(base, c)
        if n // c.size > 1024:
            order = np.argpartition(key, _starts(counts[level + 1])[1:])
        else:
            order = np.argsort(key, kind="stable")
        p = np.take(p, order, axis=0)
        perm = perm.take(order)
    return perm


def _splits(lo: np.ndarray, hi: np.ndarray, inner: int) -> tuple[np.ndarray, np.ndarray]:
    """Split of each inner node: axis int64 (inner,) of widest gap-free extent and
    the midpoint float64 (inner,) between its children's boxes on that axis."""
    node = np.arange(inner)
    axis = np.argmax(hi[:, :inner] - lo[:, :inner], axis=0)
    at = 0.5 * (hi[axis, 2 * node + 1] + lo[axis, 2 * node + 2])
    return axis, at


def _node_boxes(p: np.ndarray, counts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Tight boxes (lo, hi), float64 (3, nodes + 1), of points p (N, 3) in tree order.

    Nodes are numbered level by level (children of i: 2i+1, 2i+2); the extra
    last node is empty (lo = +inf, hi = -inf: infinitely far from any query).
    """
    starts = _starts(counts[-1])
    lo = [np.minimum.reduceat(p, starts, axis=0)]
    hi = [np.maximum.reduceat(p, starts, axis=0)]
    for _ in counts[:-1]:
        lo.append(np.minimum(lo[-1][0::2], lo[-1][1::2]))
        hi.append(np.maximum(hi[-1][0::2], hi[-1][1::2]))
    lo = np.concatenate(lo[::-1] + [np.full((1, 3), _INF, np.float32)])
    hi = np.concatenate(hi[::-1] + [np.full((1, 3), -_INF, np.float32)])
    return lo.astype(np.float64).T.copy(), hi.astype(np.float64).T.copy()


def _padded_leaves(
    xyz: np.ndarray, perm: np.ndarray, counts: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Leaf points as rows: coordinates float64 (3, L + 1, S), indices int64 (L + 1, S).

    Padding, and the extra empty last leaf, have infinite coordinates and
    index ``n`` (the number of points), so they are never selected.
    """
    width = int(counts.max())
    valid = np.arange(width) < counts[:, None]
    pos = np.where(valid, _starts(counts)[:, None] + np.arange(width), 0)
    coords = np.full((3, counts.size + 1, width), _INF)
    coords[:, :-1] = np.where(valid, xyz[:, pos], _INF)
    index = np.full((counts.size + 1, width), n, dtype=np.int64)
    index[:-1] = np.where(valid, perm[pos], n)
    return coords, index
