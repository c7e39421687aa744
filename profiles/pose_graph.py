"""Time of one Sim(3) pose-graph solve (:class:`mgso.loop.graph.PoseGraph`, GTSAM's Levenberg-Marquardt) at the size
of a long run: ``--nodes`` keyframes on a path that goes ``--laps`` times around a room (a circle of 3 m, the height
and the scale swinging), each keyframe joined to its ``--neighbours`` previous ones by odometry edges (the relative
true poses, each off by a small Sim(3): drift that accumulates), ``--loops`` loop edges from the true poses between a
keyframe of the last lap and the same place on an earlier lap; the first keyframe fixed, the drifted chain as the
initial values.

    python profiles/pose_graph.py [--nodes 500] [--neighbours 3] [--loops 5] [--laps 5] [--repeats 3]
                                  [--iterations 50] [--drift 0.001] [--seed 0]

Prints one JSON line: ``nodes``, ``edges``, ``odometry_edges``, ``loop_edges``, ``seconds`` (median of the repeats
of ``optimize()``, building GTSAM's graph included), ``seconds_all``, ``solve_seconds`` (median of the part inside
GTSAM's optimiser), ``iterations``, ``initial_error``,
``final_error``, the largest position error against the true path before and after (``drift_max_m``,
``solved_max_m``), ``other_thread_share``: how much of its solo speed a pure-Python loop on this thread keeps while
``optimize()`` runs on another (1: the call leaves the interpreter to other threads; 0: it holds the GIL throughout),
and ``other_thread_share_in_gtsam``: the same during GTSAM's Levenberg-Marquardt alone.
The development machine is shared: the load average is in the output.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso.geometry import sim3_exp, sim3_from_parts, sim3_inverse  # noqa: E402
from mgso.loop.graph import PoseGraph  # noqa: E402


def true_path(n: int, laps: int) -> list[np.ndarray]:
    poses = []
    for k in range(n):
        a = 2.0 * np.pi * laps * k / n
        centre = np.array([3.0 * np.cos(a), 0.3 * np.sin(3 * a), 3.0 * np.sin(a)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z], axis=1)
        poses.append(sim3_from_parts(R, centre, float(np.exp(0.3 * np.sin(a / laps)))))
    return poses


def build(args) -> tuple[PoseGraph, list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(args.seed)
    n = args.nodes
    true = true_path(n, args.laps)
    scale = np.r_[np.full(3, args.drift), np.full(3, 0.5 * args.drift), args.drift]
    drift = [sim3_exp(scale * (np.r_[1, -1, 1, 1, 1, -1, 1] + rng.normal(size=7))) for _ in range(n)]
    chain = [true[0]]
    for k in range(1, n):
        chain.append(chain[-1] @ sim3_inverse(true[k - 1]) @ true[k] @ drift[k])
    g = PoseGraph()
    for k, p in enumerate(chain):
        g.add_node(k, p)
    for k in range(1, n):
        for d in range(1, args.neighbours + 1):
            if k - d >= 0:  # odometry: the relative pose, off by the drift of the edges between (as the chain has it)
                g.add_edge(k - d, k, sim3_inverse(chain[k - d]) @ chain[k] @ sim3_exp(rng.normal(size=7) * 1e-3))
    per_lap = n // args.laps
    for m in range(args.loops):
        j = n - 1 - m * (per_lap // max(args.loops, 1))
        i = j - per_lap * (args.laps - 1)  # the same place, first lap
        g.add_edge(j, i, sim3_inverse(true[j]) @ true[i], kind="loop")
    g.fix(0)
    return g, true, chain


def python_rate(seconds: float) -> float:
    """Pure-Python loop iterations a second on this thread over ``seconds``."""
    count, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(1000):
            count += 1
    return count / (time.perf_counter() - t0)


def other_thread_share(work) -> float:
    """A Python loop's speed on this thread while ``work()`` runs on another, over its speed alone."""
    done = threading.Event()

    def run():
        work()
        done.set()

    solo = python_rate(0.3)
    count = 0
    th = threading.Thread(target=run)
    t0 = time.perf_counter()
    th.start()
    while not done.is_set():
        for _ in range(1000):
            count += 1
    elapsed = time.perf_counter() - t0
    th.join()
    return (count / elapsed) / solo


def gtsam_solve(g: PoseGraph, iterations: int):
    """GTSAM's part of ``optimize()`` alone: the Levenberg-Marquardt run on the graph ``optimize`` would build."""
    graph, values, params, _ = g.gtsam_problem(iterations)
    return lambda: gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()


def position_max(poses, true) -> float:
    return float(max(np.linalg.norm(p[:3, 3] - t[:3, 3]) for p, t in zip(poses, true)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=500)
    ap.add_argument("--neighbours", type=int, default=3, help="odometry edges per keyframe (loop.odometry_neighbours)")
    ap.add_argument("--loops", type=int, default=5)
    ap.add_argument("--laps", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=50, help="loop.graph_iterations")
    ap.add_argument("--drift", type=float, default=0.001,
                    help="per-edge error (translation and log-scale; half of it in rotation, radians): a bias of this "
                         "size plus noise of the same size")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.nodes < 2 * args.laps or args.laps < 2:
        sys.exit(f"profiles/pose_graph.py: --nodes {args.nodes} and --laps {args.laps}: need laps >= 2 and at least "
                 f"2 nodes a lap")
    load0 = os.getloadavg()[0]
    g, true, chain = build(args)
    runs = [g.optimize(args.iterations) for _ in range(args.repeats)]
    seconds = [r.seconds for r in runs]
    r = runs[0]
    n = len(g.nodes)
    share = other_thread_share(lambda: g.optimize(args.iterations))
    share_gtsam = other_thread_share(gtsam_solve(g, args.iterations))
    print(json.dumps({
        "profile": "pose_graph", "cpu_count": os.cpu_count(), "load_avg_1min": round(load0, 2),
        "nodes": n, "edges": len(g.edges), "odometry_edges": g.num_odometry_edges, "loop_edges": g.num_loop_edges,
        "seconds": round(float(np.median(seconds)), 4), "seconds_all": [round(s, 4) for s in seconds],
        "solve_seconds": round(float(np.median([x.solve_seconds for x in runs])), 4),
        "iterations": r.iterations, "initial_error": round(r.initial_error, 6), "final_error": round(r.final_error, 6),
        "drift_max_m": round(position_max(chain, true), 4),
        "solved_max_m": round(position_max([r.poses[k] for k in range(n)], true), 4),
        "other_thread_share": round(share, 3), "other_thread_share_in_gtsam": round(share_gtsam, 3),
        "load_avg_1min_end": round(os.getloadavg()[0], 2),
    }))


if __name__ == "__main__":
    main()
