"""bid-sim: the world side of the closed loop (towns, traffic, ego, routes, infractions)."""

__version__ = "0.1.0"
