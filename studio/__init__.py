"""Serve Studio: design, plan, simulate and optimize table-tennis serves for a robot arm.

Implements the serve-generation system of "Ace! Motion Planning of Professional-Level
Table Tennis Serves with a Robot Arm". Units are SI; frames and clocks as in
``docs/frames-and-units.md`` (origin at the table centre, +X to the receiver, +Z up).

The public API is the names below (``studio.evaluate_serve``, ``studio.ServeLibrary``,
...). They load on first use, so ``import studio`` stays cheap; the subpackages hold
the rest, one layer each:

- :mod:`studio.physics` ball flight, table, net and racket impacts, and their fits;
- :mod:`studio.robot` the 8-DoF robot: description, kinematics, dynamics, collisions;
- :mod:`studio.toss` the ball toss and its recordings;
- :mod:`studio.planning` the minimum-jerk strike planner;
- :mod:`studio.sim` MuJoCo rollouts;
- :mod:`studio.serve` serve files, the evaluation chain, ITTF rules, reward, efforts;
- :mod:`studio.library` the serve library, serve selection, match statistics;
- :mod:`studio.optimize` HEBO optimization, robustification, training;
- :mod:`studio.ui` the viser studio and the Panel dashboard;
- :mod:`studio.storage` locked and append-only files; :mod:`studio.cli` the command line.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_API: dict[str, str] = {
    # used by the examples and notebooks beside the names above
    "DEFAULT_COURT": "studio.physics.court",
    "DEFAULT_FLIGHT": "studio.physics.ball",
    "CollisionChecker": "studio.robot.collision",
    "Plan": "studio.planning.strike",
    "start_from_toss": "studio.planning.serve_plan",
    "SWITCH_DELAY": "studio.serve.evaluate",
    "strike_target": "studio.serve.evaluate",
    "report_markdown": "studio.serve.evaluate",
    "OptimizationResult": "studio.optimize.optimizer",
    "RobustScore": "studio.optimize.robust",
    # errors
    "StudioError": "studio.errors",
    "InvalidInputError": "studio.errors",
    "DataFileError": "studio.errors",
    "EffortLimitError": "studio.serve.efforts",
    # ball physics
    "BallState": "studio.physics.ball",
    "FlightModel": "studio.physics.ball",
    "RacketModel": "studio.physics.ball",
    "TableBounceModel": "studio.physics.ball",
    "simulate": "studio.physics.ball",
    "spin_components": "studio.physics.ball",
    # robot
    "Robot": "studio.robot.model",
    "load_robot": "studio.robot.model",
    # toss
    "TossModel": "studio.toss.model",
    "load_default_toss_model": "studio.toss.defaults",
    # planning and simulation
    "StrikePlanner": "studio.planning.planner",
    "StrikeTarget": "studio.planning.strike",
    "plan_serve": "studio.planning.serve_plan",
    "rollout": "studio.sim.rollout",
    # serves and their evaluation
    "HandServe": "studio.serve.params",
    "ServeParams": "studio.serve.params",
    "LimitScale": "studio.serve.params",
    "load_serve": "studio.serve.params",
    "save_serve": "studio.serve.params",
    "EvaluationContext": "studio.serve.evaluate",
    "Evaluation": "studio.serve.evaluate",
    "evaluate_serve": "studio.serve.evaluate",
    "evaluate_robust": "studio.serve.evaluate",
    "effort_report": "studio.serve.efforts",
    # optimization
    "OptimizeOptions": "studio.optimize.optimizer",
    "optimize_serve": "studio.optimize.optimizer",
    "RobustifyOptions": "studio.optimize.robust",
    "robustify_serve": "studio.optimize.robust",
    "TrainConfig": "studio.optimize.training",
    "train_serves": "studio.optimize.training",
    # library and matches
    "ServeLibrary": "studio.library.store",
    "select_next": "studio.library.selection",
    "match_stats": "studio.library.match",
}

__all__ = [
    "BallState",
    "CollisionChecker",
    "DEFAULT_COURT",
    "DEFAULT_FLIGHT",
    "DataFileError",
    "EffortLimitError",
    "Evaluation",
    "EvaluationContext",
    "FlightModel",
    "HandServe",
    "InvalidInputError",
    "LimitScale",
    "OptimizationResult",
    "OptimizeOptions",
    "Plan",
    "RacketModel",
    "Robot",
    "RobustScore",
    "RobustifyOptions",
    "SWITCH_DELAY",
    "ServeLibrary",
    "ServeParams",
    "StrikePlanner",
    "StrikeTarget",
    "StudioError",
    "TableBounceModel",
    "TossModel",
    "TrainConfig",
    "effort_report",
    "evaluate_robust",
    "evaluate_serve",
    "load_default_toss_model",
    "load_robot",
    "load_serve",
    "match_stats",
    "optimize_serve",
    "plan_serve",
    "report_markdown",
    "robustify_serve",
    "rollout",
    "save_serve",
    "select_next",
    "simulate",
    "spin_components",
    "start_from_toss",
    "strike_target",
    "train_serves",
]

if TYPE_CHECKING:
    from studio.errors import DataFileError, InvalidInputError, StudioError
    from studio.library.match import match_stats
    from studio.library.selection import select_next
    from studio.library.store import ServeLibrary
    from studio.optimize.optimizer import OptimizationResult, OptimizeOptions, optimize_serve
    from studio.optimize.robust import RobustifyOptions, RobustScore, robustify_serve
    from studio.optimize.training import TrainConfig, train_serves
    from studio.physics.ball import (
        DEFAULT_FLIGHT,
        BallState,
        FlightModel,
        RacketModel,
        TableBounceModel,
        simulate,
        spin_components,
    )
    from studio.physics.court import DEFAULT_COURT
    from studio.planning.planner import StrikePlanner
    from studio.planning.serve_plan import plan_serve, start_from_toss
    from studio.planning.strike import Plan, StrikeTarget
    from studio.robot.collision import CollisionChecker
    from studio.robot.model import Robot, load_robot
    from studio.serve.efforts import EffortLimitError, effort_report
    from studio.serve.evaluate import (
        SWITCH_DELAY,
        Evaluation,
        EvaluationContext,
        evaluate_robust,
        evaluate_serve,
        report_markdown,
        strike_target,
    )
    from studio.serve.params import HandServe, LimitScale, ServeParams, load_serve, save_serve
    from studio.sim.rollout import rollout
    from studio.toss.defaults import load_default_toss_model
    from studio.toss.model import TossModel


def __getattr__(name: str) -> Any:
    """Load a public name from its module on first use (PEP 562)."""
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'studio' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
