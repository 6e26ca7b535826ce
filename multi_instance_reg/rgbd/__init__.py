"""The RGB-D front end: images, SIFT, the stored object model, 3D lifting. No ROS import."""
