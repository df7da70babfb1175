"""ROS 2 nodes: thin adapters that wire the cores to topics, parameters and services."""
