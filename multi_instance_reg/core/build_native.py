"""python -m multi_instance_reg.core.build_native: compile the ECC kernels ahead of time
(see native.py; run by ``make install``). Needs a C compiler; takes about a minute."""
from __future__ import annotations

import os
import subprocess
import sys
import time


def main() -> int:
    if os.environ.get("MIREG_KERNELS") != "build":
        # The stage modules must be imported in build mode: numba functions, serial.
        return subprocess.call([sys.executable, "-m", "multi_instance_reg.core.build_native"], env=dict(os.environ, MIREG_KERNELS="build"))
    from . import native

    t0 = time.perf_counter()
    native.build()
    print(f"compiled {len(native.ENTRY_POINTS)} ECC kernels ahead of time into "
          f"{native._HERE}/{native._AOT_NAME}*.so in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
