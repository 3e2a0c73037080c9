"""LidarMetaSeg per frame: messages -> probabilities -> segment metrics -> meta models ->
output messages (no rclpy).

Shared by ``lms_node`` (through :class:`LmsProcessor`, the node's whole frame callback
body), training and evaluation (through :func:`decode` and :func:`frame_metrics`, so that
a model is trained on exactly the metrics the node computes). Message classes are
imported only when output messages are built.

Input layouts (:func:`decode`)
  One cloud with ``x, y, z``, optionally an intensity field (``intensity``,
  ``reflectance`` or ``i``; without one the intensity metrics read 0), optionally the
  ring field, and one probability field per class named
  ``LmsSettings.field_names()`` (class name with ``-`` / space -> ``_``, as
  ``reference_perception.messages.probability_field``); or two clouds, the points and
  the probabilities, with equal point counts (point i of one is point i of the other).
  A probability field is float32 / float64 (taken as is) or uint8 (quantized:
  value / 255); fields of one cloud may mix both. Float32 fields one after the other
  in the point record (the usual layout) are read in the message, not copied. x, y, z
  are float32 / float64 metres (integer coordinates, in practice mm or cm, are
  refused). Anything else (missing field, count != 1, other dtype, unequal counts)
  raises :class:`CloudFormatError` naming the problem.
Probability checks (per point, vectorized)
  A point whose probabilities hold a non-finite or negative value, or sum to 0, has
  unusable probabilities: it is treated like a point with non-finite coordinates (no
  pixel, no segment, label :data:`NO_LABEL`) and counted in ``n_invalid_points`` (and
  ``n_bad_probabilities``). Usable probabilities whose sum is off 1 by more than
  ``sum_tolerance`` are divided by their sum and counted (``n_renormalized``); for uint8
  input the tolerance is widened by the quantization bound n * 0.5 / 255 (each rounded
  value may be off by half a step), so correctly quantized softmax outputs are not
  flagged.
Image geometry
  ``sensor`` selects a preset of ``config/sensors.yaml`` (or ``sensors_file``): its beam
  elevation table (one row per beam) and width (360 deg / the azimuth resolution at 10 Hz)
  replace ``channels``, ``width``, ``fov_up_deg`` / ``fov_down_deg`` and
  ``beam_elevations_deg`` (:meth:`LmsSettings.resolved`). Without a preset, a
  ``beam_elevations_deg`` table gives one row per beam; without either, ``channels`` equal
  rows from ``fov_up_deg`` down to ``fov_down_deg``.
Ring
  With ``use_ring`` the ring (beam index) field is the first of ``ring_field`` (``auto``:
  ring, channel, laser_id, laser_number, laser, beam, beam_id, line, scan_line; or a
  comma-separated list) that the cloud has. ``beam_rows`` says how it gives the row:
  ``index``: ``row = channels - 1 - ring`` (Velodyne drivers number ring 0 = lowest beam,
  our row 0 is the top) unless ``ring_zero_top`` (``lidar_sim`` and Ouster: ring 0 = top);
  ``elevation``: each beam index's median elevation, estimated from the clouds and kept by
  the processor (:class:`lidar_quality_core.lms.beams.BeamTable`), gives the row of the
  elevation table that holds it, or without a table the beam's rank (highest = row 0), so
  that any numbering works (nebula's laser order, bottom-up, top-down); ``auto``
  (default): ``elevation`` with a preset or a table, else ``index`` (as before issue 16).
  Without a ring field the row is the elevation bin of the point. A ring field that is not
  an integer beam index (a float / multi-value field, or a value outside ``[0, channels)``
  (index) / ``[0, MAX_CHANNELS)`` (elevation) at a valid point) is not used: the frame takes
  the elevation rows and the processor reports it (issue ``"ring"``). Chosen over
  dropping the frame or the out-of-range points: the frame still gets segments and
  confidences over all its points, and the warning names the setting to fix.
  ``LmsSettings.validate`` refuses a ``ring_field`` naming x, y, z or an intensity field.
Invalid points
  Non-finite coordinates and exact (0, 0, 0) (the padding of organized Ouster-style
  clouds, :func:`lidar_quality_core.pointcloud.valid_points`) take no pixel and enter no
  segment or metric; counted in ``points.invalid`` (the zeros also in ``points.padding``).
Points without a pixel
  Every point without a segment is counted once (:func:`point_accounting`):
  ``points.invalid``, ``points.unprojected`` (a valid point outside the image: above or
  below the vertical field of view, or a beam without a row) or ``points.occluded`` (it
  lost its pixel to a nearer point and no 8-neighbour pixel of its class gave it a
  segment). The share of the valid points without a pixel (unprojected + occluded) is the
  per-frame value ``points.no_pixel_ratio``: above ``no_pixel_warn_ratio`` the frame
  warns (issue ``"unprojected"``), above ``no_pixel_error_ratio`` at ERROR; the frame is
  published either way.
Outputs (:class:`LmsProcessor`)
  ``output/points``: the input points in the input order and layout (height / width),
  fields :data:`OUTPUT_FIELDS`: ``x, y, z`` (float32, as received),
  ``label`` (uint16 predicted class = argmax, lowest class on ties, for every point with
  usable probabilities, with or without a pixel or a segment; :data:`NO_LABEL` for
  unusable probabilities), ``segment`` (int32, -1: no segment: invalid point (non-finite,
  (0, 0, 0) padding, unusable probabilities), outside the image, or no pixel of its class
  around it),
  ``confidence`` (float32, P(IoU_adj > 0) of its segment) and ``predicted_iou``
  (float32, predicted IoU_adj), both NaN for points without a segment or in a segment
  excluded from the meta models (SP < ``min_segment_points``). With ``all_fields``
  (``output_all_fields``) every other field of ``input/points`` comes first, as received
  (intensity, ring, probabilities, ...).
  ``output/segments``: every segment (kept or not) in id order: id, class, point count,
  SP, confidence and predicted IoU (NaN when excluded); for the frame the message version
  and the drift check's verdict (level, window score, frames, most drifted metrics,
  passthrough: ``DomainVerdict.message_fields``).
  ``output/markers`` (optional): centroids of the kept segments coloured by confidence.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_quality_core.cloud_cdr import decode_point_cloud, serialized_cloud
from lidar_quality_core.domain_profile import DomainCheck, DomainVerdict, DriftParameters
from lidar_quality_core.conventions import probability_field
from lidar_quality_core.intensity import IntensityScale, intensity_scale_param
from lidar_quality_core.meta_model import MetaModels, model_path_param
from lidar_quality_core.model_store import models_dir
from lidar_quality_core.parameters import group, param
from lidar_quality_core.segment_quality_cdr import encode_segment_quality_array
from lidar_quality_core.pointcloud import (CloudFormatError, PaddingNote, check_xyz_fields,
                                            cloud_to_structured, field_run_view, finite_mask,
                                            pack_cloud, valid_points,
                                            xyz_columns)
from lidar_quality_core.lms import beams, segment_metrics
from lidar_quality_core.lms.point_results import (RESULT_LAYOUT, pack_point_results,
                                                  result_layout, segment_table)
from lidar_quality_core.lms.projection import RangeImageConfig
from lidar_quality_core.lms.segment_metrics import SegmentResult, compute_segments

__all__ = ["CLASS_NAMES", "NO_LABEL", "INTENSITY_FIELDS", "MAX_CHANNELS", "MAX_WIDTH",
           "MAX_PIXELS", "LmsSettings", "LmsInput",
           "decode", "frame_metrics", "default_model_paths", "LmsParameters", "load_models",
           "probability_field",
           "LmsOutputs", "LmsProcessor", "OUTPUT_FIELDS", "RESULT_FIELDS", "geometry_mismatch",
           "point_accounting", "sensor_presets", "shipped_sensors_file"]

#: The reference segmenter's classes (``lidar_sim.classes.CLASS_NAMES``, copied: this
#: package must not need the simulator at run time; a test checks they agree).
CLASS_NAMES: tuple[str, ...] = (
    "unlabeled", "road", "sidewalk", "terrain", "building", "fence", "vegetation", "trunk",
    "pole", "traffic-sign", "car", "truck", "pedestrian", "cyclist")

#: ``label`` of a point whose probabilities are unusable.
NO_LABEL = 65535
INTENSITY_FIELDS = ("intensity", "reflectance", "i")

#: Fields of ``output/points`` in order (name, dtype) (``all_fields``: the input's before
#: the last four).
OUTPUT_FIELDS = tuple((nm, dt) for nm, dt, _ in RESULT_LAYOUT)
#: The per-point results among them.
RESULT_FIELDS = tuple(nm for nm, _ in OUTPUT_FIELDS[3:])


#: Range image bounds of :meth:`LmsSettings.validate` (see ``_LIMIT_WHY``).
MAX_CHANNELS = 1024
MAX_WIDTH = 36000
MAX_PIXELS = 1 << 22
_LIMIT_WHY = {
    "channels": "one image row per beam, and the largest lidars have a few hundred",
    "width": "360 deg / width is the column resolution, and 36000 columns are 0.01 deg, "
             "finer than any scanning lidar",
    "pixels": "a frame needs ~150 bytes per pixel (measured: ~600 MB and seconds of work "
              "at this bound), so far larger images fail every frame with MemoryError",
}


def shipped_sensors_file() -> Path:
    """``config/sensors.yaml`` of lms_ros: the installed share directory, else the source
    tree (a workspace that was not installed)."""
    try:
        from ament_index_python.packages import get_package_share_directory

        p = Path(get_package_share_directory("lms_ros")) / "config" / "sensors.yaml"
        if p.is_file():
            return p
    except Exception:  # noqa: BLE001 - no ament index: the source tree
        pass
    return Path(__file__).resolve().parents[1] / "config" / "sensors.yaml"


@functools.lru_cache(maxsize=8)
def sensor_presets(path: str = "") -> dict[str, beams.SensorPreset]:
    """The sensor presets of ``path`` (empty: :func:`shipped_sensors_file`)."""
    return beams.load_presets(path or shipped_sensors_file())


@dataclass(frozen=True)
class LmsSettings:
    """Metric settings; a model is valid only for the class map it was trained with (its
    feature schema is :meth:`metric_names`). Fields made with ``param`` are lms_node's
    parameters (declared from here)."""

    class_names: tuple = param(
        list(CLASS_NAMES), "Class map: class c (the models' class order) reads the probability "
        "field named class_names[c] with '-' and ' ' replaced by '_'.")
    sensor: str = param(
        "", "Sensor preset (config/sensors.yaml or sensors_file: VLP-16, VLP-32C, HDL-32E, "
        "HDL-64E, VLS-128, Pandar40P, Pandar64, PandarXT16, PandarXT32, PandarXT32M, "
        "PandarQT64, PandarQT128, OT128, AT128, OS1-64, OS1-128, OS2-64, OS2-128): its beam "
        "elevation table and width replace channels, width, fov_up_deg, fov_down_deg and "
        "beam_elevations_deg; empty: those parameters.")
    sensors_file: str = param(
        "", "YAML file of sensor presets (the format of config/sensors.yaml); empty: the "
        "shipped config/sensors.yaml.")
    channels: int = param(64, "Range image rows (sensor beams).", min_value=1)
    fov_up_deg: float = param(
        3.0, "Upper edge of the vertical field of view [deg] (rows from elevation when the "
        "cloud has no ring field).", min_value=-90.0, max_value=90.0)
    fov_down_deg: float = param(
        -25.0, "Lower edge of the vertical field of view [deg], below fov_up_deg.",
        min_value=-90.0, max_value=90.0)
    beam_elevations_deg: tuple = param(
        "", "Per-beam elevation table [deg], comma-separated, any order (sensors with "
        "non-uniform beams): one image row per beam, replacing channels and the uniform "
        "fov_up_deg / fov_down_deg rows; empty: uniform rows.",
        to_field=lambda v: beams.parse_degrees(v),
        to_param=lambda v: ", ".join(f"{x:g}" for x in v))
    width: int = param(2048, "Range image columns = 360 deg / horizontal resolution.",
                       min_value=1)
    use_ring: bool = param(True, "Take the image row from the cloud's ring field when it has one.")
    ring_zero_top: bool = param(
        False, "Ring 0 is the top beam (Ouster, lidar_sim); false: ring 0 is the lowest beam "
        "(Velodyne drivers). Read by beam_rows index only.")
    ring_field: str = param(
        "auto", "Name of the ring (beam index) field, or comma-separated names tried in order; "
        "auto: ring, channel, laser_id, laser_number, laser, beam, beam_id, line, scan_line.")
    beam_rows: str = param(
        "auto", "How a ring field gives the image row: index (row = ring, flipped unless "
        "ring_zero_top), elevation (each beam's median elevation, estimated from the clouds "
        "and kept: the row of the elevation table holding it, or without a table the beam's "
        "rank, highest beam = row 0: any beam numbering), auto (elevation with a sensor "
        "preset or beam_elevations_deg, else index).",
        choices=("auto", "index", "elevation"))
    min_segment_points: int = param(
        10, "Segments with fewer projected points (SP) get no confidence (NaN); the models "
        "must be trained with the same value.", min_value=1)
    sum_tolerance: float = param(
        0.02, "Per-point probabilities summing outside 1 +- this are renormalized (with a "
        "warning); uint8 input adds the quantization bound n * 0.5 / 255.",
        min_value=0.0, max_value=0.999)
    no_pixel_warn_ratio: float = param(
        0.05, "Share of a frame's valid points without a pixel (outside the image, or losing "
        "their pixel to a nearer point and left without a segment) above which the frame "
        "warns (issue 'unprojected', /diagnostics WARN); the frame is still published.",
        min_value=0.0, max_value=1.0)
    no_pixel_error_ratio: float = param(
        0.25, "... above which /diagnostics reports ERROR (>= no_pixel_warn_ratio): the image "
        "does not fit the sensor (set sensor, or channels / width / the field of view).",
        min_value=0.0, max_value=1.0)
    intensity_scale: str = intensity_scale_param(
        "the intensity metrics (output/points with output_all_fields keeps the input's "
        "values)")

    def preset(self) -> beams.SensorPreset | None:
        """The selected sensor preset, or None; ``ValueError`` for an unknown name."""
        if not self.sensor:
            return None
        presets = sensor_presets(self.sensors_file)
        if self.sensor not in presets:
            raise ValueError(f"sensor {self.sensor!r} is not a preset of "
                             f"{self.sensors_file or 'config/sensors.yaml'} (known: "
                             f"{', '.join(presets)}); add it there or leave sensor empty")
        return presets[self.sensor]

    def resolved(self) -> "LmsSettings":
        """These settings with the image geometry in force: a preset's (``sensor``) or the
        beam table's rows in ``channels``, ``beam_elevations_deg`` (top first), ``width``
        and the outer bin edges in ``fov_up_deg`` / ``fov_down_deg`` (what the models'
        recorded geometry is compared with)."""
        p = self.preset()
        table = p.elevations_deg if p else tuple(sorted(self.beam_elevations_deg, reverse=True))
        if not table:
            return self
        cfg = RangeImageConfig.from_elevations(table, p.width if p else self.width)
        e = cfg.row_edges_deg
        return dataclasses.replace(self, channels=cfg.rows, width=cfg.cols,
                                   beam_elevations_deg=cfg.elevations_deg,
                                   fov_up_deg=round(float(e[0]), 4),
                                   fov_down_deg=round(float(e[-1]), 4))

    def has_table(self) -> bool:
        """The rows follow a beam elevation table (a preset or beam_elevations_deg)."""
        return bool(self.sensor or self.beam_elevations_deg)

    def rows_by_elevation(self) -> bool:
        """A ring field's beams take their rows from their elevations (``beam_rows``)."""
        return self.beam_rows == "elevation" or (self.beam_rows == "auto" and self.has_table())

    def range_config(self) -> RangeImageConfig:
        r = self.resolved()
        if r.beam_elevations_deg:
            return RangeImageConfig.from_elevations(r.beam_elevations_deg, r.width)
        return RangeImageConfig.uniform(r.channels, r.width, r.fov_up_deg, r.fov_down_deg)

    def metric_names(self) -> tuple[str, ...]:
        """The feature schema of the meta models (86 + 2n names)."""
        return segment_metrics.metric_names(len(self.class_names), self.class_names)

    def field_names(self) -> tuple[str, ...]:
        """Probability field of each class, in class order."""
        return tuple(probability_field(c) for c in self.class_names)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad setting."""
        names = self.class_names
        if isinstance(names, str) or len(names) < 1 or not all(
                isinstance(c, str) and c for c in names):
            raise ValueError(f"class_names must be a non-empty list of non-empty names, "
                             f"got {names!r}")
        fields = self.field_names()
        if len(set(fields)) != len(fields):
            raise ValueError(f"class_names give duplicate probability fields: {fields}")
        try:
            ring_names = beams.ring_field_names(self.ring_field)
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        bad = set(ring_names) & ({"x", "y", "z"} | set(INTENSITY_FIELDS))
        if self.use_ring and bad:
            raise ValueError(
                f"ring_field {self.ring_field!r} names a coordinate / intensity field "
                f"({', '.join(sorted(bad))}), not the beam index: every frame would fall back "
                "to elevation rows (set ring_field to the cloud's ring field, e.g. ring, "
                "auto, or use_ring: false)")
        explicit = () if ring_names == beams.RING_FIELD_NAMES else ring_names
        clash = set(fields) & ({"x", "y", "z"} | set(explicit) | set(INTENSITY_FIELDS))
        if clash:
            raise ValueError(f"class_names clash with point fields: {sorted(clash)}")
        if self.beam_rows not in ("auto", "index", "elevation"):
            raise ValueError(f"beam_rows must be auto, index or elevation, got "
                             f"{self.beam_rows!r}")
        for name in ("no_pixel_warn_ratio", "no_pixel_error_ratio"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v <= 1):
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.no_pixel_error_ratio < self.no_pixel_warn_ratio:
            raise ValueError(f"no_pixel_error_ratio {self.no_pixel_error_ratio} is below "
                             f"no_pixel_warn_ratio {self.no_pixel_warn_ratio}")
        try:
            table = tuple(self.beam_elevations_deg)
            beams.parse_degrees(table)
            if len(set(table)) != len(table):
                raise ValueError("two beams at the same elevation")
            geo = self.resolved()       # an unknown sensor / unreadable presets file raise
        except (ValueError, OSError) as exc:
            raise ValueError(f"sensor / beam_elevations_deg: {exc}") from None
        for name, top in (("channels", MAX_CHANNELS), ("width", MAX_WIDTH)):
            # the width as given unless a preset sets it (resolving casts it to int)
            v = getattr(self if name == "width" and not self.sensor else geo, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
            if v > top:
                raise ValueError(f"{name} must be <= {top}, got {v}: {_LIMIT_WHY[name]}")
        if geo.channels * geo.width > MAX_PIXELS:
            raise ValueError(
                f"channels x width = {geo.channels} x {geo.width} = "
                f"{geo.channels * geo.width} pixels exceeds {MAX_PIXELS}: "
                f"{_LIMIT_WHY['pixels']}")
        up, down = geo.fov_up_deg, geo.fov_down_deg
        if not (math.isfinite(up) and math.isfinite(down) and -90 <= down < up <= 90):
            raise ValueError(f"need -90 <= fov_down_deg < fov_up_deg <= 90, got "
                             f"fov_up_deg={up}, fov_down_deg={down}")
        m = self.min_segment_points
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise ValueError(f"min_segment_points must be an integer >= 1, got {m!r}")
        if not (math.isfinite(self.sum_tolerance) and 0 <= self.sum_tolerance < 1):
            raise ValueError(f"sum_tolerance must be in [0, 1), got {self.sum_tolerance}")


@dataclass
class LmsInput:
    """One decoded frame. ``xyz`` is the transposed view of a coordinate-major (3, N)
    float32 array (one contiguous array per coordinate: what :func:`compute_segments` and
    the output read fastest); ``probs`` (N, n) the message's own float32 fields where they
    lie one after the other in each point (read in place, not copied), else the transposed
    view of a class-major (n, N) copy."""

    xyz: np.ndarray                   # (N, 3) float32, as received
    intensity: np.ndarray | None      # (N,) float32; None: the cloud has none
    ring: np.ndarray | None           # (N,) int32 image row (flipped unless ring_zero_top)
    probs: np.ndarray                 # (N, n) float32, checked and renormalized: a
                                      # read-only view into the message (float32 fields
                                      # in a run, none changed) or class-major, transposed
    n_renormalized: int               # points whose probabilities were renormalized
    n_invalid_points: int             # non-finite or (0, 0, 0) coordinates, or unusable
                                      # probabilities
    valid: np.ndarray = field(repr=False, default=None)   # (N,) bool: neither of those
    n_bad_probabilities: int = 0      # unusable probabilities (part of n_invalid_points)
    quantized: bool = False           # some probability field was uint8
    shape: tuple = ()                 # (height, width) of the points cloud
    ring_issue: str | None = None     # why the cloud's ring field was not used (rows from
                                      # elevation), None when it was or there is none
    n_padding: int = 0                # finite points at exactly (0, 0, 0): organized-cloud
                                      # padding (part of n_invalid_points)
    ring_field: str | None = None     # the ring field found in the cloud
    dispersion: tuple | None = field(repr=False, default=None)  # (argmax, E, D, V) of
                                      # probs when decode took them (segment_metrics);
                                      # whoever changes probs afterwards sets it None
    cloud: np.ndarray | None = field(repr=False, default=None)   # input/points as decoded
                                      # (structured, (N,) or (H, W))

    def __len__(self) -> int:
        return len(self.xyz)


def _xyz_intensity(arr: np.ndarray):
    """``(xyz, intensity or None, valid points, padding points)``: ``xyz`` (N, 3) float32,
    the transposed view of a (3, N) copy (compute_segments and the output read its
    columns); ``valid`` as ``pointcloud.valid_points``."""
    fields = arr.dtype.fields or {}
    check_xyz_fields(arr.dtype, "input/points")
    cols = xyz_columns(arr)
    if cols is not None:
        xyz, points_ok, n_padding = cols
    else:   # float64 (or mixed) coordinates
        xyz = np.empty((3, arr.size), np.float32)
        _gather(arr.reshape(-1), "xyz", xyz)
        xyz = xyz.T
        points_ok = valid_points(xyz)
        n_padding = int(np.count_nonzero(finite_mask(xyz) & ~points_ok))
    inten_name = next((nm for nm in INTENSITY_FIELDS if nm in fields), None)
    if inten_name is None:
        return xyz, None, points_ok, n_padding
    if fields[inten_name][0].shape or fields[inten_name][0].kind not in "fiu":
        raise CloudFormatError(f"intensity field {inten_name!r} must be one numeric value "
                               "per point")
    return (xyz, np.asarray(arr[inten_name], dtype=np.float32).reshape(-1), points_ok,
            n_padding)


def _ring(arr: np.ndarray, xyz: np.ndarray, valid: np.ndarray, settings: LmsSettings,
          table: beams.BeamTable | None) -> tuple[np.ndarray | None, str | None, str | None]:
    """(image row of each point or None, why the ring field was not used or None, the ring
    field's name or None). A ring field that is not an integer beam index in range (at the
    valid points) leaves the frame to the elevation rows, with the reason. ``settings``
    resolved (:meth:`LmsSettings.resolved`)."""
    fields = arr.dtype.fields or {}
    name = beams.find_ring_field(fields, settings.ring_field) if settings.use_ring else None
    if name is None:
        return None, None, None
    dt = fields[name][0]
    fix = ("rows from elevation for this frame (set ring_field to the beam index field, "
           "channels to the beam count, or use_ring: false)")
    if dt.shape or dt.kind not in "iu":
        what = f"count {dt.shape[0]}" if dt.shape else str(dt.base)
        return None, (f"ring field {name!r} ({what}) is not one integer beam index per "
                      f"point: {fix}"), name
    # one pass over the message's records: the checks below read a contiguous copy
    wide = dt.itemsize > 4 or dt == np.uint32
    raw = np.asarray(arr[name]).reshape(-1).astype(np.int64 if wide else np.int32)
    by_elevation = settings.rows_by_elevation()
    C = settings.channels
    top, what = (MAX_CHANNELS, "beam indices") if by_elevation else (C, "channels")
    if raw.size and (raw.min() < 0 or raw.max() >= top):
        out = valid & ((raw < 0) | (raw >= top))
        n_out = int(np.count_nonzero(out))
        if n_out:  # a sentinel ring on NaN points (no return) is no problem
            lo, hi = int(raw[valid].min()), int(raw[valid].max())
            return None, (f"ring field {name!r} holds {lo}..{hi} at finite points ({n_out} of "
                          f"{int(np.count_nonzero(valid))} outside [0, {what}={top})): "
                          f"{fix}"), name
    if not by_elevation:
        ring = raw.astype(np.int32, copy=False)
        if not settings.ring_zero_top:
            np.subtract(np.int32(C - 1), ring, out=ring)
        return ring, None, name
    el = beams.elevation_deg(xyz)
    el[~valid] = np.nan
    beam = np.where(valid, raw, 0).astype(np.int64)
    table = beams.BeamTable(MAX_CHANNELS) if table is None else table
    table.update(beam, el)
    cfg = settings.range_config() if settings.has_table() else None
    row = table.rows(cfg, C)[beam]
    if cfg is not None:
        # a beam not estimated yet (too few points so far): the point's own elevation bin
        late = valid & (row < 0)
        if late.any():
            row[late] = beams.elevation_rows(el[late], cfg)
    row[~valid] = -1
    return row, None, name


def _probabilities(arr: np.ndarray, names, source: str
                   ) -> tuple[np.ndarray, bool, np.ndarray, np.ndarray, tuple | None]:
    """(N, n) float32 probabilities, whether any field was uint8, per point their sum and
    minimum, and their dispersion or None. Float32 fields one after the other (the usual
    layout) are read in place: a read-only (N, n) view into the message
    (``field_run_view``), the sums taken in the pass of their dispersion
    (``segment_metrics.dispersion``: the metrics' per-point values); any other layout is
    gathered (``_gather``, the sums during the gather) into a class-major copy, returned
    transposed, the dispersion left to the metrics."""
    fields = arr.dtype.fields or {}
    missing = [nm for nm in names if nm not in fields]
    if missing:
        raise CloudFormatError(
            f"probability field(s) {', '.join(missing)} not in {source} (expected one "
            f"field per class: {', '.join(names)}); available fields: "
            f"{', '.join(arr.dtype.names or ()) or '(none)'}")
    quantized = False
    for nm in names:
        dt = fields[nm][0]
        if dt.shape:
            raise CloudFormatError(f"probability field {nm!r} has count {dt.shape[0]}, "
                                   "expected 1")
        if dt.kind == "u" and dt.itemsize == 1:
            quantized = True
        elif dt.kind != "f":
            raise CloudFormatError(f"probability field {nm!r} has type {dt}: expected "
                                   "float32/float64 or uint8 (value / 255)")
    # (no class: a zero sum, so that no point is usable)
    total, smallest = np.zeros(arr.size, np.float32), np.full(arr.size, np.inf, np.float32)
    view = None if quantized else field_run_view(arr, names)
    if view is not None:
        disp = segment_metrics.dispersion(view, sums=(total, smallest))
        return view, quantized, total, smallest, disp
    out = np.empty((len(names), arr.size), np.float32)
    _gather(arr.reshape(-1), names, out, sums=(total, smallest))
    return out.T, quantized, total, smallest, None


def _gather(flat: np.ndarray, names, out: np.ndarray, block: int = 4096, sums=None) -> None:
    """``out[c] = flat[names[c]]`` as float32 (uint8 fields / 255), block by block of
    points: the columns of one block share the cache lines of its records (one pass over
    the message instead of one per field: ~1.5x faster). ``sums``: ``(total, smallest)``
    (N,) float32, filled with ``out.sum(axis=0)`` and ``out.min(axis=0)`` block by block
    while the block is in cache (numpy's own reductions of the block's columns: the same
    bits; over the whole array afterwards they read it from memory twice more)."""
    cols = [flat[nm] for nm in names]
    scale = [np.float32(255.0) if col.dtype.kind == "u" and col.dtype.itemsize == 1
             else None for col in cols]
    for b0 in range(0, len(flat), block):
        b1 = b0 + block
        for c, col in enumerate(cols):
            if scale[c] is None:
                out[c, b0:b1] = col[b0:b1]
            else:
                np.divide(col[b0:b1], scale[c], out=out[c, b0:b1])
        if sums is not None and len(cols):
            blk = out[:, b0:b1]
            np.add.reduce(blk, axis=0, out=sums[0][b0:b1])
            np.minimum.reduce(blk, axis=0, out=sums[1][b0:b1])


def decode(points_msg, settings: LmsSettings, probabilities_msg=None,
           beam_table: beams.BeamTable | None = None) -> LmsInput:
    """Points and checked probabilities of one frame (see the module doc); raises
    :class:`CloudFormatError` for an unusable input. ``beam_table``: the per-beam
    elevations kept across frames (``beam_rows: elevation``; None: this frame's only)."""
    settings = settings.resolved()
    arr = cloud_to_structured(points_msg)
    xyz, intensity, points_ok, n_padding = _xyz_intensity(arr)
    N = len(xyz)
    ring, ring_issue, ring_name = _ring(arr, xyz, points_ok, settings, beam_table)
    if probabilities_msg is None:
        probs, quantized, s, smallest, disp = _probabilities(arr, settings.field_names(),
                                                             "input/points")
    else:
        parr = cloud_to_structured(probabilities_msg)
        if parr.size != N:
            raise CloudFormatError(f"input/probabilities has {parr.size} points, "
                                   f"input/points {N}: they must match point for point")
        probs, quantized, s, smallest, disp = _probabilities(parr, settings.field_names(),
                                                             "input/probabilities")
    n = probs.shape[1]
    if N:
        with np.errstate(invalid="ignore", over="ignore"):
            # s, smallest: the probabilities' sum and minimum per point
            usable = np.isfinite(s)            # NaN / inf anywhere makes the sum so
            usable &= s > 0
            usable &= smallest >= 0
            tol = settings.sum_tolerance + (n * 0.5 / 255.0 if quantized else 0.0)
            renorm = np.abs(s - np.float32(1.0)) > np.float32(tol)
        renorm &= usable
        n_renorm = int(np.count_nonzero(renorm))
        bad = ~usable
        n_bad = int(np.count_nonzero(bad))
        if n_renorm or n_bad:
            disp = None                                 # of probabilities about to change
            if not (probs.flags.f_contiguous and probs.flags.writeable):
                probs = np.ascontiguousarray(probs.T).T     # a view into the message: a copy
        probs_cm = probs.T
        if n_renorm:
            idx = np.flatnonzero(renorm)
            probs_cm[:, idx] /= s[idx]
        if n_bad:
            probs_cm[:, bad] = 0.0
        valid = usable
        valid &= points_ok
    else:
        n_renorm = n_bad = 0
        valid = np.zeros(0, bool)
    shape = tuple(arr.shape) if arr.ndim == 2 else (1, N)
    return LmsInput(xyz=xyz, intensity=intensity, ring=ring, probs=probs, dispersion=disp,
                    n_renormalized=n_renorm, n_invalid_points=int(N - np.count_nonzero(valid)),
                    valid=valid, n_bad_probabilities=n_bad, quantized=quantized, shape=shape,
                    ring_issue=ring_issue, n_padding=n_padding, ring_field=ring_name,
                    cloud=arr)


def frame_metrics(inp: LmsInput, settings: LmsSettings,
                  intensity: IntensityScale | None = None) -> SegmentResult:
    """:func:`compute_segments` of a decoded frame with the settings' image; points with
    unusable probabilities are left out of the image like non-finite ones. The intensity
    metrics read the intensity in [0, 1]: ``intensity`` is the stream's ``IntensityScale``
    (None: a new one of ``settings.intensity_scale``, deciding on this frame alone)."""
    xyz = inp.xyz
    if inp.n_invalid_points:
        xyz = xyz.copy()
        xyz[~inp.valid] = np.nan
    inten = inp.intensity
    if inten is not None:
        scale = intensity if intensity is not None else IntensityScale(settings.intensity_scale)
        inten = scale.scale(inten[inp.valid] if inp.n_invalid_points else inten)
        if inp.n_invalid_points:   # decided on the valid points only
            full = np.zeros(len(inp), np.float32)
            full[inp.valid] = inten
            inten = full
    return compute_segments(xyz, inp.probs, settings.range_config(), ring=inp.ring,
                            intensity=inten, min_points=settings.min_segment_points,
                            class_names=settings.class_names,
                            point_dispersion=inp.dispersion)


def default_model_paths() -> tuple[Path, Path]:
    """The shipped models: ``models/lms/lms_classifier.joblib``, ``lms_regressor.joblib``."""
    d = models_dir() / "lms"
    return d / "lms_classifier.joblib", d / "lms_regressor.joblib"


@dataclass(frozen=True)
class LmsParameters:
    """Every parameter of lms_node besides the common ones (``QualityNode``)."""

    settings: LmsSettings = group(LmsSettings())
    separate_probabilities: bool = param(
        False, "Take the probabilities from a second cloud on input/probabilities (same "
        "points, same order, matched by stamp) instead of fields of input/points.")
    output_all_fields: bool = param(
        False, "output/points carries every field of input/points (probabilities included) "
        "besides the four results; false: x, y, z and the results only (a viewer's needs, "
        "about a third of the bytes of a 14-class float32 input).")
    publish_markers: bool = param(
        True, "Publish output/markers (segment centroids coloured by confidence; built only "
        "while someone subscribes).")
    drift: DriftParameters = group(DriftParameters())
    classifier_path: str = model_path_param(
        "classifier", "confidence", "models/lms/lms_classifier.joblib")
    regressor_path: str = model_path_param(
        "regressor", "predicted IoU_adj", "models/lms/lms_regressor.joblib")


def load_models(params: LmsParameters, warn=None) -> MetaModels:
    """The meta models of ``params`` (the shipped pair unless paths are set), checked
    against the metric schema and the recorded training settings; ``RuntimeError`` saying
    what and why otherwise."""
    s = params.settings.resolved()
    dc, dr = default_model_paths()
    names = s.metric_names()
    try:
        return MetaModels(params.classifier_path or str(dc), params.regressor_path or str(dr),
                          names, settings=s, method="lms", warn=warn)
    except Exception as exc:  # noqa: BLE001 - any load failure refuses the start
        hint = (" (class_names must be the class map the models were trained with)"
                if "schema" in str(exc) else "")
        raise RuntimeError(
            f"cannot load the LMS meta models for {len(s.class_names)} classes "
            f"({len(names)} metrics): {exc}{hint}") from exc


_GEOMETRY = ("channels", "width", "fov_up_deg", "fov_down_deg")


def geometry_mismatch(models, settings: LmsSettings) -> str | None:
    """How the image geometry the models were trained on (their manifests' recorded
    settings) differs from ``settings`` (resolved), e.g. ``"trained 64 x 2048, fov 3 ..
    -25 deg; running 16 x 1800, fov 16 .. -16 deg"``; None when it does not or the
    manifests do not record it."""
    rec = None
    for m in (getattr(models, "classifier", None), getattr(models, "regressor", None)):
        r = ((getattr(m, "manifest", None) or {}).get("training_data") or {}).get("settings")
        if isinstance(r, dict) and all(k in r for k in _GEOMETRY):
            rec = r
            break
    if rec is None:
        return None
    s = settings.resolved()
    if all(math.isclose(float(rec[k]), float(getattr(s, k)), abs_tol=1e-6) for k in _GEOMETRY):
        return None

    def show(v):
        return (f"{int(v['channels'])} x {int(v['width'])}, fov {float(v['fov_up_deg']):g} .. "
                f"{float(v['fov_down_deg']):g} deg")
    return f"trained {show(rec)}; running {show({k: getattr(s, k) for k in _GEOMETRY})}"


# -- the node's frame work -----------------------------------------------------------------


def _per_point(res: SegmentResult, per_segment) -> np.ndarray:
    """(N,) float32 value of each point's segment (``per_segment``: n_segments values,
    NaN for excluded segments), NaN for points without one: ``segment_metrics.to_points`` as
    one gather (segment -1 reads the table's last row, NaN)."""
    return segment_table(per_segment)[res.point_segment]


@dataclass
class LmsOutputs:
    """Everything one frame produces. ``confidence`` / ``predicted_iou`` per segment
    (n_segments, NaN for excluded segments)."""

    inp: LmsInput
    result: SegmentResult
    confidence: np.ndarray
    predicted_iou: np.ndarray
    points_cdr: np.ndarray   # output/points as published: serialized PointCloud2 (uint8)
    segments_cdr: bytes      # output/segments as published: serialized SegmentQualityArray
    markers: object | None   # visualization_msgs/MarkerArray
    issues: dict             # key -> message of a throttled warning
    errors: frozenset = frozenset()   # keys of ``issues`` at /diagnostics level ERROR
    accounting: dict = field(default_factory=dict)   # point_accounting
    notes: list = field(default_factory=list)        # decisions to log once (info)
    intensity_scale: str | None = None               # the scale the metrics read
    drift: dict = field(default_factory=dict)        # the drift check's values
    #: builds ``segments`` (the same SegmentQualityArray as a message) when first asked
    build_segments: object = field(default=None, repr=False, compare=False)

    @functools.cached_property
    def points(self):
        """``output/points`` read back from ``points_cdr`` (what the node publishes) as
        ``cloud_cdr.DecodedCloud``: the fields of a PointCloud2, read by ``pointcloud``
        as a message is."""
        return decode_point_cloud(self.points_cdr.tobytes())

    @functools.cached_property
    def segments(self):
        """``output/segments`` as a lidar_quality_msgs/SegmentQualityArray message (built
        on first use: the node publishes ``segments_cdr``, the same message's bytes)."""
        return self.build_segments()

    @property
    def messages(self) -> dict:
        return {"output/points": self.points_cdr, "output/segments": self.segments_cdr}

    @property
    def counts(self) -> dict:
        """Per-frame increments (summed into /diagnostics). Every point without a segment
        (``points.no_segment``) is in exactly one of ``points.invalid`` (of which
        ``points.padding``), ``points.unprojected`` and ``points.occluded``."""
        res, inp = self.result, self.inp
        a = self.accounting
        return {"points.in": len(inp), "points.invalid": inp.n_invalid_points,
                "points.padding": inp.n_padding,
                "points.unprojected": a["unprojected"], "points.occluded": a["occluded"],
                "points.no_segment": a["no_segment"],
                "points.renormalized": inp.n_renormalized, "segments": res.n_segments,
                "segments.scored": len(res.kept_ids)}

    @property
    def values(self) -> dict:
        """Per-frame diagnostics values (set, not summed): the shares of the frame's valid
        points without a pixel (``unprojected``: outside the image; ``occluded``: lost
        their pixel to a nearer point and got no segment) and their sum."""
        a = self.accounting
        return {"points.unprojected_ratio": a["unprojected_ratio"],
                "points.occluded_ratio": a["occluded_ratio"],
                "points.no_pixel_ratio": a["no_pixel_ratio"],
                **({"intensity_scale": self.intensity_scale} if self.intensity_scale else {}),
                **self.drift}


def point_accounting(inp: LmsInput, res: SegmentResult) -> dict:
    """Where a frame's points went: ``unprojected`` (valid points outside the image),
    ``occluded`` (valid points that lost their pixel to a nearer point and got no
    segment), ``no_segment`` (all points without a segment = invalid + unprojected +
    occluded) and the shares of the valid points (0 for a frame without one)."""
    pr = res.projection
    valid = inp.valid
    unproj = int(np.count_nonzero(valid & ~pr.valid))
    no_seg = res.point_segment < 0
    occl = int(np.count_nonzero(valid & pr.valid & no_seg))
    nv = int(np.count_nonzero(valid))
    d = max(nv, 1)
    return {"unprojected": unproj, "occluded": occl, "no_segment": int(no_seg.sum()),
            "valid": nv, "unprojected_ratio": unproj / d, "occluded_ratio": occl / d,
            "no_pixel_ratio": (unproj + occl) / d}


class LmsProcessor:
    """The node's frame work without ROS: decode, metrics, meta models, output messages.

    ``models``: a ``MetaModels`` loaded with ``settings.metric_names()``; ``all_fields``:
    ``output/points`` repeats every input field (``output_all_fields``); ``drift``: the
    drift monitor's parameters (``domain_profile``).
    """

    def __init__(self, settings: LmsSettings, models, *, all_fields: bool = False,
                 drift: DriftParameters | None = None):
        settings.validate()
        settings = settings.resolved()
        if tuple(models.feature_names) != settings.metric_names():
            raise ValueError(
                f"the models expect {len(models.feature_names)} features, the settings "
                f"({len(settings.class_names)} classes) give {len(settings.metric_names())}: "
                "models were trained for another class map")
        self.settings = settings
        self.models = models
        self.all_fields = all_fields
        #: live metrics against the models' training data (``domain_profile``)
        self.domain = DomainCheck(getattr(models, "domain_profile", None), drift)
        self.new_stream()
        from lidar_quality_msgs.msg import SegmentQuality, SegmentQualityArray
        self._Quality, self._QualityArray = SegmentQuality, SegmentQualityArray

    def new_stream(self) -> None:
        """Forget what one input stream taught: the intensity scale decided, the padding
        note, the per-beam elevations estimated from its clouds (kept for a node's
        lifetime: one sensor), the drift window (``process_bag``: each bag of a batch is a
        new stream)."""
        self.intensity = IntensityScale(self.settings.intensity_scale)
        self._padding = PaddingNote()
        self.beam_table = beams.BeamTable(MAX_CHANNELS)
        self.domain.reset()

    def process(self, points_msg, probabilities_msg=None, *, markers: bool = False
                ) -> LmsOutputs:
        """One frame. Raises ``CloudFormatError`` for an unusable input (the frame is
        dropped); bad points never raise."""
        s = self.settings
        inp = decode(points_msg, s, probabilities_msg, self.beam_table)
        self.intensity.note = None
        res = frame_metrics(inp, s, self.intensity)
        conf_k, iou_k = self.models.predict(res.features)
        verdict = self.domain((res.names, res.features))
        if verdict.passthrough:     # out of the models' domain, and no detector score
            conf_k, iou_k = np.full_like(conf_k, np.nan), np.full_like(iou_k, np.nan)
        ns = res.n_segments
        conf = np.full(ns, np.nan)
        iou = np.full(ns, np.nan)
        kid = res.kept_ids
        conf[kid], iou[kid] = conf_k, iou_k
        header = points_msg.header
        cloud = self.output_cloud(header, inp, res, conf, iou, all_fields=self.all_fields)
        segs = self.segment_bytes(header, res, conf, iou, verdict)
        mk = self.markers(header, inp, res, conf) if markers else None
        issues = {}
        if inp.n_renormalized:
            issues["probabilities"] = (
                f"{inp.n_renormalized} of {len(inp)} points had probabilities summing "
                f"outside 1 +- {s.sum_tolerance}: renormalized")
        if inp.n_bad_probabilities:
            issues["bad_probabilities"] = (
                f"{inp.n_bad_probabilities} of {len(inp)} points had unusable probabilities "
                "(non-finite, negative or all 0): no segment, label "
                f"{NO_LABEL}, NaN confidence")
        if inp.ring_issue:
            issues["ring"] = inp.ring_issue
        clash = [nm for nm in RESULT_FIELDS if nm in inp.cloud.dtype.names] \
            if self.all_fields else []
        if clash:
            issues["replaced_fields"] = (
                f"input/points field(s) {', '.join(clash)} replaced in output/points by the "
                "results of the same name (output_all_fields)")
        acc = point_accounting(inp, res)
        errors = set()
        ratio = acc["no_pixel_ratio"]
        if acc["valid"] and ratio > s.no_pixel_warn_ratio:
            issues["unprojected"] = (
                f"{acc['unprojected'] + acc['occluded']} of {acc['valid']} valid points "
                f"({100 * ratio:.1f} %) have no pixel: {acc['unprojected']} outside the "
                f"{s.channels} x {s.width} image, {acc['occluded']} lost their pixel to a "
                "nearer point (no segment, NaN confidence): the range image does not fit "
                "the sensor (set sensor to its preset, or channels / width / "
                "beam_elevations_deg / the field of view)")
            if ratio > s.no_pixel_error_ratio:
                errors.add("unprojected")
        if inp.intensity is None:
            issues["intensity"] = ("input/points has no intensity field (intensity, "
                                   "reflectance or i): the intensity metrics read 0")
        if probabilities_msg is not None and (
                probabilities_msg.header.frame_id != points_msg.header.frame_id):
            issues["frame_id"] = (f"input/points frame_id {points_msg.header.frame_id!r} != "
                                  f"input/probabilities {probabilities_msg.header.frame_id!r}")
        if verdict.issue:
            issues["domain_drift"] = verdict.issue
            if verdict.error:
                errors.add("domain_drift")
        return LmsOutputs(inp, res, conf, iou, cloud, segs, mk, issues, frozenset(errors), acc,
                          ([self.intensity.note] if self.intensity.note else [])
                          + self._padding(inp.n_padding, len(inp)),
                          self.intensity.decided, verdict.values,
                          functools.partial(self.segment_array, header, res, conf, iou, verdict))

    @staticmethod
    def output_cloud(header, inp: LmsInput, res: SegmentResult, conf, iou, *,
                     all_fields: bool = False) -> np.ndarray:
        """``output/points`` (see the module doc) as its serialized bytes (uint8): x, y, z
        and the results, written straight into the message (``cloud_cdr.serialized_cloud``;
        as a message, rclpy's conversion and the rmw's serialization copied the 3.1 MB of
        a 120k-point frame twice more), or with ``all_fields`` every field of
        ``inp.cloud`` (a field named like a result replaced by it) and the results; the
        input's height and width."""
        N = len(inp)
        h, w = inp.shape if len(inp.shape) == 2 and inp.shape[0] * inp.shape[1] == N \
            else (1, N)
        label = None
        if inp.n_bad_probabilities:
            label = res.point_class.astype(np.uint16)
            label[inp.probs.sum(axis=1) == 0] = NO_LABEL   # decode zeroed exactly those
        if all_fields:   # (N, count) columns for fields of count > 1
            flat = inp.cloud.reshape(-1)
            results = {"label": res.point_class.astype(np.uint16) if label is None else label,
                       "segment": res.point_segment, "confidence": _per_point(res, conf),
                       "predicted_iou": _per_point(res, iou)}
            cols = {nm: flat[nm] for nm in flat.dtype.names if nm not in results}
            packed = pack_cloud({**cols, **results})
            message, data = serialized_cloud(header, h, w, packed.fields, packed.is_bigendian,
                                             packed.point_step)
            data[:] = np.frombuffer(packed.data, np.uint8)
        else:   # the records in one pass (point_results), into the message
            dtype, fields, big = result_layout()
            message, data = serialized_cloud(header, h, w, fields, big, dtype.itemsize)
            packed = pack_point_results(inp.xyz, res.point_class, res.point_segment, conf, iou,
                                        label=label, height=h, out=data)
        message[-1] = packed.is_dense
        return message

    def segment_bytes(self, header, res: SegmentResult, conf, iou,
                      drift: DomainVerdict | None = None) -> bytes:
        """:meth:`segment_array`'s message as its serialized bytes, written from the arrays
        (``segment_quality_cdr``: 2000 segments as Python messages and rclpy's conversion
        of them cost ~3 ms a frame)."""
        return encode_segment_quality_array(
            header, self.models.confidence_model_id, self.models.iou_model_id,
            res.segment_class, self.settings.class_names, res.n_points, res.size_projected,
            conf, iou, **(drift or DomainVerdict({})).message_fields(self._QualityArray))

    def segment_array(self, header, res: SegmentResult, conf, iou,
                      drift: DomainVerdict | None = None):
        """``output/segments``: every segment in id order, with the drift check's verdict
        (``drift``; None: not checked, drift_level DRIFT_OFF)."""
        Q = self._Quality
        new = Q.__new__
        names = self.settings.class_names
        out = []
        # Thousands of segments per frame: the generated constructor (keyword lookups and
        # a checking property setter per field) costs ~5 us a message, 3x this. The values
        # are plain ints / floats / str of the right ranges, so the slots are set directly.
        for i, (c, npt, sp, cf, pi) in enumerate(zip(
                res.segment_class.tolist(), res.n_points.tolist(),
                res.size_projected.tolist(), conf.tolist(), iou.tolist())):
            q = new(Q)
            q._check_fields = False
            q._segment_id = i
            q._class_index = c
            q._class_name = names[c]
            q._point_count = npt
            q._projected_point_count = sp
            q._confidence = cf
            q._predicted_iou = pi
            out.append(q)
        return self._QualityArray(header=header,
                                  confidence_model_id=self.models.confidence_model_id,
                                  iou_model_id=self.models.iou_model_id, segments=out,
                                  **(drift or DomainVerdict({})).message_fields(
                                      self._QualityArray))

    @staticmethod
    def centroids(inp: LmsInput, res: SegmentResult) -> np.ndarray:
        """(n_segments, 3) mean position of each segment's points (NaN when it has none)."""
        ps = res.point_segment
        ok = ps >= 0
        ns = res.n_segments
        cnt = np.bincount(ps[ok], minlength=ns).astype(np.float64)
        out = np.stack([np.bincount(ps[ok], weights=inp.xyz[ok, k], minlength=ns)
                        for k in range(3)], axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return out / cnt[:, None]

    def markers(self, header, inp: LmsInput, res: SegmentResult, conf):
        """Centroids of the kept segments coloured by confidence."""
        from lidar_quality_ros.markers import point_markers

        kid = res.kept_ids
        return point_markers(header, self.centroids(inp, res)[kid], conf[kid], ns="lms")
