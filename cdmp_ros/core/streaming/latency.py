"""Latency samples kept in a ring, summarised as diagnostics key/values (no ROS)."""
from typing import Dict, Sequence

import numpy as np

from cdmp_ros.core.errors import ValidationError


class LatencyRing:
    """The last ``size`` latencies [ms] and their percentiles.

    Parameters
    ----------
    prefix : str
        Key prefix of :meth:`values` (``<prefix>_n``, ``<prefix>_ms_last``, ...).
    size : int
        Samples kept for the percentiles.
    percentiles : sequence of float
        Reported as ``<prefix>_ms_p<q>`` (besides ``_ms_last`` and ``_ms_max``).
    """

    def __init__(self, prefix: str, size: int = 1024, percentiles: Sequence[float] = (50, 95)):
        if size < 1:
            raise ValidationError(f'size: expected >= 1, got {size}')
        self.prefix = prefix
        self.percentiles = tuple(percentiles)
        self._ms = np.zeros(size)
        self.n = 0
        self.last = float('nan')

    def add(self, ms: float) -> None:
        """Record one latency [ms] (a ring write, no allocation)."""
        self._ms[self.n % self._ms.size] = ms
        self.n += 1
        self.last = ms

    def values(self) -> Dict[str, object]:
        """``<prefix>_n`` and, once there is a sample, ``_ms_last``, ``_ms_p<q>`` for each
        percentile and ``_ms_max`` over the kept samples."""
        p = self.prefix
        if self.n == 0:
            return {f'{p}_n': 0}
        lat = self._ms[:min(self.n, self._ms.size)]
        *qs, top = np.percentile(lat, [*self.percentiles, 100.0])
        out = {f'{p}_n': self.n, f'{p}_ms_last': f'{self.last:.3f}'}
        out.update({f'{p}_ms_p{q:g}': f'{v:.3f}' for q, v in zip(self.percentiles, qs)})
        out[f'{p}_ms_max'] = f'{top:.3f}'
        return out
