"""Package discovery for setuptools; every other setting is in pyproject.toml.

The repository keeps ``drivers/`` and ``sim_backends/`` as folders of their own; they install as
``rths_hil.drivers`` and ``rths_hil.sim_backends`` (``[tool.setuptools.package-dir]``). Every
package below the three folders is found here, so a new sub-package needs no list.
"""

from setuptools import find_namespace_packages, setup

#: Installed package name → the repository folder that holds it.
ROOTS = {
    "rths_hil": "rths_hil",
    "rths_hil.drivers": "drivers",
    "rths_hil.sim_backends": "sim_backends",
}


def packages() -> list[str]:
    """The installed packages: each root and every folder below it (data folders included)."""
    found: list[str] = []
    for name, folder in ROOTS.items():
        found.append(name)
        below = find_namespace_packages(where=folder, exclude=["*__pycache__*"])
        found += [f"{name}.{p}" for p in below if f"{name}.{p}" not in ROOTS]
    return found


setup(packages=packages())
