"""Dataset readers and writers (rosbag2 via rosbags; no ROS install needed)."""
