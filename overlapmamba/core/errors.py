"""One exception tree for the shared LiDAR core.

    LidarCoreError
     ├── PointCloudError        a scan that cannot be used            (ValueError)
     │    ├── DecodeError        bytes/files that do not decode to points
     │    │    └── DataTooLargeError  whose header declares more data than allowed
     │    ├── NonFiniteError     NaN or ±Inf in coordinates or intensity
     │    └── PointCountError    too few or too many points
     ├── ProfileError           an unknown or invalid sensor profile   (ValueError)
     ├── DatasetError           a sequence folder that cannot be read  (ValueError)
     └── ConfigError            a configuration (dataclass) with fields not allowed (ValueError)

Every error carries a stable machine-readable ``code`` and a ``detail`` dict that says what
was wrong and what is allowed, so the HTTP service can map it to a 4xx without parsing text.
"""

from __future__ import annotations

from typing import Any


class LidarCoreError(Exception):
    """Base class: ``code`` is stable, ``str(err)`` is for people, ``detail`` for programs."""

    code = "lidar_core_error"

    def __init__(self, message: str, **detail: Any) -> None:
        super().__init__(message)
        self.message = message
        self.detail: dict[str, Any] = detail


class PointCloudError(LidarCoreError, ValueError):
    code = "invalid_point_cloud"


class DecodeError(PointCloudError):
    code = "undecodable_point_cloud"


class DataTooLargeError(DecodeError):
    """A header (a compressed PCD's uncompressed size) that declares more bytes than a
    decoder may build: refused before any of it is allocated."""

    code = "decoded_too_large"


class NonFiniteError(PointCloudError):
    code = "non_finite_points"


class PointCountError(PointCloudError):
    code = "point_count_out_of_range"


class ProfileError(LidarCoreError, ValueError):
    code = "invalid_sensor_profile"


class DatasetError(LidarCoreError, ValueError):
    code = "invalid_dataset"


class ConfigError(LidarCoreError, ValueError):
    code = "invalid_config"
