"""The metric frame of a map: the running upgrade that completes planar links, and the final upgrade.

Beside ``sl4slam.upgrade`` (the self-calibration of a set of cameras) and ``sl4slam.completion``
(completing one link from the cameras) this module holds the policy of a run:

- **while the run goes on**, a link that only the shared frame's cameras fix (a fallback on a
  planar frame) is completed from the new submap's cameras, made metric in the running upgrade of
  the map so far (:meth:`MetricFrame.complete_link`), so that the map stays one projective frame
  for the final upgrade; only where the run ends with the upgrade, on SL(4) links
  (``ResolvedConfig.complete_links``);
- **at the end**, each map segment is upgraded to a metric frame by one ``H_metric_world``
  applied to its submaps' and keyframes' transforms (:meth:`MetricFrame.upgrade`), when the
  resolved config says so (``ResolvedConfig.metric_upgrade``).

Both read the keyframes a run has stored and where the graph places them; neither changes the graph.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .backend import Backend, WorldEstimate
from .completion import complete_camera_link, plane_normal, shared_camera_agreement
from .upgrade import UpgradeConfig
from .errors import UserError
from .result import world_cameras
from .submap import StoredKeyframe, principal_points
from .types import Alignment, FrameView, SubmapPrediction
from .upgrade import MetricUpgrade, UpgradeStatus, estimate_metric_upgrade, upgrade_graph_nodes

log = logging.getLogger("sl4slam")


@dataclass(frozen=True)
class RunningFrame:
    """The metric frame of one segment of the map so far, or why there is none.

    Attributes:
        H_metric_world: ``(4, 4)`` maps the segment's world into a metric frame (the identity when
            its cameras are already metric), or ``None``.
        focal: the focal length (px) of the cameras in that frame.
        problem: why there is no frame (``None`` when there is one).
    """

    H_metric_world: np.ndarray | None
    focal: float = 0.0
    problem: str | None = None


class MetricFrame:
    """The running and the final metric upgrade of a run's map (see the module doc).

    Args:
        config: the upgrade's settings.
        backend: the graph, read for where submaps and keyframes sit.
        upgrade_at_end: whether the run ends with the metric upgrade.
        complete_links: whether fallback links on planar frames are completed from the cameras.
    """

    def __init__(self, config: UpgradeConfig, backend: Backend, upgrade_at_end: bool, complete_links: bool) -> None:
        self.config = config
        self.backend = backend
        self.upgrade_at_end = upgrade_at_end
        self.complete_links = complete_links
        self._running: dict[int, tuple[int, RunningFrame]] = {}  # segment: (its keyframes then, frame)
        self._submap_ids = np.zeros(0, np.int64)  # the keyframes' submap ids seen so far (see _keyframe_submaps)
        self._ids_of: Sequence[StoredKeyframe] | None = None  # ... of this list

    # ------------------------------------------------------------------ during the run
    def complete_link(self, alignment: Alignment, old_submap: int, old_view: FrameView, new_view: FrameView,
                      prediction: SubmapPrediction, slot: int, keyframes: Sequence[StoredKeyframe]) -> Alignment:
        """A fallback link that only the shared frame's cameras fix, completed from the new submap's
        cameras in the running metric frame of ``old_submap``'s segment (``sl4slam.completion``);
        any other measurement as it is. ``slot``: the shared frame in the new submap."""
        if not alignment.fallback or alignment.model != "sl4" or not self.complete_links:
            return alignment
        if shared_camera_agreement(old_view.camera, new_view.camera, alignment.H) > 1e-6:
            return alignment  # a stand-in that does not keep the shared camera: nothing to complete
        frame = self.running(old_submap, keyframes)
        if frame.H_metric_world is None:
            alignment.extras["completion"] = {"applied": False, "reason": frame.problem}
            return alignment
        others = [s for s in range(len(prediction.K)) if s != slot]
        T = np.asarray(prediction.T_cam_submap, dtype=np.float64)
        cameras = np.einsum("nij,njk->nik", prediction.K[others], T[others, :3])
        points = new_view.points[new_view.mask].astype(np.float64)
        # a camera-constrained fit took the plane's tilt from its points: only the relief along the
        # normal is left free; the calibration link took nothing from them
        free = plane_normal(points) if alignment.extras.get("camera_constrained") and len(points) >= 3 else None
        H_metric_old = frame.H_metric_world @ self.backend.H_world_submap(old_submap)
        completion = complete_camera_link(alignment.H, new_view.centre, points, cameras, principal_points(prediction)[others],
                                          H_metric_old, frame.focal, self.config, free)
        alignment.extras["completion"] = completion.summary()
        if not completion.applied:
            return alignment
        return dataclasses.replace(alignment, H=completion.H_a_b, extras=dict(alignment.extras), fallback=(
            f"{alignment.fallback}; completed from the new submap's cameras (constraint residual "
            f"{completion.residual_before:.2g} -> {completion.residual_after:.2g})"))

    def running(self, submap_id: int, keyframes: Sequence[StoredKeyframe]) -> RunningFrame:
        """The metric frame of the map so far in ``submap_id``'s segment (its keyframes under iSAM2's
        current estimate), estimated again once the segment has grown by ``running_refresh`` of its
        keyframes since the last estimate: reading the estimate is a back-substitution of the whole
        map, so reading it for every link would make a link's cost grow with the map."""
        segment = self.backend.segment_of(submap_id)
        placed = self._segment_keyframes(keyframes, segment)
        last = self._running.get(segment)
        if last is not None and len(placed) < last[0] * (1.0 + self.config.running_refresh):
            return last[1]
        picks = placed[running_picks(len(placed), self.config.running_keyframes)]
        frame = self._estimate_running([keyframes[i] for i in picks])
        self._running[segment] = (len(placed), frame)
        return frame

    def _estimate_running(self, members: Sequence[StoredKeyframe]) -> RunningFrame:
        """The running metric frame from ``members`` under iSAM2's current estimate."""
        if len(members) < self.config.min_keyframes:
            return RunningFrame(None, problem=f"too few keyframes for a running upgrade ({len(members)})")
        try:
            # only the members' transforms are read out (converting the whole map's costs O(map) per
            # link); the estimate is still iSAM2's full back-substitution, which every reader of the
            # map gets: reading nodes alone would leave iSAM2's step partly solved, and the run's bits
            # would then depend on whether a viewer, a query or a checkpoint read the map meanwhile
            upgrade = self.estimate(members, self.backend.world_estimate(submaps={k.submap_id for k in members}))
        except (UserError, ValueError, np.linalg.LinAlgError) as exc:
            return RunningFrame(None, problem=f"no running upgrade: {exc}")
        if upgrade.status is UpgradeStatus.APPLIED:
            return RunningFrame(upgrade.H_metric_world, upgrade.focal)
        if upgrade.status is UpgradeStatus.ALREADY_METRIC:
            return RunningFrame(np.eye(4), upgrade.focal)
        return RunningFrame(None, problem=f"no running upgrade: {upgrade.reason}")

    # ------------------------------------------------------------------ at the end
    def upgrade(self, world: WorldEstimate, keyframes: Sequence[StoredKeyframe]) -> tuple[WorldEstimate, list[dict]]:
        """Each map segment upgraded to a metric frame (one ``H_metric_world`` per segment, applied to
        its submaps' and keyframes' transforms: every pose and map point follows), when the run ends
        with the upgrade; else ``world`` as it is. Returns the estimate and one summary per segment."""
        if not self.upgrade_at_end:
            return world, []
        upgraded, summaries = WorldEstimate(dict(world.H_world_submap), dict(world.H_world_keyframe), world.polish_blocks), []
        for segment, members in sorted(self.segment_members(world, keyframes).items()):
            try:
                upgrade = self.estimate(members, world)
            except (UserError, ValueError, np.linalg.LinAlgError) as exc:
                # e.g. a camera at infinity in a broken map: the map is kept as it is, never lost
                summaries.append({"segment": int(segment), "applied": False, "status": UpgradeStatus.SKIPPED.value,
                                  "reason": f"cannot be estimated: {exc}"})
                log.warning("metric upgrade of segment %d skipped: %s", segment, exc)
                continue
            summaries.append({"segment": int(segment), **upgrade.summary()})
            if upgrade.applied:
                submaps = {k.submap_id for k in members}
                frames = {k.frame_index for k in members} & set(world.H_world_keyframe)
                upgraded.H_world_submap.update(upgrade_graph_nodes(
                    {s: world.H_world_submap[s] for s in submaps}, upgrade.H_metric_world))
                upgraded.H_world_keyframe.update(upgrade_graph_nodes(
                    {f: world.H_world_keyframe[f] for f in frames}, upgrade.H_metric_world))
            log.info("metric upgrade of segment %d: %s", segment, upgrade.reason)
        return upgraded, summaries

    # ------------------------------------------------------------------ shared
    def segment_members(self, world: WorldEstimate, keyframes: Sequence[StoredKeyframe]) -> dict[int, list[StoredKeyframe]]:
        """The keyframes placed in ``world``, by map segment (0, 1, ...)."""
        placed = [k for k in keyframes if k.submap_id in world.H_world_submap]
        members: dict[int, list[StoredKeyframe]] = {}
        for keyframe, segment in zip(placed, self.backend.segments_of([k.submap_id for k in placed])):
            members.setdefault(int(segment), []).append(keyframe)
        return members

    def _segment_keyframes(self, keyframes: Sequence[StoredKeyframe], segment: int) -> np.ndarray:
        """Positions ``(n,)`` in ``keyframes`` of segment ``segment``'s keyframes whose submaps are in
        the graph, in time order (``running_picks`` of them give the same members as
        ``running_members(segment_members(world, keyframes)[segment], running_keyframes)``), found
        with array operations on the keyframes' submap ids: this runs for every completed link."""
        ids = self._keyframe_submaps(keyframes)
        placed = np.isin(ids, np.asarray(self.backend.submap_ids, dtype=np.int64))
        candidates = np.flatnonzero(placed)
        return candidates[self.backend.segments_of(ids[candidates]) == segment]

    def _keyframe_submaps(self, keyframes: Sequence[StoredKeyframe]) -> np.ndarray:
        """``(n,)`` int64 the submap id of each of ``keyframes``. The run's keyframe list (the store's
        own) only grows at its end, so the ids read before are kept and only the new keyframes' are
        read (reading every keyframe's id for every link made a link's cost grow with the map);
        another list, or a shorter one, is read whole."""
        known = len(self._submap_ids)
        if keyframes is not self._ids_of or known > len(keyframes):
            self._ids_of, known = keyframes, 0
        if known < len(keyframes):
            new = np.fromiter((keyframes[i].submap_id for i in range(known, len(keyframes))), dtype=np.int64,
                              count=len(keyframes) - known)
            self._submap_ids = np.concatenate([self._submap_ids[:known], new])
        return self._submap_ids[: len(keyframes)]

    def estimate(self, members: Sequence[StoredKeyframe], world: WorldEstimate) -> MetricUpgrade:
        """``sl4slam.upgrade.estimate_metric_upgrade`` of these keyframes' cameras in ``world``."""
        # only the members' transforms: world_cameras inverts every transform it is given
        submaps = {k.submap_id for k in members}
        frames = {k.frame_index for k in members}
        H_world_submap = {s: H for s, H in world.H_world_submap.items() if s in submaps}
        H_world_keyframe = {f: H for f, H in world.H_world_keyframe.items() if f in frames}
        return estimate_metric_upgrade(world_cameras(members, H_world_submap, H_world_keyframe),
                                       np.stack([k.principal_point for k in members]), self.config,
                                       image_sizes=np.array([k.shape[::-1] for k in members]))


def running_members(members: Sequence[StoredKeyframe], count: int) -> list[StoredKeyframe]:
    """At most ``count`` of ``members`` (in time order): the newest half of them, where the new link
    is, and the rest spread evenly over the older keyframes (``UpgradeConfig.running_keyframes``)."""
    members = list(members)
    return [members[i] for i in running_picks(len(members), count)]


def running_picks(num_members: int, count: int) -> np.ndarray:
    """Indices ``(k,)`` ascending, ``k <= count``, of the members :func:`running_members` keeps out of
    ``num_members`` in time order."""
    if num_members <= count:
        return np.arange(num_members)
    newest = count - count // 2
    older = num_members - newest
    picks = np.unique(np.linspace(0, older - 1, count - newest).round().astype(int))
    return np.concatenate([picks, np.arange(older, num_members)])
