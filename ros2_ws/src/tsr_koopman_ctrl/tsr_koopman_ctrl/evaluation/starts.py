"""The initial states every comparison, sweep and test deploys from: declared once, here."""

from tsr_sim import dynamics

#: The paper's start (Section IV-D): l = 0.01, l' = 0.5.
PAPER_START = tuple(float(v) for v in dynamics.PAPER_INITIAL_STATE)

#: The comparison's starts: the paper's and three other initial lengths and deployment rates.
COMPARISON_STARTS = (PAPER_START, (0.0, 0.0, -0.9, 0.3), (0.0, 0.0, -0.95, 1.0),
                     (0.0, 0.0, -0.7, 0.0))

#: Starts the tuning never sees (lab/tune.py tunes on COMPARISON_STARTS): an initial swing and
#: swing rate, l0 from 0.01 to 0.5 and l'0 from 0 to 1.
HELD_OUT_STARTS = ((0.1, -0.1, -0.9, 0.5), (-0.2, 0.2, -0.6, 0.2), (0.15, 0.05, -0.99, 1.0),
                   (-0.1, -0.2, -0.5, 0.0), (0.05, 0.1, -0.8, 0.8))

#: Two more tuning starts with an initial swing and swing rate (`tune --starts swing` tunes on
#: COMPARISON_STARTS + these): the comparison starts all begin at rest in theta, the held-out
#: ones all do not. Not held-out starts, not in the comparison table's rows.
SWING_TUNING_STARTS = ((0.2, -0.1, -0.7, 0.1), (-0.1, 0.1, -0.95, 0.7))

#: Every start with a frontier row, in the frontier table's order (lab/frontier.py indexes it).
TABULATED_STARTS = COMPARISON_STARTS + HELD_OUT_STARTS + SWING_TUNING_STARTS
