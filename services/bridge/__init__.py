"""Adapters to other ecosystems (Foxglove, ROS 2): one module per ecosystem."""
