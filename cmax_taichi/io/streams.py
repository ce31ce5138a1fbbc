"""Events that arrive over time: live sources behind one small protocol, :class:`EventStream`.

:func:`open_stream` opens

* ``tcp://HOST:PORT``: an event stream of iniVation's dv-processing (``dv_processing.io.NetworkReader``;
  a DV software output, a ``NetworkWriter``, :func:`serve_replay`), needs the optional package
  ``dv-processing`` (``pip install "cmax-taichi[live]"``);
* ``camera`` or ``camera:SERIAL``: a camera that dv-processing opens (DAVIS, DVXplorer);
* a recording (any path :func:`~cmax_taichi.io.open_recording` opens, or an open
  :class:`~cmax_taichi.io.Recording` or :class:`~cmax_taichi.Events`), replayed at its recorded speed or
  ``speed`` times it, ``loops`` times (:class:`ReplayStream`).

A stream hands out :class:`EventPacket` s (``t`` in seconds of the source's clock, ``x, y`` px, ``p``
+-1, and the wall time the packet arrived) through :meth:`EventStream.read`, which waits at most a
timeout, and says when it has :attr:`~EventStream.ended`. The dv-processing sources run their reader
in a child process: dv-processing's reader holds the interpreter while it blocks (a server that accepts
and never sends would freeze the whole process) and aborts the process on some malformed packets
(``std::length_error`` for a bad length field); in a child these become one clear error of the stream
(:class:`StreamError`), after the packets received before it, and a source that does not open within
``connect_timeout`` is given up.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cmax_taichi.core import checks
from cmax_taichi.core.events import Camera, Events

__all__ = [
    "EventPacket",
    "EventStream",
    "ReplayStream",
    "DvStream",
    "StreamError",
    "open_stream",
    "ReplayServer",
    "serve_replay",
    "start_replay_server",
]

PACKAGE = "dv-processing"
EXTRA = "live"
#: events the reader process of a dv-processing source holds for a parent that does not read them (then
#: the oldest are dropped, and counted: :attr:`EventStream.dropped`)
CHILD_BACKLOG_EVENTS = 1_000_000
#: seconds of data per packet of a replay (a camera's driver sends about a packet per millisecond)
PACKET_SECONDS = 0.001


class StreamError(OSError):
    """A live source failed (its reader died, the connection broke, it is not an event stream)."""


@dataclass
class EventPacket:
    """Events that arrived together: ``t`` (s, float64, the source's clock), ``x``, ``y`` (px), ``p``
    (+1 / -1), and ``arrival``, the wall time (``time.perf_counter``) the packet was received."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray
    arrival: float

    def __len__(self) -> int:
        return len(self.t)


class EventStream:
    """A source of events that arrive over time (see the module docstring).

    Attributes
    ----------
    address : str
        What was opened (``tcp://...``, ``camera``, the replayed recording).
    sensor_size : (int, int)
        ``(W, H)``, px.
    camera : Camera or None
        Intrinsics where the source gives them (a replayed recording) or the caller does.
    dropped : int
        Events the source dropped before they could be read (a reader that did not keep up).
    """

    address: str = ""
    dropped: int = 0
    sensor_size: tuple[int, int] = (0, 0)
    camera: Camera | None = None
    _ended = False

    def read(self, timeout: float) -> EventPacket | None:
        """The next packet, waiting at most ``timeout`` seconds; None when none came (or the stream
        ended: see :attr:`ended`). Raises :class:`StreamError` when the source failed."""
        raise NotImplementedError

    @property
    def ended(self) -> bool:
        """Whether the source has no more events (a replay that finished, a server that closed)."""
        return self._ended

    def close(self) -> None:
        """Release the source (a child process, a connection); reading afterwards gives nothing."""
        self._ended = True

    def __enter__(self) -> EventStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        W, H = self.sensor_size
        return f"{type(self).__name__}({self.address!r}, sensor={W}x{H})"


# --- a recording replayed ----------------------------------------------------------------------------
class ReplayStream(EventStream):
    """A recording replayed at its recorded speed times ``speed``, ``loops`` times, in packets of
    ``packet_seconds`` of data, each handed out when the wall clock reaches the time of its last event.

    Each loop after the first is shifted by the recording's span plus one packet, so that time keeps
    increasing. The replay's clock starts at the first :meth:`read` (or :meth:`start`); a reader that
    falls behind gets the packets that are due at once.

    Parameters
    ----------
    source : Recording, Events or path
        What to replay (a path is opened with :func:`~cmax_taichi.io.open_recording` and closed with
        the stream).
    speed : float
        Replay speed, a multiple of the recorded speed (default 1).
    loops : int
        Times the recording is played (default 1).
    packet_seconds : float
        Data per packet, s.
    camera : Camera, optional
        Replaces the recording's camera.
    """

    def __init__(
        self,
        source,
        *,
        speed: float = 1.0,
        loops: int = 1,
        packet_seconds: float = PACKET_SECONDS,
        camera: Camera | None = None,
        **recording_options,
    ) -> None:
        self.speed = checks.seconds("speed", speed, positive=True)
        self.loops = checks.whole_number("loops", loops, 1)
        self.packet_seconds = checks.seconds("packet_seconds", packet_seconds, positive=True)
        self._owned = None
        if isinstance(source, (str, os.PathLike)):
            from cmax_taichi.io import open_recording

            source = self._owned = open_recording(source, **recording_options)
        if isinstance(source, Events):
            if not len(source):
                raise ValueError("nothing to replay: no events")
            self._events = source
            self.address = f"Events(n={len(source)})"
            self.sensor_size, base_camera, self.n_events = tuple(source.sensor_size), None, len(source)
        elif hasattr(source, "read_time"):
            source.check_times()
            if not source.n_events:
                raise ValueError(f"{source.path}: nothing to replay: no events")
            self._events = None
            self._recording = source
            self.address = str(source.path)
            self.sensor_size, base_camera, self.n_events = source.sensor_size, source.camera, source.n_events
        else:
            raise TypeError(f"a replay needs a Recording, Events or a path, got {type(source).__name__}")
        self.camera = camera if camera is not None else base_camera
        self._packets = self._generate()
        self._wall0: float | None = None
        self._t0 = math.nan
        self._pending: EventPacket | None = None

    def _slices(self) -> Iterator[tuple[np.ndarray, ...]]:
        """(t, x, y, p) of one loop, packet by packet (bounded memory: a recording is read by time)."""
        if self._events is not None:
            ev = self._events
            t = np.asarray(ev.t)
            edges = np.searchsorted(t, np.arange(t[0], t[-1] + self.packet_seconds, self.packet_seconds))
            edges = np.unique(np.concatenate([edges, [len(t)]]))
            start = 0
            for stop in edges[1:]:
                yield t[start:stop], ev.x[start:stop], ev.y[start:stop], ev.p[start:stop]
                start = stop
            return
        rec = self._recording
        block = max(1, int(round(0.25 / self.packet_seconds)))  # read a quarter second at a time
        t_read = rec.t_start
        while t_read <= rec.t_end:
            t_next = t_read + block * self.packet_seconds
            i0, i1 = (
                rec._search_time(t_read),
                rec._search_time(t_next) if t_next <= rec.t_end else rec.n_events,
            )
            x, y, t, p = rec._columns(i0, i1)
            t = np.asarray(t, dtype=np.float64)
            edges = np.searchsorted(t, t_read + self.packet_seconds * np.arange(1, block + 1))
            start = 0
            for stop in np.unique(np.concatenate([edges, [len(t)]])):
                if stop > start:
                    yield t[start:stop], np.asarray(x[start:stop]), np.asarray(y[start:stop]), p[start:stop]
                start = stop
            t_read = t_next

    def _generate(self) -> Iterator[tuple[np.ndarray, ...]]:
        if self._events is not None:
            first, last = float(self._events.t[0]), float(self._events.t[-1])
        else:
            first, last = self._recording.t_start, self._recording.t_end
        period = last - first + self.packet_seconds  # a loop's shift: the next loop follows one packet later
        for loop in range(self.loops):
            for t, x, y, p in self._slices():
                if len(t):
                    yield t + loop * period, x, y, np.where(np.asarray(p) > 0, 1, -1).astype(np.int8)

    def start(self) -> None:
        """Start the replay's clock now (the first :meth:`read` does it otherwise)."""
        if self._wall0 is None:
            self._wall0 = time.perf_counter()

    def due(self, t: float) -> float:
        """The wall time (``time.perf_counter``) at which data time ``t`` is replayed."""
        return self._wall0 + (t - self._t0) / self.speed

    def read(self, timeout: float) -> EventPacket | None:
        if self._ended:
            return None
        self.start()
        if self._pending is None:
            nxt = next(self._packets, None)
            if nxt is None:
                self._ended = True
                return None
            if math.isnan(self._t0):
                self._t0 = float(nxt[0][0])
            self._pending = EventPacket(*nxt, arrival=math.nan)
        packet = self._pending
        wait = self.due(float(packet.t[-1])) - time.perf_counter()
        if wait > timeout:
            time.sleep(max(0.0, timeout))
            return None
        if wait > 0:
            time.sleep(wait)
        self._pending = None
        packet.arrival = time.perf_counter()
        return packet

    def close(self) -> None:
        super().close()
        if self._owned is not None:
            self._owned.close()
            self._owned = None


# --- dv-processing sources, in a child process ------------------------------------------------------------
def _dv(what: str):
    try:
        import dv_processing
    except ImportError:
        raise ImportError(
            f"{what} needs the optional package '{PACKAGE}': pip install \"cmax-taichi[{EXTRA}]\"  "
            f"(or pip install {PACKAGE})"
        ) from None
    return dv_processing


def _dv_child(conn, kind: str, target: str, port: int, timeout: float) -> None:
    """The child process of a :class:`DvStream`: open the source, say hello, forward each event batch as
    a structured array until the source ends; an error goes back as one message."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when this ends
    try:
        dv = _dv(f"a dv-processing {kind}")
        conn.send(("started",))  # the parent's timeout for opening the source starts now
        if kind == "tcp":
            reader = dv.io.NetworkReader(target, port)
            if not reader.isEventStreamAvailable():
                raise ConnectionError("the stream has no events")
        else:
            found = dv.io.camera.discover()
            if not found:
                raise ConnectionError("no camera that dv-processing can open is connected")
            reader = dv.io.camera.open(target) if target else dv.io.camera.open()
        size = reader.getEventResolution()
        if size is None:
            raise ConnectionError("the source gives no event resolution")
        conn.send(("hello", (int(size[0]), int(size[1])), str(reader.getCameraName())))
    except Exception as exc:  # any failure to open: one message, then this process ends
        reason = str(exc).split(" [", 1)[0]  # without boost's source location
        conn.send(("error", f"{type(exc).__name__}: {reason}"))
        return
    _forward(reader, conn)


def _forward(reader, conn) -> None:
    """Take every batch from ``reader`` at once (dv-processing drops the batches it still holds when the
    connection closes) and send them to the parent from a thread, holding at most
    :data:`CHILD_BACKLOG_EVENTS` (beyond, the oldest are dropped and counted in an ``"overflow"``
    message); ``"end"`` once the source closed and everything was sent."""
    import collections
    import threading

    pending: collections.deque = collections.deque()
    held = [0, 0]  # events held, events dropped since the last report
    cond = threading.Condition()
    finished = []

    def send() -> None:
        while True:
            with cond:
                while not pending and not finished:
                    cond.wait()
                if not pending:
                    break
                batch, dropped = pending.popleft(), held[1]
                held[0] -= len(batch)
                held[1] = 0
            if dropped:
                conn.send(("overflow", dropped))
            conn.send(("events", batch))
        conn.send(("end", finished[0]))

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    while True:
        batch = reader.getNextEventBatch()
        if batch is None:
            if not reader.isRunning():
                break
            time.sleep(0.0005)
            continue
        events = batch.numpy()
        with cond:
            pending.append(events)
            held[0] += len(events)
            while held[0] > CHILD_BACKLOG_EVENTS and len(pending) > 1:
                oldest = pending.popleft()
                held[0] -= len(oldest)
                held[1] += len(oldest)
            cond.notify()
    with cond:
        finished.append("the source closed the stream")
        cond.notify()
    sender.join()


class DvStream(EventStream):
    """A dv-processing source (``kind`` ``"tcp"``: ``target`` the host, ``port`` its port; ``"camera"``:
    ``target`` a serial number or ``""``), read in a child process (see the module docstring).

    Times are the source's microseconds (``timestamp``), in seconds; polarity 1 is +1, 0 is -1.

    Raises
    ------
    ImportError
        dv-processing is not installed.
    StreamError
        The source cannot be opened within ``connect_timeout`` s (nothing listens, it is not a
        dv-processing stream, no camera), or later fails.
    """

    def __init__(
        self,
        kind: str,
        target: str,
        port: int = 0,
        *,
        camera: Camera | None = None,
        connect_timeout: float = 10.0,
    ) -> None:
        if kind not in ("tcp", "camera"):
            raise ValueError(f"kind must be 'tcp' or 'camera', got {kind!r}")
        self.address = (
            f"tcp://{target}:{port}" if kind == "tcp" else f"camera{':' + target if target else ''}"
        )
        _dv(self.address)  # the missing package is named here, not in the child
        timeout = checks.seconds("connect_timeout", connect_timeout, positive=True)
        ctx = multiprocessing.get_context("spawn")  # never fork a process that runs Taichi's threads
        self._conn, child = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_dv_child, args=(child, kind, target, port, timeout), daemon=True)
        self._process.start()
        child.close()
        message = self._receive(60.0)  # the child's imports take a few seconds
        if message is not None and message[0] == "started":
            message = self._receive(timeout)
        if message is None:
            self.close()
            raise StreamError(
                f"{self.address}: no event stream opened within {timeout:g} s (a server that accepts but "
                "does not speak dv-processing's protocol?)"
            )
        if message[0] != "hello":
            self.close()
            raise StreamError(f"{self.address}: cannot open ({message[1]})")
        self.sensor_size = message[1]
        self.name = message[2]
        self.camera = camera

    def _receive(self, timeout: float):
        """The child's next message, None when none came within ``timeout`` s; StreamError when the
        child ended without saying why."""
        try:
            if not self._conn.poll(timeout):
                return None
            return self._conn.recv()
        except (EOFError, OSError):
            self._process.join(timeout=2.0)
            code = self._process.exitcode
            raise StreamError(f"{self.address}: the reader process ended {_exit_reason(code)}") from None

    def read(self, timeout: float) -> EventPacket | None:
        if self._ended:
            return None
        try:
            message = self._receive(timeout)
        except StreamError:
            self._ended = True
            raise
        if message is None:
            return None
        kind, payload = message
        if kind == "overflow":
            self.dropped += int(payload)
            return None
        if kind == "end":
            self._ended = True
            return None
        if kind == "error":
            self._ended = True
            raise StreamError(f"{self.address}: {payload}")
        arrival = time.perf_counter()
        return EventPacket(
            t=payload["timestamp"] / 1e6,
            x=payload["x"],
            y=payload["y"],
            p=np.where(payload["polarity"] > 0, 1, -1).astype(np.int8),
            arrival=arrival,
        )

    def close(self) -> None:
        super().close()
        process = getattr(self, "_process", None)
        if process is not None and process.is_alive():
            process.terminate()
            process.join(timeout=5.0)
        if getattr(self, "_conn", None) is not None:
            self._conn.close()


def _exit_reason(code: int | None) -> str:
    if code is None:
        return "(still running, but not answering)"
    if code < 0:
        import signal

        name = signal.Signals(-code).name
        why = " (dv-processing aborted: a malformed packet?)" if name == "SIGABRT" else ""
        return f"on signal {name}{why}"
    return f"with exit code {code}"


# --- opening ----------------------------------------------------------------------------------------------
def open_stream(
    source,
    *,
    speed: float = 1.0,
    loops: int = 1,
    camera: Camera | None = None,
    connect_timeout: float = 10.0,
    **recording_options,
) -> EventStream:
    """Open a live source of events (see the module docstring).

    Parameters
    ----------
    source : str, path, Recording or Events
        ``tcp://HOST:PORT``, ``camera`` / ``camera:SERIAL``, or a recording to replay.
    speed, loops : float, int
        A replay's speed (a multiple of the recorded speed) and repetitions.
    camera : Camera, optional
        Intrinsics (a network stream or a camera carries none; a recording's own by default).
    connect_timeout : float
        Seconds a dv-processing source may take to open.
    **recording_options
        Passed to :func:`~cmax_taichi.io.open_recording` for a replayed path (``format=``, ``topic=``).

    Raises
    ------
    ValueError
        A malformed address (``tcp://`` without a port, a port out of range).
    FileNotFoundError
        A path that does not exist.
    StreamError, ImportError
        As :class:`DvStream`.
    """
    if isinstance(source, str) and source.startswith("tcp://"):
        host, _, port = source[len("tcp://") :].rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"{source}: expected tcp://HOST:PORT with a port in 1..65535")
        return DvStream("tcp", host.strip("[]"), int(port), camera=camera, connect_timeout=connect_timeout)
    if isinstance(source, str) and (source == "camera" or source.startswith("camera:")):
        return DvStream("camera", source.partition(":")[2], camera=camera, connect_timeout=connect_timeout)
    if isinstance(source, (str, os.PathLike)) and not Path(source).exists():
        raise FileNotFoundError(f"{source}: no such file or folder (nor tcp://HOST:PORT, camera)")
    return ReplayStream(source, speed=speed, loops=loops, camera=camera, **recording_options)


# --- a replay served over TCP (tests, benchmarks, demos) --------------------------------------------------
#: a replay of at most this many events has its packets built before it starts (dv-processing's
#: EventStore is filled event by event, about 1 us each: 1.85 million events per second, an ECD rotation
#: cut's rate, would not be served in time)
PREBUILD_EVENTS = 4_000_000


def serve_replay(
    source,
    port: int,
    *,
    host: str = "127.0.0.1",
    speed: float = 1.0,
    loops: int = 1,
    wait_for_client: float = 30.0,
    ready=None,
    started=None,
    linger: float = 1.0,
    keep: list | None = None,
    go=None,
) -> int:
    """Serve ``source`` replayed (:class:`ReplayStream`: each packet sent when the wall clock reaches
    its last event) as a dv-processing TCP event stream on ``host:port`` until the replay ends; returns
    the events sent. Blocks: run it in its own process (:func:`start_replay_server`).

    The replay starts when a client connects (at most ``wait_for_client`` s later: TimeoutError);
    ``ready`` (an event) is set once the server listens, ``started`` (a shared double) gets the wall
    time (``time.perf_counter``, the same clock in every process of the machine) at which the first
    event's time is replayed. Up to :data:`PREBUILD_EVENTS` events are packed before the replay starts;
    a longer replay packs each packet when it is due. With ``go`` (an event), the replay waits for it too
    (a client that prepares before it reads). The connection closes ``linger`` s after the last
    packet (dv-processing's reader drops the packets it holds when the connection closes: the end of the
    stream is seen that much later); ``keep``, a list, receives the writer instead of closing it."""
    dv = _dv("serving a dv-processing stream")
    replay = ReplayStream(source, speed=speed, loops=loops)
    W, H = replay.sensor_size

    def pack(t, x, y, p):
        store = dv.EventStore()
        micros = np.rint(t * 1e6).astype(np.int64).tolist()
        for ts, xi, yi, pi in zip(micros, x.tolist(), y.tolist(), p.tolist(), strict=True):
            store.push_back(ts, int(xi), int(yi), pi > 0)
        return float(t[-1]), float(t[0]), len(t), store

    packets = replay._generate()
    if replay.n_events * replay.loops <= PREBUILD_EVENTS:
        packets = iter([pack(*packet) for packet in packets])
    else:
        packets = (pack(*packet) for packet in packets)
    stream = dv.io.Stream.EventStream(0, "events", "cmax-taichi replay", (W, H))
    writer = dv.io.NetworkWriter(host, port, stream)
    if ready is not None:
        ready.set()
    deadline = time.monotonic() + wait_for_client
    while writer.getClientCount() == 0 or (go is not None and not go.is_set()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"no client connected to tcp://{host}:{port} within {wait_for_client:g} s")
        time.sleep(0.002)
    sent, wall0, t0 = 0, None, math.nan
    with replay:
        for t_last, t_first, n, store in packets:
            if wall0 is None:
                wall0, t0 = time.perf_counter(), t_first
                if started is not None:
                    started.value = wall0
            wait = wall0 + (t_last - t0) / speed - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            writer.writeEvents(store)
            sent += n
    while writer.getQueuedPacketCount() > 0:
        time.sleep(0.001)
    # dv-processing's reader drops what it holds once the connection closes (the writer's destructor
    # closes it): give the clients time to take the last packets first
    time.sleep(linger)
    if keep is not None:
        keep.append(writer)  # the caller ends the process without the destructor (it waits for clients)
    return sent


def _serve_child(ready, started, go, source, port, host, speed, loops, wait_for_client, linger) -> None:
    keep: list = []
    serve_replay(
        source, port, host=host, speed=speed, loops=loops, wait_for_client=wait_for_client, ready=ready,
        started=started, linger=linger, keep=keep, go=go,
    )  # fmt: skip
    os._exit(0)  # without the writer's destructor, which waits for its clients


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that nothing listens on now (the system's choice)."""
    with contextlib.closing(socket.socket()) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@dataclass
class ReplayServer:
    """A replay served over TCP by a child process (:func:`start_replay_server`)."""

    process: multiprocessing.Process
    address: str
    started: object  # a shared double: the wall time the replay's first event time was sent at (0 before)
    go: object = None  # with wait_for_go: the replay starts once this event is set (and a client is there)

    def stop(self) -> None:
        """End the server now (when it has not ended by itself)."""
        if self.process.is_alive():
            self.process.terminate()
        self.process.join(timeout=5.0)


def start_replay_server(
    source,
    *,
    host: str = "127.0.0.1",
    port: int | None = None,
    speed: float = 1.0,
    loops: int = 1,
    wait_for_client: float = 60.0,
    linger: float = 1.0,
    wait_for_go: bool = False,
) -> ReplayServer:
    """:func:`serve_replay` of ``source`` (a path: the child opens it) in a child process, once it
    listens (it packs its packets first); the process ends ``linger`` s after the last packet. With
    ``wait_for_go``, the replay starts only once ``server.go`` is set as well."""
    port = free_port(host) if port is None else port
    ctx = multiprocessing.get_context("spawn")
    ready, started, go = ctx.Event(), ctx.Value("d", 0.0), ctx.Event() if wait_for_go else None
    args = (ready, started, go, str(source), port, host, speed, loops, wait_for_client, linger)
    process = ctx.Process(target=_serve_child, args=args, daemon=True)
    process.start()
    if not ready.wait(120.0):
        process.terminate()
        raise StreamError(f"the replay server of {source} did not start")
    return ReplayServer(process, f"tcp://{host}:{port}", started, go)
