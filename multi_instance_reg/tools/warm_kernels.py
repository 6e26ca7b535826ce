"""python -m multi_instance_reg.tools.warm_kernels: compile the numba kernels of the front ends,
the verification and the tracker once, into numba's on-disk cache (run by ``make install``).

Without it, every process of a new checkout compiles them on its first frame: ``make test``'s
four pytest processes and the tools they start each built the same kernels at once, some
30 s of CPU each on this 2-core machine. A convex and a non-convex mesh model (a carton,
an L bracket) reach the shape path's kernels; the rest are called once on small input."""
from __future__ import annotations

import sys
import time

import numpy as np


def main() -> int:
    from ..evaluation.pose_errors import mspd, mssd
    from ..models.mesh_model import build_model_from_mesh
    from ..models.mesh_render import rasterise
    from ..rgbd.registration import register_depth
    from ..rgbd.pipeline import InstanceRegistration
    from ..synthetic.objects import get_object, object_mesh
    from ..tracking.icp import warm_up as warm_up_tracker

    t0 = time.perf_counter()
    for name in ("carton", "bracket"):
        spec = get_object(name)
        InstanceRegistration(build_model_from_mesh(object_mesh(spec), spec.name)).warm_up()
    warm_up_tracker()
    K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    register_depth(np.full((48, 64), 0.5, np.float32), K, K, np.eye(4), (48, 64))
    T = np.eye(4)
    T[2, 3] = 0.5
    mesh = object_mesh(get_object("carton"))
    for weights in (False, True):
        rasterise(mesh.vertices, mesh.triangles, T, K, 64, 48, weights)
    vertices, no_symmetry = np.asarray(mesh.vertices, np.float64), np.eye(4)[None]
    mssd(T, T, vertices, no_symmetry)
    mspd(T, T, K, vertices, no_symmetry)
    print(f"numba kernels of the front ends and the tracker compiled into numba's cache in "
          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
