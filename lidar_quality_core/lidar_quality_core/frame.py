"""The frame contract every method's processor keeps (no rclpy).

``process(inputs) -> outputs`` where outputs have ``messages`` (output name -> message, in
publication order), ``markers`` (or None), ``issues`` (warning cause -> text: input
problems of this frame, the frame still goes out) and ``counts`` (name -> increment, summed
into diagnostics and process_bag's summary), and optionally ``notes`` (decisions to log
once at info level, e.g. an ``intensity_scale: auto`` decision), ``values`` (diagnostics
values of the latest frame) and ``errors`` (the keys of ``issues`` at level ERROR rather
than WARN). A frame that cannot be processed raises
:class:`FrameRejected`: it is dropped and counted under its ``reason``. The node base class
(``lidar_quality_ros.node_base.QualityNode``) and ``process_bag`` run processors this way.
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["FrameRejected", "FrameOutputs"]


class FrameRejected(ValueError):
    """A frame dropped as a whole; ``reason`` names the drop in diagnostics, ``cause`` the
    throttled warning (None: counted, not warned)."""

    reason = "processing_error"
    cause: str | None = None


@dataclass
class FrameOutputs:
    """Outputs of a frame for processors without their own outputs class."""

    messages: dict
    markers: object = None
    issues: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    values: dict = field(default_factory=dict)
    errors: frozenset = frozenset()
