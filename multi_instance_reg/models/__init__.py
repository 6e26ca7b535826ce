"""Object models: the stored file and everything that builds it. No ROS.

- ``model``: the model file (npz), loading and saving it, and building it from capture views.
- ``mesh_model``: a model from a CAD or scanned mesh (shape, symmetries, rendered keypoints).
- ``mesh_render``: colour and depth pictures of a coloured mesh, for its SIFT keypoints.
- ``capture_alignment``: capture views placed on a mesh by shape (texture and shape in one model).
"""
