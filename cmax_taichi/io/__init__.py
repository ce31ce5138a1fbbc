"""Dataset readers: every format opens as a :class:`Recording` that returns the core
:class:`~cmax_taichi.Events` window by window (plus a :class:`~cmax_taichi.Camera` and ground truth
where the format has them), reading only the rows a window needs.

======== =========================================================== ==========================
format   layout                                                      module
======== =========================================================== ==========================
ecd      folder: events.txt ``t x y p`` + calib.txt (+ ground truth) :mod:`.ecd`
text     ``t x y p`` / ``t x y depth p`` text (+ calib.txt)          :mod:`.text`
mvsec    ``*_data.hdf5`` (``davis/left/events``) + gt_flow_dist.npz  :mod:`.mvsec`
dsec     ``events.h5`` (``events/{x,y,t,p}``, ``ms_to_idx``) + PNG   :mod:`.dsec`
aedat4   ``.aedat4`` (needs the optional package ``aedat``)          :mod:`.aedat4`
raw      Prophesee ``.raw`` / ``.evt`` (EVT 2.0, 2.1, 3.0; ``faery``)  :mod:`.faery_formats`
dat      Prophesee ``.dat`` starting with ``%`` (CD; ``faery``)       :mod:`.faery_formats`
es       Event Stream ``.es`` (DVS, ATIS; ``faery``)                  :mod:`.faery_formats`
rosbag   ROS1 ``.bag`` / ROS2 bag folder, an event topic (rosbags)    :mod:`.rosbag`
======== =========================================================== ==========================
"""

from __future__ import annotations

import importlib
import inspect
import os
from pathlib import Path

from cmax_taichi.core import checks
from cmax_taichi.core.events import Events
from cmax_taichi.io._files import check_regular, is_present
from cmax_taichi.io.base import Recording
from cmax_taichi.io.text import EVENT_FILE_NAMES, count_columns, find_events_file

__all__ = ["FORMATS", "Recording", "detect_format", "open_recording", "read_events"]

#: format name -> (module, class)
_READERS = {
    "ecd": ("ecd", "ECDRecording"),
    "text": ("text", "TextRecording"),
    "mvsec": ("mvsec", "MVSECRecording"),
    "dsec": ("dsec", "DSECRecording"),
    "aedat4": ("aedat4", "AEDAT4Recording"),
    "raw": ("faery_formats", "RawRecording"),
    "dat": ("faery_formats", "DatRecording"),
    "es": ("faery_formats", "EventStreamRecording"),
    "rosbag": ("rosbag", "RosbagRecording"),
}
#: the supported format names
FORMATS = tuple(_READERS)


def _unknown(path: Path, why: str) -> ValueError:
    return ValueError(f"{path}: {why}; supported formats: {', '.join(FORMATS)} (pass format= to choose)")


def _hdf5_format(path: Path) -> str:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if "davis" in f:
                return "mvsec"
            if "events" in f and isinstance(f.get("events"), h5py.Group) and "x" in f["events"]:
                return "dsec"
            keys = sorted(f.keys())
    except KeyError as exc:  # a broken (external) link: h5py names neither the file nor the link
        reason = exc.args[0] if exc.args else exc
        raise OSError(f"{path}: cannot open an object of this HDF5 file (a broken link? {reason})") from None
    except OSError as exc:
        raise OSError(f"{path}: not a readable HDF5 file ({exc})") from None
    raise _unknown(path, f"HDF5 file without 'davis/left/events' (MVSEC) or 'events/x' (DSEC); keys {keys}")


def _starts_with(path: Path, prefix: bytes) -> bool:
    with open(check_regular(path), "rb") as f:
        return f.read(len(prefix)) == prefix


def detect_format(path: str | os.PathLike) -> str:
    """The format name of ``path`` (a file or a folder), from its name and, for HDF5, text and
    ``.dat``, its content (a Prophesee DAT file starts with a ``%`` header, a text file with a number
    or ``#``). Raises FileNotFoundError for a missing path, OSError for a FIFO, a device or a socket
    (never opened: reading one could block for ever) and ValueError for an unknown format."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    if path.is_dir():
        if is_present(path / "metadata.yaml") and (any(path.glob("*.db3")) or any(path.glob("*.mcap"))):
            return "rosbag"
        if any([is_present(path / name) for name in EVENT_FILE_NAMES]):
            return "ecd" if count_columns(find_events_file(path)) == 4 else "text"
        if is_present(path / "events.h5") or is_present(path / "events" / "left" / "events.h5"):
            return "dsec"
        for pattern, name in (("*_data.hdf5", "mvsec"), ("*.aedat4", "aedat4")):
            found = sorted(path.glob(pattern))
            if len(found) == 1:
                return name
            if len(found) > 1:
                raise _unknown(path, f"{len(found)} {pattern} files in this folder: open one of them")
        raise _unknown(path, "no events file found in this folder")
    check_regular(path)
    suffix = path.suffix.lower()
    if suffix == ".aedat4":
        return "aedat4"
    if suffix in (".h5", ".hdf5"):
        return _hdf5_format(path)
    if suffix in (".raw", ".evt"):
        return "raw"
    if suffix == ".bag" or (suffix in (".db3", ".mcap") and is_present(path.parent / "metadata.yaml")):
        return "rosbag"
    if suffix == ".es" or _starts_with(path, b"Event Stream"):
        return "es"
    if suffix == ".dat" and _starts_with(path, b"%"):
        return "dat"
    if suffix in (".txt", ".dat", ".csv", ""):
        return "ecd" if count_columns(path) == 4 else "text"
    raise _unknown(path, f"unknown file type {suffix!r}")


def open_recording(path: str | os.PathLike, format: str | None = None, **options) -> Recording:
    """Open an event recording.

    Parameters
    ----------
    path : path
        A file (``events.txt``, ``*_data.hdf5``, ``events.h5``, ``*.aedat4``, ``*.raw``, ``*.dat``,
        ``*.es``, a ROS1 ``*.bag``) or a folder holding
        one (an ECD folder, a DSEC sequence, a ROS2 bag).
    format : str, optional
        One of :data:`FORMATS`; detected from the path when None.
    **options
        Passed to the format's reader. Every reader takes ``sensor_size=(W, H)`` (px) and
        ``camera=`` (a :class:`~cmax_taichi.Camera`); text formats take ``columns=``,
        ``undistorted=``, ``cache_dir=`` and ``cache=``; the ``faery`` formats (raw, dat, es) take
        ``version=``, ``cache_dir=`` and ``cache=``; ROS bags take ``topic=``, ``camera_topic=``,
        ``cache_dir=`` and ``cache=``; see each module.

    Returns
    -------
    Recording
        Use it as a context manager to close HDF5 files.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    OSError
        ``path`` (or a file of the folder that the reader opens) is a FIFO, a device or a socket:
        refused before anything reads from it.
    ValueError
        Unknown format, or a malformed file (the message names the file and the problem).
    KeyError
        An HDF5 file without a dataset the format needs.
    ImportError
        The optional package a format needs is not installed (the message names it).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a file or folder (str or os.PathLike), got {type(path).__name__}")
    path = Path(path).expanduser()
    if "sort" in options:
        options["sort"] = checks.flag("sort", options["sort"])
    if options.get("sensor_size") is not None:
        # before any decoder sees it (faery would answer "out of range integral type conversion")
        options["sensor_size"] = checks.sensor_size(options["sensor_size"])
    if format is None:
        format = detect_format(path)
    elif not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    elif not path.is_dir():
        check_regular(path)
    if format not in _READERS:
        raise ValueError(f"unknown format {format!r}; supported formats: {', '.join(FORMATS)}")
    module_name, class_name = _READERS[format]
    module = importlib.import_module(f"{__name__}.{module_name}")
    reader = getattr(module, class_name)
    _check_options(reader, format, path, options)
    return reader(path, **options)


def _check_options(reader, format: str, path: Path, options: dict) -> None:
    """ValueError naming the options that the format's reader does not take (``topic=`` for a text
    file), rather than Python's "unexpected keyword argument" from inside the reader."""
    for cls in reader.__mro__:  # the first __init__ that names its options (ECD passes them to text's)
        init = cls.__dict__.get("__init__")
        if init is None:
            continue
        parameters = inspect.signature(init).parameters
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
            break
    else:
        return
    unknown = sorted(set(options) - set(parameters))
    if unknown:
        takes = sorted(name for name in parameters if name not in ("self", "path"))
        raise ValueError(
            f"{path}: the {format} reader takes no option {', '.join(unknown)} (it takes "
            f"{', '.join(takes)})"
        )


def read_events(
    path: str | os.PathLike, format: str | None = None, start: int = 0, stop: int | None = None, **options
) -> Events:
    """Events ``start:stop`` (by index) of the recording at ``path``; see :func:`open_recording`."""
    with open_recording(path, format, **options) as recording:
        return recording.read(start, stop)
