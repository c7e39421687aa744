"""3DGS PLY export/import (exact graphdeco layout) and the coloured point-cloud writer."""

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from mgso.io.ply import (PlyError, gaussian_ply_properties, read_gaussians_ply, read_point_cloud_ply,
                         write_gaussians_ply, write_point_cloud_ply)
from mgso.mapping.gaussian_map import GaussianArrays


def _gaussians(rng, n, degree):
    k = (degree + 1) ** 2
    return GaussianArrays(means=rng.standard_normal((n, 3)), log_scales=rng.standard_normal((n, 3)),
                          quats=rng.standard_normal((n, 4)), opacity_logits=rng.standard_normal(n),
                          sh=rng.standard_normal((n, k, 3)))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_roundtrip_is_exact(tmp_path, rng, degree):
    g = _gaussians(rng, 17, degree)
    path = write_gaussians_ply(tmp_path / "map.ply", g)
    back = read_gaussians_ply(path)
    assert back.sh_degree == degree
    for f in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(getattr(back, f), getattr(g, f)), f


@pytest.mark.parametrize("degree", [0, 1])
def test_header_and_bytes_are_the_3dgs_layout(tmp_path, rng, degree):
    n = 3
    g = _gaussians(rng, n, degree)
    raw = write_gaussians_ply(tmp_path / "map.ply", g).read_bytes()
    # graphdeco save_ply's order (construct_list_of_attributes): xyz, normals, f_dc, f_rest, opacity, scale, rot
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    if degree == 1:
        names += [f"f_rest_{i}" for i in range(9)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert gaussian_ply_properties(degree) == names
    header = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
              + b"".join(b"property float " + s.encode() + b"\n" for s in names) + b"end_header\n")
    assert raw[:len(header)] == header
    body = np.frombuffer(raw[len(header):], dtype="<f4")
    assert body.size == n * len(names)
    body = body.reshape(n, len(names))
    np.testing.assert_array_equal(body[:, 0:3], g.means)
    assert not np.any(body[:, 3:6])                                    # normals zero
    np.testing.assert_array_equal(body[:, 6:9], g.sh[:, 0, :])
    col = 9
    if degree == 1:
        for c in range(3):                                             # channel-major: R's 3 coefficients, then G's..
            for k in range(1, 4):
                np.testing.assert_array_equal(body[:, col], g.sh[:, k, c])
                col += 1
    np.testing.assert_array_equal(body[:, col], g.opacity_logits)      # logit
    np.testing.assert_array_equal(body[:, col + 1:col + 4], g.log_scales)
    np.testing.assert_array_equal(body[:, col + 4:col + 8], g.quats)   # w first, as given


def test_reads_files_with_extra_and_reordered_properties(tmp_path, rng):
    g = _gaussians(rng, 5, 1)
    names = gaussian_ply_properties(1)
    order = names[::-1] + ["confidence"]
    rec = np.empty(5, dtype=[(s, "<f4") for s in order])
    write_gaussians_ply(tmp_path / "a.ply", g)
    src = PlyData.read(str(tmp_path / "a.ply"))["vertex"]
    for s in names:
        rec[s] = src[s]
    rec["confidence"] = 1.0
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp_path / "b.ply"))
    back = read_gaussians_ply(tmp_path / "b.ply")
    assert np.array_equal(back.sh, g.sh) and np.array_equal(back.quats, g.quats)


def test_bad_files_are_named(tmp_path):
    with pytest.raises(PlyError, match="nothere.ply"):
        read_gaussians_ply(tmp_path / "nothere.ply")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"hello")
    with pytest.raises(PlyError, match="junk.ply"):
        read_gaussians_ply(junk)
    pts = tmp_path / "points.ply"
    write_point_cloud_ply(pts, np.zeros((2, 3)))
    with pytest.raises(PlyError, match="points.ply.*missing properties.*opacity"):
        read_gaussians_ply(pts)
    names = gaussian_ply_properties(0) + ["f_rest_0", "f_rest_1", "f_rest_2", "f_rest_3"]
    rec = np.zeros(2, dtype=[(s, "<f4") for s in names])
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp_path / "odd.ply"))
    with pytest.raises(PlyError, match="odd.ply.*4 f_rest"):
        read_gaussians_ply(tmp_path / "odd.ply")


def test_point_cloud_layout_and_roundtrip(tmp_path, rng):
    p = rng.standard_normal((4, 3)).astype(np.float32)
    c = rng.integers(0, 256, (4, 3)).astype(np.uint8)
    idepth = rng.random(4).astype(np.float32)
    raw = write_point_cloud_ply(tmp_path / "points.ply", p, c, extra={"idepth": idepth}).read_bytes()
    header = (b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              b"property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
              b"property float idepth\nend_header\n")
    assert raw.startswith(header) and len(raw) == len(header) + 4 * (12 + 3 + 4)
    pts, cols, other = read_point_cloud_ply(tmp_path / "points.ply")
    assert np.array_equal(pts, p) and np.array_equal(cols, c) and np.array_equal(other["idepth"], idepth)
    write_point_cloud_ply(tmp_path / "f.ply", p, np.array([[0.0, 0.5, 1.0]] * 4))
    assert read_point_cloud_ply(tmp_path / "f.ply")[1][0].tolist() == [0, 128, 255]
    with pytest.raises(ValueError, match="colors"):
        write_point_cloud_ply(tmp_path / "g.ply", p, np.zeros((3, 3)))
