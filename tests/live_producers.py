"""Producers of dv-processing TCP event streams for the live tests, each run in its own (spawned) process:
a scripted server (packets, pauses, late packets, bursts) and a server that sends a malformed packet.
Module level (spawn imports them by name); imports dv-processing only."""

from __future__ import annotations

import os
import socket
import time

import numpy as np

_KEEP: list = []


def _store(dv, t_us, x, y, p):
    store = dv.EventStore()
    for ts, xi, yi, pi in zip(t_us.tolist(), x.tolist(), y.tolist(), p.tolist(), strict=True):
        store.push_back(int(ts), int(xi), int(yi), bool(pi))
    return store


def scripted_server(port: int, ready, script: list, sensor: tuple[int, int]) -> None:
    """Serve ``script`` on 127.0.0.1:``port`` once a client connects: ``("events", t_us, x, y, p)``
    writes a packet, ``("sleep", s)`` pauses; then keeps the connection 1 s and ends."""
    import dv_processing as dv

    stream = dv.io.Stream.EventStream(0, "events", "scripted", sensor)
    writer = dv.io.NetworkWriter("127.0.0.1", port, stream)
    stores = [(_store(dv, *step[1:]) if step[0] == "events" else step) for step in script]
    ready.set()
    while writer.getClientCount() == 0:
        time.sleep(0.002)
    time.sleep(0.2)
    for step in stores:
        if isinstance(step, tuple):
            time.sleep(step[1])
        else:
            writer.writeEvents(step)
    while writer.getQueuedPacketCount() > 0:
        time.sleep(0.001)
    time.sleep(1.0)
    os._exit(0)


def _captured_stream(dv, sensor, t_us, x, y, p) -> tuple[bytes, bytes]:
    """(header, one packet) as a NetworkWriter sends them, captured on a raw socket."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    stream = dv.io.Stream.EventStream(0, "events", "malformed", sensor)
    writer = dv.io.NetworkWriter("127.0.0.1", port, stream)
    conn = socket.create_connection(("127.0.0.1", port), timeout=2)
    while writer.getClientCount() == 0:
        time.sleep(0.002)
    writer.writeEvents(_store(dv, t_us, x, y, p))
    data = b""
    conn.settimeout(0.5)
    try:
        while True:
            chunk = conn.recv(65536)
            if not chunk:
                break
            data += chunk
    except TimeoutError:
        pass
    conn.close()
    _KEEP.append(writer)  # its destructor would wait for the client it had: never destroyed
    n = int.from_bytes(data[:4], "little")
    return data[: 4 + n], data[4 + n :]


def malformed_server(port: int, ready, sensor: tuple[int, int], n_good: int) -> None:
    """A server that sends dv-processing's header, one good packet of ``n_good`` events, then a packet
    whose length field claims 4 GB (dv-processing's reader aborts on it)."""
    import dv_processing as dv

    t_us = 1_000_000 + np.arange(n_good) * 10
    x, y = np.arange(n_good) % sensor[0], (np.arange(n_good) // 7) % sensor[1]
    header, packet = _captured_stream(dv, sensor, t_us, x, y, np.arange(n_good) % 2)
    with socket.socket() as server:
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", port))
        server.listen(1)
        ready.set()
        conn, _ = server.accept()
        conn.sendall(header)
        time.sleep(0.2)
        conn.sendall(packet)
        time.sleep(0.5)
        conn.sendall((0).to_bytes(4, "little") + (0xFFFFFFF0).to_bytes(4, "little") + b"x" * 64)
        time.sleep(5.0)
        conn.close()
    os._exit(0)
