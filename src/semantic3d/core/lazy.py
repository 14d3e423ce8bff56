"""Lazy package exports: a package ``__init__`` names its public objects without importing them.

Importing ``semantic3d.io`` must not compile numba kernels, nor ``semantic3d.baselines``
load scikit-learn: the command line imports only what the command it runs needs. A
package lists ``{name: module}`` and gets a module-level ``__getattr__`` that imports the
module on first access (PEP 562); static type checkers read the ``TYPE_CHECKING`` imports
that sit beside it.

>>> getattr_, dir_ = lazy_exports("pkg", {"dumps": "json"})
>>> getattr_("dumps").__name__
'dumps'
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(
    package: str, exports: Mapping[str, str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package`` exporting ``name`` from ``exports[name]``.

    A name is imported on first access and then stored in the package's namespace, so
    later accesses cost nothing.
    """

    def get_attribute(name: str) -> Any:
        module_name = exports.get(name)
        if module_name is not None:
            value = getattr(importlib.import_module(module_name), name)
        elif not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}"):
            # A submodule, as it was when the package imported its modules eagerly.
            value = importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = sys.modules.get(package)
        if module is not None:
            setattr(module, name, value)
        return value

    def list_attributes() -> list[str]:
        module = sys.modules.get(package)
        return sorted(set(exports) | set(vars(module) if module is not None else ()))

    return get_attribute, list_attributes
