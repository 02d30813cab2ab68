"""One parameter schema: the laws' settings, the plant's and the nodes' own parameters are
frozen dataclasses of `setting` fields (`tsr_sim.schema`); the tables, the command-line values
and the hints for an unknown name are derived from them (the nodes' parameters:
nodes/test_parameter_schemas.py)."""

import dataclasses

import pytest


def test_the_plant_parameters_are_a_frozen_dataclass_the_tables_derive_from():
    from tsr_sim import plant
    from tsr_sim.node_parameters import ScaleSettings, SimulatorNodeSettings
    for schema, table in ((plant.PlantSettings, plant.PLANT_PARAMETERS),
                          (SimulatorNodeSettings, plant.SIMULATOR_PARAMETERS)):
        assert dataclasses.is_dataclass(schema) and schema.__dataclass_params__.frozen
        assert dict(table) == {
            field.name: (list(field.default) if isinstance(field.default, tuple)
                         else field.default, field.metadata['description'],
                         field.metadata['low'], field.metadata['high'])
            for field in dataclasses.fields(schema)}
        with pytest.raises(TypeError):
            table['seed'] = (1, 'a seed', 0, 1)       # a view, read-only
    assert plant.SCALE_PARAMETERS == tuple(f.name for f in dataclasses.fields(ScaleSettings))
    with pytest.raises(ValueError, match='substeps must be >= 1, got 0'):
        plant.PlantSettings(substeps=0)
    # A sequence of any length where the plant takes one (a planar or a 3-D start).
    assert len(plant.PlantSettings(initial_state=[0.0] * 6).initial_state) == 6


def test_a_name_none_of_them_has_gets_one_hint_everywhere():
    """A law's settings, the plant's parameters and the sections a node takes: the same
    ' (did you mean ...?)' from one function."""
    from tsr_koopman_ctrl.control import KoopmanMpc
    from tsr_koopman_ctrl.control.registry import parse_assignments, settings_sections
    from tsr_sim.plant import check_plant_parameter_names
    from tsr_sim.schema import build, did_you_mean, parse_value, unknown_setting_names
    hint = " (did you mean 'horizon'?)"
    assert did_you_mean('horizn', ['horizon', 'q', 'r']) == hint
    assert did_you_mean('zeta', ['horizon', 'q', 'r']) == ''
    for refuse in (lambda: build(KoopmanMpc.Settings, None, {'horizn': 8}),
                   lambda: parse_value(KoopmanMpc.Settings, 'horizn', '8'),
                   lambda: parse_assignments(['koopman_mpc.horizn=8'])):
        with pytest.raises(ValueError) as error:
            refuse()
        assert f"koopman_mpc has no setting 'horizn'{hint}" in str(error.value)
    (line,) = unknown_setting_names(['koopman_mpc.horizn'], settings_sections())
    assert line.endswith(" (did you mean 'koopman_mpc.horizon'?)")
    with pytest.raises(ValueError, match=r"'actuator_gian' is not a plant parameter "
                                         r"\(did you mean 'actuator_gain'\?\)"):
        check_plant_parameter_names(['actuator_gian'], 'plant file')


def test_command_line_values_of_any_schema():
    """`parse_value` reads a node's or the plant's values as it reads a law's."""
    from tsr_koopman_ctrl.nodes.recorder_parameters import RecorderNodeSettings
    from tsr_sim.plant import PlantSettings
    from tsr_sim.schema import parse_value
    assert parse_value(RecorderNodeSettings, 'topics', 'tsr/state,/clock') == (
        'tsr/state', '/clock')
    assert parse_value(PlantSettings, 'initial_state', '0,0,-0.9,0.5') == (0.0, 0.0, -0.9, 0.5)
    assert parse_value(PlantSettings, 'out_of_plane', 'true') is True
    with pytest.raises(ValueError, match="substeps: cannot read 'ten' as int"):
        parse_value(PlantSettings, 'substeps', 'ten')
    with pytest.raises(ValueError, match="topics must be a list of strings"):
        RecorderNodeSettings(topics=(1, 2))
