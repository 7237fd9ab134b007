"""Bringup: the fleet configuration, the supervisor that starts the physical and digital twins, launch files and the paper's experiments."""
