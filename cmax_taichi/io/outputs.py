"""Output folders that never touch the inputs: what the commands write (``estimate``, ``segment``,
``reproduce``, and the tables of a batch) and the atomic writes of the result files.

Guarantees of an :class:`OutputFolder` (``OUT``):

* **inputs are never touched**: ``OUT`` must not be an input (a recording's file or folder), nor a
  folder that holds one; it is refused before anything is written (:class:`OutputConflictError`);
* **nothing a run did not write is replaced**: a run recognises its own earlier outputs by the manifest
  it writes, ``OUT/.cmax-taichi-manifest.json`` (each file's path, size and modification time). A file
  that this run would write and that the manifest does not list (or that changed since) is refused
  before any work, and again before it is replaced;
* **no half files**: everything is written into a staging folder inside ``OUT``
  (``.cmax-taichi-staging-<pid>-<random>``) and moved into place, file by file with ``os.replace``,
  when the run completes; an interrupted run (Ctrl-C, SIGTERM, an error) removes its staging folder
  and leaves ``OUT`` as it was. The files of the previous run that this one did not rewrite (listed
  in the manifest, unchanged since) are removed, so ``OUT`` holds the outputs of one run;
* **one run at a time**: the run holds an exclusive lock on ``OUT/.cmax-taichi.lock`` (``flock``,
  released by the kernel when the process ends, however it ends); a second run on the same ``OUT`` is
  refused at once with :class:`OutputBusyError` naming the other run. (On file systems without
  ``flock`` support, e.g. some NFS mounts, the lock may not hold.)

:func:`atomic_path` and :func:`atomic_write_text` are the single-file form: a temporary file in the
same folder, ``fsync``, then ``os.replace``.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
import shutil
import tempfile
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

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
    "atomic_path",
    "atomic_write_text",
    "check_inputs",
    "hold_lock",
    "read_manifest",
    "refuse_foreign",
    "write_manifest",
]

MANIFEST_NAME = ".cmax-taichi-manifest.json"
LOCK_NAME = ".cmax-taichi.lock"
STAGING_PREFIX = ".cmax-taichi-staging-"
MANIFEST_VERSION = 1
#: names in an output folder that belong to the machinery (never an output, never to be given as one)
RESERVED_NAMES = (MANIFEST_NAME, LOCK_NAME)


class OutputConflictError(ValueError):
    """An output would touch an input, or replace a file that no cmax-taichi run wrote."""


class OutputBusyError(OSError):
    """Another run holds the output folder's lock."""


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
    """OutputConflictError when the output folder ``out`` is one of ``inputs`` (files or folders) or a
    folder that holds one (at any depth), or an existing file. Inputs that do not exist have nothing to
    protect (the command reports them itself)."""
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
    if target.exists() and not target.is_dir():
        raise OutputConflictError(f"{option} {out} is an existing file, not a folder")


# --- the lock ---------------------------------------------------------------------------------------
@contextlib.contextmanager
def hold_lock(folder: str | os.PathLike, what: str = "cmax-taichi") -> Iterator[None]:
    """Hold the exclusive lock of ``folder`` (created) for the block; :class:`OutputBusyError` at once
    when another process holds it (its pid and command are in the message)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if fcntl is None:  # pragma: no cover
        yield
        return
    lock_path = folder / LOCK_NAME
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        locked = True
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # another process holds it
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            raise OutputBusyError(
                f"{folder} is in use by another cmax-taichi run ({holder}): wait for it to end, "
                "or choose another output folder"
            ) from None
        except OSError:  # a file system without flock (ENOLCK, ENOTSUP: some NFS mounts): no lock
            locked = False
        if locked:
            os.ftruncate(fd, 0)
            stamp = f"pid {os.getpid()}, {what}, since {time.strftime('%Y-%m-%d %H:%M:%S')}"
            os.pwrite(fd, stamp.encode(), 0)
        try:
            yield
        finally:
            if locked:
                with contextlib.suppress(OSError):
                    os.ftruncate(fd, 0)
                fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


# --- the manifest -----------------------------------------------------------------------------------
def _stamp(path: Path) -> dict:
    st = path.stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


def read_manifest(folder: Path) -> dict[str, dict]:
    """``{relative path: {"size", "mtime_ns"}}`` of the files the last run wrote into ``folder`` ({}
    without a manifest; a damaged manifest counts as none, so nothing is replaced on its word)."""
    try:
        data = json.loads((folder / MANIFEST_NAME).read_text())
        files = data["files"]
        return {str(k): dict(v) for k, v in files.items()} if isinstance(files, dict) else {}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def refuse_foreign(folder: str | os.PathLike, relative_paths: Iterable[str], option: str = "--out") -> None:
    """OutputConflictError for the first of ``relative_paths`` that exists in ``folder`` and that no
    cmax-taichi run wrote (or that changed since); for writers that write in place (a batch's tables)."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    for relative in relative_paths:
        target = folder / relative
        if target.is_dir() and not target.is_symlink():
            raise OutputConflictError(f"{target} is a folder where this run writes a file: not replaced")
        if (target.exists() or target.is_symlink()) and not _ours(folder, relative, manifest):
            raise OutputConflictError(_foreign_message(target, relative in manifest, option))


def write_manifest(folder: str | os.PathLike, relative_paths: Iterable[str], command: str) -> None:
    """Record ``relative_paths`` (files in ``folder``, as they are now) as this run's outputs, beside
    the files of earlier manifests that are still unchanged."""
    folder = Path(folder)
    previous = read_manifest(folder)
    files = {rel: stamp for rel, stamp in previous.items() if _ours(folder, rel, previous)}
    files.update({rel: _stamp(folder / rel) for rel in relative_paths})
    manifest = {
        "version": MANIFEST_VERSION,
        "command": command,
        "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "files": files,
    }
    atomic_write_text(folder / MANIFEST_NAME, json.dumps(manifest, indent=1))


def _foreign_message(target: Path, listed: bool, option: str) -> str:
    why = (
        "changed since a cmax-taichi run wrote it"
        if listed
        else (f"not written by a cmax-taichi run (no {MANIFEST_NAME} lists it)")
    )
    return f"{target} exists and was {why}: not replaced; choose another {option} or move it away"


def _ours(folder: Path, relative: str, manifest: dict[str, dict]) -> bool:
    """Whether the existing file ``folder/relative`` is one a run wrote and nobody changed since."""
    stamp = manifest.get(relative)
    if stamp is None:
        return False
    try:
        return _stamp(folder / relative) == {"size": stamp.get("size"), "mtime_ns": stamp.get("mtime_ns")}
    except OSError:
        return False


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
        name (``"figures/window_*.png"``): existing files that match and that no run wrote are refused
        before any work.
    command : str
        Named in the lock (for the message a second run gets) and the manifest.
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

    # --- entering: every check before any work ---------------------------------------------------
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
            for relative in self._existing(self.patterns):
                self._refuse_foreign(relative)
            self.staging = Path(tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", dir=self.out))
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

    def _refuse_foreign(self, relative: str) -> None:
        target = self.out / relative
        if target.is_dir() and not target.is_symlink():
            raise OutputConflictError(f"{target} is a folder where this run writes a file: not replaced")
        if not _ours(self.out, relative, self._manifest):
            raise OutputConflictError(_foreign_message(target, relative in self._manifest, self.option))

    # --- writing ---------------------------------------------------------------------------------
    def path(self, relative: str | os.PathLike) -> Path:
        """Where to write ``OUT/relative`` during the run (in the staging folder; folders created)."""
        if self.staging is None:
            raise RuntimeError("OutputFolder.path() outside its with-block")
        staged = self.staging / relative
        staged.parent.mkdir(parents=True, exist_ok=True)
        return staged

    def final(self, relative: str | os.PathLike) -> Path:
        """Where ``relative`` will be once committed (``OUT/relative``)."""
        return self.out / relative

    def commit(self) -> list[Path]:
        """Move every staged file into ``OUT`` (``os.replace``, each file whole), remove the previous
        run's files that this one did not rewrite, write the manifest; returns the files, in ``OUT``.

        Raises OutputConflictError, before anything is moved, when a staged file would replace a file
        that no run wrote (it appeared during the run): the staging folder is then kept and named."""
        assert self.staging is not None
        staged = sorted(
            os.path.relpath(os.path.join(root, name), self.staging)
            for root, _, files in os.walk(self.staging)
            for name in files
        )
        for relative in staged:
            if relative in RESERVED_NAMES:
                raise OutputConflictError(f"{relative} is a name this folder's machinery uses")
            if (self.out / relative).exists() or (self.out / relative).is_symlink():
                try:
                    self._refuse_foreign(relative)
                except OutputConflictError as exc:
                    kept, self.staging = self.staging, None  # not removed: the results are there
                    raise OutputConflictError(f"{exc}; this run's outputs are in {kept}") from None
        written = []
        for relative in staged:
            target = self.out / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(self.staging / relative, target)
            written.append(target)
        new = {rel: _stamp(self.out / rel) for rel in staged}
        for relative in self._manifest:  # the previous run's files that this one did not rewrite
            if relative not in new and _ours(self.out, relative, self._manifest):
                with contextlib.suppress(OSError):
                    (self.out / relative).unlink()
                    self._remove_empty_parents(self.out / relative)
        manifest = {
            "version": MANIFEST_VERSION,
            "command": self.command,
            "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "files": new,
        }
        atomic_write_text(self.out / MANIFEST_NAME, json.dumps(manifest, indent=1))
        self._manifest = new
        self._committed = True
        return written

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
                    (self.out / LOCK_NAME).unlink()
                    self.out.rmdir()

    def __exit__(self, *exc) -> None:
        self._release()
