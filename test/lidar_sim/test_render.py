"""BEV rendering of a simulated frame (lidar_sim.render)."""
from __future__ import annotations

import struct
from dataclasses import replace

import numpy as np
import pytest

from lidar_sim import classes as C
from lidar_sim.frames import sequence_frames
from lidar_sim.render import main, render_bev

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def frame():
    return next(sequence_frames(7000, 1))


def _png_size(path):
    blob = path.read_bytes()
    assert blob[:8] == PNG_MAGIC and blob[12:16] == b"IHDR"
    return struct.unpack(">II", blob[16:24]), len(blob)


def _pixels_of(path, cid: int) -> int:
    """Pixels within 1.5/255 of class ``cid``'s colour (markers have no edge to blend)."""
    from matplotlib.image import imread

    img = imread(path)[..., :3]
    return int((np.abs(img - C.colors_rgb(normalized=True)[cid]).max(axis=-1) < 1.5 / 255).sum())


def _only(frame, keep):
    return replace(frame, xyz=frame.xyz[keep], intensity=frame.intensity[keep],
                   ring=frame.ring[keep], semantic=frame.semantic[keep],
                   instance=frame.instance[keep])


def test_render_bev_png_shows_the_cars(frame, tmp_path):
    out = render_bev(frame, tmp_path / "bev.png", extent=40.0, size_px=600)
    (w, h), nbytes = _png_size(out)
    assert (w, h) == (600, 600)
    assert 10_000 < nbytes < 600_000
    car = _pixels_of(out, C.CAR)

    # controls: without car points no pixel has the car colour; with a single car point
    # only its marker and the legend patch do (~170 px at this size)
    none = render_bev(_only(frame, frame.semantic != C.CAR), tmp_path / "none.png",
                      extent=40.0, size_px=600)
    one = render_bev(_only(frame, np.flatnonzero(frame.semantic == C.CAR)[:1]),
                     tmp_path / "one.png", extent=40.0, size_px=600)
    assert _pixels_of(none, C.CAR) == 0
    legend = _pixels_of(one, C.CAR)
    assert 0 < legend < 400
    assert car > legend + 500  # the ~30k car points (measured: ~1500 px)


def test_render_bev_aspect_and_custom_boxes(frame, tmp_path):
    boxes = frame.gt_boxes[:3] + np.array([1.0, 0, 0, 0, 0, 0, 0])
    out = render_bev(frame, tmp_path / "det.png", extent=50.0, y_extent=25.0, size_px=500,
                     boxes=boxes, name="detections")
    (w, h), _ = _png_size(out)
    assert (w, h) == (500, 250)


def test_render_cli(tmp_path, capsys):
    out = tmp_path / "sub" / "cli.png"
    assert main(["--seed", "7000", "--frame", "1", "--frames", "2", "--out", str(out),
                 "--size", "400"]) == 0
    assert _png_size(out)[0] == (400, 400)
    assert "wrote" in capsys.readouterr().out


def test_render_cli_scene_type(tmp_path, capsys):
    out = tmp_path / "suburban.png"
    assert main(["--seed", "7000", "--frames", "1", "--scene", "suburban", "--out", str(out),
                 "--size", "300"]) == 0
    assert _png_size(out)[0] == (300, 300)
    with pytest.raises(SystemExit):
        main(["--scene", "nope", "--out", str(tmp_path / "x.png")])
    assert "invalid choice" in capsys.readouterr().err
