"""Domain report: does LMD's drift monitor stay quiet in its training domain and fire on
shifts? (issue 18's domain-shift benchmark, first part: LMD's monitor only.)

    python -m lidar_quality_tools.domain_report --out out/domain [--frames 30] [--sequences 3]

Simulated scans (``lidar_sim``) behind the reference detector, fed frame by frame to
``LmdProcessor`` with the shipped models and the node's drift defaults:

* ``in domain``: the training sensor (HDL-64, 64 x 2048) on new scenes;
* ``sensor HDL-32E`` / ``sensor VLS-128``: another sensor preset, same kind of scenes;
* ``scores x 0.6``: another detector's calibration (every score scaled);
* ``intensity 0..255 read as unit``: a driver's byte intensities with
  ``intensity_scale: unit`` (with the default ``auto`` the node rescales them);
* ``real KITTI`` (``../shared/realdata_kitti`` when present; three scans, so one window
  of three frames): real scans behind the same detector.

Per case: frames, alarm rate (frames at WARN or ERROR), frames until the first ERROR in
each sequence, the last drift score and the quantities named. Written to
``OUT/report.md`` and ``OUT/summary.json``. Not yet here: LMS and MIMO, the scene-type
shift, a second trained detector, adaptation with labelled frames.
"""
from __future__ import annotations

import argparse
import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

SEED0 = 9100      # scene seeds far from the meta splits'
CASES = ("in domain", "sensor HDL-32E", "sensor VLS-128", "scores x 0.6",
         "intensity 0..255 read as unit")


def _frames(case: str, seed: int, n: int, columns: int):
    """(cloud, detections, proposals) messages of ``n`` frames of one simulated sequence."""
    from lidar_quality_core.pointcloud import create_cloud
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl32, hdl64, vls128
    from reference_perception.cli import Perception
    from reference_perception.detector import PROB_NAMES
    from reference_perception.messages import detector_messages
    from std_msgs.msg import Header

    cfg = {"sensor HDL-32E": hdl32, "sensor VLS-128": vls128}.get(case, hdl64)(columns=columns)
    perception = _frames.perception = getattr(_frames, "perception", None) or Perception(
        detector=True, segmenter=False, heads=0)
    for k, f in enumerate(sequence_frames(seed, n, cfg=cfg)):
        h = Header(frame_id="lidar")
        h.stamp.sec, h.stamp.nanosec = 1000 + k // 10, (k % 10) * 100_000_000
        inten = f.intensity * 255.0 if case.startswith("intensity") else f.intensity
        cloud = create_cloud(h, {"x": f.xyz[:, 0].astype(np.float32),
                                 "y": f.xyz[:, 1].astype(np.float32),
                                 "z": f.xyz[:, 2].astype(np.float32),
                                 "intensity": inten.astype(np.float32),
                                 "ring": f.ring.astype(np.uint16)})
        # the detector reads its own scale: only LMD sees the byte intensities
        result = perception.run(f.xyz, f.intensity, f.ring)
        dets, props = detector_messages(h, result["detector"], PROB_NAMES[1:])
        if case == "scores x 0.6":
            for arr in (dets, props):
                for d in arr.detections:
                    for r in d.results:
                        r.hypothesis.score *= 0.6
        yield cloud, dets, props


def run_case(case: str, *, sequences: int, frames: int, columns: int) -> dict:
    """One case over ``sequences`` simulated sequences of ``frames`` frames."""
    from lidar_quality_core.meta_model import MetaModels
    from lmd_ros.pipeline import LmdProcessor, LmdSettings, default_model_paths

    s = LmdSettings()
    if case.startswith("intensity"):
        s = replace(s, intensity_scale="unit")
    models = MetaModels(*default_model_paths(s.proposal_mode), s.feature_names())
    levels, first, last = [], [], {}
    for q in range(sequences):
        proc = LmdProcessor(s, models)
        hit = None
        for k, (cloud, dets, props) in enumerate(_frames(case, SEED0 + q, frames, columns)):
            out = proc.process(cloud, dets, props)
            level = out.values.get("drift.level", "off")
            levels.append(level)
            if hit is None and level == "ERROR":
                hit = k + 1
            last = out.values
        first.append(hit)
    return {"case": case, "frames": len(levels),
            "alarm_rate": round(sum(v in ("WARN", "ERROR") for v in levels) / len(levels), 4),
            "frames_to_error": first, "last_score": last.get("drift.score"),
            "quantities": last.get("drift.quantities", "")}


def real_kitti(root: Path) -> dict | None:
    """The three real KITTI scans as one window (``None`` without them)."""
    import tempfile

    from lidar_quality_core.domain_profile import LEVEL_NAMES, DriftMonitor
    from lidar_quality_core.meta_model import MetaModels
    from lidar_quality_training.lmd.dataset import load_kitti, settings_for
    from lmd_ros.pipeline import LmdSettings, default_model_paths
    from reference_perception.cli import main as perception_main

    if not (root / "training" / "velodyne").is_dir():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        perception_main(["kitti", "--root", str(root), "--out", tmp, "--heads", "0",
                         "--no-segmenter", "--quiet"])
        ds = load_kitti(root, Path(tmp), [settings_for("none")], progress=False)["none"]
    names = LmdSettings(proposal_mode="none").feature_names()
    profile = MetaModels(*default_model_paths("none"), names).domain_profile
    mon = DriftMonitor(profile, window=ds.n_frames, min_frames=1)
    for k in range(ds.n_frames):
        rows = ds.frame == k
        r = mon.add({**{n: ds.X[rows, j] for j, n in enumerate(names)},
                     "detector score": ds.score[rows], "points per frame": [ds.frame_points[k]]})
    return {"case": "real KITTI (3 scans, one window)", "frames": ds.n_frames,
            "alarm_rate": None, "frames_to_error": [ds.n_frames] if r.level == 2 else [None],
            "last_score": round(r.score, 3), "level": LEVEL_NAMES[r.level],
            "quantities": ", ".join(k for k, _ in r.drifted), "text": r.text}


def report(rows: list[dict], args) -> str:
    lines = ["# Domain report: LMD's drift monitor", "",
             f"Shipped LMD models (threshold mode), node defaults (window 50, WARN 0.25, ERROR "
             f"0.5); {args.sequences} simulated sequence(s) of {args.frames} frames per case "
             f"(64 x {args.columns} for the HDL-64), scene seeds from {SEED0}.", "",
             "| case | frames | alarm rate | frames to ERROR (per sequence) | last score | "
             "most drifted |", "|---|---|---|---|---|---|"]
    for r in rows:
        rate = "-" if r["alarm_rate"] is None else f"{100 * r['alarm_rate']:.1f} %"
        first = ", ".join("never" if f is None else str(f) for f in r["frames_to_error"])
        lines.append(f"| {r['case']} | {r['frames']} | {rate} | {first} | {r['last_score']} "
                     f"| {r['quantities']} |")
    lines += ["", "Not yet in this report: LMS and MIMO, another scene type, a second trained "
              "detector, adaptation with 1 / 5 / 20 / 50 labelled frames (issue 18)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/domain"))
    ap.add_argument("--sequences", type=int, default=3)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--columns", type=int, default=2048)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated subset")
    ap.add_argument("--kitti", type=Path, default=Path(os.environ.get(
        "LQ_REALDATA_KITTI", Path(__file__).resolve().parents[3] / "shared" / "realdata_kitti")))
    args = ap.parse_args(argv)
    rows = []
    for case in [c.strip() for c in args.cases.split(",") if c.strip()]:
        if case not in CASES:
            ap.error(f"unknown case {case!r} (known: {', '.join(CASES)})")
        rows.append(run_case(case, sequences=args.sequences, frames=args.frames,
                             columns=args.columns))
        print(f"domain_report: {case}: {rows[-1]}", flush=True)
    kitti = real_kitti(args.kitti)
    if kitti is None:
        print(f"domain_report: real KITTI scans not found at {args.kitti}: left out", flush=True)
    else:
        rows.append(kitti)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(rows, indent=1, default=str) + "\n")
    (args.out / "report.md").write_text(report(rows, args))
    print(f"domain_report: wrote {args.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
