"""Logs as one JSON object per line, each stamped with the id of the request it belongs to.

    {"ts": "2026-11-23T05:40:01.123Z", "level": "info", "logger": "overlapmamba.access",
     "msg": "POST /v1/maps/town/observe 200", "request_id": "7f3c…", "method": "POST",
     "path": "/v1/maps/town/observe", "status": 200, "duration_ms": 93.1, "client": "10.0.0.7"}

The request id is the caller's ``X-Request-ID`` when it is a sane token, else a new one; it
is echoed in the response header, so a robot's log line and the service's meet. It lives in
a context variable, which follows the request into worker threads. Anything passed as
``extra={...}`` becomes a field of the line.
"""

from __future__ import annotations

import json
import logging
import re
import sys
import time
import uuid
from contextvars import ContextVar
from typing import Any

request_id: ContextVar[str | None] = ContextVar("request_id", default=None)

_TOKEN = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")
_STANDARD = set(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {
    "message",
    "asctime",
    "color_message",  # uvicorn's ANSI twin of msg
}


def new_request_id(given: str | None = None) -> str:
    """The caller's id if it is a plain token (no log injection), else a fresh one."""
    if given and _TOKEN.fullmatch(given):
        return given
    return uuid.uuid4().hex


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        rid = request_id.get()
        if rid is not None:
            line["request_id"] = rid
        for key, value in record.__dict__.items():
            if key not in _STANDARD and not key.startswith("_"):
                line[key] = value
        if record.exc_info:
            line["exc"] = self.formatException(record.exc_info)
        return json.dumps(line, default=str, ensure_ascii=False)


class TextFormatter(logging.Formatter):
    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        rid = request_id.get()
        return f"{text} [request {rid}]" if rid else text


def configure(level: str = "info", fmt: str = "json") -> None:
    """Route every logger — ours and uvicorn's, and Python's warnings — through one stderr
    handler (a library's warning, such as Qdrant's client on a key sent over http, was a
    raw line among the JSON ones, which a log shipper could not parse)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level.upper())
    logging.captureWarnings(True)  # as records of the logger "py.warnings"
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        lg = logging.getLogger(name)
        lg.handlers.clear()
        lg.propagate = True
    # The middleware writes one access line per request (with its id and duration).
    logging.getLogger("uvicorn.access").disabled = True
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)  # which SIMD build it found
