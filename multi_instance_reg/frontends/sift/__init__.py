"""The SIFT front end: correspondences from texture. No ROS.

- ``features``: SIFT keypoints and descriptors of a colour image (OpenCV).
- ``matching``: one-to-many matching of a frame's keypoints to a model's (or several models').
- ``guided``: a second look, with each instance's pose, at the keypoints near it.
"""
