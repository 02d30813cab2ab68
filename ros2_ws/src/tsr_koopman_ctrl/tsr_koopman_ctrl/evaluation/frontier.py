"""The minimum-time deployment frontier a controller's settle time is divided by.

A controller that swings to max |theta| = s cannot deploy faster than the minimum-time solution
with |theta| <= s (docs/frontier.md). The table (frontier_table.json, next to this module) holds,
for every comparison, held-out and tuning start, the least time (tau) in which 0 <= u <= 5 brings
the plant to x = 0 under a grid of swing bounds, and the least swing the solver could reach,
as the lab's minimum-time solver (lab/min_time.py) computed it; `python -m lab.frontier`
recomputes it. This module only reads it (no casadi on the control or scoring path).
"""

import functools
import json
import math
import pathlib

import numpy as np

TABLE_PATH = pathlib.Path(__file__).with_name('frontier_table.json')


@functools.lru_cache(maxsize=None)
def load_table(path=TABLE_PATH):
    """The frontier table: {'provenance': {...}, 'starts': [{x0, u_max, rows, least_swing}]}."""
    return json.loads(pathlib.Path(path).read_text())


def start_key(start):
    # Rounded: a start read back from a bag or a numpy array still finds its row.
    return tuple(round(float(v), 9) for v in start)


def table_entry(start, table=None):
    """The table's entry for `start`, or None where the start is not tabulated."""
    table = load_table() if table is None else table
    key = start_key(start)
    return next((e for e in table['starts'] if start_key(e['x0']) == key), None)


def envelope(entry):
    """(swings, taus) of the entry's solved bounds, ascending in swing, as the lower envelope:
    T(s) = least T of any solved plan with swing <= s (a plan admissible at a tighter bound is
    admissible at s, so a worse local optimum at a looser bound never raises the frontier). The
    least-swing plan is left out: its T is one slow plan's, not a minimum."""
    points = sorted((r['swing'], r['T']) for r in entry['rows'] if r['success'])
    swings, taus = [], []
    for swing, tau in points:
        tau = min(tau, taus[-1]) if taus else tau
        if swings and swing <= swings[-1]:
            taus[-1] = tau   # same swing (a bound looser than the free optimum): keep the least
        else:
            swings.append(swing)
            taus.append(tau)
    return np.array(swings), np.array(taus)


def frontier_tau(start, swing):
    """Minimum deployment time (tau) from `start` within a swing max |theta| <= `swing`.

    None where the start is not tabulated, or where `swing` is below the least swing the
    solver reached from it (no admissible deployment known). At or above the unconstrained
    optimum's swing: that optimum's T. Between solved bounds: linear in the swing, an estimate
    (only the solved bounds are solver results; the true frontier may bend either way between
    them). Between the least swing and the tightest solved bound: that bound's T, a lower bound
    of the frontier there (the ratio to it over-states the gap). Every solved T is a local
    optimum, an upper bound of the true minimum.
    """
    if not math.isfinite(swing) or swing < 0.0:
        raise ValueError(f'frontier_tau: swing must be a finite angle >= 0 [rad], got {swing!r}')
    entry = table_entry(start)
    if entry is None:
        return None
    least = entry['least_swing']
    if least['success'] and swing < least['swing']:
        return None
    swings, taus = envelope(entry)
    if swings.size == 0:
        return None
    return float(np.interp(swing, swings, taus))
