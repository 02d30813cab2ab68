"""The laws by name: what the node, the tools and users build a controller from."""

import dataclasses

from tsr_koopman_ctrl.control.excitation import ExcitationSettings
from tsr_koopman_ctrl.control.fractional_pd import FractionalOrderPd
from tsr_koopman_ctrl.control.koopman_lqr import KoopmanLqr
from tsr_koopman_ctrl.control.koopman_mpc import KoopmanMpc
from tsr_koopman_ctrl.control.nmpc import KoopmanNmpc, PhysicsNmpc
from tsr_koopman_ctrl.control.linear_lqr import LinearisedLqr
from tsr_koopman_ctrl.control.offset_free import ObserverSettings, OffsetFree
from tsr_koopman_ctrl.control.safety_filter import SafetyFilter, SafetyFilterSettings
from tsr_koopman_ctrl.control.settings import build, LawSettings
from tsr_koopman_ctrl.control.settings import parse_assignments as parse_section_assignments
from tsr_koopman_ctrl.control.supervisor import Supervisor, SupervisorSettings

#: The law the controller node, deploy and the main job run unless told otherwise.
DEFAULT_LAW = 'koopman_nmpc'
CONTROLLERS = {law.name: law for law in (LinearisedLqr, FractionalOrderPd, KoopmanLqr,
                                         KoopmanMpc, KoopmanNmpc, PhysicsNmpc)}
#: The controller's settings sections that are not laws: the observer (offset-free control)
#: and the excitation. The node declares them, deploy and its presets take them.
NODE_SECTIONS = {'observer': ObserverSettings, 'excitation': ExcitationSettings,
                 'supervisor': SupervisorSettings, 'safety_filter': SafetyFilterSettings}


def settings_sections():
    """{section: settings class} of every section the controller's parameters may hold: each
    law's and NODE_SECTIONS."""
    return {**{name: law.Settings for name, law in CONTROLLERS.items()}, **NODE_SECTIONS}


def settings_class(section):
    """The settings class of a settings section: a law's or one of NODE_SECTIONS (ValueError,
    one line naming both kinds, for an unknown one)."""
    if section in NODE_SECTIONS:
        return NODE_SECTIONS[section]
    if section not in CONTROLLERS:
        raise ValueError(f'unknown settings section {section!r}: a law '
                         f"({', '.join(sorted(CONTROLLERS))}) or one of "
                         f"{', '.join(sorted(NODE_SECTIONS))}")
    return CONTROLLERS[section].Settings


def parse_assignments(assignments, section_class=settings_class):
    """{section: {setting: value}} from 'SECTION.SETTING=VALUE' strings (deploy's --set, the
    lab's, a campaign's), each value read as its setting's type and checked
    (`settings.parse_assignments`); a section is a law's or one of NODE_SECTIONS unless
    `section_class(section)` says otherwise."""
    return parse_section_assignments(assignments, section_class)


def law_class(name):
    try:
        return CONTROLLERS[name]
    except KeyError:
        raise ValueError(f'unknown law {name!r}; choose from {sorted(CONTROLLERS)}')


def make_controller(name, settings=None, observer=None, supervisor=None, safety=None,
                    **overrides):
    """Build the law `name`: its settings (an instance of its Settings class, or the defaults)
    with `overrides` (settings fields, or the loop's h and u_max) applied, wrapped for
    offset-free control unless `observer` (ObserverSettings, a dict of them, or the defaults;
    'none' for the bare law) says disturbance 'none'. A learned law (one with a model) flies
    under the runtime-assurance supervisor, its verified fallback wrapped the same way,
    unless `supervisor` (SupervisorSettings, a dict of them, or the defaults) says fallback
    'none' (or is 'none'), and under the predictive safety filter, its backups planned by the
    verified law, unless `safety` (SafetyFilterSettings, a dict of them, or the defaults)
    says backup 'none' (or is 'none')."""
    law = law_class(name)(settings, **overrides)
    observer = section_settings(ObserverSettings, observer, 'disturbance')
    supervisor = section_settings(SupervisorSettings, supervisor, 'fallback')
    safety = section_settings(SafetyFilterSettings, safety, 'backup')

    def offset_free(law):
        return law if observer.disturbance == 'none' else OffsetFree(law, observer)
    if law.model is None:
        return offset_free(law)
    backup = safety.backup
    if backup == 'auto':
        backup = 'physics_nmpc' if law.filtered else 'none'
    flown = (offset_free(law) if supervisor.fallback == 'none' else
             Supervisor(offset_free(law), offset_free(fallback_law(law, supervisor.fallback)),
                        supervisor, filtered=backup != 'none'))
    if backup == 'none':
        return flown
    verified = None if backup == 'hold' else lambda: fallback_law(law, backup)
    return SafetyFilter(flown, verified, safety)


def section_settings(settings_class, value, off_field):
    """A wrapper's settings from an instance, a dict (checked as a law's settings: one line
    naming the key), None (the defaults) or 'none' (`off_field` set to 'none')."""
    if isinstance(value, str):
        value = {off_field: value}
    if isinstance(value, dict):
        return build(settings_class, None, value)
    return value or settings_class()


def fallback_law(learned, name):
    """The supervisor's fallback for `learned`: `name` built with the settings both laws'
    classes inherit from one declaration (the NMPCs: cost, horizon, bounds; none for laws of
    other families, which give it only their swing bound), the loop's h and u_max."""
    cls = law_class(name)
    common = next((base for base in type(learned.settings).__mro__
                   if issubclass(cls.Settings, base) and issubclass(base, LawSettings)
                   and base is not LawSettings), None)
    shared = {} if common is None else {
        field.name: getattr(learned.settings, field.name)
        for field in dataclasses.fields(common)}
    if 'theta_max' in type(learned.settings).__dataclass_fields__:
        shared['theta_max'] = learned.settings.theta_max
    return cls(None, h=learned.h, u_max=learned.u_max, **shared)


def preset(name, sections=None):
    """{law: {setting: value}} of a settings preset (and of the `sections` asked for): a
    parameter file (`ros__parameters` with a section per law, or `law.setting` keys), given by
    path or by name under the installed config/ ('untuned': the settings before tuning). The
    laws' defaults are the tuned settings.
    `sections`: {name: settings class} of other sections the caller applies too (deploy: the
    observer and the excitation). Anything else in the file, a setting a law does not have, or
    a value of the wrong type or range is one ValueError line naming the file."""
    import os

    from tsr_sim.parameter_file import node_parameters
    from tsr_sim.share import NOT_SOURCED, share_directory
    path = name
    if not os.path.isfile(path):
        # By name, from the installed package: a path works without a sourced workspace.
        share = share_directory('tsr_koopman_ctrl')
        path = (f'share/tsr_koopman_ctrl/config ({NOT_SOURCED})' if share is None
                else os.path.join(share, 'config', f'{name}.yaml'))
        if not os.path.isfile(path):
            raise ValueError(f'no settings preset {name!r} (tried {os.path.abspath(name)}, '
                             f'{path})')
    classes = {law: cls.Settings for law, cls in CONTROLLERS.items()}
    classes.update(sections or {})
    grouped = {}
    for key, value in node_parameters(path).items():
        section, dot, setting = key.partition('.')     # 'law.setting' keys, as ROS takes them
        values = grouped.setdefault(section, {})
        if dot:
            if not isinstance(values, dict):
                raise ValueError(f'{path}: {section} is not a section of settings')
            values[setting] = value
        elif isinstance(value, dict) and isinstance(values, dict):
            values.update(value)
        else:
            grouped[section] = value
    for section, values in grouped.items():
        if section not in classes:
            elsewhere = ('; deploy applies it, as the controller node does'
                         if section in NODE_SECTIONS else '')
            raise ValueError(f'{path}: {section!r} is not a section a preset can hold '
                             f"here ({', '.join(sorted(classes))}){elsewhere}")
        if not isinstance(values, dict):
            raise ValueError(f'{path}: {section} is not a section of settings')
        try:
            build(classes[section], None, values)
        except ValueError as error:      # one line: a setting it lacks, a type or a range
            raise ValueError(f'{path}: {error}') from None
    return grouped
