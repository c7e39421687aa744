"""Random trajectories for the ATE / RPE tests."""

from __future__ import annotations

import numpy as np

from mgso import geometry as g
from mgso.io.trajectory import Trajectory


def random_traj(rng, n, t0=0.0, dt=0.1):
    """A smooth random walk of poses (metres, radians)."""
    xi = np.cumsum(rng.normal(scale=[0.05, 0.05, 0.05, 0.02, 0.02, 0.02], size=(n, 6)), axis=0)
    T = g.se3_exp(xi)
    return Trajectory(t0 + dt * np.arange(n), T)


def noisy_estimate(rng, ref: Trajectory, scale=0.37, jitter=0.002, drop=0.1):
    S = g.sim3_exp(rng.normal(size=7) * [1, 1, 1, 0.5, 0.5, 0.5, 0.0])
    Rs, ts, _ = g.sim3_to_parts(S)
    T = ref.cam_to_world.copy()
    T[:, :3, 3] = scale * (T[:, :3, 3] @ Rs.T) + ts
    T[:, :3, :3] = Rs @ T[:, :3, :3]
    T = T @ g.se3_exp(rng.normal(scale=0.01, size=(len(T), 6)))
    keep = rng.uniform(size=len(T)) > drop
    stamps = ref.timestamps + rng.uniform(-jitter, jitter, size=len(T))
    return Trajectory(stamps[keep], T[keep])
