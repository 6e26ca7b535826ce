"""The DDS transport for camera-sized messages.

Fast DDS's default shared-memory segment (512 KiB) is smaller than one 640x480 colour image,
so images travel as UDP fragments instead (measured here: publish -> callback p50 14 ms for
640x480 rgb8, 3 ms through a large enough segment). ``fastdds_large_data.xml`` gives the
shared-memory transport a 64 MiB segment. Every ROS process of this package uses it unless the
user chose a profile of their own (or /dev/shm is small); the camera driver needs it too, since the sender's segment
is the one that carries a sample:

    export FASTRTPS_DEFAULT_PROFILES_FILE=$(python -m multi_instance_reg.ros.transport)

Run as a module, this prints the profile's path.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

PROFILE = Path(__file__).with_name("fastdds_large_data.xml")
_PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
# Each participant maps a segment of 64 MiB (touched only as used); below this much free
# shared memory (Docker's default /dev/shm is 64 MiB) Fast DDS keeps its own defaults.
_MIN_FREE_SHM = 512 * 2**20


def _free_shared_memory(path: str = "/dev/shm") -> int:
    try:
        return shutil.disk_usage(path).free
    except OSError:
        return 0


def use_large_data_profile(environ=os.environ, free_shared_memory=None) -> bool:
    """Point Fast DDS at the large-data profile unless a profile is already chosen, another
    middleware is, or /dev/shm is too small for it. Call before rclpy.init; returns whether
    it was set."""
    if any(environ.get(v) for v in _PROFILE_VARIABLES):
        return False
    free = _free_shared_memory() if free_shared_memory is None else free_shared_memory
    if free < _MIN_FREE_SHM:
        return False
    if environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") not in ("rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"):
        return False
    environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(PROFILE)
    return True


if __name__ == "__main__":
    print(PROFILE)
