"""zagv's services.

Importing the package makes OpenBLAS single-threaded in every zagv process (``OPENBLAS_NUM_THREADS=1`` unless the
environment already sets it), before numpy or scipy load it. The services' arrays are small (541 beams, a few
thousand particles), so a BLAS thread pool per process only oversubscribes the robot's cores; and OpenBLAS has
returned wrong results when one process calls it from more than one thread at a time, as a service does from its
event loop and its Zenoh reader threads (numpy issues 11046, 27036, 29391: all gone with one BLAS thread).
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
