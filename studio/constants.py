"""Physical constants of the serve studio, in SI units, each with its source.

Frames follow ``DESIGN.md``: the world origin is the centre of the table's playing
surface, +X points towards the receiver, +Z up. The robot serves from the -X end.

Everything numeric that is a property of the world (not a tuning knob of a model)
lives here, so that physics, MuJoCo, the collision checker and the 3D scene share it.
Calibrated model parameters (drag, lift, bounce) live with their models in
:mod:`studio.physics.ball`, with their own sources.
"""

from __future__ import annotations

import math
from typing import Final

# --- Environment -------------------------------------------------------------------

GRAVITY: Final[float] = 9.81
"""Gravitational acceleration [m/s^2], standard value rounded (ISO 80000-3: 9.80665)."""

AIR_DENSITY: Final[float] = 1.20
"""Air density [kg/m^3] at 20 degC, 1013 hPa (ISA sea-level value 1.225 at 15 degC)."""

AIR_KINEMATIC_VISCOSITY: Final[float] = 1.5e-5
"""Kinematic viscosity of air [m^2/s] at 20 degC (for Reynolds numbers only)."""

# --- Ball (ITTF Law 2.3) -----------------------------------------------------------

BALL_RADIUS: Final[float] = 0.020
"""Ball radius [m]: ITTF Law 2.3.1, a 40 mm diameter sphere."""

BALL_MASS: Final[float] = 0.0027
"""Ball mass [kg]: ITTF Law 2.3.2, 2.7 g."""

BALL_INERTIA: Final[float] = 2.0 / 3.0 * BALL_MASS * BALL_RADIUS**2
"""Ball moment of inertia [kg m^2]: thin spherical shell, (2/3) m r^2."""

BALL_AREA: Final[float] = math.pi * BALL_RADIUS**2
"""Ball cross-section [m^2]."""

# --- Table, net and posts (ITTF Laws 2.1, 2.2) -------------------------------------

TABLE_LENGTH: Final[float] = 2.74
"""Playing surface length along X [m]: ITTF Law 2.1.1."""

TABLE_WIDTH: Final[float] = 1.525
"""Playing surface width along Y [m]: ITTF Law 2.1.1."""

TABLE_HEIGHT: Final[float] = 0.76
"""Height of the playing surface above the floor [m]: ITTF Law 2.1.1. The floor is
therefore at z = -0.76 in the world frame."""

TABLE_THICKNESS: Final[float] = 0.025
"""Table top thickness [m] (typical competition top: 25 mm; not fixed by the laws)."""

EDGE_LINE_WIDTH: Final[float] = 0.020
"""Width of the white edge lines [m]: ITTF Law 2.1.4 (2 cm)."""

CENTRE_LINE_WIDTH: Final[float] = 0.003
"""Width of the white centre line for doubles [m]: ITTF Law 2.1.5 (3 mm)."""

NET_HEIGHT: Final[float] = 0.1525
"""Height of the top of the net above the playing surface [m]: ITTF Law 2.2.3."""

NET_POST_OFFSET: Final[float] = 0.1525
"""Distance of the outside of the net posts from the side lines [m]: ITTF Law 2.2.2."""

NET_THICKNESS: Final[float] = 0.004
"""Thickness of the net along X used for contact geometry [m] (mesh netting ~ a few mm)."""

NET_POST_SIZE: Final[float] = 0.03
"""Side of the square cross-section of a net post [m] (typical clamp posts, not in the laws)."""

TOSS_MIN_RISE: Final[float] = 0.16
"""Minimal rise of the tossed ball after leaving the hand/cup [m]: ITTF Law 2.6.2."""

DROP_TEST_HEIGHT: Final[float] = 0.30
"""Drop height of the table bounce test [m]: ITTF Law 2.1.3."""

DROP_TEST_REBOUND: Final[float] = 0.23
"""Expected rebound height of the drop test [m]: ITTF Law 2.1.3 ("about 23 cm")."""

FLOOR_Z: Final[float] = -TABLE_HEIGHT
"""World z of the floor [m]."""

# --- Racket (frame "racket") ------------------------------------------------------
# Racket frame: origin at the centre of the blade on its mid-plane; z = normal of face A
# (the forehand face); y along the handle axis pointing from the handle to the blade tip;
# x = y cross z. Both faces carry rubber. The ball cup sits on the handle, on face A's side.

RACKET_BLADE_WIDTH: Final[float] = 0.150
"""Blade width along the racket x axis [m] (ITTF: size free; typical blades 150 mm)."""

RACKET_BLADE_LENGTH: Final[float] = 0.158
"""Blade length along the racket y axis [m] (typical blades 157-158 mm)."""

RACKET_HALF_THICKNESS: Final[float] = 0.007
"""Half the racket thickness at the blade, rubbers included [m]: blade ~5.8 mm plus two
rubbers of 2.1 mm sponge + ~1.9 mm top sheet each, ~14 mm in all."""

RACKET_HANDLE_LENGTH: Final[float] = 0.100
"""Handle length beyond the blade [m] (typical flared handles: 100 mm)."""
