"""Front ends: what turns an RGB-D frame and an object model into model-to-scene
correspondences for ECC, and checks the poses ECC finds from them. No ROS.

- ``sift``: from texture (SIFT keypoints lifted to 3D, one-to-many matching, guided matching).
- ``shape``: from depth alone (point pairs over connected segments, faces), each pose explained
  against the frame and the instances chosen jointly (``shape/explain.py``).

The per-frame pipeline (``rgbd.pipeline``) runs one or both of them.
"""
