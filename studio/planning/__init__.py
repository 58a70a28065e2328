"""The minimum-jerk strike planner (racket position, normal and velocity at tau, back to rest, within limits)."""
