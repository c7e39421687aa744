"""mgso: monocular SLAM with a 3D Gaussian Splatting map (DSO tracking + DSO-seeded 3DGS mapping) on NVIDIA Warp.

Subpackages: ``io`` (datasets, calibration files, trajectories, maps), ``tracking`` (DSO front end), ``window``
(sliding-window bundle adjustment), ``mapping`` (Gaussian map, seeding, training), ``eval`` (ATE, render metrics).
Kernels live in the separate ``mgso_kernels`` package.
"""

__version__ = "0.1.0"
