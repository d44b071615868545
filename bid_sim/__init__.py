"""bid-sim: the world side of the closed loop (towns, traffic, ego, routes, infractions)."""

# OpenCV is loaded before libsumo on purpose: a C++ extension first loaded after libsumo has
# raised an error (e.g. a vehicle gone mid-episode) makes the next SUMO start segfault
# (libsumo 1.28, opencv-python-headless 4.x and torch 2.13, seen here). torch is loaded by
# the agents that need it, before any episode runs.
import cv2  # noqa: F401

__version__ = "0.1.0"
