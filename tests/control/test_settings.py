"""Each law's settings: declared once, checked once, parsed from the command line."""

import dataclasses

import numpy as np
import pytest

from tsr_koopman_ctrl.control import CONTROLLERS, KoopmanMpc, LinearisedLqr, make_controller
from tsr_koopman_ctrl.control.law import planar_state
from tsr_koopman_ctrl.control.registry import settings_sections
from tsr_koopman_ctrl.control.settings import parse_value, unknown_setting_names


def test_every_law_has_described_settings():
    for name, law in CONTROLLERS.items():
        assert law.name == name and law.Settings.law == name
        for field in dataclasses.fields(law.Settings):
            assert field.metadata['description'], f'{name}.{field.name} has no description'


@pytest.mark.parametrize('law, overrides, message', [
    ('koopman_mpc', {'horizon': 0}, 'koopman_mpc.horizon must be >= 1, got 0'),
    ('koopman_mpc', {'terminal': 'stage'}, "koopman_mpc.terminal must be one of"),
    ('linear_lqr', {'q': (1.0, 2.0)}, 'linear_lqr.q needs 4 numbers'),
    ('linear_lqr', {'r': float('nan')}, 'linear_lqr.r must be finite'),
    ('linear_lqr', {'bogus': 1}, "linear_lqr has no setting 'bogus'"),
    ('koopman_mpc', {'horizon': '5'}, "koopman_mpc.horizon must be an integer, got '5'"),
    ('koopman_mpc', {'horizon': 5.0}, 'koopman_mpc.horizon must be an integer, got 5.0'),
    ('linear_lqr', {'r': '1'}, "linear_lqr.r must be a number, got '1'"),
    ('linear_lqr', {'q': (1.0, True, 1.0, 1.0)}, 'linear_lqr.q must be 4 numbers'),
    ('physics_nmpc', {'trust': True}, 'physics_nmpc.trust must be a number, got True'),
    ('koopman_nmpc', {'precision': 'float16'}, 'koopman_nmpc.precision must be one of')])
def test_bad_settings_are_one_line_naming_the_setting(law, overrides, message):
    with pytest.raises(ValueError, match=message.replace('(', r'\(')) as error:
        make_controller(law, **overrides)
    assert '\n' not in str(error.value)


def test_a_parameter_naming_no_setting_of_its_section_is_found():
    sections = settings_sections()
    given = {'koopman_mpc.horizn', 'koopman_mpc.horizon', 'linear_lqr.q', 'linear_lqr.zeta',
             'observer.disturbnce', 'rate_hz', 'tsr_sim.anything', 'controller'}
    assert unknown_setting_names(given, sections) == [
        "parameter 'koopman_mpc.horizn': koopman_mpc has no setting 'horizn' (did you mean "
        "'koopman_mpc.horizon'?)",
        "parameter 'linear_lqr.zeta': linear_lqr has no setting 'zeta'",
        "parameter 'observer.disturbnce': observer has no setting 'disturbnce' (did you mean "
        "'observer.disturbance'?)"]
    every_setting = {f'{name}.{field.name}' for name, cls in sections.items()
                     for field in dataclasses.fields(cls)}
    assert unknown_setting_names(every_setting, sections) == []


def test_settings_reach_the_law_and_the_loop_limits_stay_apart():
    law = make_controller('linear_lqr', q=[10.0, 1.0, 10.0, 1.0], r=0.1, u_max=4.0)
    assert law.settings.q == (10.0, 1.0, 10.0, 1.0) and law.u_max == 4.0
    # A heavier weight on l - 1 than Q = I, R = 1: a larger gain on it.
    assert abs(law.law.gain[2]) > abs(LinearisedLqr(q=(1.0,) * 4, r=1.0).gain[2])
    mpc = KoopmanMpc(horizon=3, u_max=4.0)
    assert mpc.horizon == 3 and mpc.input_range[1] == pytest.approx(
        float(mpc.model.input_map(4.0)))


def test_command_line_values_take_the_setting_type():
    settings = CONTROLLERS['koopman_mpc'].Settings
    assert parse_value(settings, 'horizon', '8') == 8
    assert parse_value(settings, 'q', '1,2,3,4') == (1.0, 2.0, 3.0, 4.0)
    assert parse_value(settings, 'terminal', 'riccati') == 'riccati'
    with pytest.raises(ValueError, match="koopman_mpc.horizon: cannot read 'five' as int"):
        parse_value(settings, 'horizon', 'five')


def test_assignments_parse_into_sections_once_for_deploy_and_the_lab():
    """SECTION.SETTING=VALUE: one parser (control.registry, over control.settings) for
    deploy's --set and the lab's."""
    from tsr_koopman_ctrl.control.registry import parse_assignments
    assert parse_assignments(['koopman_mpc.horizon=8', 'observer.disturbance=none',
                              'koopman_mpc.q=1,2,3,4', 'supervisor.fallback=none']) == {
        'koopman_mpc': {'horizon': 8, 'q': (1.0, 2.0, 3.0, 4.0)},
        'observer': {'disturbance': 'none'}, 'supervisor': {'fallback': 'none'}}
    for bad, message in (('koopman_mpc.horizon', 'SECTION.SETTING=VALUE'),
                         ('horizon=8', 'SECTION.SETTING=VALUE'),
                         ('pid.gain=1', "unknown settings section 'pid': a law "
                                        r"\(fractional_pd, .*\) or one of excitation, "
                                        'observer, safety_filter, supervisor'),
                         ('koopman_mpc.horizn=8', "no setting 'horizn'"),
                         ('koopman_mpc.horizon=five', "cannot read 'five'")):
        with pytest.raises(ValueError, match=message):
            parse_assignments([bad])
    mpc = CONTROLLERS['koopman_mpc'].Settings        # the caller's own sections
    assert parse_assignments(['mine.horizon=3'], lambda section: mpc) == {
        'mine': {'horizon': 3}}


@pytest.mark.parametrize('steps', [-5, 2.5, True])
def test_closed_loop_refuses_a_step_count_that_is_not_a_whole_number(steps):
    from tsr_koopman_ctrl.control import closed_loop
    with pytest.raises(ValueError, match='closed_loop: steps must be an integer >= 0'):
        closed_loop(make_controller('linear_lqr'), [0.0, 0.0, -0.99, 0.5], steps)


def test_closed_loop_takes_a_plant_variant_by_name():
    from tsr_koopman_ctrl.control import closed_loop
    from tsr_sim.plant import plant_parameters
    law = make_controller('linear_lqr')
    by_name = closed_loop(law, [0.0, 0.0, -0.99, 0.5], 50, plant='actuator_weak')
    by_mapping = closed_loop(law, [0.0, 0.0, -0.99, 0.5], 50,
                             plant=plant_parameters('actuator_weak'))
    nominal = closed_loop(law, [0.0, 0.0, -0.99, 0.5], 50)
    np.testing.assert_array_equal(by_name[0], by_mapping[0])
    assert not np.array_equal(by_name[0], nominal[0])
    with pytest.raises(ValueError, match='closed_loop: plant must be a mapping'):
        closed_loop(law, [0.0, 0.0, -0.99, 0.5], 5, plant=[('mass', 2.0)])


@pytest.mark.parametrize('law', ['linear_lqr', 'fractional_pd', 'koopman_lqr', 'koopman_mpc'])
@pytest.mark.parametrize('observer', [None, {'disturbance': 'none'}])
@pytest.mark.parametrize('state, message', [
    ([0.0, 0.0, -0.99], 'a TSR state has 4 (planar) or 6 (3-D) components, got 3'),
    ([0.0, 0.0, -0.99, 0.5, 0.0], 'a TSR state has 4 (planar) or 6 (3-D) components, got 5'),
    ([[0.0, 0.0, -0.99, 0.5]], 'a TSR state is one vector of 4 or 6 components, got shape'),
    ([float('nan'), 0.0, -0.99, 0.5], 'is not finite: no tension for it')])
def test_a_bad_state_is_refused_and_leaves_the_law_as_it_was(law, observer, state, message):
    """A wrong vector gave a plausible tension (the offset-free wrapper cut it to 4 and its
    filter took 3); a NaN gave a finite one and every later command was NaN."""
    good = [0.0, 0.0, -0.99, 0.5]
    fresh, used = (make_controller(law, observer=observer) for _ in range(2))
    with pytest.raises(ValueError, match=message.replace('(', r'\(').replace(')', r'\)')):
        used.compute(state)
    assert [used.compute(good) for _ in range(3)] == [fresh.compute(good) for _ in range(3)]


@pytest.mark.filterwarnings('ignore:overflow encountered in reduce')
def test_a_state_whose_sum_overflows_is_still_finite():
    np.testing.assert_array_equal(planar_state([1e308, 1e308, 0.0, 0.0]), [1e308, 1e308, 0, 0])


@pytest.mark.filterwarnings('ignore:invalid value encountered')    # the NaN put in the filter
@pytest.mark.parametrize('law', ['linear_lqr', 'koopman_mpc'])
def test_a_diverged_observer_gives_no_tension_rather_than_an_exception(law):
    """The node answers a non-finite tension with NON_FINITE_OUTPUT and no command; an
    exception out of its callback would end the node."""
    controller = make_controller(law, supervisor='none', safety='none')
    controller.compute([0.0, 0.0, -0.99, 0.5])
    controller.observer.estimate[:] = np.nan
    assert np.isnan(controller.compute([0.0, 0.0, -0.98, 0.5]))
