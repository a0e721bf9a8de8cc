"""EdgeLoc: pure algorithms (no ROS import) and the thin ROS 2 nodes around them."""
