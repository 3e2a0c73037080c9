"""Fleet figures (issue 20): ``process_bags`` throughput on Dask LocalClusters of this
machine, and the per-task costs that bound it on a larger cluster.

``BAGS`` simulated perception bags of ``FRAMES`` HDL-64 frames (64 x ``COLUMNS``),
perceived by the reference perception (the multi-head detector: all three nodes run),
are generated once into ``out/bench/fleet/bags``. Figures (item kind ``"figures"``):

* ``fleet.frames_per_s_w1`` / ``_w2``: frames (clouds) per second of wall time of one
  ``process_bags`` run, all three nodes, output bags and result tables written, on a
  LocalCluster of 1 / 2 worker processes (cluster start-up not counted; task start-up,
  the models' loading in the worker included);
* ``fleet.sequential_frames_per_s``: the same bags in this process, one after another
  (``process.process_one``, no Dask): the single-worker figure without the scheduler;
* ``fleet.task_overhead_ms``: the scheduler's cost per task, the mean round trip of
  ``OVERHEAD_TASKS`` empty tasks on the two-worker cluster;
* ``fleet.task_setup_ms``: a task's own set-up in a warm worker (parameters, models
  loaded and checked: ``build_runners``);
* ``fleet.frame_mb``: bytes read per frame (input bag size / frames), the storage side.
"""
from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "out" / "bench" / "fleet"
BAGS, FRAMES, COLUMNS = 8, 10, 1024
OVERHEAD_TASKS = 200


def _bags() -> Path:
    """The bench's bags (generated once; ``.done`` marks a complete set)."""
    from lidar_sim import classes
    from lidar_sim.bag import SimBagWriter
    from lidar_sim.frames import sequence_frames
    from lidar_sim.sensor import hdl64
    from reference_perception.cli import Perception, process_bag

    bags = OUT / f"bags_{BAGS}x{FRAMES}x{COLUMNS}"
    if (bags / ".done").exists():
        return bags
    shutil.rmtree(bags, ignore_errors=True)
    sim = OUT / "sim"
    perception = Perception(heads=2)
    for s in range(BAGS):
        shutil.rmtree(sim, ignore_errors=True)
        with SimBagWriter(sim) as w:
            for f in sequence_frames(2000 + s, FRAMES, cfg=hdl64(columns=COLUMNS)):
                w.write_frame(f.stamp_ns, xyz=f.xyz, intensity=f.intensity, ring=f.ring,
                              label=f.semantic, instance=f.instance, gt_boxes=f.gt_boxes,
                              gt_class_names=[classes.class_name(c) for c in f.gt_class],
                              gt_ids=[str(k) for k in f.gt_instance])
        process_bag(sim, bags / f"drive_{s:02d}", perception, quiet=True)
    shutil.rmtree(sim, ignore_errors=True)
    (bags / ".done").touch()
    return bags


def _cluster(n: int):
    from distributed import Client
    from lidar_quality_tools.fleet import local_cluster

    cluster = local_cluster(n)
    return cluster, Client(cluster)


def _fleet_run(bags: Path, n_workers: int) -> float:
    from lidar_quality_tools.fleet import process_bags

    out = OUT / f"run_w{n_workers}"
    shutil.rmtree(out, ignore_errors=True)
    cluster, client = _cluster(n_workers)
    try:
        client.wait_for_workers(n_workers)
        t0 = time.perf_counter()
        m = process_bags([bags], out, client=client, progress=False)
        wall = time.perf_counter() - t0
    finally:
        client.close()
        cluster.close()
    done = [r for r in m["tasks"] if r["status"] == "done"]
    if len(done) != BAGS:
        raise RuntimeError(f"fleet bench: {BAGS - len(done)} task(s) failed: {m['tasks']}")
    return sum(r["frames"] for r in done) / wall


def _sequential(bags: Path) -> float:
    from lidar_quality_tools.process import build_runners, process_one

    out = OUT / "run_seq"
    shutil.rmtree(out, ignore_errors=True)
    frames, t0 = 0, time.perf_counter()
    for b in sorted(p for p in bags.iterdir() if p.is_dir()):
        s = process_one(b, out / "bags" / b.name, build_runners(), results=out / "results")
        frames += s["frames"]
    return frames / (time.perf_counter() - t0)


def _overhead_ms() -> float:
    cluster, client = _cluster(2)
    try:
        client.wait_for_workers(2)
        client.gather(client.map(abs, range(20)))        # connections warm
        t0 = time.perf_counter()
        client.gather(client.map(abs, range(OVERHEAD_TASKS), pure=False))
        return (time.perf_counter() - t0) / OVERHEAD_TASKS * 1e3
    finally:
        client.close()
        cluster.close()


def _setup_ms() -> float:
    from lidar_quality_tools.process import build_runners

    build_runners()                                       # imports, caches
    t = []
    for _ in range(5):
        t0 = time.perf_counter()
        build_runners()
        t.append(time.perf_counter() - t0)
    return sorted(t)[len(t) // 2] * 1e3


def experiment() -> dict:
    bags = _bags()
    frame_bytes = sum(f.stat().st_size for f in bags.rglob("*.mcap")) / (BAGS * FRAMES)
    figs = {"fleet.frame_mb": round(frame_bytes / 1e6, 3),
            "fleet.task_setup_ms": round(_setup_ms(), 1),
            "fleet.task_overhead_ms": round(_overhead_ms(), 2),
            "fleet.sequential_frames_per_s": round(_sequential(bags), 2)}
    for n in (1, 2):
        figs[f"fleet.frames_per_s_w{n}"] = round(_fleet_run(bags, n), 2)
    return figs


def figures():
    yield "fleet", experiment, "figures"


if __name__ == "__main__":
    for k, v in experiment().items():
        print(f"{k:40s} {v}")
    sys.exit(0)
