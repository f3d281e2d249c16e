"""Names a package re-exports from a heavy submodule, imported when first used (PEP 562).

Importing any submodule runs its package's `__init__.py` first: one that imported the
detectors (OpenCV) or the geometric checks (OpenCV, SciPy) eagerly would make
`import doseqslam_logs.detector.params` cost a second, and so every command's `--help`. The
package lists the names under `TYPE_CHECKING` for the type checker and sets
`__getattr__ = lazy_names(__name__, {submodule: names})`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable, Mapping


def lazy_names(package: str, names: Mapping[str, Iterable[str]]) -> Callable[[str], object]:
    """A module `__getattr__` for `package`: the names of each submodule (relative to
    `package`) read from it, imported at the first access to one of them."""
    homes = {name: module for module, listed in names.items() for name in listed}

    def attribute(name: str) -> object:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{home}"), name)

    return attribute
