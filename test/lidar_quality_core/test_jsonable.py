import json
from pathlib import Path

import numpy as np

from lidar_quality_core.jsonable import jsonable


def test_numpy_paths_and_non_finite_values_become_plain_json():
    d = {1: np.float32(0.5), "a": np.arange(3), "n": np.nan, "i": np.int64(7),
         "b": np.bool_(True), "p": Path("x/y"), "t": (np.inf, -1.5), "s": "ok"}
    out = jsonable(d)
    assert out == {"1": 0.5, "a": [0, 1, 2], "n": None, "i": 7, "b": True, "p": "x/y",
                   "t": [None, -1.5], "s": "ok"}
    assert type(out["i"]) is int and type(out["b"]) is bool
    json.dumps(out, allow_nan=False)  # strict JSON


def test_private_keys_dropped_on_request():
    d = {"auroc": 0.9, "_oof": np.zeros(4), "nested": [{"_x": 1, "y": np.float64(2)}]}
    assert jsonable(d, drop_private=True) == {"auroc": 0.9, "nested": [{"y": 2.0}]}
    assert "_oof" in jsonable(d)
