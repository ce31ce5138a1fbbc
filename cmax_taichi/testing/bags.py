"""ROS bags of events written with ``rosbags``, for the tests and the benchmarks of the bag reader
(:mod:`cmax_taichi.io.rosbag`).

:func:`write_event_bag` writes an :class:`~cmax_taichi.Events` as a ROS1 ``.bag`` or a ROS2 bag folder of
``dvs_msgs/EventArray`` / ``prophesee_event_msgs/EventArray`` messages (serialized by ``rosbags``
itself, the independent check of the reader's NumPy decoding) or of ``event_camera_msgs/EventPacket``
messages whose EVT 3.0 / 2.0 payloads ``faery`` encodes, with an optional ``sensor_msgs/CameraInfo``.
:func:`ros1_event_array_bytes` serializes an EventArray with NumPy (for multi-GB bags: ``rosbags``'
serializer takes about a microsecond per event), and is checked against ``rosbags``' bytes.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.io.rosbag import _ROS1_EVENT, PACKET_TYPE, typestore

__all__ = ["event_times_ns", "ros1_event_array_bytes", "write_event_bag"]


def event_times_ns(t: np.ndarray) -> np.ndarray:
    """Integer nanoseconds of times in seconds (exact for times written with at most 9 decimals)."""
    return np.rint(np.asarray(t, dtype=np.float64) * 1e9).astype(np.int64)


def ros1_event_array_bytes(
    x, y, t_ns, on, width: int, height: int, seq: int = 0, frame_id: str = ""
) -> bytes:
    """A ``dvs_msgs/EventArray`` serialized for ROS1 with NumPy (the header stamped with the first event)."""
    n = len(t_ns)
    events = np.empty(n, dtype=_ROS1_EVENT)
    events["x"], events["y"] = x, y
    events["sec"], events["nsec"] = np.divmod(np.asarray(t_ns, dtype=np.int64), 1_000_000_000)
    events["p"] = np.asarray(on, dtype=bool)
    stamp = divmod(int(t_ns[0]), 1_000_000_000) if n else (0, 0)
    frame = frame_id.encode()
    head = np.array([seq, stamp[0], stamp[1], len(frame)], dtype="<u4").tobytes() + frame
    return head + np.array([height, width, n], dtype="<u4").tobytes() + events.tobytes()


def _camera_info(store, camera: Camera, size: tuple[int, int], stamp, ros2: bool):
    types = store.types
    header = _header(store, stamp, "camera", ros2)
    k = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], dtype=np.float64)
    p = np.array([camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0], dtype=np.float64)
    roi = types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    fields = dict(header=header, height=size[1], width=size[0], distortion_model="plumb_bob",
                  binning_x=0, binning_y=0, roi=roi)  # fmt: skip
    names = ("d", "k", "r", "p") if ros2 else ("D", "K", "R", "P")
    values = (np.array(camera.dist, dtype=np.float64), k, np.eye(3).ravel(), p)
    fields.update(zip(names, values, strict=True))
    return types["sensor_msgs/msg/CameraInfo"](**fields)


def _header(store, stamp_ns: int, frame_id: str, ros2: bool, seq: int = 0):
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    time = store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    if ros2:
        return store.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)
    return store.types["std_msgs/msg/Header"](seq=seq, stamp=time, frame_id=frame_id)


def _array_messages(store, events: Events, msgtype: str, per_message: int, ros2: bool):
    package = msgtype.split("/")[0]
    Event = store.types[f"{package}/msg/Event"]
    Time = store.types["builtin_interfaces/msg/Time"]
    Array = store.types[msgtype]
    W, H = events.sensor_size
    t_ns = event_times_ns(events.t)
    for k, a in enumerate(range(0, len(events), per_message)):
        sl = slice(a, a + per_message)
        sec, nsec = np.divmod(t_ns[sl], 1_000_000_000)
        items = [
            Event(x=int(x), y=int(y), ts=Time(sec=int(s), nanosec=int(n)), polarity=bool(p > 0))
            for x, y, s, n, p in zip(events.x[sl], events.y[sl], sec, nsec, events.p[sl], strict=True)
        ]
        header = _header(store, int(t_ns[sl][-1]), "camera" + "_" * (k % 4), ros2, seq=k)  # varied alignment
        yield int(t_ns[sl][-1]), Array(header=header, height=H, width=W, events=items)


def _packet_messages(store, events: Events, encoding: str, per_message: int, ros2: bool):
    """EventPackets of the EVT words ``faery`` writes for ``events`` (times in whole microseconds), cut
    every ``per_message`` words; stamped with the time of the first event."""
    import faery

    from cmax_taichi.io.faery_formats import read_header

    array = np.zeros(len(events), dtype=faery.EVENTS_DTYPE)
    array["t"] = np.rint(np.asarray(events.t) * 1e6).astype(np.uint64)
    array["x"], array["y"], array["on"] = events.x, events.y, np.asarray(events.p) > 0
    with tempfile.TemporaryDirectory() as folder:
        raw = Path(folder) / "events.raw"
        faery.events_stream_from_array(array, dimensions=tuple(events.sensor_size)).to_file(
            raw, version=encoding, zero_t0=False
        )
        _, length = read_header(raw)
        payload = np.frombuffer(raw.read_bytes()[length:], dtype=np.uint8)
    word = 2 if encoding == "evt3" else 4
    W, H = events.sensor_size
    Packet = store.types[PACKET_TYPE]
    stamp = int(event_times_ns(events.t[:1])[0]) if len(events) else 0
    for k, a in enumerate(range(0, len(payload), per_message * word)):
        chunk = payload[a : a + per_message * word].copy()
        header = _header(store, stamp, "camera", ros2, seq=k)
        yield stamp, Packet(header=header, height=H, width=W, seq=k, time_base=0, encoding=encoding,
                            is_bigendian=False, events=chunk)  # fmt: skip


def write_event_bag(
    path: str | os.PathLike,
    events: Events,
    *,
    ros2: bool,
    msgtype: str = "dvs_msgs/msg/EventArray",
    topic: str = "/dvs/events",
    per_message: int = 5000,
    camera: Camera | None = None,
    encoding: str = "evt3",
    extra_topics: dict[str, Events] | None = None,
) -> Path:
    """Write ``events`` as a bag at ``path`` (a ``.bag`` file, or a ROS2 bag folder that must not exist).

    Parameters
    ----------
    ros2 : bool
        A ROS2 bag (sqlite3 storage, CDR messages) or a ROS1 bag.
    msgtype : str
        ``dvs_msgs/msg/EventArray``, ``prophesee_event_msgs/msg/EventArray`` or
        ``event_camera_msgs/msg/EventPacket`` (then ``encoding`` ``"evt3"`` or ``"evt2"``, and
        ``per_message`` counts words).
    per_message : int
        Events (words) per message.
    camera : Camera, optional
        Also write one ``sensor_msgs/CameraInfo`` on ``<namespace>/camera_info``.
    extra_topics : dict, optional
        More event topics (same message type), e.g. to make the topic ambiguous.
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2

    path = Path(path)
    store = typestore(ros2)
    serialize = store.serialize_cdr if ros2 else store.serialize_ros1
    writer = Writer2(path, version=9) if ros2 else Writer1(path)
    with writer:
        streams = {topic: events, **(extra_topics or {})}
        for name, source in streams.items():
            connection = writer.add_connection(name, msgtype, typestore=store)
            if msgtype == PACKET_TYPE:
                messages = _packet_messages(store, source, encoding, per_message, ros2)
            else:
                messages = _array_messages(store, source, msgtype, per_message, ros2)
            for stamp, message in messages:
                writer.write(connection, stamp, serialize(message, msgtype))
        if camera is not None:
            info = topic.rsplit("/", 1)[0] + "/camera_info"
            connection = writer.add_connection(info, "sensor_msgs/msg/CameraInfo", typestore=store)
            stamp = int(event_times_ns(events.t[:1])[0]) if len(events) else 0
            message = _camera_info(store, camera, events.sensor_size, stamp, ros2)
            writer.write(connection, stamp, serialize(message, "sensor_msgs/msg/CameraInfo"))
    return path
