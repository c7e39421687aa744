"""PSNR / SSIM against closed forms and independent implementations; the MonoGS and Photo-SLAM protocols."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.signal import convolve2d

from mgso.eval.render_metrics import (MONOGS, PHOTO_SLAM, evaluate_protocols, evaluate_renders, gaussian_window_1d,
                                      get_protocol, psnr, select_frames, select_monogs_frames,
                                      select_photo_slam_frames, ssim, ssim_map)

C1, C2 = 0.01 ** 2, 0.03 ** 2


def _images(rng, shape=(37, 45, 3)):
    """A structured image (smooth ramps + texture) and a distorted copy."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]] / 40.0
    base = 0.5 + 0.3 * np.sin(5 * xx + 3 * yy)[..., None] * np.array([1.0, 0.6, -0.4])[: shape[2]]
    a = np.clip(base + 0.1 * rng.random(shape), 0, 1)
    b = np.clip(a + 0.05 * rng.normal(size=shape) + 0.02, 0, 1)
    return a, b


def _ssim_by_2d_convolution(a, b, border):
    """Independent SSIM: a direct 2-D convolution with the 11x11 window (scipy.signal.convolve2d)."""
    g = gaussian_window_1d()
    w = np.outer(g, g)
    mode = "same" if border == "same-zero" else "valid"
    out = []
    for c in range(a.shape[2]):
        x, y = a[..., c], b[..., c]
        f = lambda z: convolve2d(z, w, mode=mode, boundary="fill", fillvalue=0.0)  # noqa: E731
        mx, my = f(x), f(y)
        sx, sy, sxy = f(x * x) - mx ** 2, f(y * y) - my ** 2, f(x * y) - mx * my
        out.append(((2 * mx * my + C1) * (2 * sxy + C2)) / ((mx ** 2 + my ** 2 + C1) * (sx + sy + C2)))
    return float(np.mean(out))


def test_window_is_the_standard_gaussian():
    g = gaussian_window_1d()
    assert g.shape == (11,) and g.sum() == pytest.approx(1.0)
    assert g[5] / g[4] == pytest.approx(np.exp(1 / (2 * 1.5 ** 2)))  # sigma 1.5


def test_psnr_closed_form_and_identity():
    rng = np.random.default_rng(0)
    a = 0.8 * rng.random((20, 30, 3))
    assert psnr(a + 0.05, a) == pytest.approx(-20 * np.log10(0.05), abs=1e-9)
    assert psnr(a, a) == np.inf
    assert psnr(a[..., 0] + 0.1, a[..., 0]) == pytest.approx(20.0, abs=1e-9)
    # a mask keeps only the selected elements' error
    b = a.copy()
    b[:5] += 0.1
    assert psnr(b, a, mask=np.arange(20)[:, None] < 5) == pytest.approx(20.0, abs=1e-9)


@pytest.mark.parametrize("border", ["same-zero", "valid"])
def test_ssim_identical_is_one(border):
    a, _ = _images(np.random.default_rng(1))
    assert ssim(a, a, border=border) == pytest.approx(1.0, abs=1e-12)


def test_ssim_constant_shift_closed_form():
    a, c = 0.4, 0.1
    x = np.full((30, 40), a)
    y = x + c
    closed = (2 * a * (a + c) + C1) / (a * a + (a + c) ** 2 + C1)  # the variances are 0: only luminance remains
    assert ssim(x, y, border="valid") == pytest.approx(closed, abs=1e-12)
    m = ssim_map(x, y, border="same-zero")
    assert np.allclose(m[5:-5, 5:-5], closed, atol=1e-12)
    # With zero padding, a pixel whose window has mass W inside the image sees mu = a W, sigma^2 = a^2 W (1 - W):
    # the map follows in closed form from W (the window mass inside the image, 1-D sums of the taps).
    g = gaussian_window_1d()
    wr = np.convolve(np.ones(30), g, mode="same")
    wc = np.convolve(np.ones(40), g, mode="same")
    W = np.outer(wr, wc)
    mx, my = a * W, (a + c) * W
    v = W * (1 - W)
    expected = (((2 * mx * my + C1) * (2 * a * (a + c) * v + C2))
                / ((mx ** 2 + my ** 2 + C1) * ((a * a + (a + c) ** 2) * v + C2)))
    np.testing.assert_allclose(m[..., 0], expected, atol=1e-12)
    assert ssim(x, y) == pytest.approx(expected.mean(), abs=1e-12)
    assert ssim(x, y) < ssim(x, y, border="valid")  # the zero-padded border lowers the mean


@pytest.mark.parametrize("border", ["same-zero", "valid"])
def test_ssim_matches_direct_2d_convolution(border):
    a, b = _images(np.random.default_rng(2))
    assert ssim(a, b, border=border) == pytest.approx(_ssim_by_2d_convolution(a, b, border), abs=1e-12)


@pytest.mark.parametrize("shape", [(40, 52), (40, 52, 3), (11, 11, 3)])
def test_ssim_valid_matches_scikit_image(shape):
    skm = pytest.importorskip("skimage.metrics")
    rng = np.random.default_rng(3)
    a = rng.random(shape)
    b = np.clip(a + 0.1 * rng.normal(size=shape), 0, 1)
    kw = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0)
    if len(shape) == 3:
        kw["channel_axis"] = -1
    ref = skm.structural_similarity(a, b, **kw)
    assert ssim(a, b, border="valid") == pytest.approx(ref, abs=1e-12)
    assert abs(ssim(a, b, border="same-zero") - ref) > 1e-4  # the two conventions really differ


def test_bad_inputs_are_refused():
    a = np.zeros((20, 20, 3))
    with pytest.raises(ValueError, match="dtype uint8"):
        ssim(a.astype(np.uint8), a)
    with pytest.raises(ValueError, match="differ in shape"):
        psnr(a, a[:10])
    with pytest.raises(ValueError, match="border must be"):
        ssim(a, a, border="reflect")
    with pytest.raises(ValueError, match="smaller than"):
        ssim(a[:8, :8], a[:8, :8], border="valid")
    with pytest.raises(ValueError, match="non-finite"):
        psnr(a + np.nan, a)


def test_monogs_frame_selection():
    # MonoGS eval_rendering: for idx in range(0, len(frames) - 1, 5): skip keyframes.
    assert select_monogs_frames(range(23), {0, 10}) == [5, 15, 20]
    assert select_monogs_frames(range(21), {0}) == [5, 10, 15]  # frame 20 is the last frame: range stops before it
    # positions, not values: a strided sequence of frame ids
    assert select_monogs_frames([100, 102, 104, 106, 108, 110, 112, 114], {100}) == [110]
    assert select_frames("MonoGS", range(12), [5]) == [0, 10]


def test_photo_slam_frame_selection():
    assert select_photo_slam_frames(range(4)) == [0, 1, 2, 3]
    assert select_frames("photo_slam", [3, 7, 9], [3]) == [3, 7, 9]  # keyframes are kept
    with pytest.raises(ValueError, match="unknown rendering protocol"):
        get_protocol("splatam")


def test_evaluate_renders_under_both_protocols():
    rng = np.random.default_rng(4)
    refs = [np.clip(rng.random((24, 32, 3)), 0.05, 0.85) for _ in range(3)]
    renders = [r + 0.1 for r in refs]  # constant error 0.1 -> PSNR 20 dB wherever nothing is clamped
    renders[0][:4] = 1.5  # out of range: MonoGS clamps the render to [0, 1], Photo-SLAM does not
    refs[1][:6] = 0.0  # MonoGS ignores elements whose reference is 0 in PSNR
    frames = [0, 5, 10]
    mono = evaluate_renders(zip(renders, refs), frames, MONOGS)
    photo = evaluate_renders(((r, g) for r, g in zip(renders, refs)), frames, PHOTO_SLAM)
    assert mono.protocol == MONOGS.name and "MonoGS" in mono.summary() and "every 5th" in mono.protocol
    assert photo.protocol == "Photo-SLAM protocol (all frames)" and photo.ssim_border == "valid"
    np.testing.assert_array_equal(mono.frame_indices, frames)
    assert mono.psnr[1] == pytest.approx(20.0, abs=1e-9)  # the zero-reference rows are ignored
    assert photo.psnr[1] < 19.0
    assert mono.psnr[2] == pytest.approx(20.0, abs=1e-9) and photo.psnr[2] == pytest.approx(20.0, abs=1e-9)
    assert mono.psnr[0] > photo.psnr[0]  # clamping 1.5 -> 1 lowers the error
    assert mono.ssim[2] == pytest.approx(ssim(renders[2], refs[2], border="same-zero"))
    assert photo.ssim[2] == pytest.approx(ssim(renders[2], refs[2], border="valid"))
    assert mono.mean_psnr == pytest.approx(np.mean(mono.psnr)) and mono.mean_ssim == pytest.approx(np.mean(mono.ssim))
    d = mono.as_dict()
    assert d["num_frames"] == 3 and d["frames"][1]["frame"] == 5 and d["protocol"] == MONOGS.name
    with pytest.raises(ValueError, match="2 image pairs for 3 frame"):
        evaluate_renders(zip(renders[:2], refs[:2]), frames, PHOTO_SLAM)
    with pytest.raises(ValueError, match="frame 10"):
        evaluate_renders(zip(renders, [refs[0], refs[1], refs[2][:5]]), frames, PHOTO_SLAM)


@pytest.mark.parametrize("border", ["same-zero", "valid"])
def test_ssim_in_strips_equals_the_whole_image(border):
    """The metrics take 32 rows at a time with the window's 5-row halo: on an image of several strips (and a last
    strip cut part-way) the map equals the direct 2-D convolution's, and so do PSNR with and without a mask."""
    a, b = _images(np.random.default_rng(7), shape=(101, 47, 3))
    assert ssim(a, b, border=border) == pytest.approx(_ssim_by_2d_convolution(a, b, border), abs=1e-12)
    m = ssim_map(a, b, border=border)
    assert m.shape == ((101, 47, 3) if border == "same-zero" else (91, 37, 3))
    mask = np.random.default_rng(8).random(a.shape[:2]) > 0.3
    d2 = (a - b) ** 2
    assert psnr(a, b) == pytest.approx(10 * np.log10(1 / d2.mean()), abs=1e-10)
    assert psnr(a, b, mask=mask) == pytest.approx(10 * np.log10(1 / d2[mask].mean()), abs=1e-10)


@pytest.mark.parametrize("border", ["same-zero", "valid"])
def test_float32_ssim_is_the_float64_figure_to_1e6_and_the_protocols_take_it(border):
    """The protocols take SSIM in float32 (as the papers' PyTorch scripts): on a 640x480 photograph-like pair
    (smooth shading, texture, a noisy render; strips of 64 rows, the last cut part-way) the float32 mean is the
    float64 one to 1e-6 (measured 1.1e-7), and its map to 2e-4 everywhere (1.1e-4: the variances' cancellation in
    flat regions, as in float32 PyTorch); the protocol's figure is the float32 function's, bit for bit. The control:
    noise of 1e-3 on the render moves the figure 800 times as far as float32 does (8e-5)."""
    rng = np.random.default_rng(11)
    a, b = _images(rng, shape=(480, 640, 3))
    a, b = a.astype(np.float32), b.astype(np.float32)
    s64, s32 = ssim(a, b, border=border), ssim(a, b, border=border, dtype=np.float32)
    assert abs(s32 - s64) < 1e-6, (s32, s64)
    m64, m32 = ssim_map(a, b, border=border), ssim_map(a, b, border=border, dtype=np.float32)
    assert m32.dtype == np.float32 and m32.shape == m64.shape and np.abs(m32 - m64).max() < 2e-4
    proto = MONOGS if border == "same-zero" else PHOTO_SLAM
    got = evaluate_renders([(b, a)], [0], proto)
    assert got.ssim[0] == ssim(np.clip(b, 0, 1), a, border=border, dtype=np.float32)
    moved = ssim(np.clip(b + 1e-3 * rng.standard_normal(b.shape).astype(np.float32), 0, 1), a, border=border)
    assert abs(moved - s64) > 10 * abs(s32 - s64)
    with pytest.raises(ValueError, match="float64 or float32"):
        ssim(a, b, dtype=np.float16)


@pytest.mark.parametrize("pipelined", [True, False])
def test_evaluate_protocols_renders_each_frame_once_with_the_same_figures(pipelined):
    rng = np.random.default_rng(5)
    refs = {i: np.clip(rng.random((40, 30, 3)), 0.0, 0.9).astype(np.float32) for i in range(12)}
    renders = {i: (r + rng.normal(0, 0.1, r.shape)).astype(np.float32) for i, r in refs.items()}
    renders[5][:3] = 1.4                                       # clamped by MonoGS only
    mono_frames, photo_frames = [0, 5, 10], list(range(12))
    calls, seen = [], []

    def render(i):
        calls.append(i)
        return renders[i]

    out = evaluate_protocols({MONOGS: mono_frames, "photo-slam": photo_frames}, render, refs.__getitem__,
                             on_frame=lambda i, r, g, keys: seen.append((i, keys)), pipelined=pipelined)
    assert calls == list(range(12))                           # each frame rendered once, in order
    assert [s[0] for s in seen] == list(range(12)) and dict(seen)[5] == ("monogs", "photo-slam")
    assert dict(seen)[6] == ("photo-slam",)
    for got, proto, frames in zip(out, (MONOGS, PHOTO_SLAM), (mono_frames, photo_frames)):
        want = evaluate_renders(((renders[i], refs[i]) for i in frames), frames, proto)
        assert got.protocol == want.protocol
        np.testing.assert_array_equal(got.frame_indices, want.frame_indices)
        np.testing.assert_array_equal(got.psnr, want.psnr)      # bit for bit
        np.testing.assert_array_equal(got.ssim, want.ssim)
    assert out[0].psnr[1] != out[1].psnr[5]                    # the clamp differs between the two protocols


def test_evaluate_protocols_with_a_render_function_a_thread_gives_the_same_figures():
    """Three render functions (as ``mgso run`` gives one a core on the CPU): every frame rendered once, by one of
    them; the references read in increasing order (a video reads forwards) and ``on_frame`` never entered twice at
    once; the figures bit for bit those of one function. The functions sleep so that the threads interleave; the
    control is that more than one of them rendered."""
    import threading

    rng = np.random.default_rng(6)
    refs = {i: np.clip(rng.random((40, 30, 3)), 0.0, 0.9).astype(np.float32) for i in range(30)}
    renders = {i: (r + rng.normal(0, 0.1, r.shape)).astype(np.float32) for i, r in refs.items()}
    mono_frames, photo_frames = list(range(0, 29, 5)), list(range(30))
    sel = {MONOGS: mono_frames, PHOTO_SLAM: photo_frames}
    by, read, inside, overlaps = {}, [], [0], []

    def make(k):
        def render(i):
            by.setdefault(i, []).append(k)
            time.sleep(0.002 * (1 + (i + k) % 3))
            return renders[i]
        return render

    def reference(i):
        read.append(i)
        return refs[i]

    def on_frame(i, r, g, keys):
        inside[0] += 1
        overlaps.append(inside[0] > 1)
        time.sleep(0.001)
        inside[0] -= 1

    out = evaluate_protocols(sel, [make(k) for k in range(3)], reference, on_frame=on_frame)
    assert sorted(by) == photo_frames and all(len(v) == 1 for v in by.values())    # each frame once
    assert len({v[0] for v in by.values()}) > 1                                     # the threads shared the work
    assert read == photo_frames and not any(overlaps) and len(overlaps) == 30
    want = evaluate_protocols(sel, lambda i: renders[i], refs.__getitem__, pipelined=False)
    for got, w in zip(out, want):
        np.testing.assert_array_equal(got.frame_indices, w.frame_indices)
        np.testing.assert_array_equal(got.psnr, w.psnr)
        np.testing.assert_array_equal(got.ssim, w.ssim)
    assert not any(t.name.startswith("mgso-eval-") for t in threading.enumerate())       # all joined


def test_evaluate_protocols_names_the_bad_frame_and_stops():
    refs = {i: np.full((20, 20, 3), 0.5, np.float32) for i in range(6)}
    rendered = []

    def render(i):
        rendered.append(i)
        return refs[i][:10] if i == 2 else refs[i] + 0.1

    with pytest.raises(ValueError, match="frame 2: .*differ in shape"):
        evaluate_protocols({PHOTO_SLAM: list(range(6))}, render, refs.__getitem__)
    assert max(rendered) <= 4                                  # stopped within the two frames in flight
    # a render function a thread: each thread ends after its frame in flight (the renders sleep, as a real one
    # leaves the interpreter lock, so that a thread cannot run through many frames before the other raises)
    refs = {i: np.full((20, 20, 3), 0.5, np.float32) for i in range(20)}
    rendered.clear()

    def slow(i):
        time.sleep(0.005)
        return render(i)

    with pytest.raises(ValueError, match="frame 2: .*differ in shape"):
        evaluate_protocols({PHOTO_SLAM: list(range(20))}, [slow, slow], refs.__getitem__)
    assert 2 in rendered and max(rendered) <= 8
    with pytest.raises(ValueError, match="no render function"):
        evaluate_protocols({PHOTO_SLAM: [0]}, [], refs.__getitem__)
    # a signal's KeyboardInterrupt in the caller's render (the first function runs on the caller's thread): raised
    # here once the other thread has ended its frame
    import threading

    rendered.clear()

    def interrupted(i):
        time.sleep(0.005)
        if i >= 4:
            raise KeyboardInterrupt
        return refs[i] + 0.1

    def good(i):
        time.sleep(0.005)
        rendered.append(i)
        return refs[i] + 0.1

    with pytest.raises(KeyboardInterrupt):
        evaluate_protocols({PHOTO_SLAM: list(range(20))}, [interrupted, good], refs.__getitem__)
    assert not any(t.name.startswith("mgso-eval-") for t in threading.enumerate())
    assert max(rendered) <= 10
    with pytest.raises(ValueError, match="selected twice"):
        evaluate_protocols({PHOTO_SLAM: [0], "photo_slam": [1]}, render, refs.__getitem__)
