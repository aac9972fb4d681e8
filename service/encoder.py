"""The exported encoder, as onnxruntime runs it: range images in, descriptors out.

    images       (B, 1, H, W) float32, the model's own projection (from its metadata)
    descriptor   (B, D) float32, unit norm
    yaw_features (B, C, W) float32, rolled by the sensor's yaw

Nothing about the projection is configured here: :class:`EncoderMetadata` in the file says
which sensor profile the network was trained on, and :meth:`Encoder.project` uses exactly it.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from lidar_core.modelmeta import INPUT, OUTPUTS, EncoderMetadata
from lidar_core.points import PointCloud
from lidar_core.projection import project

log = logging.getLogger("overlapmamba.service")


class ModelLoadError(RuntimeError):
    """The model file is missing, unreadable, or not an OverlapMamba encoder."""


@dataclass(frozen=True)
class Encoded:
    descriptor: np.ndarray  # (D,) float32
    yaw_features: np.ndarray  # (C, W) float32


class Encoder:
    def __init__(self, path: Path, *, intra_op_threads: int = 0) -> None:
        if not Path(path).is_file():
            raise ModelLoadError(f"model file {path} does not exist")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = intra_op_threads or (os.cpu_count() or 1)
        opts.inter_op_num_threads = 1
        t0 = time.perf_counter()
        try:
            self.session = ort.InferenceSession(
                str(path), sess_options=opts, providers=["CPUExecutionProvider"]
            )
        except Exception as err:  # onnxruntime raises its own unrelated classes
            raise ModelLoadError(f"onnxruntime cannot load {path}: {err}") from None
        try:
            self.meta = EncoderMetadata.from_props(self.session.get_modelmeta().custom_metadata_map)
        except ValueError as err:
            raise ModelLoadError(f"{path}: {err}") from None
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if inputs != [INPUT] or tuple(outputs) != OUTPUTS:
            raise ModelLoadError(
                f"{path} has inputs {inputs} and outputs {outputs}; expected [{INPUT}] and "
                f"{list(OUTPUTS)}"
            )
        self.path = Path(path)
        self.load_s = time.perf_counter() - t0
        if self.meta.weights != "trained":
            log.warning(
                "model %s has %s weights: its descriptors are not trained for place recognition",
                self.meta.model_id,
                self.meta.weights,
            )

    @property
    def model_id(self) -> str:
        return self.meta.model_id

    @property
    def dim(self) -> int:
        return self.meta.descriptor_dim

    def project(self, points: PointCloud) -> np.ndarray:
        """(1, H, W) float32 range image in the model's sensor profile."""
        return project(points, self.meta.profile)[None]

    def encode(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """images (B, 1, H, W) → descriptor (B, D), yaw_features (B, C, W)."""
        desc, yaw = self.session.run(
            list(OUTPUTS), {INPUT: np.ascontiguousarray(images, dtype=np.float32)}
        )
        return desc, yaw
