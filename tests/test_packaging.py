"""A non-editable install carries every package: pyproject.toml lists each folder of tg_gpudrive/ (and
kernels/, installed as tg_gpudrive.kernels) that holds an __init__.py."""

from __future__ import annotations

import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_pyproject_lists_every_package():
    setup = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(setup["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "tg_gpudrive").rglob("__init__.py")
             if "__pycache__" not in p.parts}
    found |= {"tg_gpudrive.kernels"} if (REPO / "kernels" / "__init__.py").exists() else set()
    assert found <= listed, f"packages missing from pyproject.toml: {sorted(found - listed)}"
    assert setup["package-dir"]["tg_gpudrive.kernels"] == "kernels"


def test_every_packaged_checkpoint_is_package_data():
    """A non-editable install ships only the package-data files: every .pt beside the code (the packaged
    policies and world models that configs name, e.g. grid.yaml's `init_policy: shipped_v1`) is listed."""
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for pt in (REPO / "tg_gpudrive").rglob("*.pt"):
        pkg = ".".join(pt.parent.relative_to(REPO).parts)
        assert pt.name in data.get(pkg, []), f"{pt.relative_to(REPO)} is missing from pyproject's package-data[{pkg!r}]"
