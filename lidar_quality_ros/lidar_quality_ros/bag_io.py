"""rosbag2 files as rclpy messages, via the ``rosbags`` library (no rosbag2 needed).

Messages are (de)serialised by rclpy itself (``rclpy.serialization``), so the objects read
and written are exactly the ones nodes publish and receive; messages that are only copied
keep their original bytes. Our own message packages are registered in the ``rosbags``
typestore from their .msg files (:mod:`lidar_quality_core.rosbag_types`), so the bags carry
the definitions ``ros2 bag`` and Foxglove need.

Any bag ``ros2 bag`` reads is read here (:func:`open_bag`): metadata of older rosbag2
versions with an empty ``storage_identifier`` (taken from the files: ``*.db3`` sqlite3,
``*.mcap`` MCAP) or an empty topic ``serialization_format`` (CDR, the only one rosbag2
writes) is read through a corrected copy of ``metadata.yaml`` in a temporary folder beside
links to the bag's files; the bag itself is never changed. Messages of types without an
rclpy class here (e.g. a driver's raw packets) are read and copied as bytes; the tools
that decode or publish skip them with one :class:`UnknownTypes` warning per type.

Older definitions of our own messages: a bag recorded with an earlier definition of a
``lidar_quality_msgs`` type (e.g. a quality array of message version 0, before the drift
fields) holds bytes the installed definition cannot deserialize (rclpy raises "failed to
deserialize ROS message": they end where the appended fields begin). When the bag records
its definition and that differs from the installed one (by RIHS01 type hash),
:meth:`BagMessage.decode` reads the bytes by the recorded definition (rosbags) and fills
the installed message class field by field: fields the old definition lacks keep their
defaults (``version`` 0, ``drift_level`` DRIFT_UNKNOWN). Bags without recorded definitions
(rosbag2 before Iron) cannot be told apart and decode as before.
"""
from __future__ import annotations

import contextlib
import importlib
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from lidar_quality_core.rosbag_types import typestore

STORAGES = ("mcap", "sqlite3")


def message_class(msgtype: str):
    """rclpy message class of ``pkg/msg/Name``."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


@lru_cache(maxsize=None)
def known_type(msgtype: str) -> bool:
    """Whether ``msgtype`` has an rclpy class here (it can be decoded and published)."""
    try:
        message_class(msgtype)
    except (ImportError, AttributeError, ValueError):
        return False
    return True


@dataclass
class UnknownTypes:
    """One warning per message type without an rclpy class (``warn(text)``), naming its
    topics; ``seen``: type -> topics, for summaries."""

    warn: Callable[[str], None]
    what: str = "skipped"
    seen: dict = field(default_factory=dict)

    def check(self, topic: str, msgtype: str) -> bool:
        """True when ``msgtype`` is known; else warns once for the type and returns False."""
        if known_type(msgtype):
            return True
        topics = self.seen.setdefault(msgtype, [])
        if topic not in topics:
            topics.append(topic)
            if len(topics) == 1:
                self.warn(f"message type {msgtype} (topic {topic}) is not available here "
                          f"(no rclpy class; source the workspace that defines it): "
                          f"{self.what}")
        return False

    def check_all(self, topics: dict[str, str]) -> list[str]:
        """Topics (topic -> type) whose type is known; one warning per unknown type, naming
        all its topics."""
        unknown: dict[str, list[str]] = {}
        for t, ty in topics.items():
            if not known_type(ty):
                unknown.setdefault(ty, []).append(t)
        for ty, ts in unknown.items():
            new = [t for t in ts if t not in self.seen.get(ty, [])]
            if new and ty not in self.seen:
                self.warn(f"message type {ty} (topic{'s' if len(ts) > 1 else ''} "
                          f"{', '.join(ts)}) is not available here (no rclpy class; source the "
                          f"workspace that defines it): {self.what}")
            self.seen.setdefault(ty, []).extend(new)
        return [t for t, ty in topics.items() if known_type(ty)]


# ----------------------------------------------------------------------- reading
def metadata_fixes(path: Path | str) -> tuple[dict, list[str]]:
    """The bag's metadata (``rosbag2_bagfile_information``) as rosbags can read it, and
    what was corrected (empty: the file is read as it is). Raises ``ValueError`` for a
    ``metadata.yaml`` that is not a rosbag2 one."""
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load((path / "metadata.yaml").read_text())
        meta = doc["rosbag2_bagfile_information"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: unreadable rosbag2 metadata.yaml: {exc}") from None
    fixes = []
    if not meta.get("storage_identifier"):
        files = [Path(f).name for f in meta.get("relative_file_paths") or []]
        suffixes = {Path(f).suffix for f in files} or {
            q.suffix for q in path.iterdir() if q.suffix in (".db3", ".mcap")}
        by_suffix = {".db3": "sqlite3", ".mcap": "mcap"}
        kinds = {by_suffix.get(x) for x in suffixes}
        if len(kinds) != 1 or None in kinds:
            raise ValueError(f"{path}: empty storage_identifier and files "
                             f"{sorted(files) or 'none'}: cannot tell sqlite3 from mcap")
        meta["storage_identifier"] = kinds.pop()
        fixes.append(f"empty storage_identifier: {meta['storage_identifier']} (from the "
                     f"files)")
    for t in meta.get("topics_with_message_count") or []:
        tm = t.get("topic_metadata") or {}
        if not tm.get("serialization_format"):
            tm["serialization_format"] = "cdr"
            fixes.append(f"empty serialization_format of {tm.get('name')}: cdr")
    return doc, fixes


@contextlib.contextmanager
def open_bag(path: Path | str):
    """An open rosbags ``Reader`` of any rosbag2 directory ``ros2 bag`` reads (see the
    module doc); ``reader.fixes`` lists the metadata corrections."""
    import yaml
    from rosbags.rosbag2 import Reader

    path = Path(path)
    doc, fixes = metadata_fixes(path)
    with contextlib.ExitStack() as stack:
        where = path
        if fixes:  # rosbags refuses such metadata: a corrected copy beside links to the files
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bag_io_")))
            for f in doc["rosbag2_bagfile_information"].get("relative_file_paths") or []:
                src = (path / Path(f).name).resolve()
                try:
                    os.symlink(src, tmp / src.name)
                except OSError:  # no symlinks on this filesystem
                    shutil.copy2(src, tmp / src.name)
            (tmp / "metadata.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
            where = tmp
        reader = stack.enter_context(Reader(where))
        reader.fixes = fixes
        yield reader


def _storage_connections(reader, topics=None) -> list:
    # The storage files' own connections: rosbags matches the metadata's connections to
    # the files' by their serialization format and QoS too, and old bags' metadata and
    # files may disagree (an empty format in the .db3): those messages would be left out.
    storages = getattr(reader.storage, "storages", None) or [reader.storage]
    return [c for s in storages for c in s.connections if topics is None or c.topic in topics]


@dataclass
class BagMessage:
    topic: str
    msgtype: str
    stamp_ns: int       # log time
    raw: bytes
    #: the definition the bag recorded for ``msgtype`` when it is an older one of a
    #: ``VERSIONED`` package ("" when it is the installed one, or unknown)
    recorded: str = ""

    def decode(self):
        """The rclpy message (of the installed definition; see the module doc for bytes
        of an older one)."""
        if self.recorded:
            return decode_recorded(self.raw, self.msgtype, self.recorded)
        from rclpy.serialization import deserialize_message

        return deserialize_message(self.raw, message_class(self.msgtype))


#: message packages of ours whose definitions change between versions: bags recorded with
#: an older definition are read by it (module doc)
VERSIONED = ("lidar_quality_msgs/",)


@lru_cache(maxsize=None)
def _installed_hash(msgtype: str) -> str:
    try:
        return typestore().hash_rihs01(msgtype)
    except Exception:  # noqa: BLE001 - rosbags raises several kinds for an unknown type
        return ""


@lru_cache(maxsize=16)
def _recorded_store(msgtype: str, msgdef: str):
    """A typestore holding ``msgtype`` as ``msgdef`` (with its dependencies) defines it."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(msgdef, msgtype))
    return store


def older_definition(msgtype: str, msgdef: str, digest: str = "") -> bool:
    """Whether ``msgdef`` (a bag's recorded definition of ``msgtype``, with its type hash
    ``digest`` if known) is another one than the installed, for a ``VERSIONED`` type."""
    if not msgtype.startswith(VERSIONED) or not (msgdef or "").strip():
        return False
    installed = _installed_hash(msgtype)
    try:
        recorded = digest or _recorded_store(msgtype, msgdef).hash_rihs01(msgtype)
    except Exception:  # noqa: BLE001 - an unparsable recorded definition: decode as installed
        return False
    return bool(installed) and recorded != installed


def recorded_definition(conn) -> str:
    """``conn``'s (a rosbags connection) recorded definition when ``older_definition``,
    else "" (the installed one, none recorded, or not ours)."""
    msgdef = getattr(getattr(conn, "msgdef", None), "data", "") or ""
    return msgdef if older_definition(conn.msgtype, msgdef, conn.digest or "") else ""


def decode_recorded(raw: bytes, msgtype: str, msgdef: str):
    """The installed rclpy message of ``raw`` serialized with the definition ``msgdef``:
    fields by name, those ``msgdef`` lacks at their defaults."""
    return _to_rclpy(_recorded_store(msgtype, msgdef).deserialize_cdr(raw, msgtype),
                     message_class(msgtype))


def _message_type(kind: str) -> tuple[str, bool]:
    """(element type, is a sequence or array) of an rclpy field type string."""
    if kind.startswith("sequence<"):
        return kind[len("sequence<"):-1].split(",")[0].strip(), True
    if kind.endswith("]"):
        return kind[:kind.index("[")], True
    return kind, False


def _to_rclpy(obj, cls):
    msg = cls()
    for name, kind in cls.get_fields_and_field_types().items():
        if not hasattr(obj, name):
            continue        # not in the recorded definition: the installed default
        value = getattr(obj, name)
        base, many = _message_type(kind)
        if "/" in base:     # a message, or a sequence / array of them
            pkg, _, typ = base.partition("/")
            sub = message_class(f"{pkg}/msg/{typ}")
            value = [_to_rclpy(v, sub) for v in value] if many else _to_rclpy(value, sub)
        elif hasattr(value, "tolist"):   # rosbags' numpy arrays of primitives
            value = value.tolist()
        setattr(msg, name, value)
    return msg


def bag_topics(path: Path | str) -> dict[str, str]:
    """Topic -> message type of a bag."""
    with open_bag(path) as r:
        return {c.topic: c.msgtype for c in r.connections}


def read_bag(path: Path | str, topics=None, *, start_ns: int | None = None,
             stop_ns: int | None = None) -> Iterator[BagMessage]:
    """Messages of a bag (optionally only ``topics``, only of log times in [``start_ns``,
    ``stop_ns``)) in log-time order."""
    with open_bag(path) as r:
        conns = _storage_connections(r, topics)
        if not conns:  # rosbags reads every topic when given no connection
            return
        recorded: dict = {}
        for conn, stamp, raw in r.messages(connections=conns, start=start_ns, stop=stop_ns):
            key = (conn.id, conn.topic, conn.msgtype)
            if key not in recorded:
                recorded[key] = recorded_definition(conn)
            yield BagMessage(conn.topic, conn.msgtype, int(stamp), bytes(raw), recorded[key])


@dataclass
class TopicInfo:
    msgtype: str
    count: int
    qos: list           # offered QoS profiles of metadata.yaml (rclpy QoSProfile), may be empty
    msgdef: str = ""    # message definition recorded in the bag ("" when it has none)
    digest: str = ""    # its type hash (RIHS01), "" when the bag has none


@dataclass
class BagInfo:
    start_ns: int       # first log time
    end_ns: int         # last log time
    topics: dict[str, TopicInfo]
    fixes: list = field(default_factory=list)   # metadata corrections (``metadata_fixes``)


def bag_info(path: Path | str) -> BagInfo:
    """Time span, topics, message counts, recorded QoS and definitions of a bag."""
    with open_bag(path) as r:
        topics = {c.topic: TopicInfo(c.msgtype, c.msgcount,
                                     [_qos_to_rclpy(q) for q in c.ext.offered_qos_profiles],
                                     c.msgdef.data or "", c.digest or "")
                  for c in r.connections}
        if not r.message_count:
            return BagInfo(0, 0, topics, r.fixes)
        # rosbags' end_time is exclusive
        return BagInfo(r.start_time, r.end_time - 1, topics, r.fixes)


def _qos_to_rclpy(q):
    # rosbags' QoS enums have the rmw values, as rclpy's policies do
    from rclpy.duration import Duration
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                           ReliabilityPolicy)

    def dur(t):
        return Duration(seconds=t.sec, nanoseconds=t.nsec)

    return QoSProfile(history=HistoryPolicy(q.history.value), depth=q.depth,
                      reliability=ReliabilityPolicy(q.reliability.value),
                      durability=DurabilityPolicy(q.durability.value),
                      deadline=dur(q.deadline), lifespan=dur(q.lifespan),
                      liveliness=LivelinessPolicy(q.liveliness.value),
                      liveliness_lease_duration=dur(q.liveliness_lease_duration),
                      avoid_ros_namespace_conventions=q.avoid_ros_namespace_conventions)


def _qos_from_rclpy(p):
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)

    def t(d):
        sec, nsec = divmod(d.nanoseconds, 10**9)
        return QosTime(sec, nsec)

    return Qos(QosHistory(int(p.history)), p.depth, QosReliability(int(p.reliability)),
               QosDurability(int(p.durability)), t(p.deadline), t(p.lifespan),
               QosLiveliness(int(p.liveliness)), t(p.liveliness_lease_duration),
               p.avoid_ros_namespace_conventions)


class BagWriter:
    """Writes rclpy messages (or raw CDR bytes) to a new rosbag2 (format version 9)."""

    def __init__(self, path: Path | str, *, storage: str = "mcap"):
        from rosbags.rosbag2 import StoragePlugin, Writer

        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
        self._writer = Writer(Path(path), version=9, storage_plugin=plugin)
        self._ts = typestore()
        self._conns: dict[str, object] = {}

    def __enter__(self):
        self._writer.open()
        return self

    def __exit__(self, *exc):
        self._writer.close()

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg, *, qos=(),
              source: TopicInfo | None = None) -> None:
        """Write ``msg`` (an rclpy message, or bytes already serialised: bytes-like or a
        uint8 numpy array, as the nodes publish their outputs) on ``topic``;
        ``qos`` (rclpy QoSProfiles, taken at a topic's first message) are recorded as
        its offered QoS profiles. A type our typestore does not know (copied bytes) is
        recorded with the definition and hash of ``source`` (the input bag's topic), or
        with none, as older rosbag2 versions record every topic; so is one of ours whose
        ``source`` definition is an older one (``older_definition``: copied bytes of it
        keep the definition they were written with)."""
        from rclpy.serialization import serialize_message

        conn = self._conns.get(topic)
        if conn is None:
            conn = self._conns[topic] = self._add(topic, msgtype, qos, source)
        if isinstance(msg, (bytes, bytearray, memoryview, np.ndarray)):
            raw = bytes(msg)
        else:
            raw = serialize_message(msg)
            if msgtype in self._ts.fielddefs:
                # rclpy leaves CDR alignment padding uninitialised: re-serialised by rosbags
                # (zero padding), the same message gives the same bytes in every run
                raw = self._ts.serialize_cdr(self._ts.deserialize_cdr(raw, msgtype), msgtype)
        self._writer.write(conn, int(stamp_ns), bytes(raw))

    def _add(self, topic, msgtype, qos, source):
        offered = [_qos_from_rclpy(p) for p in qos]
        older = source is not None and older_definition(msgtype, source.msgdef, source.digest)
        if not older:
            try:
                return self._writer.add_connection(topic, msgtype, typestore=self._ts,
                                                   offered_qos_profiles=offered)
            except Exception:  # noqa: BLE001 - rosbags raises several kinds for an unknown type
                pass
        msgdef, digest = (source.msgdef, source.digest) if source else ("", "")
        if older and not digest:
            digest = _recorded_store(msgtype, msgdef).hash_rihs01(msgtype)
        # rosbags insists on a hash; the metadata then records the source's ("" if none)
        conn = self._writer.add_connection(topic, msgtype, msgdef=msgdef,
                                           rihs01=digest or "unknown",
                                           offered_qos_profiles=offered)
        if not digest:
            conns = self._writer.connections
            conns[conns.index(conn)] = conn = conn._replace(digest="")
        return conn


# ----------------------------------------------------------------------- output
def partial_dirs(target: Path | str) -> list[Path]:
    """Leftovers of runs that were killed (SIGKILL, power loss) while writing ``target``."""
    target = Path(target)
    return sorted(target.parent.glob(f".{target.name}.partial-*"))


@contextlib.contextmanager
def atomic_output(target: Path | str, *, overwrite: bool = False):
    """Yield a path, beside ``target``, that does not exist yet: write the output (a bag,
    a folder) there; it is moved to ``target`` when the block ends without an exception
    (an existing ``target`` replaced only then, and only with ``overwrite``). On any
    exception, Ctrl-C included, the partial output is removed and ``target`` is untouched.
    """
    target = Path(target)
    if (target.exists() or target.is_symlink()) and not overwrite:
        raise FileExistsError(f"{target} exists (overwrite it explicitly)")
    target.parent.mkdir(parents=True, exist_ok=True)
    for stale in partial_dirs(target):    # a killed run's: nobody writes there any more
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-", dir=target.parent))
    try:
        out = tmp / target.name   # rosbags names the storage file after its folder
        yield out
        if not out.exists():
            raise FileNotFoundError(f"nothing was written for {target}")
        if target.exists() or target.is_symlink():
            old = tmp / ".replaced"
            os.replace(target, old)   # then the rename below is one step on the same disk
        os.replace(out, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
