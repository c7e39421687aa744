"""The browser viewer (docs/viewer.md): a live run (``mgso run --viewer``) or a finished one (``mgso view RUN_DIR``).

Built on viser (https://viser.studio, the optional ``viewer`` extra): a web server in this process that a browser
opens. It shows the Gaussian map as splats, DSO's marginalised points, the trajectory and the keyframe frusta (the
ground truth beside them, Sim(3)-aligned to the estimate, when the sequence has it), the current frame with its
tracking status, and a panel of figures; controls: pause the view (and optionally the run), follow the camera,
show or hide each layer, render the map from the browser's view with mgso's own rasteriser.

**The viewer never slows the odometry.** :class:`LiveViewer` is an :class:`~mgso.observers.Observer` whose callbacks
only store references to the newest values (O(1) each, no copies, no locks held for long, never a wait unless the
user paused the run); a thread of its own pushes to viser at a bounded rate (:data:`FRAME_HZ` for the frame, the
trajectory and the panel, :data:`MAP_HZ` for the map) and skips what changed in between rather than queueing it. The
map is never read directly: the viewer asks the mapper for a copy (``mapper.request_snapshot``), which the mapper makes
at its next safe point, and shows the newest copy published; it asks only while a browser is connected.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from mgso.geometry import matrix_to_quat_wxyz
from mgso.io.trajectory import Trajectory
from mgso.messages import sim3_apply_to_pose
from mgso.observers import Observer

__all__ = ["ViewerError", "ViewerScene", "LiveViewer", "open_run", "require_viser", "INSTALL_HINT", "FRAME_HZ",
           "MAP_HZ", "MAX_SPLATS", "RENDER_WIDTH", "DEFAULT_PORT", "DEFAULT_HOST", "check_address"]

log = logging.getLogger(__name__)

INSTALL_HINT = 'pip install "mgso[viewer]"'
#: How often the viewer thread pushes the current frame, the trajectory, the keyframes and the panel (Hz).
FRAME_HZ = 4.0
#: How often it asks the mapper for a copy of the map and pushes the newest one (Hz).
MAP_HZ = 1.0
#: At most this many Gaussians go to the browser (the most opaque; a browser draws a few hundred thousand smoothly).
MAX_SPLATS = 300_000
#: Width of "render from this view" images (the height follows the browser's aspect).
RENDER_WIDTH = 480
DEFAULT_PORT = 8080
DEFAULT_HOST = "127.0.0.1"
#: Width of the current-frame image in the panel (downscaled by striding, no copy beyond the small image).
PANEL_IMAGE_WIDTH = 320

_COLORS = {"trajectory": (230, 90, 20), "groundtruth": (40, 160, 60), "keyframe": (30, 90, 220),
           "current": (220, 30, 30)}
_LAYERS = ("gaussians", "points", "trajectory", "keyframes", "groundtruth", "current")
_LAYER_LABELS = {"gaussians": "Gaussian map", "points": "DSO points", "trajectory": "Trajectory",
                 "keyframes": "Keyframes", "groundtruth": "Ground truth", "current": "Current camera"}



class _Watched:
    """The frames of a run seen by the viewer on their way (:meth:`LiveViewer.watch`); any other attribute is the
    source's."""

    def __init__(self, frames: Iterable, recent):
        self._frames = frames
        self._recent = recent

    def __iter__(self) -> Iterator:
        it = iter(self._frames)
        try:
            for f in it:
                self._recent.append(f)
                yield f
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.__dict__["_frames"], name)

class ViewerError(Exception):
    """A one-line user-facing error of the viewer (viser missing, a run folder without what it needs)."""


def require_viser():
    """The viser module, or :class:`ViewerError` with the install hint."""
    try:
        import viser
    except ImportError:
        raise ViewerError(f"the viewer needs viser, which is not installed: {INSTALL_HINT}") from None
    return viser


# ------------------------------------------------------------------------------------------------ geometry
def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (viser's order)."""
    return matrix_to_quat_wxyz(R)


def _rotation(wxyz) -> np.ndarray:
    w, x, y, z = (float(v) for v in wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def camera_for_view(wxyz, position, fov: float, aspect: float, width: int = RENDER_WIDTH):
    """A pinhole camera and the world-to-camera matrix of a browser view (viser's cameras are OpenCV's, as mgso's:
    x right, y down, z forward; ``fov`` vertical in radians, ``aspect`` width / height)."""
    from mgso.camera import PinholeCamera

    w = int(width)
    h = max(8, int(round(w / max(float(aspect), 1e-3))))
    fy = 0.5 * h / math.tan(0.5 * float(fov))
    cam = PinholeCamera(fy, fy, (w - 1) / 2.0, (h - 1) / 2.0, w, h)
    R = _rotation(wxyz)
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ np.asarray(position, np.float64)
    return cam, T


def _small_image(img: np.ndarray, width: int = PANEL_IMAGE_WIDTH, hi: float | None = None) -> np.ndarray:
    """uint8 RGB no wider than ``width`` (by striding: the copy is of the small image only); a float image's white is
    ``hi`` (default: 1 when its values are in [0, 1], else 255)."""
    a = np.asarray(img)
    step = max(1, int(math.ceil(a.shape[1] / width)))
    a = a[::step, ::step]
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if np.issubdtype(a.dtype, np.floating):
        if hi is None:
            hi = 1.0 if a.max(initial=0.0) <= 1.0 + 1e-6 else 255.0
        a = np.clip(a * (255.0 / hi), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a[:, :, :3].astype(np.uint8))


def _segments(positions: np.ndarray) -> np.ndarray:
    """(N-1, 2, 3) line segments joining consecutive positions."""
    p = np.asarray(positions, np.float32)
    return np.stack([p[:-1], p[1:]], axis=1)


def _align_groundtruth(est_t, est_p, gt_t, gt_p) -> np.ndarray | None:
    """Ground-truth positions moved onto the estimate by the Sim(3) of the matched pairs (``None``: too few)."""
    from mgso.geometry import umeyama_alignment
    from mgso.io.trajectory import matching_time_indices

    if len(est_t) < 3 or len(gt_t) < 3:
        return None
    i, j = matching_time_indices(est_t, gt_t, max_diff=0.02)
    if len(i) < 3:
        return None
    try:
        a = umeyama_alignment(np.asarray(gt_p)[j], np.asarray(est_p)[i], with_scale=True)
    except ValueError:
        return None
    return a.apply_points(gt_p)


def check_address(host: str, port: int) -> None:
    """Refuse, in one line, an address the viewer could never serve on (viser's own thread would print a traceback
    for a port out of range and wait forever, and say nothing for a host that is not this machine's): the port in
    0-65535, the host a name or address this machine can listen on."""
    import socket

    if not isinstance(port, int) or not 0 <= port <= 65535:
        raise ViewerError(f"viewer port {port!r} is not a port number (1-65535, or 0: any free port)")
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise ViewerError(f"viewer host {host!r} is not an address this machine knows: "
                          f"{getattr(exc, 'strerror', None) or exc}") from None
    errors = []
    for family, kind, proto, _name, addr in infos:
        try:
            with socket.socket(family, kind, proto) as s:
                s.bind((addr[0], 0, *addr[2:]))      # any free port: only the host is tested here
            return
        except OSError as exc:
            errors.append(exc.strerror or str(exc))
    raise ViewerError(f"the viewer cannot listen on {host!r}: {errors[0] if errors else 'no address'} "
                      "(use 127.0.0.1, or 0.0.0.0 for every interface of this machine)")


# ------------------------------------------------------------------------------------------------ the scene
class ViewerScene:
    """A viser server with mgso's layers and panel; what both the live viewer and ``mgso view`` draw on.

    ``renderer(camera, world_to_cam) -> ticket`` asks for a render of the map from a browser's view (``None``: no
    button); the image arrives through :meth:`show_render`."""

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *, title: str = "mgso",
                 live: bool = True, renderer: Callable | None = None):
        check_address(host, port)
        viser = require_viser()
        # a browser tab that closes mid-handshake is logged by websockets with a traceback: not the user's problem
        logging.getLogger("websockets").setLevel(logging.CRITICAL)
        with contextlib.redirect_stdout(io.StringIO()):       # viser prints a banner; we print one line ourselves
            try:
                self.server = viser.ViserServer(host=host, port=int(port), label=title, verbose=False)
            except OSError as exc:
                raise ViewerError(f"the viewer cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self.host = host
        self.port = int(self.server.get_port())
        self.renderer = renderer
        self.scale = 0.1                 # frustum size: follows the trajectory's extent
        self._lock = threading.Lock()
        self._nodes: dict[str, Any] = {}
        self.pushed = {"splats": 0, "points": 0, "frames": 0}
        srv = self.server
        srv.scene.set_up_direction("-y")          # mgso's cameras have y down: the first camera's up is -y
        gui = srv.gui
        self.stats = gui.add_markdown("*waiting for the first frame*")
        self.frame_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="current frame", visible=False)
        with gui.add_folder("Controls"):
            self.pause_view = gui.add_checkbox("Pause view", False,
                                               hint="freeze the display; the run goes on (live runs)")
            self.pause_run = gui.add_checkbox("Pause the run too", False, disabled=not live,
                                              hint="hold the odometry before its next frame until unticked")
            self.follow = gui.add_checkbox("Follow camera", False, disabled=not live,
                                           hint="move the view behind the current camera")
            self.render_button = gui.add_button("Render map from this view", disabled=renderer is None)
        self.render_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="mgso render", visible=False)
        with gui.add_folder("Layers"):
            self.layers = {k: gui.add_checkbox(_LAYER_LABELS[k], True) for k in _LAYERS}
        for name, box in self.layers.items():
            box.on_update(lambda _e, n=name: self._set_visible(n))
        self.render_button.on_click(self._on_render_click)
        self._render_ticket: int | None = None
        self.closed = threading.Event()
        self.url = f"http://{'localhost' if host == '0.0.0.0' else host}:{self.port}"

    # ------------------------------------------------------------------ layers
    def _set_visible(self, layer: str) -> None:
        vis = bool(self.layers[layer].value)
        with self._lock:
            for name, h in self._nodes.items():
                if name.split("/")[1] == layer:
                    h.visible = vis

    def _put(self, name: str, handle) -> None:
        with self._lock:
            self._nodes[name] = handle

    def _visible(self, name: str) -> bool:
        return bool(self.layers[name.split("/")[1]].value)

    def has_node(self, name: str) -> bool:
        """Whether the server's scene holds a node ``name`` (what a browser that connects receives)."""
        return name in getattr(self.server.scene, "_handle_from_node_name", self._nodes)

    def set_splats(self, means, covariances, colors, opacities) -> None:
        n = len(means)
        if n == 0:
            return
        h = self.server.scene.add_gaussian_splats(
            "/gaussians/map", centers=np.asarray(means, np.float32),
            # viser sends covariances as float16: a huge Gaussian (a far-away floater) would overflow to inf
            covariances=np.clip(np.asarray(covariances, np.float32), -6.0e4, 6.0e4),
            rgbs=np.clip(np.asarray(colors, np.float32), 0, 1),
            opacities=np.asarray(opacities, np.float32).reshape(n, 1), visible=self._visible("/gaussians"))
        self._put("/gaussians/map", h)
        self.pushed["splats"] += 1

    def set_points(self, points, colors) -> None:
        if len(points) == 0:
            return
        points = np.asarray(points, np.float32)
        h = self.server.scene.add_point_cloud(
            "/points/dso", points=points,
            # viser sends float16 by default: points beyond 65504 (a far point of a long run) would overflow to inf
            precision="float32" if np.abs(points).max(initial=0.0) > 6.0e4 else "float16",
            colors=(np.clip(np.asarray(colors, np.float32), 0, 1) * 255).astype(np.uint8),
            point_size=0.01 * self.scale, point_shape="circle", point_shading="flat",
            visible=self._visible("/points"))
        self._put("/points/dso", h)
        self.pushed["points"] += 1

    def set_path(self, layer: str, positions: np.ndarray) -> None:
        if len(positions) < 2:
            return
        h = self.server.scene.add_line_segments(
            f"/{layer}/path", _segments(positions), colors=_COLORS[layer], thickness=2.0,
            thickness_units="screen", visible=self._visible(f"/{layer}"))
        self._put(f"/{layer}/path", h)

    def set_frustum(self, name: str, cam_to_world: np.ndarray, fov: float, aspect: float, color,
                    image: np.ndarray | None = None, scale: float | None = None) -> None:
        T = np.asarray(cam_to_world, np.float64)
        h = self.server.scene.add_camera_frustum(
            name, fov=float(fov), aspect=float(aspect), scale=float(scale or self.scale), color=color,
            thickness=1.5, thickness_units="screen", image=image, wxyz=_quat_wxyz(T[:3, :3]), position=T[:3, 3],
            visible=self._visible(name))
        self._put(name, h)

    def move_frustum(self, name: str, cam_to_world: np.ndarray) -> bool:
        """Move an existing frustum (False when there is none yet)."""
        with self._lock:
            h = self._nodes.get(name)
        if h is None:
            return False
        T = np.asarray(cam_to_world, np.float64)
        h.wxyz = _quat_wxyz(T[:3, :3])
        h.position = T[:3, 3]
        return True

    def set_stats(self, lines: list[str]) -> None:
        self.stats.content = "\n\n".join(lines)

    def set_frame_image(self, img: np.ndarray, label: str, hi: float | None = None) -> None:
        self.frame_image.image = _small_image(img, hi=hi)
        self.frame_image.label = label
        self.frame_image.visible = True

    def follow_camera(self, cam_to_world: np.ndarray) -> None:
        T = np.asarray(cam_to_world, np.float64)
        c, R = T[:3, 3], T[:3, :3]
        d = 4.0 * self.scale
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position = c - d * R[:, 2] - 0.5 * d * R[:, 1]
                client.camera.look_at = c + d * R[:, 2]

    def frame_view(self, cam_to_world: np.ndarray, points: np.ndarray | None = None) -> None:
        """Open a browser's first view behind the camera ``cam_to_world`` (the first keyframe), looking where it
        looked, at the median depth of ``points`` in front of it: the first picture shows the scene and its first
        camera, not the origin of a world whose units are the odometry's."""
        T = np.asarray(cam_to_world, np.float64)
        centre, forward, up = T[:3, 3], T[:3, 2], -T[:3, 1]       # mgso's cameras look along +z with y down
        depth = 0.0
        if points is not None and len(points):
            d = (np.asarray(points, np.float64) - centre) @ forward
            d = d[np.isfinite(d) & (d > 0)]
            depth = float(np.median(d)) if len(d) else 0.0
        if not depth > 0:
            depth = 50.0 * self.scale                             # no points: a few frustum sizes ahead
        ic = self.server.initial_camera
        ic.position = tuple(centre - 0.5 * depth * forward)
        ic.look_at = tuple(centre + depth * forward)
        ic.up = tuple(up)

    def update_scale(self, positions: np.ndarray) -> None:
        if len(positions) >= 2:
            ext = float(np.linalg.norm(np.ptp(np.asarray(positions), axis=0)))
            if ext > 0:
                self.scale = max(0.02 * ext, 1e-3)

    # ------------------------------------------------------------------ render from the view
    def _on_render_click(self, event) -> None:
        client = getattr(event, "client", None)
        if client is None or self.renderer is None:
            return
        cam = client.camera
        camera, w2c = camera_for_view(cam.wxyz, cam.position, cam.fov, cam.aspect)
        self.render_image.label = "mgso render: waiting for the mapper ..."
        try:
            self._render_ticket = self.renderer(camera, w2c)
        except Exception as exc:  # noqa: BLE001 - shown in the panel, the run goes on
            self.render_image.label = f"mgso render failed: {exc}"
            log.debug("render request failed", exc_info=True)

    @property
    def render_ticket(self) -> int | None:
        return self._render_ticket

    def show_render(self, ticket: int, image: np.ndarray) -> None:
        self.render_image.image = np.clip(np.asarray(image)[:, :, :3] * 255.0, 0, 255).astype(np.uint8)
        self.render_image.label = f"mgso render #{ticket} (its own rasteriser)"
        self.render_image.visible = True

    def clients(self) -> int:
        return len(self.server.get_clients())

    def close(self) -> None:
        self.closed.set()
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()


# ------------------------------------------------------------------------------------------------ live
class LiveViewer(Observer):
    """The live viewer of a run: an observer (callbacks store the newest values) plus a thread that pushes them to
    a :class:`ViewerScene` at :data:`FRAME_HZ` / :data:`MAP_HZ` (see the module doc).

    Use: ``v = LiveViewer(host, port, groundtruth=seq.groundtruth); v.start()``; pass it to the system as an
    observer, :meth:`attach` the :class:`~mgso.system.System` (for the mapper's snapshots and renders) and wrap the
    frames with :meth:`watch` (for the current image); :meth:`close` at the end."""

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *, groundtruth=None,
                 frame_hz: float = FRAME_HZ, map_hz: float = MAP_HZ, max_splats: int = MAX_SPLATS):
        if frame_hz <= 0 or map_hz <= 0:
            raise ViewerError(f"viewer rates must be > 0, got frame_hz={frame_hz}, map_hz={map_hz}")
        require_viser()
        self.host, self.port = host, int(port)
        self.frame_hz, self.map_hz, self.max_splats = float(frame_hz), float(map_hz), int(max_splats)
        self.groundtruth = groundtruth
        self.scene: ViewerScene | None = None
        self._mapper = None
        self._serve_while_paused = False
        self._closed = threading.Event()
        self._run_gate = threading.Event()        # set: the run may go on
        self._run_gate.set()
        self._thread: threading.Thread | None = None
        # the newest values (written by the callbacks, read by the viewer thread; plain references)
        self._recent: deque = deque(maxlen=4)     # the newest input frames (mgso.io.Frame; real time reads ahead)
        self._last = None                         # the newest OdometryFrame
        self._poses: list = []                    # (timestamp, cam_to_world) of every frame with a pose
        self._kf_poses: dict[int, np.ndarray] = {}
        self._kf_frame: dict[int, int] = {}
        self._camera = None                       # the keyframes' pinhole camera
        self._points: list = []                   # PointsMessages not yet merged by the viewer thread
        self._closer = None                       # the system's LoopCloser (attach): frame poses into its world
        self._loop_events: list = []              # (LoopCorrection, PointsMessages before it), on_loop_closed
        self.loops = 0
        self._times: deque = deque(maxlen=32)     # arrival times of the newest frames (frames per second)
        self.frames = 0
        self.keyframes = 0
        self.losses = 0
        self.paused_seconds = 0.0                 # how long "Pause the run too" held the odometry
        self.num_gaussians = 0
        self._lost = False
        self.ended = False
        self.info: Any = None
        # the viewer thread's own state
        self._cloud_p: list[np.ndarray] = []
        self._cloud_c: list[np.ndarray] = []
        self._cloud_n = 0
        self._cloud_msg: list[int] = []           # the PointsMessage (index in _points) of each cloud part
        self._loops_applied = 0
        self._path: tuple = (0, 0, np.zeros((0, 3)), np.zeros(0))    # (poses, loops, positions, times) corrected
        self._snap = None
        self._prev_snap = None
        self._steps_per_s = 0.0
        self._pushed_frame = -1
        self._pushed_kf: dict[int, int] = {}
        self._pushed_render = None
        self._gt_aligned: np.ndarray | None = None
        self._gt_at = 0
        self.errors = 0

    # ------------------------------------------------------------------ wiring
    def start(self) -> "LiveViewer":
        self.scene = ViewerScene(self.host, self.port, title="mgso (live)", live=True, renderer=self._request_render)
        self.port = self.scene.port
        self.scene.pause_run.on_update(lambda _e: self._set_run_paused(bool(self.scene.pause_run.value)))
        self.scene.server.on_client_disconnect(self._on_disconnect)
        self._thread = threading.Thread(target=self._loop, name="mgso-viewer", daemon=True)
        self._thread.start()
        return self

    @property
    def url(self) -> str:
        return self.scene.url if self.scene is not None else f"http://{self.host}:{self.port}"

    def attach(self, system) -> None:
        """The running :class:`~mgso.system.System`: its mapper answers the viewer's snapshot and render requests."""
        self._mapper = getattr(system, "mapper", None)
        self._closer = getattr(system, "loop", None)
        # the mapper in this thread (deterministic, system.mapper_lead 0): it runs between frames, so while the run is
        # paused its safe point is reached from here and the paused view still gets its map copies and renders; a
        # mapper on a thread or in a process of its own serves them itself, and only it may touch the map
        self._serve_while_paused = (getattr(system, "mapper_in", None) == "caller"
                                    and hasattr(self._mapper, "safe_point"))

    def watch(self, frames: Iterable) -> "_Watched":
        """Pass ``frames`` through, keeping a reference to the newest (its image is the panel's current frame). The
        wrapper answers for the source (a live source's ``live``, ``dropped`` and thread-safe ``close``, which the
        real-time player asks for)."""
        return _Watched(frames, self._recent)

    def close(self) -> None:
        self._closed.set()
        self._run_gate.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        if self.scene is not None:
            try:
                self.scene.close()
            except Exception:  # noqa: BLE001 - closing must not fail a run
                log.debug("closing the viewer", exc_info=True)

    # ------------------------------------------------------------------ pause the run
    def _set_run_paused(self, paused: bool) -> None:
        if paused:
            self._run_gate.clear()
        else:
            self._run_gate.set()

    def pause_run(self, paused: bool = True) -> None:
        """What the panel's "Pause the run too" does: hold the odometry before its next frame (or let it go on)."""
        if self.scene is not None and not self._closed.is_set():
            self.scene.pause_run.value = bool(paused)     # on_update follows, as from a browser
        self._set_run_paused(paused)

    def _on_disconnect(self, _client) -> None:
        # nobody left to unpause it: a run is never left held by a closed browser tab
        if self.scene is not None and self.scene.clients() == 0 and not self._run_gate.is_set():
            log.warning("viewer: the last browser left while the run was paused; resuming it")
            self.pause_run(False)

    def _wait_gate(self) -> None:
        while not self._run_gate.wait(0.1):
            if self._closed.is_set():
                return
            if self._serve_while_paused:
                self._mapper.safe_point()       # answer the viewer's requests; nothing is trained

    # ------------------------------------------------------------------ observer callbacks (O(1), no copies)
    def on_sequence_start(self, info) -> None:
        self.info = info

    def on_frame(self, r) -> None:
        if not self._run_gate.is_set():
            t0 = time.perf_counter()
            self._wait_gate()
            self.paused_seconds += time.perf_counter() - t0
        self._times.append(time.perf_counter())
        self.frames += 1
        self._last = r
        if r.cam_to_world is not None:
            self._poses.append((r.timestamp, r.cam_to_world))
        lost = str(getattr(r.status, "value", r.status)) == "lost"
        if lost and not self._lost:
            self.losses += 1
        self._lost = lost

    def on_keyframe(self, msg) -> None:
        self.keyframes += 1
        self._kf_poses[msg.keyframe_id] = msg.cam_to_world
        self._kf_frame[msg.keyframe_id] = msg.frame_index
        self._camera = msg.camera

    def on_window_optimized(self, update) -> None:
        self._kf_poses.update(update.cam_to_world)        # a window's worth of references

    def on_points_marginalized(self, msg) -> None:
        self._points.append(msg)

    def on_loop_closed(self, correction) -> None:
        # the keyframes' poses move now (a few hundred 4x4 products, once a loop); the DSO points and the frames'
        # path in the viewer thread (_apply_loops, _frame_path)
        for kid, S in correction.transforms.items():
            T = self._kf_poses.get(kid)
            if T is not None:
                self._kf_poses[kid] = sim3_apply_to_pose(S, T)
        self.loops += 1
        self._loop_events.append((correction, len(self._points)))

    def on_map_updated(self, stats) -> None:
        self.num_gaussians = int(getattr(stats, "num_gaussians", self.num_gaussians))

    def on_sequence_end(self, summary) -> None:
        self.ended = True

    # ------------------------------------------------------------------ the viewer thread
    def _request_render(self, camera, world_to_cam) -> int | None:
        if self._mapper is None:
            raise RuntimeError("no map yet")
        return self._mapper.request_render(camera, world_to_cam)

    def _loop(self) -> None:
        period = 1.0 / self.frame_hz
        map_period = 1.0 / self.map_hz
        next_map = 0.0
        while not self._closed.wait(period):
            if self.scene.pause_view.value:
                continue
            try:
                self._merge_points()
                self._apply_loops()
                if self.scene.clients() == 0:
                    continue           # nothing is drawn for nobody: no map copies asked, nothing pushed
                self.push_frame()
                now = time.monotonic()
                if now >= next_map:
                    next_map = now + map_period
                    self.push_map()
            except Exception:  # noqa: BLE001 - the viewer must never take the run down
                self.errors += 1
                log.debug("viewer update failed", exc_info=True)
                if self.errors == 1:
                    log.warning("viewer: an update failed (see -v for details); the run goes on")
        self._merge_points()

    def _merge_points(self) -> None:
        """Take the PointsMessages that arrived since the last call (the callbacks only append references)."""
        n = len(self._points)
        for i, msg in enumerate(self._points[self._cloud_n:n], start=self._cloud_n):
            if len(msg):
                self._cloud_p.append(np.asarray(msg.points, np.float32))
                self._cloud_c.append(np.asarray(msg.colors, np.float32))
                self._cloud_msg.append(i)
        self._cloud_n = n

    def _apply_loops(self) -> None:
        """Move the DSO points that arrived before each new loop correction by their host keyframe's Sim(3) (the
        points that came after it are in the corrected world already); after :meth:`_merge_points`, which has
        merged every message a correction counted."""
        events = self._loop_events[self._loops_applied:]
        for corr, before in events:
            tf = corr.transforms
            for j, i in enumerate(self._cloud_msg):
                if i >= before:
                    break
                S = tf.get(self._points[i].host_keyframe_id)
                if S is not None:
                    self._cloud_p[j] = (self._cloud_p[j] @ S[:3, :3].T.astype(np.float32)
                                        + S[:3, 3].astype(np.float32))
            if self.scene is not None:
                self.scene.pushed["cloud_parts"] = None       # push the whole cloud again
            self._gt_at = 0                                    # and the ground truth, aligned to the new path
        self._loops_applied += len(events)

    def _frame_path(self) -> tuple[np.ndarray, np.ndarray]:
        """(positions (N, 3), timestamps (N,)) of every frame with a pose, in the map's world: the odometry's
        poses moved by loop closure's correction of their time (recomputed after a loop; new frames appended)."""
        poses = self._poses[:]                     # a list of references (the callbacks append to the original)
        n, loops, pos, ts = self._path
        if len(poses) == n and loops == self._loops_applied:
            return pos, ts
        start = n if loops == self._loops_applied else 0
        new = poses[start:]
        t_new = np.array([t for t, _ in new], dtype=np.float64)
        p_new = (self._in_map_world(t_new, np.stack([T for _, T in new]))[:, :3, 3] if new
                 else np.zeros((0, 3)))
        if start:
            p_new, t_new = np.concatenate([pos, p_new]), np.concatenate([ts, t_new])
        self._path = (len(poses), self._loops_applied, p_new, t_new)
        return p_new, t_new

    def _in_map_world(self, timestamps: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
        """Frame poses (N, 4, 4) of the odometry moved into the map's world by loop closure's correction of their
        time (the poses themselves until a loop has moved anything)."""
        if self._closer is None or not self._closer.corrected:
            return cam_to_world
        return self._closer.correct_trajectory(Trajectory(timestamps, cam_to_world)).cam_to_world

    def _frame_lines(self) -> list[str]:
        r = self._last
        fps = 0.0
        if len(self._times) >= 2 and self._times[-1] > self._times[0]:
            fps = (len(self._times) - 1) / (self._times[-1] - self._times[0])
        status = "-" if r is None else str(getattr(r.status, "value", r.status))
        state = "run ended" if self.ended else ("run paused" if not self._run_gate.is_set() else "running")
        return [f"**{state}** · frame {'-' if r is None else r.index} · status **{status}**",
                f"frames/s **{fps:.1f}** · frames {self.frames} · keyframes **{self.keyframes}**",
                f"Gaussians **{self.num_gaussians}** · mapping steps/s **{self._steps_per_s:.1f}**",
                f"tracking losses **{self.losses}** · DSO points {sum(len(p) for p in self._cloud_p)}"]

    def push_frame(self) -> None:
        """The current frame, its camera, the trajectory, the keyframes and the panel (the viewer thread; public
        so that a test can push without waiting for the thread)."""
        sc = self.scene
        r = self._last
        sc.set_stats(self._frame_lines())
        if r is None or r.index == self._pushed_frame:
            return
        self._pushed_frame = r.index
        sc.pushed["frames"] += 1
        pos, _ = self._frame_path()
        sc.update_scale(pos)
        sc.set_path("trajectory", pos)
        cam = self._camera
        fov, aspect = (2 * math.atan(0.5 * cam.height / cam.fy), cam.width / cam.height) if cam else (1.0, 4 / 3)
        status = str(getattr(r.status, "value", r.status))
        f = next((f for f in list(self._recent) if getattr(f, "index", None) == r.index), None)
        if f is not None:     # the image the odometry tracked (gray: its colour may not have been made)
            sc.set_frame_image(f.gray, f"frame {r.index}: {status}", hi=255.0)
        if r.cam_to_world is not None:
            T = self._in_map_world(np.array([r.timestamp]), r.cam_to_world[None])[0]
            color = _COLORS["current"] if status != "lost" else (120, 120, 120)
            sc.set_frustum("/current/camera", T, fov, aspect, color, scale=1.5 * sc.scale)
            if sc.follow.value:
                sc.follow_camera(T)
        for kid, T in list(self._kf_poses.items()):
            if self._pushed_kf.get(kid) is T:
                continue
            name = f"/keyframes/kf{kid}"
            if kid not in self._pushed_kf or not sc.move_frustum(name, T):
                sc.set_frustum(name, T, fov, aspect, _COLORS["keyframe"])
            self._pushed_kf[kid] = T
        render = self._mapper.latest_render() if self._mapper is not None else None
        if render is not None and render[0] == sc.render_ticket and render is not self._pushed_render:
            self._pushed_render = render
            sc.show_render(*render)

    def push_map(self) -> None:
        """The newest map copy, DSO's points and the aligned ground truth (the viewer thread, :data:`MAP_HZ`)."""
        sc = self.scene
        if self._mapper is not None:
            snap = self._mapper.latest_snapshot()
            if snap is not None and snap is not self._snap:
                if self._snap is not None and snap.time > self._snap.time:
                    self._steps_per_s = (snap.steps - self._snap.steps) / (snap.time - self._snap.time)
                self._snap = snap
                if snap.num_gaussians:
                    self.num_gaussians = snap.num_gaussians
                if len(snap):
                    sc.set_splats(snap.means, snap.covariances(), snap.colors, snap.opacities)
            if not self.ended:
                self._mapper.request_snapshot(self.max_splats)    # answered at the mapper's next safe point
        if self._cloud_p and len(self._cloud_p) != sc.pushed.get("cloud_parts"):
            sc.set_points(np.concatenate(self._cloud_p), np.concatenate(self._cloud_c))
            sc.pushed["cloud_parts"] = len(self._cloud_p)
        gt = self.groundtruth
        if gt is not None and len(self._poses) >= 3 and len(self._poses) != self._gt_at:
            pos, ts = self._frame_path()
            self._gt_at = len(pos)
            al = _align_groundtruth(ts, pos, gt.timestamps, gt.positions)
            if al is not None:
                sc.set_path("groundtruth", al)


# ------------------------------------------------------------------------------------------------ finished runs
def _read_camera(run: Path):
    """fov (vertical, radians) and aspect of the run's output camera from sequence.json (defaults when absent)."""
    try:
        info = json.loads((run / "sequence.json").read_text())
        k = info.get("intrinsics") or {}
        w, h = info.get("image_size_out") or info.get("image_size_in")
        return 2 * math.atan(0.5 * float(h) / float(k["fy"])), float(w) / float(h), (float(k["fx"]), float(k["fy"]),
                                                                                     float(k["cx"]), float(k["cy"]),
                                                                                     int(w), int(h))
    except Exception:  # noqa: BLE001 - a map.ply alone, or an older run: a usual camera
        return 1.0, 4 / 3, None


class _MapRenderer:
    """Renders a map read from a PLY with mgso's rasteriser (``mgso view``): synchronous, in viser's callback
    thread; the image waits in :meth:`latest_render` for the scene."""

    def __init__(self, arrays, device: str = "cpu"):
        self.arrays = arrays
        self.device = device
        self._state = None
        self._latest = None
        self._tickets = 0
        self._lock = threading.Lock()

    def __call__(self, camera, world_to_cam) -> int:
        with self._lock:
            if self._state is None:
                from mgso.config import load_config
                from mgso.mapping.gaussian_map import GaussianMap
                from mgso.mapping.trainer import TrainStep
                from mgso_kernels import runtime

                dev = runtime.init(self.device)
                cfg = load_config(None, [])
                gmap = GaussianMap.from_arrays(self.arrays, device=dev)
                self._state = (gmap, TrainStep(cfg.mapping, dev))
            gmap, step = self._state
            self._tickets += 1
            img = step.render(gmap, camera, world_to_cam, sh_degree=self.arrays.sh_degree)
            self._latest = (self._tickets, img)
            return self._tickets

    def latest_render(self):
        return self._latest


def open_run(path: str | Path, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, *,
             device: str = "cpu") -> ViewerScene:
    """Serve a finished run (a run folder, or a ``map.ply``) in the viewer; returns the scene (its server runs in
    its own threads until :meth:`ViewerScene.close`). Raises :class:`ViewerError` (one line) when there is nothing
    to show."""
    from mgso.io.ply import PlyError, read_gaussians_ply, read_point_cloud_ply
    from mgso.io.trajectory import TrajectoryError, read_tum

    require_viser()
    p = Path(path)
    if not p.exists():
        raise ViewerError(f"{p}: no such run folder or map.ply")
    run = p if p.is_dir() else p.parent
    map_path = p if p.is_file() else p / "map.ply"
    if p.is_file() and p.suffix.lower() != ".ply":
        raise ViewerError(f"{p}: not a run folder or a .ply map")
    found = [n for n in ("map.ply", "points.ply", "trajectory.txt", "keyframes.txt") if (run / n).is_file()]
    if p.is_dir() and not found:
        raise ViewerError(f"{p}: not a run folder (none of map.ply, points.ply, trajectory.txt, keyframes.txt)")
    arrays = None
    if map_path.is_file():
        try:
            arrays = read_gaussians_ply(map_path)
        except PlyError as exc:
            raise ViewerError(str(exc)) from None
        arrays = _finite_gaussians(arrays, map_path)
    renderer = _MapRenderer(arrays, device) if arrays is not None and arrays.n > 0 else None
    sc = ViewerScene(host, port, title=f"mgso view: {run.name}", live=False, renderer=renderer)
    try:
        fov, aspect, _k = _read_camera(run)
        lines = [f"**{run.name}** (finished run)"]

        def read(name):
            f = run / name
            if not p.is_dir() or not f.is_file():     # a map.ply given alone is shown alone
                return None
            try:
                return read_tum(f)
            except TrajectoryError as exc:
                log.warning("viewer: %s", exc)
                return None

        traj, kfs, gt = read("trajectory.txt"), read("keyframes.txt"), read("groundtruth.txt")
        if traj is not None:
            sc.update_scale(traj.positions)
            sc.set_path("trajectory", traj.positions)
            lines.append(f"frames with a pose **{len(traj)}**")
            if gt is not None:
                al = _align_groundtruth(traj.timestamps, traj.positions, gt.timestamps, gt.positions)
                if al is not None:
                    sc.set_path("groundtruth", al)
        if kfs is not None:
            for i, T in enumerate(kfs.cam_to_world):
                sc.set_frustum(f"/keyframes/kf{i}", T, fov, aspect, _COLORS["keyframe"])
            lines.append(f"keyframes **{len(kfs)}**")
        pts = None
        if (run / "points.ply").is_file() and p.is_dir():
            try:
                pts, cols, _ = read_point_cloud_ply(run / "points.ply")
                sc.set_points(pts, cols if cols is not None else np.full((len(pts), 3), 0.5, np.float32))
                lines.append(f"DSO points {len(pts)}")
            except PlyError as exc:
                log.warning("viewer: %s", exc)
        scene_points = arrays.means if arrays is not None and arrays.n > 0 else pts
        first = kfs if kfs is not None else traj
        if first is not None and len(first):
            sc.frame_view(first.cam_to_world[0], scene_points)
        elif scene_points is not None and len(scene_points):      # a map.ply alone: look at it from outside
            c = np.median(scene_points, axis=0)
            r = float(np.percentile(np.linalg.norm(scene_points - c, axis=1), 90)) or 1.0
            T = np.eye(4)
            T[:3, 3] = c - np.array([0.0, 0.0, 2.5 * r])
            sc.frame_view(T, scene_points)
        if arrays is not None and arrays.n > 0:
            act = arrays.activated()
            from mgso.mapping.snapshot import MapSnapshot

            snap = MapSnapshot(act.means, act.scales, act.quats, act.opacities, np.clip(act.rgb, 0, 1))
            if traj is None:
                sc.update_scale(act.means)
            sc.set_splats(snap.means, snap.covariances(), snap.colors, snap.opacities)
            lines.append(f"Gaussians **{arrays.n}**")
        sc.set_stats(lines)
        if renderer is not None:
            threading.Thread(target=_poll_renders, args=(sc, renderer), name="mgso-view-render", daemon=True).start()
    except BaseException:
        sc.close()
        raise
    return sc


def _finite_gaussians(arrays, path: Path):
    """The map without Gaussians that hold a NaN or an infinity (which the renderer and the browser cannot draw),
    each case said in one warning line, as is a map with no Gaussians at all."""
    if arrays.n == 0:
        log.warning("viewer: %s has no Gaussians: only the trajectory and points are shown", path)
        return arrays
    fields = (arrays.means, arrays.log_scales, arrays.quats, arrays.opacity_logits, arrays.sh)
    ok = np.all([np.isfinite(f.reshape(arrays.n, -1)).all(axis=1) for f in fields], axis=0)
    if ok.all():
        return arrays
    log.warning("viewer: %s: %d of %d Gaussians hold NaN or infinite values and are not shown", path,
                int((~ok).sum()), arrays.n)
    return type(arrays)(*(f[ok] for f in fields))


def _poll_renders(sc: ViewerScene, renderer: _MapRenderer) -> None:
    shown = None
    while not sc.closed.wait(0.2):
        r = renderer.latest_render()
        if r is not None and r is not shown:
            shown = r
            try:
                sc.show_render(*r)
            except Exception:  # noqa: BLE001 - the server stopped
                return
