"""The initial states every comparison, sweep and test deploys from: declared once, here."""

from tsr_sim import dynamics

#: The paper's start (Section IV-D): l = 0.01, l' = 0.5.
PAPER_START = tuple(float(v) for v in dynamics.PAPER_INITIAL_STATE)

#: The comparison's starts: the paper's and three other initial lengths and deployment rates.
COMPARISON_STARTS = (PAPER_START, (0.0, 0.0, -0.9, 0.3), (0.0, 0.0, -0.95, 1.0),
                     (0.0, 0.0, -0.7, 0.0))
