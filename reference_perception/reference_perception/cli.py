"""``reference-perception``: run the reference perception offline, without DDS.

    reference-perception bag --in data/sim/bags/seq_00 --out data/perception/seq_00
    reference-perception split --split demo --out data/perception/demo
    reference-perception kitti --root data/sim/kitti --out out/kitti_results
    reference-perception semantickitti --root data/sim/semantickitti --out out/sk_pred

``bag`` copies every message of the input bag and adds, stamped like the cloud they come
from (topic prefix ``--prefix``, default ``/perception``):

- ``detections`` / ``proposals``: post-NMS / pre-NMS Detection3DArray of the detector;
- ``segmentation``: PointCloud2, the cloud's points with one probability field per class
  (uint8, round(p * 255); ``--probabilities float32`` for float32 fields);
- ``head_k`` and ``head_k/variance`` (k < ``--heads``): the multi-head detector's heads.

``--topic KEY=TOPIC`` (repeatable; the keys of ``perception_bag.TOPIC_KEYS``) names the
input cloud topic (``points``, default ``/lidar/points``) and any output topic (e.g.
``detections=/perception/object_recognition/objects``); the input may be any rosbag2 that
``ros2 bag`` reads, its messages of types unknown here copied as bytes (one warning per
type). The output bag is written beside ``--out`` and moved into place when complete (a
failed run leaves none; ``--overwrite`` replaces an existing one).

This "perception bag" is the standard input of the demo and of the node tests. ``split``
simulates a data split (``lidar_sim.splits``) sequence by sequence into perception bags.
``kitti`` writes KITTI result files (label format plus a score column) for a KITTI object
dataset's velodyne scans, each in the camera frame of the scan's own ``calib/<id>.txt``
(a scan without one: the simulator's calibration, with a warning), and records the
calibration used in ``<out>/calib/<id>.txt`` (``bag --kitti-results``: the simulator's
calibration, recorded the same way); ``semantickitti`` writes ``predictions/*.label`` and
``probabilities/*.npy`` (float32 (N, classes), class order of ``lidar_sim.classes``).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .messages import QUANTIZE_DEFAULT

PROB_TOPIC, DET_TOPIC, PROP_TOPIC = "segmentation", "detections", "proposals"
POINTS_TOPIC = "/lidar/points"


class Perception:
    """The reference models, loaded once; ``run`` gives every output of one cloud."""

    def __init__(self, *, detector: bool = True, segmenter: bool = True, heads: int = 2,
                 model_dir: Path | None = None):
        from .detector import ReferenceDetector
        from .segmenter import DEFAULT_MODEL_PATH, ReferenceSegmenter

        self.detector = ReferenceDetector(model_dir) if detector else None
        seg_path = (Path(model_dir) / DEFAULT_MODEL_PATH.name) if model_dir else DEFAULT_MODEL_PATH
        self.segmenter = ReferenceSegmenter.load(seg_path) if segmenter else None
        self.multihead = None
        if heads:
            from .multihead import MultiHeadDetector

            self.multihead = MultiHeadDetector(model_dir, num_heads=heads)

    def run(self, xyz, intensity, ring=None) -> dict:
        from .cloud_input import finite_points

        out = {}
        x, i, r = finite_points(xyz, intensity, ring)
        props = None
        if self.detector is not None:
            props = self.detector.proposals(x, i, r)
            out["detector"] = self.detector.detect_proposals(props)
        if self.multihead is not None:
            out["heads"] = (self.multihead.detect_proposals(props) if props is not None
                            else self.multihead.detect(x, i, r))
        if self.segmenter is not None:
            out["probs"] = self.segmenter.predict_proba(xyz, intensity, ring)
        return out


def _messages(header, cloud, result: dict, quantize: bool):
    """(relative topic, msgtype, message) of one cloud's outputs."""
    from lidar_sim.classes import CLASS_NAMES

    from .detector import PROB_NAMES
    from .messages import detector_messages, head_messages, probability_cloud

    msgs = []
    if "detector" in result:
        dets, props = detector_messages(header, result["detector"], PROB_NAMES[1:])
        msgs += [(DET_TOPIC, "vision_msgs/msg/Detection3DArray", dets),
                 (PROP_TOPIC, "vision_msgs/msg/Detection3DArray", props)]
    if "heads" in result:
        for k, (dets, var) in enumerate(head_messages(header, result["heads"], PROB_NAMES[1:])):
            msgs += [(f"head_{k}", "vision_msgs/msg/Detection3DArray", dets),
                     (f"head_{k}/variance", "lidar_quality_msgs/msg/BoxVarianceArray", var)]
    if "probs" in result:
        msgs.append((PROB_TOPIC, "sensor_msgs/msg/PointCloud2",
                     probability_cloud(header, cloud.xyz, cloud.intensity, result["probs"],
                                       CLASS_NAMES, quantize=quantize)))
    return msgs


def _write_kitti(directory: Path, frame_id: str, det, calib) -> int:
    """KITTI result file (and its calibration) of the post-NMS boxes of a DetectorOutput
    or a HeadOutput."""
    from lidar_sim import classes, kitti

    boxes, labels, scores = det.boxes[det.keep], det.labels[det.keep], det.scores[det.keep]
    types = [classes.kitti_type(int(c)) for c in labels]
    return kitti.write_results(directory, frame_id, boxes, types, scores, calib=calib)


def process_bag(src: Path, dst: Path, perception: Perception, *, points_topic: str | None = None,
                prefix: str = "/perception", topics: dict | None = None, storage: str = "mcap",
                quantize: bool = QUANTIZE_DEFAULT, kitti_results: Path | None = None, quiet: bool = False,
                overwrite: bool = False) -> dict:
    """Copy ``src`` into ``dst`` adding the perception outputs of every cloud.

    ``topics``: key -> topic (``--topic``) for the input cloud (``points``) and the outputs
    (``detections``, ``head_0/variance`` ...); outputs not named go under ``prefix``.
    ``dst`` appears only once complete (``bag_io.atomic_output``); an existing one is
    replaced with ``overwrite``, else ``FileExistsError``.
    """
    from lidar_quality_ros.bag_io import BagWriter, UnknownTypes, atomic_output, bag_info, read_bag
    from lidar_quality_ros.perception_bag import parse_topic_options, topic_of

    from .cloud_input import read_cloud

    topics = parse_topic_options([f"{k}={v}" for k, v in (topics or {}).items()])
    if points_topic is not None:
        if topics.get("points", points_topic) != points_topic:
            raise ValueError(f"--points-topic {points_topic} and --topic points="
                             f"{topics['points']} disagree")
        topics["points"] = points_topic
    points_topic = topic_of("points", topics)

    def out_topic(rel: str) -> str:
        return topics.get(rel) or f"{prefix.rstrip('/')}/{rel}"

    info = bag_info(src)
    if points_topic not in info.topics:
        raise SystemExit(f"{src}: no topic {points_topic} (topics: {sorted(info.topics)}; "
                         "name it with --topic points=TOPIC)")
    unknown = UnknownTypes(lambda t: print(f"{src}: warning: {t}", file=sys.stderr),
                           "copied unchanged")
    unknown.check_all({t: i.msgtype for t, i in info.topics.items()})
    if points_topic in {t for ts in unknown.seen.values() for t in ts}:
        raise SystemExit(f"{src}: {points_topic} has type {info.topics[points_topic].msgtype}, "
                         "not a PointCloud2: choose the cloud with --topic points=TOPIC")
    if kitti_results:
        Path(kitti_results).mkdir(parents=True, exist_ok=True)
    n, t_model, t0 = 0, 0.0, time.monotonic()
    with atomic_output(dst, overwrite=overwrite) as tmp, BagWriter(tmp, storage=storage) as w:
        for m in read_bag(src):
            t = info.topics[m.topic]
            w.write(m.topic, m.msgtype, m.stamp_ns, m.raw, qos=t.qos, source=t)
            if m.topic != points_topic:
                continue
            try:
                msg = m.decode()
                cloud = read_cloud(msg)
            except Exception as exc:  # noqa: BLE001 - rclpy and the cloud reader raise several
                raise SystemExit(f"{src}: the {points_topic} message logged at {m.stamp_ns} "
                                 f"cannot be read ({type(exc).__name__}: {exc}): {dst} not "
                                 "written") from None
            t1 = time.perf_counter()
            result = perception.run(cloud.xyz, cloud.intensity, cloud.ring)
            t_model += time.perf_counter() - t1
            for rel, msgtype, out in _messages(msg.header, cloud, result, quantize):
                w.write(out_topic(rel), msgtype, m.stamp_ns, out)
            if kitti_results and "detector" in result:
                from lidar_sim.kitti import SIM_CALIB  # a bag has no camera

                _write_kitti(Path(kitti_results), f"{n:06d}", result["detector"], SIM_CALIB)
            n += 1
            if not quiet:
                sys.stderr.write(f"\r{dst.name}: {n} clouds ({n / (time.monotonic() - t0):.1f}/s)")
    if not quiet:
        sys.stderr.write("\n")
    return {"clouds": n, "model_ms_per_cloud": 1e3 * t_model / max(n, 1),
            "wall_s": time.monotonic() - t0,
            "unknown_types": {ty: list(ts) for ty, ts in unknown.seen.items()}}


def process_split(split: str, out: Path, perception: Perception, *, storage: str = "mcap",
                  quantize: bool = QUANTIZE_DEFAULT, sequences=None, quiet: bool = False) -> list[Path]:
    """Simulate a split's sequences and write one perception bag per sequence."""
    from lidar_sim import classes
    from lidar_sim.bag import SimBagWriter
    from lidar_sim.frames import split_frames
    from lidar_sim.splits import split as get_split

    sp = get_split(split)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for s in (range(sp.sequences) if sequences is None else sequences):
        dst = out / f"seq_{s:02d}"
        if dst.exists():
            raise SystemExit(f"{dst} exists: remove it or choose another --out")
        with tempfile.TemporaryDirectory(dir=out) as tmp:
            sim = Path(tmp) / "sim"
            with SimBagWriter(sim, storage=storage) as bag:
                for f in split_frames(sp, sequences=[s]):
                    bag.write_frame(f.stamp_ns, xyz=f.xyz, intensity=f.intensity, ring=f.ring,
                                    label=f.semantic, instance=f.instance, gt_boxes=f.gt_boxes,
                                    gt_class_names=[classes.class_name(c) for c in f.gt_class],
                                    gt_ids=[str(k) for k in f.gt_instance])
            process_bag(sim, dst, perception, storage=storage, quantize=quantize, quiet=quiet)
        written.append(dst)
    return written


def _read_bin(path: Path):
    scan = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    return np.ascontiguousarray(scan[:, :3]), np.ascontiguousarray(scan[:, 3])


def _frame_calib(base: Path, frame_id: str, warned: list):
    """The scan's own calibration; the simulator's (warned once per run) without one."""
    from lidar_sim.kitti import SIM_CALIB, Calibration, calib_path

    path = calib_path(base, frame_id)
    if path.exists():
        try:
            return Calibration.from_file(path)
        except ValueError as exc:
            raise SystemExit(f"unusable calibration: {exc}") from None
    if not warned:
        sys.stderr.write(f"warning: {path} missing: writing results in the simulator's camera "
                         f"frame (lidar_sim.kitti.SIM_CALIB), recorded in the output's "
                         f"calib/<id>.txt; scans with their own calib file use theirs\n")
        warned.append(path)
    return SIM_CALIB


def process_kitti(root: Path, out: Path, perception: Perception, *, split: str = "training",
                  quiet: bool = False) -> int:
    """KITTI result files for ``root/<split>/velodyne/*.bin`` (heads: ``out/head_k/``),
    each with the calibration it was written with in ``calib/<id>.txt`` beside it."""
    base = Path(root) / split
    scans = sorted((base / "velodyne").glob("*.bin"))
    if not scans:
        raise SystemExit(f"no scans in {base / 'velodyne'}")
    out.mkdir(parents=True, exist_ok=True)
    warned: list = []
    for n, path in enumerate(scans, 1):
        calib = _frame_calib(base, path.stem, warned)
        xyz, inten = _read_bin(path)
        res = perception.run(xyz, inten)
        if "detector" in res:
            _write_kitti(out, path.stem, res["detector"], calib)
        for k, head in enumerate(res.get("heads", [])):
            d = out / f"head_{k}"
            _write_kitti(d, path.stem, head, calib)
            np.savez_compressed(d / f"{path.stem}.npz", boxes=head.boxes[head.keep],
                                class_probs=head.class_probs[head.keep],
                                variances=head.variances[head.keep])
        if not quiet:
            sys.stderr.write(f"\r{n}/{len(scans)} scans")
    if not quiet:
        sys.stderr.write("\n")
    return len(scans)


def process_semantickitti(root: Path, out: Path, perception: Perception, *, sequences=None,
                          quiet: bool = False) -> int:
    """SemanticKITTI predictions and probabilities for ``root/sequences/NN/velodyne``."""
    from lidar_sim.classes import to_semantickitti
    from lidar_sim.semantickitti import encode_labels

    seqs = sorted(p for p in (Path(root) / "sequences").iterdir() if p.is_dir())
    if sequences is not None:
        seqs = [p for p in seqs if int(p.name) in set(sequences)]
    n = 0
    for seq in seqs:
        pred = out / "sequences" / seq.name / "predictions"
        prob = out / "sequences" / seq.name / "probabilities"
        pred.mkdir(parents=True, exist_ok=True)
        prob.mkdir(parents=True, exist_ok=True)
        for path in sorted((seq / "velodyne").glob("*.bin")):
            xyz, inten = _read_bin(path)
            p = perception.run(xyz, inten)["probs"].astype(np.float32)
            labels = encode_labels(to_semantickitti(p.argmax(axis=1)), np.zeros(len(p), np.uint32))
            (pred / f"{path.stem}.label").write_bytes(labels.astype("<u4").tobytes())
            np.save(prob / f"{path.stem}.npy", p)
            n += 1
            if not quiet:
                sys.stderr.write(f"\r{seq.name}: {n} scans")
    if not quiet:
        sys.stderr.write("\n")
    return n


def main(argv=None) -> int:
    from lidar_quality_ros.perception_bag import add_topic_option

    ap = argparse.ArgumentParser(prog="reference-perception", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)

    def add_probability_option(p):
        p.add_argument("--probabilities", choices=("uint8", "float32"),
                       default="uint8" if QUANTIZE_DEFAULT else "float32",
                       help="type of the segmentation's probability fields (default uint8: "
                       "round(p * 255), a quarter of the bytes of float32; its effect on the "
                       "LMS estimates: README 'Benchmarks')")

    def common(p, heads=True):
        p.add_argument("--models", type=Path, default=None, help="model directory (default: shipped)")
        p.add_argument("--quiet", action="store_true")
        if heads:
            p.add_argument("--heads", type=int, default=2, help="multi-head heads (0: none)")
            p.add_argument("--no-detector", action="store_true")
            p.add_argument("--no-segmenter", action="store_true")

    p = sub.add_parser("bag", help="add the perception outputs to a bag")
    p.add_argument("--in", dest="src", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--points-topic", default=None,
                   help=f"input cloud topic (default {POINTS_TOPIC}; = --topic points=TOPIC)")
    p.add_argument("--prefix", default="/perception",
                   help="namespace of the output topics not named by --topic")
    add_topic_option(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out bag")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    add_probability_option(p)
    p.add_argument("--kitti-results", type=Path, default=None)
    common(p)
    p = sub.add_parser("split", help="simulate a data split into perception bags")
    p.add_argument("--split", required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--sequences", type=int, nargs="*", default=None)
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    add_probability_option(p)
    common(p)
    p = sub.add_parser("kitti", help="KITTI result files of a KITTI object dataset")
    p.add_argument("--root", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--split", default="training")
    common(p)
    p = sub.add_parser("semantickitti", help="predictions of a SemanticKITTI dataset")
    p.add_argument("--root", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--sequences", type=int, nargs="*", default=None)
    common(p, heads=False)
    a = ap.parse_args(argv)
    if a.cmd == "bag":
        if (a.out.exists() or a.out.is_symlink()) and not a.overwrite:
            ap.error(f"{a.out} exists: pass --overwrite or choose another --out")
        topics = dict(a.topic)
        if a.points_topic and topics.get("points", a.points_topic) != a.points_topic:
            ap.error(f"--points-topic {a.points_topic} and --topic points={topics['points']} "
                     "disagree")

    if a.cmd == "semantickitti":
        perception = Perception(detector=False, segmenter=True, heads=0, model_dir=a.models)
        n = process_semantickitti(a.root, a.out, perception, sequences=a.sequences, quiet=a.quiet)
        print(f"{n} scans -> {a.out}")
        return 0
    perception = Perception(detector=not a.no_detector, segmenter=not a.no_segmenter,
                            heads=a.heads, model_dir=a.models)
    if a.cmd == "bag":
        try:
            stats = process_bag(a.src, a.out, perception, points_topic=a.points_topic,
                                prefix=a.prefix, topics=topics, storage=a.storage,
                                quantize=a.probabilities == "uint8", kitti_results=a.kitti_results,
                                quiet=a.quiet, overwrite=a.overwrite)
        except KeyboardInterrupt:
            print(f"\ninterrupted: {a.out} not written", file=sys.stderr)
            return 130
        print(f"{stats['clouds']} clouds, {stats['model_ms_per_cloud']:.0f} ms of models per cloud "
              f"-> {a.out}")
    elif a.cmd == "split":
        for path in process_split(a.split, a.out, perception, storage=a.storage,
                                  quantize=a.probabilities == "uint8", sequences=a.sequences,
                                  quiet=a.quiet):
            print(path)
    else:
        n = process_kitti(a.root, a.out, perception, split=a.split, quiet=a.quiet)
        print(f"{n} scans -> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
