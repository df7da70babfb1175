"""ROS-free cores (numpy + numba): physics, samples, lock-in, z controller, scanner, imaging."""
