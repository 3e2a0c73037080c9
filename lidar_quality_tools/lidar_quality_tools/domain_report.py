"""Domain report: the domain-shift benchmark of issue 18. Does the drift monitor stay
quiet in the training domain and fire on shifts, and how far does adaptation with 1, 5,
20 and 50 labelled frames bring LMD back?

    python -m lidar_quality_tools.domain_report --out out/domain   (make domain-report)

Cases (simulated with ``lidar_sim`` behind the reference detector, LMD in the node's
default ``threshold`` mode with the shipped models):

* ``in domain``: the training sensor (HDL-64) and scene type on new seeds;
* ``sensor HDL-32E`` / ``sensor VLS-128``: another sensor preset;
* ``scene suburban``: an open suburban road with parked cars and vegetation;
* ``scores x 0.6`` and ``scores recalibrated``: another detector's calibration (every
  score scaled; every score through ``sigmoid((logit(s) - 1) / 2)``);
* ``intensity 0..255 read as unit``: a driver's byte intensities with
  ``intensity_scale: unit`` (the default ``auto`` rescales them);
* ``real KITTI``: the three labelled scans of ``../shared/realdata_kitti`` behind the same
  detector (``none`` mode: KITTI result files carry no proposals).

Per case: ``TEST_SEQUENCES`` test sequences and ``POOL_SEQUENCES`` sequences of labelled
frames to adapt on, on other seeds. Monitor: every test frame through ``LmdProcessor``
with the node's drift defaults (alarm rate, frames until the first ERROR, last score).
Adaptation (``lidar_quality_training.adapt``): for n in ``N_FRAMES`` labelled frames of
the pool (``DRAWS`` random draws below 50), the adapted pair and a model trained on those
frames only, against the shipped pair and the detector score, all on the test frames:
AUROC, ECE, R². Held-out false alarms: the three nodes' monitors over the held-out
``meta_test`` bags (``make meta-data``), when present. Written to ``OUT/report.md`` and
``OUT/summary.json``.

LMS and MIMO (``--methods``; sections ``lms`` / ``mimo`` of the summary): per case,
perception bags written in a temporary directory (``lidar_sim`` frames ->
``SimBagWriter`` -> ``reference_perception.cli.process_bag`` with the reference segmenter
or the 2-head detector, the case's shift applied to their outputs), read by each method's
dataset loader (``lms`` ``build_dataset`` / ``mimo`` ``load_bags``) and by the node
(``process_one``, fresh per bag) for the monitor; nothing is shared between readers, so no
processor re-scores another's messages. Fewer frames than LMD (``LM_*``). Cases: LMS
``LMS_CASES`` (the segmenter's probabilities tempered: ``temper``), MIMO ``MIMO_CASES``
(every head's class scores x 0.6); node parameters per case: ``node_params``. Baselines:
LMS the paper's "Entropy" pair (``mean_E`` alone, fitted on the in-domain ``meta_train``
bags as ``lms-eval`` does), MIMO the merged score.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

SEED0 = 9100      # scene seeds far from the meta splits'
CASES = ("in domain", "sensor HDL-32E", "sensor VLS-128", "scene suburban", "scores x 0.6",
         "scores recalibrated", "intensity 0..255 read as unit")
N_FRAMES = (1, 5, 20, 50)
DRAWS = 3
TEST_SEQUENCES, TEST_FRAMES = 4, 20
POOL_SEQUENCES, POOL_FRAMES = 5, 10
MODE = "threshold"


def _shift_scores(case: str, arrays) -> None:
    from lidar_quality_core.recalibration import logit

    if case == "scores x 0.6":
        f = lambda s: 0.6 * s  # noqa: E731 - the case's definition, read beside the other
    elif case == "scores recalibrated":
        f = lambda s: float(1.0 / (1.0 + np.exp(-(logit(s) - 1.0) / 2.0)))  # noqa: E731 - as above
    else:
        return
    for arr in arrays:
        for d in arr.detections:
            for r in d.results:
                r.hypothesis.score = float(f(r.hypothesis.score))


def simulate(case: str, seed: int, n: int, columns: int):
    """``(cloud, detections, proposals, gt_boxes, gt_names, gt_ids)`` of ``n`` frames of
    one simulated sequence of ``case``."""
    from lidar_quality_core.pointcloud import create_cloud
    from lidar_sim import classes
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl32, hdl64, vls128
    from reference_perception.cli import Perception
    from reference_perception.detector import PROB_NAMES
    from reference_perception.messages import detector_messages
    from std_msgs.msg import Header

    cfg = {"sensor HDL-32E": hdl32, "sensor VLS-128": vls128}.get(case, hdl64)(columns=columns)
    scene = "suburban" if case == "scene suburban" else None
    perception = simulate.perception = getattr(simulate, "perception", None) or Perception(
        detector=True, segmenter=False, heads=0)
    frames = (sequence_frames(seed, n, cfg=cfg, scene=scene) if scene
              else sequence_frames(seed, n, cfg=cfg))
    for k, f in enumerate(frames):
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
        _shift_scores(case, (dets, props))
        yield (cloud, dets, props, np.asarray(f.gt_boxes, np.float64).reshape(-1, 7),
               [classes.class_name(c) for c in f.gt_class],
               [str(i) for i in f.gt_instance])


def _settings(case: str, mode: str = MODE):
    from lmd_ros.pipeline import LmdSettings

    s = LmdSettings(proposal_mode=mode)
    return replace(s, intensity_scale="unit") if case.startswith("intensity") else s


def _base_models(settings):
    from lidar_quality_core.meta_model import MetaModels
    from lmd_ros.pipeline import default_model_paths

    return MetaModels(*default_model_paths(settings.proposal_mode), settings.feature_names())


def sequences(case: str, seeds, n: int, columns: int) -> list[list]:
    """The frames of one sequence per seed, as lists (used twice: monitor and dataset)."""
    return [list(simulate(case, s, n, columns)) for s in seeds]


def monitor(case: str, seqs: list[list]) -> dict:
    """The node's drift monitor over each test sequence (a fresh processor per sequence)."""
    from lmd_ros.pipeline import LmdProcessor

    s = _settings(case)
    models = _base_models(s)
    levels, first, scores, last = [], [], [], {}
    for seq in seqs:
        proc = LmdProcessor(s, models)
        hit = None
        for k, (cloud, dets, props, *_gt) in enumerate(seq):
            out = proc.process(cloud, dets, props)
            levels.append(out.values.get("drift.level", "off"))
            if isinstance(out.values.get("drift.score"), (int, float)):
                scores.append(float(out.values["drift.score"]))
            if hit is None and levels[-1] == "ERROR":
                hit = k + 1
            last = out.values
        first.append(hit)
    return {"frames": len(levels),
            "alarm_rate": round(sum(v in ("WARN", "ERROR") for v in levels) / len(levels), 4),
            "frames_to_error": first, "last_score": last.get("drift.score"),
            "max_score": round(max(scores), 3) if scores else None,
            "quantities": last.get("drift.quantities", "")}


def dataset(case: str, seqs: list[list], tag: str, mode: str = MODE):
    """The LMD dataset (features and targets) of ``seqs``, one group per sequence."""
    from lidar_quality_training.lmd.dataset import dataset_from_messages

    def frames():
        for q, seq in enumerate(seqs):
            for k, (cloud, dets, props, boxes, names, ids) in enumerate(seq):
                yield cloud, dets, props, boxes, names, ids, f"{tag}{q}", str(k)

    return dataset_from_messages(frames(), [_settings(case, mode)],
                                 source={"kind": "simulated", "path": f"{case} ({tag})"})[mode]


def _metrics(ds, conf, pred) -> dict:
    from lidar_quality_training.adapt import evaluate

    m = evaluate(ds.tp, ds.iou, conf, pred)
    return {k: m.get(k) for k in ("auroc", "ece", "r2")}


def adapted_alarms(profile_json: dict, test, names) -> dict:
    """The drift monitor of an adapted pair (its profile of the user's frames, node
    defaults) over the test sequences: alarms among the scored frames."""
    from lidar_quality_core.domain_profile import WARN, DomainProfile, DriftMonitor

    profile = DomainProfile.from_json(profile_json)
    scored = alarms = 0
    for g in test.groups:
        mon = DriftMonitor(profile)
        for k in np.flatnonzero(test.frame_group == g):
            rows = test.frame == k
            r = mon.add({**{n: test.X[rows, j] for j, n in enumerate(names)},
                         "detector score": test.score[rows],
                         "points per frame": [test.frame_points[k]]})
            if r.frames >= mon.min_frames:
                scored += 1
                alarms += r.level >= WARN
    return {"scored": int(scored), "alarms": int(alarms)}


def adaptation(pool, test, *, n_frames=N_FRAMES, draws: int = DRAWS, seed: int = 0) -> dict:
    """Test metrics of the shipped pair, the detector score, and per n of the adapted pair
    (with its choice) and of a model trained on the n frames only (mean over draws, and
    each draw); for n >= 20 (and the largest n) also the adapted pair's drift monitor on the
    test frames."""
    from lidar_quality_training import adapt as A
    from lidar_quality_training.lmd.adapt import adapt_data, profile_extra

    models = _base_models(_settings("", pool.mode))
    base_c, base_r = models.classifier.estimator, models.regressor.estimator
    conf, pred = models.predict(test.X)
    out = {"shipped": _metrics(test, conf, pred),
           "detector score": _metrics(test, test.score, None),
           "test": {"frames": test.n_frames, "boxes": len(test), "tp": int(test.tp.sum())},
           "adapted": {}, "frames only": {}}
    data = adapt_data(pool)
    rng = np.random.default_rng(seed)
    for n in n_frames:
        if n > pool.n_frames:
            continue
        runs, fresh_runs = [], []
        for d in range(1 if n >= pool.n_frames else draws):
            pick = rng.choice(pool.n_frames, n, replace=False) if n < pool.n_frames else \
                np.arange(pool.n_frames)
            sub = data.rows(np.flatnonzero(np.isin(pool.frame, pick)))
            if not len(sub):
                runs.append({"chosen": None, "note": "no boxes"})
                continue
            res = A.adapt(sub, base_c, base_r, n_boot=50, seed=seed + d)
            c = A.predict(res.classifier, "classification", test.X)
            r = A.predict(res.regressor, "regression", test.X)
            runs.append({**_metrics(test, c, r), "chosen": res.chosen, "rows": len(sub),
                         "tp": res.n_tp})
            if (n >= 20 or n == max(n_frames)) and d == 0:
                extra, groups = profile_extra(pool, np.sort(pick), np.flatnonzero(
                    np.isin(pool.frame, pick)))
                base = models.classifier.manifest["training_data"]["domain_profile"]
                runs[-1]["monitor"] = adapted_alarms(A.profile_of(sub, extra, groups, base),
                                                     test, pool.feature_names)
            fc = A.fit_candidate("fresh", "classification", base_c, sub, seed=seed + d)
            fr = A.fit_candidate("fresh", "regression", base_r, sub, seed=seed + d)
            fresh_runs.append(_metrics(
                test, None if fc is None else A.predict(fc, "classification", test.X),
                A.predict(fr, "regression", test.X)))
        out["adapted"][n] = {"mean": _mean(runs), "draws": runs}
        out["frames only"][n] = {"mean": _mean(fresh_runs), "draws": fresh_runs}
    return out


def _mean(runs: list[dict]) -> dict:
    keys = ("auroc", "ece", "r2")
    res = {}
    for k in keys:
        v = [r.get(k) for r in runs if r.get(k) is not None and np.isfinite(r.get(k))]
        res[k] = round(float(np.mean(v)), 4) if v else None
    return res


def run_case(case: str, *, columns: int, n_frames=N_FRAMES, draws: int = DRAWS,
             test_sequences: int = TEST_SEQUENCES, test_frames: int = TEST_FRAMES,
             pool_sequences: int = POOL_SEQUENCES, pool_frames: int = POOL_FRAMES) -> dict:
    t0 = time.monotonic()
    test_seqs = sequences(case, [SEED0 + q for q in range(test_sequences)], test_frames,
                          columns)
    pool_seqs = sequences(case, [SEED0 + 500 + q for q in range(pool_sequences)],
                          pool_frames, columns)
    # the datasets first: the processor re-scores the messages it is given in place
    pool, test = dataset(case, pool_seqs, "pool"), dataset(case, test_seqs, "test")
    row = {"case": case, **monitor(case, test_seqs)}
    row["adaptation"] = adaptation(pool, test, n_frames=n_frames, draws=draws)
    row["seconds"] = round(time.monotonic() - t0, 1)
    return row


# --------------------------------------------------------------------------- real KITTI
def real_kitti(root: Path) -> dict | None:
    """The three real KITTI scans: the monitor over them as one window, and adaptation
    on two scans tested on the third (each scan left out once)."""
    import tempfile

    from lidar_quality_core.domain_profile import LEVEL_NAMES, DriftMonitor
    from lidar_quality_training.lmd.dataset import load_kitti, settings_for
    from reference_perception.cli import main as perception_main

    if not (root / "training" / "velodyne").is_dir():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        perception_main(["kitti", "--root", str(root), "--out", tmp, "--heads", "0",
                         "--no-segmenter", "--quiet"])
        ds = load_kitti(root, Path(tmp), [settings_for("none")], progress=False,
                        group_digits=0)["none"]
    names = tuple(ds.feature_names)
    models = _base_models(_settings("", "none"))
    mon = DriftMonitor(models.domain_profile, window=ds.n_frames, min_frames=1)
    for k in range(ds.n_frames):
        rows = ds.frame == k
        r = mon.add({**{n: ds.X[rows, j] for j, n in enumerate(names)},
                     "detector score": ds.score[rows], "points per frame": [ds.frame_points[k]]})
    out = {"case": "real KITTI (3 scans, one window)", "frames": ds.n_frames,
           "alarm_rate": None, "frames_to_error": [ds.n_frames] if r.level == 2 else [None],
           "last_score": round(r.score, 3), "level": LEVEL_NAMES[r.level],
           "quantities": ", ".join(k for k, _ in r.drifted), "text": r.text}
    out["adaptation"] = _leave_one_scan_out(ds, models)
    return out


def _leave_one_scan_out(ds, models) -> dict:
    from lidar_quality_training import adapt as A
    from lidar_quality_training.lmd.adapt import adapt_data

    data = adapt_data(ds)
    base_c, base_r = models.classifier.estimator, models.regressor.estimator
    conf, pred = models.predict(ds.X)
    c_all = np.full(len(ds), np.nan)
    r_all = np.full(len(ds), np.nan)
    chosen = []
    for k in range(ds.n_frames):
        test = ds.frame == k
        res = A.adapt(data.rows(np.flatnonzero(~test)), base_c, base_r, n_boot=50)
        c_all[test] = A.predict(res.classifier, "classification", ds.X[test])
        r_all[test] = A.predict(res.regressor, "regression", ds.X[test])
        chosen.append(res.chosen)
    n = ds.n_frames - 1
    return {"shipped": _metrics(ds, conf, pred), "detector score": _metrics(ds, ds.score, None),
            "test": {"frames": ds.n_frames, "boxes": len(ds), "tp": int(ds.tp.sum())},
            "adapted": {n: {"mean": _metrics(ds, c_all, r_all),
                            "draws": [{"chosen": c} for c in chosen]}},
            "frames only": {}, "scheme": "each scan scored by the pair adapted on the other two"}


# --------------------------------------------------------------------------- held out
def held_out_alarms(bags: list[Path]) -> dict | None:
    """Every node's monitor over the held-out bags: frames scored, alarms, score p99."""
    from lidar_quality_tools.process import build_runners, process_one

    if not bags:
        return None
    got: dict[str, dict] = {}

    def collect(node, frame, out):
        g = got.setdefault(node, {"levels": [], "scores": []})
        g["levels"].append(out.values.get("drift.level", "off"))
        sc = out.values.get("drift.score")
        if isinstance(sc, (int, float)) and np.isfinite(sc):
            g["scores"].append(float(sc))

    for bag in bags:
        process_one(bag, None, build_runners(), collect=collect)  # fresh monitors per bag
    res = {}
    for node, g in got.items():
        lv = g["levels"]
        scored = [v for v in lv if v in ("OK", "WARN", "ERROR")]
        res[node] = {"frames": len(lv), "scored": len(scored),
                     "alarms": sum(v in ("WARN", "ERROR") for v in lv),
                     "alarm_rate": round(sum(v in ("WARN", "ERROR") for v in lv)
                                         / max(len(scored), 1), 4),
                     "score_p99": round(float(np.quantile(g["scores"], 0.99)), 3)
                     if g["scores"] else None}
    return {"bags": len(bags), "nodes": res}


# --------------------------------------------------------------------------- LMS / MIMO
# Perception bags per case (lidar_sim -> SimBagWriter -> reference_perception process_bag),
# read by the methods' own dataset loaders and by the nodes' processors (process_one) from
# the bags: every reader decodes its own messages, nothing is shared or re-scored in place.
METHODS = ("lmd", "lms", "mimo")
TEMPERATURE = 2.0
LMS_CASES = ("in domain", "scene suburban", "sensor HDL-32E", "intensity 0..255 read as unit",
             f"probabilities tempered (T = {TEMPERATURE:g})")
MIMO_CASES = ("in domain", "scene suburban", "sensor HDL-32E", "head scores x 0.6")
LM_TEST_SEQUENCES, LM_TEST_FRAMES = 2, 15
LM_POOL_SEQUENCES, LM_POOL_FRAMES = 5, 6
LM_N_FRAMES = (1, 5, 20, 30)
LMS_TRAIN, LMS_CACHE = "data/perception/meta_train", "data/cache/lms"
_SENSORS = {"sensor HDL-32E": "hdl32", "sensor VLS-128": "vls128"}


def temper(probs, t: float = TEMPERATURE) -> np.ndarray:
    """Another segmenter calibration: ``softmax(log p / t)`` per point, i.e. ``p ** (1 / t)``
    renormalised (rows summing to 0 stay 0)."""
    q = np.power(np.clip(np.asarray(probs, np.float64), 0.0, None), 1.0 / t)
    s = q.sum(axis=1, keepdims=True)
    return (q / np.where(s > 0, s, 1.0)).astype(np.float32)


class ShiftedPerception:
    """The reference segmenter (``lms``) or 2-head detector (``mimo``) with the case's
    shift applied to its outputs; what ``reference_perception.cli.process_bag`` runs. The
    models read their own intensity scale (only the nodes see byte intensities)."""

    _loaded: dict = {}

    def __init__(self, method: str, case: str):
        from reference_perception.cli import Perception

        if method not in self._loaded:
            self._loaded[method] = Perception(detector=False, segmenter=method == "lms",
                                              heads=2 if method == "mimo" else 0)
        self.perception, self.case = self._loaded[method], case

    def run(self, xyz, intensity, ring=None) -> dict:
        if self.case.startswith("intensity"):
            intensity = np.asarray(intensity, np.float32) / 255.0
        out = self.perception.run(xyz, intensity, ring)
        if "probs" in out and self.case.startswith("probabilities tempered"):
            out["probs"] = temper(out["probs"])
        if "heads" in out and self.case == "head scores x 0.6":
            for h in out["heads"].heads:   # every class score of every head's detections
                h.class_probs = h.class_probs.copy()
                h.class_probs[:, 1:] *= 0.6
        return out


def write_bags(method: str, case: str, seeds, n: int, columns: int, out: Path) -> list[Path]:
    """One perception bag per seed under ``out`` (``seq_00`` ...): ``n`` simulated frames of
    ``case`` with the method's perception outputs."""
    import shutil

    from lidar_sim import classes, sensor
    from lidar_sim.bag import SimBagWriter
    from lidar_sim.frames import sequence_frames
    from reference_perception.cli import process_bag

    cfg = getattr(sensor, _SENSORS.get(case, "hdl64"))(columns=columns)
    scene = "suburban" if case == "scene suburban" else None
    perception = ShiftedPerception(method, case)
    out.mkdir(parents=True, exist_ok=True)
    bags = []
    for q, seed in enumerate(seeds):
        sim, dst = out / f"sim_{q:02d}", out / f"seq_{q:02d}"
        frames = (sequence_frames(seed, n, cfg=cfg, scene=scene) if scene
                  else sequence_frames(seed, n, cfg=cfg))
        with SimBagWriter(sim) as bag:
            for f in frames:
                inten = f.intensity * 255.0 if case.startswith("intensity") else f.intensity
                bag.write_frame(f.stamp_ns, xyz=f.xyz, intensity=inten, ring=f.ring,
                                label=f.semantic, instance=f.instance, gt_boxes=f.gt_boxes,
                                gt_class_names=[classes.class_name(c) for c in f.gt_class],
                                gt_ids=[str(k) for k in f.gt_instance])
        process_bag(sim, dst, perception, quiet=True)
        shutil.rmtree(sim)
        bags.append(dst)
    return bags


def node_params(method: str, case: str, columns: int) -> dict:
    """The node parameters a user would set for the case's data. LMS: the two-cloud input
    (``separate_probabilities``: rows from /lidar/points' ring, as the shipped models were
    trained), the sensor preset for another sensor (its beams and width), ``width`` = the
    sensor's columns for HDL-64 at another resolution, ``intensity_scale: unit`` for the
    byte case; MIMO: the defaults (it has no sensor geometry; ``use_points`` off)."""
    if method != "lms":
        return {}
    p: dict = {"separate_probabilities": True}
    if case in _SENSORS:
        p["sensor"] = case.split()[-1]
    elif columns != 2048:
        p["width"] = int(columns)
    if case.startswith("intensity"):
        p["intensity_scale"] = "unit"
    return p


def node_monitor(method: str, bags: list[Path], params: dict) -> dict:
    """The node's drift monitor (defaults) over each bag, a fresh node per bag: as
    ``monitor`` for LMD."""
    from lidar_quality_tools.process import build_runners, process_one

    levels, first, scores, last = [], [], [], {}
    for bag in bags:
        seen: list[dict] = []
        process_one(bag, None, build_runners(nodes=(method,), params={method: params}),
                    collect=lambda node, frame, out: seen.append(out.values))
        hit = None
        for k, v in enumerate(seen):
            levels.append(v.get("drift.level", "off"))
            sc = v.get("drift.score")
            if isinstance(sc, (int, float)) and np.isfinite(sc):
                scores.append(float(sc))
            if hit is None and levels[-1] == "ERROR":
                hit = k + 1
            last = v
        first.append(hit)
    return {"frames": len(levels),
            "alarm_rate": round(sum(v in ("WARN", "ERROR") for v in levels)
                                / max(len(levels), 1), 4),
            "frames_to_error": first, "last_score": last.get("drift.score"),
            "max_score": round(max(scores), 3) if scores else None,
            "quantities": last.get("drift.quantities", "")}


def lms_data(bags: list[Path], params: dict):
    """``(AdaptData, MetaModels, per-frame monitor quantities by sequence)`` of LMS on
    ``bags``: the node's metrics with the node's settings (``params``)."""
    from lidar_quality_core.meta_model import MetaModels
    from lidar_quality_tools.process import node_settings
    from lidar_quality_training.lms.adapt import adapt_data
    from lidar_quality_training.lms.dataset import build_dataset
    from lms_ros.pipeline import default_model_paths

    settings = node_settings("lms", params)
    ds = build_dataset(bags, settings, quiet=True)
    data = adapt_data(ds)
    models = MetaModels(*default_model_paths(), ds.names)
    quantities = [[{n: ds.X[(ds.sequence == s) & (ds.frame == f), j]
                    for j, n in enumerate(ds.names)}
                   for f in np.unique(ds.frame[ds.sequence == s])]
                  for s in np.unique(ds.sequence)]
    return data, models, quantities, ds


def mimo_data(bags: list[Path]):
    """``(AdaptData, MetaModels, per-frame monitor quantities by sequence, dataset)`` of
    MIMO on ``bags`` with the node's ``use_points`` pair."""
    from lidar_quality_core.meta_model import MetaModels
    from lidar_quality_training.mimo.adapt import adapt_data
    from lidar_quality_training.mimo.dataset import load_bags
    from mimo_ros.pipeline import MimoSettings, default_model_paths

    use_points = MimoSettings().use_points
    ds = load_bags(bags, progress=False)
    data = adapt_data(ds, use_points)
    models = MetaModels(*default_model_paths(use_points), data.feature_names)
    quantities = []
    for g in ds.groups:
        seq = []
        for k in np.flatnonzero(ds.frame_group == g):
            rows = ds.m_frame == k
            seq.append({**{n: data.X[rows, j] for j, n in enumerate(data.feature_names)},
                        "detector score": ds.m_score[rows]})
        quantities.append(seq)
    return data, models, quantities, ds


def _monitor_of(profile_json: dict, quantities: list[list[dict]]) -> dict:
    """An adapted pair's drift monitor (its profile, node defaults) over the test frames:
    alarms among the scored frames."""
    from lidar_quality_core.domain_profile import WARN, DomainProfile, DriftMonitor

    profile = DomainProfile.from_json(profile_json)
    scored = alarms = 0
    for seq in quantities:
        mon = DriftMonitor(profile)
        for q in seq:
            r = mon.add(q)
            if r.frames >= mon.min_frames:
                scored += 1
                alarms += r.level >= WARN
    return {"scored": int(scored), "alarms": int(alarms)}


def adapt_rows(pool, test, models, baseline: tuple[str, dict], *, n_frames, draws: int,
               test_quantities=None, profile_extra=None, seed: int = 0) -> dict:
    """As ``adaptation`` for any method's ``AdaptData``: test metrics of the shipped pair,
    the baseline (``(name, metrics)``), and per n labelled frames of ``pool`` the adapted
    pair and a pair trained on those frames only; for n >= 20 (and the largest n) the
    adapted pair's monitor over ``test_quantities`` (``profile_extra(rows)``: the
    non-feature quantities of its profile and their sequences)."""
    from lidar_quality_training import adapt as A

    base_c, base_r = models.classifier.estimator, models.regressor.estimator
    conf, pred = models.predict(test.X)

    def metrics(c, r) -> dict:
        m = A.evaluate(test.tp, test.iou, c, r)
        return {k: m.get(k) for k in ("auroc", "ece", "r2")}

    out = {"shipped": metrics(conf, pred), "baseline": baseline[1],
           "baseline_name": baseline[0],
           "test": {"frames": len(test.frames), "rows": len(test), "tp": int(test.tp.sum())},
           "pool_frames": len(pool.frames), "adapted": {}, "frames only": {}}
    frames = np.asarray(pool.frames)
    rng = np.random.default_rng(seed)
    for n in n_frames:
        if n > len(frames):
            continue
        runs, fresh_runs = [], []
        for d in range(1 if n >= len(frames) else draws):
            pick = rng.choice(frames, n, replace=False) if n < len(frames) else frames
            rows = np.flatnonzero(np.isin(pool.frame, pick))
            sub = pool.rows(rows)
            res = A.adapt(sub, base_c, base_r, n_boot=50, seed=seed + d)
            runs.append({**metrics(A.predict(res.classifier, "classification", test.X),
                                   A.predict(res.regressor, "regression", test.X)),
                         "chosen": res.chosen, "rows": len(sub), "tp": res.n_tp})
            if test_quantities is not None and (n >= 20 or n == max(n_frames)) and d == 0:
                extra, groups = profile_extra(rows) if profile_extra else (None, None)
                base = models.classifier.manifest["training_data"].get("domain_profile")
                runs[-1]["monitor"] = _monitor_of(A.profile_of(sub, extra, groups, base),
                                                  test_quantities)
            fc = A.fit_candidate("fresh", "classification", base_c, sub, seed=seed + d)
            fr = A.fit_candidate("fresh", "regression", base_r, sub, seed=seed + d)
            fresh_runs.append(metrics(
                None if fc is None else A.predict(fc, "classification", test.X),
                A.predict(fr, "regression", test.X)))
        out["adapted"][n] = {"mean": _mean(runs), "draws": runs}
        out["frames only"][n] = {"mean": _mean(fresh_runs), "draws": fresh_runs}
    return out


def entropy_baseline(train: Path | None):
    """The paper's "Entropy" baseline as ``lms-eval`` computes it: an XGBoost pair on
    ``mean_E`` alone, fitted on the in-domain training data (``train``: its bags, rows
    cached under ``LMS_CACHE``), or None when those bags are missing."""
    from lidar_quality_training.lms.dataset import build_dataset
    from lidar_quality_training.lms.train import feature_set, fit_pair

    if not train or not Path(train).is_dir():
        return None
    ds = build_dataset([Path(train)], cache_dir=Path(LMS_CACHE), quiet=True)
    names = feature_set(ds.names, "entropy")
    clf, reg = fit_pair(ds, names)
    return {"names": names, "classifier": clf, "regressor": reg,
            "fitted_on": f"{train} ({ds.n_frames} frames, {len(ds)} segments)"}


def run_method_case(method: str, case: str, *, columns: int, tmp: Path, entropy=None,
                    n_frames=LM_N_FRAMES, draws: int = DRAWS,
                    test_sequences: int = LM_TEST_SEQUENCES, test_frames: int = LM_TEST_FRAMES,
                    pool_sequences: int = LM_POOL_SEQUENCES,
                    pool_frames: int = LM_POOL_FRAMES) -> dict:
    """One LMS or MIMO case: bags, the node's monitor over the test bags, adaptation.
    LMS baseline: ``entropy`` (``entropy_baseline``), else the same pair fitted on the
    case's whole pool; MIMO baseline: the merged score as the confidence."""
    from lidar_quality_core.meta_model import predict
    from lidar_quality_training.adapt import evaluate

    t0 = time.monotonic()
    d = tmp / method / case.replace(" ", "_").replace(".", "").replace("(", "").replace(
        ")", "").replace("=", "")
    test_bags = write_bags(method, case, [SEED0 + q for q in range(test_sequences)],
                           test_frames, columns, d / "test")
    pool_bags = write_bags(method, case, [SEED0 + 500 + q for q in range(pool_sequences)],
                           pool_frames, columns, d / "pool")
    params = node_params(method, case, columns)
    row = {"case": case, "params": params, **node_monitor(method, test_bags, params)}
    if method == "lms":
        test, models, quantities, _ = lms_data(test_bags, params)
        pool, _, _, pool_ds = lms_data(pool_bags, params)
        fit_on = entropy
        if fit_on is None:
            from lidar_quality_training.lms.train import feature_set, fit_pair

            names = feature_set(pool_ds.names, "entropy")
            clf, reg = fit_pair(pool_ds, names)
            fit_on = {"names": names, "classifier": clf, "regressor": reg,
                      "fitted_on": "the case's pool"}
        cols = [list(test.feature_names).index(n) for n in fit_on["names"]]
        m = evaluate(test.tp, test.iou,
                     predict(fit_on["classifier"], "classification", test.X[:, cols]),
                     predict(fit_on["regressor"], "regression", test.X[:, cols]))
        baseline = ("entropy", {**{k: m.get(k) for k in ("auroc", "ece", "r2")},
                                "fitted_on": fit_on["fitted_on"]})
        extra = None
    else:
        test, models, quantities, test_ds = mimo_data(test_bags)
        pool, _, _, pool_ds = mimo_data(pool_bags)
        from lidar_quality_training.mimo.adapt import profile_extra

        m = evaluate(test.tp, test.iou, test_ds.m_score, None)
        baseline = ("merged score", {k: m.get(k) for k in ("auroc", "ece", "r2")})
        extra = lambda rows: profile_extra(pool_ds, rows)  # noqa: E731 - bound to the pool
    row["adaptation"] = adapt_rows(pool, test, models, baseline, n_frames=n_frames,
                                   draws=draws, test_quantities=quantities,
                                   profile_extra=extra)
    row["seconds"] = round(time.monotonic() - t0, 1)
    return row


# --------------------------------------------------------------------------- report
def _f(v, digits=3) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else \
        f"{v:.{digits}f}"


def acceptance(rows: list[dict], n: int = 20) -> list[dict]:
    """Per shifted case with ``n`` frames: adapted AUROC >= the score's and ECE <= the
    score's, on the mean over draws and on every draw."""
    res = []
    for r in rows:
        a = r.get("adaptation") or {}
        if r["case"] == "in domain" or n not in a.get("adapted", {}):
            continue
        s = a["detector score"]
        runs = [d for d in a["adapted"][n]["draws"] if d.get("auroc") is not None]
        m = a["adapted"][n]["mean"]
        ok_mean = (m["auroc"] is not None and m["auroc"] >= s["auroc"]
                   and m["ece"] <= s["ece"])
        ok_all = all(d["auroc"] >= s["auroc"] and d["ece"] <= s["ece"] for d in runs)
        res.append({"case": r["case"], "adapted_auroc": m["auroc"], "score_auroc": s["auroc"],
                    "adapted_ece": m["ece"], "score_ece": s["ece"], "met_mean": ok_mean,
                    "met_every_draw": ok_all})
    return res


def report(rows: list[dict], held: dict | None, args, methods: dict | None = None) -> str:
    """The Markdown report: LMD (``rows``, when run), the held-out false alarms, then the
    LMS and MIMO sections (``methods``: ``{"lms": section, "mimo": section}``)."""
    L = ["# Domain report (issue 18's domain-shift benchmark)"]
    if rows:
        L.append("")
        L += _lmd_report(rows, args)
    if held:
        L += ["", f"### Held-out in-domain frames ({held['bags']} `meta_test` bags, every node)",
              "", "| node | frames | scored windows | alarms | false-alarm rate | score p99 |",
              "|---|---|---|---|---|---|"]
        for node, h in held["nodes"].items():
            L.append(f"| {node} | {h['frames']} | {h['scored']} | {h['alarms']} | "
                     f"{100 * h['alarm_rate']:.2f} % | {h['score_p99']} |")
    if rows:
        L += _lmd_adaptation_report(rows, args)
    for name, sec in (methods or {}).items():
        L += _method_report(name, sec, args)
    L += ["", "Not in this benchmark: a second trained detector or segmenter (the score, "
          "head-score and tempered-probability cases stand for another network's calibration); "
          "LMS and MIMO on VLS-128 and with the detectors' scores recalibrated (LMD only); MIMO "
          "with `use_points` (the node's default pair only); real KITTI for LMS and MIMO (no "
          "labelled KITTI segmentation or multi-head results here)."]
    return "\n".join(L) + "\n"


def _lmd_report(rows: list[dict], args) -> list[str]:
    L = [f"LMD with the shipped `{MODE}` models and the node's drift defaults (window 50, WARN "
         f"0.25, ERROR 0.5). Per simulated case: {args.test_sequences} test sequences of "
         f"{args.test_frames} frames (seeds from {SEED0}) and {args.pool_sequences} sequences of "
         f"{args.pool_frames} labelled frames to adapt on (seeds from {SEED0 + 500}); HDL-64 at "
         f"64 x {args.columns}.", "", "## Drift monitor", "",
         "| case | frames | alarm rate | frames to ERROR (per sequence) | max score | "
         "last score | most drifted |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        rate = "-" if r["alarm_rate"] is None else f"{100 * r['alarm_rate']:.1f} %"
        first = ", ".join("never" if f is None else str(f) for f in r["frames_to_error"])
        L.append(f"| {r['case']} | {r['frames']} | {rate} | {first} | "
                 f"{r.get('max_score', '-')} | {r['last_score']} | {r['quantities']} |")
    L += ["", "The monitor scores from the 10th frame (`min_frames`); a frame's level is its "
          "window's (the last 50 frames)."]
    return L


def _lmd_adaptation_report(rows: list[dict], args) -> list[str]:
    L = ["", "## Adaptation (LMD)", "",
          "Test-frame metrics. *adapted n*: `lidar_quality_training.adapt` on n labelled "
          "frames of the case (candidates shipped / recalibrate / continue / fresh, chosen by "
          f"cross validation over the n frames; mean of {args.draws} random draws below "
          f"{args.pool_sequences * args.pool_frames} frames); *only n*: an XGBoost pair trained on the "
          "n frames alone; *detector score*: the score as the confidence. *its monitor*: the "
          "drift monitor of the adapted pair (first draw; profile of its n frames) over the "
          "test frames.", "",
          "| case | model | AUROC | ECE | R² | chosen (confidence / IoU, per draw) |",
          "|---|---|---|---|---|---|"]
    for r in rows:
        a = r.get("adaptation")
        if not a:
            continue
        L.append(f"| {r['case']} | detector score | {_f(a['detector score']['auroc'])} | "
                 f"{_f(a['detector score']['ece'])} | - | |")
        L.append(f"| | shipped | {_f(a['shipped']['auroc'])} | {_f(a['shipped']['ece'])} | "
                 f"{_f(a['shipped']['r2'])} | |")
        for n, e in a["adapted"].items():
            ch = "; ".join(f"{d['chosen']['classification']} / {d['chosen']['regression']}"
                           for d in e["draws"] if d.get("chosen"))
            m = e["mean"]
            mon = next((d["monitor"] for d in e["draws"] if d.get("monitor")), None)
            if mon:
                ch += f" · its monitor: {mon['alarms']} alarms / {mon['scored']} frames"
            L.append(f"| | adapted {n} | {_f(m['auroc'])} | {_f(m['ece'])} | {_f(m['r2'])} "
                     f"| {ch} |")
            o = a["frames only"].get(n)
            if o:
                mo = o["mean"]
                L.append(f"| | only {n} | {_f(mo['auroc'])} | {_f(mo['ece'])} | "
                         f"{_f(mo['r2'])} | |")
        if a.get("scheme"):
            L.append(f"| | ({a['scheme']}) | | | | |")
    acc = acceptance(rows)
    if acc:
        L += ["", "## Acceptance: 20 labelled frames, every shift", "",
              "| case | adapted AUROC | score AUROC | adapted ECE | score ECE | met (mean) | "
              "met (every draw) |", "|---|---|---|---|---|---|---|"]
        for a in acc:
            L.append(f"| {a['case']} | {_f(a['adapted_auroc'])} | {_f(a['score_auroc'])} | "
                     f"{_f(a['adapted_ece'])} | {_f(a['score_ece'])} | "
                     f"{'yes' if a['met_mean'] else 'NO'} | "
                     f"{'yes' if a['met_every_draw'] else 'NO'} |")
    return L


_METHOD_TEXT = {
    "lms": ("LMS (LidarMetaSeg)", "the reference segmenter's probabilities (uint8 fields, as "
            "the perception bags) into `lms_node` with the shipped models",
            "*entropy*: the paper's \"Entropy\" baseline as `lms-eval` computes it, an XGBoost "
            "pair on `mean_E` alone fitted on {fitted_on}", "segments",
            "Node parameters: `separate_probabilities: true` (rows from /lidar/points' ring, as "
            "the shipped models were trained), `sensor: HDL-32E` for the HDL-32E (the preset's "
            "beams and width, 2250 columns; what a user sets for that sensor; the models were "
            "trained on a 64 x 2048 image, the node warns), `width` = the sensor's columns when "
            "not 2048, `intensity_scale: unit` for the byte intensities. *probabilities "
            "tempered*: every point's probabilities through softmax(log p / T), renormalised "
            "(another segmenter's calibration)."),
    "mimo": ("MIMO (LiDAR-MIMO)", "the reference 2-head detector into `mimo_node` (node "
             "defaults: `use_points` off, the cluster-statistics pair)",
             "*merged score*: the merged detection's score as the confidence", "merged "
             "detections", "*head scores x 0.6*: every class score of every head's detections "
             "scaled (another detector's calibration); the node's parameters are its defaults "
             "in every case (MIMO has no sensor geometry)."),
}


def _method_report(name: str, sec: dict, args) -> list[str]:
    title, what, base, unit, notes = _METHOD_TEXT[name]
    z = sec["sizes"]
    fitted = next((r["adaptation"]["baseline"].get("fitted_on") for r in sec["cases"]
                   if r["adaptation"]["baseline"].get("fitted_on")), "-")
    L = ["", f"## {title}", "",
         f"Simulated frames (lidar_sim, HDL-64 at 64 x {args.columns} unless the case says "
         f"otherwise) through {what} and the node's drift defaults. Per case: "
         f"{z['test_sequences']} test sequences of {z['test_frames']} frames (seeds from "
         f"{SEED0}) and {z['pool_sequences']} sequences of {z['pool_frames']} labelled frames "
         f"to adapt on (seeds from {SEED0 + 500}): fewer than LMD's, to keep the run short. "
         + notes, "", "### Drift monitor", "",
         "| case | frames | alarm rate | frames to ERROR (per sequence) | max score | "
         "last score | most drifted |", "|---|---|---|---|---|---|---|"]
    for r in sec["cases"]:
        first = ", ".join("never" if f is None else str(f) for f in r["frames_to_error"])
        L.append(f"| {r['case']} | {r['frames']} | {100 * r['alarm_rate']:.1f} % | {first} | "
                 f"{r.get('max_score') if r.get('max_score') is not None else '-'} | "
                 f"{r['last_score']} | {r['quantities']} |")
    L += ["", "### Adaptation", "",
          f"Metrics on the test {unit}; *adapted n* / *only n* as for LMD (mean of {args.draws} draws "
          f"below {z['pool_sequences'] * z['pool_frames']} frames); "
          + base.format(fitted_on=fitted) + ".", "",
          "| case | model | AUROC | ECE | R² | chosen (confidence / IoU, per draw) |",
          "|---|---|---|---|---|---|"]
    for r in sec["cases"]:
        a = r["adaptation"]
        b = a["baseline"]
        L.append(f"| {r['case']} | {a['baseline_name']} | {_f(b['auroc'])} | {_f(b['ece'])} | "
                 f"{_f(b.get('r2'))} | |")
        L.append(f"| | shipped | {_f(a['shipped']['auroc'])} | {_f(a['shipped']['ece'])} | "
                 f"{_f(a['shipped']['r2'])} | |")
        for n, e in a["adapted"].items():
            ch = "; ".join(f"{d['chosen']['classification']} / {d['chosen']['regression']}"
                           for d in e["draws"] if d.get("chosen"))
            mon = next((d["monitor"] for d in e["draws"] if d.get("monitor")), None)
            if mon:
                ch += f" · its monitor: {mon['alarms']} alarms / {mon['scored']} frames"
            m = e["mean"]
            L.append(f"| | adapted {n} | {_f(m['auroc'])} | {_f(m['ece'])} | {_f(m['r2'])} "
                     f"| {ch} |")
            o = a["frames only"].get(n)
            if o:
                mo = o["mean"]
                L.append(f"| | only {n} | {_f(mo['auroc'])} | {_f(mo['ece'])} | "
                         f"{_f(mo['r2'])} | |")
    return L


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/domain"))
    ap.add_argument("--test-sequences", type=int, default=TEST_SEQUENCES)
    ap.add_argument("--test-frames", type=int, default=TEST_FRAMES)
    ap.add_argument("--pool-sequences", type=int, default=POOL_SEQUENCES)
    ap.add_argument("--pool-frames", type=int, default=POOL_FRAMES)
    ap.add_argument("--n-frames", default=",".join(map(str, N_FRAMES)),
                    help="labelled frame counts to adapt with (comma-separated)")
    ap.add_argument("--draws", type=int, default=DRAWS)
    ap.add_argument("--columns", type=int, default=2048)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated subset")
    ap.add_argument("--kitti", type=Path, default=Path(os.environ.get(
        "LQ_REALDATA_KITTI", Path(__file__).resolve().parents[3] / "shared" / "realdata_kitti")))
    ap.add_argument("--held-out", default="data/perception/meta_test",
                    help="held-out in-domain bags for the false-alarm rate ('' : skip)")
    ap.add_argument("--methods", default=",".join(METHODS),
                    help="comma-separated subset of lmd, lms, mimo (LMD includes real KITTI)")
    ap.add_argument("--lms-cases", default=",".join(LMS_CASES), help="comma-separated subset")
    ap.add_argument("--mimo-cases", default=",".join(MIMO_CASES), help="comma-separated subset")
    ap.add_argument("--lm-test-sequences", type=int, default=LM_TEST_SEQUENCES,
                    help="LMS / MIMO: test sequences per case")
    ap.add_argument("--lm-test-frames", type=int, default=LM_TEST_FRAMES)
    ap.add_argument("--lm-pool-sequences", type=int, default=LM_POOL_SEQUENCES)
    ap.add_argument("--lm-pool-frames", type=int, default=LM_POOL_FRAMES)
    ap.add_argument("--lm-n-frames", default=",".join(map(str, LM_N_FRAMES)),
                    help="LMS / MIMO: labelled frame counts to adapt with")
    ap.add_argument("--lms-train", default=LMS_TRAIN,
                    help="in-domain training bags of the LMS entropy baseline ('': fit it on "
                         "each case's pool)")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in METHODS:
            ap.error(f"unknown method {m!r} (known: {', '.join(METHODS)})")
    known = {"lms": LMS_CASES, "mimo": MIMO_CASES}
    method_cases = {}
    for m in ("lms", "mimo"):
        cases = [c.strip() for c in getattr(args, f"{m}_cases").split(",") if c.strip()]
        bad = [c for c in cases if c not in known[m]]
        if bad:
            ap.error(f"unknown {m} case {bad[0]!r} (known: {', '.join(known[m])})")
        if m in methods:
            method_cases[m] = cases
    t_start = time.monotonic()
    rows = []
    for case in [c.strip() for c in args.cases.split(",") if c.strip()] \
            if "lmd" in methods else []:
        if case not in CASES:
            ap.error(f"unknown case {case!r} (known: {', '.join(CASES)})")
        rows.append(run_case(case, columns=args.columns, draws=args.draws,
                             test_sequences=args.test_sequences, test_frames=args.test_frames,
                             pool_sequences=args.pool_sequences, pool_frames=args.pool_frames,
                             n_frames=tuple(int(v) for v in args.n_frames.split(","))))
        a = rows[-1]["adaptation"]
        print(f"domain_report: {case}: alarm rate {rows[-1]['alarm_rate']}, to ERROR "
              f"{rows[-1]['frames_to_error']}; AUROC score {_f(a['detector score']['auroc'])} "
              f"shipped {_f(a['shipped']['auroc'])} adapted "
              + ", ".join(f"{n}: {_f(e['mean']['auroc'])}" for n, e in a["adapted"].items())
              + f" ({rows[-1]['seconds']} s)", flush=True)
    kitti = real_kitti(args.kitti) if "lmd" in methods else False
    if kitti is None:
        print(f"domain_report: real KITTI scans not found at {args.kitti}: left out", flush=True)
    elif kitti:
        rows.append(kitti)
    sections = run_methods(method_cases, args)
    held = None
    if args.held_out and Path(args.held_out).is_dir():
        from lidar_quality_ros.perception_bag import resolve_bags

        held = held_out_alarms(resolve_bags([Path(args.held_out)]))
    else:
        print(f"domain_report: no held-out bags at {args.held_out} (make meta-data): the "
              "false-alarm rate is left out", file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    seconds = round(time.monotonic() - t_start, 1)
    (args.out / "summary.json").write_text(json.dumps(
        {"cases": rows, "held_out": held, "acceptance": acceptance(rows), **sections,
         "methods": methods, "seconds": seconds}, indent=1, default=str) + "\n")
    (args.out / "report.md").write_text(report(rows, held, args, sections))
    print(f"domain_report: wrote {args.out / 'report.md'} ({seconds} s)")
    return 0


def run_methods(method_cases: dict, args) -> dict:
    """The LMS / MIMO sections: ``{method: {"sizes", "cases"}}``, bags in a temporary
    directory removed afterwards."""
    import tempfile

    sizes = {"test_sequences": args.lm_test_sequences, "test_frames": args.lm_test_frames,
             "pool_sequences": args.lm_pool_sequences, "pool_frames": args.lm_pool_frames,
             "n_frames": [int(v) for v in args.lm_n_frames.split(",")], "draws": args.draws,
             "columns": args.columns}
    out = {}
    with tempfile.TemporaryDirectory(prefix="domain_report_") as tmp:
        for method, cases in method_cases.items():
            entropy = None
            if method == "lms" and cases:
                entropy = entropy_baseline(Path(args.lms_train) if args.lms_train else None)
                if entropy is None:
                    print(f"domain_report: no LMS training bags at {args.lms_train!r}: the "
                          "entropy baseline is fitted on each case's pool", file=sys.stderr)
            res = []
            for case in cases:
                r = run_method_case(method, case, columns=args.columns, tmp=Path(tmp),
                                    entropy=entropy, draws=args.draws,
                                    n_frames=tuple(sizes["n_frames"]),
                                    **{k: sizes[k] for k in ("test_sequences", "test_frames",
                                                             "pool_sequences", "pool_frames")})
                a = r["adaptation"]
                print(f"domain_report: {method} {case}: alarm rate {r['alarm_rate']}, to ERROR "
                      f"{r['frames_to_error']}; AUROC {a['baseline_name']} "
                      f"{_f(a['baseline']['auroc'])} shipped {_f(a['shipped']['auroc'])} "
                      "adapted " + ", ".join(f"{n}: {_f(e['mean']['auroc'])}"
                                             for n, e in a["adapted"].items())
                      + f" ({r['seconds']} s)", flush=True)
                res.append(r)
            out[method] = {"sizes": sizes, "cases": res}
    return out


if __name__ == "__main__":
    raise SystemExit(main())
