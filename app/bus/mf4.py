"""MF4 support loaded when a log needs it, not when python-can is imported.

`import can` imports python-can's MF4 module, which imports asammdf when it is installed (the
`mf4` extra), and asammdf imports numpy, pandas, sympy and canmatrix: about a second of CPU, a
third of a gateway's start, paid by every `eqgw` process whether or not it ever reads or writes
an MF4 log. `defer()` (called by `eqgw/__init__`, before anything imports `can`) has python-can's
MF4 module first load as if asammdf were absent; `load()` (called before an MF4 file is read or
written) runs that module again with asammdf, in the same module object, so python-can's
`MF4Reader`, `MF4Writer` and its reader table, which look asammdf up in that module's globals,
work from then on. Where `can` was imported before `eqgw`, nothing is deferred and `load()` only
says whether asammdf is there.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import threading
from collections.abc import Sequence
from types import ModuleType

_MODULE = "can.io.mf4"
_lock = threading.Lock()
_deferred = False  # python-can's MF4 module was first run without asammdf by this module


class _WithoutAsammdf(importlib.abc.Loader):
    """Runs python-can's MF4 module the first time with `import asammdf` failing."""

    def __init__(self, loader: importlib.abc.Loader) -> None:
        self._loader = loader

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        global _deferred
        if _deferred or "asammdf" in sys.modules:  # load()'s run, or asammdf already in
            self._loader.exec_module(module)
            return
        sys.modules["asammdf"] = None  # type: ignore[assignment]  # import fails: ImportError
        try:
            self._loader.exec_module(module)
            _deferred = True
        finally:
            del sys.modules["asammdf"]


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname != _MODULE:
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is not None and spec.loader is not None:
            spec.loader = _WithoutAsammdf(spec.loader)
        return spec


def defer() -> None:
    """Have python-can's MF4 module load without asammdf (a no-op once `can` is imported)."""
    if _MODULE in sys.modules or "can" in sys.modules:
        return
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())


def load() -> bool:
    """Make python-can's MF4 reader and writer usable: whether asammdf is installed."""
    with _lock:
        mf4 = importlib.import_module(_MODULE)
        if getattr(mf4, "asammdf", None) is not None:
            return True
        if not _deferred:
            return False  # run with asammdf visible: it is not installed
        try:
            importlib.import_module("asammdf")
        except ImportError:
            return False
        importlib.reload(mf4)
        return getattr(mf4, "asammdf", None) is not None
