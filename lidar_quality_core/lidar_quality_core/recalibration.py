"""Recalibration of a trained meta model on top of it (issue 18's adaptation): the node
loads these like any joblib estimator of the model store.

* :class:`RecalibratedClassifier`: ``P = sigmoid(a * logit(base(X)) + b * g(X[:, c]) + d)``;
* :class:`RecalibratedRegressor`: ``y = a * base(X) + b * g(X[:, c]) + d``;

with ``base`` the model being adapted (kept whole inside), ``c`` one feature column that
carries the user's own signal (the detector score, the mean entropy) and ``g`` ``logit``
(scores, probabilities) or ``identity``. Two inputs and three coefficients: learnable from
a handful of labelled frames, and monotone in the base model where ``a > 0``. Fitting is
``lidar_quality_training.adapt``'s; this module only predicts, so runtime packages import
no training code. NaN in the column counts as its training mean (``fill``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["TRANSFORMS", "logit", "RecalibratedClassifier", "RecalibratedRegressor"]

TRANSFORMS = ("logit", "identity")
_EPS = 1e-4  # scores of exactly 0 or 1 stay finite in logit space


def logit(p) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), _EPS, 1.0 - _EPS)
    return np.log(p) - np.log1p(-p)


class _Recalibrated:
    def __init__(self, base, coef, intercept: float, *, column: int | None,
                 transform: str = "logit", fill: float = 0.0):
        if transform not in TRANSFORMS:
            raise ValueError(f"transform must be one of {TRANSFORMS}, got {transform!r}")
        self.base = base
        self.coef = np.asarray(coef, np.float64).reshape(-1)
        self.intercept = float(intercept)
        self.column = None if column is None else int(column)
        self.transform = transform
        self.fill = float(fill)
        if self.coef.size != (1 if self.column is None else 2):
            raise ValueError(f"need {1 if self.column is None else 2} coefficients, got "
                             f"{self.coef.size}")
        n_in = getattr(base, "n_features_in_", None)
        if n_in is not None:
            self.n_features_in_ = int(n_in)

    def _column(self, X) -> np.ndarray:
        v = np.asarray(X, np.float64)[:, self.column]
        v = logit(v) if self.transform == "logit" else v
        return np.where(np.isfinite(v), v, self.fill)

    def inputs(self, X, base_out) -> np.ndarray:
        """The (n, 1 or 2) design matrix the coefficients apply to."""
        cols = [np.asarray(base_out, np.float64).reshape(-1)]
        if self.column is not None:
            cols.append(self._column(X))
        return np.column_stack(cols)


class RecalibratedClassifier(_Recalibrated):
    """Binary classifier: the base model's confidence recalibrated (see module)."""

    classes_ = np.array([0, 1])

    @staticmethod
    def base_output(base, X) -> np.ndarray:
        return logit(np.asarray(base.predict_proba(X), np.float64)[:, 1])

    def predict_proba(self, X) -> np.ndarray:
        z = self.inputs(X, self.base_output(self.base, X)) @ self.coef + self.intercept
        p = 1.0 / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))
        return np.column_stack([1.0 - p, p])

    def predict(self, X) -> np.ndarray:
        return (self.predict_proba(X)[:, 1] >= 0.5).astype(np.int64)


class RecalibratedRegressor(_Recalibrated):
    """Regressor: the base model's prediction recalibrated linearly (see module)."""

    @staticmethod
    def base_output(base, X) -> np.ndarray:
        return np.asarray(base.predict(X), np.float64).reshape(-1)

    def predict(self, X) -> np.ndarray:
        return self.inputs(X, self.base_output(self.base, X)) @ self.coef + self.intercept
