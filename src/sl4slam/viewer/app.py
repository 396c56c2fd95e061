"""The browser viewer: a viser server that mirrors a :class:`~sl4slam.viewer.scene.MapState`.

Scene layout: ``/map/submap_NNNN`` one point cloud per submap (float16 offsets from the node's
position, uint8 colours), ``/cameras/kf_NNNNNN`` keyframe frustums with thumbnails,
``/trajectory``, ``/loops`` and ``/ground_truth`` line segments. Only the parts that changed are
sent again: a new submap is one cloud; a point-size change touches no point data; the confidence
slider and the colouring resend the clouds (the browser cannot filter them itself).

What a browser that opens the page sees first: viser replays its messages in the order they were
sent (in windows of 128, a window applied per frame), so the control panel is built (when the
server starts) and filled (counts, summary, slider ranges: :meth:`MapViewer.fill_gui`) and the
view that frames the map is set (:meth:`MapViewer.frame_map`) before any geometry; then come the
lines, the clouds, and last the frustums with their thumbnails: the panel is complete in the first
frame that shows the map. viser's default environment map is switched off: nothing drawn here is
lit by it, and while its image loads viser draws the canvas at 5 % opacity and fades it in over
five frames, which with software WebGL and a large cloud took tens of seconds during which the
map was a white haze.

A result folder is served before its map is read (:mod:`sl4slam.viewer.result`): a status line under
the title says what is still loading (:meth:`MapViewer.set_status`), and the panel's point counts
are the whole map's from the start (:attr:`~sl4slam.viewer.scene.MapState.totals`).
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import sys
import threading
from typing import TextIO

import numpy as np

from ..errors import UserError
from .scene import (
    COLOR_MODES,
    MapState,
    MapTotals,
    SubmapCloud,
    ViewerSettings,
    auto_point_size,
    confidence_threshold,
    follow_view,
    frustum_fov,
    frustum_indices,
    frustum_scale,
    map_spacing,
    map_sphere,
    overview,
    path_segments,
    rotation_wxyz,
    scene_extent,
    visible_part,
)

TRAJECTORY_COLOR = (40, 110, 255)
LOOP_COLOR = (230, 40, 40)
GT_COLOR = (30, 30, 30)
FRUSTUM_COLOR = (255, 140, 0)


def require_viser():
    """Import viser, or one clear line saying how to install it."""
    try:
        import viser
    except ImportError:
        raise UserError('the viewer needs the optional viser package: pip install "sl4slam[viewer]"') from None
    return viser


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def start_server(host: str, port: int, stream: TextIO = sys.stdout):
    """Start a viser server on ``host:port`` (the next free port when taken); print its URL.

    Returns the server. A host that is not loopback gets a one-line warning.
    """
    viser = require_viser()
    if not 0 < int(port) < 65536:
        raise UserError(f"--port must be between 1 and 65535, got {port}")
    if not is_loopback(host):
        print(f"warning: binding {host}: anyone who can reach this machine on port {port}+ can see the map", file=stream)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its own banner; we print one line
            server = viser.ViserServer(host=host, port=int(port), verbose=False)
    except OSError as exc:
        raise UserError(f"cannot serve on {host}:{port} ({exc.strerror or exc}); pass another --host or --port") from None
    actual = server.get_port()
    if actual != int(port):
        print(f"port {port} is in use; using {actual}", file=stream)
    shown = f"[{host}]" if ":" in host else host
    print(f"viewer at http://{shown}:{actual}", file=stream, flush=True)
    return server


class MapViewer:
    """A viser server showing a map; call the ``draw_*`` methods when the state changes.

    Controls: point budget (fixed at start), point size, confidence percentile, colouring
    (RGB / submap / confidence), visibility of cameras, trajectory, loops and ground truth, a
    follow-camera toggle with a keyframe slider, and the run summary.

    Attributes:
        loader: what reads a result folder's map into this viewer
            (:class:`~sl4slam.viewer.result.ResultLoader`, set by
            :func:`~sl4slam.viewer.result.view_result`); ``None`` otherwise.
    """

    def __init__(self, settings: ViewerSettings | None = None, title: str = "sl4slam", stream: TextIO = sys.stdout) -> None:
        self.settings = settings or ViewerSettings()
        self._closed = False
        self._close_callbacks: list = []
        self.loader = None
        self.server = start_server(self.settings.host, self.settings.port, stream=stream)
        # no share button: the map stays on the interface it is served on
        self.server.gui.configure_theme(control_width="medium", show_share_button=False, show_logo=False)
        # no environment map: nothing drawn is lit by it, and loading it fades the canvas in (module doc)
        self.server.scene.configure_environment_map(hdri=None)
        self.state = MapState()
        self.lock = threading.RLock()
        self._clouds: dict[int, object] = {}
        self._frustums: dict[int, object] = {}
        self._extent = 1.0
        self._point_size = self.settings.point_size
        self._spacing: float | None = None
        self._spacing_of: tuple = ()
        self._status = None
        self._given_views: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._build_gui(title)

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    # ------------------------------------------------------------------ GUI
    def _build_gui(self, title: str) -> None:
        gui = self.server.gui
        self._title = gui.add_markdown(f"**{title}**")
        with gui.add_folder("Map"):
            self.gui_size = gui.add_slider(
                "Point size", min=0.1, max=10.0, step=0.1, initial_value=1.0,
                hint="times the default, which the map's own point spacing sets (1: neighbouring points overlap)")
            self.gui_confidence = gui.add_slider("Min confidence %", min=0, max=99, step=1, initial_value=0,
                                                 hint="hide the given percentage of least confident points")
            self.gui_color = gui.add_dropdown("Colour", COLOR_MODES, initial_value="rgb")
            self.gui_points = gui.add_markdown("points: 0")
        with gui.add_folder("Show"):
            self.gui_show_cameras = gui.add_checkbox("Cameras", True)
            self.gui_all_frustums = gui.add_checkbox(
                "All frustums", False,
                hint=f"a frustum for every keyframe (by default at most {self.settings.max_frustums}, "
                     "spread along the trajectory)")
            self.gui_show_trajectory = gui.add_checkbox("Trajectory", True)
            self.gui_show_loops = gui.add_checkbox("Loop edges", True)
            self.gui_show_gt = gui.add_checkbox("Ground truth", True)
        with gui.add_folder("Camera"):
            self.gui_follow = gui.add_checkbox("Follow camera", False, hint="view from behind the selected keyframe")
            self.gui_keyframe = gui.add_slider("Keyframe", min=0, max=1, step=1, initial_value=0)
        with gui.add_folder("Run"):
            self.gui_summary = gui.add_markdown("")

        self.gui_size.on_update(lambda _: self._apply_point_size())
        self.gui_confidence.on_update(lambda _: self.draw_clouds())
        self.gui_color.on_update(lambda _: self.draw_clouds())
        self.gui_show_cameras.on_update(lambda _: self._apply_visibility())
        self.gui_all_frustums.on_update(lambda _: self.draw_frustums())
        self.gui_show_trajectory.on_update(lambda _: self._apply_visibility())
        self.gui_show_loops.on_update(lambda _: self._apply_visibility())
        self.gui_show_gt.on_update(lambda _: self._apply_visibility())
        self.gui_follow.on_update(lambda _: self.apply_follow())
        self.gui_keyframe.on_update(lambda _: self.apply_follow())
        self.server.on_client_connect(lambda client: self._view_client(client))

    # ------------------------------------------------------------------ drawing
    def _size(self) -> float:
        """The point size sent to viser: the settings' size, or the one derived from the map's point
        spacing (:func:`~sl4slam.viewer.scene.auto_point_size`), times the slider."""
        base = self._point_size if self._point_size > 0 else auto_point_size(self._spacing, self._extent / 500.0)
        return float(base * self.gui_size.value)

    def _measure_spacing(self) -> None:
        """The map's point spacing, measured again only when the clouds changed."""
        key = tuple((i, len(c)) for i, c in sorted(self.state.clouds.items()))
        if key != self._spacing_of:
            self._spacing = map_spacing(self.state.clouds.values(), seed=self.settings.seed)
            self._spacing_of = key

    def fill_gui(self) -> None:
        """Put the state's numbers into the control panel (point count, summary, slider ranges); call
        before sending geometry, so that a browser gets a complete panel before any cloud."""
        with self.lock:
            state = self.state
            totals: MapTotals = state.totals if state.totals is not None else state.counted_totals()
            points = (f"points: {totals.shown:,} shown of {totals.full:,}"
                      + ("" if totals.confidence else " (no per-pixel confidence saved: mask only)"))
            # only what changed is sent: a browser that opens later gets the panel before the clouds
            if self.gui_points.content != points:
                self.gui_points.content = points
            if self.gui_confidence.disabled != (not totals.confidence):
                self.gui_confidence.disabled = not totals.confidence
            if self.gui_keyframe.max != max(1, len(state.T_world_cam) - 1):
                self.gui_keyframe.max = max(1, len(state.T_world_cam) - 1)
            if self.gui_summary.content != state.summary_markdown:
                self.gui_summary.content = state.summary_markdown

    def set_status(self, markdown: str | None) -> None:
        """Show ``markdown`` in a line under the panel's title (``None`` removes the line)."""
        with self.lock:
            if markdown is None:
                if self._status is not None:
                    self._status.remove()
                    self._status = None
            elif self._status is None:
                self._status = self.server.gui.add_markdown(markdown, order=self._title.order + 0.5)
            elif self._status.content != markdown:
                self._status.content = markdown

    def has_browsers(self) -> bool:
        """Whether a browser is connected."""
        return bool(self.server.get_clients())

    def sent_clouds(self) -> list[int]:
        """The submaps whose clouds were sent."""
        with self.lock:
            return list(self._clouds)

    def unsent_clouds(self) -> list[int]:
        """The submaps in the state whose clouds were not sent yet."""
        with self.lock:
            return [i for i in self.state.clouds if i not in self._clouds]

    def _apply_point_size(self) -> None:
        size = self._size()
        with self.lock:
            for handle in self._clouds.values():
                handle.point_size = size

    def draw_clouds(self, submap_ids=None) -> None:
        """Send the clouds of ``submap_ids`` (all when ``None``) as they are in the state (the panel's
        numbers first, and the point size measured on the map before the first cloud goes out)."""
        with self.lock:
            state = self.state
            self.fill_gui()
            size_before = self._size()
            self._measure_spacing()
            if self._size() != size_before:
                self._apply_point_size()
            threshold = confidence_threshold(state.clouds.values(), float(self.gui_confidence.value))
            crange = state.confidence_range()
            ids = list(state.clouds) if submap_ids is None else [i for i in submap_ids if i in state.clouds]
            mode = str(self.gui_color.value)
            with self.server.atomic():
                for submap_id in ids:
                    self._draw_cloud(state.clouds[submap_id], threshold, mode, crange)
                for submap_id in [i for i in self._clouds if i not in state.clouds]:
                    self._clouds.pop(submap_id).remove()

    def _draw_cloud(self, cloud: SubmapCloud, threshold: float, mode: str, crange) -> None:
        offsets, colors = visible_part(cloud, threshold, mode, crange)
        handle = self._clouds.get(cloud.submap_id)
        if handle is not None and len(offsets) == len(handle.points):
            handle.points, handle.colors = offsets, colors
            handle.position = cloud.centre
            return
        if handle is not None:
            handle.remove()
        self._clouds[cloud.submap_id] = self.server.scene.add_point_cloud(
            f"/map/submap_{cloud.submap_id:04d}", points=offsets, colors=colors, point_size=self._size(),
            point_shape="square", precision="float16", point_shading="flat", position=cloud.centre)

    def draw_cameras(self, thumbnails_for=()) -> None:
        """Trajectory, loop and ground-truth lines, then the keyframe frustums (``thumbnails_for``:
        frame indices whose image changed)."""
        self.draw_lines()
        self.draw_frustums(thumbnails_for)

    def draw_lines(self) -> None:
        """Trajectory, loop edges and ground truth (a few small messages)."""
        with self.lock:
            state = self.state
            size_before = self._size()
            positions = state.T_world_cam[:, :3, 3]
            self._extent = scene_extent(positions)
            with self.server.atomic():
                self._lines("/trajectory", path_segments(positions), TRAJECTORY_COLOR, self.gui_show_trajectory)
                self._lines("/loops", state.loop_segments, LOOP_COLOR, self.gui_show_loops, width=2.0)
                gt = state.gt_positions
                self._lines("/ground_truth", path_segments(gt) if gt is not None else np.zeros((0, 2, 3)), GT_COLOR,
                            self.gui_show_gt)
            if self._size() != size_before:  # the fallback size follows the trajectory's extent
                self._apply_point_size()

    def draw_frustums(self, thumbnails_for=()) -> None:
        """Keyframe frustums with thumbnails: at most ``settings.max_frustums`` spread along the
        trajectory (:func:`~sl4slam.viewer.scene.frustum_indices`), every keyframe's with "All
        frustums"; sized to the map (:func:`~sl4slam.viewer.scene.frustum_scale`)."""
        with self.lock:
            state = self.state
            positions = state.T_world_cam[:, :3, 3]
            limit = len(positions) if self.gui_all_frustums.value else self.settings.max_frustums
            picked = frustum_indices(positions, limit)
            if len(state.K) != len(state.T_world_cam):  # trajectory only (no keyframe files): no frustums
                picked = np.zeros(0, np.int64)
            shown = set(picked.tolist())
            scale = frustum_scale(map_sphere(state)[1], positions[picked])
            wxyz = rotation_wxyz(state.T_world_cam) if len(state.T_world_cam) else np.zeros((0, 4))
            with self.server.atomic():
                for i, frame_index in enumerate(state.frame_indices.tolist()):
                    handle = self._frustums.get(frame_index)
                    if i not in shown:
                        if handle is not None:
                            self._frustums.pop(frame_index).remove()
                        continue
                    if handle is None or frame_index in thumbnails_for:
                        if handle is not None:
                            handle.remove()
                        width, height = state.image_sizes[i]
                        self._frustums[frame_index] = self.server.scene.add_camera_frustum(
                            f"/cameras/kf_{frame_index:06d}", fov=frustum_fov(state.K[i], int(height)),
                            aspect=float(width) / float(height), scale=scale, color=FRUSTUM_COLOR, thickness=1.5,
                            thickness_units="screen",
                            image=state.thumbnails.get(frame_index), format="jpeg", jpeg_quality=80,
                            wxyz=wxyz[i], position=positions[i], visible=bool(self.gui_show_cameras.value))
                    else:
                        handle.wxyz, handle.position, handle.scale = wxyz[i], positions[i], scale
                for frame_index in [f for f in self._frustums if f not in set(state.frame_indices.tolist())]:
                    self._frustums.pop(frame_index).remove()

    def _lines(self, name: str, segments: np.ndarray, color, toggle, width: float = 1.0) -> None:
        if len(segments) == 0:
            self.server.scene.remove_by_name(name)
            return
        self.server.scene.add_line_segments(name, points=np.asarray(segments, np.float32), colors=color,
                                            thickness=2.0 * width, thickness_units="screen", visible=bool(toggle.value))

    def _apply_visibility(self) -> None:
        with self.lock:
            for handle in self._frustums.values():
                handle.visible = bool(self.gui_show_cameras.value)
            self.draw_cameras()

    def set_summary(self, markdown: str) -> None:
        self.state.summary_markdown = markdown
        if self.gui_summary.content != markdown:
            self.gui_summary.content = markdown

    def set_up_direction(self) -> None:
        """World up: the first keyframe's -y axis (cameras are held upright at the start)."""
        if len(self.state.T_world_cam):
            self.server.scene.set_up_direction(-self.state.T_world_cam[0, :3, 1])

    def frame_map(self) -> None:
        """Make the view that frames the map (:func:`~sl4slam.viewer.scene.overview`) the one a
        browser opens with (and returns to with "Reset View"): it is part of what a new browser
        receives first, so its first frame already looks at the map. Browsers already open keep
        their view."""
        view = overview(self.state)
        if view is None:
            return
        camera = self.server.initial_camera
        camera.position, camera.look_at, camera.up = view

    # ------------------------------------------------------------------ camera
    def apply_follow(self, newest: bool = False) -> None:
        """When following: view every client from behind the selected (or the newest) keyframe."""
        if not self.gui_follow.value or not len(self.state.T_world_cam):
            return
        if newest:
            self.gui_keyframe.value = len(self.state.T_world_cam) - 1
        index = int(min(self.gui_keyframe.value, len(self.state.T_world_cam) - 1))
        position, look_at, up = follow_view(self.state.T_world_cam[index], 0.15 * self._extent)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position, client.camera.look_at, client.camera.up_direction = position, look_at, up

    def _view_client(self, client) -> None:
        """Frame the whole map for a newly connected browser. Under the lock: a loader may be adding
        clouds to the state meanwhile, and :meth:`reframe_unmoved` must see the view given here."""
        with self.lock:
            view = overview(self.state)
            if view is None:
                return
            with client.atomic():
                client.camera.position, client.camera.look_at, client.camera.up_direction = view
            self._given_views[client.client_id] = (np.array(view[0], np.float64), np.array(view[1], np.float64))

    def reframe_unmoved(self) -> None:
        """Give the view that frames the map (:func:`~sl4slam.viewer.scene.overview`) to every open
        browser whose camera is still where this viewer put it (to within 1e-3 of the viewing
        distance); browsers whose camera was moved keep their view."""
        with self.lock:
            view = overview(self.state)
            if view is None:
                return
            for client_id, client in self.server.get_clients().items():
                given = self._given_views.get(client_id)
                if given is None:
                    continue
                position, look_at = given
                tolerance = 1e-3 * max(float(np.linalg.norm(position - look_at)), 1e-9)
                try:
                    current = np.asarray(client.camera.position), np.asarray(client.camera.look_at)
                except AssertionError:  # the browser has not reported a camera yet
                    continue
                if max(np.abs(current[0] - position).max(), np.abs(current[1] - look_at).max()) > tolerance:
                    continue
                with client.atomic():
                    client.camera.position, client.camera.look_at, client.camera.up_direction = view
                self._given_views[client_id] = (np.array(view[0], np.float64), np.array(view[1], np.float64))

    def on_close(self, callback) -> None:
        """Call ``callback()`` when the viewer closes (before its server stops)."""
        self._close_callbacks.append(callback)

    def close(self) -> None:
        """Run the close callbacks (:meth:`on_close`), then stop the server (once; later calls do
        nothing). ``closed`` is set under ``lock``: code that draws under ``lock`` after checking
        ``closed`` never draws on a stopped server."""
        with self.lock:
            if self._closed:
                return
            self._closed = True
        for callback in self._close_callbacks:
            callback()
        self.server.stop()
