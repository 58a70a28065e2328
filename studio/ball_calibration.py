"""Calibration of the ball models: racket impact fit with cross-validation, table drop test.

Racket: :func:`fit_racket_model` fits :class:`studio.ball.RacketModel` on measured
racket-ball bounces (``studio/data/racket_bounces/``, T. Gossard's public dataset, MIT
licence) by nonlinear least squares on the outgoing velocity and spin, each residual
divided by a scale (:data:`VELOCITY_SCALE`, :data:`SPIN_SCALE`) so both count alike.
:func:`cross_validate` reports k-fold errors on rows not used for the fit, for the
model and for the reference elastic-rubber model of the dataset's README (tangential
compliance ``k_p`` + restitution linear in the normal speed).

Table: :func:`tune_table_restitution` finds the restitution that makes the ITTF Law
2.1.3 drop test (30 cm drop, air drag included) bounce to 23 cm.

Entry point: ``python -m studio.ball_calibration [--folds K] [--write]`` prints the
cross-validation table (``--write`` also refreshes ``racket_models.json``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq, least_squares

from studio import constants as C
from studio.ball import (
    RACKET_DATA_DIR,
    RACKET_MODELS_JSON,
    BallState,
    FlightModel,
    RacketModel,
    TableBounceModel,
    simulate,
)
from studio.errors import DataFileError, InvalidInputError

FloatArray = npt.NDArray[np.float64]

VECTOR_COLUMNS = ("spin_before", "spin_after", "v_in", "v_out")
"""Vector column prefixes of the bounce CSV (suffixes _x, _y, _z)."""

REQUIRED_COLUMNS = ("racket_angle", "traj_dir") + tuple(
    f"{prefix}_{axis}" for prefix in VECTOR_COLUMNS for axis in "xyz"
)
"""Columns a bounce CSV must have (extra columns are ignored)."""

VELOCITY_SCALE = 0.5
"""Normalization of velocity residuals in the fit [m/s] (about the attainable RMS)."""

SPIN_SCALE = 40.0
"""Normalization of spin residuals in the fit [rad/s] (about the reference model's RMS)."""

RACKETS = ("racket_01", "racket_03")
"""Rackets of the shipped dataset."""


# =====================================================================================
# Data
# =====================================================================================


@dataclass(frozen=True, slots=True)
class BounceRows:
    """Measured racket bounces, racket frame (z = face normal, racket at rest)."""

    v_in: FloatArray
    """Ball velocity before impact (N, 3) [m/s]."""
    w_in: FloatArray
    """Ball spin before impact (N, 3) [rad/s]."""
    v_out: FloatArray
    """Ball velocity after impact (N, 3) [m/s]."""
    w_out: FloatArray
    """Ball spin after impact (N, 3) [rad/s]."""
    racket_angle: FloatArray
    """Tilt of the recording set-up (N,) [deg] (bookkeeping; not a model input)."""
    traj_dir: tuple[str, ...]
    """Launcher setting id of each row."""
    source: str = ""
    """File the rows come from."""

    def __len__(self) -> int:
        return int(self.v_in.shape[0])

    def subset(self, index: npt.ArrayLike) -> BounceRows:
        """Rows at ``index`` (integer array or boolean mask)."""
        idx = np.asarray(index)
        if idx.dtype == bool:
            idx = np.nonzero(idx)[0]
        return BounceRows(
            v_in=self.v_in[idx],
            w_in=self.w_in[idx],
            v_out=self.v_out[idx],
            w_out=self.w_out[idx],
            racket_angle=self.racket_angle[idx],
            traj_dir=tuple(self.traj_dir[i] for i in idx.tolist()),
            source=self.source,
        )


def load_bounce_csv(path: str | os.PathLike[str]) -> BounceRows:
    """Read a racket-bounce CSV (columns :data:`REQUIRED_COLUMNS`, SI units).

    Raises:
        DataFileError: unreadable file, missing column, a non-numeric or non-finite
            value (the message names the file, line and column), no rows, or a ball not
            approaching the face (``v_in_z >= 0``) / not leaving it (``v_out_z <= 0``).
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            try:
                header = [h.strip() for h in next(reader)]
            except StopIteration:
                raise DataFileError(path, "empty file (no header line)") from None
            missing = [c for c in REQUIRED_COLUMNS if c not in header]
            if missing:
                raise DataFileError(path, f"line 1: missing column(s) {missing}")
            col = {name: header.index(name) for name in REQUIRED_COLUMNS}
            numeric = [c for c in REQUIRED_COLUMNS if c != "traj_dir"]
            values: list[list[float]] = []
            dirs: list[str] = []
            for line_no, row in enumerate(reader, start=2):
                if not row or all(not cell.strip() for cell in row):
                    continue
                if len(row) != len(header):
                    raise DataFileError(path, f"line {line_no}: {len(row)} fields, expected {len(header)}")
                rec: list[float] = []
                for name in numeric:
                    cell = row[col[name]].strip()
                    try:
                        val = float(cell)
                    except ValueError:
                        raise DataFileError(path, f"line {line_no}, column {name!r}: not a number: {cell!r}") from None
                    if not math.isfinite(val):
                        raise DataFileError(path, f"line {line_no}, column {name!r}: not finite: {cell!r}")
                    rec.append(val)
                values.append(rec)
                dirs.append(row[col["traj_dir"]].strip())
                vz_in = rec[numeric.index("v_in_z")]
                vz_out = rec[numeric.index("v_out_z")]
                if vz_in >= 0.0:
                    raise DataFileError(path, f"line {line_no}, column 'v_in_z': ball must approach the face (< 0), got {vz_in}")
                if vz_out <= 0.0:
                    raise DataFileError(path, f"line {line_no}, column 'v_out_z': ball must leave the face (> 0), got {vz_out}")
    except OSError as exc:
        raise DataFileError(path, f"cannot read: {exc}") from exc
    if not values:
        raise DataFileError(path, "no data rows")
    arr = np.array(values, dtype=float)

    def vec(prefix: str) -> FloatArray:
        return np.stack([arr[:, numeric.index(f"{prefix}_{a}")] for a in "xyz"], axis=1)

    return BounceRows(
        v_in=vec("v_in"),
        w_in=vec("spin_before"),
        v_out=vec("v_out"),
        w_out=vec("spin_after"),
        racket_angle=arr[:, numeric.index("racket_angle")],
        traj_dir=tuple(dirs),
        source=str(path),
    )


def dataset_path(racket: str) -> Path:
    """Path of a shipped racket's train CSV (``studio/data/racket_bounces/train``)."""
    return RACKET_DATA_DIR / "train" / f"{racket}.csv"


# =====================================================================================
# Fit
# =====================================================================================

_LOWER = {
    "restitution_0": 0.0,
    "restitution_slope": -0.2,
    "restitution_slip": 0.0,
    "compliance_0": -1.0,
    "compliance_slope": -0.2,
    "compliance_slip": -1.0,
    "friction": 0.01,
    "lever_ratio": 0.5,
    "torsion": 0.0,
}
_UPPER = {
    "restitution_0": 1.5,
    "restitution_slope": 0.2,
    "restitution_slip": 1.0,
    "compliance_0": 1.0,
    "compliance_slope": 0.2,
    "compliance_slip": 1.0,
    "friction": 3.0,
    "lever_ratio": 1.0,
    "torsion": 1.0,
}
_START = RacketModel(
    restitution_0=0.9,
    restitution_slope=0.02,
    restitution_slip=0.0,
    compliance_0=0.7,
    compliance_slope=0.0,
    compliance_slip=0.0,
    friction=0.6,
    lever_ratio=0.99,
    torsion=0.1,
)

REFERENCE_FIXED = {
    "restitution_slip": 0.0,
    "compliance_slope": 0.0,
    "compliance_slip": 0.0,
    "friction": 1e6,
    "lever_ratio": 1.0,
    "torsion": 0.0,
}
"""Parameters held fixed in the reference elastic-rubber model of the dataset README
(k_p + restitution linear in normal speed; no friction limit, no normal-spin change)."""


def residuals(model: RacketModel, rows: BounceRows) -> FloatArray:
    """Normalized residuals (6 N,): velocity errors / VELOCITY_SCALE, spin errors / SPIN_SCALE."""
    v, w = model.bounce(rows.v_in, rows.w_in)
    return np.concatenate([((v - rows.v_out) / VELOCITY_SCALE).ravel(), ((w - rows.w_out) / SPIN_SCALE).ravel()])


def prediction_errors(model: RacketModel, rows: BounceRows) -> tuple[FloatArray, FloatArray]:
    """Per-row error norms: (|v_pred - v_out| (N,) [m/s], |w_pred - w_out| (N,) [rad/s])."""
    v, w = model.bounce(rows.v_in, rows.w_in)
    return np.linalg.norm(v - rows.v_out, axis=1), np.linalg.norm(w - rows.w_out, axis=1)


def _fit(rows: BounceRows, free: Sequence[str], fixed: dict[str, float], name: str) -> RacketModel:
    if len(rows) < len(free) + 1:
        raise InvalidInputError(f"fit_racket_model: {len(rows)} rows are too few for {len(free)} parameters")
    base = replace(_START, **fixed, name=name)
    x0 = np.array([getattr(base, n) for n in free])
    lo = np.array([_LOWER[n] for n in free])
    hi = np.array([_UPPER[n] for n in free])

    def make(x: FloatArray) -> RacketModel:
        return replace(base, **{n: float(val) for n, val in zip(free, x, strict=True)})

    sol = least_squares(lambda x: residuals(make(x), rows), np.clip(x0, lo, hi), bounds=(lo, hi), x_scale="jac")
    return make(sol.x)


def fit_racket_model(rows: BounceRows, *, name: str = "fitted") -> RacketModel:
    """Fit all :attr:`RacketModel.PARAMETERS` on ``rows`` (scipy least_squares, TRF, bounds).

    Residuals are the outgoing velocity and spin errors normalized by
    :data:`VELOCITY_SCALE` and :data:`SPIN_SCALE`.
    """
    return _fit(rows, RacketModel.PARAMETERS, {}, name)


def fit_reference_model(rows: BounceRows, *, name: str = "reference") -> RacketModel:
    """Fit the dataset README's reference model (free: e0, e1, k0; rest :data:`REFERENCE_FIXED`)."""
    free = [n for n in RacketModel.PARAMETERS if n not in REFERENCE_FIXED]
    return _fit(rows, free, REFERENCE_FIXED, name)


@dataclass(frozen=True, slots=True)
class CrossValidation:
    """k-fold cross-validated prediction errors of a fitting procedure."""

    folds: int
    """Number of folds."""
    rms_velocity: float
    """RMS over all held-out rows of the outgoing velocity error norm [m/s]."""
    rms_spin: float
    """RMS over all held-out rows of the outgoing spin error norm [rad/s]."""
    rms_velocity_in_plane: float
    """Same as ``rms_velocity`` for the x-z components only [m/s] (the data set has
    v_y = 0 by construction, see the README of the shipped data)."""


def cross_validate(
    rows: BounceRows,
    *,
    folds: int = 5,
    seed: int = 0,
    fitter: Callable[[BounceRows], RacketModel] = fit_racket_model,
) -> CrossValidation:
    """k-fold cross-validation (random row split with ``seed``) of a fitting procedure."""
    if folds < 2 or folds > len(rows):
        raise InvalidInputError(f"cross_validate: folds must be in [2, {len(rows)}], got {folds}")
    idx = np.random.default_rng(seed).permutation(len(rows))
    ev: list[FloatArray] = []
    ew: list[FloatArray] = []
    exz: list[FloatArray] = []
    for test in np.array_split(idx, folds):
        train = np.setdiff1d(idx, test)
        model = fitter(rows.subset(train))
        held = rows.subset(test)
        v, w = model.bounce(held.v_in, held.w_in)
        ev.append(np.sum((v - held.v_out) ** 2, axis=1))
        ew.append(np.sum((w - held.w_out) ** 2, axis=1))
        exz.append((v[:, 0] - held.v_out[:, 0]) ** 2 + (v[:, 2] - held.v_out[:, 2]) ** 2)
    return CrossValidation(
        folds=folds,
        rms_velocity=float(np.sqrt(np.mean(np.concatenate(ev)))),
        rms_spin=float(np.sqrt(np.mean(np.concatenate(ew)))),
        rms_velocity_in_plane=float(np.sqrt(np.mean(np.concatenate(exz)))),
    )


# =====================================================================================
# Table drop test
# =====================================================================================


def drop_test_rebound(
    table: TableBounceModel | None = None,
    flight: FlightModel | None = None,
    *,
    drop_height: float = C.DROP_TEST_HEIGHT,
) -> float:
    """Rebound height [m] of the ITTF Law 2.1.3 drop test.

    The ball is released at rest with its bottom ``drop_height`` above the playing
    surface (away from the net), bounces once, and the highest point of its bottom
    after the bounce is returned.
    """
    table = TableBounceModel() if table is None else table
    flight = FlightModel() if flight is None else flight
    r = flight.radius
    state = BallState([0.6, 0.3, drop_height + r], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    traj = simulate(state, 1.2, flight=flight, table=table, max_table_bounces=2, dt_out=5e-4)
    bounces = traj.table_bounces
    if not bounces:
        raise InvalidInputError("drop_test_rebound: the ball did not reach the table")
    # apex after the first bounce: vertical velocity 0 (root of the dense path)
    i0 = int(np.searchsorted(traj.t, bounces[0].t))
    i1 = int(np.searchsorted(traj.t, bounces[1].t)) if len(bounces) > 1 else len(traj.t)
    k = i0 + int(np.argmax(traj.p[i0:i1, 2]))
    # refine the apex with a local parabola through three samples
    if i0 < k < i1 - 1:
        z0, z1, z2 = traj.p[k - 1 : k + 2, 2]
        denom = z0 - 2.0 * z1 + z2
        z_apex = z1 - 0.125 * (z2 - z0) ** 2 / denom if denom < 0.0 else z1
    else:
        z_apex = traj.p[k, 2]
    return float(z_apex - r)


def tune_table_restitution(
    flight: FlightModel | None = None,
    *,
    target: float = C.DROP_TEST_REBOUND,
    drop_height: float = C.DROP_TEST_HEIGHT,
    friction: float = TableBounceModel().friction,
) -> float:
    """Restitution e for which :func:`drop_test_rebound` equals ``target`` [m]."""

    def gap(e: float) -> float:
        return drop_test_rebound(TableBounceModel(restitution=e, friction=friction), flight, drop_height=drop_height) - target

    return float(brentq(gap, 0.5, 1.0, xtol=1e-6))


# =====================================================================================
# Entry point
# =====================================================================================


def calibrate(folds: int = 5, seed: int = 0) -> dict[str, dict[str, object]]:
    """Fit every shipped racket and cross-validate model and reference.

    Returns:
        ``{racket: {"model": RacketModel, "cv": CrossValidation, "reference_cv":
        CrossValidation, "rows": int, "train_rms": (v, w)}}``.
    """
    out: dict[str, dict[str, object]] = {}
    for racket in RACKETS:
        rows = load_bounce_csv(dataset_path(racket))
        cv = cross_validate(rows, folds=folds, seed=seed)
        ref = cross_validate(rows, folds=folds, seed=seed, fitter=fit_reference_model)
        model = fit_racket_model(rows, name=racket)
        ev, ew = prediction_errors(model, rows)
        model = replace(model, cv_rms_velocity=cv.rms_velocity, cv_rms_spin=cv.rms_spin)
        out[racket] = {
            "model": model,
            "cv": cv,
            "reference_cv": ref,
            "rows": len(rows),
            "train_rms": (float(np.sqrt(np.mean(ev**2))), float(np.sqrt(np.mean(ew**2)))),
        }
    return out


def write_models_json(results: dict[str, dict[str, object]], path: Path = RACKET_MODELS_JSON) -> None:
    """Write the fitted models and their figures (schema 1), atomically."""
    doc: dict[str, object] = {
        "schema": 1,
        "description": (
            "RacketModel parameters (studio.ball) fitted by studio.ball_calibration on "
            "studio/data/racket_bounces/train/<racket>.csv; errors are RMS of vector norms."
        ),
        "normalization": {"velocity_scale_m_s": VELOCITY_SCALE, "spin_scale_rad_s": SPIN_SCALE},
        "models": {},
    }
    models: dict[str, object] = {}
    for racket, res in results.items():
        model = res["model"]
        cv = res["cv"]
        ref = res["reference_cv"]
        assert isinstance(model, RacketModel) and isinstance(cv, CrossValidation) and isinstance(ref, CrossValidation)
        train_v, train_w = res["train_rms"]  # type: ignore[misc]
        models[racket] = {
            "parameters": {n: round(float(getattr(model, n)), 6) for n in RacketModel.PARAMETERS},
            "rows": res["rows"],
            "train_fit": {"rms_velocity": round(train_v, 4), "rms_spin": round(train_w, 3)},
            "cross_validation": {
                "folds": cv.folds,
                "rms_velocity": round(cv.rms_velocity, 4),
                "rms_spin": round(cv.rms_spin, 3),
                "rms_velocity_in_plane": round(cv.rms_velocity_in_plane, 4),
            },
            "reference_model_cross_validation": {
                "rms_velocity": round(ref.rms_velocity, 4),
                "rms_spin": round(ref.rms_spin, 3),
                "rms_velocity_in_plane": round(ref.rms_velocity_in_plane, 4),
            },
        }
    doc["models"] = models
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".racket_models.", suffix=".json")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2)
            fh.write("\n")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def format_table(results: dict[str, dict[str, object]]) -> str:
    """Cross-validation table (text) of :func:`calibrate` results."""
    lines = [
        "racket     rows  folds | model CV: |dv| RMS  |dw| RMS  (x-z |dv|) | reference CV: |dv| RMS  |dw| RMS",
        "-" * 100,
    ]
    for racket, res in results.items():
        cv = res["cv"]
        ref = res["reference_cv"]
        assert isinstance(cv, CrossValidation) and isinstance(ref, CrossValidation)
        lines.append(
            f"{racket:<9} {res['rows']:>5} {cv.folds:>6} | {cv.rms_velocity:>9.3f} m/s {cv.rms_spin:>6.1f} rad/s"
            f" ({cv.rms_velocity_in_plane:.3f} m/s) | {ref.rms_velocity:>9.3f} m/s {ref.rms_spin:>6.1f} rad/s"
        )
    lines.append("")
    for racket, res in results.items():
        model = res["model"]
        assert isinstance(model, RacketModel)
        params = ", ".join(f"{n}={getattr(model, n):.4g}" for n in RacketModel.PARAMETERS)
        lines.append(f"{racket}: {params}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Fit the racket models, print the k-fold CV table; ``--write`` refreshes the JSON."""
    parser = argparse.ArgumentParser(prog="python -m studio.ball_calibration", description=main.__doc__)
    parser.add_argument("--folds", type=int, default=5, help="number of cross-validation folds (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random fold split (default 0)")
    parser.add_argument("--write", action="store_true", help=f"write the fitted models to {RACKET_MODELS_JSON}")
    parser.add_argument("--drop-test", action="store_true", help="also tune the table restitution (ITTF drop test)")
    args = parser.parse_args(list(argv) if argv is not None else None)
    try:
        results = calibrate(folds=args.folds, seed=args.seed)
    except InvalidInputError as exc:
        print(f"error: {exc}")
        return 2
    print(format_table(results))
    if args.drop_test:
        e = tune_table_restitution()
        print(f"\ntable restitution for a {C.DROP_TEST_HEIGHT * 100:.0f} cm -> {C.DROP_TEST_REBOUND * 100:.0f} cm drop test: {e:.4f}")
    if args.write:
        write_models_json(results)
        print(f"\nwrote {RACKET_MODELS_JSON}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
