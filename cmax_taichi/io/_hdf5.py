"""HDF5 helpers shared by the MVSEC and DSEC readers: opening with one-line errors, finding a
dataset, and telling the user which plugin a compressed dataset needs."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np


def open_h5(path: Path) -> h5py.File:
    """Open ``path`` read-only; OSError naming the file when it is not readable HDF5."""
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise OSError(f"{path}: not a readable HDF5 file ({exc})") from None


@contextlib.contextmanager
def closed_on_error(f: h5py.File) -> Iterator[h5py.File]:
    """Close ``f`` when the block raises (a reader that fails in its constructor leaves no file open)."""
    try:
        yield f
    except BaseException:
        f.close()
        raise


def dataset(f: h5py.File, key: str, path: Path, what: str) -> h5py.Dataset:
    """``f[key]`` as a dataset whose filters this h5py can decode.

    Raises KeyError naming the file and the missing key, and OSError telling the user to
    ``pip install hdf5plugin`` when the dataset uses a compression filter that is not registered
    (DSEC files use blosc)."""
    if key not in f:
        raise KeyError(f"{path}: no dataset '{key}' ({what})")
    try:
        ds = f[key]
    except (KeyError, OSError) as exc:  # a broken soft or external link: h5py names neither file nor key
        reason = exc.args[0] if exc.args else exc
        raise OSError(f"{path}: dataset '{key}' cannot be opened (a broken link? {reason})") from None
    if not isinstance(ds, h5py.Dataset):
        raise KeyError(f"{path}: no dataset '{key}' ({what})")
    plist = ds.id.get_create_plist()
    for i in range(plist.get_nfilters()):
        code, _flags, _values, name = plist.get_filter(i)
        if h5py.h5z.filter_avail(code):
            continue
        try:
            import hdf5plugin  # noqa: F401  (registers blosc, lz4, zstd, ... with h5py)
        except ImportError:
            raise OSError(
                f"{path}: dataset '{key}' is compressed with the HDF5 filter "
                f"'{name.decode(errors='replace')}' (id {code}), which h5py cannot decode without "
                f"plugins: pip install hdf5plugin"
            ) from None
        if not h5py.h5z.filter_avail(code):
            raise OSError(
                f"{path}: dataset '{key}' needs the HDF5 filter '{name.decode(errors='replace')}' "
                f"(id {code}), which neither h5py nor hdf5plugin provides"
            )
    return ds


def numeric_dataset(f: h5py.File, key: str, path: Path, what: str) -> h5py.Dataset:
    """:func:`dataset`, and ValueError naming the file and the dataset when its values are not
    real numbers (strings, compound or complex values)."""
    ds = dataset(f, key, path, what)
    if ds.dtype.kind not in "biuf":
        raise ValueError(f"{path}: dataset '{key}' holds values of type {ds.dtype}; expected real numbers")
    return ds


def finite(values, path: Path, key: str, where: str = "") -> np.ndarray:
    """``values`` as an array, with ValueError naming the file, the dataset and the first bad row when
    one is NaN or infinite (``where``: the rows, e.g. ``"rows 0..100"``)."""
    arr = np.asarray(values)
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        rows = f", {where}" if where else ""
        raise ValueError(f"{path}: dataset '{key}'{rows} has {bad} non-finite value(s) (NaN or inf)")
    return arr


def read(ds: h5py.Dataset, index, path: Path):
    """``ds[index]`` with read errors (corrupt or truncated files) as one OSError naming the file."""
    try:
        return ds[index]
    except OSError as exc:
        raise OSError(f"{path}: cannot read '{ds.name}' ({exc})") from None
