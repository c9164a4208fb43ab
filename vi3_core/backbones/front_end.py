"""What a feature-tracking front end says about its tracks: ``FrameLosses``, per frame or summed over frames (the
``classical`` backbone's ``tracks.FrameTracker`` keeps one per frame and reports a clip's sum in its diagnostics, key
``front_end``), and ``run_summary``, the rates over a run that ``vi3 eval`` reports."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import astuple, dataclass

LONG_TRACK = 10  # frames a track is seen in to count as long (FrameLosses.ended_long)


@dataclass(frozen=True)
class FrameLosses:
    """What became of the tracks followed into a frame (summed over frames by ``+``): frames: how many frames this
    sums; starts: of them, frames with no track to follow (the first after a reset), whose corners are ``seeded``;
    followed: live tracks of the frame before; lost_no_flow: Lucas-Kanade found no flow (either way);
    lost_round_trip: the backward flow missed the start by the tracker's threshold or more; lost_border: the flow left
    the frame; lost_epipolar: outliers of the pair's epipolar geometry; new: corners detected in a frame that followed
    tracks (the grid's top-up); new_lost: of the new corners of the frame before, those lost into this one (corners on
    noise, on a plain wall or in the dark, die at their first step); ended_frames: the frames the tracks lost into
    this frame (``ended``: every lost_* above) had been seen in, summed (their mean length: ended_frames / ended),
    ended_long: those of them seen in ``LONG_TRACK`` frames or more (the tracks that carry a clip's structure)."""

    frames: int = 0
    starts: int = 0
    seeded: int = 0
    followed: int = 0
    lost_no_flow: int = 0
    lost_round_trip: int = 0
    lost_border: int = 0
    lost_epipolar: int = 0
    new: int = 0
    new_lost: int = 0
    ended_frames: int = 0
    ended_long: int = 0

    @property
    def ended(self) -> int:
        """The tracks lost into the frame(s), by any check."""
        return self.lost_no_flow + self.lost_round_trip + self.lost_border + self.lost_epipolar

    def __add__(self, other: FrameLosses) -> FrameLosses:
        return FrameLosses(*(a + b for a, b in zip(astuple(self), astuple(other))))


def run_summary(rows: Iterable[dict | None]) -> dict | None:
    """The run's rates from its clips' ``FrameLosses`` as dicts (None or empty for a clip whose backbone has no front
    end): frames tracked and how many of them started afresh (``starts``: an independent run starts every clip), then
    per frame that followed tracks: tracks followed, the share of them each check dropped (``lost``: no_flow,
    round_trip, border, epipolar), new corners, and the share of those lost at their first step (``new_lost``); of
    the tracks that ended, the mean of the frames each was seen in (``track_length``) and the share seen in
    ``LONG_TRACK`` frames or more (``long_tracks``; both None where no track ended); None where no clip has a front
    end."""
    total = sum((FrameLosses(**r) for r in rows if r), FrameLosses())
    if not total.frames:
        return None
    following, followed, ended = max(total.frames - total.starts, 1), max(total.followed, 1), total.ended
    return {"frames": total.frames, "starts": total.starts, "followed_per_frame": total.followed / following,
            "lost": {name: getattr(total, f"lost_{name}") / followed
                     for name in ("no_flow", "round_trip", "border", "epipolar")},
            "new_per_frame": total.new / following, "new_lost": total.new_lost / max(total.new, 1),
            "track_length": total.ended_frames / ended if ended else None,
            "long_tracks": total.ended_long / ended if ended else None}
