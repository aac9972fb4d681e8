"""The container's HEALTHCHECK: exit 0 when the service on this host answers /readyz with 200.

Stdlib only (it runs every few seconds); the port comes from OVERLAPMAMBA_PORT, like the
service's own.
"""

from __future__ import annotations

import os
import sys
import urllib.request

port = os.environ.get("OVERLAPMAMBA_PORT", "8000")
try:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=3) as r:
        sys.exit(0 if r.status == 200 else 1)
except Exception as err:  # refused, 503 while loading or draining, timeout
    print(f"not ready: {err}", file=sys.stderr)
    sys.exit(1)
