"""lidar_quality_training.distributed_training on a real Dask cluster (2 worker processes)
with real xgboost: a cluster fit is the plain estimator the nodes load, grouped folds are
fitted on every worker, lmd-train / lms-train / mimo-train with --features and --scheduler
write models MetaModels loads, and a cluster-trained LMD model's held-out AUROC is within
0.005 of the single-machine one."""
import json

import dask
import numpy as np
import pytest
from dask.utils import key_split
from distributed import Client, LocalCluster, get_task_stream
from lidar_quality_core import meta_model
from lidar_quality_core import metrics as M
from lidar_quality_core.meta_model import MetaModels
from lidar_quality_core.model_store import read_manifest
from lmd_bags import write_split
from lms_data import COLUMNS
from lms_data import perception_bags as lms_bags
from mimo_data import perception_bags as mimo_bags
from lidar_quality_training import distributed_training as DT
from lidar_quality_training.lmd import dataset as D
from lidar_quality_training.lmd import train as lmd_train
from lidar_quality_training.lms import train as lms_train
from lidar_quality_training.mimo import train as mimo_train
from lms_ros.pipeline import LmsSettings
from mimo_ros.pipeline import MimoSettings


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None,
                      scheduler_kwargs={"dashboard": False,
                                        "dashboard_address": "127.0.0.1:0"}) as c:
        yield c


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("dt_lmd")
    write_split(root / "meta_train", 4, 4, seed0=0, n_objects=25)
    write_split(root / "meta_test", 2, 4, seed0=500, n_objects=25)
    return root


def training_workers(ts) -> list[str]:
    """The worker of each xgboost.dask training task in a task stream (xgboost 3.2 runs
    its per-worker training function as tasks named ``fn-<id>``)."""
    return [t["worker"] for t in ts.data if key_split(t["key"]) == "fn"]


def lmd_sets(data, part, mode="threshold"):
    return D.load_bags([data / f"meta_{part}"], [D.settings_for(mode)],
                       cache_dir=data / "cache", progress=False)[mode]


def test_scheduler_forms(tmp_path):
    assert DT.parse_scheduler("local") == ("local", None)
    assert DT.parse_scheduler("local:3") == ("local", 3)
    assert DT.parse_scheduler("tcp://10.0.0.1:8786") == ("address", "tcp://10.0.0.1:8786")
    f = tmp_path / "scheduler.json"
    f.write_text("{}")
    assert DT.parse_scheduler(str(f)) == ("file", f)
    with pytest.raises(ValueError, match="at least 1 worker"):
        DT.parse_scheduler("local:0")
    for bad in ("10.0.0.1:8786", str(tmp_path / "missing.json")):
        with pytest.raises(ValueError, match="expected a Dask scheduler address"):
            DT.parse_scheduler(bad)


def test_a_cluster_fit_is_the_plain_estimator_the_nodes_load(cluster, data, tmp_path):
    ds, te = lmd_sets(data, "train"), lmd_sets(data, "test")
    with DT.training_backend(cluster.scheduler_address) as b:
        assert b.record() == {"scheduler": cluster.scheduler_address, "workers": 2,
                              "library": "xgboost.dask"}
        with get_task_stream(b.client) as ts:
            clf = b.fit("xgboost", "classification", ds.X, ds.tp.astype(float))
        reg = b.fit("xgboost", "regression", ds.X, ds.iou)
        again = b.fit("xgboost", "classification", ds.X, ds.tp.astype(float))
    # both workers trained it, and the same data gave the same model
    assert sorted(training_workers(ts)) == sorted(cluster.scheduler_info["workers"])
    np.testing.assert_array_equal(clf.predict_proba(te.X), again.predict_proba(te.X))
    for est, task in ((clf, "classification"), (reg, "regression")):
        plain = meta_model.make_estimator("xgboost", task)
        assert type(est) is type(plain)
        assert repr(est.get_params()) == repr(plain.get_params())  # repr: NaN == NaN
        assert est.get_booster().num_boosted_rounds() == 300
    settings = D.settings_for("threshold")
    cpath, rpath = meta_model.save_pair(
        tmp_path, "lmd_threshold", clf, reg, ds.feature_names, compress=3,
        training_data=meta_model.settings_record(settings, "lmd"))
    models = MetaModels(cpath, rpath, settings.feature_names(), settings=settings,
                        method="lmd")
    conf, iou = models.predict(te.X)
    np.testing.assert_allclose(conf, np.clip(clf.predict_proba(te.X)[:, 1], 0, 1), atol=1e-6)
    np.testing.assert_allclose(iou, np.clip(reg.predict(te.X), 0, 1), atol=1e-6)
    assert M.auroc(te.tp, conf) > 0.9 and M.r2(te.iou, iou) > 0.5


def test_grouped_folds_are_fitted_on_the_cluster(cluster, data):
    ds = lmd_sets(data, "train", "none")
    y = ds.tp.astype(float)
    local = meta_model.cross_validate(ds.X, y, ds.group, task="classification", n_folds=4)
    with DT.training_backend(cluster.scheduler_address) as b:
        with get_task_stream(b.client) as ts:
            dist = meta_model.cross_validate(ds.X, y, ds.group, task="classification",
                                             n_folds=4, fold_fitter=b.fit_folds)
    workers = training_workers(ts)
    assert len(workers) == 4 * 2 and len(set(workers)) == 2  # every fold on both workers
    assert len(dist.folds) == 4 and np.isfinite(dist.oof).all()
    for a, b in zip(local.folds, dist.folds):
        assert b.val["auroc"] == pytest.approx(a.val["auroc"], abs=0.02)
    assert np.corrcoef(local.oof, dist.oof)[0, 1] > 0.98


def test_other_kinds_are_refused_with_the_reason(data, tmp_path, capsys):
    with pytest.raises(ValueError, match="fits xgboost models only"):
        with DT.training_backend("local:1", "linear"):
            pass
    assert lmd_train.main(["--train", str(data / "meta_train"), "--test", "--out",
                           str(tmp_path / "m"), "--cache", str(data / "cache"), "--modes",
                           "none", "--kind", "linear", "--scheduler", "local:2",
                           "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "lmd-train: --scheduler fits xgboost models only (xgboost.dask); kind " \
           "'linear' trains on this machine" in err and "Traceback" not in err
    assert not (tmp_path / "m").exists()


def test_an_unreachable_scheduler_ends_the_run_with_the_reason(data, tmp_path, capsys):
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        assert lmd_train.main(["--train", str(data / "meta_train"), "--test", "--out",
                               str(tmp_path / "m"), "--cache", str(data / "cache"),
                               "--modes", "none", "--scheduler", "tcp://127.0.0.1:9",
                               "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "lmd-train: cannot reach the Dask scheduler tcp://127.0.0.1:9" in err
    assert "Traceback" not in err


def test_lmd_train_on_the_cluster_matches_the_single_machine_auroc(data, tmp_path):
    args = ["--train", str(data / "meta_train"), "--test", str(data / "meta_test"),
            "--cache", str(data / "cache"), "--modes", "threshold", "none", "--cv-folds", "2",
            "--quiet"]
    assert lmd_train.main([*args, "--out", str(tmp_path / "single")]) == 0
    assert lmd_train.main([*args, "--out", str(tmp_path / "dask"), "--scheduler",
                           "local:2"]) == 0
    te = {m: lmd_sets(data, "test", m) for m in ("threshold", "none")}
    for mode in ("threshold", "none"):
        one = read_manifest(tmp_path / "single" / f"lmd_{mode}_classifier.joblib")
        two = read_manifest(tmp_path / "dask" / f"lmd_{mode}_classifier.joblib")
        assert two["metrics"]["held_out"]["auroc"] == pytest.approx(
            one["metrics"]["held_out"]["auroc"], abs=0.005)
        assert two["training_data"]["fitted_on"] == {"scheduler": "local:2", "workers": 2,
                                                     "library": "xgboost.dask"}
        assert "fitted_on" not in one["training_data"]
        assert two["feature_names"] == one["feature_names"] and two["format"] == "joblib"
        settings = D.settings_for(mode)
        models = MetaModels(tmp_path / "dask" / f"lmd_{mode}_classifier.joblib",
                            tmp_path / "dask" / f"lmd_{mode}_regressor.joblib",
                            settings.feature_names(), settings=settings, method="lmd")
        conf, _ = models.predict(te[mode].X)
        assert M.auroc(te[mode].tp, conf) == pytest.approx(
            two["metrics"]["held_out"]["auroc"], abs=1e-5)
    card = (tmp_path / "dask" / "MODEL_CARD.md").read_text()
    assert "fitted with xgboost.dask on 2 Dask workers (`--scheduler local:2`)" in card


def test_lmd_train_from_tables_on_the_cluster(cluster, data, tmp_path):
    tables = tmp_path / "tables"
    assert lmd_train.main(["--train", str(data / "meta_train"), "--test",
                           str(data / "meta_test"), "--cache", str(data / "cache"),
                           "--modes", "threshold", "--export-features", str(tables),
                           "--export-only", "--quiet"]) == 0
    out = tmp_path / "m"
    assert lmd_train.main(["--features", str(tables / "train"), "--test-features",
                           str(tables / "test"), "--out", str(out), "--cv-folds", "2",
                           "--scheduler", cluster.scheduler_address, "--quiet"]) == 0
    settings = D.settings_for("threshold")
    MetaModels(out / "lmd_threshold_classifier.joblib", out / "lmd_threshold_regressor.joblib",
               settings.feature_names(), settings=settings, method="lmd")
    td = read_manifest(out / "lmd_threshold_classifier.joblib")["training_data"]
    assert td["sources"] == [str(tables / "train" / "lmd_threshold.parquet")]
    assert td["held_out"]["sources"] == [str(tables / "test" / "lmd_threshold.parquet")]


def test_lms_train_from_tables_on_the_cluster(cluster, tmp_path):
    bags = lms_bags(tmp_path / "pb", n_sequences=2, n_frames=4)
    common = ["--folds", "2", "--block-frames", "2", "--quiet"]
    assert lms_train.main(["--data", str(bags), "--width", str(COLUMNS), "--cache", "",
                           "--export-features", str(tmp_path / "t"), "--export-only",
                           *common]) == 0
    out = tmp_path / "m"
    assert lms_train.main(["--features", str(tmp_path / "t" / "lms_points.parquet"), "--out",
                           str(out), "--scheduler", cluster.scheduler_address, *common]) == 0
    settings = LmsSettings(width=COLUMNS)
    models = MetaModels(out / "lms_classifier.joblib", out / "lms_regressor.joblib",
                        settings.metric_names(), settings=settings, method="lms")
    man = read_manifest(out / "lms_classifier.joblib")
    assert man["training_data"]["fitted_on"]["workers"] == 2
    assert man["metrics"]["cv_folds"] == 2
    assert models.predict(np.zeros((1, len(settings.metric_names()))))[0].shape == (1,)


def test_mimo_train_from_tables_on_the_cluster(cluster, tmp_path):
    bags = mimo_bags(tmp_path, n_sequences=2, n_frames=3, seed=11)
    assert mimo_train.main(["--data", str(bags), "--cache", "", "--export-features",
                            str(tmp_path / "t"), "--export-only", "--quiet"]) == 0
    out = tmp_path / "m"
    assert mimo_train.main(["--features", str(tmp_path / "t"), "--out", str(out), "--folds",
                            "2", "--scheduler", cluster.scheduler_address, "--quiet"]) == 0
    for use_points, prefix in ((False, "mimo"), (True, "mimo_points")):
        settings = MimoSettings(num_heads=2, use_points=use_points)
        MetaModels(out / f"{prefix}_classifier.joblib", out / f"{prefix}_regressor.joblib",
                   settings.feature_names(), settings=settings, method="mimo")
        td = read_manifest(out / f"{prefix}_classifier.joblib")["training_data"]
        assert td["fitted_on"]["scheduler"] == cluster.scheduler_address
        assert td["sources"] == [str(tmp_path / "t" / "mimo_points.parquet")]


def test_a_scheduler_file_names_the_cluster(cluster, tmp_path):
    path = tmp_path / "scheduler.json"
    # what `dask scheduler --scheduler-file` writes, of it what a client reads
    path.write_text(json.dumps({"type": "Scheduler", "address": cluster.scheduler_address}))
    with Client(cluster.scheduler_address) as c:
        pids = c.run(lambda: __import__("os").getpid())
    assert len(set(pids.values())) == 2  # two worker processes
    with DT.training_backend(str(path)) as b:
        assert b.record() == {"scheduler": str(path), "workers": 2, "library": "xgboost.dask"}
