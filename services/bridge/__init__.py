"""Adapters from lelsonar to other ecosystems, outside the core data flow.

One module per ecosystem:

* :mod:`lelsonar.bridge.ros2` — ROS 2 messages (the only module importing
  ``rosbags``), the rosbag2 export, and the observer that turns a scan into
  ROS 2 topics;
* :mod:`lelsonar.bridge.rmw_zenoh` — the same topics live on rmw_zenoh key
  expressions;
* :mod:`lelsonar.bridge.foxglove` — the live Foxglove WebSocket view (the only
  module importing ``foxglove``);
* :mod:`lelsonar.cli.bridge` — ``lelsonar export`` and ``lelsonar ros2-bridge``.
"""
