"""Simulated frames of a split, optionally cached on disk.

The frames are the same as ``lidar-sim generate`` writes for the split's seed (same
sequence seeds, same noise generator), so a model trained from this source and one trained
from the generated datasets see identical data. The cache (one ``.npz`` per frame) is keyed
by a hash of the simulator's source files: any change to the simulator invalidates it.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import fields
from pathlib import Path
from typing import Iterator

import numpy as np

from .scene import SceneConfig, scene_config
from .sensor import SensorConfig, hdl64
from .sequence import generate_sequence
from .simulate import SimFrame, simulate_frame
from .splits import Split, split as get_split

_ARRAY_FIELDS = [f.name for f in fields(SimFrame) if f.name not in ("sequence", "index", "stamp_ns",
                                                                    "gt_kitti_type")]


#: Modules whose code determines the simulated frames (writers and renderers do not).
SIMULATOR_MODULES = ("classes", "primitives", "scene", "sequence", "raycast", "sensor",
                     "simulate", "splits", "frames")


def simulator_version() -> str:
    """Short hash of the simulator's source (the cache key)."""
    h = hashlib.sha256()
    for p in (Path(__file__).parent / f"{m}.py" for m in SIMULATOR_MODULES):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:12]


def default_cache_dir() -> Path | None:
    """``$LQ_SIM_CACHE`` if set (``""`` disables caching), else ``<repo>/data/cache/sim``
    when running from a source checkout, else no cache."""
    env = os.environ.get("LQ_SIM_CACHE")
    if env is not None:
        return Path(env) if env else None
    repo = Path(__file__).resolve().parents[2]
    return repo / "data" / "cache" / "sim" if (repo / "lidar_sim").is_dir() else None


def _save(path: Path, f: SimFrame) -> None:
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, sequence=f.sequence, index=f.index, stamp_ns=f.stamp_ns,
             gt_kitti_type=np.array(f.gt_kitti_type, dtype=str),
             **{k: getattr(f, k) for k in _ARRAY_FIELDS})
    os.replace(tmp, path)


def _load(path: Path) -> SimFrame:
    with np.load(path) as z:
        return SimFrame(sequence=int(z["sequence"]), index=int(z["index"]),
                        stamp_ns=int(z["stamp_ns"]), gt_kitti_type=tuple(z["gt_kitti_type"].tolist()),
                        **{k: z[k] for k in _ARRAY_FIELDS})


def sequence_frames(seed: int, n_frames: int, *, sequence: int = 0,
                    cfg: SensorConfig | None = None,
                    scene: str | SceneConfig | None = None) -> Iterator[SimFrame]:
    """Simulate the frames of one sequence with scene / noise seed ``seed``.

    ``cfg``: the sensor (default HDL-64); ``scene``: a scene type name of
    :data:`~lidar_sim.scene.SCENE_TYPES` ("street", "suburban"), a ``SceneConfig``, or
    None for the default street (the one the splits use).
    """
    cfg = cfg or hdl64()
    seq = generate_sequence(seed, n_frames, scene_config(scene))
    rng = np.random.default_rng(seed)
    for i in range(n_frames):
        yield simulate_frame(seq.frame(i, max_range=cfg.max_range), cfg, rng, sequence=sequence)


def split_frames(split: Split | str, *, sequences=None, frames: int | None = None,
                 cache_dir: Path | str | None | bool = True) -> Iterator[SimFrame]:
    """Frames of a split (HDL-64), sequence by sequence.

    ``sequences``: indices to produce (default all); ``frames``: frames per sequence
    (default the split's; a prefix of the full sequence only if it equals the split's
    length, because the drive is planned over the sequence length). ``cache_dir``: True
    for :func:`default_cache_dir`, a path, or None / False for no cache.
    """
    sp = get_split(split) if isinstance(split, str) else split
    n = sp.frames if frames is None else int(frames)
    if cache_dir is True:
        cache_dir = default_cache_dir()
    cache = Path(cache_dir) / simulator_version() / f"{sp.seed}_{n}" if cache_dir else None
    for s in (range(sp.sequences) if sequences is None else sequences):
        seed = sp.sequence_seed(s)
        paths = [cache / f"{s:02d}_{i:04d}.npz" for i in range(n)] if cache else None
        if paths and all(p.exists() for p in paths):
            for p in paths:
                yield _load(p)
            continue
        if cache:
            cache.mkdir(parents=True, exist_ok=True)
        for i, f in enumerate(sequence_frames(seed, n, sequence=s)):
            if cache:
                _save(paths[i], f)
            yield f
