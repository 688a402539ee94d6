"""dali's CPU LiDAR car detector: pillars + a multi-scale BEV backbone + CenterPoint heads with an
IoU-aware score (a documented stand-in for the paper's SECOND-IoU, see docs/method.md).

Public interface: `Detector.load(model_dir).predict(points_list, scale=1.0, mount_height_m=None)`,
`predict_frameset(model_dir, data_dir, scale=1.0, score_min=0.0, progress=True) -> BoxTable`,
and the training API (`DetectorConfig`, `load_labeled`, `Augmentation`, `TrainSettings`, `train`).
Importing this package imports torch.
"""

from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.data import Augmentation, LabeledFrames, load_labeled, size_normalize
from dali_cli.detector.infer import Detector, predict_frameset, save_checkpoint
from dali_cli.detector.model import PillarCenterNet
from dali_cli.detector.train import TrainResult, TrainSettings, train

__all__ = [
    "Augmentation",
    "Detector",
    "DetectorConfig",
    "LabeledFrames",
    "PillarCenterNet",
    "TrainResult",
    "TrainSettings",
    "load_labeled",
    "predict_frameset",
    "save_checkpoint",
    "size_normalize",
    "train",
]
