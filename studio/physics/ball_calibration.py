"""Calibration of the ball models: racket impact fit with cross-validation, table drop test.

Racket: :func:`fit_racket_model` fits :class:`studio.physics.ball.RacketModel` on measured
racket-ball bounces (``studio/data/racket_bounces/``, T. Gossard's public dataset, MIT
licence) by nonlinear least squares on the outgoing velocity and spin, each residual
divided by a scale (:data:`VELOCITY_SCALE`, :data:`SPIN_SCALE`) so both count alike.
:func:`cross_validate` reports k-fold errors on rows not used for the fit, for the
model and for the reference elastic-rubber model of the dataset's README (tangential
compliance ``k_p`` + restitution linear in the normal speed).

Table: :func:`tune_table_restitution` finds the restitution that makes the ITTF Law
2.1.3 drop test (30 cm drop, air drag included) bounce to 23 cm.

Entry point: ``serve-studio calibrate [--folds K] [--write]`` prints the
cross-validation table (``--write`` also refreshes ``racket_models.json``).
"""

from __future__ import annotations

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
from scipy.spatial.transform import Rotation

from studio import constants as C
from studio.errors import DataFileError, InvalidInputError
from studio.paths import DATA_DIR
from studio.physics.ball import (
    DEFAULT_RACKET,
    RACKET_DATA_DIR,
    RACKET_MODELS_JSON,
    BallState,
    FlightModel,
    RacketModel,
    TableBounceModel,
    _local_frame,
    simulate,
)
from studio.storage.jsonfile import not_utf8_file

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


def _finite_cell(path: Path, line_no: int, name: str, cell: str) -> float:
    """The finite number in a CSV cell, or DataFileError naming file, line and column."""
    cell = cell.strip()
    try:
        val = float(cell)
    except ValueError:
        raise DataFileError(path, f"line {line_no}, column {name!r}: not a number: {cell!r}") from None
    if not math.isfinite(val):
        raise DataFileError(path, f"line {line_no}, column {name!r}: not finite: {cell!r}")
    return val


def load_bounce_csv(path: str | os.PathLike[str]) -> BounceRows:
    """Read a racket-bounce CSV (columns :data:`REQUIRED_COLUMNS`, SI units).

    Raises:
        DataFileError: unreadable file, missing column, a non-numeric or non-finite
            value (the message names the file, line and column), no rows, or a ball not
            approaching the face (``v_in_z >= 0``) / not leaving it (``v_out_z <= 0``).
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
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
                    rec.append(_finite_cell(path, line_no, name, row[col[name]]))
                values.append(rec)
                dirs.append(row[col["traj_dir"]].strip())
                vz_in = rec[numeric.index("v_in_z")]
                vz_out = rec[numeric.index("v_out_z")]
                if vz_in >= 0.0:
                    raise DataFileError(
                        path, f"line {line_no}, column 'v_in_z': ball must approach the face (< 0), got {vz_in}"
                    )
                if vz_out <= 0.0:
                    raise DataFileError(
                        path, f"line {line_no}, column 'v_out_z': ball must leave the face (> 0), got {vz_out}"
                    )
    except UnicodeDecodeError:
        raise not_utf8_file(path) from None
    except (OSError, csv.Error) as exc:
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


SERVE_CONTACTS_CSV = DATA_DIR / "robot_serve_contacts" / "serve_contacts.csv"
"""Shipped real robot serve contacts (Sony AI, BSD-3, ``studio/data/robot_serve_contacts/``)."""

_CONTACT_GROUPS = {
    "v_pre": "Global_Ball_Vel_Pre_",
    "w_pre": "Global_Ball_Spin_Pre_",
    "v_post": "Global_Ball_Vel_Post_",
    "w_post": "Global_Ball_Spin_Post_",
    "v_racket": "Global_Racket_Velocity_",
    "w_racket": "Global_Racket_Spin_",
}
_OFFSET_COLUMNS = ("Global_dx_pre", "Global_dy_pre", "Global_dz_pre")
CONTACT_COLUMNS = (
    tuple(f"{p}{a}" for p in _CONTACT_GROUPS.values() for a in "XYZ")
    + tuple(f"Orientation_{a}" for a in "XYZW")
    + _OFFSET_COLUMNS
)
"""Columns a serve-contact CSV must have (the Ace robot's format; extra columns are ignored)."""


def _read_numeric_csv(path: Path, columns: Sequence[str]) -> tuple[FloatArray, list[dict[str, str]], list[int]]:
    """(N, len(columns)) finite values, the raw rows and their line numbers in the file;
    DataFileError naming line and column."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in columns if c not in (reader.fieldnames or [])]
            if missing:
                raise DataFileError(path, f"line 1: missing column(s) {missing}")
            values: list[list[float]] = []
            raw: list[dict[str, str]] = []
            lines: list[int] = []
            for row in reader:
                line_no = reader.line_num
                rec: list[float] = []
                for name in columns:
                    rec.append(_finite_cell(path, line_no, name, row.get(name) or ""))
                values.append(rec)
                raw.append(row)
                lines.append(line_no)
    except UnicodeDecodeError:
        raise not_utf8_file(path) from None
    except (OSError, csv.Error) as exc:
        raise DataFileError(path, f"cannot read: {exc}") from exc
    if not values:
        raise DataFileError(path, "no data rows")
    return np.array(values, dtype=float), raw, lines


def load_serve_contacts_csv(path: str | os.PathLike[str] = SERVE_CONTACTS_CSV) -> BounceRows:
    """Read robot serve contacts (moving racket) as rows relative to the racket.

    Each row's ball velocity relative to the racket-fixed point at the ball's centre
    (racket velocity plus ``omega x d``, ``d`` = ``Global_d{x,y,z}_pre``, the data's own
    racket-frame columns ``Before_*``/``After_*`` use the same) and spin relative to the
    racket's angular velocity are written in a face frame whose z axis is the face normal (the
    racket frame's x axis, ``Orientation_*`` quaternion, scalar last) turned towards
    the incoming ball; the outgoing state likewise. An isotropic model's error norms are
    the same in this frame as in the world frame (the scoring rule of the data's README).

    Raises:
        DataFileError: unreadable file, missing column, non-numeric or non-finite value
            (file, line and column named), no rows, or a degenerate quaternion.
    """
    path = Path(path)
    arr, raw, lines = _read_numeric_csv(path, CONTACT_COLUMNS)
    vec = {key: arr[:, 3 * i : 3 * i + 3] for i, key in enumerate(_CONTACT_GROUPS)}
    quat = arr[:, 18:22]
    qn = np.linalg.norm(quat, axis=1)
    if np.any(qn < 0.5) or np.any(qn > 1.5):
        bad = int(np.nonzero((qn < 0.5) | (qn > 1.5))[0][0])
        raise DataFileError(
            path, f"line {lines[bad]}, columns 'Orientation_*': not a unit quaternion (norm {qn[bad]:.3g})"
        )
    normal = Rotation.from_quat(quat / qn[:, None]).as_matrix()[:, :, 0]
    # the racket-fixed point at the ball centre (offset Global_d*_pre from the racket centre)
    v_point = vec["v_racket"] + np.cross(vec["w_racket"], arr[:, 22:25])
    rel = vec["v_pre"] - v_point
    normal *= -np.sign(np.einsum("ij,ij->i", rel, normal) + 1e-300)[:, None]
    frames = np.array([_local_frame(n) for n in normal])  # z = the face normal

    def local(a: FloatArray) -> FloatArray:
        return np.einsum("nji,nj->ni", frames, a)

    rows = BounceRows(
        v_in=local(rel),
        w_in=local(vec["w_pre"] - vec["w_racket"]),
        v_out=local(vec["v_post"] - v_point),
        w_out=local(vec["w_post"] - vec["w_racket"]),
        racket_angle=np.full(len(arr), np.nan),
        traj_dir=tuple(f"line {n}: {r.get('date', '')}{r.get('shot_ID', '')}" for n, r in zip(lines, raw, strict=True)),
        source=str(path),
    )
    if np.any(rows.v_in[:, 2] >= 0.0) or np.any(rows.v_out[:, 2] <= 0.0):
        bad = int(np.nonzero((rows.v_in[:, 2] >= 0.0) | (rows.v_out[:, 2] <= 0.0))[0][0])
        raise DataFileError(path, f"line {lines[bad]}: the ball does not approach and leave the racket face")
    return rows


# =====================================================================================
# Fit
# =====================================================================================


@dataclass(frozen=True, slots=True)
class ContactSet:
    """One data set of a joint racket fit, with the scales its residuals are divided by."""

    name: str
    """Label of the set in tables and JSON (e.g. ``racket_bounces``)."""
    rows: BounceRows
    """The measured impacts, relative to the racket."""
    velocity_scale: float = VELOCITY_SCALE
    """Divisor of the velocity residuals [m/s]."""
    spin_scale: float = SPIN_SCALE
    """Divisor of the spin residuals [rad/s]."""
    weight: float = 1.0
    """Multiplier of the set's normalized residuals [-]."""

    def subset(self, index: npt.ArrayLike) -> ContactSet:
        """The same set restricted to rows ``index``."""
        return replace(self, rows=self.rows.subset(index))


SERVE_VELOCITY_SCALE = 1.0
"""Velocity residual divisor of the robot serve contacts [m/s] (their velocity errors are
about twice the racket-at-rest rows': estimated pre-contact spins of a tossed ball)."""

SERVE_WEIGHT = 3.0
"""Weight of the 46 serve contacts beside the 794 racket-at-rest rows: each serve row counts
9 times a racket-at-rest row in the squared residuals (about half of the total weight), so
that the brushing regime is fitted and not drowned. Chosen by 5-fold CV (weights 1, 2, 3, 5:
3 gave the lowest serve-contact velocity error without raising the racket-at-rest one)."""

_BOUNDS = {
    "restitution_0": (0.0, 1.5),
    "restitution_slope": (-0.2, 0.2),
    "restitution_slip": (0.0, 1.0),
    "compliance_0": (-1.0, 1.0),
    "compliance_slope": (-0.2, 0.2),
    "compliance_slip": (-1.0, 1.0),
    "compliance_slip_speed": (0.5, 30.0),
    "friction": (0.01, 5.0),
    "lever_ratio": (0.5, 1.0),
    "torsion": (0.0, 1.0),
    "normal_return": (0.0, 1.0),
}
_START = RacketModel(
    restitution_0=0.95,
    restitution_slope=0.024,
    restitution_slip=0.0,
    compliance_0=0.95,
    compliance_slope=-0.02,
    compliance_slip=-0.3,
    compliance_slip_speed=10.0,
    friction=1.2,
    lever_ratio=0.98,
    torsion=0.3,
    normal_return=0.1,
)

REFERENCE_FIXED = {
    "restitution_slip": 0.0,
    "compliance_slope": 0.0,
    "compliance_slip": 0.0,
    "friction": 5.0,
    "lever_ratio": 1.0,
    "torsion": 0.0,
    "normal_return": 0.0,
}
"""Parameters held fixed in the reference elastic-rubber model of the dataset README
(k_p + restitution linear in normal speed; practically no friction limit, no normal-spin
change)."""


def _as_sets(data: BounceRows | Sequence[ContactSet]) -> list[ContactSet]:
    return [ContactSet("rows", data)] if isinstance(data, BounceRows) else list(data)


def residuals(model: RacketModel, data: BounceRows | Sequence[ContactSet]) -> FloatArray:
    """Normalized, weighted residuals of every set: velocity and spin errors / their scales."""
    parts: list[FloatArray] = []
    for cs in _as_sets(data):
        v, w = model.bounce(cs.rows.v_in, cs.rows.w_in)
        parts.append(cs.weight * ((v - cs.rows.v_out) / cs.velocity_scale).ravel())
        parts.append(cs.weight * ((w - cs.rows.w_out) / cs.spin_scale).ravel())
    return np.concatenate(parts)


def prediction_errors(model: RacketModel, rows: BounceRows) -> tuple[FloatArray, FloatArray]:
    """Per-row error norms: (|v_pred - v_out| (N,) [m/s], |w_pred - w_out| (N,) [rad/s])."""
    v, w = model.bounce(rows.v_in, rows.w_in)
    return np.linalg.norm(v - rows.v_out, axis=1), np.linalg.norm(w - rows.w_out, axis=1)


def _fit(sets: list[ContactSet], free: Sequence[str], fixed: dict[str, float], name: str) -> RacketModel:
    n_rows = sum(len(cs.rows) for cs in sets)
    if n_rows < len(free) + 1:
        raise InvalidInputError(f"fit_racket_model: {n_rows} rows are too few for {len(free)} parameters")
    base = replace(_START, **fixed, name=name)
    lo = np.array([_BOUNDS[n][0] for n in free])
    hi = np.array([_BOUNDS[n][1] for n in free])
    x0 = np.clip(np.array([getattr(base, n) for n in free]), lo, hi)

    def make(x: FloatArray) -> RacketModel:
        return replace(base, **{n: float(val) for n, val in zip(free, x, strict=True)}, name=name)

    sol = least_squares(lambda x: residuals(make(x), sets), x0, bounds=(lo, hi), x_scale="jac")
    return make(sol.x)


def fit_racket_model(data: BounceRows | Sequence[ContactSet], *, name: str = "fitted") -> RacketModel:
    """Fit all :attr:`RacketModel.PARAMETERS` jointly on one or several data sets.

    scipy least_squares (TRF, bounds) on the residuals of :func:`residuals`: each set's
    velocity and spin errors divided by its scales and multiplied by its weight.
    """
    return _fit(_as_sets(data), RacketModel.PARAMETERS, {}, name)


def fit_reference_model(data: BounceRows | Sequence[ContactSet], *, name: str = "reference") -> RacketModel:
    """Fit the dataset README's reference model (free: e0, e1, k0; rest :data:`REFERENCE_FIXED`)."""
    free = [n for n in RacketModel.PARAMETERS if n not in REFERENCE_FIXED and n != "compliance_slip_speed"]
    return _fit(_as_sets(data), free, REFERENCE_FIXED, name)


@dataclass(frozen=True, slots=True)
class CrossValidation:
    """k-fold cross-validated prediction errors of a fitting procedure on one data set."""

    folds: int
    """Number of folds."""
    rms_velocity: float
    """RMS over all held-out rows of the outgoing velocity error norm [m/s]."""
    rms_spin: float
    """RMS over all held-out rows of the outgoing spin error norm [rad/s]."""
    rms_velocity_in_plane: float
    """Same as ``rms_velocity`` for the x-z components only [m/s] (the racket-bounce data
    set has v_y = 0 by construction, see the README of the shipped data)."""
    repeats: int = 1
    """Number of random fold splits pooled (each row is held out once per split)."""


def _split(n: int, folds: int, rng: np.random.Generator) -> list[FloatArray]:
    return list(np.array_split(rng.permutation(n), folds))


def cross_validate_sets(
    sets: Sequence[ContactSet],
    *,
    folds: int = 5,
    repeats: int = 1,
    seed: int = 0,
    fitter: Callable[[list[ContactSet]], RacketModel] = fit_racket_model,
) -> dict[str, CrossValidation]:
    """k-fold CV of a joint fit, folds drawn within each set, errors reported per set.

    Fold j of every set is held out together; the model is fitted on the rest of all
    sets. ``repeats`` random splits are pooled.
    """
    sets = list(sets)
    if folds < 2 or any(folds > len(cs.rows) for cs in sets):
        raise InvalidInputError(f"cross_validate: folds must be in [2, smallest set's rows], got {folds}")
    sq: dict[str, list[FloatArray]] = {cs.name: [] for cs in sets}
    rng = np.random.default_rng(seed)
    for _ in range(repeats):
        splits = [_split(len(cs.rows), folds, rng) for cs in sets]
        for j in range(folds):
            train = [
                cs.subset(np.setdiff1d(np.arange(len(cs.rows)), sp[j])) for cs, sp in zip(sets, splits, strict=True)
            ]
            model = fitter(train)
            for cs, sp in zip(sets, splits, strict=True):
                held = cs.rows.subset(sp[j])
                v, w = model.bounce(held.v_in, held.w_in)
                dv, dw = v - held.v_out, w - held.w_out
                sq[cs.name].append(np.stack([np.sum(dv**2, 1), np.sum(dw**2, 1), dv[:, 0] ** 2 + dv[:, 2] ** 2], 1))
    out: dict[str, CrossValidation] = {}
    for name, parts in sq.items():
        r = np.sqrt(np.mean(np.concatenate(parts), axis=0))
        out[name] = CrossValidation(folds, float(r[0]), float(r[1]), float(r[2]), repeats)
    return out


def cross_validate(
    rows: BounceRows,
    *,
    folds: int = 5,
    seed: int = 0,
    fitter: Callable[[BounceRows], RacketModel] = fit_racket_model,
) -> CrossValidation:
    """k-fold cross-validation (random row split with ``seed``) on one set of rows."""
    res = cross_validate_sets(
        [ContactSet("rows", rows)], folds=folds, seed=seed, fitter=lambda sets: fitter(sets[0].rows)
    )
    return res["rows"]


def measurement_noise(rows: BounceRows, model: RacketModel) -> tuple[float, float] | None:
    """Noise floor of a data set with repeated settings: (velocity, spin) RMS [m/s, rad/s].

    Rows of one launcher setting and racket angle (``traj_dir``, ``racket_angle``) are paired; the difference of two
    outcomes minus the model's predicted difference (which accounts for the small change of
    the incoming state) is twice the per-row noise variance: ``sqrt(mean |d|^2 / 2)``. It is
    what no smooth map of the measured inputs can explain. None when no setting repeats:
    the serve contacts (every row is its own shot) and the shipped racket bounces (each
    launcher setting appears at one racket angle only).
    """
    groups: dict[tuple[str, float], list[int]] = {}
    for i, key in enumerate(rows.traj_dir):
        groups.setdefault((key, float(rows.racket_angle[i])), []).append(i)
    pairs = np.array([(g[a], g[b]) for g in groups.values() for a in range(len(g)) for b in range(a + 1, len(g))])
    if len(pairs) == 0:
        return None
    v, w = model.bounce(rows.v_in, rows.w_in)
    dv = (rows.v_out - v)[pairs[:, 0]] - (rows.v_out - v)[pairs[:, 1]]
    dw = (rows.w_out - w)[pairs[:, 0]] - (rows.w_out - w)[pairs[:, 1]]
    return math.sqrt(float(np.mean(np.sum(dv**2, 1))) / 2.0), math.sqrt(float(np.mean(np.sum(dw**2, 1))) / 2.0)


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
    state = BallState(np.array([0.6, 0.3, drop_height + r]), np.zeros(3), np.zeros(3))
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
        return (
            drop_test_rebound(TableBounceModel(restitution=e, friction=friction), flight, drop_height=drop_height)
            - target
        )

    return float(brentq(gap, 0.5, 1.0, xtol=1e-6))


# =====================================================================================
# Racket calibration: joint fit, figures, JSON
# =====================================================================================


@dataclass(frozen=True, slots=True)
class RacketCalibration:
    """A racket's joint fit with its cross-validated errors per data set."""

    model: RacketModel
    """The model fitted on all rows of every set."""
    sets: tuple[str, ...]
    """Names of the data sets, in table order."""
    rows: dict[str, int]
    """Rows per set."""
    cv: dict[str, CrossValidation]
    """CV errors of the joint fit, per set."""
    cv_rest_only: dict[str, CrossValidation]
    """CV errors of the same model fitted on the racket-at-rest rows only, per set."""
    cv_reference: dict[str, CrossValidation]
    """CV errors of the reference elastic-rubber model (joint fit), per set."""
    before: dict[str, tuple[float, float]]
    """RMS errors (velocity, spin) of the model shipped before the fit, per set (that
    model may have been fitted on the racket-at-rest rows: not cross-validated there)."""
    noise: dict[str, tuple[float, float] | None]
    """:func:`measurement_noise` per set (None where it cannot be estimated)."""


def default_contact_sets(
    racket: str = DEFAULT_RACKET, serve_contacts: Path | None = SERVE_CONTACTS_CSV
) -> list[ContactSet]:
    """The shipped data of a racket: its racket-at-rest rows and the robot serve contacts."""
    sets = [ContactSet("racket_bounces", load_bounce_csv(dataset_path(racket)))]
    if serve_contacts is not None:
        rows = load_serve_contacts_csv(serve_contacts)
        sets.append(ContactSet("serve_contacts", rows, SERVE_VELOCITY_SCALE, SPIN_SCALE, SERVE_WEIGHT))
    return sets


def _previous_errors(name: str, sets: Sequence[ContactSet]) -> dict[str, tuple[float, float]]:
    try:
        previous = RacketModel.for_racket(name)
    except DataFileError:
        return {}
    out: dict[str, tuple[float, float]] = {}
    for cs in sets:
        ev, ew = prediction_errors(previous, cs.rows)
        out[cs.name] = (float(np.sqrt(np.mean(ev**2))), float(np.sqrt(np.mean(ew**2))))
    return out


def calibrate_racket(
    sets: Sequence[ContactSet], *, name: str = DEFAULT_RACKET, folds: int = 5, repeats: int = 1, seed: int = 0
) -> RacketCalibration:
    """Fit a racket jointly on ``sets`` and cross-validate it, its racket-at-rest-only fit and the reference."""
    sets = list(sets)
    rest = [cs for cs in sets if cs.name == "racket_bounces"] or sets[:1]
    cv_opts = {"folds": folds, "repeats": repeats, "seed": seed}
    model = fit_racket_model(sets, name=name)
    cv = cross_validate_sets(sets, **cv_opts)  # type: ignore[arg-type]
    first = cv[rest[0].name]
    return RacketCalibration(
        model=replace(model, cv_rms_velocity=first.rms_velocity, cv_rms_spin=first.rms_spin),
        sets=tuple(cs.name for cs in sets),
        rows={cs.name: len(cs.rows) for cs in sets},
        cv=cv,
        cv_rest_only=cross_validate_sets(
            sets,
            fitter=lambda tr: fit_racket_model([c for c in tr if c.name == rest[0].name]),
            **cv_opts,  # type: ignore[arg-type]
        ),
        cv_reference=cross_validate_sets(sets, fitter=fit_reference_model, **cv_opts),  # type: ignore[arg-type]
        before=_previous_errors(name, sets),
        noise={cs.name: measurement_noise(cs.rows, model) for cs in sets},
    )


def calibrate(
    folds: int = 5, seed: int = 0, *, repeats: int = 1, serve_contacts: Path | None = SERVE_CONTACTS_CSV
) -> dict[str, RacketCalibration]:
    """Fit every shipped racket jointly with the robot serve contacts and cross-validate."""
    return {
        racket: calibrate_racket(
            default_contact_sets(racket, serve_contacts), name=racket, folds=folds, repeats=repeats, seed=seed
        )
        for racket in RACKETS
    }


def _cv_json(cv: CrossValidation) -> dict[str, float]:
    return {
        "rms_velocity": round(cv.rms_velocity, 4),
        "rms_spin": round(cv.rms_spin, 3),
        "rms_velocity_in_plane": round(cv.rms_velocity_in_plane, 4),
    }


def _racket_json(res: RacketCalibration) -> dict[str, object]:
    return {
        "parameters": {n: round(float(getattr(res.model, n)), 6) for n in RacketModel.PARAMETERS},
        "rows": res.rows,
        "cross_validation": {
            "folds": next(iter(res.cv.values())).folds,
            "repeats": next(iter(res.cv.values())).repeats,
            **{name: _cv_json(cv) for name, cv in res.cv.items()},
        },
        "cross_validation_rest_only_fit": {name: _cv_json(cv) for name, cv in res.cv_rest_only.items()},
        "reference_model_cross_validation": {name: _cv_json(cv) for name, cv in res.cv_reference.items()},
    }


def write_models_json(results: dict[str, RacketCalibration], path: Path = RACKET_MODELS_JSON) -> None:
    """Write the fitted models and their figures (schema 2), atomically."""
    doc: dict[str, object] = {
        "schema": 2,
        "description": (
            "RacketModel parameters (studio.physics.ball) fitted jointly by studio.physics.ball_calibration on "
            "studio/data/racket_bounces/train/<racket>.csv (racket at rest, Gossard, MIT) and "
            "studio/data/robot_serve_contacts/serve_contacts.csv (Ace robot serves, Sony AI, BSD-3); "
            "errors are RMS of vector norms, relative to the racket."
        ),
        "fit": {
            "racket_bounces": {"velocity_scale_m_s": VELOCITY_SCALE, "spin_scale_rad_s": SPIN_SCALE, "weight": 1.0},
            "serve_contacts": {
                "velocity_scale_m_s": SERVE_VELOCITY_SCALE,
                "spin_scale_rad_s": SPIN_SCALE,
                "weight": SERVE_WEIGHT,
            },
        },
        "models": {racket: _racket_json(res) for racket, res in results.items()},
    }
    write_json_atomic(path, doc)


def write_json_atomic(path: Path, doc: object) -> None:
    """Write ``doc`` as indented JSON to ``path`` through a temporary file and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".json")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2)
            fh.write("\n")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _pair(v: float, w: float) -> str:
    return f"{v:6.3f} m/s {w:6.1f} rad/s"


def racket_table_rows(results: dict[str, RacketCalibration]) -> list[tuple[str, str, str, str, str]]:
    """Rows ``(model, data set, before, after, noise)`` of the calibration table."""
    rows: list[tuple[str, str, str, str, str]] = []
    for racket, res in results.items():
        for name in res.sets:
            before = res.before.get(name)
            noise = res.noise.get(name)
            rows.append(
                (
                    f"racket {racket} ({res.rows[name]} rows)",
                    name,
                    _pair(*before) if before else "n/a",
                    _pair(res.cv[name].rms_velocity, res.cv[name].rms_spin) + " (CV)",
                    _pair(*noise) if noise else "n/a",
                )
            )
    return rows


def format_table(results: dict[str, RacketCalibration]) -> str:
    """Text table of :func:`calibrate` results: errors per set and model variant, and the parameters."""
    lines = [
        f"{'racket':<10} {'data set':<15} {'shipped before':>25} | {'joint fit, CV':>25} | "
        f"{'rest-only fit, CV':>25} | {'reference, CV':>25} | {'noise floor':>25}",
        "-" * 170,
    ]
    for racket, res in results.items():
        for name in res.sets:
            before, noise = res.before.get(name), res.noise.get(name)
            cv, ro, ref = res.cv[name], res.cv_rest_only[name], res.cv_reference[name]
            lines.append(
                f"{racket:<10} {name:<15} {(_pair(*before) if before else 'n/a'):>25} | "
                f"{_pair(cv.rms_velocity, cv.rms_spin):>25} | {_pair(ro.rms_velocity, ro.rms_spin):>25} | "
                f"{_pair(ref.rms_velocity, ref.rms_spin):>25} | {(_pair(*noise) if noise else 'n/a'):>25}"
            )
    lines.append("")
    for racket, res in results.items():
        params = ", ".join(f"{n}={getattr(res.model, n):.4g}" for n in RacketModel.PARAMETERS)
        lines.append(f"{racket}: {params}")
    return "\n".join(lines)
