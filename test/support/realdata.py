"""Where the real sensor clouds are (``$LQ_REALDATA`` or ``<repo>/../shared/realdata``)."""
from __future__ import annotations

import os
from pathlib import Path

REAL_FILES = ["hesai_40p", "hesai_64", "hesai_at128", "hesai_ot128", "hesai_qt128",
              "hesai_qt64", "hesai_xt16", "hesai_xt32", "hesai_xt32m", "velodyne_vlp16",
              "velodyne_vlp32", "velodyne_vls128"]


def realdata_dir() -> Path:
    env = os.environ.get("LQ_REALDATA")
    return Path(env) if env else Path(__file__).resolve().parents[3] / "shared" / "realdata"
