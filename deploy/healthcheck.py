"""The container's HEALTHCHECK: exit 0 when the service on this host answers /readyz with 200.

Stdlib only (it runs every few seconds); the port and address come from OVERLAPMAMBA_PORT
and OVERLAPMAMBA_HOST, like the service's own (a --port given to ``serve`` on the command
line instead is not seen: set the variable). It probes readiness, so a replica replaying a
long map, or without its Qdrant, reads unhealthy meanwhile: an orchestrator that restarts
unhealthy containers should probe /healthz for liveness instead (docs/deploy.md).
"""

from __future__ import annotations

import os
import sys
import urllib.request

port = os.environ.get("OVERLAPMAMBA_PORT", "8000")
# the address it listens on; every address (the image's 0.0.0.0) answers on loopback
host = os.environ.get("OVERLAPMAMBA_HOST", "").strip() or "127.0.0.1"
if host in ("0.0.0.0", "::", "[::]"):
    host = "127.0.0.1"
elif ":" in host and not host.startswith("["):  # an IPv6 address, in a URL
    host = f"[{host}]"
direct = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # never an HTTP_PROXY's
try:
    with direct.open(f"http://{host}:{port}/readyz", timeout=3) as r:
        sys.exit(0 if r.status == 200 else 1)
except Exception as err:  # refused, 503 while loading or draining, timeout
    print(f"not ready: {err}", file=sys.stderr)
    sys.exit(1)
