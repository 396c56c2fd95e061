"""A run's :class:`~sl4slam.result.SLAMResult` from its graph estimate, stored keyframes and ledger."""

from __future__ import annotations

import logging

import numpy as np

from ..backend import Backend, BackendUpdateError, WorldEstimate
from ..errors import UserError
from ..keyframe_store import KeyframeStore
from ..ledger import RunLedger
from ..source_knowledge import SourceKnowledge
from . import SLAMResult, SourceColors, keyframe_cameras

log = logging.getLogger("sl4slam")


def final_estimate(backend: Backend, ledger: RunLedger) -> WorldEstimate:
    """The graph's polished estimate (``Backend.world_estimate(final=True)``); iSAM2's own when the
    polish fails (a singular node), with a note in ``ledger``.

    Raises:
        UserError: not even iSAM2's estimate can be computed.
    """
    try:
        world = backend.world_estimate(final=True)
        if world.polish_blocks > 1:
            note = (f"the final polish ran in {world.polish_blocks} consecutive blocks of the graph, each exact "
                    "given the ones before, to stay within --backend-polish-memory-mib; raise it (0: no limit) "
                    "for the whole graph's optimum")
            log.warning(note)
            ledger.notes.append(note)
        return world
    except (BackendUpdateError, RuntimeError, ValueError) as exc:
        first_line = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        note = f"the final polish of the graph failed ({first_line}); the map is iSAM2's estimate"
        log.warning(note)
        ledger.notes.append(note)
    try:
        return backend.world_estimate()
    except (RuntimeError, ValueError) as exc:
        raise UserError(f"the graph cannot be solved at the end of the run ({exc}); no trajectory can be written") from None


def assemble_result(world: WorldEstimate, store: KeyframeStore, ledger: RunLedger, backend: Backend,
                    knowledge: SourceKnowledge, colors: SourceColors | None) -> SLAMResult:
    """The result under ``world``: every stored keyframe whose submap it places, with its camera,
    ground truth (when the source gave it for all of them), map segment, and the summary's counts
    and timings.

    Args:
        world: the graph estimate (``Backend.world_estimate``, possibly metric-upgraded).
        store: the run's stored keyframes.
        ledger: the run's record (edges, drops, failures, notes, timings).
        backend: the graph (it numbers the map segments).
        knowledge: what the run knows of its source (its notes and summary entries).
        colors: where the keyframes' colours come from, or ``None``.
    """
    keyframes = [k for k in store.keyframes if k.submap_id in world.H_world_submap]
    T_world_cam, K = keyframe_cameras(keyframes, world.H_world_submap, world.H_world_keyframe)
    gt = store.ground_truth(keyframes)
    segments = backend.segments_of([k.submap_id for k in keyframes])
    stats = {
        "frames": ledger.frames,
        "keyframes": len(keyframes),
        "submaps": ledger.submaps,
        "loops": ledger.num_loops,
        "loops_rejected": ledger.loops_rejected,
        "fallbacks": ledger.fallbacks,
        "segments": int(segments.max()) + 1 if len(segments) else 0,
        "dropped_frames": dict(ledger.dropped),
        "frontend_failures": list(ledger.frontend_failures),
        "notes": list(ledger.notes) + knowledge.notes(),
        **knowledge.summary(),
        "seconds_by_stage": dict(ledger.timer.seconds),
        "stored_bytes": int(sum(k.nbytes for k in keyframes)),
        "seconds_per_submap": {
            stage: round(float(np.median([s.get(stage, 0.0) for s in ledger.submap_seconds])), 5)
            for stage in sorted({k for s in ledger.submap_seconds for k in s})
        },
    }
    return SLAMResult(keyframes, T_world_cam, K, world.H_world_submap, gt, list(ledger.edges), segments, stats,
                      colors=colors, H_world_keyframe=dict(world.H_world_keyframe))
