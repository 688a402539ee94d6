"""dali: domain adaptive LiDAR car detection (PTSN + PPCG) on a CPU."""

import os

__version__ = "0.1.0"

# MKL's conditional numerical reproducibility: the same matrix products on every run of one
# machine and thread count (dali_cli/runtime/kernels.py says why). MKL reads it when it starts,
# so it is set here, before any command imports torch; a user's own MKL_CBWR is kept.
MKL_CNR_MODE = "AUTO,STRICT"
os.environ.setdefault("MKL_CBWR", MKL_CNR_MODE)
