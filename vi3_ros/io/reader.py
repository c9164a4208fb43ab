"""One reader for every way an EuRoC-style recording arrives: an ASL folder (``mav0/`` or its parent), a ROS 1
``.bag``, a rosbag2 directory (sqlite3 or MCAP, with ``metadata.yaml``) or a bare ``.mcap`` file.

Bags are read with rosbags (``AnyReader``; bare MCAP files through the ``mcap`` package and the rosbags Jazzy
typestore's CDR deserialiser) and decoded with ``msg_adapters``. Topics default to EuRoC's (``/cam0/image_raw``,
``/imu0``, ``/vicon/firefly_sbx/firefly_sbx``) or else the only topic of the right type (``choose_topics``: one
rule for replay and eval). Camera frames may be ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` (JPEG/PNG):
the image topic's type is read from the recording.

``iter_events`` never stops at one bad message: a message that cannot be decoded (or an ASL frame whose PNG is
missing or corrupt) becomes a ``DropEvent`` naming it, as the node drops such a message and goes on; an input it
cannot read at all (not a bag, a truncated ROS 1 bag, no image topic, an IMU csv that is empty or unsorted) raises
DataError. An MCAP recording cut short (no summary; a rosbag2 folder without its metadata.yaml, which ros2 bag
writes when it closes) is read as far as its records go, and a ``DropEvent`` ``bag_truncated`` says so.
It streams: an ASL folder's IMU csv is read row by row and its ground truth not at all, so memory does not grow
with the length of the recording.

Bags carry no calibration (EuRoC's carry no CameraInfo): pass ``calib=`` (a ``CameraCalib`` or a path to a
Kalibr camchain-imucam / EuRoC sensor.yaml), or leave a ``*camchain-imucam*.yaml`` next to the bag or inside
the rosbag2 directory (``vi3 make-bag`` writes one). A bag that does carry ``sensor_msgs/CameraInfo`` or
``/tf_static`` gives them to ``iter_events`` on request, as recorded (``CameraInfoEvent``, ``TfStaticEvent``), in
record order with the frames and IMU samples, as a node subscribed to them would receive them. A ``vi3 make-bag``
output folder opens as its rosbag2 MCAP. Ground truth from a bag is poses only: velocities are derived from them
(``GroundTruthTrack``: central differences) and biases are unknown.
"""

from __future__ import annotations

import functools
import heapq
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msg_adapters.errors import drop_reason
from msg_adapters.image import camera_frame
from msg_adapters.imu import imu_to_sample
from msg_adapters.poses import transform_to_T
from msg_adapters.stamps import stamp_to_ns
from msg_adapters.types import full_name, jazzy_types
from vi3_core.dataset.asl import camera_frames, find_mav0, iter_imu, read_asl, read_frame
from vi3_core.dataset.calib import CameraCalib, load_calib
from vi3_core.dataset.sequence import GroundTruthTrack, Sequence
from vi3_core.errors import DataError
from vi3_core.paths import missing_reason
from vi3_core.types import ImuSamples
from vi3_ros.io import topics


@dataclass(frozen=True)
class ImageEvent:
    """One camera frame: stamp (float64 s and int ns) and the raw image [H,W] (mono) or [H,W,3] RGB, as
    recorded (uint8 for 8-bit encodings; the pipeline drops any other dtype, naming it)."""

    t: float
    t_ns: int
    image: np.ndarray


@dataclass(frozen=True)
class ImuEvent:
    """One IMU sample: stamp, gyro [3] rad/s, accel [3] m/s^2, orientation [4] (x, y, z, w) or None."""

    t: float
    t_ns: int
    gyro: np.ndarray
    accel: np.ndarray
    orientation: np.ndarray | None = None


@dataclass(frozen=True)
class CameraInfoEvent:
    """A ``sensor_msgs/CameraInfo`` message as recorded (a rosbags class; from a ROS 1 bag, or one converted from
    ROS 1, with the ROS 1 field names), for ``Pipeline.add_camera_info``."""

    msg: Any


@dataclass(frozen=True)
class TfStaticEvent:
    """A ``tf2_msgs/TFMessage`` of ``/tf_static`` as recorded (a rosbags class), for ``Pipeline.add_tf_static``."""

    msg: Any


@dataclass(frozen=True)
class DropEvent:
    """A message that could not be decoded, dropped: ``reason`` (``image_malformed``, ``image_unsupported``,
    ``imu_malformed``, ``camera_info_malformed``, ``tf_static_malformed``; ``BAG_DAMAGE``'s: the recording's
    records end early or some could not be read, the last event), its stamp (int ns; None when even the header is
    unreadable) and ``detail``, a sentence naming the topic or file and the problem."""

    reason: str
    t_ns: int | None
    detail: str


Event = ImageEvent | ImuEvent | CameraInfoEvent | TfStaticEvent | DropEvent


BAG_DAMAGE = ("bag_truncated", "bag_damaged")  # the DropEvent reasons of a recording read only in part


class BagDamage(DataError):
    """A recording read only in part (``reason``: ``bag_truncated``, its records end early; ``bag_damaged``, some of
    them could not be read): what could be read was."""

    def __init__(self, text: str, reason: str) -> None:
        super().__init__(text)
        self.reason = reason


@dataclass(frozen=True)
class _GtEvent:
    t_ns: int
    T_WB: np.ndarray


#: role -> (accepted message types, preferred topic); image and IMU are required, the others read where present.
_ROLES: dict[str, tuple[tuple[str, ...], str | None]] = {
    "image": (topics.IMAGE_TYPES, topics.IMAGE_TOPIC), "imu": ((topics.IMU_TYPE,), topics.IMU_TOPIC),
    "gt": ((topics.GT_TYPE,), topics.GT_TOPIC), "camera_info": ((topics.CAMERA_INFO_TYPE,), None),
    "tf_static": ((topics.TF_TYPE,), topics.TF_STATIC_TOPIC)}
_REQUIRED = ("image", "imu")
_CALIBRATION_ROLES = ("camera_info", "tf_static")  # named topics, skipped when the recording lacks them
MCAP_MAGIC = b"\x89MCAP0\r\n"  # an MCAP file's first and last 8 bytes
_ZERO_BLOCK = 1 << 16  # bytes read at a time looking for a file's last non-zero byte
#: Errors of rosbags' deserialisers on a message whose bytes do not fit its type.
_UNDECODABLE = (ValueError, IndexError, KeyError, TypeError, struct.error)


@dataclass(frozen=True)
class TopicRequest:
    """Which topic to read for a role: ``explicit`` (a command-line option: must exist with an accepted type), else
    ``preferred`` when the recording has it, else the only topic of an accepted type; ``types`` overrides the
    role's accepted types (e.g. only CompressedImage)."""

    explicit: str | None = None
    preferred: str | None = None
    types: tuple[str, ...] | None = None


# ------------------------------------------------------------------------------------------- bag access
def resolve_input(path) -> tuple[Path, str]:
    """(path to read, kind): "asl", "rosbag1", "rosbag2" or "mcap". A ``vi3 make-bag`` folder reads its MCAP."""
    path = Path(path)
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return path, "rosbag2"
        if (path / "mcap" / "metadata.yaml").is_file():
            return path / "mcap", "rosbag2"
        try:
            find_mav0(path)
        except DataError as err:
            files = sorted(path.glob("*.mcap"))
            if len(files) == 1:  # a rosbag2 recording cut short: ros2 bag writes metadata.yaml when it closes
                return files[0], "mcap"
            split = f" and holds {len(files)} .mcap files: give them one at a time" if files else ""
            raise DataError(f"{err}; nor a rosbag2 directory (no metadata.yaml){split}") from None
        return path, "asl"
    if not path.exists():
        raise DataError(f"{path}: {missing_reason(path)}")
    if path.suffix == ".bag":
        return path, "rosbag1"
    if path.suffix == ".mcap":
        return path, "mcap"
    raise DataError(f"{path}: not an ASL folder, ROS 1 .bag, rosbag2 directory, .mcap file or make-bag folder")


def _option(role: str) -> str:
    """The command-line option of ``vi3 replay`` and ``vi3 eval`` that names the topic of ``role``."""
    return f"--{role.replace('_', '-')}-topic"


def choose_topics(path: Path, available: dict[str, str], want: dict[str, TopicRequest]) -> dict[str, str]:
    """topic -> role for the roles in ``want``, given the recording's topics (name -> ROS 2 type name); the one
    topic rule of replay and eval (see ``TopicRequest``). A calibration role whose topic the recording lacks is
    left out; a required role without a single candidate is a DataError listing the candidates."""
    chosen = {}
    for role, req in want.items():
        types, default = _ROLES[role]
        types = req.types or types
        if role in _CALIBRATION_ROLES and req.explicit not in available:
            continue
        cands = sorted(t for t, ty in available.items() if ty in types)
        listing = ", ".join(f"{t} ({available[t]})" for t in cands) or "none"
        if req.explicit is not None:
            if req.explicit not in cands:
                found = f"has type {available[req.explicit]}" if req.explicit in available else "is not in it"
                raise DataError(f"{path}: topic {req.explicit!r} {found}; {role} topics ({' or '.join(types)}): "
                                f"{listing}")
            topic = req.explicit
        else:
            preferred = req.preferred if req.preferred is not None else default
            if role in _REQUIRED and preferred in available and preferred not in cands:
                raise DataError(f"{path}: topic {preferred!r} has type {available[preferred]}, not "
                                f"{' or '.join(types)}; {role} topics: {listing}; choose one with {_option(role)}")
            topic = preferred if preferred in cands else cands[0] if len(cands) == 1 else None
        if topic is None and role in _REQUIRED:
            what = f"several {role} topics: {listing}; choose one with {_option(role)}" if cands else \
                f"no {role} topic ({' or '.join(types)}); topics: {available}"
            raise DataError(f"{path}: {what}")
        if topic is not None:
            chosen[topic] = role
    return chosen


def _bag_messages(path: Path, kind: str, want: dict[str, TopicRequest]) -> Iterator[tuple[str, str, Any]]:
    """Yield (role, topic, msg) in record order for the roles in ``want``; msg is a DataError for a message whose
    bytes cannot be deserialised."""
    if kind == "mcap":
        yield from _mcap_messages(path, want)
        return
    from rosbags.highlevel import AnyReader, AnyReaderError

    files = sorted(path.glob("*.mcap")) if kind == "rosbag2" else []
    if len(files) == 1:
        with files[0].open("rb") as f:
            summary = _mcap_reader(f)[1]
        if summary is None:  # cut short: rosbags reads only a file with its summary
            yield from _mcap_salvage(files[0], want)
            return
    try:
        with AnyReader([path], default_typestore=jazzy_types().typestore) as reader:
            chosen = choose_topics(path, {c.topic: full_name(c.msgtype) for c in reader.connections}, want)
            conns = [c for c in reader.connections if c.topic in chosen]
            for conn, _, raw in reader.messages(connections=conns):
                yield chosen[conn.topic], conn.topic, _deserialize(reader.deserialize, raw, conn.msgtype, conn.topic)
    except AnyReaderError as err:
        raise DataError(f"{path}: cannot read the bag (truncated, unindexed or not a bag?): {err}") from err
    except DataError:
        raise
    except (_UNDECODABLE + (EOFError, OSError, UnicodeDecodeError)) as err:  # rosbags on bytes that are no bag
        raise DataError(f"{path}: cannot read the bag (not a bag, or corrupt): {type(err).__name__}: {err}") \
            from err


def _deserialize(fn, raw, msgtype: str, topic: str) -> Any:
    try:
        return fn(raw, msgtype)
    except _UNDECODABLE as err:
        return DataError(f"{topic}: a {msgtype} message of {len(raw)} bytes cannot be deserialised "
                         f"({type(err).__name__}: {err})")


def _mcap_messages(path: Path, want: dict[str, TopicRequest]) -> Iterator[tuple[str, str, Any]]:
    """A bare .mcap file (no metadata.yaml): the mcap package reads it, the Jazzy typestore decodes CDR. A file
    without its summary, as a recording cut short leaves it, is read record by record (``_mcap_salvage``)."""
    from mcap.exceptions import McapError

    store = jazzy_types().typestore
    if path.stat().st_size == 0:
        raise DataError(f"{path}: cannot read the MCAP file: it is empty (0 bytes)")
    try:
        with path.open("rb") as f:
            reader, summary = _mcap_reader(f)
            if summary is None:
                yield from _mcap_salvage(path, want)
                return
            chosen = choose_topics(path, {ch.topic: summary.schemas[ch.schema_id].name
                                          for ch in summary.channels.values()}, want)
            for schema, channel, message in reader.iter_messages(topics=list(chosen), log_time_order=True):
                yield chosen[channel.topic], channel.topic, _deserialize(store.deserialize_cdr, message.data,
                                                                         schema.name, channel.topic)
    except (McapError, EOFError, struct.error) as err:
        raise DataError(f"{path}: cannot read the MCAP file: {str(err) or type(err).__name__}") from err


def _mcap_reader(f: Any) -> tuple[Any, Any | None]:
    """(the mcap package's reader of the open MCAP file ``f``, its summary, which the reader keeps; None where it has
    none that can be read: a file cut short ends elsewhere than its closing magic, so what precedes it is no footer,
    or its summary is damaged)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    size = f.seek(0, 2)
    f.seek(-min(len(MCAP_MAGIC), size), 2)
    closed = f.read() == MCAP_MAGIC
    f.seek(0)
    reader = make_reader(f)
    if not closed:
        return reader, None
    try:
        return reader, reader.get_summary()
    except (McapError, EOFError, struct.error, ValueError, OSError):
        return reader, None


class _Prefix:
    """``read(n)`` of the first ``end`` bytes of an open binary file; ``pos``: the bytes read so far."""

    def __init__(self, f: Any, end: int) -> None:
        self._f, self.end, self.pos = f, end, 0

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(self.end - self.pos if n < 0 else min(n, self.end - self.pos))
        self.pos += len(data)
        return data


def _data_end(f: Any, size: int) -> int:
    """``size`` less the run of zero bytes the open file ends with (a file system can leave the unwritten end of a
    file zeroed when the power is lost: those bytes are no records)."""
    end = size
    while end > 0:
        start = max(end - _ZERO_BLOCK, 0)
        f.seek(start)
        nonzero = np.flatnonzero(np.frombuffer(f.read(end - start), np.uint8))
        if len(nonzero):
            return start + int(nonzero[-1]) + 1
        end = start
    return 0


class _McapRecords:
    """The records of an MCAP file in file order, read as far as its framing goes: each chunk opened on its own
    (CRCs checked where the writer set them), a chunk that cannot be (damaged, or cut: the file's last) skipped and
    named in ``skipped``; once iterated, ``ended`` says why the records ended early ("" where the file ended with its
    footer), ``whole`` where the last whole record ends (bytes) and ``size`` the file's size."""

    def __init__(self, path: Path) -> None:
        self.path, self.ended, self.skipped, self.whole, self.size = path, "", [], 0, 0

    def __iter__(self) -> Iterator[Any]:
        from mcap.exceptions import McapError
        from mcap.records import Chunk, Footer
        from mcap.stream_reader import StreamReader, breakup_chunk
        from zstandard import ZstdError

        with self.path.open("rb") as f:
            self.size = f.seek(0, 2)
            end = _data_end(f, self.size)
            f.seek(0)
            stream = _Prefix(f, end)
            zeros = f", then {self.size - end} zero bytes" if end < self.size else ""
            try:
                for record in StreamReader(stream, emit_chunks=True).records:  # each chunk checks its own CRC
                    self.whole = stream.pos
                    if isinstance(record, Chunk):
                        try:
                            yield from breakup_chunk(record, validate_crc=True)
                        except (McapError, struct.error, ValueError, EOFError, ZstdError, RuntimeError) as err:
                            # RuntimeError: lz4's for a frame it cannot decompress
                            self.skipped.append(f"bytes {self.whole - len(record.data)}-{self.whole}: {_why(err)}")
                        continue
                    yield record
                    if isinstance(record, Footer):
                        return
                self.ended = f"no footer after the last whole record, at byte {self.whole} of {self.size}{zeros}"
            except (McapError, struct.error, ValueError, EOFError) as err:
                self.ended = (f"{_why(err)} after the last whole record, at byte {self.whole} of {self.size}{zeros}")


def _why(err: Exception) -> str:
    name = "struct.error" if isinstance(err, struct.error) else type(err).__name__
    return f"{name}{f': {err}' if str(err) else ''}"


def _mcap_salvage(path: Path, want: dict[str, TopicRequest]) -> Iterator[tuple[str, str, Any]]:
    """The messages of an MCAP file that has no summary (a recording cut short: the writer never closed it) in the
    order they were written, as far as its records can be read (``_McapRecords``: a chunk that cannot be opened is
    skipped, the rest read; the file is read twice, its topics first); then, where the file did not end cleanly,
    ("bag", "", a BagDamage saying where it ended, what was skipped and how much was read)."""
    from mcap.records import Channel, Message, Schema

    store = jazzy_types().typestore
    schemas: dict[int, str] = {}
    channels: dict[int, Channel] = {}
    first = _McapRecords(path)
    for record in first:  # the topics first (a writer records each channel before its first message)
        if isinstance(record, Schema):
            schemas[record.id] = record.name
        elif isinstance(record, Channel):
            channels[record.id] = record
    try:
        chosen = choose_topics(path, {c.topic: schemas.get(c.schema_id, "") for c in channels.values()}, want)
    except DataError as err:
        if first.ended or first.skipped:
            raise DataError(f"{err}; {_damage_text(first, 0, None)}") from None
        raise
    wanted = {i: c.topic for i, c in channels.items() if c.topic in chosen}
    count, span = 0, None
    records = _McapRecords(path)
    for record in records:
        if isinstance(record, Message):
            count += 1
            span = (record.log_time, record.log_time) if span is None else (span[0], record.log_time)
            topic = wanted.get(record.channel_id)
            if topic is not None:
                yield chosen[topic], topic, _deserialize(store.deserialize_cdr, record.data,
                                                         schemas[channels[record.channel_id].schema_id], topic)
    if records.ended or records.skipped:
        yield "bag", "", BagDamage(_damage_text(records, count, span),
                                   "bag_truncated" if records.ended else "bag_damaged")


def _damage_text(records: _McapRecords, count: int, span: tuple[int, int] | None) -> str:
    """What a read of ``records`` got: ``count`` messages logged over ``span`` (ns, first and last; None: none)."""
    over = f" logged over {(span[1] - span[0]) * 1e-9:.1f} s" if span is not None else ""
    skipped = f"; {len(records.skipped)} damaged chunk(s) skipped ({'; '.join(records.skipped[:3])})" \
        if records.skipped else ""
    ended = f"its records end early ({records.ended})" if records.ended else "its records end with its footer"
    cut = " (a recording cut short?)" if records.ended else ""
    return f"the MCAP file {records.path} has no summary and {ended}{skipped}: {count} messages read{over}{cut}"


def _decode(role: str, topic: str, msg: Any) -> Event | _GtEvent:
    """The event of one message; a DropEvent naming the topic when it cannot be decoded."""
    ns = None
    if isinstance(msg, BagDamage):
        return DropEvent(msg.reason, None, str(msg))
    try:
        if isinstance(msg, DataError):
            raise msg
        if role == "camera_info":
            return CameraInfoEvent(msg)
        if role == "tf_static":
            return TfStaticEvent(msg)
        ns = stamp_to_ns(msg.header.stamp)
        if role == "image":
            return ImageEvent(ns * 1e-9, ns, camera_frame(msg))
        if role == "imu":
            s = imu_to_sample(msg)
            return ImuEvent(ns * 1e-9, ns, s.gyro, s.accel, s.orientation)
        return _GtEvent(ns, transform_to_T(msg.transform))
    except DataError as err:
        return DropEvent(drop_reason(role, err), ns, f"{topic}: {err}")


def _events(path: Path, kind: str, want: dict[str, TopicRequest]) -> Iterator[Event | _GtEvent]:
    for role, topic, msg in _bag_messages(path, kind, want):
        yield _decode(role, topic, msg)


# ------------------------------------------------------------------------------------------- public API
def merge_by_time(*stamps_ns: np.ndarray) -> Iterator[tuple[int, int, int]]:
    """Streams of int ns stamps (one [N_k] array each, e.g. an ASL folder's camera, IMU and ground-truth CSVs)
    merged into one record order, as a recorded bag has them: (stamp ns, stream k, index in stream k), by stamp,
    ties by stream then index."""
    ns = np.concatenate([np.asarray(s, np.int64).reshape(-1) for s in stamps_ns])
    stream = np.concatenate([np.full(len(s), k) for k, s in enumerate(stamps_ns)])
    index = np.concatenate([np.arange(len(s)) for s in stamps_ns])
    order = np.lexsort((index, stream, ns))
    return zip(ns[order].tolist(), stream[order].tolist(), index[order].tolist())


def iter_events(path, *, image: TopicRequest = TopicRequest(), imu: TopicRequest = TopicRequest(),
                camera_info_topic: str | None = None, tf_static: bool = False) -> Iterator[Event]:
    """Camera frames and IMU samples of any supported recording in record order (images decoded lazily), and a
    ``DropEvent`` for each message that cannot be decoded.

    ``image`` / ``imu`` choose the topics (``TopicRequest``). With ``camera_info_topic`` the
    ``sensor_msgs/CameraInfo`` messages of that topic, with ``tf_static`` those of ``/tf_static``, come in the same
    stream where the recording has them (an ASL folder has neither: its calibration is ``cam0/sensor.yaml``)."""
    path, kind = resolve_input(path)
    if kind == "asl":
        _check_no_topics(path, image=image.explicit, imu=imu.explicit)
        yield from _asl_events(path)
        return
    want = {"image": image, "imu": imu}
    if camera_info_topic:
        want["camera_info"] = TopicRequest(explicit=camera_info_topic)
    if tf_static:
        want["tf_static"] = TopicRequest(explicit=topics.TF_STATIC_TOPIC)
    yield from _events(path, kind, want)


def _check_no_topics(path: Path, **explicit: str | None) -> None:
    """DataError when a topic was named for an ASL folder, which has files, not topics (never ignored silently)."""
    named = [f"{_option(role)} {topic}" for role, topic in explicit.items() if topic is not None]
    if named:
        raise DataError(f"{', '.join(named)}: {path} is an ASL folder, which has no topics (its camera is cam0/, "
                        "its IMU imu0/); leave the option out")


def _asl_events(path: Path) -> Iterator[Event]:
    """An ASL folder's frames and IMU samples merged by stamp (ties: the frame first), the IMU csv streamed."""
    mav0 = find_mav0(path)
    frames = camera_frames(mav0)
    ns, files = frames if frames is not None else (np.zeros(0, np.int64), [])
    cams = ((int(t), 0, f) for t, f in zip(ns.tolist(), files))
    imus = ((t, 1, gyro, accel) for t, gyro, accel in iter_imu(mav0))
    for item in heapq.merge(cams, imus, key=lambda e: e[:2]):
        t = item[0]
        if item[1] == 1:
            yield ImuEvent(t * 1e-9, t, item[2], item[3])
            continue
        try:
            yield ImageEvent(t * 1e-9, t, read_frame(item[2]))
        except DataError as err:  # a missing or corrupt PNG: that frame is dropped, as a bad message would be
            yield DropEvent("image_malformed", t, str(err))


def find_calib(path) -> Path | None:
    """A Kalibr ``*camchain-imucam*.yaml`` in a rosbag2 directory, beside a bag, or beside its directory."""
    path = Path(path).resolve()
    for folder in ((path,) if path.is_dir() else ()) + (path.parent, path.parent.parent):
        found = sorted(folder.glob("*camchain-imucam*.yaml"))
        if found:
            return found[0]
    return None


def open_sequence(path, *, calib: CameraCalib | str | Path | None = None, image_topic: str | None = None,
                  imu_topic: str | None = None, gt_topic: str | None = None) -> Sequence:
    """Open any supported recording as a ``Sequence``.

    ASL folders load images and depth lazily; bags are read once into memory (images as arrays). ``calib``
    overrides or supplies the calibration (bags have none of their own; see the module docstring). The topics are
    chosen by ``choose_topics`` (``image_topic`` etc. explicit). Evaluation takes no partial data: a message that
    cannot be decoded is a DataError naming it.
    """
    path, kind = resolve_input(path)
    if isinstance(calib, (str, Path)):
        calib = load_calib(calib)
    if kind == "asl":
        _check_no_topics(path, image=image_topic, imu=imu_topic)
        seq = read_asl(path)
        if calib is not None:
            seq.calib = calib
        return seq
    if calib is None and (found := find_calib(path)) is not None:
        calib = load_calib(found)
    images: list[ImageEvent] = []
    imus: list[ImuEvent] = []
    gts: list[_GtEvent] = []
    sink = {ImageEvent: images, ImuEvent: imus, _GtEvent: gts}
    for ev in _events(path, kind, {"image": TopicRequest(image_topic), "imu": TopicRequest(imu_topic),
                                   "gt": TopicRequest(gt_topic)}):
        if isinstance(ev, DropEvent):
            if ev.reason in BAG_DAMAGE:
                raise DataError(f"{ev.detail}; evaluation takes whole recordings (vi3 replay reads what it can)")
            raise DataError(f"{path}: {ev.detail}")
        sink[type(ev)].append(ev)
    if not images:
        raise DataError(f"{path}: the image topic has no messages")
    images.sort(key=lambda e: e.t_ns)
    cam_ns = np.array([e.t_ns for e in images], dtype=np.int64)
    imu = imu_samples(imus)
    gt = None
    if len(gts) >= 2:
        gts.sort(key=lambda e: e.t_ns)
        gt_ns = np.array([e.t_ns for e in gts], dtype=np.int64)
        gt = GroundTruthTrack(gt_ns * 1e-9, np.stack([e.T_WB for e in gts]), t_ns=gt_ns)
    frames = [e.image for e in images]
    name = path.stem if kind != "rosbag2" else path.name
    return Sequence(name=name, stamps=cam_ns * 1e-9, imu=imu, calib=calib, gt=gt,
                    load_image=functools.partial(_frame, frames), stamps_ns=cam_ns, imu_ns=imu.t_ns)


def imu_samples(events: Iterable[ImuEvent]) -> ImuSamples:
    """IMU events -> ``ImuSamples`` in stamp order, times from the exact ns stamps (``t_ns``)."""
    imus = sorted(events, key=lambda e: e.t_ns)
    ns = np.array([e.t_ns for e in imus], dtype=np.int64)
    return ImuSamples(ns * 1e-9, np.array([e.gyro for e in imus]).reshape(-1, 3),
                      np.array([e.accel for e in imus]).reshape(-1, 3), t_ns=ns)


def _frame(frames: list[np.ndarray], i: int) -> np.ndarray:
    return frames[i]
