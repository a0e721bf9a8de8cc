"""EdgeLoc algorithms, pure Python/numpy/torch. Nothing here imports ROS or pyroute2."""
