"""Names given up because they meant more than one thing, and the names that replaced them.

``max_distance`` named three thresholds (the unverified loop-closure call, the verification
gate, a query filter), ``k`` four counts and ``exclude_recent`` was frames here and seconds
in the service. Each now has its own name. The old ones are still accepted, with a
:class:`DeprecatedName` warning, until :data:`REMOVED_IN`; giving both an old name and its
new one is refused.

    where          old name        new name               what it is
    loop_closure   max_distance    accept_distance        unverified call: top-1 L2 below this
    verify         max_distance    gate_distance          candidates above it are not registered
    verify         k               candidates             candidates registered per scan query
    rerank         k               shortlist              nearest descriptors re-ranked
    query          max_distance    max_match_distance     matches farther than this are left out
    loops          exclude_recent  exclude_recent_frames  a loop's query is this many frames later

``k`` stays the number of matches a query returns. Files keep their keys: a loop table's
``params`` still say ``exclude_recent`` (frames), and calibrations written before the rename
are read with the new names.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

REMOVED_IN = "0.3.0"

RENAMED: dict[str, dict[str, str]] = {
    "loop_closure": {"max_distance": "accept_distance"},
    "verify": {"max_distance": "gate_distance", "k": "candidates"},
    "rerank": {"k": "shortlist"},
    "query": {"max_distance": "max_match_distance"},
    "loops": {"exclude_recent": "exclude_recent_frames"},
}


class DeprecatedName(FutureWarning):
    """An old name was used (shown by default: the people who write settings see it)."""


def renamed(values: Mapping[str, Any], where: str, *, stacklevel: int = 3) -> dict[str, Any]:
    """``values`` with ``where``'s old names replaced by the new ones (a warning each); a
    ValueError when both an old name and its new one are given."""
    out = dict(values)
    for old, new in RENAMED[where].items():
        if old not in out:
            continue
        if new in out:
            raise ValueError(
                f"{where}: give {new} only; {old} is its old name (deprecated), not a second "
                "setting"
            )
        warnings.warn(
            f"{where}.{old} is deprecated and goes in {REMOVED_IN}: it is now {where}.{new}",
            DeprecatedName,
            stacklevel=stacklevel,
        )
        out[new] = out.pop(old)
    return out
