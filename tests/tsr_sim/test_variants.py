"""Each plant variant against an independent computation (solve_ivp on equations written out
here, or a closed form), and every variant at its off setting against the nominal plant."""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from tsr_sim import dynamics
from tsr_sim.units import Scale

from tsr_sim import variants
from tsr_sim.plant import config_from_parameters, Plant, plant_parameters

H = dynamics.PAPER_STEP
START = np.array([0.1, -0.05, -0.5, 0.2])


def run_open_loop(variant, x0, commands):
    """[x, actuator, anomaly] after the commands, the actuator starting at rest on the first."""
    state = np.r_[x0, commands[0], variant.initial_anomaly]
    for command in commands:
        state = variants.step(variant, state, command)
    return state


def commands(count=300, seed=3):
    return np.random.default_rng(seed).uniform(1.0, 4.5, count)


def test_default_variant_is_the_nominal_plant():
    """...to the last bit: the variants step the plant's own equations and RK4."""
    sequence = commands()
    state = run_open_loop(variants.PlantVariant(), START, sequence)
    x = START.copy()
    for command in sequence:
        x = dynamics.planar_step(x, command, H, 10)
    np.testing.assert_array_equal(state[:4], x)
    x = START.copy()
    for command in sequence:
        x = dynamics.rk4_step(x, command, H, 10)
    np.testing.assert_allclose(state[:4], x, rtol=0.0, atol=1e-12)


def test_the_variants_hold_no_equations_or_integrator_of_their_own():
    """One definition of the plant (`dynamics.planar_rates`, `dynamics.rk4`): the variants'
    module neither writes the equations of motion again nor integrates."""
    import inspect
    source = inspect.getsource(variants)
    for copy in ('3.0 * ', 'cos_t * cos_t', 'k1 =', 'k4 =', '/ 6.0'):
        assert copy not in source, copy
    assert 'dynamics.planar_rates(' in source and 'dynamics.rk4(' in source


def test_vanishing_eccentricity_reduces_to_the_nominal_plant():
    sequence = commands(200)
    nominal = run_open_loop(variants.PlantVariant(), START, sequence)
    nearly_circular = run_open_loop(variants.PlantVariant(eccentricity=1e-12,
                                                          initial_anomaly=0.7), START, sequence)
    np.testing.assert_allclose(nearly_circular[:4], nominal[:4], atol=1e-10)
    assert not np.allclose(run_open_loop(variants.PlantVariant(eccentricity=0.01), START,
                                         sequence)[:4], nominal[:4], atol=1e-4)


def test_eccentric_orbit_matches_the_true_anomaly_form():
    """The standard form with nu as independent variable (Modi & Misra; Kumar 2006):
    theta°° = 2 (1 + theta°) [e sin nu / (1 + e cos nu) - l° / l] - 3 sin cos / (1 + e cos nu)
    l°° = 2 e sin nu / (1 + e cos nu) l° + l [(1 + theta°)^2 + (3 cos^2 - 1) / (1 + e cos nu)]
          - u (1 - e^2)^3 / (1 + e cos nu)^4,   tau° = (1 - e^2)^(3/2) / (1 + e cos nu)^2."""
    e, nu0, u, samples = 0.05, 0.3, 2.5, 300
    variant = variants.PlantVariant(eccentricity=e, initial_anomaly=nu0)
    final = run_open_loop(variant, START, np.full(samples, u))
    nu_end = final[-1]

    def anomaly_rate(nu):   # d nu / d tau
        return (1.0 + e * math.cos(nu)) ** 2 / (1.0 - e * e) ** 1.5

    def rhs(nu, s):
        theta, theta_d, length, length_d, _ = s
        ecos = 1.0 + e * math.cos(nu)
        esin = e * math.sin(nu) / ecos
        theta_dd = (2.0 * (1.0 + theta_d) * (esin - length_d / length)
                    - 3.0 * math.sin(theta) * math.cos(theta) / ecos)
        length_dd = (2.0 * esin * length_d
                     + length * ((1.0 + theta_d) ** 2 + (3.0 * math.cos(theta) ** 2 - 1.0) / ecos)
                     - u * (1.0 - e * e) ** 3 / ecos ** 4)
        return [theta_d, theta_dd, length_d, length_dd, 1.0 / anomaly_rate(nu)]

    rate0 = anomaly_rate(nu0)
    s0 = [START[0], START[1] / rate0, START[2] + 1.0, START[3] / rate0, 0.0]
    sol = solve_ivp(rhs, (nu0, nu_end), s0, method='DOP853', rtol=1e-12, atol=1e-12)
    theta, theta_d, length, length_d, tau = sol.y[:, -1]
    rate = anomaly_rate(nu_end)
    np.testing.assert_allclose(tau, samples * H, atol=1e-9)
    np.testing.assert_allclose(final[:4], [theta, theta_d * rate, length - 1.0, length_d * rate],
                               atol=1e-8)


def actuator_closed_form(variant, x0, sequence):
    """solve_ivp on the plant with the actuator's exact first-order response in each sample:
    a(s) = u_k + (a_k - u_k) exp(-s / T_lag), felt u = ratio * max(0, g a + b)."""
    x, actuator = np.asarray(x0, dtype=float), sequence[0]
    for command in sequence:
        a_start = actuator

        def rhs(s, state, a_start=a_start, command=command):
            a = command + (a_start - command) * math.exp(-s / variant.actuator_lag)
            felt = max(0.0, variant.actuator_gain * a + variant.actuator_bias)
            return dynamics.derivative(state, felt)

        x = solve_ivp(rhs, (0.0, H), x, method='DOP853', rtol=1e-12, atol=1e-13).y[:, -1]
        actuator = command + (a_start - command) * math.exp(-H / variant.actuator_lag)
    return x, actuator


# the negative bias clips the felt tension at 0 while the command is 0: RK4 steps over that
# kink are locally first order, hence the looser tolerance
@pytest.mark.parametrize('gain, bias, lag, tolerance', [(0.8, 0.0, 0.05, 1e-9),
                                                        (1.2, -0.3, 0.05, 2e-5),
                                                        (1.0, 0.2, 0.3, 1e-9)])
def test_actuator_gain_bias_and_lag_match_the_exact_actuator_response(gain, bias, lag, tolerance):
    variant = variants.PlantVariant(actuator_gain=gain, actuator_bias=bias, actuator_lag=lag)
    sequence = np.r_[commands(60), np.zeros(20), commands(40, seed=4)]
    state = run_open_loop(variant, START, sequence)
    x, actuator = actuator_closed_form(variant, START, sequence)
    np.testing.assert_allclose(state[:4], x, atol=tolerance)
    np.testing.assert_allclose(state[4], actuator, atol=1e-12)


def test_gain_without_lag_is_the_nominal_plant_under_a_scaled_command():
    sequence = commands(150)
    state = run_open_loop(variants.PlantVariant(actuator_gain=0.9, actuator_bias=0.1), START,
                          sequence)
    nominal = run_open_loop(variants.PlantVariant(), START, 0.9 * sequence + 0.1)
    np.testing.assert_allclose(state[:4], nominal[:4], atol=1e-13)


def test_a_heavier_robot_feels_the_command_scaled_down():
    """The simulator's mass is the true mass: a command converted with 20 kg is felt by 25 kg as
    u 20 / 25, as an actuator gain of 0.8 would make it."""
    sequence = commands(150)
    # Open loop past the tumbling bound: the equations, not the halt, are checked here.
    heavy = Plant(config_from_parameters({'initial_state': START.tolist(), 'max_swing': 100.0},
                                         Scale(mass=25.0)))
    as_gain = run_open_loop(variants.PlantVariant(actuator_gain=0.8), START, sequence)
    assumed = Scale(mass=20.0)
    for command in sequence:
        heavy.advance(assumed.u_to_tension(command))
    np.testing.assert_allclose(heavy.state, as_gain[:4], atol=1e-13)


def test_plant_files_set_the_variant_and_the_bias_is_in_newtons():
    weak = config_from_parameters(plant_parameters('actuator_weak'), Scale())
    assert (weak.variant.actuator_gain, weak.variant.actuator_lag) == (0.9, 0.05)
    unit = Scale().tension_unit   # m Omega^2 L = 2.787 N for 20 kg
    biased = config_from_parameters({'actuator_bias': unit}, Scale())
    assert biased.variant.actuator_bias == pytest.approx(1.0)
    assert config_from_parameters(plant_parameters('nominal'), Scale()).variant.nominal
    with pytest.raises(ValueError, match="no plant variant 'bogus'"):
        plant_parameters('bogus')


def test_a_plant_file_with_a_name_that_is_not_a_plant_parameter_is_refused(tmp_path):
    """ROS would drop the misspelt name and simulate the nominal actuator without a word; a
    simulator setting that is not the plant's (deploy sets those) is refused too, so a plant
    file means the same to `deploy --plant` and to `closed_loop(plant=...)`."""
    path = tmp_path / 'weak.yaml'
    for content, message in (
            ('actuator_gian: 0.9', "'actuator_gian' is not a plant parameter "
             "(did you mean 'actuator_gain'?)"),
            ('rate_hz: 50.0', "'rate_hz' is not a plant parameter"),
            ('1: 2\n    bogus: 3', "1 is not a plant parameter")):
        path.write_text(f'/**:\n  ros__parameters:\n    {content}\n')
        with pytest.raises(ValueError) as refused:
            plant_parameters(str(path))
        assert str(refused.value) == f'{path}: {message}'
    path.write_text('/**:\n  ros__parameters:\n    actuator_gain: 0.9\n    mass: 25.0\n'
                    '    max_tension: 20.0\n    plant: weak\n')
    weak = config_from_parameters(plant_parameters(str(path)), Scale())
    assert (weak.variant.actuator_gain, weak.scale.mass, weak.max_tension) == (0.9, 25.0, 20.0)


def test_out_of_plane_matches_the_3d_equations():
    """Williams 2008 3-D model, written out: the controller still sees 4 states."""
    u, samples, beta = 2.8, 200, (0.2, 0.05)

    def rhs(_, s):
        theta, w, x3, v, b, b_d = s
        w, length = w + 1.0, x3 + 1.0
        gravity = w * w + 3.0 * math.cos(theta) ** 2
        return [s[1], 2.0 * w * (b_d * math.tan(b) - v / length)
                - 3.0 * math.sin(theta) * math.cos(theta),
                v, length * (b_d ** 2 + gravity * math.cos(b) ** 2 - 1.0) - u,
                b_d, -2.0 * v / length * b_d - gravity * math.sin(b) * math.cos(b)]

    plant = Plant(config_from_parameters({'initial_state': START.tolist(), 'out_of_plane': True,
                                          'initial_beta': list(beta), 'max_swing': 100.0},
                                         Scale()))
    for _ in range(samples):
        plant.advance(Scale().u_to_tension(u))
    expected = solve_ivp(rhs, (0.0, samples * H), np.r_[START, beta], method='DOP853',
                         rtol=1e-12, atol=1e-12).y[:, -1]
    np.testing.assert_allclose(plant.state, expected, atol=1e-9)


def test_the_simulated_plant_with_a_lagging_actuator_matches_the_variant_step():
    """Plant (what the node and the ROS-free loop run) against variants.step alone."""
    sequence = commands(100)
    config = config_from_parameters({'initial_state': START.tolist(),
                                     **plant_parameters('actuator_weak')}, Scale())
    plant = Plant(config)
    for command in sequence:
        plant.advance(Scale().u_to_tension(command))
    np.testing.assert_allclose(plant.state, run_open_loop(config.variant, START, sequence)[:4],
                               atol=1e-12)
