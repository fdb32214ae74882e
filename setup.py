"""The C extensions: the A* search loop (services/nav/_astar.c) and the grid distance transform and labelling
(services/common/_gridops.c); everything else is declared in pyproject.toml.

``optional=True``: where no C compiler is available the install goes on; services.nav.astar then runs its pure-Python
loop (same paths, about 15x slower) with a warning, and services.common.gridops uses scipy.ndimage.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("services.nav._astar", ["services/nav/_astar.c"],
                             extra_compile_args=["-O2", "-ffp-contract=off"], optional=True),
                        Extension("services.common._gridops", ["services/common/_gridops.c"],
                                  extra_compile_args=["-O2", "-ffp-contract=off"], optional=True)])
