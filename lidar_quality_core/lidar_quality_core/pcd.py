"""PCD (Point Cloud Library) files: a minimal reader of ``DATA binary`` v0.7 files, enough
for the real sensor clouds the robustness tests and benchmarks use."""
from __future__ import annotations

from pathlib import Path

import numpy as np

PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4",
             ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4"}


class PCDFormatError(ValueError):
    """A PCD file this reader cannot decode."""


def read_pcd(path: Path | str):
    """``(structured array, layout dtype, raw bytes)`` of a PCD file; the array is
    ``(height, width)`` for organized clouds, else 1-D. Only ``DATA binary``."""
    blob = Path(path).read_bytes()
    header, pos = {}, 0
    while True:
        end = blob.find(b"\n", pos)
        if end < 0:
            raise PCDFormatError(f"{path}: header without a DATA line")
        line = blob[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key] = vals
        if key == "DATA":
            break
    if header["DATA"] != ["binary"]:
        raise PCDFormatError(f"{path}: DATA {header['DATA']} not supported (binary only)")
    try:
        names = header["FIELDS"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        types = [PCD_TYPES[(t, int(s))] for t, s in zip(header["TYPE"], header["SIZE"])]
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        points = int(header["POINTS"][0])
    except (KeyError, ValueError, IndexError) as e:
        raise PCDFormatError(f"{path}: bad header field {e}") from None
    offsets = np.cumsum([0] + [np.dtype(t).itemsize * c for t, c in zip(types, counts)])
    layout = np.dtype({"names": names,
                       "formats": [("<" + t) if c == 1 else ("<" + t, (c,))
                                   for t, c in zip(types, counts)],
                       "offsets": [int(o) for o in offsets[:-1]], "itemsize": int(offsets[-1])})
    if points != width * height:
        raise PCDFormatError(f"{path}: POINTS {points} != WIDTH x HEIGHT {width * height}")
    raw = blob[pos: pos + points * layout.itemsize]
    if len(raw) != points * layout.itemsize:
        raise PCDFormatError(f"{path}: truncated data ({len(raw)} of {points * layout.itemsize} bytes)")
    arr = np.frombuffer(raw, layout)
    return (arr.reshape(height, width) if height > 1 else arr), layout, raw
