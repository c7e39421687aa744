"""Camera models, undistortion, camera.txt and other calibration files, photometric calibration.

Independent twins: OpenCV's ``projectPoints`` / ``fisheye.projectPoints`` / ``undistortPoints`` for the models, and a
rendered blob for the remap tables (a point drawn where the distorted camera sees it must land where the pinhole
output camera projects it).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mgso.camera import (KEEP_BORDER_PX, Calibration, CalibrationError, CameraSpec, EquidistantCamera, FOVCamera,
                         OutputSpec, PhotometricCalibration, PinholeCamera, RadTanCamera, Undistorter,
                         crop_output_camera, full_output_camera, keep_output_camera, make_output_camera,
                         read_inverse_response, read_vignette)
# calibration files are read in mgso.io (each dataset's format beside its reader)
from mgso.io import (load_calibration, read_camera_file, read_dso_camera_txt,
                     read_euroc_sensor_yaml, read_kitti_calib, read_plain_intrinsics, read_replica_cam_params,
                     tum_rgbd_default)

W, H = 120, 90
MODELS = {
    "pinhole": PinholeCamera(80.0, 82.0, 59.3, 44.6, W, H),
    "radtan": RadTanCamera(80.0, 82.0, 59.3, 44.6, W, H, -0.25, 0.07, 0.001, -0.0008, 0.002),
    "equidistant": EquidistantCamera(55.0, 56.0, 59.3, 44.6, W, H, 0.02, -0.01, 0.004, -0.001),
    "fov": FOVCamera(70.0, 71.0, 59.3, 44.6, W, H, omega=0.9),
}


def random_points(rng, n=500, spread=0.6):
    xy = rng.uniform(-spread, spread, (n, 2))
    z = rng.uniform(0.5, 5.0, n)
    return np.concatenate([xy * z[:, None], z[:, None]], axis=1)


# ------------------------------------------------------------------------------------------------------ models
@pytest.mark.parametrize("name", list(MODELS))
def test_projection_unprojection_round_trip(name, rng):
    cam = MODELS[name]
    P = random_points(rng)
    uv, ok = cam.project(P)
    assert ok.all()
    rays, ok2 = cam.unproject(uv, depth=P[:, 2])
    assert ok2.all()
    np.testing.assert_allclose(rays, P, rtol=1e-9, atol=1e-9)
    # behind the camera is never valid
    _, ok3 = cam.project(-P)
    assert not ok3.any()


def test_radtan_matches_opencv_projectpoints(rng):
    cam = MODELS["radtan"]
    P = random_points(rng)
    uv, _ = cam.project(P)
    ref, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_radtan_undistortion_matches_opencv_undistortpoints(rng):
    cam = MODELS["radtan"]
    uv = np.stack([rng.uniform(0, W - 1, 300), rng.uniform(0, H - 1, 300)], axis=1)
    xn, ok = cam.normalized_from_pixel(uv)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), cam.K, cam.dist_coeffs, None, None, crit) if hasattr(
        cv2, "undistortPointsIter") else cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist_coeffs,
                                                             criteria=crit)
    assert ok.all()
    np.testing.assert_allclose(xn, ref.reshape(-1, 2), atol=1e-8)


def test_equidistant_matches_opencv_fisheye(rng):
    cam = MODELS["equidistant"]
    P = random_points(rng, spread=1.5)
    uv, ok = cam.project(P)
    ref, _ = cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K,
                                       cam.dist_coeffs.reshape(4, 1))
    assert ok.all()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-8)
    xn, ok = cam.normalized_from_pixel(uv)
    np.testing.assert_allclose(xn, P[:, :2] / P[:, 2:], atol=1e-9)


def test_fov_matches_the_atan_formula():
    cam = MODELS["fov"]
    # r_d = atan(2 r tan(w / 2)) / w, written out for one point (PTAM / DSO FOV model)
    x, y = 0.3, -0.4
    r = math.hypot(x, y)
    rd = math.atan(2 * r * math.tan(0.9 / 2)) / 0.9
    expect = (cam.fx * x * rd / r + cam.cx, cam.fy * y * rd / r + cam.cy)
    uv, _ = cam.project(np.array([[x, y, 1.0]]))
    np.testing.assert_allclose(uv[0], expect, atol=1e-12)


def test_folding_radtan_is_limited_to_its_monotone_region():
    cam = RadTanCamera(100, 100, 50, 50, 101, 101, k1=-0.5)  # x (1 - 0.5 x^2) peaks at x = sqrt(2/3)
    assert cam.max_radius == pytest.approx(math.sqrt(2 / 3))
    _, ok = cam.project(np.array([[0.7, 0.0, 1.0], [0.9, 0.0, 1.0]]))
    assert ok.tolist() == [True, False]


def test_pinhole_scaling_keeps_pixel_centres():
    cam = PinholeCamera(100.0, 110.0, 63.5, 47.5, 128, 96)
    half = cam.scaled(0.5)
    assert (half.fx, half.fy, half.width, half.height) == (50.0, 55.0, 64, 48)
    # the centre of a 2x2 block of level-0 pixels (x, x+1) is level-1 pixel x/2: cx' = (cx + 0.5) / 2 - 0.5
    assert half.cx == pytest.approx(31.5) and half.cy == pytest.approx(23.5)
    P = np.array([[0.3, -0.2, 2.0]])
    u0, _ = cam.project(P)
    u1, _ = half.project(P)
    np.testing.assert_allclose(u1, (u0 + 0.5) / 2 - 0.5)
    assert cam.pyramid_level(2) == half.scaled(0.5)
    assert PinholeCamera(1, 1, 0, 0, 1241, 376).scaled(0.5).size == (620, 188)


# -------------------------------------------------------------------------------------------------- undistortion
def blob_image(cam, uv, sigma=1.2):
    """An input image (float32) with a Gaussian blob centred on pixel ``uv`` of ``cam``."""
    yy, xx = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    return (200.0 * np.exp(-((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2) / (2 * sigma ** 2))).astype(np.float32)


def centroid(img, around, radius=5):
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    m = (np.abs(xx - around[0]) <= radius) & (np.abs(yy - around[1]) <= radius)
    w = img * m
    return np.array([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()])


@pytest.mark.parametrize("name", ["radtan", "equidistant", "fov"])
@pytest.mark.parametrize("mode", ["crop", "full", "none"])
def test_undistorted_image_puts_points_at_the_pinhole_projection(name, mode):
    cam = MODELS[name]
    if name == "equidistant" and mode == "full":
        mode = "crop"  # this fisheye sees beyond 90 degrees in the corners: full is impossible (tested below)
    cal = Calibration.create(cam, mode)
    out = cal.output
    # a 3D point that both cameras see away from the borders
    for target in ([0.35 * W, 0.4 * H], [0.7 * W, 0.62 * H]):
        xn = np.array([[(target[0] - out.cx) / out.fx, (target[1] - out.cy) / out.fy]])
        P = np.array([[xn[0, 0] * 3.0, xn[0, 1] * 3.0, 3.0]])
        uv_in, ok = cam.project(P)
        uv_out, _ = out.project(P)
        assert ok.all()
        img = cal.undistorter.apply(blob_image(cam, uv_in[0]))
        c = centroid(img, uv_out[0])
        # the blob is stretched by the distortion, so its centroid moves a little: 0.15 px is far below a pixel
        np.testing.assert_allclose(c, uv_out[0], atol=0.15)


@pytest.mark.parametrize("name", ["radtan", "equidistant", "fov"])
def test_remap_tables_agree_with_the_model(name):
    cam = MODELS[name]
    u = Undistorter(cam, make_output_camera(cam, "crop"))
    vv, uu = np.mgrid[0:H:7, 0:W:9]
    uv_out = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64)
    src = u.source_pixels(uv_out)
    tab = np.stack([u.map_x[vv.ravel(), uu.ravel()], u.map_y[vv.ravel(), uu.ravel()]], 1)
    np.testing.assert_allclose(tab, src, atol=2e-3)  # float32 tables


@pytest.mark.parametrize("name", ["radtan", "equidistant", "fov"])
def test_crop_is_valid_everywhere_and_tight(name):
    cam = MODELS[name]
    out = crop_output_camera(cam, W, H)
    assert Undistorter(cam, out).valid_mask.all()
    # 3 % wider in both directions and some output pixels fall outside the input: the crop is (nearly) tight
    wider = PinholeCamera(out.fx / 1.03, out.fy / 1.03, (out.cx - (W - 1) / 2) / 1.03 + (W - 1) / 2,
                          (out.cy - (H - 1) / 2) / 1.03 + (H - 1) / 2, W, H)
    assert not Undistorter(cam, wider).valid_mask.all()


@pytest.mark.parametrize("name", ["radtan", "fov"])
def test_full_shows_the_whole_input(name):
    cam = MODELS[name]
    out = full_output_camera(cam, W, H)
    us, vs = np.arange(W, dtype=float), np.arange(H, dtype=float)
    border = np.concatenate([np.stack([us, np.zeros(W)], 1), np.stack([us, np.full(W, H - 1.0)], 1),
                             np.stack([np.zeros(H), vs], 1), np.stack([np.full(H, W - 1.0), vs], 1)])
    rays, ok = cam.unproject(border)
    uv, _ = out.project(rays)
    assert ok.all()
    eps = 1e-6
    assert uv[:, 0].min() >= -eps and uv[:, 0].max() <= W - 1 + eps
    assert uv[:, 1].min() >= -eps and uv[:, 1].max() <= H - 1 + eps
    # and the border touches all four sides of the output
    assert uv[:, 0].min() < 1e-6 and uv[:, 0].max() > W - 1 - 1e-6
    assert uv[:, 1].min() < 1e-6 and uv[:, 1].max() > H - 1 - 1e-6


def test_full_refuses_a_view_beyond_90_degrees():
    wide = EquidistantCamera(25.0, 25.0, 59.5, 44.5, W, H)  # corners at 3.0 rad /... theta_d = r_d > pi / 2
    with pytest.raises(CalibrationError, match="cannot be undistorted onto a pinhole"):
        full_output_camera(wide, W, H)


def kept_fraction(cam, out):
    """Share of the input pixels whose ray lands inside the output image (what a rectification keeps)."""
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    rays, ok = cam.unproject(np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64))
    uv, ok2 = out.project(rays)
    inside = ok & ok2 & (uv[:, 0] >= -0.5) & (uv[:, 0] <= out.width - 0.5) & (uv[:, 1] >= -0.5) & (
        uv[:, 1] <= out.height - 0.5)
    return float(inside.mean())


def border_distance(h, w):
    yy, xx = np.mgrid[0:h, 0:w]
    return np.minimum(np.minimum(xx, w - 1 - xx), np.minimum(yy, h - 1 - yy))


def test_fr1_default_keeps_the_field_of_view():
    spec = tum_rgbd_default(1)
    cam = spec.model
    keep = Calibration.from_spec(spec)
    assert keep.output_mode == "keep"
    out = keep.output
    # DSO's crop search zooms fr1 1.37x horizontally (711.2 for 517.3); the default stays within 5 % of the input
    assert out.fx < 1.05 * cam.fx and out.fy < 1.05 * cam.fy
    assert (round(out.fx, 1), round(out.fy, 1)) == (541.8, 536.6)
    assert kept_fraction(cam, out) > 0.97
    # the pixels without a source only lie in the outer KEEP_BORDER_PX rows and columns, and there are some
    valid = keep.undistorter.valid_mask
    d = border_distance(*valid.shape)
    assert valid[d >= KEEP_BORDER_PX].all() and not valid.all()
    assert keep.valid_mask is valid and keep.undistorter.valid_fraction > 0.998


def test_rectify_crop_still_gives_dsos_crop_camera():
    """Negative control: asked for, crop is today's (DSO's) camera: all pixels valid, most of the view gone."""
    crop = Calibration.from_spec(tum_rgbd_default(1), rectify="crop")
    out = crop.output
    assert crop.output_mode == "crop"
    np.testing.assert_allclose([out.fx, out.fy, out.cx, out.cy], [711.215, 533.334, 320.858, 252.900], atol=5e-3)
    assert crop.valid_mask is None and crop.undistorter.valid_mask.all()
    assert kept_fraction(crop.input, out) < 0.75


@pytest.mark.parametrize("name", ["radtan", "fov", "fr1", "fr2"])
def test_keep_sees_at_least_what_crop_sees(name):
    cam = MODELS[name] if name in MODELS else tum_rgbd_default(int(name[2])).model
    keep = keep_output_camera(cam, cam.width, cam.height)
    crop = crop_output_camera(cam, cam.width, cam.height)
    # crop may keep a little more of one axis by giving up much of the other (fr1: fy 533.3 vs 536.6, fx 711 vs 542)
    assert keep.fx <= crop.fx * 1.01 and keep.fy <= crop.fy * 1.01
    valid = Undistorter(cam, keep).valid_mask
    assert valid[border_distance(*valid.shape) >= KEEP_BORDER_PX].all()
    assert kept_fraction(cam, keep) >= kept_fraction(cam, crop)


def test_keep_falls_back_to_crop_beyond_90_degrees():
    wide = EquidistantCamera(25.0, 25.0, 59.5, 44.5, W, H)  # full is impossible for it (tested above)
    cal = Calibration.create(wide, "keep")
    assert cal.output_mode == "crop" and cal.output == crop_output_camera(wide, W, H)


@pytest.mark.parametrize("name, mode", [("radtan", "full"), ("fov", "full"), ("equidistant", "wide"),
                                        ("fr1", "keep"), ("fr1", "none")])
def test_valid_mask_marks_exactly_the_pixels_without_a_source(name, mode):
    cam = MODELS[name] if name in MODELS else tum_rgbd_default(1).model.resized(160, 120)
    wide = PinholeCamera(30.0, 31.0, 59.5, 44.5, W, H)  # sees beyond the fisheye's corners
    und = Undistorter(cam, wide if mode == "wide" else make_output_camera(cam, mode))
    out, mask = und.output, und.valid_mask
    assert not mask.all()
    # slow: one pixel at a time through the camera model
    slow = np.zeros_like(mask)
    for v in range(out.height):
        for u in range(out.width):
            xn = np.array([[(u - out.cx) / out.fx, (v - out.cy) / out.fy]])
            uv, ok = cam.pixel_from_normalized(xn)
            x, y = uv[0]
            slow[v, u] = bool(ok[0]) and 0 <= x <= cam.width - 1 and 0 <= y <= cam.height - 1
    np.testing.assert_array_equal(mask, slow)
    # OpenCV's own tables agree away from the input's edge (float32 tables: a few 1e-3 px)
    inside = (und.map_x > 2e-3) & (und.map_x < cam.width - 1 - 2e-3) & (und.map_y > 2e-3) & (
        und.map_y < cam.height - 1 - 2e-3)
    outside = (und.map_x < -2e-3) | (und.map_x > cam.width - 1 + 2e-3) | (und.map_y < -2e-3) | (
        und.map_y > cam.height - 1 + 2e-3)
    assert mask[inside].all() and not mask[outside].any()


def test_pixels_without_a_source_hold_the_nearest_input_pixel_not_black(rng):
    cam = MODELS["radtan"]
    und = Undistorter(cam, full_output_camera(cam, W, H))
    img = rng.uniform(50, 200, (H, W)).astype(np.float32)
    out = und.apply(img)
    bad = ~und.valid_mask
    assert bad.any() and out[bad].min() >= 50.0  # edge replicate, never 0
    # the source clamped onto the input's edge, sampled bilinearly
    clamped = cv2.remap(img, np.clip(und.map_x, 0, W - 1), np.clip(und.map_y, 0, H - 1), cv2.INTER_LINEAR)
    far = (und.map_x[bad] < -1) | (und.map_x[bad] > W) | (und.map_y[bad] < -1) | (und.map_y[bad] > H)
    assert far.sum() > 100
    np.testing.assert_allclose(out[bad][far], clamped[bad][far], atol=1e-3)
    black = und.apply(img, fill_edge=False)
    assert black[bad][far].max() == 0.0
    assert und.apply_nearest(img)[bad].max() == 0.0  # depth and labels: 0 = no value


def test_pinhole_passthrough_is_bit_exact(rng):
    cam = PinholeCamera(80.0, 82.0, 59.3, 44.6, W, H)
    cal = Calibration.create(cam, "crop")
    assert cal.undistorter.kind == "passthrough" and cal.output == cam
    raw = rng.integers(0, 256, (H, W), dtype=np.uint8)
    assert cal.undistorter.apply(raw) is raw
    g = cal.gray_from_raw(raw)
    np.testing.assert_array_equal(g, raw.astype(np.float32))
    assert g.dtype == np.float32 and not np.shares_memory(g, raw)
    # a radtan model with all-zero coefficients is a pinhole too
    assert Calibration.create(RadTanCamera(80.0, 82.0, 59.3, 44.6, W, H), "full").undistorter.passthrough


def test_resize_follows_the_pixel_centre_rule():
    cam = PinholeCamera(80.0, 82.0, 59.3, 44.6, W, H)
    cal = Calibration.create(cam, "none", size=(60, 45))
    assert cal.undistorter.kind == "resize"
    out = cal.output
    P = np.array([[0.2, 0.1, 1.5]])
    uv_in, _ = cam.project(P)
    uv_out, _ = out.project(P)
    np.testing.assert_allclose(uv_out, (uv_in + 0.5) / 2 - 0.5)
    img = cal.undistorter.apply(blob_image(cam, uv_in[0], sigma=2.0))
    np.testing.assert_allclose(centroid(img, uv_out[0], radius=4), uv_out[0], atol=0.05)


# ------------------------------------------------------------------------------------------------- camera.txt
def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_camera_txt_relative_and_absolute_are_the_same_camera(tmp_path):
    rel = read_dso_camera_txt(write(tmp_path, "rel.txt", "Pinhole 0.5 0.6 0.5 0.5 0\n640 480\nnone\n640 480\n"))
    ab = read_dso_camera_txt(write(tmp_path, "abs.txt", "Pinhole 320 288 319.5 239.5 0\n640 480\nnone\n640 480\n"))
    # DSO: fx = 0.5 * 640, cx = 0.5 * 640 - 0.5 (relative calibrations integrate pixel (0, 0) over [0, 1]^2)
    assert rel.model == ab.model == PinholeCamera(320.0, 288.0, 319.5, 239.5, 640, 480)
    assert Calibration.from_spec(rel).undistorter.passthrough


def test_camera_txt_models(tmp_path):
    cases = {
        "0.35 0.44 0.49 0.5 0.93\n1280 1024\ncrop\n640 480\n": FOVCamera,  # TUM monoVO's legacy ATAN line
        "0.35 0.44 0.49 0.5 0\n1280 1024\ncrop\n640 480\n": PinholeCamera,
        "458.6 457.3 367.2 248.4 -0.28 0.07 0.0002 0.00002\n752 480\ncrop\n752 480\n": RadTanCamera,
        "RadTan 458.6 457.3 367.2 248.4 -0.28 0.07 0.0002 0.00002\n752 480\nfull\n376 240\n": RadTanCamera,
        "EquiDistant 190.9 190.9 254.9 256.9 0.0034 0.0007 -0.002 0.0002\n512 512\ncrop\n512 512\n":
            EquidistantCamera,
        "KannalaBrandt 190.9 190.9 254.9 256.9 0.0034 0.0007 -0.002 0.0002\n512 512\ncrop\n512 512\n":
            EquidistantCamera,
        "FOV 0.35 0.44 0.49 0.5 0.93\n1280 1024\nnone\n1280 1024\n": FOVCamera,
        "RadTan 517.3 516.5 318.6 255.3 0.2624 -0.9531 -0.0054 0.0026 1.1633\n640 480\ncrop\n640 480\n": RadTanCamera,
    }
    for i, (text, cls) in enumerate(cases.items()):
        spec = read_dso_camera_txt(write(tmp_path, f"c{i}.txt", text))
        assert type(spec.model) is cls, text
    spec = read_dso_camera_txt(write(tmp_path, "fov.txt", next(iter(cases))))
    assert spec.model.fx == pytest.approx(0.35 * 1280) and spec.model.cx == pytest.approx(0.49 * 1280 - 0.5)
    assert spec.model.omega == pytest.approx(0.93)
    assert spec.output == OutputSpec(mode="crop", size=(640, 480))
    k3 = read_dso_camera_txt(tmp_path / f"c{len(cases) - 1}.txt").model
    assert k3.k3 == 1.1633 and k3.k1 == 0.2624


def test_camera_txt_output_modes(tmp_path):
    base = "RadTan 80 82 59.3 44.6 -0.25 0.07 0.001 -0.0008\n120 90\n"
    for mode in ("crop", "full", "none"):
        cal = Calibration.from_spec(read_dso_camera_txt(write(tmp_path, f"{mode}.txt", base + f"{mode}\n60 45\n")))
        assert cal.output_mode == mode and cal.output_size == (60, 45)
    none = Calibration.from_spec(read_dso_camera_txt(write(tmp_path, "n.txt", base + "none\n60 45\n")))
    assert none.output == MODELS["radtan"].pinhole().resized(60, 45)  # input intrinsics scaled to the size
    rel = Calibration.from_spec(read_dso_camera_txt(write(tmp_path, "r.txt", base + "0.5 0.6 0.5 0.5 0\n60 45\n")))
    assert (rel.output.fx, rel.output.fy, rel.output.cx, rel.output.cy) == (30.0, 27.0, 29.5, 22.0)
    ab = Calibration.from_spec(read_dso_camera_txt(write(tmp_path, "a.txt", base + "40 41 29.5 22 0\n60 45\n")))
    assert (ab.output.fx, ab.output.fy, ab.output.cx, ab.output.cy) == (40.0, 41.0, 29.5, 22.0)
    short = read_dso_camera_txt(write(tmp_path, "s.txt", base))
    assert short.output == OutputSpec(mode="none")
    # the rectify override and an output size override
    over = Calibration.from_spec(short, rectify="crop", size=(30, 20))
    assert over.output_mode == "crop" and over.output_size == (30, 20) and over.undistorter.valid_mask.all()


@pytest.mark.parametrize("text, message", [
    ("Pinhole 1 2 3\n640 480\n", "takes 5 numbers"),
    ("1 2 3 4 5 6\n640 480\n", "expected 5"),
    ("Pinhole 300 300 320 240 0\n640\n", "input image size"),
    ("Pinhole 300 300 320 240 0\n640 480\ncropped\n640 480\n", "crop, full, none"),
    ("Pinhole 300 300 320 240 0\n640 480\n0.5 0.5 0.5 0.5 0.1\n640 480\n", "fifth number must be 0"),
    ("Pinhole 300 300 320 240 0\n640 480\ncrop\n640 x\n", "output image size"),
    ("Pinhole 300 300 320 240 0.5\n640 480\n", "Pinhole takes a 0"),
    ("FOV 300 300 320 240 4.0\n640 480\n", "omega"),
    ("Pinhole -300 300 320 240 0\n640 480\n", "focal lengths must be positive"),
    ("Pinhole 300\n", "at least 2 lines"),
])
def test_malformed_camera_txt_names_the_file(tmp_path, text, message):
    p = write(tmp_path, "bad_camera.txt", text)
    with pytest.raises(CalibrationError, match=message) as err:
        read_dso_camera_txt(p)
    assert "bad_camera.txt" in str(err.value)


def test_missing_calibration_file(tmp_path):
    with pytest.raises(CalibrationError, match="nothere.txt.*not found"):
        read_camera_file(tmp_path / "nothere.txt")


# ------------------------------------------------------------------------------------ other calibration formats
EUROC_YAML = """%YAML:1.0
# General sensor definitions.
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def test_euroc_sensor_yaml_with_yaml_1_0_header(tmp_path):
    spec, T_BS = read_euroc_sensor_yaml(write(tmp_path, "sensor.yaml", EUROC_YAML))
    m = spec.model
    assert isinstance(m, RadTanCamera) and m.size == (752, 480)
    assert (m.fx, m.fy, m.cx, m.cy, m.k1, m.p2) == (458.654, 457.296, 367.215, 248.375, -0.28340811, 1.76187114e-05)
    assert T_BS[0, 3] == pytest.approx(-0.0216401454975) and spec.output.mode == "keep"
    assert read_camera_file(tmp_path / "sensor.yaml").model == m
    # OpenCV FileStorage style matrices are read too
    cv = EUROC_YAML.replace("T_BS:\n  cols", "T_BS: !!opencv-matrix\n  cols")
    assert np.allclose(read_euroc_sensor_yaml(write(tmp_path, "cv.yaml", cv))[1], T_BS)


@pytest.mark.parametrize("change, message", [
    (("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296]"), "4 numbers"),
    (("distortion_model: radial-tangential", "distortion_model: polynomial9"), "unknown distortion_model"),
    (("resolution: [752, 480]\n", ""), "missing key 'resolution'"),
    (("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0]"), "T_BS must be a 4x4"),
    (("T_BS:", "T_BS: [: oops\nx:"), "not valid YAML"),
])
def test_malformed_euroc_yaml(tmp_path, change, message):
    p = write(tmp_path, "broken_sensor.yaml", EUROC_YAML.replace(*change))
    with pytest.raises(CalibrationError, match=message) as err:
        read_euroc_sensor_yaml(p)
    assert "broken_sensor.yaml" in str(err.value)


def test_kitti_calib(tmp_path):
    p = write(tmp_path, "calib.txt", "P0: 7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0\n"
                                     "P2: 7.188560e+02 0 6.071928e+02 4.538225e+01 0 7.188560e+02 1.852157e+02 "
                                     "-1.130887e-01 0 0 1 3.779761e-03\n")
    spec, _ = read_kitti_calib(p, (1241, 376))
    assert spec.model == PinholeCamera(718.856, 718.856, 607.1928, 185.2157, 1241, 376)
    assert read_kitti_calib(p, (1241, 376), camera=2)[1][0, 3] == pytest.approx(45.38225)
    assert read_camera_file(p, (1241, 376)).model == spec.model
    with pytest.raises(CalibrationError, match="no 'P1:' line"):
        read_kitti_calib(p, (1241, 376), camera=1)
    with pytest.raises(CalibrationError, match="needs 12 numbers"):
        read_kitti_calib(write(tmp_path, "c2.txt", "P0: 1 2 3\n"), (10, 10))
    with pytest.raises(CalibrationError, match="no image size"):
        read_kitti_calib(p, None)


def test_plain_intrinsics(tmp_path):
    assert read_plain_intrinsics(write(tmp_path, "a.txt", "517.3 516.5 318.6 255.3\n"), (640, 480)).model == \
        PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480)
    rt = read_plain_intrinsics(write(tmp_path, "b.txt", "# fx fy cx cy k1 k2 p1 p2 k3\n517.3, 516.5, 318.6, 255.3,"
                                                        " 0.2624, -0.9531, -0.0054, 0.0026, 1.1633\n"), (640, 480))
    assert isinstance(rt.model, RadTanCamera) and rt.model.k3 == 1.1633 and rt.output.mode == "keep"
    assert isinstance(read_camera_file(tmp_path / "b.txt", (640, 480)).model, RadTanCamera)
    with pytest.raises(CalibrationError, match="c.txt: expected 4"):
        read_plain_intrinsics(write(tmp_path, "c.txt", "1 2 3 4 5\n"), (640, 480))
    with pytest.raises(CalibrationError, match="needed from the images"):
        read_plain_intrinsics(tmp_path / "a.txt", None)
    with pytest.raises(CalibrationError, match="d.txt: expected numbers"):
        read_plain_intrinsics(write(tmp_path, "d.txt", "fx=1 fy=2\n"), (640, 480))


def test_tum_rgbd_defaults_by_name():
    # values from the TUM RGB-D file-formats page (see mgso/io/tum.py)
    fr2 = tum_rgbd_default("rgbd_dataset_freiburg2_desk").model
    assert (fr2.fx, fr2.fy, fr2.cx, fr2.cy) == (520.9, 521.0, 325.1, 249.7)
    assert tum_rgbd_default("fr3").model.has_distortion is False
    assert tum_rgbd_default(1).output.mode == "keep"
    with pytest.raises(CalibrationError, match="no TUM RGB-D camera"):
        tum_rgbd_default("rgbd_dataset_freiburg4")
    with pytest.raises(CalibrationError, match="640x480"):
        tum_rgbd_default(1, 320, 240)


def test_replica_cam_params(tmp_path):
    p = write(tmp_path, "cam_params.json", '{"camera": {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, '
                                           '"cx": 599.5, "cy": 339.5, "scale": 6553.5}}')
    spec, scale = read_replica_cam_params(p)
    assert spec.model == PinholeCamera(600.0, 600.0, 599.5, 339.5, 1200, 680) and scale == 6553.5
    with pytest.raises(CalibrationError, match="missing"):
        read_replica_cam_params(write(tmp_path, "x.json", '{"camera": {"w": 10}}'))
    with pytest.raises(CalibrationError, match="not valid JSON"):
        read_replica_cam_params(write(tmp_path, "y.json", '{"camera": '))


# -------------------------------------------------------------------------------------- photometric calibration
def write_vignette(path, img):
    assert cv2.imwrite(str(path), img)
    return path


def test_photometric_identity_and_known_response(tmp_path, rng):
    raw = rng.integers(0, 256, (H, W), dtype=np.uint8)
    ident = PhotometricCalibration.identity()
    assert ident.is_identity
    np.testing.assert_array_equal(ident.apply(raw), raw.astype(np.float32))
    # G^-1(x) = 3 + x^1.5 (any scale: rescaled to 0..255 as DSO does)
    g = 3.0 + np.arange(256) ** 1.5
    p = write(tmp_path, "pcalib.txt", " ".join(f"{v:.9f}" for v in g) + "\n")
    vig = np.full((H, W), 40000, np.uint16)
    vig[:10] = 20000
    v = write_vignette(tmp_path / "vignette.png", vig)
    pc = PhotometricCalibration.from_files(p, v, (W, H))
    expect = 255.0 * (raw.astype(np.float64) ** 1.5) / 255.0 ** 1.5
    expect[:10] *= 2.0  # V is 0.5 there after normalising the max to 1
    np.testing.assert_allclose(pc.apply(raw), expect, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(pc.apply(raw, 8.0, normalize_exposure=True), expect / 8.0, rtol=1e-5, atol=1e-4)
    with pytest.raises(ValueError, match="positive exposure"):
        pc.apply(raw, None, normalize_exposure=True)
    # 8-bit vignettes are read too
    v8 = write_vignette(tmp_path / "v8.png", (vig // 257).astype(np.uint8))
    assert read_vignette(v8).max() == 1.0


def test_photometric_is_applied_before_undistortion(tmp_path, rng):
    g = np.arange(256, dtype=np.float64) ** 2
    p = write(tmp_path, "pcalib.txt", " ".join(str(v) for v in g))
    vig = np.tile(np.linspace(30000, 65535, W).astype(np.uint16), (H, 1))
    v = write_vignette(tmp_path / "vignette.png", vig)
    pc = PhotometricCalibration.from_files(p, v, (W, H))
    cal = Calibration.create(MODELS["radtan"], "crop", photometric=pc)
    raw = rng.integers(0, 256, (H, W), dtype=np.uint8)
    np.testing.assert_allclose(cal.gray_from_raw(raw), cal.undistorter.apply(pc.apply(raw)), rtol=1e-6)
    np.testing.assert_allclose(cal.gray_from_raw(raw, photometric=False),
                               cal.undistorter.apply(raw.astype(np.float32)), rtol=1e-6)
    with pytest.raises(CalibrationError, match="vignette is"):
        Calibration.create(MODELS["radtan"].resized(60, 45), "crop", photometric=pc)


@pytest.mark.parametrize("text, message", [
    ("1 2 3\n", "at least 256"),
    (" ".join(["1"] * 256), "strictly increasing"),
    (" ".join(["x"] * 256), "must be numbers"),
    ("", "empty"),
])
def test_malformed_pcalib_names_the_file(tmp_path, text, message):
    p = write(tmp_path, "bad_pcalib.txt", text)
    with pytest.raises(CalibrationError, match=message) as err:
        read_inverse_response(p)
    assert "bad_pcalib.txt" in str(err.value)


def test_malformed_vignette_names_the_file(tmp_path):
    bad = write(tmp_path, "bad_vignette.png", "not a png")
    with pytest.raises(CalibrationError, match="bad_vignette.png: not a readable image"):
        read_vignette(bad)
    ok = write_vignette(tmp_path / "small_vignette.png", np.full((10, 10), 100, np.uint8))
    with pytest.raises(CalibrationError, match="small_vignette.png: vignette is 10x10 but the images are"):
        read_vignette(ok, (W, H))
    zero = write_vignette(tmp_path / "zero_vignette.png", np.zeros((10, 10), np.uint8))
    with pytest.raises(CalibrationError, match="all zero"):
        read_vignette(zero)


def test_load_calibration_convenience(tmp_path):
    p = write(tmp_path, "camera.txt", "RadTan 80 82 59.3 44.6 -0.25 0.07 0.001 -0.0008\n120 90\nfull\n60 45\n")
    cal = load_calibration(p)
    assert cal.output_mode == "full" and cal.output_size == (60, 45) and cal.source.endswith("camera.txt")
    assert cal.describe()["undistortion"] == "remap"
    assert isinstance(CameraSpec(MODELS["fov"]).output, OutputSpec)
