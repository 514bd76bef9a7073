"""Error policy of streaming readers (:class:`appliance.errors.ErrorPolicy`) applied and counted.

Daemons log and count (``LOG``), tests raise (``RAISE``), batch tools may only count (``SKIP``).
Whatever the policy, a bad record never becomes a value: it is dropped and counted.
"""

from __future__ import annotations

import logging
from collections import Counter

from appliance.errors import ErrorPolicy, ViperError

__all__ = ["ErrorCounter", "ErrorPolicy"]


class ErrorCounter:
    """Counts rejected records by reason and applies an :class:`ErrorPolicy` to each."""

    def __init__(self, policy: ErrorPolicy, logger: logging.Logger) -> None:
        self.policy = policy
        self.logger = logger
        self.counts: Counter[str] = Counter()

    def reject(self, reason: str, exc: ViperError) -> None:
        """Count one rejected record under ``reason``; raise, log a warning or stay silent."""
        self.counts[reason] += 1
        if self.policy is ErrorPolicy.RAISE:
            raise exc
        if self.policy is ErrorPolicy.LOG:
            self.logger.warning("%s: %s", reason, exc)

    def count(self, reason: str, n: int = 1) -> None:
        """Count ``n`` events that are not errors in themselves (e.g. skipped garbage bytes)."""
        self.counts[reason] += n
