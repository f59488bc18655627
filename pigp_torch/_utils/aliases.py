r"""The old import path of a renamed package: :func:`alias_package` makes ``old.<m>`` import as
``new.<m>`` — the same module object (its state and a monkeypatch are shared), loaded on first
use like any import — and ``python -m old.<m>`` run ``new.<m>``. Nothing else stays at the old
path but its ``__init__``, so that a file moved by ``git mv`` is seen as moved."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys


class _AliasLoader(importlib.abc.Loader):
    """Loads ``old.<m>`` as the module ``new.<m>`` itself (imported if it is not yet)."""

    def __init__(self, target: str) -> None:
        self.target = target
        self._spec = None

    def create_module(self, spec):
        module = importlib.import_module(self.target)
        self._spec = module.__spec__  # the import machinery sets the alias's spec on it
        return module

    def exec_module(self, module) -> None:
        module.__spec__ = self._spec  # the module keeps its own spec; nothing runs twice

    def get_code(self, fullname: str):
        """The moved module's code (``python -m old.<m>``)."""
        return importlib.util.find_spec(self.target).loader.get_code(self.target)


class _AliasFinder(importlib.abc.MetaPathFinder):
    """Finds ``old.<m>`` wherever ``new.<m>`` exists."""

    def __init__(self, old: str, new: str) -> None:
        self.old, self.new = old, new

    def find_spec(self, fullname: str, path=None, target=None):
        if not fullname.startswith(self.old + "."):
            return None
        moved = self.new + fullname[len(self.old) :]
        if moved not in sys.modules and importlib.util.find_spec(moved) is None:
            return None
        return importlib.util.spec_from_loader(fullname, _AliasLoader(moved))


def alias_package(old: str, new: str, namespace: dict | None = None) -> None:
    """Make every module ``new.<m>`` importable as ``old.<m>`` (idempotent); call it from the
    ``__init__`` of ``old``. With ``namespace`` (that ``__init__``'s ``globals()``), ``new`` is
    imported and its public names (``__all__``, and ``__all__`` itself) are set there, so that
    ``from old import name`` gives ``new``'s object."""
    if not any(isinstance(f, _AliasFinder) and f.old == old for f in sys.meta_path):
        sys.meta_path.append(_AliasFinder(old, new))
    if namespace is not None:
        moved = importlib.import_module(new)
        namespace["__all__"] = list(moved.__all__)
        namespace.update({name: getattr(moved, name) for name in moved.__all__})
