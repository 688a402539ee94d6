"""dali: domain adaptive LiDAR car detection (PTSN + PPCG) on a CPU."""

__version__ = "0.1.0"
