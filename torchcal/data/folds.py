"""Cross-validation folds that keep near-twin poses together.

A random row split of a grid or a sweep leaves, for every held-out pose, a training pose that
differs only in a joint that barely moves the tool point (a wrist swept in 10 deg steps), often
measured seconds apart. Any flexible model then scores well on the held-out part by
interpolating its neighbours, and the score says nothing about new poses. So folds here are:

* ``grouped`` (default): poses are embedded in a joint space scaled by each joint's lever arm
  at the tool point (:func:`pose_embedding`, metres: the distance between two embedded poses
  approximates how far the nominal tool point moves between them), clustered by k-means into
  ``groups`` regions of configuration space (default 20, four per fold), groups holding poses
  closer than ``twin_radius_mm`` merged, and whole groups assigned to folds. A held-out fold is
  thus a set of whole regions the fit has not seen, as poses of a new series are: on UR10
  series A (a grid), a residual MLP passes 5-fold CV over groups of 10 poses and over time blocks
  (15-30 % better than geometry) yet makes series C worse (0.629 against 0.575 mm); over 20
  regions it gains nothing beyond noise and is rejected;
* ``blocks``: contiguous blocks of measurement order (the file's row order, or a time column),
  for data that drifts while it is measured;
* ``random``: a seeded random permutation of rows; available for comparison, never a default.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.data.splits import SPLITS


@dataclass(frozen=True)
class Folds:
    """Fold of every pose and how it was made.

    Attributes:
        fold: ``(n,)`` fold index of each pose, ``0..k-1``.
        kind: ``grouped``, ``blocks`` or ``random``.
        description: one line naming the protocol (printed next to every CV number).
        groups: ``(n,)`` configuration group of each pose (``grouped`` only).
    """

    fold: np.ndarray
    kind: str
    description: str
    groups: np.ndarray | None = None

    @property
    def k(self) -> int:
        return int(self.fold.max()) + 1 if len(self.fold) else 0

    @property
    def label(self) -> str:
        """``5-fold grouped cross-validation`` (blocked, random): the protocol in a few words."""
        kind = {"grouped": "grouped", "blocks": "blocked (contiguous measurement order)", "random": "random-row"}
        return f"{self.k}-fold {kind.get(self.kind, self.kind)} cross-validation"

    def splits(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """``(train, held-out)`` pose indices of each fold."""
        return [(np.flatnonzero(self.fold != f), np.flatnonzero(self.fold == f)) for f in range(self.k)]

    def units(self) -> np.ndarray:
        """Independent units for standard errors: the groups, or the folds' blocks, or poses."""
        if self.groups is not None:
            return self.groups
        if self.kind == "blocks":
            return self.fold
        return np.arange(len(self.fold))


def joint_lever_arms(robot, q: torch.Tensor, max_poses: int = 500, step_rad: float = 1e-6) -> np.ndarray:
    """RMS over poses of ``|d p_tcp / d q_j|`` (m/rad) of the nominal robot, per joint.

    A joint whose rotation barely moves the tool point (a wrist roll with the tool on its axis)
    gets a small weight, so poses that differ only in it are near-twins for position data.
    """
    q = q.detach().to("cpu", torch.float64)
    if len(q) > max_poses:
        q = q[torch.linspace(0, len(q) - 1, max_poses).round().long()]
    arms = []
    for j in range(q.shape[1]):
        dq = torch.zeros_like(q)
        dq[:, j] = step_rad
        dp = (robot.tcp_position(q + dq) - robot.tcp_position(q - dq)) / (2 * step_rad)
        arms.append(float(dp.norm(dim=-1).pow(2).mean().sqrt()))
    return np.asarray(arms)


def pose_embedding(robot, q: torch.Tensor, arms: np.ndarray | None = None) -> np.ndarray:
    """``(n, 2N)`` points (m) whose distances approximate tool-point displacement between poses.

    Joint ``j`` contributes ``w_j (cos q_j, sin q_j)``, ``w_j`` its lever arm
    (:func:`joint_lever_arms`): the chord ``2 w_j sin(dq/2)`` is ``w_j |dq|`` for small steps and
    a full turn of a continuous joint is no distance at all.
    """
    arms = joint_lever_arms(robot, q) if arms is None else arms
    qn = q.detach().to("cpu", torch.float64).numpy()
    return np.concatenate([arms * np.cos(qn), arms * np.sin(qn)], axis=1)


def _merge_twins(labels: np.ndarray, points: np.ndarray, radius_m: float) -> np.ndarray:
    """Union of groups that hold two poses closer than ``radius_m`` (so no twin pair straddles folds)."""
    from scipy.sparse.csgraph import connected_components
    from sklearn.neighbors import radius_neighbors_graph

    if radius_m <= 0 or len(points) < 2:
        return labels
    graph = radius_neighbors_graph(points, radius_m, mode="connectivity", include_self=False)
    n_groups = int(labels.max()) + 1
    rows, cols = graph.nonzero()
    import scipy.sparse as sp

    n = len(labels)
    # bipartite graph pose <-> group: poses join their group and their twins' groups
    edges = sp.coo_matrix((np.ones(n + len(rows)), (np.concatenate([np.arange(n), rows]),
                                                      np.concatenate([labels, labels[cols]]))),
                          shape=(n, n_groups)).tocsr()
    joint = sp.bmat([[None, edges], [edges.T, None]])
    _, comp = connected_components(joint, directed=False)
    _, merged = np.unique(comp[:n], return_inverse=True)
    return merged


def _assign_groups(groups: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Whole groups to ``k`` folds of nearly equal size (largest groups first, seeded tie order)."""
    rng = np.random.default_rng(seed)
    ids, sizes = np.unique(groups, return_counts=True)
    order = np.lexsort((rng.permutation(len(ids)), -sizes))
    load = np.zeros(k, dtype=np.int64)
    fold_of_group = np.empty(len(ids), dtype=np.int64)
    for i in order:
        f = int(np.argmin(load))
        fold_of_group[i] = f
        load[f] += sizes[i]
    return fold_of_group[np.searchsorted(ids, groups)]


def grouped_folds(robot, q: torch.Tensor, k: int = 5, *, seed: int = 0, groups: int = 20,
                  twin_radius_mm: float = 2.0) -> Folds:
    """Folds of configuration groups (see the module docstring); at most ``n / 2`` groups."""
    from sklearn.cluster import KMeans
    from sklearn.exceptions import ConvergenceWarning
    from threadpoolctl import threadpool_limits

    n = len(q)
    points = pose_embedding(robot, q)
    n_clusters = int(max(k, min(groups, n // 2)))
    # one OpenMP thread: k-means sums its clusters thread by thread, so the folds would depend on the
    # cores of the process that makes them (this one or a worker, this machine or another)
    with warnings.catch_warnings(), threadpool_limits(1):
        # fewer distinct configurations than clusters: refused below with a message that says so
        warnings.simplefilter("ignore", ConvergenceWarning)
        labels = KMeans(n_clusters=n_clusters, n_init=1, random_state=seed).fit_predict(points)
    group_of = _merge_twins(labels, points, twin_radius_mm * 1e-3)  # `groups` was the requested count
    n_groups = int(group_of.max()) + 1
    if n_groups < k:
        raise DataError(f"grouped cross-validation needs at least {k} configuration groups; these {n} poses form "
                        f"{n_groups} (near-twins within {twin_radius_mm:g} mm of tool motion are one group): "
                        "measure more distinct configurations or use split=blocks")
    fold = _assign_groups(group_of, k, seed)
    desc = (f"{k}-fold CV over {n_groups} configuration regions (k-means on lever-arm-weighted joints; "
            f"whole regions held out, twins within {twin_radius_mm:g} mm merged)")
    return Folds(fold, "grouped", desc, group_of)


def block_folds(order: np.ndarray, k: int = 5) -> Folds:
    """``k`` contiguous blocks of ``order`` (row order, time stamps: any sortable key per pose)."""
    order = np.asarray(order)
    n = len(order)
    rank = np.empty(n, dtype=np.int64)
    rank[np.argsort(order, kind="stable")] = np.arange(n)
    fold = (rank * k) // max(n, 1)
    return Folds(fold, "blocks", f"{k}-fold CV over contiguous blocks of measurement order")


def random_folds(n: int, k: int = 5, *, seed: int = 0) -> Folds:
    """Seeded random row folds; near-twins leak across them (comparison only)."""
    fold = np.random.default_rng(seed).permutation(n) % k
    return Folds(fold, "random", f"{k}-fold CV over random rows (near-twin poses may leak across folds)")


def make_folds(kind: str, robot, q: torch.Tensor, *, k: int = 5, seed: int = 0, order: np.ndarray | None = None,
               groups: int = 20, twin_radius_mm: float = 2.0, series: np.ndarray | torch.Tensor | None = None) -> Folds:
    """Folds of ``kind`` for poses ``q (n, N)`` rad; ``order`` defaults to the row order.

    ``series``: ``(n,)`` index of each pose's measurement series (:mod:`torchcal.data.series`);
    with several, each series is split on its own (:func:`series_folds`).
    """
    n = len(q)
    if kind not in SPLITS:
        raise DataError(f"unknown split '{kind}'; choose one of {', '.join(SPLITS)}")
    if n < 2 * k:
        raise DataError(f"{k}-fold cross-validation needs at least {2 * k} poses, got {n}")
    if series is not None and kind != "random" and len(np.unique(np.asarray(series))) > 1:
        return series_folds(kind, robot, q, np.asarray(series), k=k, seed=seed, order=order, groups=groups,
                            twin_radius_mm=twin_radius_mm)
    if kind == "random":
        return random_folds(n, k, seed=seed)
    if kind == "blocks":
        return block_folds(np.arange(n) if order is None else order, k)
    return grouped_folds(robot, q, k, seed=seed, groups=groups, twin_radius_mm=twin_radius_mm)


def series_folds(kind: str, robot, q: torch.Tensor, series: np.ndarray, *, k: int = 5, seed: int = 0,
                 order: np.ndarray | None = None, groups: int = 20, twin_radius_mm: float = 2.0) -> Folds:
    """Folds of pooled series: each series split on its own, fold ``f`` the union of every series' fold ``f``.

    ``grouped``: each series' configuration regions (its share of ``groups``, at least ``k``) are
    clustered and assigned within it, so no region straddles two series and every held-out fold
    holds regions of each series (its frame stays identified by the rest). ``blocks``: each
    series' measurement order cut into ``k`` blocks (order is defined within a file only).
    Near-twin configurations measured in two series are not merged: they are different set-ups.
    """
    n = len(q)
    order = np.arange(n) if order is None else np.asarray(order)
    fold = np.empty(n, dtype=np.int64)
    group_of = np.empty(n, dtype=np.int64) if kind == "grouped" else None
    ids = np.unique(series)
    offset = 0
    for s in ids:
        rows = np.flatnonzero(series == s)
        if len(rows) < 2 * k:
            raise DataError(f"{k}-fold cross-validation needs at least {2 * k} poses in each series; "
                            f"series {int(s) + 1} has {len(rows)}")
        if kind == "blocks":
            fold[rows] = block_folds(order[rows], k).fold
            continue
        share = max(k, round(groups * len(rows) / n))
        part = grouped_folds(robot, q[torch.as_tensor(rows)], k, seed=seed, groups=share, twin_radius_mm=twin_radius_mm)
        assert part.groups is not None and group_of is not None
        fold[rows] = part.fold
        group_of[rows] = part.groups + offset
        offset += int(part.groups.max()) + 1
    if kind == "blocks":
        return Folds(fold, "blocks", f"{k}-fold CV over contiguous blocks of measurement order within each of "
                                     f"{len(ids)} series")
    desc = (f"{k}-fold CV over {offset} configuration regions within each of {len(ids)} series (k-means on "
            f"lever-arm-weighted joints per series; whole regions held out, twins within {twin_radius_mm:g} mm merged)")
    return Folds(fold, "grouped", desc, group_of)
