"""Pairs: what is known about a matched scan pair (labels, odometry disagreement, features)."""
