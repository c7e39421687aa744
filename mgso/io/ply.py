"""PLY files: the 3DGS Gaussian map every splat viewer opens, and coloured point clouds.

Gaussian map (graphdeco 3DGS ``GaussianModel.save_ply``; SuperSplat and antimatter15's splat viewer open it): binary
little-endian, one ``vertex`` element with float32 properties in exactly this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 ... f_rest_{3(K-1)-1} opacity scale_0 scale_1 scale_2
    rot_0 rot_1 rot_2 rot_3

- normals are written as zeros (3DGS does the same);
- ``f_dc_c`` = sh[:, 0, c]; ``f_rest`` is **channel-major**: all K-1 higher coefficients of R, then of G, then of B,
  i.e. ``f_rest_{c (K-1) + (k-1)} = sh[:, k, c]`` (graphdeco writes ``features_rest.transpose(1, 2).flatten(1)`` from
  (N, K-1, 3); gsplat's ``load_ply_to_splats`` reads it back with ``reshape(N, 3, K-1).swapaxes(1, 2)``); none at
  SH degree 0;
- ``opacity`` is the logit, ``scale_i`` the log standard deviations, ``rot_*`` the raw quaternion w, x, y, z.

Reading accepts files with extra properties (e.g. normals that are not zero, or a viewer's own fields) and infers the
SH degree from the number of ``f_rest_*`` properties; a file that lacks a required property or has an impossible
``f_rest`` count is a :class:`PlyError` naming the file.

Point cloud (DSO's ``points.ply``): ``x y z`` float32, ``red green blue`` uchar, then optional extra float32
properties (e.g. ``idepth``, ``idepth_var``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np
from plyfile import PlyData, PlyElement

from mgso.mapping.gaussian_map import GaussianArrays, sh_degree_from_coeffs

__all__ = ["PlyError", "gaussian_ply_properties", "write_gaussians_ply", "read_gaussians_ply",
           "write_point_cloud_ply", "read_point_cloud_ply"]


class PlyError(ValueError):
    """A PLY file is not what was expected; the message names the file and what is wrong."""


def gaussian_ply_properties(sh_degree: int) -> list[str]:
    """Property names of a 3DGS Gaussian PLY with this SH degree, in file order."""
    k = (sh_degree + 1) ** 2
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def write_gaussians_ply(path: str | os.PathLike, gaussians: GaussianArrays) -> Path:
    """Write ``gaussians`` (e.g. ``GaussianMap.to_numpy()``) as a 3DGS PLY; returns the path."""
    path = Path(path)
    g = gaussians
    n, k = g.n, g.sh.shape[1]
    names = gaussian_ply_properties(g.sh_degree)
    cols = [g.means, np.zeros((n, 3), np.float32), g.sh[:, 0, :],
            g.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)),
            g.opacity_logits[:, None], g.log_scales, g.quats]
    data = np.concatenate(cols, axis=1).astype("<f4")
    assert data.shape[1] == len(names)
    rec = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        rec[name] = data[:, i]
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(str(path))
    return path


def _read(path: Path) -> PlyData:
    if not path.is_file():
        raise PlyError(f"{path}: no such file")
    try:
        return PlyData.read(str(path))
    except Exception as exc:  # plyfile raises PlyParseError, ValueError, struct errors...
        raise PlyError(f"{path}: not a readable PLY file ({exc})") from None


def _vertex(path: Path, ply: PlyData):
    try:
        return ply["vertex"]
    except KeyError:
        raise PlyError(f"{path}: no 'vertex' element (elements: {[e.name for e in ply.elements]})") from None


def read_gaussians_ply(path: str | os.PathLike) -> GaussianArrays:
    """Read a 3DGS Gaussian PLY (ours, graphdeco's, gsplat's, SuperSplat's uncompressed export)."""
    path = Path(path)
    v = _vertex(path, _read(path))
    props = [p.name for p in v.properties]
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [r for r in required if r not in props]
    if missing:
        raise PlyError(f"{path}: not a 3DGS Gaussian PLY, missing properties {missing} (has {props[:12]}"
                       f"{'...' if len(props) > 12 else ''})")
    rest = sorted((p for p in props if p.startswith("f_rest_")), key=lambda s: int(s[len("f_rest_"):]))
    if rest and [int(s[7:]) for s in rest] != list(range(len(rest))):
        raise PlyError(f"{path}: f_rest properties are not numbered 0..{len(rest) - 1}")
    if len(rest) % 3:
        raise PlyError(f"{path}: {len(rest)} f_rest properties is not a multiple of 3 (RGB)")
    k = len(rest) // 3 + 1
    try:
        sh_degree_from_coeffs(k)
    except ValueError:
        raise PlyError(f"{path}: {len(rest)} f_rest properties means {k} SH coefficients per channel, which is "
                       "not (degree + 1)^2") from None

    def col(name):
        return np.asarray(v[name], dtype=np.float32)

    n = len(v.data)
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0, :] = np.stack([col(f"f_dc_{c}") for c in range(3)], axis=1)
    if rest:
        fr = np.stack([col(r) for r in rest], axis=1).reshape(n, 3, k - 1)
        sh[:, 1:, :] = fr.transpose(0, 2, 1)
    arrays = GaussianArrays(
        means=np.stack([col("x"), col("y"), col("z")], axis=1),
        log_scales=np.stack([col(f"scale_{i}") for i in range(3)], axis=1),
        quats=np.stack([col(f"rot_{i}") for i in range(4)], axis=1),
        opacity_logits=col("opacity"), sh=sh)
    return arrays


def write_point_cloud_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None,
                          extra: Mapping[str, np.ndarray] | None = None) -> Path:
    """Write a coloured point cloud: ``x y z`` float32, ``red green blue`` uchar, then ``extra`` float32 properties.

    ``points`` (N, 3); ``colors`` (N, 3) uint8, or floats in [0, 1] (scaled by 255), or (N,) gray; default gray 128.
    ``extra``: name -> (N,) values, e.g. ``{"idepth": ..., "idepth_var": ...}``.
    """
    path = Path(path)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"write_point_cloud_ply({path}): points must be (N, 3), got {p.shape}")
    n = len(p)
    if colors is None:
        rgb = np.full((n, 3), 128, np.uint8)
    else:
        c = np.asarray(colors)
        if c.ndim == 1:
            c = np.repeat(c[:, None], 3, axis=1)
        if c.shape != (n, 3):
            raise ValueError(f"write_point_cloud_ply({path}): colors must be (N, 3) or (N,), got {c.shape}")
        if np.issubdtype(c.dtype, np.floating):
            c = np.clip(np.round(c * 255.0), 0, 255)
        rgb = c.astype(np.uint8)
    extra = dict(extra or {})
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    for name, vals in extra.items():
        if name in ("x", "y", "z", "red", "green", "blue") or not name.isidentifier():
            raise ValueError(f"write_point_cloud_ply({path}): bad extra property name {name!r}")
        if np.asarray(vals).shape != (n,):
            raise ValueError(f"write_point_cloud_ply({path}): extra property {name!r} must have shape ({n},)")
        dtype.append((name, "<f4"))
    rec = np.empty(n, dtype=dtype)
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    for name, vals in extra.items():
        rec[name] = np.asarray(vals, dtype=np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(str(path))
    return path


def read_point_cloud_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
    """Read a point cloud PLY: (points (N, 3) float32, colours (N, 3) uint8 or None, other properties by name)."""
    path = Path(path)
    v = _vertex(path, _read(path))
    props = [p.name for p in v.properties]
    if not all(a in props for a in ("x", "y", "z")):
        raise PlyError(f"{path}: vertex element has no x, y, z (has {props})")
    pts = np.stack([np.asarray(v[a], dtype=np.float32) for a in ("x", "y", "z")], axis=1)
    colors = None
    if all(a in props for a in ("red", "green", "blue")):
        colors = np.stack([np.asarray(v[a]) for a in ("red", "green", "blue")], axis=1).astype(np.uint8)
    others = {p: np.asarray(v[p]) for p in props if p not in ("x", "y", "z", "red", "green", "blue")}
    return pts, colors, others
