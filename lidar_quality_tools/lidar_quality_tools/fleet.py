"""``process_bags``: the quality nodes over a fleet of recorded bags, on Dask.

    process_bags --bags IN [--bags IN2 ...] --out OUT [--scheduler tcp://host:8786 |
                 --scheduler-file FILE | --workers N] [--slice-s S] [--no-bags]
                 [--nodes ...] [--param ...] [--topic ...] [--retry-failed]

IN: a bag, a folder of bags, a glob (``'fleet/**/drive_*'``) or a text file listing them
(one per line, ``#`` comments). One task per bag, and per ``--slice-s`` seconds of a
longer bag (frames whose cloud is logged in the slice; default 600 s). Each task runs
``process.process_one`` (the nodes' processors, as ``process_bag``) on a Dask worker; a
slice after the first is preceded by a run without outputs over the frames before it (the
nodes' largest ``drift_window``, :func:`warm_up_window`), so that the drift monitor's
window at the slice's first frame, and with it every output, is the whole bag's:

    OUT/bags/<name>[/part-NNNN]            annotated output bag (one per slice; --no-bags: none)
    OUT/results/<node>/bag=<name>/part-NNNN.parquet   per-detection / per-segment rows
    OUT/tasks/<task>.json                  the task's status, summary and run key
    OUT/manifest.json                      code, models, settings, every task's status

By default a ``distributed.LocalCluster`` on this machine (``local_cluster``: one
single-threaded worker process per core, bound to 127.0.0.1; its dashboard address is
printed); ``--scheduler``
or ``--scheduler-file`` uses an existing cluster, whose workers must have this suite
installed and see the bags and OUT at the same paths.

Resumable and idempotent: a task's outputs are written beside their place and moved in
when complete, then its status file; a task whose status says done with the same run key
(input files' size and mtime, node parameters, topics, slice, model ids, code hash) is
skipped. A failing bag is reported with its error and the run goes on; a worker that dies
has its task retried elsewhere (``distributed``'s ``allowed_failures``), and a task whose
workers keep dying is reported as failed. A rerun does what is left. Exit codes: 0 every
task done; 1 a task failed or a node processed no frame of a bag; 2 bad arguments.
"""
from __future__ import annotations

import argparse
import glob
import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .process import NODES, UsageError, _parse_params, build_runners, nodes_parameters

__all__ = ["Task", "RunSpec", "plan_tasks", "resolve_inputs", "run_task", "process_bags",
           "worker_environ", "local_cluster", "status_table", "warm_up_window", "main"]

DEFAULT_SLICE_S = 600.0
PROGRESS_TOPIC = "lq-frames"     # workers' frame events to the client's progress bar
PROGRESS_EVERY = 10              # frames between two events


# ----------------------------------------------------------------------- planning
@dataclass(frozen=True)
class Task:
    """One unit of work: a bag, or the slice ``[start_ns, stop_ns)`` of it (log time)."""

    bag: str
    name: str
    part: int = 0
    parts: int = 1
    start_ns: int | None = None
    stop_ns: int | None = None
    frames: int = 0          # clouds in the bag (or slice): the progress bar's total

    @property
    def id(self) -> str:
        return self.name if self.parts == 1 else f"{self.name}.part-{self.part:04d}"

    @property
    def window(self):
        return None if self.parts == 1 else (self.start_ns, self.stop_ns)


@dataclass(frozen=True)
class RunSpec:
    """What every task of a run shares (sent to the workers)."""

    out: str
    nodes: tuple
    params: dict = field(default_factory=dict)
    topics: dict = field(default_factory=dict)
    write_bags: bool = True


def resolve_inputs(items) -> list[Path]:
    """Bag directories of ``items``: bags, folders of bags, globs, list files."""
    from lidar_quality_ros.perception_bag import resolve_bags

    out = []
    for item in map(str, items):
        p = Path(item)
        if p.is_file() and p.name != "metadata.yaml":
            lines = [ln.split("#")[0].strip() for ln in p.read_text().splitlines()]
            base = p.parent
            out += resolve_inputs([str(base / ln) if not os.path.isabs(ln) else ln
                                   for ln in lines if ln])
        elif p.exists():
            out += resolve_bags([p])
        else:
            hits = sorted(glob.glob(item, recursive=True))
            bags = [Path(h) for h in hits if (Path(h) / "metadata.yaml").exists()]
            if not bags:
                raise UsageError(f"--bags {item}: no such bag, folder, list file or matching "
                                 "bag")
            out += bags
    seen, unique = set(), []
    for b in out:
        if b.resolve() not in seen:
            seen.add(b.resolve())
            unique.append(b)
    return unique


def _names(bags: list[Path]) -> list[str]:
    """Output names: the bag's folder name, with its parent's where two would clash."""
    names = [b.name for b in bags]
    clash = {n for n in names if names.count(n) > 1}
    names = [f"{b.parent.name}_{b.name}" if b.name in clash else b.name for b in bags]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise UsageError(f"several input bags would be named {', '.join(dup)}: rename them")
    return names


def plan_tasks(bags: list[Path], slice_s: float | None, points_topic: str) -> list[Task]:
    """One task per bag, or per ``slice_s`` seconds of log time of a longer bag."""
    from lidar_quality_ros.bag_io import bag_info

    tasks = []
    for bag, name in zip(bags, _names(bags)):
        try:
            info = bag_info(bag)
        except Exception:  # noqa: BLE001 - an unreadable bag is the task's failure, reported
            tasks.append(Task(str(bag), name))
            continue
        frames = info.topics[points_topic].count if points_topic in info.topics else 0
        start, stop = info.start_ns, info.end_ns + 1
        span = slice_s and int(slice_s * 1e9)
        if not span or stop - start <= span:
            tasks.append(Task(str(bag), name, frames=frames))
            continue
        n = -(-(stop - start) // span)
        tasks += [Task(str(bag), name, k, n, start + k * span, min(start + (k + 1) * span, stop),
                       frames=-(-frames // n)) for k in range(n)]
    return tasks


def warm_up_window(bag: Path, runners, points_topic: str, start_ns: int):
    """``(first, start_ns)``: the log times of the last frames before ``start_ns`` that the
    runners' processors carry over to the next (their drift monitors' windows, the largest
    ``drift_window``), or None when there is no such frame or monitor. The clouds' log
    times are read from a span before ``start_ns`` that grows until it holds enough."""
    from lidar_quality_ros.bag_io import bag_info, read_bag

    need = max((m.window for m in (getattr(getattr(r.processor, "domain", None), "monitor",
                                           None) for r in runners) if m is not None),
               default=0)
    info = bag_info(bag)
    t = info.topics.get(points_topic)
    if not need or t is None or not t.count or start_ns <= info.start_ns:
        return None
    period = max((info.end_ns - info.start_ns) // max(t.count - 1, 1), 1)
    span = 2 * need * period
    while True:
        lo = max(start_ns - span, info.start_ns)
        stamps = [m.stamp_ns for m in read_bag(bag, {points_topic}, start_ns=lo,
                                                stop_ns=start_ns)]
        if len(stamps) >= need or lo == info.start_ns:
            break
        span *= 2
    return (stamps[-need] if len(stamps) >= need else stamps[0], start_ns) if stamps else None


# ----------------------------------------------------------------------- versions
def code_version() -> dict:
    """The runtime code: a hash of its sources, and the git commit where there is one."""
    import importlib
    import subprocess

    h = hashlib.sha256()
    for pkg in ("lidar_quality_core", "lidar_quality_ros", "lidar_quality_tools", "lmd_ros",
                "lms_ros", "mimo_ros"):
        root = Path(importlib.import_module(pkg).__file__).resolve().parent
        for f in sorted(root.rglob("*.py")):
            h.update(f"{pkg}/{f.relative_to(root).as_posix()}".encode())
            h.update(f.read_bytes())
    try:
        commit = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "rev-parse",
                                 "HEAD"], text=True, capture_output=True, timeout=10)
        commit = commit.stdout.strip() if commit.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return {"sources": h.hexdigest()[:16], "git": commit}


def _input_fingerprint(bag: Path) -> list:
    return sorted([p.name, p.stat().st_size, p.stat().st_mtime_ns]
                  for p in bag.iterdir() if p.is_file())


def _model_ids(runners) -> dict:
    return {r.name: r.model_ids() for r in runners}


def run_key(task: Task, spec: RunSpec, versions: dict) -> str:
    """What a task's outputs depend on, hashed: equal keys, equal outputs."""
    try:
        fingerprint = _input_fingerprint(Path(task.bag))
    except OSError:
        fingerprint = None
    record = {"task": asdict(task), "inputs": fingerprint, "nodes": list(spec.nodes),
              "topics": spec.topics, "bags": spec.write_bags, **versions}
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()


# ----------------------------------------------------------------------- one task
def _status_path(out: Path, task: Task) -> Path:
    return out / "tasks" / f"{task.id}.json"


def _write_json(path: Path, data: dict) -> None:
    from lidar_quality_core.model_store import write_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=1, sort_keys=True)
    write_atomic(path, lambda tmp: Path(tmp).write_text(text), digest=False)


def _progress_event(task_id: str, frames: int) -> None:
    try:
        from distributed import get_worker

        get_worker().log_event(PROGRESS_TOPIC, {"task": task_id, "frames": frames})
    except (ImportError, ValueError):   # not on a worker (in-process run): no events
        pass


def run_task(task: Task, spec: RunSpec, key: str) -> dict:
    """Process one task where it is called (a Dask worker, or this process) and write its
    outputs and status file; returns the status (failures are returned, not raised)."""
    from lidar_quality_ros.perception_bag import topic_of

    from .process import process_one

    out = Path(spec.out)
    t0 = time.perf_counter()
    status = {"task": task.id, "bag": task.bag, "name": task.name, "part": task.part,
              "parts": task.parts, "key": key, "host": os.uname().nodename,
              "pid": os.getpid()}
    tmp = out / ".partial" / f"{task.id}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        runners = build_runners(spec.nodes, spec.params, spec.topics)
        bag_rel = Path("bags") / task.name / (f"part-{task.part:04d}" if task.parts > 1 else "")
        tmp_bag = tmp / "bag" / (bag_rel.name or task.name) if spec.write_bags else None
        done = [0]

        def on_frame():
            done[0] += 1
            if done[0] % PROGRESS_EVERY == 0:
                _progress_event(task.id, PROGRESS_EVERY)

        warm = task.window and warm_up_window(
            Path(task.bag), runners, topic_of("points", spec.topics), task.start_ns)
        if warm:    # the frames before the slice, no outputs: the processors' state
            process_one(Path(task.bag), None, runners, topics=spec.topics, window=warm)
        summary = process_one(Path(task.bag), tmp_bag, runners, results=tmp / "results",
                              part=f"part-{task.part:04d}", name=task.name, topics=spec.topics,
                              window=task.window, on_frame=on_frame)
        _progress_event(task.id, done[0] % PROGRESS_EVERY)
        # move into place: results first, the bag, the status file last (the done marker)
        files = {}
        for node, f in summary["results"].items():
            rel = Path(f).relative_to(tmp)
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(f, out / rel)
            files[node] = str(rel)
        if spec.write_bags:
            target = out / bag_rel
            target.parent.mkdir(parents=True, exist_ok=True)
            if target.exists():
                shutil.rmtree(target)
            os.replace(tmp_bag, target)
            files["bag"] = str(bag_rel)
        summary.update(results=files, out=files.get("bag"))
        status.update(status="done", files=files, summary=summary,
                      frames=summary["frames"], models=_model_ids(runners),
                      no_output=summary["no_output"])
    except Exception as exc:  # noqa: BLE001 - a failing bag is reported, the run goes on
        status.update(status="failed", error=f"{type(exc).__name__}: {exc}", frames=0)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    status["wall_s"] = round(time.perf_counter() - t0, 3)
    _write_json(_status_path(out, task), status)
    return status


def _skip(out: Path, task: Task, key: str) -> dict | None:
    """The status of a task already done with the same key, its files all present."""
    try:
        st = json.loads(_status_path(out, task).read_text())
    except (OSError, ValueError):
        return None
    if st.get("status") != "done" or st.get("key") != key:
        return None
    if not all((out / f).exists() for f in st.get("files", {}).values()):
        return None
    return {**st, "skipped": True}


def _part(path: Path) -> int | None:
    name = path.name.split(".")[0]
    return int(name[5:]) if name.startswith("part-") and name[5:].isdigit() else None


def _clear_stale(out: Path, tasks: list[Task], todo: list[Task]) -> None:
    """Remove what an earlier run left of the bags about to be processed and does not
    belong to a task kept as done: another slicing's parts, other nodes' tables, a bag
    written before. The Parquet dataset then holds exactly this run's rows."""
    pending = {t.id for t in todo}
    names = {t.name for t in todo}
    for name in names:
        mine = [t for t in tasks if t.name == name]
        keep = {t.part for t in mine if t.id not in pending}
        sliced = mine[0].parts > 1
        for f in (out / "results").glob(f"*/bag={name}/*.parquet"):
            if _part(f) not in keep:
                f.unlink()
        bag = out / "bags" / name
        if bag.is_dir():
            if not sliced or (bag / "metadata.yaml").exists():
                if not keep:
                    shutil.rmtree(bag)
            else:
                for p in bag.glob("part-*"):
                    if _part(p) not in keep:
                        shutil.rmtree(p)
        for f in (out / "tasks").glob(f"{name}*.json"):
            stem = f.name[:-5]
            if stem == name or stem.startswith(f"{name}.part-"):
                if stem not in {t.id for t in mine if t.id not in pending}:
                    f.unlink()


# ----------------------------------------------------------------------- the run
def worker_environ() -> dict:
    """The environment Dask's nannies give new worker processes, without the
    ``MALLOC_TRIM_THRESHOLD_`` that distributed sets by default: an explicit trim
    threshold turns off glibc's dynamic mmap threshold, and every large array is then a
    fresh mmap: the frame work ran 2x slower (bench_fleet)."""
    import dask
    import distributed  # noqa: F401 - registers distributed's configuration defaults

    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    env["MALLOC_TRIM_THRESHOLD_"] = None     # None: not set (distributed's convention)
    return env


def local_cluster(n_workers: int):
    """A LocalCluster for the tasks: ``n_workers`` single-threaded processes on 127.0.0.1
    (dashboard on a free port), started with ``worker_environ``."""
    import dask
    from distributed import LocalCluster

    # a nanny writes its environment into this process's os.environ before it spawns:
    # after any other LocalCluster here, Dask's trim threshold would be inherited
    dask_value = dask.config.get("distributed.nanny.pre-spawn-environ", {}).get(
        "MALLOC_TRIM_THRESHOLD_")
    if dask_value is not None and os.environ.get("MALLOC_TRIM_THRESHOLD_") == str(dask_value):
        del os.environ["MALLOC_TRIM_THRESHOLD_"]
    with dask.config.set({"distributed.nanny.pre-spawn-environ": worker_environ()}):
        return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                            host="127.0.0.1", dashboard_address="127.0.0.1:0")


def _trim_note(client, say) -> None:
    """Say so when an existing cluster's workers run with the slow allocator setting."""
    try:
        envs = client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
    except Exception:  # noqa: BLE001 - only a note: a cluster that refuses run() still works
        return
    if any(v is not None for v in envs.values()):
        say("process_bags: note: the workers run with MALLOC_TRIM_THRESHOLD_ set (Dask's "
            "default), which makes the frame work about 2x slower; start them without it "
            "(README, 'Running over a fleet')")


def _cluster(scheduler: str | None, scheduler_file: str | None, workers: int | None, say):
    """A ``distributed.Client``: to an existing scheduler, or to a new LocalCluster."""
    from distributed import Client

    if scheduler or scheduler_file:
        client = Client(scheduler, scheduler_file=scheduler_file, timeout="30s")
        say(f"process_bags: cluster {client.scheduler.address} "
            f"({len(client.scheduler_info()['workers'])} workers), dashboard "
            f"{client.dashboard_link}")
        _trim_note(client, say)
        return client, None
    n = workers or os.cpu_count() or 1
    cluster = local_cluster(n)
    client = Client(cluster)
    say(f"process_bags: local cluster of {n} worker process(es), dashboard "
        f"{cluster.dashboard_link}")
    return client, cluster


def process_bags(bags, out, *, nodes=tuple(NODES), params: dict | None = None,
                 topics: dict | None = None, scheduler: str | None = None,
                 scheduler_file: str | None = None, workers: int | None = None,
                 slice_s: float | None = DEFAULT_SLICE_S, write_bags: bool = True,
                 retry_failed: bool = True, progress: bool = True, client=None) -> dict:
    """Run every task of ``bags`` (``resolve_inputs``) on Dask into ``out``; returns the
    manifest (also written to ``out/manifest.json``). ``client``: an existing
    ``distributed.Client`` to use (else one is made as the CLI does)."""
    from lidar_quality_core.progress import Progress
    from lidar_quality_ros.perception_bag import topic_of

    out = Path(out)
    nodes = tuple(nodes.split(",")) if isinstance(nodes, str) else tuple(nodes)
    spec = RunSpec(str(out.resolve()), nodes, dict(params or {}), dict(topics or {}),
                   write_bags)
    runners = build_runners(nodes, spec.params, spec.topics)   # refuses bad settings here
    inputs = resolve_inputs(bags if isinstance(bags, (list, tuple)) else [bags])
    if not inputs:
        raise UsageError("no input bag")
    for b in inputs:
        r, o = b.resolve(), out.resolve()
        if r == o or o in r.parents or r in o.parents:
            raise UsageError(f"--out {out} overlaps input {b}")
    versions = {"code": code_version(), "models": _model_ids(runners),
                "settings": nodes_parameters(nodes, spec.params)}
    tasks = plan_tasks(inputs, slice_s, topic_of("points", spec.topics))
    keys = {t.id: run_key(t, spec, versions) for t in tasks}
    say = (lambda text: print(text, file=sys.stderr)) if progress else (lambda text: None)
    results: dict[str, dict] = {}
    todo = []
    for t in tasks:
        prev = _skip(out, t, keys[t.id])
        if prev is None and not retry_failed:
            try:
                st = json.loads(_status_path(out, t).read_text())
                if st.get("status") == "failed" and st.get("key") == keys[t.id]:
                    prev = {**st, "skipped": True}
            except (OSError, ValueError):
                pass
        if prev is not None:
            results[t.id] = prev
        else:
            todo.append(t)
    say(f"process_bags: {len(inputs)} bag(s), {len(tasks)} task(s): {len(todo)} to run, "
        f"{len(tasks) - len(todo)} already done")
    t0 = time.perf_counter()
    own = None
    _clear_stale(out, tasks, todo)
    if todo:
        if client is None:
            client, own = _cluster(scheduler, scheduler_file, workers, say)
            own = (client, own)
        total = sum(t.frames for t in todo)
        bar = Progress("process_bags: frames", total or None,
                       enabled=progress)
        finished = [0]

        def tasks_note() -> str:
            return f"tasks {finished[0]}/{len(todo)}"

        def task_done() -> None:
            finished[0] += 1
            bar.update(0, tasks_note())

        client.subscribe_topic(PROGRESS_TOPIC,
                               lambda ev: bar.update(ev[1]["frames"], tasks_note()))
        try:
            results.update(_submit(client, todo, spec, keys, say, task_done))
        finally:
            client.unsubscribe_topic(PROGRESS_TOPIC)
            bar.close()
            if own is not None:
                own[0].close()
                if own[1] is not None:
                    own[1].close()
    wall = time.perf_counter() - t0
    shutil.rmtree(out / ".partial", ignore_errors=True)   # a killed worker's leftovers
    manifest = {"created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "command": " ".join(sys.argv), "out": str(out), "nodes": list(nodes),
                "topics": spec.topics, "params": spec.params, "write_bags": write_bags,
                "slice_s": slice_s, **versions, "wall_s": round(wall, 3),
                "tasks": [_task_row(t, results[t.id]) for t in tasks]}
    _write_json(out / "manifest.json", manifest)
    return manifest


def _submit(client, todo, spec, keys, say, task_done) -> dict:
    """Submit every task (longest bags first), collect the statuses as they finish."""
    from distributed import as_completed

    futures = {}
    for t in sorted(todo, key=lambda t: -t.frames):
        f = client.submit(run_task, t, spec, keys[t.id], key=f"lq-{t.id}-{keys[t.id][:12]}",
                          pure=False, retries=0)
        futures[f] = t
    out = {}
    for f in as_completed(futures):
        t = futures[f]
        try:
            st = f.result()
        except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker: reported, the run goes on
            st = {"task": t.id, "bag": t.bag, "status": "failed", "frames": 0,
                  "error": f"{type(exc).__name__}: {exc}"}
            _write_json(_status_path(Path(spec.out), t), {**st, "key": ""})
        if st["status"] != "done":
            say(f"process_bags: FAILED: {t.id} ({t.bag}): {st.get('error')}")
        out[t.id] = st
        task_done()
    return out


def _task_row(t: Task, st: dict) -> dict:
    s = st.get("summary") or {}
    nodes = s.get("nodes", {})
    return {"task": t.id, "bag": t.bag, "part": t.part, "parts": t.parts,
            "status": st.get("status"), "skipped": bool(st.get("skipped")),
            "frames": st.get("frames", 0),
            "dropped": {n: v.get("frames_dropped", 0) for n, v in nodes.items()},
            "no_output": st.get("no_output") or {},
            "wall_s": st.get("wall_s"), "error": st.get("error"),
            "files": st.get("files", {})}


def status_table(manifest: dict) -> str:
    """Every task's status, frames, drops per node and time; then the totals."""
    rows = manifest["tasks"]
    w = max([len(r["task"]) for r in rows] + [4])
    nodes = manifest["nodes"]
    head = f"{'task':<{w}}  {'status':<8}{'frames':>7}" + "".join(
        f"{n + ' drop':>10}" for n in nodes) + f"{'wall s':>9}  note"
    lines = [head]
    for r in rows:
        state = "skipped" if r["skipped"] else r["status"]
        note = r["error"] or "; ".join(f"{n}: {why}" for n, why in r["no_output"].items())
        lines.append(f"{r['task']:<{w}}  {state:<8}{r['frames']:>7}" + "".join(
            f"{r['dropped'].get(n, '-'):>10}" for n in nodes) +
            f"{(r['wall_s'] or 0):>9.2f}  {note}")
    done = [r for r in rows if r["status"] == "done"]
    frames = sum(r["frames"] for r in done if not r["skipped"])
    wall = manifest["wall_s"]
    lines.append(f"{len(done)}/{len(rows)} task(s) done ({sum(r['skipped'] for r in rows)} "
                 f"skipped), {len(rows) - len(done)} failed; {frames} frames processed in "
                 f"{wall:.1f} s ({frames / wall if wall else 0:.1f} frames/s)")
    return "\n".join(lines)


# ----------------------------------------------------------------------- command line
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="process_bags", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="exit codes: 0 every task done; 1 a task failed or "
                                 "a node processed no frame of a bag; 2 bad arguments")
    ap.add_argument("--bags", action="append", required=True, metavar="IN",
                    help="bag, folder of bags, glob or list file (repeatable)")
    ap.add_argument("--out", required=True, type=Path, help="output folder (bags, results, "
                    "tasks, manifest.json)")
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--scheduler", help="address of an existing Dask scheduler, e.g. "
                       "tcp://host:8786 (default: a LocalCluster here)")
    where.add_argument("--scheduler-file", help="scheduler file of an existing cluster")
    where.add_argument("--workers", type=int, help="worker processes of the LocalCluster "
                       "(default: one per core)")
    ap.add_argument("--slice-s", type=float, default=DEFAULT_SLICE_S, help="one task per "
                    "this many seconds of a longer bag (0: one task per bag; default "
                    f"{DEFAULT_SLICE_S:g})")
    ap.add_argument("--no-bags", action="store_true", help="result tables only, no output bags")
    ap.add_argument("--nodes", default=",".join(NODES), help="comma-separated subset of "
                    f"{','.join(NODES)} (default: all)")
    ap.add_argument("--param", action="append", default=[], metavar="NODE.NAME=VALUE",
                    help="override a node parameter of its config YAML (repeatable)")
    from lidar_quality_ros.perception_bag import add_topic_option

    add_topic_option(ap)
    ap.add_argument("--no-retry-failed", action="store_true", help="leave tasks that failed "
                    "in an earlier run with the same key as they are")
    ap.add_argument("--no-progress", action="store_true", help="no progress line on stderr")
    args = ap.parse_args(argv)
    if args.workers is not None and args.workers < 1:
        ap.error("--workers must be at least 1")
    try:
        manifest = process_bags(
            args.bags, args.out, nodes=tuple(n.strip() for n in args.nodes.split(",")
                                             if n.strip()),
            params=_parse_params(args.param), topics=dict(args.topic),
            scheduler=args.scheduler, scheduler_file=args.scheduler_file,
            workers=args.workers, slice_s=args.slice_s or None, write_bags=not args.no_bags,
            retry_failed=not args.no_retry_failed, progress=not args.no_progress)
    except UsageError as exc:
        ap.error(str(exc))
    except KeyboardInterrupt:
        print("\nprocess_bags: interrupted: finished tasks are kept; rerun to do the rest",
              file=sys.stderr)
        return 130
    print(status_table(manifest))
    bad = [r for r in manifest["tasks"] if r["status"] != "done" or r["no_output"]]
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
