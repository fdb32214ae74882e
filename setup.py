"""The C extensions, each built at install: the A* search loop (services/nav/_astar.c), the DWA rollout
(services/nav/_navops.c), the grid distance transform and labelling (services/common/_gridops.c) and the scan
likelihood of the refinement at rest (services/localization/_refine.c); everything else is declared in
pyproject.toml.

``optional=True``: where no C compiler is available the install goes on; services.nav.astar then runs its pure-Python
loop (same paths, about 15x slower) with a warning, services.common.gridops uses scipy.ndimage, and the DWA rollout
and the refinement use NumPy (about 3x and 6x slower).
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("services.nav._astar", ["services/nav/_astar.c"],
                             extra_compile_args=["-O2", "-ffp-contract=off"], optional=True),
                        Extension("services.nav._navops", ["services/nav/_navops.c"], include_dirs=["services/common"],
                                  depends=["services/common/_pybuffer.h"],
                                  extra_compile_args=["-O2", "-ffp-contract=off"], optional=True),
                        Extension("services.localization._refine", ["services/localization/_refine.c"],
                                  include_dirs=["services/common"], depends=["services/common/_pybuffer.h"],
                                  extra_compile_args=["-O2", "-ffp-contract=off"], optional=True),
                        Extension("services.common._gridops", ["services/common/_gridops.c"],
                                  extra_compile_args=["-O2", "-ffp-contract=off"], optional=True)])
