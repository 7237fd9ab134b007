"""The network testbed: two network namespaces joined by a tc-shaped veth pair, iperf3, and ROS across it."""
