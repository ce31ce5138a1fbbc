"""The checkpoints of a batch (:mod:`cmax_taichi.solve.batch`): what a worker writes after every window
into ``OUT/<name>/checkpoint.json`` (atomically: a temporary file, ``fsync``, ``os.replace``), what a
resumed run reads back, and what identifies a recording so that a checkpoint is never continued on
another one (its events file, size, modification time and content fingerprint, as the event cache's key,
and its camera).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cmax_taichi.io.outputs import atomic_write_text, json_text
from cmax_taichi.solve.results import SequenceResult, read_results
from cmax_taichi.solve.sequence import WarmState

__all__ = ["CHECKPOINT_NAME", "CHECKPOINT_VERSION", "read_progress", "recording_identity"]

CHECKPOINT_NAME = "checkpoint.json"
CHECKPOINT_VERSION = 2  # 2: the recording's identity in the key, the rows of windows not estimated


def _jsonable(value: Any) -> Any:
    """Settings as plain JSON values (to compare a checkpoint's settings with this run's)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "fx"):  # a Camera
        return [value.fx, value.fy, value.cx, value.cy, *value.dist]
    return repr(value)


def _write_checkpoint(
    folder: Path,
    result: SequenceResult,
    key: dict,
    total: int | None,
    done: bool,
    warm_state: WarmState | None = None,
) -> None:
    data = result.as_dict()  # every row: the windows not estimated too
    data["checkpoint"] = {
        "version": CHECKPOINT_VERSION,
        "key": key,
        "total_windows": total,
        "complete": done,
        # the last window's warm start for the next one (with that window's index): a run resumed
        # after it continues exactly as an uninterrupted one
        "warm_state": None
        if warm_state is None or not result.windows
        else {"index": result.windows[-1].index, **warm_state.as_dict()},
    }
    atomic_write_text(folder / CHECKPOINT_NAME, json_text(data))


def _read_checkpoint(folder: Path) -> tuple[SequenceResult, dict] | None:
    path = folder / CHECKPOINT_NAME
    if not path.exists():
        return None
    result = read_results(path)  # ValueError naming the file when it is not a results file
    meta = json.loads(path.read_text()).get("checkpoint")
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: not a cmax-taichi batch checkpoint")
    if meta.get("version") != CHECKPOINT_VERSION:
        raise ValueError(
            f"{path}: a checkpoint of another cmax-taichi version (format {meta.get('version')}, this one "
            f"writes {CHECKPOINT_VERSION}): delete {folder} to estimate the recording again"
        )
    return result, meta


def recording_identity(rec: Any) -> dict:
    """What identifies the recording ``rec`` (open) for a resumed batch: its events file, size,
    modification time and content fingerprint (as the event cache's key), and its camera."""
    from cmax_taichi.io._cache import content_fingerprint

    source = Path(getattr(rec, "events_file", None) or getattr(rec, "data_file", None) or rec.path)
    st = source.stat()
    camera = rec.camera
    return {
        "file": str(source.resolve()),
        "size": st.st_size,
        "mtime_ns": st.st_mtime_ns,
        "content": content_fingerprint(source, st.st_size) if source.is_file() else "",
        "camera": None if camera is None else [camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist],
    }


def _changed(old: Mapping, new: Mapping) -> str:
    """What differs between two recording identities, for the message."""
    parts = []
    if old.get("file") != new.get("file"):
        parts.append(f"file {old.get('file')} -> {new.get('file')}")
    if old.get("size") != new.get("size"):
        parts.append(f"size {old.get('size')} -> {new.get('size')} bytes")
    if old.get("mtime_ns") != new.get("mtime_ns"):
        parts.append("modification time")
    if old.get("content") != new.get("content"):
        parts.append("content")
    if old.get("camera") != new.get("camera"):
        parts.append("calibration")
    return ", ".join(parts) or "identity"


def read_progress(folder: Path) -> tuple[int, int | None]:
    """(windows written, total windows if known) of a recording's checkpoint; (0, None) when none."""
    try:
        data = json.loads((folder / CHECKPOINT_NAME).read_text())
        return len(data["windows"]), data["checkpoint"]["total_windows"]
    except (OSError, ValueError, KeyError, TypeError):
        return 0, None


def _mtime(path: Path) -> int:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return 0
