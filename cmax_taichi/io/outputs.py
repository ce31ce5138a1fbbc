"""Output folders that never touch the inputs: what every command writes (``estimate``, ``segment``,
``flow``, ``evaluate``, ``reproduce``, ``bench``, and the tables of a batch) and the atomic writes of the
result files. One implementation, used by all of them.

Guarantees of an :class:`OutputFolder` (``OUT``):

* **inputs are never touched**: ``OUT`` must not be an input (a recording's file or folder), nor a
  folder that holds one, nor a folder inside an input folder, nor a folder that holds any recording
  (``bench`` has no input, and a recording's folder is no place for results); it is refused before
  anything is written (:class:`OutputConflictError`);
* **nothing a run did not write is replaced**: a run recognises the outputs of cmax-taichi runs by the
  manifest ``OUT/.cmax-taichi-manifest.json`` (each file's path, size, modification time, content
  digest and the command that wrote it; a copied folder's files, whose times changed, are recognised by
  their content). A file that this run would write and that the manifest does not list (or that
  changed since) is refused before any work, and again before it is replaced; so is a file that
  *another* command wrote (``flow`` into the folder of an ``estimate`` that wrote ``results.csv``):
  commands share a folder only where their files do not collide (``evaluate``'s metrics beside the
  results it scored);
* **all or nothing**: everything is written into a staging folder inside ``OUT``
  (``.cmax-taichi-staging-<pid>-<random>``) and moved into place when the run completes. The manifest
  that lists the new files is written *before* they are moved (a full disk then stops the commit with
  ``OUT`` as it was), each file is moved with ``os.replace`` (the file it replaces set aside until
  every move succeeded, and put back if one fails), and an interrupted run (Ctrl-C, SIGTERM, an error)
  removes its staging folder. So a run's outputs are either all in place with their manifest or not
  there. The files of the same command's previous run that this one did not rewrite are removed, so
  ``OUT`` holds one run per command; ``OUT`` removed or replaced during the run is an error at the
  commit, not a "wrote" message over missing files. A full disk while the run writes is one error
  naming ``OUT`` (:class:`OutputSpaceError`);
* **one run at a time**: the run holds an exclusive lock on ``OUT/.cmax-taichi.lock`` (``flock``,
  released by the kernel when the process ends, however it ends; the file is removed when the run
  ends); a second run on the same ``OUT`` is refused at once with :class:`OutputBusyError` naming the
  other run. (On file systems without ``flock`` support, e.g. some NFS mounts, the lock may not hold.)

:func:`atomic_path` and :func:`atomic_write_text` are the single-file form: a temporary file in the
same folder, ``fsync``, then ``os.replace``; :func:`json_text` is the strict JSON every command writes
(``null`` for a missing or non-finite number, never a bare ``NaN``).
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows: no lock (documented)
    fcntl = None

__all__ = [
    "LOCK_NAME",
    "MANIFEST_NAME",
    "STAGING_PREFIX",
    "OutputBusyError",
    "OutputConflictError",
    "OutputFolder",
    "OutputSpaceError",
    "atomic_path",
    "atomic_write_text",
    "check_inputs",
    "hold_lock",
    "json_text",
    "read_manifest",
    "refuse_foreign",
    "write_manifest",
]

MANIFEST_NAME = ".cmax-taichi-manifest.json"
LOCK_NAME = ".cmax-taichi.lock"
STAGING_PREFIX = ".cmax-taichi-staging-"
MANIFEST_VERSION = 2
#: the errors of a full disk (or quota, or file-size limit)
NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
#: names in an output folder that belong to the machinery (never an output, never to be given as one)
RESERVED_NAMES = (MANIFEST_NAME, LOCK_NAME)


class OutputConflictError(ValueError):
    """An output would touch an input, or replace a file that no cmax-taichi run wrote."""


class OutputBusyError(OSError):
    """Another run holds the output folder's lock."""


class OutputSpaceError(OSError):
    """The disk (or quota) filled up while a run wrote its outputs: nothing of the run was committed."""


# --- strict JSON ------------------------------------------------------------------------------------
def _plain(value):
    """``value`` with NumPy scalars and arrays as Python numbers and lists, non-finite floats as None."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def json_text(data, indent: int | None = 1) -> str:
    """``data`` as strict JSON text (RFC 8259): NaN and infinities as ``null``, NumPy values as plain
    numbers and lists; a newline at the end. What every command's JSON output goes through."""
    return json.dumps(_plain(data), indent=indent, allow_nan=False) + "\n"


# --- single files -----------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed to ``path`` (``os.replace``) when the block
    ends without an error, removed when it raises. A reader sees the old file or the new one, never a
    partial one."""
    path = Path(path)
    while True:  # a fresh name, created with the umask's permissions (mkstemp would give 0600)
        tmp = path.with_name(f".{path.name}.{os.getpid()}-{os.urandom(4).hex()}.tmp")
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            break
        except FileExistsError:
            continue
    try:
        yield tmp
        with contextlib.suppress(OSError), open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` through :func:`atomic_path`; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


# --- inputs -----------------------------------------------------------------------------------------
def _resolved(path: str | os.PathLike) -> Path:
    return Path(path).expanduser().resolve()


def check_inputs(out: str | os.PathLike, inputs: Iterable[str | os.PathLike], option: str = "--out") -> None:
    """OutputConflictError when the output folder ``out`` is one of ``inputs`` (files or folders), a
    folder that holds one (at any depth), a folder inside an input folder, an existing file, or a
    folder that holds a recording (any, not only an input: an ECD folder, MVSEC, DSEC, AEDAT4, a ROS 2
    bag). Inputs that do not exist have nothing to protect (the command reports them itself). An empty
    name is refused too (it would be the current folder, unsaid)."""
    if not str(out).strip():
        raise OutputConflictError(f"{option} is empty: name an output folder")
    target = _resolved(out)
    for item in inputs:
        if not os.path.lexists(item):
            continue
        source = _resolved(item)
        if target == source:
            raise OutputConflictError(
                f"{option} {out} is the input {item} itself: choose another output folder "
                "(the recording's files are never written)"
            )
        if target in source.parents:
            raise OutputConflictError(
                f"{option} {out} holds the input {item}: choose an output folder outside the recordings "
                "(their files are never overwritten)"
            )
        if source.is_dir() and source in target.parents:
            raise OutputConflictError(
                f"{option} {out} is inside the input folder {item}: choose an output folder outside the "
                "recordings (nothing is ever written into them)"
            )
    if target.exists() and not target.is_dir():
        raise OutputConflictError(f"{option} {out} is an existing file, not a folder")
    recording = _recording_format(target)
    if recording is not None:
        raise OutputConflictError(
            f"{option} {out} holds a recording ({recording}): choose an output folder outside the "
            "recordings (their files are never overwritten)"
        )


def _check_writable(out: Path, option: str) -> None:
    """OSError when ``out`` cannot be written, or created (its nearest existing folder cannot be
    written): a read-only file system or no permission, found before the run's work, not at its end."""
    folder = _resolved(out)
    while not folder.exists() and folder.parent != folder:
        folder = folder.parent
    if not folder.is_dir() or os.access(folder, os.W_OK | os.X_OK):
        return  # not a folder: check_inputs or the creation says so
    read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
    why = "Read-only file system" if read_only else "Permission denied"
    what = f"write in {out}" if folder == _resolved(out) else f"create {out}"
    raise OSError(f"{option}: cannot {what} ({why})")


def _recording_format(folder: Path) -> str | None:
    """The format of the recording that ``folder`` holds (its events file, as :func:`cmax_taichi.io.
    detect_format` finds it in a folder), None for a folder without one or one that does not exist."""
    if not folder.is_dir():
        return None
    from cmax_taichi.io import detect_format

    try:
        return detect_format(folder)
    except (OSError, ValueError):  # no events file there (or one that cannot be read: not a recording)
        return None


# --- the lock ---------------------------------------------------------------------------------------
@contextlib.contextmanager
def hold_lock(folder: str | os.PathLike, what: str = "cmax-taichi") -> Iterator[None]:
    """Hold the exclusive lock of ``folder`` (created) for the block; :class:`OutputBusyError` at once
    when another process holds it (its pid and command are in the message). The lock file is removed
    when the block ends: a finished run leaves nothing of its lock behind."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if fcntl is None:  # pragma: no cover
        yield
        return
    lock_path = folder / LOCK_NAME
    while True:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # another process holds it
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise OutputBusyError(
                f"{folder} is in use by another cmax-taichi run ({holder}): wait for it to end, "
                "or choose another output folder"
            ) from None
        except OSError:  # a file system without flock (ENOLCK, ENOTSUP: some NFS mounts): no lock
            os.close(fd)
            with contextlib.suppress(OSError):
                lock_path.unlink()
            yield
            return
        # a run that ended between our open and our flock removed the file we locked: lock the new one
        try:
            same = os.stat(lock_path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        stamp = f"pid {os.getpid()}, {what}, since {time.strftime('%Y-%m-%d %H:%M:%S')}"
        with contextlib.suppress(OSError):  # a full disk: the lock holds all the same
            os.pwrite(fd, stamp.encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            lock_path.unlink()  # while still locked: the next run locks a fresh file
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


# --- the manifest -----------------------------------------------------------------------------------
def _digest(path: Path) -> str:
    """SHA-256 of a file's content (hex)."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _stamp(path: Path, command: str) -> dict:
    st = path.stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": _digest(path), "command": command}


def read_manifest(folder: Path) -> dict[str, dict]:
    """``{relative path: {"size", "mtime_ns", "sha256", "command"}}`` of the files cmax-taichi runs wrote into
    ``folder`` ({} without a manifest; a damaged manifest counts as none, so nothing is replaced on its
    word). Entries of a version-1 manifest take its one command."""
    try:
        data = json.loads((folder / MANIFEST_NAME).read_text())
        files = data["files"]
        if not isinstance(files, dict):
            return {}
        command = str(data.get("command", "cmax-taichi"))
        return {str(k): {"command": command, **dict(v)} for k, v in files.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def _write_manifest_file(folder: Path, files: dict[str, dict], command: str) -> None:
    manifest = {
        "version": MANIFEST_VERSION,
        "command": command,
        "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "files": files,
    }
    atomic_write_text(folder / MANIFEST_NAME, json_text(manifest))


def refuse_foreign(
    folder: str | os.PathLike,
    relative_paths: Iterable[str],
    option: str = "--out",
    command: str | None = None,
) -> None:
    """OutputConflictError for the first of ``relative_paths`` that exists in ``folder`` and that no
    cmax-taichi run wrote (or that changed since, or that another command than ``command`` wrote); for
    writers that write in place (a batch's tables)."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    for relative in relative_paths:
        _refuse(folder, relative, manifest, option, command)


def write_manifest(folder: str | os.PathLike, relative_paths: Iterable[str], command: str) -> None:
    """Record ``relative_paths`` (files in ``folder``, as they are now) as outputs of ``command``,
    beside the files of earlier manifests that are still unchanged."""
    folder = Path(folder)
    previous = read_manifest(folder)
    files = {rel: stamp for rel, stamp in previous.items() if _ours(folder, rel, previous)}
    files.update({rel: _stamp(folder / rel, command) for rel in relative_paths})
    _write_manifest_file(folder, files, command)


def _refuse(folder: Path, relative: str, manifest: dict[str, dict], option: str, command: str | None) -> None:
    """OutputConflictError when ``folder/relative`` exists and this run may not replace it."""
    target = folder / relative
    if target.is_dir() and not target.is_symlink():
        raise OutputConflictError(f"{target} is a folder where this run writes a file: not replaced")
    if not (target.exists() or target.is_symlink()):
        return
    if not _ours(folder, relative, manifest):
        listed = relative in manifest
        why = (
            "changed since a cmax-taichi run wrote it"
            if listed
            else f"not written by a cmax-taichi run (no {MANIFEST_NAME} lists it)"
        )
        raise OutputConflictError(
            f"{target} exists and was {why}: not replaced; choose another {option} or move it away"
        )
    other = manifest[relative].get("command")
    if command is not None and other != command:
        raise OutputConflictError(
            f"{target} is an output of 'cmax-taichi {other}': this 'cmax-taichi {command}' run would replace "
            f"it; choose another {option} (or move it away)"
        )


def _ours(folder: Path, relative: str, manifest: dict[str, dict]) -> bool:
    """Whether the existing file ``folder/relative`` is one a run wrote and nobody changed since."""
    stamp = manifest.get(relative)
    if stamp is None:
        return False
    try:
        st = (folder / relative).stat()
        if (st.st_size, st.st_mtime_ns) == (stamp.get("size"), stamp.get("mtime_ns")):
            return True
        # a copy of the folder (cp -r) keeps the content, not the times: the content decides
        return st.st_size == stamp.get("size") and stamp.get("sha256") == _digest(folder / relative)
    except OSError:
        return False


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


def _space_error(exc: OSError, where: Path, option: str) -> OutputSpaceError:
    error = OutputSpaceError(
        f"{option} {where}: {exc.strerror or exc} while writing this run's outputs; nothing of the run "
        f"was committed ({where} is as it was): free some space, or choose another {option}"
    )
    error.errno = exc.errno
    return error


class OutputFolder:
    """The output folder of one run (see the module docstring); use it as a context manager.

    Write every file under :meth:`path` (the staging folder); :meth:`commit` moves them into ``OUT``.
    Leaving the block without :meth:`commit` (an error, Ctrl-C) removes the staging folder.

    Parameters
    ----------
    path : path
        ``OUT``, created if needed.
    inputs : sequence of paths
        The run's inputs (recordings, data folders): ``OUT`` must not be nor hold any of them.
    patterns : sequence of str
        What the run may write, as paths relative to ``OUT`` with ``fnmatch`` wildcards in the file
        name (``"figures/window_*.png"``): existing files that match and that no run of this command
        wrote are refused before any work.
    command : str
        The command (``"estimate"``, ``"flow"``, ...): named in the lock (for the message a second run
        gets) and in the manifest, beside each file it wrote.
    option : str
        How the user named ``OUT`` (``"--out"``), for messages.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        inputs: Sequence[str | os.PathLike] = (),
        patterns: Sequence[str] = (),
        command: str = "cmax-taichi",
        option: str = "--out",
    ) -> None:
        self.out = Path(path)
        self.inputs = list(inputs)
        self.patterns = list(patterns)
        self.command = command
        self.option = option
        self.staging: Path | None = None
        self._lock: contextlib.AbstractContextManager | None = None
        self._manifest: dict[str, dict] = {}
        self._created = False  # the folder did not exist before this run
        self._committed = False
        self._ids: tuple = ()  # (OUT, staging) identities: removed or replaced during the run?

    # --- entering: every check before any work ---------------------------------------------------
    def check(self) -> None:
        """The checks of entering that need no lock (inputs, an existing file as ``OUT``, files this
        run may not replace): for a command that refuses before its work and enters later."""
        check_inputs(self.out, self.inputs, self.option)
        _check_writable(self.out, self.option)
        if self.out.is_dir():
            self._refuse_existing(read_manifest(self.out))

    def _refuse_existing(self, manifest: dict[str, dict]) -> None:
        """OutputConflictError for what is in ``OUT`` where this run writes: a file where it makes a
        folder, a file of its patterns that it may not replace."""
        for pattern in self.patterns:
            parts = Path(pattern).parts[:-1]
            for k in range(1, len(parts) + 1):
                folder = self.out.joinpath(*parts[:k])
                if folder.is_symlink():  # its files would land outside OUT (in a recording, a user's folder)
                    raise OutputConflictError(
                        f"{folder} is a symbolic link where this run writes a folder: not followed (the "
                        f"files would land outside {self.option}); choose another {self.option} or move it "
                        "away"
                    )
                if (folder.exists() or folder.is_symlink()) and not folder.is_dir():
                    raise OutputConflictError(
                        f"{folder} is a file where this run writes a folder: not replaced; choose another "
                        f"{self.option} or move it away"
                    )
        for relative in self._existing(self.patterns):
            _refuse(self.out, relative, manifest, self.option, self.command)

    def __enter__(self) -> OutputFolder:
        check_inputs(self.out, self.inputs, self.option)
        self._created = not self.out.exists()
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(f"{self.option}: cannot create {self.out} ({exc.strerror or exc})") from None
        self._lock = hold_lock(self.out, self.command)
        self._lock.__enter__()
        try:
            self._manifest = read_manifest(self.out)
            self._refuse_existing(self._manifest)
            try:
                staging = tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", dir=self.out)
            except OSError as exc:
                if exc.errno in NO_SPACE:
                    raise _space_error(exc, self.out, self.option) from None
                raise
            self.staging = Path(staging)
            self._ids = (_identity(self.out), _identity(self.staging))
        except BaseException:
            self._release()
            raise
        return self

    def _existing(self, patterns: Sequence[str]) -> list[str]:
        """Files under ``OUT`` whose relative path matches one of ``patterns`` (only the folders the
        patterns name are listed: an ``OUT`` that holds much else is not walked)."""
        found = set()
        for pattern in patterns:
            folder, name = os.path.split(pattern)
            try:
                entries = list(os.scandir(self.out / folder))
            except OSError:  # no such folder (or not one): nothing there to replace
                continue
            for entry in entries:
                relative = os.path.join(folder, entry.name) if folder else entry.name
                if relative not in RESERVED_NAMES and fnmatch.fnmatchcase(entry.name, name):
                    found.add(relative)
        return sorted(found)

    def _check_still_there(self) -> None:
        """OSError when ``OUT`` or the staging folder was removed or replaced since the run began."""
        if (_identity(self.out), _identity(self.staging)) != self._ids:
            raise OSError(
                f"{self.option} {self.out} was removed or replaced while the run wrote into it: nothing "
                "of this run was committed (its outputs are lost); run it again"
            )

    # --- writing ---------------------------------------------------------------------------------
    def path(self, relative: str | os.PathLike) -> Path:
        """Where to write ``OUT/relative`` during the run (in the staging folder; folders created)."""
        if self.staging is None:
            raise RuntimeError("OutputFolder.path() outside its with-block")
        self._check_still_there()
        staged = self.staging / relative
        staged.parent.mkdir(parents=True, exist_ok=True)  # inside the staging folder, which exists
        return staged

    def final(self, relative: str | os.PathLike) -> Path:
        """Where ``relative`` will be once committed (``OUT/relative``)."""
        return self.out / relative

    def commit(self) -> list[Path]:
        """Move every staged file into ``OUT``, all or nothing (see the module docstring); remove the
        previous files of this command that this run did not rewrite; returns the files, in ``OUT``.

        Raises OutputConflictError, before anything is moved, when a staged file would replace a file
        that no run wrote, or another command's (it appeared during the run): the staging folder is
        then kept and named. OSError (:class:`OutputSpaceError` for a full disk) when ``OUT`` was
        removed during the run or the commit could not complete: ``OUT`` is then as it was."""
        assert self.staging is not None
        self._check_still_there()
        staged = sorted(
            os.path.relpath(os.path.join(root, name), self.staging)
            for root, _, files in os.walk(self.staging)
            for name in files
        )
        manifest = read_manifest(self.out)
        for relative in staged:
            if relative in RESERVED_NAMES:
                raise OutputConflictError(f"{relative} is a name this folder's machinery uses")
            try:
                _refuse(self.out, relative, manifest, self.option, self.command)
            except OutputConflictError as exc:
                kept, self.staging = self.staging, None  # not removed: the results are there
                raise OutputConflictError(f"{exc}; this run's outputs are in {kept}") from None
        new = {rel: _stamp(self.staging / rel, self.command) for rel in staged}  # os.replace keeps them
        kept_files = {rel: st for rel, st in manifest.items() if _ours(self.out, rel, manifest)}
        try:
            # 1. the manifest first: once it is in place, every file it lists is recognised as ours
            _write_manifest_file(self.out, {**kept_files, **new}, self.command)
            # 2. the files, each whole; those they replace set aside until every move succeeded
            written = self._move_all(staged)
        except OSError as exc:
            with contextlib.suppress(OSError):
                _write_manifest_file(self.out, manifest, self.command)  # the previous one, as it was
            if exc.errno in NO_SPACE:
                raise _space_error(exc, self.out, self.option) from None
            raise OSError(
                f"{self.option} {self.out}: the commit failed ({exc}); nothing of this run was committed"
            ) from None
        # 3. the files of this command's previous run that this one did not write again
        for relative, stamp in kept_files.items():
            if relative not in new and stamp.get("command") == self.command:
                with contextlib.suppress(OSError):
                    (self.out / relative).unlink()
                    self._remove_empty_parents(self.out / relative)
        final = {rel: st for rel, st in kept_files.items() if rel in new or st.get("command") != self.command}
        final.update(new)
        with contextlib.suppress(OSError):  # failing, the manifest of step 1 (a superset) stays: harmless
            _write_manifest_file(self.out, final, self.command)
        self._manifest = final
        self._committed = True
        return written

    def _move_all(self, staged: list[str]) -> list[Path]:
        """``os.replace`` every staged file into ``OUT``; on a failure, the moved files go back and the
        files they replaced are restored, and the error is raised."""
        aside = self.staging / ".replaced"  # inside the staging folder: the same file system
        moved: list[str] = []
        set_aside: list[str] = []
        try:
            for relative in staged:
                source, target = self.staging / relative, self.out / relative
                target.parent.mkdir(parents=True, exist_ok=True)
                if target.exists() or target.is_symlink():
                    (aside / relative).parent.mkdir(parents=True, exist_ok=True)
                    os.replace(target, aside / relative)
                    set_aside.append(relative)
                os.replace(source, target)
                moved.append(relative)
        except OSError:
            for relative in reversed(moved):
                with contextlib.suppress(OSError):
                    os.replace(self.out / relative, self.staging / relative)
            for relative in set_aside:
                with contextlib.suppress(OSError):
                    os.replace(aside / relative, self.out / relative)
            raise
        return [self.out / rel for rel in staged]

    def _remove_empty_parents(self, path: Path) -> None:
        parent = path.parent
        while parent != self.out and self.out in parent.parents:
            try:
                parent.rmdir()  # only when empty
            except OSError:
                return
            parent = parent.parent

    # --- leaving ---------------------------------------------------------------------------------
    def _release(self) -> None:
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None
        if self._lock is not None:
            lock, self._lock = self._lock, None
            lock.__exit__(None, None, None)
            if self._created and not self._committed:  # a failed first run leaves no empty folder behind
                with contextlib.suppress(OSError):
                    self.out.rmdir()

    def __exit__(self, exc_type, exc, tb) -> None:
        self._release()
        if isinstance(exc, OSError) and not isinstance(exc, OutputSpaceError) and exc.errno in NO_SPACE:
            raise _space_error(exc, self.out, self.option) from None
