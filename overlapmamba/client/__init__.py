"""Python clients of the OverlapMamba place-recognition service (httpx).

``PlaceRecognitionClient`` (blocking) and ``AsyncPlaceRecognitionClient`` (asyncio) have
the same methods; ``overlapmamba-client`` is the command line (``overlapmamba.client.cli``), with
the fleet simulator (``overlapmamba.client.fleet``). No torch, onnxruntime or faiss here.
"""

from overlapmamba.client._async import AsyncPlaceRecognitionClient
from overlapmamba.client._base import Timeouts
from overlapmamba.client._exceptions import (
    APIError,
    AuthError,
    BadRequestError,
    ClientError,
    ConflictError,
    ConnectError,
    NotFoundError,
    OverloadedError,
    PayloadTooLargeError,
    ResponseError,
    ServerError,
    Timeout,
    TransportError,
)
from overlapmamba.client._models import (
    BatchInsertResult,
    Descriptor,
    Keyframe,
    LoopClosure,
    MapInfo,
    Match,
    Observation,
    ObserveResult,
    QueryResult,
)
from overlapmamba.client._retry import NO_RETRY, Retry
from overlapmamba.client._sync import PlaceRecognitionClient

__all__ = [
    "NO_RETRY",
    "APIError",
    "AsyncPlaceRecognitionClient",
    "AuthError",
    "BadRequestError",
    "BatchInsertResult",
    "ClientError",
    "ConflictError",
    "ConnectError",
    "Descriptor",
    "Keyframe",
    "LoopClosure",
    "MapInfo",
    "Match",
    "NotFoundError",
    "Observation",
    "ObserveResult",
    "OverloadedError",
    "PayloadTooLargeError",
    "PlaceRecognitionClient",
    "QueryResult",
    "ResponseError",
    "Retry",
    "ServerError",
    "Timeout",
    "Timeouts",
    "TransportError",
]
