"""Latency samples kept in a ring, summarised as diagnostics key/values (no ROS)."""
from typing import Dict

import numpy as np


class LatencyRing:
    """The last ``size`` latencies [ms] and their percentiles.

    Parameters
    ----------
    prefix : str
        Key prefix of :meth:`values` (``<prefix>_n``, ``<prefix>_ms_last``, ...).
    size : int
        Samples kept for the percentiles.
    """

    def __init__(self, prefix: str, size: int = 1024):
        if size < 1:
            raise ValueError(f'size: expected >= 1, got {size}')
        self.prefix = prefix
        self._ms = np.zeros(size)
        self.n = 0
        self.last = float('nan')

    def add(self, ms: float) -> None:
        """Record one latency [ms] (a ring write, no allocation)."""
        self._ms[self.n % self._ms.size] = ms
        self.n += 1
        self.last = ms

    def values(self) -> Dict[str, object]:
        """``<prefix>_n`` and, once there is a sample, ``_ms_last``, ``_ms_p50``, ``_ms_p95``
        and ``_ms_max`` over the kept samples."""
        p = self.prefix
        if self.n == 0:
            return {f'{p}_n': 0}
        lat = self._ms[:min(self.n, self._ms.size)]
        p50, p95, top = np.percentile(lat, [50.0, 95.0, 100.0])
        return {f'{p}_n': self.n, f'{p}_ms_last': f'{self.last:.3f}',
                f'{p}_ms_p50': f'{p50:.3f}', f'{p}_ms_p95': f'{p95:.3f}',
                f'{p}_ms_max': f'{top:.3f}'}
