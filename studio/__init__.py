"""Serve Studio: design, plan, simulate and optimize table-tennis serves for a robot arm.

Implements the serve-generation system of "Ace! Motion Planning of Professional-Level
Table Tennis Serves with a Robot Arm". One module per concept; see the README for a
tour. Units are SI, frames as in ``DESIGN.md`` (origin at the table centre, +X to the
receiver, +Z up).
"""

__version__ = "0.1.0"
