"""The binary event cache: a source file decoded once into a float64 ``(N, 4)`` table ``t x y p``
(seconds, px, px, polarity), stored in a user cache directory and memory-mapped afterwards.

The cache never lives beside the data (data folders may be read-only and users' data must not be
modified). A cache entry is keyed by the source's absolute path, by the decoder's options and by the
file's state: size, modification time, status-change time (``st_ctime``, which every write updates
and no tool sets back) and a SHA-256 of its content sampled in blocks (the whole file up to 1 MiB;
else the first and last 64 KiB and 14 blocks of 4 KiB spread between). So a file rewritten in place
with the same size and a restored modification time still gets a new entry; the stale entries of the
same path are removed.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import os
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from cmax_taichi.io.base import event_span

#: bump when the table layout, a decoder's output or the key changes (old entries are then ignored)
CACHE_VERSION = 2
#: the environment variable that overrides the cache directory
CACHE_ENV = "CMAX_TAICHI_CACHE"
COLUMNS = 4  # t, x, y, p


def cache_root(cache_dir: str | os.PathLike | None = None) -> Path:
    """The cache directory: ``cache_dir``, else ``$CMAX_TAICHI_CACHE``, else
    ``$XDG_CACHE_HOME/cmax_taichi``, else ``~/.cache/cmax_taichi``."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "cmax_taichi"


_WHOLE_FILE = 1 << 20  # files up to this size are hashed whole
_END_BLOCK = 64 << 10  # bytes hashed at the start and at the end of a larger file
_MID_BLOCKS, _MID_BLOCK = 14, 4 << 10  # blocks hashed in between


def content_fingerprint(source: Path, size: int) -> str:
    """SHA-256 (hex, 16 digits) of the file's content sampled as described in the module docstring:
    at most 1 MiB read, whatever the file's size."""
    digest = hashlib.sha256()
    with open(source, "rb") as f:
        if size <= _WHOLE_FILE:
            digest.update(f.read())
        else:
            offsets = [0, size - _END_BLOCK]
            span = size - 2 * _END_BLOCK - _MID_BLOCK
            offsets[1:1] = [_END_BLOCK + span * (k + 1) // (_MID_BLOCKS + 1) for k in range(_MID_BLOCKS)]
            for k, offset in enumerate(offsets):
                f.seek(offset)
                digest.update(f.read(_END_BLOCK if k in (0, len(offsets) - 1) else _MID_BLOCK))
    return digest.hexdigest()[:16]


def _keys(source: Path, kind: str, options: dict) -> tuple[str, str]:
    st = source.stat()
    path_key = hashlib.sha256(str(source.resolve()).encode()).hexdigest()[:16]
    state = json.dumps(
        [
            CACHE_VERSION,
            kind,
            st.st_size,
            st.st_mtime_ns,
            st.st_ctime_ns,
            content_fingerprint(source, st.st_size),
            options,
        ],
        sort_keys=True,
        default=str,
    )
    return path_key, hashlib.sha256(state.encode()).hexdigest()[:16]


def _map(table_path: Path, n: int) -> np.ndarray:
    if n == 0:  # an empty file cannot be memory-mapped
        return np.empty((0, COLUMNS), dtype=np.float64)
    return np.memmap(table_path, dtype=np.float64, mode="r", shape=(n, COLUMNS))


_SORT_BLOCK = 1 << 20  # rows gathered at once when a table is sorted


def sort_rows(path: Path, n: int) -> tuple[float, float, int]:
    """Sort the ``(n, 4)`` float64 table file ``path`` by time (stable: events of one time keep their
    order), through a second temporary file; returns (first time, last time, rows that were earlier
    than the row before). Memory: the time column and the order, 16 bytes per event."""
    if n == 0:
        return math.nan, math.nan, 0
    table = np.memmap(path, dtype=np.float64, mode="r", shape=(n, COLUMNS))
    t = np.array(table[:, 0])
    back = int(np.count_nonzero(np.diff(t) < 0))
    if back == 0:
        del table
        return float(t[0]), float(t[-1]), 0
    order = np.argsort(t, kind="stable")
    sorted_path = path.with_name(path.name + ".sorted")
    try:
        out = np.memmap(sorted_path, dtype=np.float64, mode="w+", shape=(n, COLUMNS))
        for a in range(0, n, _SORT_BLOCK):
            out[a : a + _SORT_BLOCK] = table[order[a : a + _SORT_BLOCK]]
        out.flush()
        del out, table
        os.replace(sorted_path, path)
    except BaseException:
        sorted_path.unlink(missing_ok=True)
        raise
    return float(t[order[0]]), float(t[order[-1]]), back


def cached_table(
    source: Path,
    kind: str,
    options: dict,
    build: Callable[[BinaryIO], dict],
    cache_dir: str | os.PathLike | None = None,
    use_cache: bool = True,
    sort: bool = False,
) -> tuple[np.ndarray, dict]:
    """The ``(N, 4)`` float64 table of ``source``, memory-mapped, and its metadata.

    With ``sort``, the rows are sorted by time (:func:`sort_rows`) before they are stored (the entry is
    another one than the unsorted table's); the metadata then has ``rows_out_of_order``.

    ``build(out)`` decodes the source, writes the rows to the binary stream ``out`` (row-major
    float64) and returns a JSON-able dict with at least ``"n"`` (the row count). It runs once per
    version of the source; later calls map the stored table. With ``use_cache=False``, or when the
    cache directory cannot be written or its disk is full (a warning says so), the table goes to a
    temporary file that is deleted when the returned array is garbage-collected (on POSIX); with no
    space there either, one OSError names the source, the cache and the temporary folder.
    """
    if sort:
        options = dict(options, sorted_by_time=True)
    path_key, state_key = _keys(source, kind, options)
    root = cache_root(cache_dir)
    table_path = root / f"{path_key}-{state_key}.f64"
    meta_path = root / f"{path_key}-{state_key}.json"
    if use_cache and meta_path.is_file() and table_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
            if table_path.stat().st_size == meta["n"] * COLUMNS * 8:
                return _map(table_path, int(meta["n"])), meta
        except (OSError, ValueError, KeyError):
            pass  # a damaged entry is rebuilt below
    if use_cache:
        try:
            root.mkdir(parents=True, exist_ok=True)
            fd, tmp_name = tempfile.mkstemp(prefix=f".{path_key}-", suffix=".tmp", dir=root)
        except OSError as exc:
            _fallback_warning(root, source, exc)
            use_cache = False
        else:
            try:
                tmp = Path(tmp_name)
                return _store(source, kind, build, sort, fd, tmp, table_path, meta_path, root, path_key)
            except OSError as exc:
                if exc.errno not in _NO_SPACE:
                    raise
                _fallback_warning(root, source, exc)  # a full disk under the cache: as if it were not there
    try:
        fd, tmp_name = tempfile.mkstemp(prefix="cmax_taichi-", suffix=".f64")
        return _store(source, kind, build, sort, fd, Path(tmp_name), None, None, root, path_key)
    except OSError as exc:
        if exc.errno not in _NO_SPACE:
            raise
        raise OSError(
            f"{source}: no space to decode its events ({exc.strerror}), neither in the event cache {root} "
            f"nor in the temporary folder {tempfile.gettempdir()}: free some space, or set {CACHE_ENV} to "
            "a folder on another disk"
        ) from None


#: the errors of a full disk (or quota, or file-size limit)
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _fallback_warning(root: Path, source: Path, exc: OSError) -> None:
    warnings.warn(
        f"cannot write the event cache in {root} ({exc.strerror or exc}); decoding {source} into a "
        f"temporary file instead (set {CACHE_ENV} or cache_dir= to a writable folder with space)",
        RuntimeWarning,
        stacklevel=4,
    )


def _store(source, kind, build, sort, fd, tmp: Path, table_path, meta_path, root, path_key):
    """Decode ``source`` with ``build`` into the open temporary file ``fd`` (``tmp``), then move it to
    ``table_path`` in the cache (with its metadata), or, without ``table_path``, map the temporary file
    itself (removed once mapped); ``(table, metadata)``."""
    use_cache = table_path is not None
    out = os.fdopen(fd, "wb")
    try:
        with out:
            meta = build(out)
        meta = dict(meta, source=str(source.resolve()), kind=kind, version=CACHE_VERSION)
        if tmp.stat().st_size != meta["n"] * COLUMNS * 8:
            raise OSError(f"event cache for {source}: wrote {tmp.stat().st_size} bytes for {meta['n']} rows")
        if sort:
            t_first, t_last, back = sort_rows(tmp, int(meta["n"]))
            meta.update(t_start=t_first, t_end=t_last, rows_out_of_order=back)
        if not use_cache:
            table = _map(tmp, int(meta["n"]))
            # POSIX: the mapping keeps the data alive until it is released; Windows cannot unlink a
            # mapped file, and the temporary folder keeps it
            with contextlib.suppress(OSError):
                tmp.unlink()
            return table, meta
        os.replace(tmp, table_path)
        meta_tmp = meta_path.with_suffix(".json.tmp")
        meta_tmp.write_text(json.dumps(meta))
        os.replace(meta_tmp, meta_path)
    except BaseException:
        with contextlib.suppress(OSError):
            out.close()
        tmp.unlink(missing_ok=True)
        if use_cache:  # no table stands in the cache without its metadata
            table_path.unlink(missing_ok=True)
            meta_path.with_suffix(".json.tmp").unlink(missing_ok=True)
        raise
    # entries of earlier versions of the same file are stale now
    for old in root.glob(f"{path_key}-*"):
        if old.name not in (table_path.name, meta_path.name) and not old.name.startswith("."):
            old.unlink(missing_ok=True)
    return _map(table_path, int(meta["n"])), meta


class CachedTableReads:
    """The reads of a :class:`~cmax_taichi.io.base.Recording` whose events are a cached table
    ``self._table`` (the ``(N, 4)`` float64 ``t x y p`` array of :func:`cached_table`, memory-mapped).

    Listed before ``Recording`` among a reader's bases so that these methods replace its generic hooks.
    """

    _table: np.ndarray | None
    #: the decoders check that times are finite and in order (or sort them: ``sort=True``)
    _times_checked = True

    @staticmethod
    def table_span(meta: dict) -> dict:
        """``n_events``, ``t_start`` and ``t_end`` (s; NaN without events) from the metadata that
        :func:`cached_table` returns, as keyword arguments of ``Recording.__init__``."""
        return event_span(meta["n"], lambda i: meta["t_start"] if i == 0 else meta["t_end"])

    def _load_table(
        self, path: Path, fmt: str, key: dict, decode, *, cache_dir, cache: bool, sort: bool
    ) -> dict:
        """``self._table`` of ``path`` through :func:`cached_table` (``decode(out)`` fills it on a cache
        miss) and ``self.rows_out_of_order``; returns the table's metadata."""
        self._table, meta = cached_table(
            path, fmt, key, decode, cache_dir=cache_dir, use_cache=cache, sort=bool(sort)
        )
        self.rows_out_of_order = int(meta.get("rows_out_of_order", 0))
        return meta

    def _init_decoded(self, path: Path, meta: dict, sensor_size, camera) -> None:
        """``Recording.__init__`` for a decoded binary format: integer pixel coordinates (never
        undistorted), on the sensor the file names unless ``sensor_size`` is given."""
        super().__init__(
            path,
            sensor_size=sensor_size or tuple(meta["sensor_size"]),
            camera=camera,
            undistorted=False,
            **self.table_span(meta),
        )

    def _columns(self, start: int, stop: int):
        rows = np.asarray(self._table[start:stop])
        return rows[:, 1], rows[:, 2], rows[:, 0], rows[:, 3]

    def _times(self, start: int, stop: int) -> np.ndarray:
        return np.asarray(self._table[start:stop, 0])

    def _search_time(self, t: float) -> int:
        # a binary search on the mapped column touches only log2(N) pages
        return int(np.searchsorted(self._table[:, 0], t, side="left"))

    def _release(self) -> None:
        self._table = None
