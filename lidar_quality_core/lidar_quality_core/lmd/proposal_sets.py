"""LidarMetaDetect proposal sets Prop(b) (paper section III; numpy only).

Which pre-NMS proposals belong to a post-NMS box b: in ``"exact"`` mode the NMS
pre-image (the proposals b's survivor suppressed, :func:`nms_preimages` and
:meth:`ProposalSets.from_nms`); in ``"threshold"`` mode every proposal whose BEV IoU with
b is above a threshold, decided in :func:`lidar_quality_core.lmd.features.compute_features`.
How the box itself and its copies enter a set is documented there.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from lidar_quality_core.nms import rotated_nms

__all__ = ["ProposalSets", "nms_preimages"]


@dataclass(frozen=True)
class ProposalSets:
    """Proposal indices per post-NMS box as CSR: box ``k`` owns
    ``index[offsets[k]:offsets[k + 1]]``."""

    offsets: np.ndarray  # (n_boxes + 1,) int64
    index: np.ndarray    # int64 proposal indices

    @classmethod
    def from_lists(cls, sets: Sequence[Sequence[int]]) -> "ProposalSets":
        """From one index sequence per box."""
        counts = np.array([len(s) for s in sets], dtype=np.int64)
        offsets = np.zeros(len(counts) + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        parts = [np.asarray(s, dtype=np.int64).reshape(-1) for s in sets]
        index = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        return cls(offsets, index)

    @classmethod
    def from_owner(cls, owner, n_boxes: int) -> "ProposalSets":
        """From the owning box per proposal (``-1``: none)."""
        owner = np.asarray(owner, dtype=np.int64).reshape(-1)
        if len(owner) and owner.max(initial=-1) >= n_boxes:
            raise ValueError(f"owner refers to box {owner.max()} of {n_boxes}")
        sel = np.flatnonzero(owner >= 0)
        order = sel[np.argsort(owner[sel], kind="stable")]
        offsets = np.zeros(n_boxes + 1, dtype=np.int64)
        np.cumsum(np.bincount(owner[sel], minlength=n_boxes), out=offsets[1:])
        return cls(offsets, order.astype(np.int64))

    @classmethod
    def from_nms(cls, suppressed_by, keep) -> "ProposalSets":
        """Pre-images of the survivors ``keep`` (post-NMS box k = proposal ``keep[k]``)
        from ``rotated_nms(...)``: ``{j : suppressed_by[j] == keep[k]}``, survivor
        included."""
        sup = np.asarray(suppressed_by, dtype=np.int64).reshape(-1)
        keep = np.asarray(keep, dtype=np.int64).reshape(-1)
        pos = np.full(len(sup) + 1, -1, dtype=np.int64)  # [-1] -> -1 for dropped boxes
        pos[keep] = np.arange(len(keep))
        return cls.from_owner(pos[sup], len(keep))

    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """(box index, proposal index) per member, grouped by box."""
        off = np.asarray(self.offsets, dtype=np.int64)
        return (np.repeat(np.arange(len(off) - 1), np.diff(off)),
                np.asarray(self.index, dtype=np.int64)[off[0]:off[-1]])


def nms_preimages(boxes, scores, valid, iou_threshold: float, score_threshold: float):
    """``(keep, suppressed_by)`` of a rotated NMS over the ``valid`` proposals (indices into
    all proposals; invalid ones take no part and are suppressed by none, ``-1``)."""
    sel = np.flatnonzero(valid)
    res = rotated_nms(np.asarray(boxes)[sel], np.asarray(scores)[sel], iou_threshold,
                      score_threshold=score_threshold)
    sup = np.full(len(valid), -1, dtype=np.int64)
    sub = res.suppressed_by
    sup[sel[sub >= 0]] = sel[sub[sub >= 0]]
    return sel[res.keep], sup
