"""process_bags on a real two-worker Dask LocalCluster (processes) over four small simulated
perception bags: outputs identical to four sequential ``process_bag`` runs, a rerun skips
what is done, a changed setting reruns, a worker killed mid-run loses no bag, a bad bag is
reported without stopping the run, slices of a bag add up to the bag (the drift monitor's
window carried over by a warm-up run), the CLI."""
import json
import os
import shutil
import signal
import threading
import time

import pyarrow.parquet as pq
import pytest
from distributed import Client
from lidar_quality_ros.bag_io import read_bag
from lidar_quality_tools.fleet import (local_cluster, main, plan_tasks, process_bags,
                                       resolve_inputs, warm_up_window)
from lidar_quality_tools.process import NODES, UsageError, build_runners, process_bag
from perception_bags import simulated_perception_bags
from reference_perception.cli import Perception

N_BAGS, N_FRAMES = 4, 3


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    return simulated_perception_bags(tmp_path_factory.mktemp("fleet"), Perception(heads=2),
                                     n_sequences=N_BAGS, n_frames=N_FRAMES, seed=5,
                                     columns=512)


@pytest.fixture(scope="module")
def sequential(bags, tmp_path_factory):
    """Four separate process_bag runs: output bags and result tables."""
    root = tmp_path_factory.mktemp("sequential")
    for b in sorted(bags.iterdir()):
        s = process_bag(b, root / "bags" / b.name, progress=False, results=root / "results")
        assert set(s["results"]) == set(NODES)
    return root


@pytest.fixture(scope="module")
def client():
    with local_cluster(2) as cluster, Client(cluster) as c:
        yield c


def messages(path):
    return [(m.topic, m.msgtype, m.stamp_ns, m.raw) for m in read_bag(path)]


def table(path):
    t = pq.read_table(path)
    return t, t.schema.metadata


def assert_same_outputs(out, sequential, names):
    for name in names:
        assert messages(out / "bags" / name) == messages(sequential / "bags" / name), name
        for node in NODES:
            rel = f"results/{node}/bag={name}/part-0000.parquet"
            got, meta = table(out / rel)
            want, want_meta = table(sequential / rel)
            assert got.num_rows > 0
            assert same_table(got, want), rel
            assert meta == want_meta


def same_table(got, want) -> bool:
    """Equal schemas and values, NaN where the other has NaN (pyarrow's ``equals`` takes
    NaN for unequal: the drift score is NaN until the monitor's window holds enough)."""
    return got.schema.equals(want.schema) and got.to_pandas().equals(want.to_pandas())


def test_two_workers_equal_sequential_runs_and_rerun_skips(bags, sequential, client, tmp_path):
    # local_cluster's workers run without Dask's MALLOC_TRIM_THRESHOLD_ (2x slower frames)
    assert set(client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_").values()) == {None}
    out = tmp_path / "fleet"
    m = process_bags([bags], out, client=client, progress=False)
    names = sorted(b.name for b in bags.iterdir())
    assert [r["status"] for r in m["tasks"]] == ["done"] * N_BAGS
    assert sum(r["frames"] for r in m["tasks"]) == N_BAGS * N_FRAMES
    pids = {json.loads((out / "tasks" / f"{n}.json").read_text())["pid"] for n in names}
    assert len(pids) == 2                      # both workers took bags
    assert_same_outputs(out, sequential, names)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["code"]["sources"] and set(manifest["models"]) == set(NODES)
    assert manifest["settings"]["lmd"]["proposal_mode"]

    stamps = {n: (out / "tasks" / f"{n}.json").stat().st_mtime_ns for n in names}
    again = process_bags([bags], out, client=client, progress=False)
    assert all(r["skipped"] for r in again["tasks"])
    assert {n: (out / "tasks" / f"{n}.json").stat().st_mtime_ns for n in names} == stamps

    # another setting is another key: the bag is processed again
    changed = process_bags([bags / names[0]], out, client=client, progress=False,
                           params={"lmd.min_confidence": 0.5})
    assert [r["skipped"] for r in changed["tasks"]] == [False]


def test_killed_worker_loses_no_bag(bags, sequential, tmp_path):
    out = tmp_path / "fleet"
    names = sorted(b.name for b in bags.iterdir())
    with local_cluster(2) as cluster, Client(cluster) as c:
        result = {}
        run = threading.Thread(target=lambda: result.update(
            m=process_bags([bags], out, client=c, progress=False)))
        run.start()
        deadline = time.monotonic() + 120
        while not any(c.processing().values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        busy = next(w for w, tasks in c.processing().items() if tasks)
        time.sleep(0.5)                        # mid-task: the first bags take seconds
        pid = c.run(os.getpid, workers=[busy])[busy]
        os.kill(pid, signal.SIGKILL)
        run.join(300)
        assert not run.is_alive()
        m = result["m"]
        if any(r["status"] != "done" for r in m["tasks"]):   # reported, then a rerun does it
            m = process_bags([bags], out, client=c, progress=False)
        assert [r["status"] for r in m["tasks"]] == ["done"] * N_BAGS
    # the killed process finished no task: its bag was done again by another worker
    assert pid not in {json.loads((out / "tasks" / f"{n}.json").read_text())["pid"]
                       for n in names}
    assert not (out / ".partial").exists()
    assert_same_outputs(out, sequential, names)


def test_failing_bag_is_reported_and_the_run_goes_on(bags, client, tmp_path):
    src = tmp_path / "in"
    shutil.copytree(bags / "seq_00", src / "good")
    shutil.copytree(bags / "seq_01", src / "broken")
    storage = next((src / "broken").glob("*.mcap"))
    storage.write_bytes(storage.read_bytes()[:2000])   # truncated recording
    out = tmp_path / "fleet"
    m = process_bags([src], out, client=client, progress=False, write_bags=False)
    rows = {r["task"]: r for r in m["tasks"]}
    assert rows["good"]["status"] == "done" and rows["good"]["frames"] == N_FRAMES
    assert rows["broken"]["status"] == "failed" and rows["broken"]["error"]
    assert not (out / "bags").exists()          # --no-bags: tables only
    assert (out / "results" / "lmd" / "bag=good" / "part-0000.parquet").exists()
    again = process_bags([src], out, client=client, progress=False, write_bags=False)
    rows = {r["task"]: r for r in again["tasks"]}
    assert rows["good"]["skipped"] and rows["broken"]["status"] == "failed"   # retried


def test_warm_up_window_is_the_drift_window_before_a_slice(bags):
    """The frames a slice's processors run over first: the last drift_window clouds before
    it (as many as there are), none before the first or without a drift monitor."""
    bag = bags / "seq_02"
    t = [m.stamp_ns for m in read_bag(bag, {"/lidar/points"})]
    assert len(t) == N_FRAMES
    runners = build_runners(("lmd", "mimo"), {"lmd.drift_window": 2, "mimo.drift_window": 1})
    assert warm_up_window(bag, runners, "/lidar/points", t[2]) == (t[0], t[2])
    assert warm_up_window(bag, runners, "/lidar/points", t[2] + 1) == (t[1], t[2] + 1)
    assert warm_up_window(bag, runners, "/lidar/points", t[1]) == (t[0], t[1])
    assert warm_up_window(bag, runners, "/lidar/points", t[0]) is None
    assert warm_up_window(bag, runners, "/no/points", t[2]) is None
    for r in runners:
        r.processor.domain.monitor = None       # as for models without a profile
    assert warm_up_window(bag, runners, "/lidar/points", t[2]) is None


def test_slices_add_up_to_the_bag(bags, sequential, client, tmp_path):
    bag = bags / "seq_02"
    tasks = plan_tasks([bag], 0.15, "/lidar/points")       # 3 frames, 0.1 s apart
    assert len(tasks) == 2 and all(t.parts == 2 for t in tasks)
    out = tmp_path / "fleet"
    m = process_bags([bag], out, client=client, progress=False, slice_s=0.15)
    assert [r["status"] for r in m["tasks"]] == ["done", "done"]
    assert sum(r["frames"] for r in m["tasks"]) == N_FRAMES
    parts = sorted((out / "bags" / "seq_02").iterdir())
    assert [p.name for p in parts] == ["part-0000", "part-0001"]
    whole = messages(sequential / "bags" / "seq_02")
    assert sorted(x for p in parts for x in messages(p)) == sorted(whole)
    for node in NODES:
        import pyarrow as pa

        got = pa.concat_tables(pq.read_table(p) for p in sorted(
            (out / "results" / node / "bag=seq_02").glob("*.parquet")))
        want = pq.read_table(sequential / f"results/{node}/bag=seq_02/part-0000.parquet")
        assert same_table(got, want), node
    # the same OUT without slices: nothing of the sliced run is left beside the new outputs
    m = process_bags([bag], out, client=client, progress=False, slice_s=None, nodes="lmd")
    assert [r["task"] for r in m["tasks"]] == ["seq_02"]
    assert sorted(p.name for p in (out / "results").rglob("*.parquet")) == ["part-0000.parquet"]
    assert messages(out / "bags" / "seq_02")
    assert sorted(p.name for p in (out / "tasks").iterdir()) == ["seq_02.json"]


def test_inputs_globs_and_list_files(bags, tmp_path):
    listing = tmp_path / "bags.txt"
    listing.write_text(f"# two bags\n{bags / 'seq_00'}\n{bags / 'seq_01'}  # the second\n")
    assert resolve_inputs([listing]) == [bags / "seq_00", bags / "seq_01"]
    assert resolve_inputs([str(bags / "seq_0[23]")]) == [bags / "seq_02", bags / "seq_03"]
    with pytest.raises(UsageError, match="no such bag"):
        resolve_inputs([str(tmp_path / "nothing*")])
    with pytest.raises(UsageError, match="overlaps"):
        process_bags([bags], bags / "seq_00" / "out", progress=False)


def test_cli_table_and_exit_code(bags, client, tmp_path, capsys):
    address = client.scheduler.address
    out = tmp_path / "fleet"
    code = main(["--bags", str(bags / "seq_03"), "--out", str(out), "--scheduler", address,
                 "--no-bags", "--nodes", "lmd", "--no-progress"])
    text = capsys.readouterr().out
    assert code == 0
    assert "seq_03" in text and "done" in text and "1/1 task(s) done" in text
    with pytest.raises(SystemExit) as exc:
        main(["--bags", str(bags), "--out", str(out), "--nodes", "nope"])
    assert exc.value.code == 2


def test_installed_executables_embedded_cluster(bags, tmp_path):
    """``process_bags`` as installed, with its own LocalCluster (the default), then
    ``fleet_review`` on its output."""
    import subprocess

    from node_shell_checks import executable

    out = tmp_path / "fleet"
    run = subprocess.run([str(executable("lidar_quality_tools", "process_bags")), "--bags",
                          str(bags / "seq_01"), "--out", str(out), "--workers", "1",
                          "--nodes", "lmd"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "local cluster of 1 worker process(es), dashboard http://127.0.0.1:" in run.stderr
    assert "1/1 task(s) done" in run.stdout
    review = subprocess.run([str(executable("lidar_quality_tools", "fleet_review")), str(out),
                             "--k", "5", "--thumbnails", "2"], capture_output=True, text=True,
                            timeout=300)
    assert review.returncode == 0, review.stderr[-2000:]
    assert (out / "review" / "sheet_annotation_errors.png").exists()
