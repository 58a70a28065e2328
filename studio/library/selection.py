"""Real-world serve selection: spin clusters and the next serve of a match.

The paper (section "Real-world serve selection"): serves are clustered by spin direction
and magnitude (topspin, backspin, sidespin, ...) and the strategy picks the least-used
serve from a cluster different from the previous one, so consecutive serves are
spin-distinct and no serve is repeated more than needed.

Cluster of a serve = direction / magnitude band of the ball's spin at the net crossing
(the index entry's ``net`` state, world frame, velocity-aligned components of
:func:`studio.physics.ball.spin_components`):

- direction: :func:`spin_cluster` (``topspin``, ``backspin``,
  ``sidespin``, ``mixed``, ``no spin``, ``no net crossing``);
- magnitude band: ``light`` when |ω| at the net is below
  :attr:`SelectionParams.heavy_spin`, ``heavy`` otherwise, e.g. ``"topspin/heavy"``.
  ``no spin`` and ``no net crossing`` carry no band.

Selection rule (:func:`select_next`), over the legal serves only:

1. candidates are the legal serves whose cluster differs from the previous serve's;
2. if there are none (one cluster only), the legal serves other than the previous one;
3. if there are none either (a single legal serve), that serve;
4. among the candidates the least used (``usage`` mapping, else the entry's
   ``usage.used`` counter, 0 when absent); ties go to ``rng`` (uniform) when given, else
   to the higher predicted reward, then the smaller id (deterministic).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from studio.errors import InvalidInputError
from studio.library.store import LibraryEntry

SPIN_DOMINANCE = 0.8
"""A spin component is dominant when its magnitude is at least this fraction of the total
spin |ω| at the net (0.8: the spin axis lies within ~37° of that component's axis).
Engineering choice for a readable colouring, not from the paper."""
MIN_SPIN = 10.0
"""Below this total spin [rad/s] a serve is classed ``"no spin"`` (a served ball with
less than ~1.6 rev/s is practically spinless)."""


def spin_cluster(
    topspin: float, sidespin: float, cork: float = 0.0, *, dominance: float = SPIN_DOMINANCE, min_spin: float = MIN_SPIN
) -> str:
    """Spin cluster of a ball by the dominant component of its spin at the net crossing.

    Args:
        topspin: top/back component ω·e_y [rad/s] (> 0 topspin, < 0 backspin).
        sidespin: side component ω·e_z [rad/s].
        cork: cork component ω·e_x [rad/s] (counts in the total only).
        dominance: fraction of |ω| a component needs to be dominant (see ``SPIN_DOMINANCE``).
        min_spin: below this |ω| [rad/s] the result is ``"no spin"``.

    Returns:
        ``"topspin"``, ``"backspin"``, ``"sidespin"``, ``"mixed"`` (no dominant component)
        or ``"no spin"``; ``"no net crossing"`` when a component is not finite.
    """
    values = (float(topspin), float(sidespin), float(cork))
    if not all(math.isfinite(x) for x in values):
        return "no net crossing"
    total = math.sqrt(sum(x * x for x in values))
    if total < min_spin:
        return "no spin"
    if abs(values[0]) >= dominance * total:
        return "topspin" if values[0] > 0 else "backspin"
    if abs(values[1]) >= dominance * total:
        return "sidespin"
    return "mixed"


@dataclass(frozen=True)
class NetState:
    """Ball at the net crossing, as stored in a library entry (world frame)."""

    speed_h: float
    """Horizontal speed sqrt(v_x² + v_y²) [m/s]."""
    spin: float
    """Total spin |ω| [rad/s]."""
    topspin: float
    """Top/back spin component [rad/s] (> 0 topspin)."""
    sidespin: float
    """Side spin component [rad/s]."""
    cork: float
    """Cork spin component [rad/s]."""
    clearance: float
    """Height of the ball's bottom above the net top [m] (NaN if not stored)."""


def net_state(entry: dict[str, Any]) -> NetState | None:
    """The ball state at the net crossing of an index entry, None if absent or malformed."""
    net = entry.get("net")
    if not isinstance(net, dict):
        return None
    try:
        v = np.asarray(net["v"], dtype=float)
        w = np.asarray(net["w"], dtype=float)
        tb, ss, ck = (float(net[k]) for k in ("topspin", "sidespin", "cork"))
        clearance = float(net["clearance"]) if net.get("clearance") is not None else math.nan
    except (KeyError, TypeError, ValueError):
        return None
    if v.shape != (3,) or w.shape != (3,) or not (np.all(np.isfinite(v)) and np.all(np.isfinite(w))):
        return None
    return NetState(
        speed_h=float(np.hypot(v[0], v[1])),
        spin=float(np.linalg.norm(w)),
        topspin=tb,
        sidespin=ss,
        cork=ck,
        clearance=clearance,
    )


def entry_cluster(entry: dict[str, Any]) -> str:
    """Spin cluster of an index entry (``"no net crossing"`` when it has no net state)."""
    net = net_state(entry)
    return "no net crossing" if net is None else spin_cluster(net.topspin, net.sidespin, net.cork)


HEAVY_SPIN = 150.0
"""Total spin at the net crossing [rad/s] from which a serve is ``heavy`` (~24 rev/s).
Engineering choice between the example serves (~80-200 rad/s at the net) and the paper's
trained serves (topspin task 218-263 rad/s on average, up to 550 rad/s); not from the
paper, which does not give its magnitude bands."""


@dataclass(frozen=True)
class SelectionParams:
    """Thresholds of the spin clusters."""

    heavy_spin: float = HEAVY_SPIN
    """|ω| at the net [rad/s] from which the magnitude band is ``heavy`` (else ``light``)."""
    dominance: float = SPIN_DOMINANCE
    """Fraction of |ω| a component needs to name the direction (see :data:`SPIN_DOMINANCE`)."""
    min_spin: float = MIN_SPIN
    """Below this |ω| [rad/s] the cluster is ``no spin``."""


def serve_cluster(entry: LibraryEntry | Mapping[str, Any], *, params: SelectionParams = SelectionParams()) -> str:
    """Spin cluster ``"<direction>/<band>"`` of a library entry (or its ``data`` dict).

    ``"no net crossing"`` when the entry has no valid net state, ``"no spin"`` below
    ``params.min_spin``.
    """
    data = entry.data if isinstance(entry, LibraryEntry) else entry
    net = net_state(dict(data))
    if net is None:
        return "no net crossing"
    direction = spin_cluster(net.topspin, net.sidespin, net.cork, dominance=params.dominance, min_spin=params.min_spin)
    if direction in ("no spin", "no net crossing"):
        return direction
    magnitude = math.sqrt(net.topspin**2 + net.sidespin**2 + net.cork**2)
    return f"{direction}/{'heavy' if magnitude >= params.heavy_spin else 'light'}"


def usage_count(entry: LibraryEntry) -> int:
    """The entry's ``usage.used`` counter (0 when the entry has no usage record)."""
    usage = entry.data.get("usage")
    return int(usage.get("used", 0)) if isinstance(usage, dict) else 0


def select_next(
    entries: Sequence[LibraryEntry],
    previous_id: str | None,
    *,
    usage: Mapping[str, int] | None = None,
    rng: np.random.Generator | None = None,
    params: SelectionParams = SelectionParams(),
) -> LibraryEntry:
    """The next serve: the least-used legal serve from a cluster other than the previous one's.

    Args:
        entries: the library's entries (illegal ones are never selected).
        previous_id: id of the serve executed last, None at the start of a match.
        usage: times each serve id was used (default: the entries' ``usage.used``);
            ids absent from the mapping count 0.
        rng: breaks ties uniformly at random when given; else ties go to the higher
            reward, then the smaller id.
        params: cluster thresholds.

    Raises:
        InvalidInputError: no legal serve, or ``previous_id`` not in ``entries``.
    """
    legal = [e for e in entries if e.data["legal"] is True]
    if not legal:
        raise InvalidInputError(f"no legal serve to select among {len(entries)} serves")
    clusters = {e.id: serve_cluster(e, params=params) for e in entries}
    candidates = legal
    if previous_id is not None:
        if previous_id not in clusters:
            raise InvalidInputError(f"previous serve {previous_id!r} is not in the library")
        other_cluster = [e for e in legal if clusters[e.id] != clusters[previous_id]]
        other_serve = [e for e in legal if e.id != previous_id]
        candidates = other_cluster or other_serve or legal

    def used(e: LibraryEntry) -> int:
        return int(usage.get(e.id, 0)) if usage is not None else usage_count(e)

    least = min(used(e) for e in candidates)
    tied = [e for e in candidates if used(e) == least]
    if rng is not None:
        return tied[int(rng.integers(len(tied)))]
    return min(tied, key=lambda e: (-float(e.data["reward"]), e.id))
