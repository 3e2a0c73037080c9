"""lidar_quality_training.feature_table: datasets -> Parquet -> datasets give the same
training arrays for LMD, LMS and MIMO; the columns and metadata follow the fixed
conventions; Hive-partitioned directories, globs and process_bags' extra columns read;
rows without targets are left out and counted; unusable tables are refused by name."""
import json

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest
from lmd_bags import write_split
from lms_data import COLUMNS
from lms_data import perception_bags as lms_bags
from mimo_data import perception_bags as mimo_bags
from lidar_quality_training import feature_table as FT
from lidar_quality_training.lmd import dataset as D
from lidar_quality_training.lms.dataset import build_dataset
from lidar_quality_training.mimo.dataset import load_bags as mimo_load
from lms_ros.pipeline import LmsSettings

MODES = ("exact", "threshold", "none")


@pytest.fixture(scope="module")
def lmd(tmp_path_factory):
    root = tmp_path_factory.mktemp("ft_lmd")
    write_split(root / "meta_train", 3, 2, seed0=0)
    return D.load_bags([root / "meta_train"], [D.settings_for(m) for m in MODES],
                       progress=False)


def assert_same_lmd(a, b, rows=None):
    rows = np.arange(len(a)) if rows is None else rows
    assert b.mode == a.mode and b.feature_names == a.feature_names
    np.testing.assert_array_equal(b.X, a.X[rows])
    for k in ("iou_any", "iou_class", "score", "label", "box", "det_index", "det_id"):
        np.testing.assert_array_equal(getattr(b, k), getattr(a, k)[rows], err_msg=k)
    np.testing.assert_array_equal(b.group, a.group[rows])
    np.testing.assert_array_equal(b.tp, a.tp[rows])
    np.testing.assert_array_equal(b.iou, a.iou[rows])
    np.testing.assert_array_equal(b.frame_key[b.frame], a.frame_key[a.frame][rows])
    np.testing.assert_array_equal(b.frame_source[b.frame], a.frame_source[a.frame][rows])
    assert b.info["settings"] == a.info["settings"]


def test_lmd_round_trip_gives_the_same_training_arrays(lmd, tmp_path):
    paths = FT.export_tables(lmd, tmp_path)
    assert [p.name for p in paths] == [f"lmd_{m}.parquet" for m in MODES]
    back = FT.read_lmd([tmp_path])
    assert set(back) == set(MODES)
    for m in MODES:
        assert_same_lmd(lmd[m], back[m])
        assert back[m].summary() == lmd[m].summary()  # frames and GT boxes from lq.info
        assert back[m].info["sources"] == [{"kind": "feature_table",
                                            "path": str(tmp_path / f"lmd_{m}.parquet"),
                                            "rows": len(lmd[m])}]
        assert back[m].info["rows_without_targets"] == back[m].info["rows_invalid"] == 0
    aware = FT.read_lmd([tmp_path / "lmd_none.parquet"], class_aware=True)["none"]
    np.testing.assert_array_equal(aware.iou, lmd["none"].iou_class)


def test_columns_and_metadata_follow_the_conventions(lmd, tmp_path):
    ds = lmd["threshold"]
    path = FT.write_dataset(ds, tmp_path / "t.parquet")
    assert [p.name for p in tmp_path.iterdir()] == ["t.parquet"]  # no temp file left
    t = pq.read_table(path)
    types = dict(zip(t.schema.names, t.schema.types))
    assert types["group"] == types["source"] == types["frame_key"] == pa.string()
    assert types["index"] == pa.int32()
    for c in ("iou_any", "iou_class", "score", "box_x", "box_y", "box_z", "box_l", "box_w",
              "box_h", "box_yaw"):
        assert types[c] == pa.float64(), c
    assert types["label"] == types["det_id"] == pa.string()
    feats = [n for n in t.schema.names if n.startswith("feat.")]
    assert feats == [f"feat.{n}" for n in ds.feature_names]
    assert all(types[f] == pa.float64() for f in feats)
    meta = {k.decode(): v.decode() for k, v in t.schema.metadata.items()}
    assert meta["lq.method"] == "lmd" and meta["lq.mode"] == "threshold"
    assert meta["lq.version"] == "1"
    assert json.loads(meta["lq.feature_names"]) == list(ds.feature_names)
    assert json.loads(meta["lq.settings"]) == ds.info["settings"]
    # bags: frame_key is the header stamp in ns; index the detection's output position
    assert t.column("frame_key").to_pylist()[0] == str(1_000_000_000)
    np.testing.assert_array_equal(t.column("index").to_numpy(), ds.det_index)


def process_bags_like(ds, *, nan_rows=(), invalid_rows=()):
    """The table of ``ds`` with process_bags' extra columns, some rows without targets
    and some with all-NaN features (an invalid box)."""
    t = FT.table_of(ds)
    n = t.num_rows
    extra = {"bag": pa.array([g.split("/")[1] for g in ds.group]),
             "stamp_ns": pa.array(ds.frame_key[ds.frame].astype(np.int64)),
             "confidence": pa.array(np.linspace(0, 1, n)),
             "predicted_iou": pa.array(np.linspace(1, 0, n)),
             "kept": pa.array(np.ones(n, bool)), "valid": pa.array(np.ones(n, bool))}
    for name, arr in extra.items():
        t = t.append_column(name, arr)
    cols = {name: t.column(name).to_numpy().copy() for name in t.column_names
            if name.startswith(("iou_", "feat."))}
    for r in nan_rows:
        cols["iou_any"][r] = cols["iou_class"][r] = np.nan
    for r in invalid_rows:
        for name in cols:
            if name.startswith("feat."):
                cols[name][r] = np.nan
    for name, v in cols.items():
        t = t.set_column(t.column_names.index(name), name, pa.array(v))
    return t


def test_hive_partitions_extra_columns_and_rows_without_targets(lmd, tmp_path):
    ds = lmd["threshold"]
    t = process_bags_like(ds, nan_rows=[3, 40], invalid_rows=[7])
    # process_bags' layout: one folder per bag, the bag name only in the folder
    pads.write_dataset(t, tmp_path / "run", format="parquet", partitioning=["bag"],
                       partitioning_flavor="hive", basename_template="part-{i}.parquet")
    files = sorted(p.relative_to(tmp_path / "run").as_posix()
                   for p in (tmp_path / "run").rglob("*.parquet"))
    assert files == [f"bag=seq_0{k}/part-0.parquet" for k in range(3)]
    back = FT.read_lmd([tmp_path / "run"])["threshold"]
    keep = np.setdiff1d(np.arange(len(ds)), [3, 7, 40])
    assert_same_lmd(ds, back, keep)
    assert back.info["rows_without_targets"] == 2 and back.info["rows_invalid"] == 1
    assert back.info["dropped_invalid"] == 1
    assert len(back.info["sources"]) == 3


def test_a_key_column_only_in_the_folder_names(lmd, tmp_path):
    ds = lmd["none"]
    pads.write_dataset(FT.table_of(ds), tmp_path / "run", format="parquet",
                       partitioning=["group"], partitioning_flavor="hive")
    assert "group" not in pq.read_schema(next((tmp_path / "run").rglob("*.parquet"))).names
    back = FT.read_lmd([tmp_path / "run"])["none"]
    assert_same_lmd(ds, back)  # groups with a '/' come back from the URI-encoded folder


def test_globs_and_several_paths(lmd, tmp_path):
    FT.export_tables(lmd, tmp_path / "a")
    got = FT.read_lmd([str(tmp_path / "a" / "lmd_[nt]*.parquet")])
    assert set(got) == {"threshold", "none"}
    got = FT.read_lmd([tmp_path / "a" / "lmd_none.parquet", tmp_path / "a" / "lmd_exact.parquet"],
                      modes=["none"])
    assert set(got) == {"none"}


def write(t, path):
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(t, path)
    return path


def refusal(call, *args, **kw):
    with pytest.raises(FT.TableError) as e:
        call(*args, **kw)
    return str(e.value)


def test_unusable_tables_are_refused_naming_what_is_missing(lmd, tmp_path):
    t = FT.table_of(lmd["threshold"])
    no_targets = write(t.drop_columns(["iou_any", "iou_class"]), tmp_path / "a" / "x.parquet")
    msg = refusal(FT.read_lmd, [no_targets])
    assert str(no_targets) in msg and "no target columns iou_any, iou_class" in msg
    no_group = write(t.drop_columns(["group", "det_id"]), tmp_path / "b" / "x.parquet")
    assert "missing columns group, det_id" in refusal(FT.read_lmd, [no_group])
    assert "a lmd feature table; lms-train trains on lms tables" in refusal(
        FT.read_lms, [no_group])
    plain = write(pa.table({"x": [1.0]}), tmp_path / "c" / "x.parquet")
    assert "not a lidar_quality feature table" in refusal(FT.read_lmd, [plain])
    # another feature list than the mode's: a feature left out
    meta = dict(t.schema.metadata)
    names = json.loads(meta[b"lq.feature_names"])[:-1]
    meta[b"lq.feature_names"] = json.dumps(names).encode()
    fewer = write(t.drop_columns(["feat.n_proposals"]).replace_schema_metadata(meta),
                  tmp_path / "d" / "x.parquet")
    msg = refusal(FT.read_lmd, [fewer])
    assert "feature names are not LMD mode threshold's (90 features)" in msg
    assert "missing ['n_proposals']" in msg
    # a feature column missing although the metadata names it
    gone = write(t.drop_columns(["feat.iou_bev_max"]), tmp_path / "e" / "x.parquet")
    assert "missing column feat.iou_bev_max" in refusal(FT.read_lmd, [gone])
    assert "no LMD table of mode exact" in refusal(FT.read_lmd, [no_group.parent.parent / "b"],
                                                    modes=["exact"])
    # two tables of one mode made with different settings
    meta = dict(t.schema.metadata)
    s = json.loads(meta[b"lq.settings"])
    meta[b"lq.settings"] = json.dumps({**s, "iou_threshold": 0.3}).encode()
    write(t, tmp_path / "f" / "1.parquet")
    write(t.replace_schema_metadata(meta), tmp_path / "f" / "2.parquet")
    msg = refusal(FT.read_lmd, [tmp_path / "f"])
    assert "different settings (iou_threshold: 0.5 vs 0.3)" in msg
    meta = dict(t.schema.metadata)
    meta[b"lq.version"] = b"2"
    v2 = write(t.replace_schema_metadata(meta), tmp_path / "g" / "x.parquet")
    assert "feature table version '2'" in refusal(FT.read_lmd, [v2])
    assert "no such file or directory" in refusal(FT.read_lmd, [tmp_path / "nothing"])
    (tmp_path / "empty").mkdir()
    assert "no *.parquet feature table" in refusal(FT.read_lmd, [tmp_path / "empty"])
    nan = process_bags_like(lmd["none"], nan_rows=range(len(lmd["none"])))
    only_nan = write(nan, tmp_path / "h" / "x.parquet")
    assert "no row with targets and features" in refusal(FT.read_lmd, [only_nan])


@pytest.fixture(scope="module")
def lms(tmp_path_factory):
    bags = lms_bags(tmp_path_factory.mktemp("ft_lms"), n_sequences=2, n_frames=3)
    return build_dataset(bags, LmsSettings(width=COLUMNS), block_frames=2, quiet=True)


def test_lms_round_trip_gives_the_same_training_arrays_and_groups(lms, tmp_path):
    (path,) = FT.export_tables(lms, tmp_path)
    assert path.name == "lms_points.parquet"
    back = FT.read_lms([path], block_frames=2)
    np.testing.assert_array_equal(back.X, lms.X)
    for k in ("iou", "iou_adj", "segment_class", "size", "size_projected", "sequence",
              "frame", "group", "tp"):
        np.testing.assert_array_equal(getattr(back, k), getattr(lms, k), err_msg=k)
    assert back.names == lms.names and back.sequences == lms.sequences
    assert back.class_names == lms.class_names
    for k in ("settings", "n_frames", "n_excluded", "dropped_undefined", "ignore_label",
              "ring_from", "block_frames"):
        assert back.info[k] == lms.info[k], k
    assert back.info["sources"] == [str(path)]
    assert len(np.unique(FT.read_lms([path], block_frames=1).group)) == 6  # 2 x 3 frames
    # without lq.info (another writer) frames are numbered by their sorted keys
    t = pq.read_table(path)
    meta = {k: v for k, v in t.schema.metadata.items() if k != b"lq.info"}
    other = write(t.replace_schema_metadata(meta), tmp_path / "o" / "x.parquet")
    np.testing.assert_array_equal(FT.read_lms([other], block_frames=2).group, lms.group)
    assert "a lms feature table; lmd-train trains on lmd tables" in refusal(
        FT.read_lmd, [path])


@pytest.fixture(scope="module")
def mimo(tmp_path_factory):
    bags = mimo_bags(tmp_path_factory.mktemp("ft_mimo"), n_sequences=2, n_frames=3, seed=11)
    return mimo_load([bags], progress=False)


def test_mimo_round_trip_gives_the_same_training_arrays(mimo, tmp_path):
    (path,) = FT.export_tables(mimo, tmp_path)
    assert path.name == "mimo_points.parquet"
    back = FT.read_mimo([path])
    for use_points in (False, True):
        X, names = back.features(use_points)
        X0, names0 = mimo.features(use_points)
        np.testing.assert_array_equal(X, X0)
        assert names == names0
    for k in ("m_iou_class", "m_iou_any", "m_score", "m_label", "m_box", "group", "tp"):
        np.testing.assert_array_equal(getattr(back, k), getattr(mimo, k), err_msg=k)
    np.testing.assert_array_equal(back.frame_stamp[back.m_frame], mimo.frame_stamp[mimo.m_frame])
    assert back.summary() == mimo.summary()
    assert back.info["settings"] == mimo.info["settings"]
    # a table without the point features (process_bags, use_points: false)
    t = pq.read_table(path)
    meta = dict(t.schema.metadata)
    names = json.loads(meta[b"lq.feature_names"])[:-5]
    meta.update({b"lq.mode": b"no_points", b"lq.feature_names": json.dumps(names).encode()})
    drop = [f"feat.{n}" for n in ("points", "points_frac", "refl_max", "refl_mean", "refl_std")]
    small = write(t.drop_columns(drop).replace_schema_metadata(meta), tmp_path / "n" / "x.parquet")
    nb = FT.read_mimo([small])
    np.testing.assert_array_equal(nb.features(False)[0], mimo.features(False)[0])
    with pytest.raises(ValueError):
        nb.features(True)
    assert "cannot be mixed" in refusal(FT.read_mimo, [path, small])
