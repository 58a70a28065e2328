"""Is the match data's vertical velocity lagged too, and what does the table bounce return?

Issue #13 left one puzzle open: with the data's velocity lag corrected (the ~19 ms of
``studio.physics.flight_calibration.VELOCITY_LAG``) the measured post-bounce vertical
speed is ~1.0 times the predicted incoming one, which no restitution below 1 gives, while
the raw post-bounce states give ~0.91, the model's value. Two readings:

1. only the horizontal velocity is lagged (e.g. a vertical fit that includes gravity):
   then the vertical lag should fit to ~0 and the raw ratio is the true one;
2. every component is lagged: then a zero vertical lag must cost landing accuracy.

Run: ``.venv/bin/python experiments/bounce_lag/study.py [--match CSV]`` (~1 min of one
core). Prints (a) the flight fit with one lag per component (horizontal, vertical), free
and with the vertical lag fixed at 0, beside the shipped model; (b) the post-bounce
vertical speed over the predicted incoming one, lag-corrected / raw, by bins of incoming
vertical speed, horizontal speed and top/back spin, and by flight kind.

Data: Ace public match data (SonyResearch/ace_public data/match_data.csv, Nature 652,
2026), by default the dev file ``../shared/data/ace_match/match_data_dev.csv``; nothing of
it is copied, only figures are printed. Results: ``RESULTS.md`` beside this file.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from studio.physics import flight_calibration as fc
from studio.physics.ball import FlightModel, spin_components

FloatArray = npt.NDArray[np.float64]


def corrected(model: FlightModel, v: FloatArray, w: FloatArray, lag_xy: float, lag_z: float) -> FloatArray:
    """Velocity at the event from one lagging by ``lag_xy`` horizontally and ``lag_z`` vertically [s]."""
    a = model.acceleration(np.zeros_like(v), v, w)
    return v - a * np.array([lag_xy, lag_xy, lag_z])


def landing(x: FloatArray, flights: fc.Flights, base: FlightModel, *, check_net: bool) -> fc.BatchLanding:
    """Fly the flights with C_D, lift_a, lift_b = x[:3] and lags x[3] (horizontal), x[4] (vertical)."""
    model = replace(base, drag_coefficient=x[0], lift_a=x[1], lift_b=x[2])
    v0 = corrected(model, flights.v0, flights.w0, x[3], x[4])
    net = ~flights.kind_mask("net") if check_net else False
    return fc.integrate_to_table(flights.p0, v0, flights.w0, model, check_net=net)


def residuals(x: FloatArray, flights: fc.Flights, base: FlightModel) -> FloatArray:
    """The project's fit residuals (landing x, y and TIME_WEIGHT x time) for per-component lags."""
    land = landing(x, flights, base, check_net=False)
    dp = np.nan_to_num(land.p[:, :2] - flights.p_end[:, :2], nan=1.0)
    dt = np.nan_to_num(land.t - (flights.t_end - flights.t0), nan=0.2)
    return np.concatenate([dp.ravel(), fc.TIME_WEIGHT * dt])


def fit(flights: fc.Flights, base: FlightModel, vertical_lag: float | None) -> tuple[FloatArray, float]:
    """Fit C_D, lift_a, lift_b and the lags (the vertical one fixed when given); (x, cost)."""
    x0 = np.array([base.drag_coefficient, base.lift_a, base.lift_b, fc.VELOCITY_LAG, fc.VELOCITY_LAG])
    lo, hi = np.array([0.1, 0.01, 0.0, -0.05, -0.05]), np.array([1.5, 10.0, 20.0, 0.1, 0.1])
    if vertical_lag is not None:
        x0[4], lo[4], hi[4] = vertical_lag, vertical_lag - 1e-9, vertical_lag + 1e-9
    sol = least_squares(
        residuals, x0, args=(flights, base), bounds=(lo, hi), loss="soft_l1", f_scale=fc.FIT_SCALE,
        diff_step=1e-3, x_scale=[0.1, 0.1, 0.5, 0.01, 0.01],
    )  # fmt: skip
    return sol.x, float(sol.cost)


def fit_row(name: str, x: FloatArray, cost: float, flights: fc.Flights, base: FlightModel) -> str:
    """One markdown row: parameters, cost, per-kind landing median, time error and false nets."""
    land = landing(x, flights, base, check_net=True)
    err = np.linalg.norm(land.p[:, :2] - flights.p_end[:, :2], axis=1)
    terr = land.t - (flights.t_end - flights.t0)
    cells = []
    for kind in fc.FIT_KINDS:
        m = flights.landed & flights.kind_mask(kind) & np.isfinite(err)
        cells.append(f"{1e3 * np.median(err[m]):.0f} mm, {1e3 * np.median(terr[m]):+.0f} ms")
    false_net = int(np.sum(land.net & flights.landed & ~flights.measured_net & ~flights.kind_mask("net")))
    params = f"{x[0]:.3f} | {x[1]:.3f} | {x[2]:.2f} | {1e3 * x[3]:.1f} | {1e3 * x[4]:.1f}"
    return f"| {name} | {params} | {cost:.2f} | " + " | ".join(cells) + f" | {false_net} |"


def bounce_ratios(flights: fc.Flights) -> list[str]:
    """Rows: post-bounce vertical speed / predicted incoming, lag-corrected and raw, by bins."""
    rep = fc.replay(flights, FlightModel())
    ok = np.isfinite(rep.v_in[:, 0]) & np.isfinite(flights.v_after[:, 0]) & flights.landed
    vin, win = rep.v_in[ok], rep.w_in[ok]
    corr = -rep.v_after[ok, 2] / vin[:, 2]
    raw = -flights.v_after[ok, 2] / vin[:, 2]
    tb = spin_components(vin, win)[0]
    rows = [f"all {ok.sum()} bounces: {np.median(corr):.3f} / {np.median(raw):.3f}"]
    for name, q in (("incoming v_z [m/s]", -vin[:, 2]), ("incoming |v_xy| [m/s]", np.hypot(vin[:, 0], vin[:, 1])),
                    ("incoming top/back spin [rad/s]", tb)):  # fmt: skip
        edges = np.percentile(q, [0, 20, 40, 60, 80, 100])
        cells = []
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            m = (q >= a) & (q <= b)
            cells.append(f"[{a:.1f}, {b:.1f}]: {np.median(corr[m]):.3f} / {np.median(raw[m]):.3f}")
        rows.append(f"{name} quintiles: " + "; ".join(cells))
    for kind in fc.FIT_KINDS:
        m = flights.kind_mask(kind)[ok]
        rows.append(f"{kind} ({m.sum()}): {np.median(corr[m]):.3f} / {np.median(raw[m]):.3f}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--match", default=None, help="Ace match CSV (default: the shared dev file)")
    args = parser.parse_args()
    flights = fc.match_flights(fc.load_match_events(args.match))
    use = flights.subset(flights.landed & flights.kind_mask(*fc.FIT_KINDS))
    base = replace(FlightModel(), spin_decay=fc.spin_decay_from_bounces(use))
    print("| fit | C_D | lift_a | lift_b | lag xy [ms] | lag z [ms] | cost | serve | serve_bounce | rally | false nets |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    shipped = FlightModel()
    x = np.array([shipped.drag_coefficient, shipped.lift_a, shipped.lift_b, fc.VELOCITY_LAG, fc.VELOCITY_LAG])
    print(fit_row("shipped (one lag)", x, 0.5 * float(np.sum(_soft_l1(residuals(x, use, base)))), flights, base))
    for name, vertical in (("lags per component, free", None), ("vertical lag fixed at 0", 0.0)):
        x, cost = fit(use, base, vertical)
        print(fit_row(name, x, cost, flights, base), flush=True)
    print("\npost-bounce v_z / predicted incoming -v_z (median; lag-corrected / raw):")
    for row in bounce_ratios(flights):
        print("-", row)


def _soft_l1(r: FloatArray) -> FloatArray:
    """scipy's soft-L1 loss rho(r) scaled back to m^2 (cost = 0.5 sum rho)."""
    z = (r / fc.FIT_SCALE) ** 2
    return fc.FIT_SCALE**2 * 2.0 * (np.sqrt(1.0 + z) - 1.0)


if __name__ == "__main__":
    main()
