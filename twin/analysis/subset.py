"""Ranking a large campaign's candidates, or diagnosing it, on a stratified subset of its trajectories (issue 18).

A diagnosis linearises every candidate effect by replaying every trajectory once per parameter; on a paper-size
campaign (hundreds of trajectories) that is most of its time. The candidates' ranking (their linearised
evidence and screening held-out figures) needs far fewer: each kind of press (sensor x indenter x path kind,
normal or angled) a few times. `sampled` picks at most `per_stratum` trajectories of each such stratum,
spread evenly over the stratum in campaign order (drifts over a campaign are sampled across it), and diagnosis
ranks on the residual of the model on them alone (the noise estimated on every trajectory), then refits the top
candidates and judges them held out (each indenter left out in turn) on every trajectory, so the verdict rests
on all the data; which trajectories ranked is reported (`RankedOn.to_dict`, the `ranked_on` key of
`twin diagnose --json`). With `--per-stratum`, such a subset is taken up front for a diagnosis that runs on it
alone (every stage: noise, base, ranking, refits, held-out judgements; the `sampled` key), for a campaign too
large to replay every trajectory many times.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, replace

import numpy as np

from twin.analysis.data import CampaignData, TrajectoryRecord


def stratum(trajectory: TrajectoryRecord) -> tuple[int, str, bool]:
    """The kind of press a trajectory is: (sensor id, indenter, normal path)."""
    return trajectory.sensor_id, trajectory.indenter, trajectory.normal


def stratified(trajectories: list[TrajectoryRecord], per_stratum: int) -> list[TrajectoryRecord]:
    """At most `per_stratum` (>= 1) trajectories of each stratum (`stratum`), evenly spread over the stratum's
    trajectories in the given order (its first and last among them when two or more are taken); given order."""
    if per_stratum < 1:
        raise ValueError(f"per_stratum must be at least 1, got {per_stratum}")
    members: dict[tuple, list[int]] = defaultdict(list)
    for i, t in enumerate(trajectories):
        members[stratum(t)].append(i)
    chosen = set()
    for indices in members.values():
        spread = np.linspace(0, len(indices) - 1, min(per_stratum, len(indices))).round().astype(int)
        chosen.update(indices[k] for k in spread)
    return [t for i, t in enumerate(trajectories) if i in chosen]


@dataclass(frozen=True)
class RankedOn:
    """Which trajectories ranked the candidates: (sensor id, trajectory id) of each, of how many, how many per
    stratum at most and how many strata."""

    trajectories: list[tuple[int, int]]
    of: int
    per_stratum: int
    strata: int

    def to_dict(self) -> dict:
        """JSON-ready form (`twin diagnose --json`'s `ranked_on`)."""
        return {
            "trajectories": [{"sensor": s, "trajectory": t} for s, t in self.trajectories],
            "of": self.of,
            "per_stratum": self.per_stratum,
            "strata": self.strata,
        }


def sampled(datasets: list[CampaignData], per_stratum: int) -> tuple[list[CampaignData], RankedOn]:
    """`datasets` with only their stratified subset (`stratified`) of trajectories (a dataset left with none is
    dropped), and which trajectories those are."""
    trajectories = [t for d in datasets for t in d.trajectories]
    keep = {id(t) for t in stratified(trajectories, per_stratum)}
    subsets = [replace(d, trajectories=[t for t in d.trajectories if id(t) in keep]) for d in datasets]
    chosen = [t for d in subsets for t in d.trajectories]
    on = RankedOn(
        [(t.sensor_id, t.trajectory_id) for t in chosen],
        len(trajectories),
        per_stratum,
        len({stratum(t) for t in trajectories}),
    )
    return [d for d in subsets if d.trajectories], on
