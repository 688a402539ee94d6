"""The detector's network as ONNX (`dali export model --onnx`) and an onnxruntime predictor.

Two graphs, opset 18, exported with torch's TorchScript exporter:

- `detector.onnx`, one frame: inputs `features` (P, 8 or 9) float32, the per-point pillar
  features of `model.pillarize`; `pillar_of_point` (P,) int64, each point's pillar; `pillar_cell`
  (V,) int64, each pillar's flat cell row * W + column of the grid. Outputs the head maps
  (1, dims, h, w) float32 named as `model.heads` (heatmap, offset, z, size, rot, iou, dir). The
  grid is fixed at export: the one the model runs on at the exported PTSN scale
  (`infer.inference_config`), recorded in onnx.json.
- `refiner.onnx` (with a second stage): inputs `features` (K, N, 9) float32 of
  `refine.box_point_features` and `sizes` (K, 3) float32; outputs `residuals` (K, 7 or 8) and
  `iou_logits` (K,).

Points to pillars, decoding, NMS and the refiner's crops stay in numpy / torch (`OnnxDetector`,
the same functions `Detector.predict` runs), so its boxes are the torch detector's up to float
rounding (tests/test_onnx.py: 1e-4 on real frames).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dali_cli.detector.config import DetectorConfig
from dali_cli.detector.model import PillarCenterNet, heads, pillarize
from dali_cli.store.regular_files import read_json_file

OPSET = 18
HEADS_NAME, REFINER_NAME, SPEC_NAME = "detector.onnx", "refiner.onnx", "onnx.json"


class FrameNetwork(nn.Module):
    """PillarCenterNet on one frame's pillarized points over a fixed `grid`, in operations ONNX
    has: the pillars' max is a scatter max onto zeros (the PFN's ReLU output is >= 0, so zeros
    change nothing), the canvas a scatter of the pillars."""

    def __init__(self, net: PillarCenterNet, grid: DetectorConfig):
        super().__init__()
        self.net, (self.rows, self.cols) = net, grid.grid_size
        self.names = sorted(heads(net.config))

    def forward(self, features, pillar_of_point, pillar_cell):
        encoder = self.net.encoder
        x = F.relu(encoder.norm(encoder.linear(features)))  # (P, C)
        channels = x.shape[1]
        pillars = torch.zeros(pillar_cell.shape[0], channels, dtype=x.dtype)
        index = pillar_of_point[:, None].expand(-1, channels)  # (P, C)
        pillars = pillars.scatter_reduce(0, index, x, reduce="amax", include_self=True)
        canvas = torch.zeros(self.rows * self.cols, channels, dtype=x.dtype)
        canvas = canvas.index_put((pillar_cell,), pillars)  # (H*W, C)
        canvas = canvas.view(1, self.rows, self.cols, channels).permute(0, 3, 1, 2)
        maps = self.net.head(self.net.backbone(canvas))
        return tuple(maps[name] for name in self.names)


def export_onnx(detector, out: Path, scale: float) -> dict:
    """Write detector.onnx (and refiner.onnx) of the torch `detector` (infer.Detector, on the
    CPU) at PTSN scale `scale` into `out`, and onnx.json; returns the spec."""
    import warnings

    from dali_cli.detector.infer import inference_config, to_network_input

    net = detector.net.cpu().eval()
    grid = inference_config(detector.config, scale)
    example = np.zeros((64, 4), np.float32)
    example[:, 0] = np.linspace(1.0, 60.0, 64)
    points, batch_index = to_network_input([example], detector.config.mount_height_m, scale)
    inputs = pillarize(points, batch_index, grid)
    module = FrameNetwork(net, grid).eval()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(
            module, inputs, str(out / HEADS_NAME), opset_version=OPSET, dynamo=False,
            input_names=["features", "pillar_of_point", "pillar_cell"],
            output_names=module.names,
            dynamic_axes={"features": {0: "points"}, "pillar_of_point": {0: "points"},
                          "pillar_cell": {0: "pillars"}},
        )  # fmt: skip
        refiner = getattr(net, "refiner", None) if detector.config.refine else None
        if refiner is not None:
            count = detector.config.refine_points
            torch.onnx.export(
                refiner, (torch.zeros(2, count, 9), torch.ones(2, 3)), str(out / REFINER_NAME),
                opset_version=OPSET, dynamo=False, input_names=["features", "sizes"],
                output_names=["residuals", "iou_logits"],
                dynamic_axes={"features": {0: "boxes"}, "sizes": {0: "boxes"},
                              "residuals": {0: "boxes"}, "iou_logits": {0: "boxes"}},
            )  # fmt: skip
    spec = {
        "opset": OPSET,
        "scale": scale,
        "grid": {
            "rows": grid.grid_size[0],
            "cols": grid.grid_size[1],
            "x_range_m": list(grid.x_range_m),
            "y_range_m": list(grid.y_range_m),
            "pillar_m": grid.pillar_m,
        },  # fmt: skip
        "outputs": module.names,
        "refiner": refiner is not None,
        "config": detector.config.to_dict(),
    }
    (out / SPEC_NAME).write_text(json.dumps(spec, indent=2) + "\n")
    return spec


class OnnxRefiner(nn.Module):
    """The refiner's graph behind BoxRefiner's call: (features, sizes) -> (residuals, logits)."""

    def __init__(self, session):
        super().__init__()
        self.session = session
        self.anchor = nn.Parameter(torch.zeros(0))  # refine_boxes reads the device from it

    def forward(self, features, sizes):
        residuals, logits = self.session.run(
            None, {"features": features.numpy(), "sizes": sizes.numpy()}
        )
        return torch.from_numpy(residuals), torch.from_numpy(logits)


class OnnxDetector:
    """`Detector.predict` with the network run by onnxruntime (an export of `export_onnx`)."""

    def __init__(self, directory: str | Path, threads: int | None = None):
        import onnxruntime

        directory = Path(directory)
        self.spec = read_json_file(directory / SPEC_NAME, "ONNX export description")
        self.config = DetectorConfig.from_dict(self.spec["config"])
        options = onnxruntime.SessionOptions()
        options.log_severity_level = 3  # errors only: not its shape notes on the scatter's output
        if threads:
            options.intra_op_num_threads = threads
        providers = ["CPUExecutionProvider"]
        self.heads = onnxruntime.InferenceSession(
            str(directory / HEADS_NAME), options, providers=providers
        )
        self.refiner = (
            OnnxRefiner(onnxruntime.InferenceSession(
                str(directory / REFINER_NAME), options, providers=providers))
            if self.spec["refiner"] else None
        )  # fmt: skip

    @torch.no_grad()
    def predict(self, points_list: list[np.ndarray], mount_height_m: float | None = None):
        """[(boxes (M, 7) float64, scores (M,) float32)] per frame, sensor frame, at the
        exported scale (see Detector.predict)."""
        from dali_cli.detector.infer import (
            decode,
            ground_boxes_to_sensor,
            inference_config,
            to_network_input,
        )

        scale = float(self.spec["scale"])
        mount = self.config.mount_height_m if mount_height_m is None else float(mount_height_m)
        grid = inference_config(self.config, scale)
        results = []
        for frame in points_list:
            points, batch_index = to_network_input([frame], mount, scale)
            features, pillar_of_point, pillar_cell = pillarize(points, batch_index, grid)
            outputs = self.heads.run(None, {"features": features.numpy(),
                                            "pillar_of_point": pillar_of_point.numpy(),
                                            "pillar_cell": pillar_cell.numpy()})  # fmt: skip
            maps = {name: torch.from_numpy(value) for name, value in
                    zip(self.spec["outputs"], outputs, strict=True)}  # fmt: skip
            ((boxes, scores),) = decode(maps, grid, self.refiner, [points.numpy()])
            results.append((ground_boxes_to_sensor(boxes, mount, scale), scores))
        return results
