"""Randomness of repeated executions of a toss and of their measurement
(:class:`TossNoise`), for synthetic recordings (:mod:`studio.toss.synthetic`). SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from studio.errors import InvalidInputError


@dataclass(frozen=True, slots=True)
class TossNoise:
    """Randomness of repeated executions of one toss and of their measurement.

    Defaults: chosen so that 15-20 tosses spread by about +/-1 cm 0.7 s after the lift,
    as the paper reports (its Fig. "toss spread"), with a +/-3 mm tracking accuracy.
    """

    vibration: float = 0.008
    """Std. dev. of the random release-velocity perturbation per axis [m/s] (arm
    vibration; isotropic)."""
    release_jitter: float = 0.001
    """Std. dev. of the release time around the contact-force crossing [s]."""
    wind: float = 0.07
    """Std. dev. of the horizontal air velocity per axis [m/s] (small room air flows;
    constant during a toss; enters the drag as the relative air velocity)."""
    wind_vertical: float = 0.02
    """Std. dev. of the vertical air velocity [m/s]."""
    measurement: float = 0.0015
    """Std. dev. of the tracking error per axis [m]: the paper's +/-3 mm read as 2 sigma."""
    camera_rate: float = 200.0
    """Camera frame rate [Hz]; each recording has a random frame phase."""
    visible_before_release: tuple[float, float] = (0.25, 0.35)
    """Range [s] (uniform) of how long before the release the recording starts: the
    ball riding in the cup is recorded too."""
    clock_offset: tuple[float, float] = (10.0, 1000.0)
    """Range [s] (uniform) of the recording clock's offset from the command clock."""
    t_max: float = 1.5
    """Latest end of a recording on the command clock [s]."""
    end_height: float = -0.30
    """A recording stops when the ball falls below this height [m]. Below the table
    level (the ball is behind the end line, nothing is in the way) so that the
    recordings cover 0.7 s after the lift like the paper's spread figure; a serve must
    strike the ball above the table level (ITTF 2.6.4)."""

    def __post_init__(self) -> None:
        for name in ("vibration", "release_jitter", "wind", "wind_vertical", "measurement"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise InvalidInputError(f"TossNoise.{name} must be finite and >= 0, got {v}")
        if not math.isfinite(self.end_height):
            raise InvalidInputError(f"TossNoise.end_height must be finite, got {self.end_height}")
        for name in ("camera_rate", "t_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise InvalidInputError(f"TossNoise.{name} must be finite and > 0, got {v}")
        for name in ("visible_before_release", "clock_offset"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise InvalidInputError(f"TossNoise.{name} must be a finite range (lo <= hi), got {(lo, hi)}")
        if self.visible_before_release[0] < 0.0:
            raise InvalidInputError("TossNoise.visible_before_release must be >= 0")

    @classmethod
    def none(cls) -> TossNoise:
        """No randomness except the camera sampling (noise-free reference)."""
        return cls(
            vibration=0.0, release_jitter=0.0, wind=0.0, wind_vertical=0.0, measurement=0.0, clock_offset=(0.0, 0.0)
        )


DEFAULT_NOISE: Final[TossNoise] = TossNoise()
"""The default randomness (that of the shipped recordings)."""
