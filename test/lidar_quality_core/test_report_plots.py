"""Report figures are written as PNGs."""
import numpy as np
from lidar_quality_core import report_plots as rp


def _png(path):
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 2000


def test_figures(tmp_path):
    rng = np.random.default_rng(0)
    p = rng.random(500)
    y = (rng.random(500) < p).astype(int)
    assert _png(rp.reliability_png(tmp_path / "r.png", {"a": (y, p), "b": (y, p ** 2)}))
    assert _png(rp.scatter_png(tmp_path / "s.png", p, p + 0.1 * rng.normal(size=500)))
    assert _png(rp.curve_png(tmp_path / "c.png", ["x", "y"], [0.5, 0.7], ylabel="AUROC"))
    assert _png(rp.histogram_png(tmp_path / "h.png", {"lmd": p * 10}, xlabel="ms"))
