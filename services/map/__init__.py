"""The map: walls fused across scan poses into a floor plan a planner uses.

* :mod:`~lelsonar.map.observation`: what the map takes in, one scan at a time (pose, walls, corners, edges).
* :mod:`~lelsonar.map.fusion`: :class:`~lelsonar.map.fusion.WallMapper`, data association and the factor
  graph (GTSAM, ISAM2), verdicts that carry over; :mod:`~lelsonar.map.tracks`: the walls while the map
  grows and the association gate; :mod:`~lelsonar.map.fused_walls`: a wall read out (verdict, pieces).
* :mod:`~lelsonar.map.result`: the fused map and its public JSON.
* :mod:`~lelsonar.map.floorplan`: segments, free space (shapely, GeoJSON), an occupancy grid, wall
  markers, and a route (networkx) that keeps the robot's radius from every wall.
* :mod:`~lelsonar.map.from_reconstruction`: the reconstruction's planes of record as wall observations.
* :mod:`~lelsonar.map.service`: the live mapper (``lelsonar mapper``), the map on ``<prefix>/map``;
  :mod:`~lelsonar.map.wire`: the map as the contract's ``Map`` message.
* :mod:`~lelsonar.map.synthetic`: walls seen from known poses with stated noise, for tests and the bench.
"""
