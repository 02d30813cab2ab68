"""koopman_nmpc: the relifted learned model planned over the physics NMPC's grid, one QP a step."""

import numpy as np
import pytest
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.control.koopman_nmpc import KoopmanNmpc
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, run_figures


def test_the_condensed_gains_predict_the_relifted_rollout_to_first_order():
    law = KoopmanNmpc(horizon=1.0)
    x = dynamics.PAPER_INITIAL_STATE
    plan, nodes = law.lqr_plan(x)
    np.testing.assert_array_equal(law.rollout(x, plan), nodes)
    gains = law.node_gains(nodes, plan)
    du = np.random.default_rng(0).normal(size=len(plan))
    errors = []
    for scale in (1e-2, 5e-3):
        moved = law.rollout(x, plan + scale * du)[1:]
        errors.append(np.abs(moved - (nodes[1:] + scale * gains @ du)).max())
    # A second-order remainder: halving the step quarters it (a wrong gain would halve it),
    # and it is small against the first-order move itself.
    assert errors[1] < 0.3 * errors[0]
    assert errors[0] < 0.05 * 1e-2 * np.abs(gains @ du).max()


def test_clarabel_solves_the_qp_as_quadprog_does():
    """The default solver (interior point) against quadprog's exact active-set solution of the
    same QP, along the first plans from the paper's start: the planned tension changes agree
    to 1e-4 (measured 4e-5 on 220 QPs, bench_qp.py --law koopman_nmpc)."""
    from tsr_koopman_ctrl.control.koopman_nmpc import solve_clarabel, solve_quadprog
    law = KoopmanNmpc()
    x = dynamics.PAPER_INITIAL_STATE
    plan, nodes = law.lqr_plan(x)
    for _ in range(3):
        problem = law.qp_problem(nodes, plan)
        exact, interior = solve_quadprog(*problem), solve_clarabel(*problem)
        change = exact[:len(plan)]
        assert np.abs(change).max() > 1e-2      # the plan moves: not a trivial QP
        np.testing.assert_allclose(interior[:len(plan)], change, atol=1e-4)
        plan = np.clip(plan + change, 0.0, law.u_max)
        nodes = law.rollout(x, plan)


def test_the_warm_start_stays_near_the_path_the_last_plan_predicted():
    """The length is unstable open loop: the last plan merely shifted by h predicts a length
    overshoot of 0.42..0.47 where the plan itself predicted 0.008 (20 steps from
    (0, 0, -0.95, 1.0) on the plant); flown with the LQR gain on the deviation, 0.04."""
    from tsr_koopman_ctrl.control.physics_nmpc import shift_plan
    law = KoopmanNmpc()
    x = np.array([0.0, 0.0, -0.95, 1.0])
    for _ in range(20):
        x = dynamics.step(x, law.compute(x), dynamics.PAPER_STEP, substeps=10)
    planned = law.plan_nodes[:, dynamics.LENGTH_OFFSET].max()
    _, warm = law.shifted_plan(x, law.h)
    plain = law.rollout(x, shift_plan(law.plan, law.starts, law.durations, law.h))
    assert planned < 0.02
    assert warm[:, dynamics.LENGTH_OFFSET].max() < planned + 0.05
    assert plain[:, dynamics.LENGTH_OFFSET].max() > planned + 0.2    # what the gain is for
    # warm_start='shift' is the plain shifted plan.
    shifting = KoopmanNmpc(warm_start='shift')
    shifting.plan, shifting.plan_nodes = law.plan, law.plan_nodes
    np.testing.assert_array_equal(shifting.shifted_plan(x, law.h)[1], plain)


@pytest.mark.parametrize('start', COMPARISON_STARTS)
def test_it_deploys_on_the_dynamics_module_within_1_3x_the_frontier(start):
    """Bare (no observer) on the nominal plant, 400 steps, the shipped koopman_retrieval: into
    the 1% zone within 1.3x the minimum time at the run's own swing (issue 14's target;
    measured 1.02, 0.98, 1.17, 1.14 from the four comparison starts; 1.03 and 1.19 from the
    first and third with the plain shifted warm start; on koopman_default, which never saw the
    tether reeled in, 1.05 and 1.54), swing within its 0.8 bound, no QP failure."""
    law = make_controller('koopman_nmpc', observer={'disturbance': 'none'})
    states, tensions = closed_loop(law, start, 400)
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions,
                          start=start)
    assert figures['frontier_ratio'] is not None and figures['frontier_ratio'] <= 1.3
    assert figures['swing'] <= 0.81 and law.fallbacks == 0


def test_it_holds_a_swing_bound_of_0_4_on_the_plant():
    """theta_max 0.4 from (0, 0, -0.7, 0), bare, 400 steps: the swing stays under the bound on
    the plant (not only at the plan's nodes) and the settle time within 1.1x the 0.4-rad
    frontier (measured: swing 0.397, 3.32 tau, 1.02x)."""
    start = (0.0, 0.0, -0.7, 0.0)
    law = make_controller('koopman_nmpc', theta_max=0.4, observer={'disturbance': 'none'})
    states, tensions = closed_loop(law, start, 400)
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions,
                          start=start)
    assert figures['swing'] <= 0.4
    assert figures['frontier_ratio'] is not None and figures['frontier_ratio'] <= 1.1


def test_an_interval_off_the_step_grid_is_one_clear_line():
    with pytest.raises(ValueError, match='koopman_nmpc.interval must be a multiple of h'):
        KoopmanNmpc(interval=0.015)
