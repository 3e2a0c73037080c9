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


#: the LMS sensor preset of each real sensor
PRESETS = {"hesai_40p": "Pandar40P", "hesai_64": "Pandar64", "hesai_at128": "AT128",
           "hesai_ot128": "OT128", "hesai_qt128": "PandarQT128", "hesai_qt64": "PandarQT64",
           "hesai_xt16": "PandarXT16", "hesai_xt32": "PandarXT32",
           "hesai_xt32m": "PandarXT32M", "velodyne_vlp16": "VLP-16",
           "velodyne_vlp32": "VLP-32C", "velodyne_vls128": "VLS-128"}


def require_realdata() -> Path:
    """The real clouds' directory, or a pytest skip saying what is missing and how to fix it."""
    import pytest

    d = realdata_dir()
    missing = [n for n in REAL_FILES if not (d / f"{n}.pcd").is_file()]
    if missing:
        pytest.skip(f"real sensor clouds not found in {d} ({len(missing)} missing, e.g. "
                    f"{missing[0]}.pcd): set LQ_REALDATA or provide ../shared/realdata")
    return d


def realdata_kitti_dir() -> Path:
    """The real labelled KITTI scans (``$LQ_REALDATA_KITTI`` or ``../shared/realdata_kitti``)."""
    env = os.environ.get("LQ_REALDATA_KITTI")
    return Path(env) if env else Path(__file__).resolve().parents[3] / "shared" / "realdata_kitti"


def require_realdata_kitti() -> Path:
    """The real KITTI directory (with ``training/{velodyne,label_2,calib}``), or a pytest
    skip saying what is missing and how to fix it."""
    import pytest

    root = realdata_kitti_dir()
    base = root / "training"
    if not all((base / d).is_dir() for d in ("velodyne", "label_2", "calib")):
        pytest.skip(f"real KITTI frames not found at {base} "
                    "(set LQ_REALDATA_KITTI to the realdata_kitti directory)")
    return root
