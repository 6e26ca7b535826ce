import os

# Integration tests pick their own ROS_DOMAIN_ID; keep DDS discovery on this machine.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
