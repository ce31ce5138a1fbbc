"""ROS bags (ROS1 ``.bag`` files and ROS2 bag folders), through the optional package ``rosbags``
(pure Python, no ROS installation; ``pip install "cmax-taichi[rosbag]"`` or ``pip install rosbags``).

One topic of events is read (``topic=``; a bag with one event topic needs none, and a bag with several
lists them in the error), of one of these message types:

======================================== ====================================================================
message type                             events
======================================== ====================================================================
``dvs_msgs/EventArray``                  ``x, y`` (uint16), ``ts`` (ROS time), ``polarity`` (bool): ECD, MVSEC
``prophesee_event_msgs/EventArray``      the same layout (Prophesee's ROS1 driver)
``event_camera_msgs/EventPacket``        a binary payload: ``evt3`` and ``evt2`` (Prophesee EVT 3.0 / 2.0
                                         words, decoded by ``faery``: the camera's microsecond clock, as a
                                         ``.raw`` file of the same words gives), ``mono`` (64-bit words:
                                         ``time_base + dt``, ns)
======================================== ====================================================================

Times are seconds of the clock the messages carry: the ROS time of each event for the two EventArray
types (``sec + nanosec / 1e9``, computed from the integer nanoseconds: a time written with at most 9
decimals reads back as the same float64 as its text), the sensor clock for ``evt3`` / ``evt2``. Polarity
``True`` is +1, ``False`` -1.

The camera comes from a ``sensor_msgs/CameraInfo`` topic when the bag has one (``camera_topic=``; by
default the one beside the event topic, ``/dvs/events`` -> ``/dvs/camera_info``, or the only one):
``K`` gives the intrinsics and ``D`` the ``plumb_bob`` distortion (``k1 k2 p1 p2 k3``); another
distortion model is not applied, with a warning. The sensor size is ``sensor_size=``, else the camera
info's, else the ``width`` and ``height`` of the first event message.

The event messages are decoded once, message by message (bounded memory: one message at a time; the
EVT payloads are copied to a temporary RAW file that ``faery`` decodes packet by packet), into the binary
event cache of :mod:`._cache`, and memory-mapped afterwards, like the other formats without an index.
The two EventArray types are decoded with NumPy straight from the serialized bytes (ROS1 and
little-endian CDR): ``rosbags``' own deserializer builds a Python object per event, about 3 us each;
any other serialization goes through it. Malformed input raises ValueError naming the bag, the topic
and the message: bytes that do not fit the message type, a nanosecond field above 1e9, an event
outside its message's ``width`` x ``height``, an unknown ``encoding``, times going backwards
(``sort=True`` sorts them, as for the other formats).
"""

from __future__ import annotations

import contextlib
import math
import os
import struct
import tempfile
import warnings
from pathlib import Path
from typing import BinaryIO

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera
from cmax_taichi.io._cache import CachedTableReads, cache_root
from cmax_taichi.io._files import check_regular, is_present
from cmax_taichi.io.base import Recording

__all__ = ["EVENT_TYPES", "ENCODINGS", "RosbagRecording", "event_topics", "is_ros2_bag", "typestore"]

PACKAGE = "rosbags"
EXTRA = "rosbag"

_EVENT = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
_ARRAY = "Header header\nuint32 height\nuint32 width\n{package}/Event[] events\n"
_PACKET = (
    "Header header\nuint32 height\nuint32 width\nuint64 seq\nuint64 time_base\nstring encoding\n"
    "bool is_bigendian\nuint8[] events\n"
)
#: the .msg text of the event message types (registered when a bag carries no definitions)
MESSAGE_DEFINITIONS = {
    "dvs_msgs/msg/Event": _EVENT,
    "dvs_msgs/msg/EventArray": _ARRAY.format(package="dvs_msgs"),
    "prophesee_event_msgs/msg/Event": _EVENT,
    "prophesee_event_msgs/msg/EventArray": _ARRAY.format(package="prophesee_event_msgs"),
    "event_camera_msgs/msg/EventPacket": _PACKET,
}
ARRAY_TYPES = ("dvs_msgs/msg/EventArray", "prophesee_event_msgs/msg/EventArray")
PACKET_TYPE = "event_camera_msgs/msg/EventPacket"
EVENT_TYPES = (*ARRAY_TYPES, PACKET_TYPE)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
#: the EventPacket encodings this reader decodes
ENCODINGS = ("evt3", "evt2", "mono")
_RAW_VERSIONS = {"evt3": ("3.0", "EVT3"), "evt2": ("2.0", "EVT2")}
_STORAGE_SUFFIXES = (".db3", ".mcap")

#: one event of an EventArray as ROS1 serializes it (packed, 13 bytes)
_ROS1_EVENT = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("p", "u1")])
#: little-endian CDR: the first event starts 4-aligned (14 bytes with its padding), every later one
#: 2 bytes past a 4-byte boundary, so that its time is padded to the next boundary (16 bytes)
_CDR_FIRST = np.dtype({"names": ["x", "y", "sec", "nsec", "p"], "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                       "offsets": [0, 2, 4, 8, 12], "itemsize": 13})  # fmt: skip
_CDR_NEXT = np.dtype({"names": ["x", "y", "sec", "nsec", "p"], "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                      "offsets": [0, 2, 6, 10, 14], "itemsize": 16})  # fmt: skip


def _rosbags(path: Path):
    try:
        import rosbags.highlevel  # noqa: F401
        import rosbags.typesys  # noqa: F401
    except ImportError:
        raise ImportError(
            f"{path}: reading ROS bags needs the optional package '{PACKAGE}': "
            f'pip install "cmax-taichi[{EXTRA}]"  (or pip install {PACKAGE})'
        ) from None
    import rosbags

    return rosbags


def typestore(ros2: bool = True):
    """A ``rosbags`` type store of ROS2 Humble (``ros2``) or ROS1 Noetic with the event message types of
    :data:`MESSAGE_DEFINITIONS` registered: what a bag without type definitions is read with, and what
    a bag of events can be written with."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    types: dict = {}
    for name, text in MESSAGE_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def is_ros2_bag(path: Path) -> bool:
    """Whether ``path`` is a ROS2 bag folder (a ``metadata.yaml`` beside ``.db3`` / ``.mcap`` files)."""
    return path.is_dir() and is_present(path / "metadata.yaml")


def _bag_paths(path: Path) -> tuple[Path, list[Path]]:
    """(the bag as rosbags opens it, the files whose state keys the cache)."""
    if path.is_dir():
        if not is_ros2_bag(path):
            raise ValueError(f"{path}: a folder without metadata.yaml is not a ROS2 bag")
        files = sorted(
            p for p in path.iterdir() if p.suffix in _STORAGE_SUFFIXES or p.name == "metadata.yaml"
        )
        for f in files:
            check_regular(f)
        return path, files
    if path.suffix in _STORAGE_SUFFIXES and is_ros2_bag(path.parent):
        return _bag_paths(path.parent)
    check_regular(path)
    return path, [path]


@contextlib.contextmanager
def _open_bag(path: Path):
    """An open ``rosbags`` AnyReader of ``path``; ValueError naming the bag when it cannot be read."""
    _rosbags(path)
    from rosbags.highlevel import AnyReader, AnyReaderError

    ros2 = path.is_dir()
    try:
        reader = AnyReader([path], default_typestore=typestore(ros2))
        reader.open()
    except (AnyReaderError, KeyError, ValueError, OSError) as exc:
        raise ValueError(f"{path}: not a readable ROS{'2' if ros2 else '1'} bag ({exc})") from None
    try:
        yield reader
    finally:
        reader.close()


def event_topics(path: str | os.PathLike) -> dict[str, tuple[str, int]]:
    """The event topics of the bag at ``path``: ``{topic: (message type, message count)}``."""
    bag, _ = _bag_paths(Path(path))
    with _open_bag(bag) as reader:
        return _topics(reader, EVENT_TYPES)


def _topics(reader, types) -> dict[str, tuple[str, int]]:
    out = {}
    for topic, info in reader.topics.items():
        if info.msgtype in types:
            out[topic] = (info.msgtype, int(info.msgcount))
    return dict(sorted(out.items()))


def _choose_topic(path: Path, reader, topic: str | None) -> tuple[str, str]:
    """(topic, message type) of the events: ``topic`` checked, or the bag's only event topic."""
    events = _topics(reader, EVENT_TYPES)
    listing = ", ".join(f"{t} ({m}, {n} messages)" for t, (m, n) in events.items())
    if topic is not None:
        if topic in events:
            return topic, events[topic][0]
        info = reader.topics.get(topic)
        if info is None:
            raise ValueError(f"{path}: no topic {topic!r}; event topics: {listing or 'none'}")
        raise ValueError(
            f"{path}: topic {topic!r} holds {info.msgtype}, not events ({', '.join(EVENT_TYPES)}); "
            f"event topics: {listing or 'none'}"
        )
    if len(events) == 1:
        name = next(iter(events))
        return name, events[name][0]
    if not events:
        every = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(reader.topics.items()))
        raise ValueError(f"{path}: no topic of events ({', '.join(EVENT_TYPES)}); topics: {every or 'none'}")
    raise ValueError(f"{path}: {len(events)} event topics, choose one with topic= (--topic): {listing}")


def _camera_topic(reader, event_topic: str, camera_topic: str | None) -> str | None:
    infos = _topics(reader, (CAMERA_INFO,))
    if camera_topic is not None:
        if camera_topic not in infos:
            raise ValueError(
                f"no {CAMERA_INFO} topic {camera_topic!r}; camera topics: {list(infos) or 'none'}"
            )
        return camera_topic
    beside = event_topic.rsplit("/", 1)[0] + "/camera_info"
    if beside in infos:
        return beside
    return next(iter(infos)) if len(infos) == 1 else None


def _camera(path: Path, reader, topic: str) -> tuple[Camera | None, tuple[int, int] | None]:
    """The first CameraInfo message of ``topic``: its camera (None when uncalibrated) and sensor size."""
    connections = [c for c in reader.connections if c.topic == topic]
    for connection, _, raw in reader.messages(connections=connections):
        msg = reader.deserialize(raw, connection.msgtype)
        k = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64)
        d = [float(v) for v in np.asarray(getattr(msg, "d", getattr(msg, "D", [])), dtype=np.float64)]
        size = (int(msg.width), int(msg.height)) if msg.width and msg.height else None
        where = f"{path}, {topic}"
        if k.shape != (9,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[4] <= 0:
            return None, size  # an uncalibrated camera publishes K = 0
        model = str(msg.distortion_model)
        if any(d) and model != "plumb_bob" and not (model == "rational_polynomial" and not any(d[5:])):
            warnings.warn(
                f"{where}: distortion model {model!r} ({len(d)} coefficients) is not the plumb_bob model "
                "that cmax_taichi.Camera applies: the camera is used without distortion",
                RuntimeWarning,
                stacklevel=4,
            )
            d = []
        try:
            return Camera(fx=k[0], fy=k[4], cx=k[2], cy=k[5], dist=tuple(d[:5])), size
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: not a usable camera ({exc})") from None
    return None, None


# --- decoding --------------------------------------------------------------------------------------
def _array_ros1(raw: bytes) -> tuple[np.ndarray, int, int]:
    """(events, width, height) of a ROS1-serialized EventArray."""
    (length,) = struct.unpack_from("<I", raw, 12)
    at = 16 + length
    height, width, n = struct.unpack_from("<III", raw, at)
    at += 12
    if len(raw) != at + n * _ROS1_EVENT.itemsize:
        raise ValueError(f"{len(raw)} bytes, but its header announces {n} events ({at + 13 * n} bytes)")
    return np.frombuffer(raw, dtype=_ROS1_EVENT, count=n, offset=at), width, height


def _array_cdr(raw: bytes) -> tuple[np.ndarray, int, int]:
    """(events, width, height) of a little-endian CDR EventArray (offsets after the 4-byte header)."""
    (length,) = struct.unpack_from("<I", raw, 4 + 8)
    at = 12 + length
    at += -at % 4
    height, width, n = struct.unpack_from("<III", raw, 4 + at)
    at += 12
    need = 0 if n == 0 else 13 if n == 1 else 16 * n - 3  # 14 bytes, then 16 each, the last 15
    body = len(raw) - 4 - at
    if not need <= body <= need + 3:  # a writer may pad the message to 4 bytes
        raise ValueError(f"{len(raw)} bytes, but its header announces {n} events")
    out = np.empty(n, dtype=_ROS1_EVENT)
    if n:
        if body < need + 1:  # the last event's 16 bytes run one past an unpadded message
            raw = bytes(raw) + b"\0"
        first = np.frombuffer(raw, dtype=_CDR_FIRST, count=1, offset=4 + at)
        rest = np.frombuffer(raw, dtype=_CDR_NEXT, count=n - 1, offset=4 + at + 14) if n > 1 else first[:0]
        for name in _ROS1_EVENT.names:
            out[name][:1] = first[name]
            out[name][1:] = rest[name]
    return out, width, height


def _array_generic(reader, raw: bytes, msgtype: str) -> tuple[np.ndarray, int, int]:
    """Any other serialization, through the rosbags deserializer (a Python object per event)."""
    msg = reader.deserialize(raw, msgtype)
    out = np.empty(len(msg.events), dtype=_ROS1_EVENT)
    for i, e in enumerate(msg.events):
        out[i] = (e.x, e.y, e.ts.sec, e.ts.nanosec, e.polarity)
    return out, int(msg.width), int(msg.height)


class _Sink:
    """Writes ``t x y p`` rows to the cache stream and keeps the checks and the metadata of a decode."""

    def __init__(self, out: BinaryIO, where: str, check_order: bool) -> None:
        self.out, self.where, self.check_order = out, where, check_order
        self.n = 0
        self.t_first = self.t_last = math.nan
        self.size: tuple[int, int] | None = None

    def add(self, t: np.ndarray, x, y, on, size: tuple[int, int], message: str) -> None:
        if not len(t):
            return
        W, H = size
        if W and H and (int(np.max(x)) >= W or int(np.max(y)) >= H):
            raise ValueError(
                f"{self.where}, {message}: x up to {int(np.max(x))}, y up to {int(np.max(y))} outside "
                f"its {W}x{H} sensor"
            )
        back = (self.n and t[0] < self.t_last) or np.any(np.diff(t) < 0)
        if self.check_order and back:
            raise ValueError(
                f"{self.where}, {message}: event times go backwards "
                "(open_recording(..., sort=True) sorts them)"
            )
        rows = np.empty((len(t), 4), dtype=np.float64)
        rows[:, 0], rows[:, 1], rows[:, 2] = t, x, y
        rows[:, 3] = np.where(on, 1.0, -1.0)
        self.out.write(rows.tobytes())
        if self.n == 0:
            self.t_first = float(t[0])
        self.t_last = float(t[-1])
        self.n += len(t)

    def meta(self, encoding: str) -> dict:
        return {
            "n": self.n, "t_start": self.t_first, "t_end": self.t_last,
            "sensor_size": None if self.size is None else list(self.size), "encoding": encoding,
        }  # fmt: skip


def _seconds(sec: np.ndarray, nsec: np.ndarray, where: str) -> np.ndarray:
    if len(nsec) and int(np.max(nsec)) >= 1_000_000_000:
        raise ValueError(f"{where}: a nanosecond field of {int(np.max(nsec))} (>= 1e9): not a ROS time")
    ns = sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64)
    return ns / 1e9  # one rounding of the exact integer: the float64 nearest to the decimal time


def _decode_arrays(reader, bag: Path, connections, msgtype: str, sink: _Sink, is2: bool) -> dict:
    for k, (connection, stamp, raw) in enumerate(reader.messages(connections=connections)):
        message = f"{connection.topic} message {k} (bag time {stamp} ns)"
        try:
            if not is2:
                events, W, H = _array_ros1(raw)
            elif raw[:2] == b"\x00\x01":
                events, W, H = _array_cdr(raw)
            else:
                events, W, H = _array_generic(reader, raw, msgtype)
        except (struct.error, ValueError) as exc:
            raise ValueError(f"{bag}, {message}: not a {msgtype} ({exc})") from None
        if sink.size is None and W and H:
            sink.size = (int(W), int(H))
        t = _seconds(events["sec"], events["nsec"], f"{bag}, {message}")
        sink.add(t, events["x"], events["y"], events["p"] != 0, (W, H), message)
    return sink.meta("events")


def _decode_packets(reader, bag: Path, connections, sink: _Sink, cache_dir) -> dict:
    """EventPackets: ``mono`` words decoded here; ``evt3`` / ``evt2`` payloads concatenated into a
    temporary RAW file (their decoder keeps state across packets) that faery decodes."""
    encoding = None
    raw_file = raw_path = None
    try:
        for k, (connection, stamp, data) in enumerate(reader.messages(connections=connections)):
            message = f"{connection.topic} message {k} (bag time {stamp} ns)"
            try:
                msg = reader.deserialize(data, connection.msgtype)
            except Exception as exc:  # rosbags' own errors for bytes that do not fit the type
                raise ValueError(f"{bag}, {message}: not a {PACKET_TYPE} ({exc})") from None
            name = str(msg.encoding).lower()
            if name not in ENCODINGS:
                raise ValueError(
                    f"{bag}, {message}: encoding {msg.encoding!r} is not decoded here; supported: "
                    f"{', '.join(ENCODINGS)}"
                )
            if encoding is None:
                encoding = name
                sink.size = (int(msg.width), int(msg.height)) if msg.width and msg.height else sink.size
            elif name != encoding:
                raise ValueError(f"{bag}, {message}: encoding {name!r} after {encoding!r} packets")
            payload = np.asarray(msg.events, dtype=np.uint8)
            if name == "mono":
                _mono(payload, msg, sink, (int(msg.width), int(msg.height)), f"{bag}, {message}", message)
                continue
            if raw_file is None:
                if sink.size is None:
                    raise ValueError(f"{bag}, {message}: no width and height (pass sensor_size=(W, H))")
                root = cache_root(cache_dir)
                root.mkdir(parents=True, exist_ok=True)
                fd, name_ = tempfile.mkstemp(prefix=".rosbag-", suffix=".raw", dir=root)
                raw_path, raw_file = Path(name_), os.fdopen(fd, "wb")
                version, label = _RAW_VERSIONS[name]
                W, H = sink.size
                raw_file.write(f"% evt {version}\n% format {label};width={W};height={H}\n% end\n".encode())
            if msg.is_bigendian:
                word = 2 if name == "evt3" else 4
                payload = payload.view(f">u{word}").astype(f"<u{word}").view(np.uint8)
            raw_file.write(payload.tobytes())
        if raw_file is not None:
            raw_file.close()
            raw_file = None
            _decode_raw(raw_path, encoding, sink, bag)
    finally:
        if raw_file is not None:
            raw_file.close()
        if raw_path is not None:
            raw_path.unlink(missing_ok=True)
    return sink.meta(encoding or "none")


def _mono(payload: np.ndarray, msg, sink: _Sink, size, where: str, message: str) -> None:
    if len(payload) % 8:
        raise ValueError(f"{where}: {len(payload)} payload bytes is not a whole number of 8-byte mono words")
    words = payload.view(">u8" if msg.is_bigendian else "<u8").astype(np.uint64)
    dt = (words & np.uint64(0xFFFFFFFF)).astype(np.int64)
    x = (words >> np.uint64(32)) & np.uint64(0xFFFF)
    y = (words >> np.uint64(48)) & np.uint64(0x7FFF)
    on = (words >> np.uint64(63)) != 0
    t = (int(msg.time_base) + dt) / 1e9
    sink.add(t, x, y, on, size, message)


def _decode_raw(raw_path: Path, encoding: str, sink: _Sink, bag: Path) -> None:
    """The EVT words of ``raw_path`` through faery, packet by packet, into ``sink``."""
    from cmax_taichi.io.faery_formats import _faery_decoder

    what = f"{encoding.upper()} payload of {bag}"
    decoder = _faery_decoder(raw_path, "evt", sink.size, encoding, what)
    try:
        for k, packet in enumerate(decoder):
            sink.add(packet["t"] / 1e6, packet["x"], packet["y"], packet["on"], sink.size, f"EVT packet {k}")
    except ValueError:
        raise
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # the Rust decoder raises plain exceptions on corrupt words
        raise ValueError(
            f"{bag}: cannot decode the {encoding} payloads after {sink.n} events ({exc})"
        ) from None


class RosbagRecording(CachedTableReads, Recording):
    """The events of one topic of a ROS1 or ROS2 bag (see the module docstring).

    Parameters
    ----------
    path : path
        A ROS1 ``.bag`` file, or a ROS2 bag folder (``metadata.yaml`` and ``.db3`` / ``.mcap`` files)
        or one of its storage files.
    topic : str, optional
        The event topic; needed when the bag has several (the error lists them).
    camera_topic : str, optional
        The ``sensor_msgs/CameraInfo`` topic; default the one beside the event topic, or the only one.
    sensor_size : (int, int), optional
        ``(W, H)`` px; default the camera info's, else the first event message's.
    camera : Camera, optional
        Replaces the camera of the camera info.
    cache_dir, cache, sort
        As for the text formats (:class:`~.text.TextRecording`).

    Attributes
    ----------
    topic : str
    msgtype : str
        The topic's message type (``dvs_msgs/msg/EventArray``, ...).
    encoding : str
        ``"events"`` for the EventArray types, else the EventPacket encoding.
    """

    format = "rosbag"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        topic: str | None = None,
        camera_topic: str | None = None,
        sensor_size: tuple[int, int] | None = None,
        camera: Camera | None = None,
        cache_dir: str | os.PathLike | None = None,
        cache: bool = True,
        sort: bool = False,
    ) -> None:
        path = Path(path)
        bag, files = _bag_paths(path)
        if sensor_size is not None:
            sensor_size = checks.sensor_size(sensor_size, where=str(path))
        with _open_bag(bag) as reader:
            self.topic, self.msgtype = _choose_topic(bag, reader, topic)
            info_topic = _camera_topic(reader, self.topic, camera_topic)
            info_camera, info_size = _camera(bag, reader, info_topic) if info_topic else (None, None)
            connections = [c for c in reader.connections if c.topic == self.topic]
            is2 = bool(reader.is2)

            def decode(out: BinaryIO) -> dict:
                sink = _Sink(out, str(bag), check_order=not sort)
                sink.size = sensor_size or info_size
                if self.msgtype == PACKET_TYPE:
                    return _decode_packets(reader, bag, connections, sink, cache_dir)
                return _decode_arrays(reader, bag, connections, self.msgtype, sink, is2)

            stats = [[f.name, f.stat().st_size, f.stat().st_mtime_ns] for f in files]
            key = {"topic": self.topic, "sensor_size": None if sensor_size is None else list(sensor_size),
                   "files": stats}  # fmt: skip
            source = next((f for f in files if f.suffix in _STORAGE_SUFFIXES), files[0])
            meta = self._load_table(
                source, "rosbag", key, decode, cache_dir=cache_dir, cache=cache, sort=sort
            )
        self.encoding = str(meta.get("encoding", "events"))
        self.camera_topic = info_topic
        size = sensor_size or info_size or (tuple(meta["sensor_size"]) if meta.get("sensor_size") else None)
        if size is None:
            if not meta["n"]:
                raise ValueError(f"{bag}, {self.topic}: no events and no sensor size (pass sensor_size=)")
            column = self._table[:, 1:3]
            size = (int(column[:, 0].max()) + 1, int(column[:, 1].max()) + 1)
        super().__init__(
            path,
            sensor_size=size,
            camera=camera if camera is not None else info_camera,
            undistorted=False,
            **self.table_span(meta),
        )
