"""ROS 2 interface package `metarig_msgs` (msg/srv files) and its colcon-free build step."""
