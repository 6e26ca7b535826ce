"""The ROS 2 layer: a thin rclpy wrapper that converts messages, holds parameters, publishes."""
