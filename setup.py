"""The A* search loop's C extension (services/nav/_astar.c); everything else is declared in pyproject.toml.

``optional=True``: where no C compiler is available the install goes on and services.nav.astar runs its pure-Python
loop (same paths, about 15x slower) with a warning.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("services.nav._astar", ["services/nav/_astar.c"],
                             extra_compile_args=["-O2", "-ffp-contract=off"], optional=True)])
