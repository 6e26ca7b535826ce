"""multi_instance_reg: find every instance of a known object in RGB-D and publish its pose.

Packages (only the last one imports ROS):
- ``core``: ECC multi-instance registration on an N x 6 correspondence array (numpy/scipy/numba).
- ``models``: object models (the stored file; built from capture views or a mesh).
- ``frontends``: correspondences for ECC from a frame: ``sift`` (texture), ``shape`` (depth).
- ``rgbd``: the per-frame pipeline over the front ends, depth lifting and checks.
- ``tracking``: instance identity over frames, kept up to date by projective ICP.
- ``datasets``: reading and writing rosbag2 files with rosbags (no ROS install needed).
- ``synthetic``: correspondence sets and rendered D455 tabletop scenes with ground truth.
- ``evaluation``: BOP scoring (VSD, MSSD, MSPD) and MHF1.
- ``tools``: the ``mireg`` command line; ``tools/bench``: the benchmarks.
- ``ros``: the rclpy node, a thin wrapper over the pipeline.

Modules beside them, used across the packages: ``transforms`` (rigid fits, poses), ``meshes``
(PLY / STL / OBJ), ``symmetry``, ``messages`` (sensor_msgs images and camera info to numpy), ``params``
(one declaration per setting), ``threads`` (BLAS thread pools), ``metrics`` (MHF1 and friends), ``gravity``,
``errors``, ``files``.
"""

__version__ = "0.1.0"
