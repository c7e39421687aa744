"""How many Gaussians a pixel blends in a finished run's map, and how many list entries the CPU's blend visits for it;
prints one JSON line.

    python profiles/blend_depth.py RUN_DIR [--downscale 4,2,1] [--views 6]

The CPU's tile blend (:mod:`mgso_kernels.splat.raster_tile_cpp`) costs about the same per list entry (a Gaussian's
lane row of 8 or 16 pixels with a pixel that takes it), and an entry is there because some pixel of it takes the
Gaussian (alpha >= 1/255 and the pixel not yet stopped at a transmittance of 1e-4). So the map's structure sets the
rasteriser's work: how many Gaussians each pixel blends before it stops, and how many of those it blends while
much light is still left. This profile renders ``RUN_DIR/map.ply`` from ``--views`` poses along
``RUN_DIR/trajectory.txt`` (``profiles/splat_raster.py``'s ``run_scene``) at the run's size divided by each
``--downscale``, with a copy of the forward snippet that counts instead of blending colour (its text changed before
the rasteriser is imported; the same stop and skip decisions, which do not depend on the colours). Per size:

- ``takes_per_px``: Gaussians a pixel blends in all (mean over the views' pixels);
- ``takes_T_above_0.1`` / ``0.01`` / ``0.001``: of those, the ones blended while the pixel's transmittance was
  still above 0.1, 0.01, 1e-3 (the rest add less than that share of the pixel's colour between them);
- ``entries_per_px``: list entries visited a pixel (entries x lanes / pixels), and ``lane_use`` = takes / entries
  (the share of the lanes' work that blends something);
- ``entries_per_view``: entries a view, in millions (the backward blend costs about 30 ns an entry on one Intel
  thread, the forward about 18: docs/rasteriser.md).

Read it beside ``profiles/splat_raster.py --run`` (the times) and ``profiles/map_weights.py`` (which Gaussians make
the weight). Needs ``sequence.json`` (the intrinsics) in ``RUN_DIR``, as ``mgso run`` writes it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "profiles"))

# the forward snippet's colour, depth and last-contributor updates, and what counts in their place (before the
# rasteriser's module is imported: its kernels are built from this text)
_COUNTING = {
    "*(vf*)CR[q] = fmav(w, vc0, *(vf*)CR[q]);": "*(vf*)CR[q] = *(vf*)CR[q] + sel(st.Tk > 0.1f, st.acc, (vf)0.0f);",
    "*(vf*)CG[q] = fmav(w, vc1, *(vf*)CG[q]);": "*(vf*)CG[q] = *(vf*)CG[q] + sel(st.Tk > 0.01f, st.acc, (vf)0.0f);",
    "*(vf*)CB[q] = fmav(w, vc2, *(vf*)CB[q]);": "*(vf*)CB[q] = *(vf*)CB[q] + sel(st.Tk > 0.001f, st.acc, (vf)0.0f);",
    "*(vf*)DD[q] = fmav(w, vc3, *(vf*)DD[q]);": "*(vf*)DD[q] = *(vf*)DD[q] + st.acc;",
    "*(vf*)LL[q] = vmax(*(vf*)LL[q], sel(st.acc > 0.0f, vpos, (vf)0.0f));": "*(vf*)LL[q] = *(vf*)LL[q] + 1.0f;",
}


def _counting_forward() -> None:
    from mgso_kernels.splat import raster_tile_cpp

    if "mgso_kernels.splat.raster_tile" in sys.modules:
        raise SystemExit("blend_depth: the rasteriser was imported before its forward snippet could be changed")
    text = raster_tile_cpp.FORWARD
    for old, new in _COUNTING.items():
        if old not in text:
            raise SystemExit(f"blend_depth: the forward snippet no longer has `{old}` (update this profile)")
        text = text.replace(old, new)
    raster_tile_cpp.FORWARD = text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a finished `mgso run` folder (map.ply, trajectory.txt, sequence.json)")
    ap.add_argument("--downscale", default="4,2,1", help="sizes: the run's size divided by each of these")
    ap.add_argument("--views", type=int, default=6, help="poses along the trajectory")
    args = ap.parse_args(argv)
    _counting_forward()
    from mgso_kernels import runtime

    device = runtime.init("cpu", threads=1)
    import splat_raster

    from mgso_kernels.splat import Rasterizer
    from mgso_kernels.splat.raster_tile import native_lanes

    lanes = native_lanes(device)
    res = {"profile": "blend_depth", "run": args.run, "views": args.views, "lanes": lanes, "sizes": {}}
    for ds in (int(x) for x in args.downscale.split(",")):
        params, cams, w, h, count, _ = splat_raster.run_scene(args.run, args.views, device, ds)
        rast = Rasterizer(device)
        tot = np.zeros(5)
        for cam in cams:
            out = rast.forward(*params, cam, background=(0.0, 0.0, 0.0))
            rgb = out.rgb.numpy().astype(np.float64)
            tot += [rgb[..., 0].sum(), rgb[..., 1].sum(), rgb[..., 2].sum(), out.depth.numpy().sum(dtype=np.float64),
                    out.n_contrib.numpy().sum(dtype=np.float64)]
        px = w * h * len(cams)
        a = tot / px
        res["gaussians"] = count
        res["sizes"][f"{w}x{h}"] = {
            "takes_per_px": round(a[3], 1), "takes_T_above_0.1": round(a[0], 1), "takes_T_above_0.01": round(a[1], 1),
            "takes_T_above_0.001": round(a[2], 1), "entries_per_px": round(a[4], 1),
            "lane_use": round(a[3] / a[4], 3) if a[4] else None,
            "entries_per_view": round(tot[4] / len(cams) / lanes / 1e6, 3)}
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
