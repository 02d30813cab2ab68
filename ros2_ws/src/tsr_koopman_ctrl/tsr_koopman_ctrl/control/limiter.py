"""The single output clamp between any law and the tether."""

import math


class TensionLimiter:
    """Clamp u into [0, u_max] (a tether cannot push) and count how often it had to."""

    def __init__(self, u_max):
        if not (math.isfinite(u_max) and u_max > 0.0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max}')
        self.u_max = u_max
        self.clamped = 0

    def __call__(self, u):
        if not math.isfinite(u):
            raise ValueError(f'controller produced a non-finite tension {u}')
        u = float(u)
        limited = min(max(u, 0.0), self.u_max)
        self.clamped += int(limited != u)
        return limited
