"""Token-bucket rate limiting of input topics (flooding protection), without numpy or scipy:
cheap to import in every node process."""
from typing import Optional

__all__ = ['RateLimiter']


class RateLimiter:
    """Token bucket: at most ``rate`` events per second on average, bursts of ``burst``."""

    def __init__(self, rate: float, burst: Optional[float] = None):
        self.rate = float(rate)
        self.burst = float(burst if burst is not None else max(10.0, 0.1 * rate))
        self.tokens = self.burst
        self.last: Optional[float] = None
        self.dropped = 0

    def allow(self, now: float) -> bool:
        if self.last is not None:
            self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        self.dropped += 1
        return False
