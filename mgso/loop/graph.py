"""The Sim(3) pose graph of loop closure (issue 17, docs/loop.md "The pose graph").

Nodes are keyframes, each with its world-from-keyframe pose as a Sim(3) in mgso's convention (:mod:`mgso.geometry`):
a 4x4 ``[[s R, t], [0, 1]]`` mapping keyframe coordinates to world coordinates, ``X_w = s R X_k + t``. An edge
``(i, j)`` carries a relative Sim(3) measurement ``Z_ij ~= pose_i^-1 @ pose_j`` (keyframe j in keyframe i's
coordinates): odometry edges from the window's relative poses, loop edges from the verified revisits. Monocular scale
drifts, so every node and edge has 7 degrees of freedom.

**Cost.** An edge's residual is ``r_ij = log(Z_ij^-1 @ pose_i^-1 @ pose_j)``, a 7-vector, and the graph minimises
``1/2 sum r_ij^T W_ij r_ij`` (``W_ij`` the edge's information, diagonal), or with ``robust=k`` the Cauchy loss of the
whitened residual (``k^2/2 log(1 + |W^1/2 r|^2 / k^2)``), so an edge whose whitened residual is well above ``k`` pulls
with a force that falls off instead of growing. ``GraphResult.initial_error`` and ``final_error`` are this cost (GTSAM's
``NonlinearFactorGraph.error``) before and after.

**Library.** GTSAM (``gtsam`` on PyPI, BSD licence): it is made for the job. Its ``Similarity3`` is a Lie group
(``Expmap``/``Logmap``, analytic Jacobians of ``between``), ``BetweenFactorSimilarity3`` is exactly the residual above,
and ``LevenbergMarquardtOptimizer`` updates the poses on the Sim(3) manifold and solves each step by sparse
elimination (COLAMD ordering, multifrontal Cholesky), so a graph of a few hundred keyframes takes tens of milliseconds.
One caveat: the between factor linearises with the identity for the logarithm's derivative (GTSAM's default build;
``Similarity3::Logmap`` has no derivative), exact at zero residual. Consistent graphs are solved exactly; where edges
disagree the solution is off the exact least-squares minimum by a second-order term (1.2e-4 on a loop whose drift is
1.1 m; docs/loop.md has the table).
``scipy.optimize.least_squares`` would have needed our own manifold update, our own Jacobians and our own sparsity
pattern. g2o (what ORB-SLAM and LDSO use) and Ceres have Python wrappers on PyPI (``g2opy``, ``pyceres``); they were
not evaluated: GTSAM's wheel has the Sim(3) group, factor and solver in C++ and is a dependency already
(pyproject.toml).

**Conventions, ours and GTSAM's.** GTSAM's ``Similarity3(R, t, s)`` maps ``p -> s (R p + t)`` (its ``matrix()`` is
``[[R, t], [0, 1/s]]``), so our ``(R, t, s)`` is GTSAM's ``(R, t / s, s)``: :func:`to_gtsam` and :func:`from_gtsam`
are the only two places that convert. GTSAM's tangent order is (rotation 3, translation 3, log-scale 1); ours
(:func:`mgso.geometry.sim3_log`) is (translation 3, rotation 3, log-scale 1). With the conversion above the two
logarithms are the same vector, reordered (tests/loop/test_graph.py checks it), so an edge's information is given in
our order and reordered once, in :func:`_gtsam_noise`.

**Information.** ``information`` is a scalar (isotropic) or the 7 diagonal weights in our order. LDSO's pose graph
gives every edge identity information, odometry and loop alike (its ``info`` defaults to ``Mat77::Identity()``); the
loop closer does the same and scales a loop edge's information by ``loop.loop_edge_weight`` (mgso/config.py).

**Gauge.** A Sim(3) pose graph is unchanged when every pose is multiplied on the left by one Sim(3): 7 free degrees of
freedom. :meth:`PoseGraph.fix` holds a node at its value exactly (a GTSAM ``NonlinearEqualitySimilarity3``, not a
stiff prior: the fixed pose comes back bit for bit). Every connected part of the graph needs a fixed node;
:meth:`PoseGraph.optimize` says which node has none instead of letting the solver fail on a singular system.

**Threads.** Nothing here is global: each :meth:`PoseGraph.optimize` builds its own GTSAM graph, values and optimiser,
so the closer can build a fresh graph each time it solves, on its own thread. One PoseGraph must not be changed while
it is being optimised. GTSAM's Python wrapper does not release the interpreter lock: while its optimiser runs
(``GraphResult.solve_seconds``) the other Python threads of the process stop (measured: a Python loop on another
thread kept 2.7 % of its speed during a 0.32 s solve of 2000 keyframes). 500 keyframes take about 0.04 s inside GTSAM
and 0.08 s in all (docs/loop.md, profiles/pose_graph.py); where even that pause matters, solve in another process.

This module depends on numpy, gtsam and :mod:`mgso.geometry` only.
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass

import gtsam
import numpy as np

from mgso.geometry import SIM3_ROTATION_TOLERANCE as ROTATION_TOLERANCE     # re-exported: the tests' name
from mgso.geometry import check_sim3, orthonormalize, sim3_from_parts, sim3_inverse, sim3_to_parts

__all__ = ["EDGE_KINDS", "ROTATION_TOLERANCE", "Edge", "GraphResult", "PoseGraph", "check_sim3", "from_gtsam",
           "to_gtsam"]

#: The kinds of edge :meth:`PoseGraph.add_edge` takes; ``num_loop_edges`` counts the ``"loop"`` ones.
EDGE_KINDS = ("odometry", "loop")



# ----------------------------------------------------------------------------------------------- conversions
def to_gtsam(S: np.ndarray) -> gtsam.Similarity3:
    """Our Sim(3) ``[[s R, t], [0, 1]]`` (``X' = s R X + t``) as GTSAM's ``Similarity3(R, t / s, s)``
    (``X' = s (R X + t / s)``), its rotation re-orthonormalised (SVD). The inverse of :func:`from_gtsam`."""
    R, t, s = sim3_to_parts(S)
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-12:  # SVD only where needed: it is most of the conversion's cost
        R = orthonormalize(R)
    return gtsam.Similarity3(gtsam.Rot3(R), t / s, s)


def from_gtsam(g: gtsam.Similarity3) -> np.ndarray:
    """GTSAM's ``Similarity3`` (``X' = s (R X + t)``) as our 4x4 ``[[s R, s t], [0, 1]]``. The inverse of
    :func:`to_gtsam`."""
    s = float(g.scale())
    return sim3_from_parts(np.asarray(g.rotation().matrix()), s * np.asarray(g.translation(), dtype=np.float64), s)


def _gtsam_order(ours: np.ndarray) -> np.ndarray:
    """A 7-vector in our tangent order (translation, rotation, log-scale) in GTSAM's (rotation, translation,
    log-scale)."""
    return np.concatenate([ours[3:6], ours[0:3], ours[6:7]])


def _node_id(node_id, what: str) -> int:
    if isinstance(node_id, (bool, np.bool_)) or not isinstance(node_id, numbers.Integral):
        raise ValueError(f"{what}: node id {node_id!r} is not an integer")
    return int(node_id)


def _information(information, what: str) -> np.ndarray:
    """The edge's 7 diagonal weights in our order from a scalar or a 7-vector; positive and finite."""
    try:
        w = np.array(information, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: information {information!r} is not a number or a 7-vector") from None
    if w.ndim == 0:
        w = np.full(7, float(w))
    if w.shape != (7,):
        raise ValueError(f"{what}: information has shape {w.shape}; give a scalar or 7 weights (translation xyz, "
                         f"rotation xyz, log-scale)")
    if not np.all(np.isfinite(w)) or np.any(w <= 0.0):
        raise ValueError(f"{what}: information {w.tolist()} must be finite and > 0")
    return w


# ----------------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class Edge:
    """One measurement ``relative ~= pose_i^-1 @ pose_j`` (our 4x4 convention) with its diagonal ``information``
    (7 weights, our tangent order), ``kind`` (one of :data:`EDGE_KINDS`) and Cauchy width ``robust`` (None: plain
    least squares)."""

    i: int
    j: int
    relative: np.ndarray
    information: np.ndarray
    kind: str
    robust: float | None


@dataclass(frozen=True)
class GraphResult:
    """What :meth:`PoseGraph.optimize` found.

    ``poses``: the optimised 4x4 Sim(3) of every node (our convention); ``initial_poses``: the values it started from;
    ``initial_error`` / ``final_error``: the cost (module docstring) at those two; ``iterations``: Levenberg-Marquardt
    iterations run; ``seconds``: wall time of the whole ``optimize`` call (building GTSAM's graph included);
    ``solve_seconds``: the part of it inside GTSAM's optimiser, which holds Python's interpreter lock throughout (the
    module docstring, "Threads")."""

    poses: dict[int, np.ndarray]
    initial_poses: dict[int, np.ndarray]
    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    solve_seconds: float

    def correction(self, node_id: int, original_pose: np.ndarray | None = None) -> np.ndarray:
        """The Sim(3) that takes the node's ``original_pose`` (default: the value the solve started from) to its
        optimised one, applied on the left in world coordinates: ``pose_new = C @ original``, ``C = pose_new @
        original^-1``. A point of the map seeded from this keyframe moves by ``X_w' = C X_w`` (scale included)."""
        if node_id not in self.poses:
            raise ValueError(f"GraphResult.correction: node {node_id!r} is not in the graph")
        original = self.initial_poses[node_id] if original_pose is None else check_sim3(
            original_pose, f"GraphResult.correction({node_id}): original_pose")
        return self.poses[node_id] @ sim3_inverse(original)


# ----------------------------------------------------------------------------------------------- the graph
class PoseGraph:
    """Sim(3) pose graph: nodes are keyframes (world-from-keyframe Sim(3), 4x4 ``[[sR, t],[0,1]]``, our convention),
    edges relative Sim(3) measurements ``Z_ij ~= pose_i^-1 @ pose_j``; solved by GTSAM's Levenberg-Marquardt (the
    module docstring says the cost, the conventions, the information and the gauge)."""

    def __init__(self) -> None:
        self._poses: dict[int, np.ndarray] = {}
        self._edges: list[Edge] = []
        self._fixed: set[int] = set()

    # ------------------------------------------------------------------------------------------- building
    def add_node(self, node_id: int, pose: np.ndarray) -> None:
        """Add keyframe ``node_id`` with its world-from-keyframe Sim(3) ``pose`` as the initial value (replaces the
        value if the node exists; a fixed node stays at its latest value)."""
        nid = _node_id(node_id, "PoseGraph.add_node")
        self._poses[nid] = check_sim3(pose, f"PoseGraph.add_node({nid}): pose")

    def add_edge(self, i: int, j: int, relative: np.ndarray, *, information=1.0, kind: str = "odometry",
                 robust: float | None = None) -> None:
        """Add the measurement ``relative ~= pose_i^-1 @ pose_j`` between two added nodes.

        ``information``: a scalar (isotropic) or 7 diagonal weights in our tangent order (translation xyz, rotation
        xyz, log-scale); ``kind``: ``"odometry"`` or ``"loop"``; ``robust``: the Cauchy kernel's width in whitened
        residual units (None: plain least squares)."""
        i = _node_id(i, "PoseGraph.add_edge")
        j = _node_id(j, "PoseGraph.add_edge")
        what = f"PoseGraph.add_edge({i}, {j})"
        for n in (i, j):
            if n not in self._poses:
                raise ValueError(f"{what}: node {n} is unknown (add_node it first)")
        if i == j:
            raise ValueError(f"{what}: both ends are node {i} (an edge joins two different nodes)")
        if kind not in EDGE_KINDS:
            raise ValueError(f"{what}: kind {kind!r} is not one of {', '.join(EDGE_KINDS)}")
        if robust is not None:
            try:
                robust = float(robust)
            except (TypeError, ValueError):
                raise ValueError(f"{what}: robust {robust!r} is not a number (the Cauchy width, or None)") from None
            if not (math.isfinite(robust) and robust > 0.0):
                raise ValueError(f"{what}: robust = {robust} must be finite and > 0 (the Cauchy width, or None)")
        self._edges.append(Edge(i, j, check_sim3(relative, f"{what}: relative"), _information(information, what),
                                kind, robust))

    def fix(self, node_id: int) -> None:
        """Hold ``node_id`` at its value (all 7 degrees of freedom): the gauge. At least one node per connected part
        of the graph must be fixed."""
        nid = _node_id(node_id, "PoseGraph.fix")
        if nid not in self._poses:
            raise ValueError(f"PoseGraph.fix({nid}): node {nid} is unknown (add_node it first)")
        self._fixed.add(nid)

    # ------------------------------------------------------------------------------------------- reading
    @property
    def nodes(self) -> tuple[int, ...]:
        """Node ids in the order they were added."""
        return tuple(self._poses)

    @property
    def edges(self) -> list[Edge]:
        """The edge records in the order they were added (a copy of the list)."""
        return list(self._edges)

    @property
    def fixed(self) -> tuple[int, ...]:
        return tuple(n for n in self._poses if n in self._fixed)

    @property
    def num_loop_edges(self) -> int:
        return sum(1 for e in self._edges if e.kind == "loop")

    @property
    def num_odometry_edges(self) -> int:
        return sum(1 for e in self._edges if e.kind == "odometry")

    def pose(self, node_id: int) -> np.ndarray:
        """The node's current initial value (a copy)."""
        if node_id not in self._poses:
            raise ValueError(f"PoseGraph.pose: node {node_id!r} is unknown")
        return self._poses[node_id].copy()

    # ------------------------------------------------------------------------------------------- solving
    def _check_gauge(self) -> None:
        """Every connected part of the graph has a fixed node (else the system is singular)."""
        if not self._poses:
            raise ValueError("PoseGraph.optimize: the graph has no nodes")
        if not self._fixed:
            raise ValueError("PoseGraph.optimize: no fixed node (call fix(node_id) on one: the Sim(3) gauge has 7 "
                             "free degrees of freedom)")
        parent = {n: n for n in self._poses}

        def root(n: int) -> int:
            while parent[n] != n:
                parent[n] = parent[parent[n]]
                n = parent[n]
            return n

        for e in self._edges:
            parent[root(e.i)] = root(e.j)
        anchored = {root(n) for n in self._fixed}
        for n in self._poses:
            if root(n) not in anchored:
                size = sum(1 for m in self._poses if root(m) == root(n))
                raise ValueError(f"PoseGraph.optimize: node {n} (in a part of {size} node(s)) is joined to no fixed "
                                 f"node: add an edge to the rest of the graph or fix one of its nodes")

    def gtsam_problem(self, iterations: int = 50, relative_tolerance: float = 1e-10,
                      absolute_tolerance: float = 1e-12):
        """What :meth:`optimize` hands to GTSAM: ``(graph, values, params, key)`` (the factor graph, the initial
        values, the Levenberg-Marquardt settings and node id -> GTSAM key), after the same checks. For measuring
        GTSAM's part alone (profiles/pose_graph.py) and for inspecting the factors."""
        if isinstance(iterations, bool) or not isinstance(iterations, numbers.Integral) or iterations < 1:
            raise ValueError(f"PoseGraph.optimize: iterations = {iterations!r} must be an integer >= 1")
        self._check_gauge()
        key = {n: k for k, n in enumerate(self._poses)}
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for n, pose in self._poses.items():
            values.insert(key[n], to_gtsam(pose))
            if n in self._fixed:
                graph.add(gtsam.NonlinearEqualitySimilarity3(key[n], to_gtsam(pose)))
        for e in self._edges:
            graph.add(gtsam.BetweenFactorSimilarity3(key[e.i], key[e.j], to_gtsam(e.relative), _gtsam_noise(e)))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(int(iterations))
        params.setRelativeErrorTol(float(relative_tolerance))
        params.setAbsoluteErrorTol(float(absolute_tolerance))
        return graph, values, params, key

    def optimize(self, iterations: int = 50, *, relative_tolerance: float = 1e-10,
                 absolute_tolerance: float = 1e-12) -> GraphResult:
        """Levenberg-Marquardt on the Sim(3) manifold (GTSAM), at most ``iterations`` iterations (the closer passes
        ``loop.graph_iterations``); it stops earlier when the cost falls by less than ``relative_tolerance`` of
        itself or ``absolute_tolerance`` in one iteration (tight: a pose graph converges in a handful of iterations
        and the tests compare poses to 1e-8)."""
        t0 = time.perf_counter()
        graph, values, params, key = self.gtsam_problem(iterations, relative_tolerance, absolute_tolerance)
        t_solve = time.perf_counter()
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        solution = optimizer.optimize()
        solve_seconds = time.perf_counter() - t_solve
        poses = {n: from_gtsam(solution.atSimilarity3(key[n])) for n in self._poses}
        for n in self._fixed:  # exact by construction; keep the caller's matrix bit for bit
            poses[n] = self._poses[n].copy()
        return GraphResult(poses=poses, initial_poses={n: p.copy() for n, p in self._poses.items()},
                           initial_error=float(graph.error(values)), final_error=float(graph.error(solution)),
                           iterations=int(optimizer.iterations()), seconds=time.perf_counter() - t0,
                           solve_seconds=solve_seconds)


def _gtsam_noise(edge: Edge):
    """The edge's GTSAM noise model: diagonal precisions reordered to GTSAM's tangent order, wrapped in a Cauchy
    M-estimator when ``edge.robust`` is set."""
    base = gtsam.noiseModel.Diagonal.Precisions(_gtsam_order(edge.information))
    if edge.robust is None:
        return base
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(edge.robust), base)
