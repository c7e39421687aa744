"""Rendering quality: PSNR and SSIM, and the two evaluation protocols 3DGS-SLAM papers report with.

Images are float arrays in [0, 1], ``[H, W]`` or ``[H, W, C]`` (C = 3 for RGB); both images of a pair have the same
shape. Integer images are refused (divide by 255 yourself: the metrics must not guess the range).

**PSNR** ``= 10 log10(data_range^2 / MSE)``, the MSE over all pixels and channels (``inf`` for identical images).
Optionally over a mask of elements.

**SSIM** (Wang et al. 2004) with the standard constants: an 11x11 Gaussian window of sigma 1.5 (the separable
normalised 1-D kernel ``exp(-(x - 5)^2 / 4.5)``, x = 0..10), ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2`` with
``L = data_range``, local statistics ``mu = w * x``, ``sigma^2 = w * x^2 - mu^2``, ``sigma_xy = w * xy - mu_x mu_y``
(no sample-covariance correction), computed per channel, then averaged: in float64 by :func:`ssim`'s default (the
exact figure the tests hold against a direct 2-D convolution and scikit-image to 1e-12), in float32 by the protocols
(as the papers' PyTorch scripts compute it; within 1e-6 of float64 on real renders, and 2.3x faster, which matters in
a run's evaluation of every frame). Two border conventions exist and give different numbers (by 0.001-0.02 on
320x240-640x480 images), so every figure names its ``border``:

- ``"same-zero"`` -- 'same'-size convolution with zero padding, the SSIM map averaged over **all** pixels and
  channels. This is the 3DGS training code's ``ssim`` (``F.conv2d(..., padding=window_size // 2)``), which MonoGS's
  ``utils/eval_utils.py::eval_rendering`` imports from its ``gaussian_splatting/utils/loss_utils.py`` to report its
  figures. Our default.
- ``"valid"`` -- only the pixels whose whole window lies inside the image (a 5-pixel border is dropped). This is
  ``pytorch_msssim.ssim`` (``F.conv2d(..., padding=0)``), which Photo-SLAM's evaluation script
  (``HuajianUP/Photo-SLAM-eval`` ``run.py``: ``ssim(..., data_range=1)``) reports with, and equals scikit-image's
  ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)``, which
  filters with reflection and then crops the same border.

**Protocols** (:data:`MONOGS`, :data:`PHOTO_SLAM`): which frames are evaluated and how the metrics are taken, so
that a figure can be compared with a paper's table. The caller renders the frames that :func:`select_frames` picks
and passes the pairs to :func:`evaluate_renders`, or gives :func:`evaluate_protocols` the selections of several
protocols and a render function, which renders each frame once for all of them; the result carries the protocol's
name.

- MonoGS (``eval_rendering``): frames ``0, 5, 10, ...`` by position in the sequence, stopping before the last frame
  (``range(0, len(frames) - 1, 5)``), keyframes skipped; the render clamped to [0, 1]; PSNR over the elements whose
  reference value is > 0 (``mask = gt_image > 0``); SSIM ``same-zero``.
- Photo-SLAM (``Photo-SLAM-eval/run.py``): every frame that has an estimated pose; PSNR over all elements of the
  unclamped render; SSIM ``valid`` (pytorch_msssim).

LPIPS is not provided (it needs downloaded network weights).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import cv2

__all__ = [
    "SSIM_BORDERS", "SSIM_WINDOW_SIZE", "SSIM_SIGMA", "gaussian_window_1d", "psnr", "ssim", "ssim_map",
    "RenderProtocol", "MONOGS", "PHOTO_SLAM", "PROTOCOLS", "get_protocol", "select_frames",
    "select_monogs_frames", "select_photo_slam_frames", "RenderMetrics", "evaluate_renders", "evaluate_protocols",
]

SSIM_BORDERS: tuple[str, ...] = ("same-zero", "valid")
SSIM_WINDOW_SIZE = 11
SSIM_SIGMA = 1.5
_K1, _K2 = 0.01, 0.03


def gaussian_window_1d(size: int = SSIM_WINDOW_SIZE, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """The normalised 1-D Gaussian of SSIM: ``exp(-(x - size//2)^2 / (2 sigma^2))``, x = 0..size-1, summing to 1."""
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-(x * x) / (2.0 * sigma * sigma))
    return g / g.sum()


# the protocols' SSIM precision: float32, as the papers' PyTorch scripts (MonoGS, Photo-SLAM-eval) compute it; 2.3x
# faster than float64 at 640x480 (11-13 against 27 ms a frame, one Zen 3 core) and within 1e-6 of it on renders
PROTOCOL_SSIM_DTYPE = np.float32
_STRIP_ROWS = 32  # rows of an image the metrics take at a time: the strip's float64 arrays stay in the cache


def _check_pair(a, b, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The two images as [H, W, C] arrays of their own dtype (no copy), after the checks every metric makes."""
    a, b = np.asarray(a), np.asarray(b)
    for name, x in (("rendered", a), ("reference", b)):
        if not np.issubdtype(x.dtype, np.floating):
            raise ValueError(f"{what}: the {name} image has dtype {x.dtype}; pass float images in [0, 1] "
                             f"(e.g. img.astype(np.float32) / 255)")
        if x.ndim not in (2, 3):
            raise ValueError(f"{what}: the {name} image must be [H, W] or [H, W, C], got shape {x.shape}")
    if a.shape != b.shape:
        raise ValueError(f"{what}: rendered image {a.shape} and reference {b.shape} differ in shape")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError(f"{what}: non-finite pixel values (NaN or inf)")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    return a, b


def psnr(rendered, reference, *, data_range: float = 1.0, mask=None) -> float:
    """Peak signal-to-noise ratio in dB: ``10 log10(data_range^2 / MSE)``; ``inf`` when the images are equal.

    ``mask``: optional boolean array of the image's shape (or ``[H, W]`` for all channels) selecting the elements
    the MSE is taken over.
    """
    a, b = _check_pair(rendered, reference, "psnr")
    m = None
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.ndim == 2 and np.ndim(rendered) == 3:
            m = m[..., None]                     # [H, W]: all channels
        elif m.shape != np.shape(rendered):
            raise ValueError(f"psnr: mask shape {m.shape} does not match the image {np.shape(rendered)}")
        try:
            m = np.broadcast_to(m.reshape(m.shape[:2] + (-1,)), a.shape)
        except ValueError:
            raise ValueError(f"psnr: mask shape {np.shape(mask)} does not match the image "
                             f"{np.shape(rendered)}") from None
        if not m.any():
            raise ValueError("psnr: the mask selects no pixel")
    # the squared differences in float64, a strip of rows at a time (the same sum as over the whole image, in
    # another order: a few ulp)
    total, count = 0.0, 0
    for y0 in range(0, a.shape[0], _STRIP_ROWS):
        d = a[y0:y0 + _STRIP_ROWS].astype(np.float64)
        d -= b[y0:y0 + _STRIP_ROWS]
        d *= d
        if m is None:
            total += float(d.sum())
            count += d.size
        else:
            ms = m[y0:y0 + _STRIP_ROWS]
            total += float(d[ms].sum())
            count += int(np.count_nonzero(ms))
    mse = total / count
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range * data_range / mse))


def _blur(x: np.ndarray, g: np.ndarray, rows: slice) -> np.ndarray:
    """``rows`` of the 11x11 Gaussian blur of ``x`` ``[h, w, C]``: zero padding ('constant', 0) ==
    F.conv2d(x, outer(g, g), padding=5) at the array's edges; OpenCV's separable filter in ``x``'s precision (float64
    or float32, ``g`` in the same; 20-40x faster than scipy.ndimage, the same sums to round-off), channel by channel
    beyond OpenCV's 4."""
    if x.shape[2] > 4:
        return np.stack([_blur(x[..., c:c + 1], g, rows)[..., 0] for c in range(x.shape[2])], axis=-1)
    return cv2.sepFilter2D(x, -1, g, g, borderType=cv2.BORDER_CONSTANT).reshape(x.shape)[rows]


def _ssim_strips(rendered, reference, border: str, data_range: float, what: str, dtype=np.float64):
    """The SSIM map a strip of rows at a time (``[rows, W, C]``, or the ``valid`` crop of them), top to bottom,
    computed in ``dtype`` (float64 or float32).

    Each strip is blurred with the 5 rows above and below it that the window reaches (real rows inside the image,
    OpenCV's zero padding at its edges), so the strips' values are the whole image's, bit for bit; strips of 32 float64
    rows (64 float32 rows) stay in the cache, where whole-image float64 temporaries (7 MB each at 640x480) cost twice
    the time in memory traffic and page faults."""
    if border not in SSIM_BORDERS:
        raise ValueError(f"ssim: border must be one of {SSIM_BORDERS}, got {border!r}")
    dtype = np.dtype(dtype)
    if dtype not in (np.float64, np.float32):
        raise ValueError(f"ssim: dtype must be float64 or float32, got {dtype}")
    a, b = _check_pair(rendered, reference, what)
    H, W = a.shape[:2]
    if border == "valid" and (H < SSIM_WINDOW_SIZE or W < SSIM_WINDOW_SIZE):
        raise ValueError(f"ssim: a {H}x{W} image is smaller than the {SSIM_WINDOW_SIZE}x{SSIM_WINDOW_SIZE} window "
                         f"(border='valid' needs at least that)")
    g = gaussian_window_1d().astype(dtype)
    r = SSIM_WINDOW_SIZE // 2
    c1 = dtype.type((_K1 * data_range) ** 2)
    c2 = dtype.type((_K2 * data_range) ** 2)
    lo, hi = (r, H - r) if border == "valid" else (0, H)
    cols = slice(r, W - r) if border == "valid" else slice(0, W)
    step = _STRIP_ROWS * 8 // dtype.itemsize
    for y0 in range(lo, hi, step):
        y1 = min(y0 + step, hi)
        s0, s1 = max(y0 - r, 0), min(y1 + r, H)
        rows = slice(y0 - s0, y1 - s0)        # the strip's own rows among the halo's
        A = np.ascontiguousarray(a[s0:s1], dtype=dtype)     # a copy only where needed (float32 renders: none)
        B = np.ascontiguousarray(b[s0:s1], dtype=dtype)
        mu1, mu2 = _blur(A, g, rows), _blur(B, g, rows)
        s11, s22, s12 = _blur(A * A, g, rows), _blur(B * B, g, rows), _blur(A * B, g, rows)
        mu12 = mu1 * mu2
        mu1 *= mu1
        mu2 *= mu2
        s11 -= mu1
        s22 -= mu2
        s12 -= mu12
        num = (dtype.type(2.0) * mu12 + c1) * (dtype.type(2.0) * s12 + c2)
        mu1 += mu2
        mu1 += c1
        s11 += s22
        s11 += c2
        yield (num / (mu1 * s11))[:, cols]


def ssim_map(rendered, reference, *, border: str = "same-zero", data_range: float = 1.0,
             dtype=np.float64) -> np.ndarray:
    """Per-pixel SSIM, ``[H, W, C]`` for ``border="same-zero"`` and ``[H - 10, W - 10, C]`` for ``"valid"``, in
    ``dtype`` (float64 or float32)."""
    strips = list(_ssim_strips(rendered, reference, border, data_range, "ssim", dtype))
    if not strips:
        return np.zeros((0,) + np.shape(rendered)[1:], dtype)
    return np.concatenate(strips, axis=0)


def ssim(rendered, reference, *, border: str = "same-zero", data_range: float = 1.0, dtype=np.float64) -> float:
    """Mean SSIM over pixels and channels; ``border`` is ``"same-zero"`` (3DGS / MonoGS, default) or ``"valid"``
    (pytorch_msssim / Photo-SLAM / scikit-image); ``dtype``: the precision of the local statistics, float64 (exact to
    round-off) or float32 (what the protocols use, as the papers' scripts; the mean is summed in float64 either way);
    see the module text."""
    total, count = 0.0, 0
    for m in _ssim_strips(rendered, reference, border, data_range, "ssim", dtype):
        total += float(m.sum(dtype=np.float64))
        count += m.size
    return total / count if count else float("nan")


# ------------------------------------------------------------------------------------------------- protocols
@dataclass(frozen=True)
class RenderProtocol:
    """How a paper's rendering figures are taken. ``name`` is printed next to every figure."""

    key: str  # short id: "monogs" or "photo-slam"
    name: str  # e.g. "MonoGS protocol (every 5th frame, keyframes excluded)"
    frame_stride: int  # evaluate every n-th frame by position in the sequence
    exclude_keyframes: bool
    exclude_last_frame: bool  # MonoGS iterates range(0, len(frames) - 1, 5)
    clamp_rendered: bool  # clamp the render to [0, 1] before the metrics
    psnr_mask_zero_reference: bool  # PSNR only over elements whose reference value is > 0
    ssim_border: str


MONOGS = RenderProtocol(key="monogs", name="MonoGS protocol (every 5th frame, keyframes excluded)", frame_stride=5,
                        exclude_keyframes=True, exclude_last_frame=True, clamp_rendered=True,
                        psnr_mask_zero_reference=True, ssim_border="same-zero")
PHOTO_SLAM = RenderProtocol(key="photo-slam", name="Photo-SLAM protocol (all frames)", frame_stride=1,
                            exclude_keyframes=False, exclude_last_frame=False, clamp_rendered=False,
                            psnr_mask_zero_reference=False, ssim_border="valid")
PROTOCOLS: dict[str, RenderProtocol] = {p.key: p for p in (MONOGS, PHOTO_SLAM)}


def get_protocol(protocol: str | RenderProtocol) -> RenderProtocol:
    """A protocol by key (``"monogs"``, ``"photo-slam"``; case and ``_`` / ``-`` insensitive) or as given."""
    if isinstance(protocol, RenderProtocol):
        return protocol
    key = str(protocol).lower().replace("_", "-")
    if key == "photoslam":
        key = "photo-slam"
    if key not in PROTOCOLS:
        raise ValueError(f"unknown rendering protocol {protocol!r}; known: {sorted(PROTOCOLS)}")
    return PROTOCOLS[key]


def select_monogs_frames(frame_indices: Sequence[int], keyframe_indices: Iterable[int] = ()) -> list[int]:
    """MonoGS's evaluation frames: positions 0, 5, 10, ... of ``frame_indices`` (the tracked frames in order),
    before the last position (``range(0, n - 1, 5)``), minus the keyframes. Returns frame indices (values)."""
    return select_frames(MONOGS, frame_indices, keyframe_indices)


def select_photo_slam_frames(frame_indices: Sequence[int]) -> list[int]:
    """Photo-SLAM's evaluation frames: every frame with a pose, keyframes included."""
    return select_frames(PHOTO_SLAM, frame_indices, ())


def select_frames(protocol: str | RenderProtocol, frame_indices: Sequence[int],
                  keyframe_indices: Iterable[int] = ()) -> list[int]:
    """The frame indices (values of ``frame_indices``) that ``protocol`` evaluates, in order."""
    p = get_protocol(protocol)
    frames = [int(f) for f in frame_indices]
    if len(set(frames)) != len(frames):
        raise ValueError("select_frames: frame_indices has duplicates")
    kf = {int(k) for k in keyframe_indices} if p.exclude_keyframes else set()
    end = len(frames) - 1 if p.exclude_last_frame else len(frames)
    return [frames[pos] for pos in range(0, max(end, 0), p.frame_stride) if frames[pos] not in kf]


@dataclass(frozen=True)
class RenderMetrics:
    """Per-frame and mean PSNR (dB) and SSIM under a named protocol."""

    protocol: str  # the protocol's name, printed next to the figures
    protocol_key: str
    ssim_border: str
    frame_indices: np.ndarray  # [F] int
    psnr: np.ndarray  # [F] dB
    ssim: np.ndarray  # [F]
    mean_psnr: float
    mean_ssim: float

    @property
    def num_frames(self) -> int:
        return int(len(self.frame_indices))

    def summary(self) -> str:
        return (f"PSNR {self.mean_psnr:.2f} dB, SSIM {self.mean_ssim:.4f} ({self.protocol}, {self.num_frames} "
                f"frames, SSIM border '{self.ssim_border}')")

    def as_dict(self) -> dict:
        return {"protocol": self.protocol, "protocol_key": self.protocol_key, "ssim_border": self.ssim_border,
                "num_frames": self.num_frames, "mean_psnr_db": self.mean_psnr, "mean_ssim": self.mean_ssim,
                "frames": [{"frame": int(f), "psnr_db": float(p), "ssim": float(s)}
                           for f, p, s in zip(self.frame_indices, self.psnr, self.ssim)]}


def _frame_figures(p: RenderProtocol, rendered, reference) -> tuple[float, float]:
    """One frame's PSNR and SSIM the way ``p`` takes them."""
    rendered = np.asarray(rendered)
    if p.clamp_rendered and np.issubdtype(rendered.dtype, np.floating):
        rendered = np.clip(rendered, 0.0, 1.0)
    mask = (np.asarray(reference) > 0) if p.psnr_mask_zero_reference else None
    return (psnr(rendered, reference, mask=mask),
            ssim(rendered, reference, border=p.ssim_border, dtype=PROTOCOL_SSIM_DTYPE))


def _metrics(p: RenderProtocol, frames, ps, ss) -> RenderMetrics:
    if len(ps) != len(frames):
        raise ValueError(f"evaluate_renders: {len(ps)} image pairs for {len(frames)} frame indices")
    if not ps:
        raise ValueError(f"evaluate_renders: no frame to evaluate under the {p.name}")
    psnr_arr, ssim_arr = np.asarray(ps, np.float64), np.asarray(ss, np.float64)
    return RenderMetrics(protocol=p.name, protocol_key=p.key, ssim_border=p.ssim_border,
                         frame_indices=np.asarray(frames, np.int64), psnr=psnr_arr, ssim=ssim_arr,
                         mean_psnr=float(psnr_arr.mean()), mean_ssim=float(ssim_arr.mean()))


def evaluate_renders(pairs: Iterable[tuple[np.ndarray, np.ndarray]], frame_indices: Sequence[int],
                     protocol: str | RenderProtocol = MONOGS) -> RenderMetrics:
    """PSNR and SSIM of ``(rendered, reference)`` pairs (float [0, 1] images), one per entry of ``frame_indices``
    (normally ``select_frames(protocol, ...)``), taken the way ``protocol`` takes them. ``pairs`` may be a generator,
    so frames can be rendered one at a time. The mean PSNR is the mean of per-frame PSNRs (as both papers' scripts);
    a frame equal to its reference (PSNR = inf) makes the mean inf."""
    p = get_protocol(protocol)
    frames = [int(f) for f in frame_indices]
    ps, ss = [], []
    for k, (rendered, reference) in enumerate(pairs):
        if k >= len(frames):
            raise ValueError(f"evaluate_renders: more image pairs than the {len(frames)} frame indices given")
        try:
            pk, sk = _frame_figures(p, rendered, reference)
        except ValueError as e:
            raise ValueError(f"frame {frames[k]}: {e}") from None
        ps.append(pk)
        ss.append(sk)
    return _metrics(p, frames, ps, ss)


def evaluate_protocols(selections: Mapping[str | RenderProtocol, Sequence[int]],
                       render: Callable[[int], np.ndarray] | Sequence[Callable[[int], np.ndarray]],
                       reference: Callable[[int], np.ndarray], *,
                       on_frame: Callable[[int, np.ndarray, np.ndarray, tuple[str, ...]], Any] | None = None,
                       pipelined: bool = True) -> list[RenderMetrics]:
    """The figures of several protocols, each frame rendered once: ``selections`` maps each protocol to its frames
    (``select_frames``); ``render(i)`` and ``reference(i)`` give frame ``i``'s render and reference image. The
    frames of all selections are taken in increasing order; each frame's figures are those
    :func:`evaluate_renders` gives (bit for bit), one :class:`RenderMetrics` per protocol, in ``selections``' order.

    ``on_frame(i, rendered, reference, keys)`` is called once a frame's figures are taken (``keys``: the protocols
    that selected it), e.g. to save the render or advance a progress bar. ``pipelined``: the figures and
    ``on_frame`` of a frame run in a worker thread while the next frame renders (the metrics are NumPy and OpenCV,
    which leave the interpreter lock to the renderer); at most two frames are in flight. An exception in either
    thread stops the evaluation (the worker's frame finishes first) and is raised here; a ``ValueError`` about an
    image names its frame.

    ``render`` may be a sequence of render functions, each safe to call beside the others (a rasteriser each): then
    one thread a function (the first is the caller's) takes the next frame, renders it and takes its figures, so
    that as many frames are in flight as there are functions (for a CPU whose cores each render a frame on one
    thread: the render's serial parts, the reference and the metrics then overlap). ``reference`` is called under a
    lock, in increasing frame order (a video is read forwards), and ``on_frame`` under another (calls never
    overlap). The figures are the same as with one function.
    """
    protos = [get_protocol(p) for p in selections]
    if len({p.key for p in protos}) != len(protos):
        raise ValueError("evaluate_protocols: a protocol is selected twice")
    sel = [[int(f) for f in frames] for frames in selections.values()]
    members: dict[int, list[int]] = {}
    for j, frames in enumerate(sel):
        if len(set(frames)) != len(frames):
            raise ValueError(f"evaluate_protocols: the {protos[j].name}'s frames have duplicates")
        for f in frames:
            members.setdefault(f, []).append(j)
    figures: dict[tuple[int, int], tuple[float, float]] = {}

    def finish(i: int, rendered, ref) -> None:
        try:
            for j in members[i]:
                figures[(j, i)] = _frame_figures(protos[j], rendered, ref)
        except ValueError as e:
            raise ValueError(f"frame {i}: {e}") from None
        if on_frame is not None:
            on_frame(i, rendered, ref, tuple(protos[j].key for j in members[i]))

    order = sorted(members)
    renders = [render] if callable(render) else list(render)
    if not renders:
        raise ValueError("evaluate_protocols: no render function")
    if len(renders) > 1:
        _frames_in_parallel(order, renders, reference, finish)
    elif not pipelined:
        for i in order:
            finish(i, renders[0](i), reference(i))
    else:
        from concurrent.futures import ThreadPoolExecutor
        pending: list = []
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="mgso-eval") as pool:
            try:
                for i in order:
                    rendered, ref = renders[0](i), reference(i)
                    while len(pending) >= 2:
                        pending.pop(0).result()
                    pending.append(pool.submit(finish, i, rendered, ref))
                for fut in pending:
                    fut.result()
            finally:
                for fut in pending:
                    fut.cancel()
    return [_metrics(p, sel[j], [figures[(j, i)][0] for i in sel[j]], [figures[(j, i)][1] for i in sel[j]])
            for j, p in enumerate(protos)]


def _frames_in_parallel(order: Sequence[int], renders: Sequence[Callable[[int], np.ndarray]],
                        reference: Callable[[int], np.ndarray], finish: Callable[[int, Any, Any], None]) -> None:
    """:func:`evaluate_protocols` with several render functions: a thread each (the first function on the calling
    thread), each taking the next frame of ``order`` and its reference under one lock and ``finish``-ing it under
    another. The first exception (a thread's, or the caller's, e.g. a signal's) stops every thread after its current
    frame and is raised once they have all ended."""
    import threading

    frames = iter(order)
    take, done = threading.Lock(), threading.Lock()
    stop = threading.Event()
    errors: list[BaseException] = []

    def work(render: Callable[[int], np.ndarray]) -> None:
        try:
            while not stop.is_set():
                with take:
                    i = next(frames, None)
                    if i is None:
                        return
                    ref = reference(i)
                rendered = render(i)
                with done:
                    finish(i, rendered, ref)
        except BaseException as e:  # noqa: BLE001 - handed to the caller
            errors.append(e)
            stop.set()

    threads = [threading.Thread(target=work, args=(r,), name=f"mgso-eval-{k + 1}", daemon=True)
               for k, r in enumerate(renders[1:])]
    for t in threads:
        t.start()
    try:
        work(renders[0])
    finally:
        stop.set()
        for t in threads:
            t.join()
    if errors:
        raise errors[0]
