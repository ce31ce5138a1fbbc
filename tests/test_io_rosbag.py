"""ROS bag reader (optional package ``rosbags``): ROS1 and ROS2 bags written by ``rosbags`` from the shared
ECD cut read back as its text file, and estimate as it; the three event message types, the topic
choice, the camera info, the NumPy decoders against ``rosbags``' own deserializer, and malformed bags."""

from __future__ import annotations

import struct
import warnings

import numpy as np
import pytest
from conftest import shared_data_dir
from hypothesis import given, settings
from hypothesis import strategies as st

from cmax_taichi.core.events import Camera, Events
from cmax_taichi.io import detect_format, open_recording

rosbags = pytest.importorskip(
    "rosbags", reason="the ROS bag reader needs 'rosbags': pip install rosbags (or cmax-taichi[rosbag])"
)

from cmax_taichi.io import rosbag  # noqa: E402
from cmax_taichi.testing.bags import event_times_ns, ros1_event_array_bytes, write_event_bag  # noqa: E402

pytestmark = pytest.mark.usefixtures("cache_in_tmp")
CUT = ("ecd_rotation", "shapes_rotation")


def _cut():
    with open_recording(shared_data_dir(*CUT)) as rec:
        return rec.read(), rec.camera


def _same(a: Events, b: Events) -> None:
    for name in "xytp":
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _ns_text_copy(events: Events, folder):
    """The cut as a text file whose times are the integer nanoseconds a ROS time holds."""
    from pathlib import Path

    path = Path(folder) / "events.txt"
    sec, nsec = np.divmod(event_times_ns(events.t), 10**9)
    rows = zip(sec, nsec, events.x, events.y, events.p, strict=True)
    path.write_text("".join(f"{s}.{n:09d} {int(x)} {int(y)} {int(p > 0)}\n" for s, n, x, y, p in rows))
    return path


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_ecd_cut_bag_reads_and_estimates_as_its_text(tmp_path, ros2):
    from cmax_taichi.solve.sequence import process

    events, camera = _cut()
    bag = write_event_bag(tmp_path / ("cut" if ros2 else "cut.bag"), events, ros2=ros2, camera=camera)
    assert detect_format(bag) == "rosbag"
    (tmp_path / "text").mkdir()
    text = _ns_text_copy(events, tmp_path / "text")
    with open_recording(bag) as rec, open_recording(text, format="ecd") as txt:
        assert rec.format == "rosbag" and rec.topic == "/dvs/events" and rec.encoding == "events"
        assert rec.sensor_size == (240, 180) and rec.camera == camera and rec.n_events == len(events)
        read = rec.read()
        _same(read, txt.read())  # the text of the same nanoseconds: identical
        # the shared text's times carry float noise below the nanosecond ("2.097134999000002"): 1 ulp
        for name in "xyp":
            np.testing.assert_array_equal(getattr(read, name), getattr(events, name))
        assert np.max(np.abs(np.asarray(read.t) - events.t)) <= 4e-15
        options = dict(camera=camera, n_events=8000, max_windows=2, progress=False, compute_fwl=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from_bag = process(rec, "rotation3", **options)
            from_text = process(txt, "rotation3", **options)
    assert len(from_bag.windows) == 2
    np.testing.assert_array_equal(from_bag.theta, from_text.theta)  # exactly the same estimates


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
@pytest.mark.parametrize(
    "msgtype, encoding",
    [("prophesee_event_msgs/msg/EventArray", None), ("event_camera_msgs/msg/EventPacket", "evt3"),
     ("event_camera_msgs/msg/EventPacket", "evt2")],
)  # fmt: skip
def test_other_message_types(tmp_path, ros2, msgtype, encoding):
    pytest.importorskip("faery") if encoding else None
    events, camera = _cut()
    events = events[:6000]
    options = {"encoding": encoding, "per_message": 777} if encoding else {}
    bag = write_event_bag(
        tmp_path / ("b" if ros2 else "b.bag"), events, ros2=ros2, msgtype=msgtype, **options
    )
    with open_recording(bag) as rec:
        assert rec.msgtype == msgtype and rec.encoding == (encoding or "events") and rec.camera is None
        read = rec.read()
    for name in "xyp":
        np.testing.assert_array_equal(getattr(read, name), getattr(events, name))
    if encoding:  # EVT words hold whole microseconds of the camera clock
        np.testing.assert_array_equal(read.t, np.rint(events.t * 1e6) / 1e6)
    else:
        np.testing.assert_array_equal(read.t, event_times_ns(events.t) / 1e9)


def test_mono_packets(tmp_path):
    """``mono`` words: polarity bit 63, y bits 48-62, x bits 32-47, dt (ns) bits 0-31 after time_base."""
    store = rosbag.typestore(False)
    types = store.types
    from rosbags.rosbag1 import Writer

    x, y, on, dt = (
        np.array([3, 9, 239]),
        np.array([0, 5, 179]),
        np.array([1, 0, 1]),
        np.array([10, 500, 7000]),
    )
    words = dt.astype(np.uint64) | (x.astype(np.uint64) << 32) | (y.astype(np.uint64) << 48)
    words |= on.astype(np.uint64) << 63
    header = types["std_msgs/msg/Header"](seq=0, stamp=types["builtin_interfaces/msg/Time"](sec=5, nanosec=0),
                                          frame_id="")  # fmt: skip
    packet = types[rosbag.PACKET_TYPE](header=header, height=180, width=240, seq=0, time_base=5_000_000_000,
                                      encoding="mono", is_bigendian=False,
                                      events=words.astype("<u8").view(np.uint8))  # fmt: skip
    with Writer(tmp_path / "m.bag") as writer:
        connection = writer.add_connection("/events", rosbag.PACKET_TYPE, typestore=store)
        writer.write(connection, 5, store.serialize_ros1(packet, rosbag.PACKET_TYPE))
    with open_recording(tmp_path / "m.bag") as rec:
        read = rec.read()
    np.testing.assert_array_equal(read.x, x)
    np.testing.assert_array_equal(read.y, y)
    np.testing.assert_array_equal(read.p, np.where(on > 0, 1, -1))
    np.testing.assert_array_equal(read.t, (5_000_000_000 + dt) / 1e9)


def test_topic_choice_and_errors(tmp_path):
    events, _ = _cut()
    a, b = events[:3000], events[3000:6000]
    bag = write_event_bag(tmp_path / "two.bag", a, ros2=False, extra_topics={"/right/events": b})
    with pytest.raises(ValueError, match=r"2 event topics.*topic=.*/dvs/events.*/right/events"):
        open_recording(bag)
    assert set(rosbag.event_topics(bag)) == {"/dvs/events", "/right/events"}
    with open_recording(bag, topic="/right/events") as rec:
        _same(rec.read(), Events(b.x, b.y, event_times_ns(b.t) / 1e9, b.p, b.sensor_size))
    with pytest.raises(ValueError, match=r"no topic '/nope'.*event topics: /dvs/events"):
        open_recording(bag, topic="/nope")


def test_camera_topic_and_non_event_topic(tmp_path):
    events, camera = _cut()
    bag = write_event_bag(tmp_path / "c", events[:2000], ros2=True, camera=camera, topic="/cam0/events")
    with open_recording(bag) as rec:
        assert rec.camera_topic == "/cam0/camera_info" and rec.camera == camera
    with pytest.raises(ValueError, match=r"holds sensor_msgs/msg/CameraInfo, not events"):
        open_recording(bag, topic="/cam0/camera_info")
    with open_recording(bag, camera=Camera(100.0, 100.0, 50.0, 40.0)) as rec:
        assert rec.camera.fx == 100.0


def _raw_bag(path, payloads: list[bytes]):
    from rosbags.rosbag1 import Writer

    store = rosbag.typestore(False)
    with Writer(path) as writer:
        connection = writer.add_connection("/dvs/events", "dvs_msgs/msg/EventArray", typestore=store)
        for k, data in enumerate(payloads):
            writer.write(connection, k + 1, data)
    return path


def _array(t_ns, x=None, width=240, height=180):
    n = len(t_ns)
    x = np.arange(n) % width if x is None else np.asarray(x)
    return ros1_event_array_bytes(x, np.arange(n) % height, np.asarray(t_ns), np.ones(n, bool), width, height)


@pytest.mark.parametrize(
    "payloads, match",
    [
        ([_array([1, 2, 3])[:-5]], r"message 0 .*not a dvs_msgs/msg/EventArray .*announces 3 events"),
        ([_array([1, 2]), _array([1])], r"message 1 .*times go backwards.*sort=True"),
        ([_array([1, 2], x=[5, 240])], r"message 0.*x up to 240.*outside its 240x180 sensor"),
        (
            [_array([1])[:-9] + struct.pack("<II", 0, 1_500_000_000) + b"\x01"],
            r"nanosecond field of 1500000000",
        ),
    ],
    ids=["truncated", "backwards", "outside", "nanoseconds"],
)
def test_malformed_messages(tmp_path, payloads, match):
    bag = _raw_bag(tmp_path / "bad.bag", payloads)
    with pytest.raises(ValueError, match=match):
        open_recording(bag)


def test_sort_and_no_events(tmp_path):
    bag = _raw_bag(tmp_path / "b.bag", [_array([5, 6]), _array([1, 2])])
    with open_recording(bag, sort=True) as rec:
        np.testing.assert_array_equal(rec.read().t, np.array([1, 2, 5, 6]) / 1e9)
        assert rec.rows_out_of_order == 1
    plain = tmp_path / "plain.bag"
    from rosbags.rosbag1 import Writer

    with Writer(plain) as writer:
        store = rosbag.typestore(False)
        connection = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        del connection
    with pytest.raises(ValueError, match=r"no topic of events.*/imu \(sensor_msgs/msg/Imu\)"):
        open_recording(plain)
    with pytest.raises(ValueError, match="not a readable ROS1 bag"):
        open_recording(_garbage(tmp_path / "junk.bag"))


def _garbage(path):
    path.write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 4)
    return path


_event = st.tuples(
    st.integers(0, 239),
    st.integers(0, 179),
    st.integers(0, 2**31 - 1),
    st.integers(0, 999_999_999),
    st.booleans(),
)


@settings(max_examples=40, deadline=None)
@given(events=st.lists(_event, max_size=9), frame=st.text(max_size=7), ros2=st.booleans())
def test_numpy_decoders_match_rosbags(events, frame, ros2):
    """The NumPy decoding of an EventArray equals rosbags' deserializer, for any event count and any
    frame id (which moves the CDR alignment of what follows)."""
    store = rosbag.typestore(ros2)
    T = store.types
    time = T["builtin_interfaces/msg/Time"]
    header = (T["std_msgs/msg/Header"](stamp=time(sec=1, nanosec=2), frame_id=frame) if ros2 else
              T["std_msgs/msg/Header"](seq=3, stamp=time(sec=1, nanosec=2), frame_id=frame))  # fmt: skip
    items = [
        T["dvs_msgs/msg/Event"](x=x, y=y, ts=time(sec=s, nanosec=n), polarity=p) for x, y, s, n, p in events
    ]
    message = T["dvs_msgs/msg/EventArray"](header=header, height=180, width=240, events=items)
    if ros2:
        decoded, W, H = rosbag._array_cdr(bytes(store.serialize_cdr(message, "dvs_msgs/msg/EventArray")))
    else:
        decoded, W, H = rosbag._array_ros1(bytes(store.serialize_ros1(message, "dvs_msgs/msg/EventArray")))
    assert (W, H) == (240, 180)
    expected = [(x, y, s, n, int(p)) for x, y, s, n, p in events]
    assert [tuple(int(v) for v in row) for row in decoded.tolist()] == expected


def test_numpy_serializer_matches_rosbags():
    store = rosbag.typestore(False)
    T = store.types
    t_ns = np.array([1_000_000_001, 2_000_000_500])
    ours = ros1_event_array_bytes([1, 2], [3, 4], t_ns, [True, False], 240, 180, seq=7, frame_id="f")
    time = T["builtin_interfaces/msg/Time"]
    items = [T["dvs_msgs/msg/Event"](x=1, y=3, ts=time(sec=1, nanosec=1), polarity=True),
             T["dvs_msgs/msg/Event"](x=2, y=4, ts=time(sec=2, nanosec=500), polarity=False)]  # fmt: skip
    header = T["std_msgs/msg/Header"](seq=7, stamp=time(sec=1, nanosec=1), frame_id="f")
    message = T["dvs_msgs/msg/EventArray"](header=header, height=180, width=240, events=items)
    assert ours == bytes(store.serialize_ros1(message, "dvs_msgs/msg/EventArray"))


def test_missing_package_names_it(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(ImportError, match=r"needs the optional package 'rosbags'.*cmax-taichi\[rosbag\]"):
        rosbag._rosbags(tmp_path / "x.bag")
