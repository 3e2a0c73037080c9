"""The suite's conventions, each written once: what a true positive is, how angles wrap,
how a class's probability field is named. Every package takes them from here."""
from __future__ import annotations

import numpy as np

#: BEV IoU with a ground-truth box at which a detection is a true positive: LMD's and
#: MIMO's confidence is the probability of this event (the papers' threshold).
TP_IOU = 0.5


def wrap_angle(a):
    """Angle(s) [rad] wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def probability_field(class_name: str) -> str:
    """PointCloud2 field of a class's softmax probability: the class name with ``-`` and
    spaces replaced by ``_`` (field names are identifiers)."""
    return str(class_name).replace("-", "_").replace(" ", "_")
