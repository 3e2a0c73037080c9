"""Intensity scale: every feature sees intensity in [0, 1] (numpy only).

Our simulator and KITTI write reflectance in [0, 1]; most lidar drivers publish 0..255
(Velodyne, Hesai, nebula), some 16-bit values. The same scan in two scales moved LMD
confidences by up to 0.40, silently. So the nodes, the offline tools and training bring
the cloud's intensity to [0, 1] before any feature reads it, by the ``intensity_scale``
setting (one per method's settings, stored in the model manifests with the training
settings):

* ``unit``: the input is in [0, 1] already (factor 1);
* ``byte``: the input is 0..255 (factor 1 / 255);
* ``auto`` (default): decided from the data: the largest finite intensity of the first
  ``AUTO_FRAMES`` frames; above ``UNIT_MAX`` (1 plus float rounding) it is ``byte``, else
  ``unit``. A later frame of those first ones that contradicts the decision (a value above
  1 after ``unit``) changes it once more; after them it is fixed. Above 255 (16-bit
  reflectivity) no preset fits: ``auto`` takes ``byte`` and reports it, so the warning
  names the problem instead of hiding it.

Output messages keep the input's own intensity values; only the features use the scaled one.
"""
from __future__ import annotations

import numpy as np

from lidar_quality_core.parameters import param

__all__ = ["INTENSITY_SCALES", "FACTORS", "AUTO_FRAMES", "UNIT_MAX", "IntensityScale",
           "intensity_scale_param"]

INTENSITY_SCALES = ("auto", "unit", "byte")
FACTORS = {"unit": 1.0, "byte": 1.0 / 255.0}
#: frames ``auto`` looks at before its decision is fixed
AUTO_FRAMES = 5
#: largest value still read as [0, 1] (float32 round trips of 1.0)
UNIT_MAX = 1.0 + 1e-3
_BYTE_MAX = 255.0 + 1e-3


class IntensityScale:
    """The scale of one input stream: ``scale(intensity)`` -> float32 in [0, 1] (for valid
    input); ``decided`` (``unit`` | ``byte``) and ``note`` (a text when the decision was
    made or changed by this call, to log once; else None)."""

    def __init__(self, mode: str = "auto"):
        if mode not in INTENSITY_SCALES:
            raise ValueError(f"intensity_scale must be one of {INTENSITY_SCALES}, got {mode!r}")
        self.mode = mode
        self.decided: str | None = None if mode == "auto" else mode
        self.frames = 0
        self.max_seen = 0.0
        self.note: str | None = None

    def factor(self, intensity) -> float:
        """The factor for this frame's ``intensity`` (``auto``: updates the decision)."""
        self.note = None
        if self.mode != "auto":
            return FACTORS[self.mode]
        if self.frames < AUTO_FRAMES:
            self.frames += 1
            v = np.asarray(intensity, dtype=np.float64)
            finite = v[np.isfinite(v)]
            if finite.size:
                self.max_seen = max(self.max_seen, float(finite.max()))
            decision = "byte" if self.max_seen > UNIT_MAX else "unit"
            if decision != self.decided:
                self.note = self._explain(decision)
                self.decided = decision
        return FACTORS[self.decided]

    def scale(self, intensity) -> np.ndarray:
        """``intensity`` times :meth:`factor` as float32 (a new array unless the factor is 1)."""
        f = self.factor(intensity)
        v = np.asarray(intensity, dtype=np.float32)
        return v if f == 1.0 else v * np.float32(f)

    def _explain(self, decision: str) -> str:
        seen = f"largest intensity of the first {self.frames} frame(s) {self.max_seen:g}"
        if decision == "unit":
            text = f"intensity_scale auto: {seen}: reading intensity as [0, 1] (factor 1)"
        else:
            text = f"intensity_scale auto: {seen}: reading intensity as 0..255 (factor 1/255)"
            if self.max_seen > _BYTE_MAX:
                text += ("; values above 255 fit no known scale (16-bit reflectivity?): "
                         "features get intensities above 1, unlike any training data")
        if self.frames > 1:
            text += " (changed after the first frames)"
        return text


def intensity_scale_param(used_for: str):
    """The ``intensity_scale`` parameter field of a method's settings (one declaration:
    ``lidar_quality_core.parameters``); ``used_for`` says what reads the scaled intensity."""
    return param("auto", f"Scale of input/points' intensity, brought to [0, 1] for {used_for}: "
                         "'unit' (already [0, 1], as our simulator and KITTI), 'byte' (0..255, "
                         "most drivers) or 'auto' (decided from the first frames and logged).",
                 choices=INTENSITY_SCALES)
