"""Readers and writers: ROS bags, LAS/LAZ, PLY, PCD, and atomic output files."""
