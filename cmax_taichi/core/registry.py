"""Named registries with explicit registration.

One :class:`Registry` each for warp models (``warps.py``), objectives (``objectives.py``) and
regularizers (``regularizers.py``). Each of those modules registers its built-in entries by one explicit
call at its bottom; users add their own with :func:`register_warp` and friends, in their own code or in
a plugin: a module or a Python file that registers entries when it is imported (:func:`load_plugin`,
``cmax-taichi ... --plugin FILE.py``). Loading a plugin is all or nothing: a plugin that fails half-way
(an error, or ``sys.exit`` while it is imported) leaves every registry as it was, so the fixed plugin
loads in the same process.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import sys
from collections.abc import Iterator, MutableMapping
from pathlib import Path
from types import ModuleType
from typing import Generic, TypeVar

T = TypeVar("T")

#: every registry's mapping (and the other name -> entry tables a plugin may fill, see :func:`track`):
#: what :func:`load_plugin` restores when a plugin fails
_TRACKED: list[MutableMapping] = []


def track(mapping: MutableMapping) -> MutableMapping:
    """Put a name -> entry table that plugins may fill (beside the registries, e.g. the NumPy twins of
    the warps) under :func:`load_plugin`'s all-or-nothing rule; returns it."""
    _TRACKED.append(mapping)
    return mapping


class Registry(Generic[T]):
    """A name -> entry mapping whose errors list the valid names.

    Parameters
    ----------
    kind : str
        What the entries are ("warp", "objective", ...), used in error messages.
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._entries: dict[str, T] = track({})
        self._origins: dict[str, str | None] = track({})

    def register(self, name: str, entry: T, *, replace: bool = False, builtin: bool = False) -> T:
        """Add ``entry`` under ``name``; refuse to overwrite an existing name unless ``replace``.
        ``builtin``: the library's own entry (:meth:`origin`)."""
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"{self.kind} name must be an identifier-like string, got {name!r}")
        if name in self._entries and not replace:
            raise ValueError(f"a {self.kind} named {name!r} is already registered")
        self._entries[name] = entry
        self._origins[name] = "" if builtin else (_LOADING[-1] if _LOADING else None)
        return entry

    def origin(self, name: str) -> str | None:
        """Where the entry ``name`` was registered: ``""`` by the library, a plugin's spec (the file or
        module :func:`load_plugin` imported), or None by the running script (which another process
        cannot import: ``pipeline/tiers.py`` compiles such entries in the process)."""
        self.get(name)
        return self._origins.get(name)

    def get(self, name: str) -> T:
        """The entry called ``name``; ValueError listing the valid names otherwise."""
        if not isinstance(name, str):
            raise TypeError(f"{self.kind} name must be a string, got {type(name).__name__}")
        try:
            return self._entries[name]
        except KeyError:
            raise ValueError(
                f"unknown {self.kind} {name!r}; valid {self.kind}s are: {', '.join(self.names())}"
            ) from None

    def unregister(self, name: str) -> T:
        """Remove the entry called ``name`` and return it; KeyError naming the valid names otherwise."""
        if name not in self._entries:
            raise KeyError(f"no {self.kind} named {name!r}; registered: {', '.join(self.names())}")
        self._origins.pop(name, None)
        return self._entries.pop(name)

    def names(self) -> list[str]:
        return list(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)


class PluginError(ImportError):
    """A plugin could not be imported (the message names it and the reason)."""


#: the plugins being imported by load_plugin (innermost last): what registers now comes from them
_LOADING: list[str] = []

#: plugins imported in this process, by module name or resolved path (each is imported once)
_PLUGINS: dict[str, ModuleType] = {}


def load_plugin(spec: str) -> ModuleType:
    """Import a plugin: a Python file (``path/to/file.py``) or an importable module (``package.module``)
    that registers warps, objectives or regularizers when it is imported. Each plugin is imported once
    per process; loading it again returns the module. All or nothing: when the import fails, whatever
    the plugin registered before it failed is removed again (and what it replaced put back).

    Raises
    ------
    PluginError
        (an ImportError) naming the plugin: no such file or module, the exception its code raised, or
        its call of ``sys.exit`` while it was imported.
    """
    snapshot = [(mapping, dict(mapping)) for mapping in _TRACKED]
    try:
        return _import_plugin(spec)
    except BaseException:
        for mapping, before in snapshot:  # the registries as they were before the plugin ran
            mapping.clear()
            mapping.update(before)
        raise


def _import_plugin(spec: str) -> ModuleType:
    if not isinstance(spec, str) or not spec.strip():
        raise PluginError(f"a plugin is a module name or a .py file, got {spec!r}")
    spec = spec.strip()
    path = Path(spec).expanduser()
    is_file = spec.endswith(".py") or path.is_file()
    key = str(path.resolve()) if is_file else spec
    if key in _PLUGINS:
        return _PLUGINS[key]
    try:
        if is_file:
            if not path.is_file():
                raise PluginError(f"plugin {spec}: no such file")
            digest = hashlib.sha1(key.encode()).hexdigest()[:8]
            name = f"cmax_taichi_plugin_{path.stem}_{digest}"
            module_spec = importlib.util.spec_from_file_location(name, path)
            if module_spec is None or module_spec.loader is None:
                raise PluginError(f"plugin {spec}: not a Python file")
            module = importlib.util.module_from_spec(module_spec)
            sys.modules[name] = module
            _LOADING.append(key)
            try:
                module_spec.loader.exec_module(module)
            except BaseException:
                sys.modules.pop(name, None)
                raise
            finally:
                _LOADING.pop()
        else:
            _LOADING.append(key)
            try:
                module = importlib.import_module(spec)
            finally:
                _LOADING.pop()
    except PluginError:
        raise
    except SystemExit as exc:  # the plugin ended the import, not the process: the command must not exit 0
        raise PluginError(f"plugin {spec}: called sys.exit({exc.code!r}) while being imported") from None
    except ModuleNotFoundError as exc:
        if not is_file and exc.name is not None and spec.startswith(exc.name):
            raise PluginError(f"plugin {spec}: no such module (nor a file of that name)") from None
        raise PluginError(f"plugin {spec}: {type(exc).__name__}: {exc}") from exc
    except Exception as exc:
        raise PluginError(f"plugin {spec}: {type(exc).__name__}: {exc}") from exc
    _PLUGINS[key] = module
    return module
