"""Python clients of the OverlapMamba place-recognition service (httpx).

``PlaceRecognitionClient`` (blocking) and ``AsyncPlaceRecognitionClient`` (asyncio) have
the same methods; ``overlapmamba-client`` is the command line (``client.cli``), with the
fleet simulator (``client.fleet``). No torch, onnxruntime or faiss here.
"""

from client._async import AsyncPlaceRecognitionClient
from client._base import NO_RETRY, Retry, Timeouts
from client._exceptions import (
    APIError,
    AuthError,
    BadRequestError,
    ClientError,
    ConflictError,
    ConnectError,
    NotFoundError,
    OverloadedError,
    PayloadTooLargeError,
    ServerError,
    Timeout,
    TransportError,
)
from client._models import (
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
from client._sync import PlaceRecognitionClient

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
    "Retry",
    "ServerError",
    "Timeout",
    "Timeouts",
    "TransportError",
]
