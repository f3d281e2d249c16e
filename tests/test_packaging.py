"""The installed package holds every subpackage and every message definition."""

from __future__ import annotations

import sys
from pathlib import Path

from doseqslam_logs.annotations.schema_files import read_schema

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]


def test_every_subpackage_is_listed_in_pyproject() -> None:
    """pyproject lists packages explicitly (schemas/ is mapped in): a new one must be added."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    listed = set(config["tool"]["setuptools"]["packages"])
    found = {
        ".".join(init.parent.relative_to(REPO).parts)
        for init in (REPO / "doseqslam_logs").rglob("__init__.py")
    }
    assert found <= listed, f"add to pyproject.toml: {sorted(found - listed)}"


def test_message_definitions_are_readable_from_the_package() -> None:
    for name in ("LoopClosure", "Sequence"):
        assert "float64 f" in read_schema(f"ros2/{name}.msg")
        assert "float64 f" in read_schema(f"ros1/{name}.msg")
        assert '"f"' in read_schema(f"json/{name}.json")


def test_every_schema_file_is_installed_by_package_data() -> None:
    """Each schemas/ folder is a listed package whose globs take all of its files.

    Folders without an `__init__.py` that are not listed make setuptools warn on every
    install and are only shipped by accident of its legacy behaviour.
    """
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages, data = set(config["packages"]), config["package-data"]
    for path in (REPO / "schemas").rglob("*"):
        if not path.is_file() or path.suffix in (".py", ".pyc"):
            continue
        folder = path.parent.relative_to(REPO / "schemas").parts
        package = ".".join(("doseqslam_logs", "schemas", *folder))
        assert package in packages, f"add {package} to pyproject.toml's packages"
        globs = data.get(package, [])
        assert any(path.match(glob) for glob in globs), f"{path.name} not in {package}'s data"
