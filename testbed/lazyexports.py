"""A package's public names, imported when first used rather than when the package is.

`testbed down` needs a few small modules of `testbed.topology`, but importing the package ran
its whole `__init__`: the builder, the link backends, the scenario loader and pyroute2, two
thirds of a second before any work. A package lists its exports here instead (PEP 562): each
name is looked up in its module the first time it is read, then kept in the package.
Type checkers and the import-layer check still see the imports, in the package's
`TYPE_CHECKING` block.

Where an export has the name of its own submodule (`testbed.topology.build` defines
`build`), importing that submodule would bind the package's attribute to the module; the
package's module class keeps the export there instead, as the eager `from .build import build`
did.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any


def lazy(package: str, exports: dict[str, str]) -> None:
    """Make `package` (an `__init__` calls this with its `__name__`) resolve `exports`, a map
    from each public name to the submodule (relative to the package) that defines it."""
    module = sys.modules[package]
    module.__class__ = type("LazyPackage", (_LazyPackage,), {"_exports": exports})


class _LazyPackage(types.ModuleType):
    _exports: dict[str, str]

    def __getattr__(self, name: str) -> Any:
        submodule = self._exports.get(name)
        if submodule is None:
            raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{self.__name__}.{submodule}"), name)
        self.__dict__[name] = value
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        if (
            isinstance(value, types.ModuleType)
            and value.__name__ == f"{self.__name__}.{name}"
            and self._exports.get(name) == name
        ):
            value = getattr(value, name)  # the submodule is loaded: keep its export here
        super().__setattr__(name, value)

    def __dir__(self) -> list[str]:
        return sorted({*self.__dict__, *self._exports})
