"""The nearest points of a fixed set: the planner's k-d tree (the resampled path and pipe
axes, the centres of a scene's boxes).

It is pykdtree's tree: ``scipy.spatial`` takes 0.25-0.5 s to import (it brings
``scipy.sparse``, ``scipy.special`` and ``numpy.f2py`` with it), most of what ``hrm plan``
spends outside planning; pykdtree is a k-d tree alone (2 ms).  Answers are
``scipy.spatial.cKDTree.query``'s: distances and indices shaped like the queries (``k``
more when ``k > 1``), a missing neighbour (none within ``distance_upper_bound``) at
distance ``inf`` and index ``len(tree)``; indices are ``np.intp`` (pykdtree's are unsigned:
``v - 1`` would wrap).

The library spreads a query over threads with OpenMP; a planner runs beside a control loop
(the way back of a stopped run), so the process's OpenMP runs one thread unless
``OMP_NUM_THREADS`` says otherwise (set before the library loads).

>>> tree = PointTree(np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]]))
>>> d, i = tree.query(np.array([[[9.0, 0, 0]], [[21.0, 0, 0]]]), k=2)
>>> d.shape, i.tolist()
((2, 1, 2), [[[1, 0]], [[2, 1]]])
>>> tree.query(np.array([[50.0, 0, 0]]), distance_upper_bound=5.0)
(array([inf]), array([3]))
"""

from __future__ import annotations

import os

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")  # read when the library's OpenMP loads

from pykdtree.kdtree import KDTree  # after the thread count above


class PointTree:
    """A k-d tree of ``points`` (n, 3), n >= 1."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self._tree = KDTree(self.points)

    def __len__(self) -> int:
        return len(self.points)

    def query(
        self, q: np.ndarray, k: int = 1, distance_upper_bound: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices of the ``k`` nearest points to each of ``q`` (..., 3),
        nearest first: shaped ``q.shape[:-1]`` (``k`` = 1) or ``q.shape[:-1] + (k,)``."""
        q = np.ascontiguousarray(q, dtype=np.float64)
        lead = q.shape[:-1]
        flat = q.reshape(-1, 3)
        if distance_upper_bound is None:
            d, i = self._tree.query(flat, k=k)
        else:
            d, i = self._tree.query(flat, k=k, distance_upper_bound=float(distance_upper_bound))
        shape = lead if k == 1 else (*lead, k)
        return d.reshape(shape), i.astype(np.intp).reshape(shape)
