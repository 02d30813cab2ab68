"""A campaign's spec: what varies from run to run and how, checked whole before any run starts.

    runs: 200                 # dispersed cases; every law flies each of them (paired)
    steps: 1500               # of h = 0.01 tau
    seed: 7                   # a run's values come from (seed, run) alone
    swing_limit: 0.4          # optional: a run swinging past it fails
    start:                    # a box, one value drawn per component ...
      low: [-0.05, -0.1, -0.995, 0.3]
      high: [0.05, 0.1, -0.98, 0.7]
      distribution: uniform   # or normal (truncated to the box, sigma a quarter of it), or
                              # dense_low (density falling linearly from low to zero at
                              # high: half the draws in the lowest 29%), or one per component
    # start: [[0, 0, -0.99, 0.5], [0, 0, -0.9, 0.3]]   # ... or a list: run n flies n mod len
    # start: [comparison, held_out]                     # ... or named sets (NAMED_STARTS),
    # start: [comparison, [0.1, -0.1, -0.9, 0.5]]       #     alone or among starts
    # start: {grid: [[-0.3, 0, 0.3], [0], [-0.99, -0.9], [-0.5, 0, 0.5]]}
    #                         # ... or a grid: every combination of the values per component,
    #                         # the last component varying fastest (here 18 starts)
    plant:                    # default: the nominal plant
      variant: heavy_robot    # a named plant variant (tsr_sim/config/plants) to start from
      actuator_gain: {low: 0.8, high: 1.2}               # dispersed, as a start component
      actuator_lag: {low: 0.0, high: 0.05, distribution: normal}
      sensor_noise_std: 0.001                            # fixed; every component's std
    cases:                    # optional: named plant cases, each over `plant` (full factorial)
      - {label: nominal}
      - {label: weak and lagging, actuator_gain: 0.8, actuator_lag: 0.05}
    laws:
      - koopman_nmpc
      - {law: koopman_nmpc, label: nmpc_bare, set: [supervisor.fallback=none]}
    set: [observer.disturbance=none]    # as deploy --set, for every law it applies to
    figures: [final_length_offset]      # optional: figures a row carries beyond the default

Cases: each is a label (any text, its rows' `case` column) and plant parameters, fixed or
dispersed, merged over the common `plant` (a case's value replaces the common one; a case's
`variant` replaces the common variant). Every start flies every case: with S starts (a box
counts as one) and C cases, run n flies start n mod S and case (n // S) mod C, and the runs
default to S * C (100 * C for a box). Without cases every run flies the common plant.

Plant parameters are the simulator's (`tsr_sim.plant.PLANT_PARAMETERS`, their declared ranges,
and the units' `mass`); `sensor_noise_std` takes one std for every component, `initial_beta`
(with `out_of_plane: true`) the start's beta (beta' 0). Laws and settings are the registry's.
`figures` names extra columns (EXTRA_FIGURES); the default row is the engine's FIGURE_COLUMNS.
Every mistake is one ValueError line.
"""

import dataclasses
import itertools
import math
import numbers

import numpy as np
from tsr_sim import dynamics
from tsr_sim.plant import (check_plant_parameter_names, check_plant_parameter_values,
                           PLANT_PARAMETERS, plant_parameters, SCALE_PARAMETERS)
from tsr_sim.schema import did_you_mean

from tsr_koopman_ctrl.control.registry import CONTROLLERS, law_class, NODE_SECTIONS, \
    settings_class
from tsr_koopman_ctrl.control.settings import build, parse_assignments
from tsr_koopman_ctrl.evaluation.starts import COMPARISON_STARTS, HELD_OUT_STARTS, PAPER_START

DISTRIBUTIONS = ('uniform', 'normal', 'dense_low')
#: Start sets a spec may name (`start: [comparison, held_out]`): the comparison's own.
NAMED_STARTS = {'comparison': COMPARISON_STARTS, 'held_out': HELD_OUT_STARTS}
#: A normal dispersion's box is +-2 sigma around its middle (truncated to the box).
NORMAL_SIGMAS = 2.0
#: Plant parameters a campaign sets itself: the start, the length of a run, the sample period
#: the laws are built for, the noise seed (from the campaign's seed and the run's number).
OWN_PARAMETERS = ('initial_state', 'max_steps', 'step', 'seed')
#: Plant parameters given as one number in a spec and as the simulator's vector.
SCALAR_FORMS = ('sensor_noise_std', 'initial_beta')
DEFAULT_RUNS = 100
DEFAULT_STEPS = 1500
SPEC_KEYS = ('runs', 'steps', 'seed', 'swing_limit', 'start', 'plant', 'cases', 'laws', 'set',
             'figures')
LAW_KEYS = ('law', 'label', 'set', 'settings')
#: Figures a spec may add to its rows (`figures:`), after the engine's own, in the spec's order;
#: `states` and `tensions` are the run's trajectory (a list per step, a number per step).
EXTRA_FIGURES = ('final_length_offset', 'frontier_tau', 'tension_integral', 'tension_max',
                 'length_overshoot', 'compute_p99_ms', 'fallbacks', 'states', 'tensions')


def _refuse_unknown(keys, known, where):
    for key in keys:
        if key not in known:
            raise ValueError(f'{where}: unknown key {key!r}{did_you_mean(key, known)}; keys: '
                             f'{", ".join(known)}')


def _number(value, where):
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(
            value):
        raise ValueError(f'{where} must be a finite number, got {value!r}')
    return float(value)


def _count(value, where, low):
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        raise ValueError(f'{where} must be an integer >= {low}, got {value!r}')
    return int(value)


@dataclasses.dataclass(frozen=True)
class Dispersion:
    """One dispersed value in [low, high]: uniform, normal about the middle (sigma a quarter
    of the width) truncated to [low, high], or dense_low (density 2 (high - v) / (high - low)^2,
    for a region the campaign should sample densely at one end of the box, such as the short
    tether); drawn from one uniform number, so that the distribution of one value never changes
    the draws of the others."""

    low: float
    high: float
    distribution: str = 'uniform'

    @classmethod
    def parse(cls, value, where):
        if not isinstance(value, dict):
            raise ValueError(f'{where} must be a number or {{low, high, distribution}}, got '
                             f'{value!r}')
        _refuse_unknown(value, ('low', 'high', 'distribution'), where)
        if 'low' not in value or 'high' not in value:
            raise ValueError(f'{where} needs low and high')
        return cls(_number(value['low'], f'{where}.low'),
                   _number(value['high'], f'{where}.high'),
                   value.get('distribution', 'uniform')).checked(where)

    def checked(self, where):
        if not self.low < self.high:
            raise ValueError(f'{where}: empty range, low {self.low:g} must be < high '
                             f'{self.high:g}')
        if self.distribution not in DISTRIBUTIONS:
            raise ValueError(f'{where}: distribution must be one of {list(DISTRIBUTIONS)}, '
                             f'got {self.distribution!r}')
        return self

    def draw(self, uniform):
        """The value at the quantile `uniform` in [0, 1)."""
        if self.distribution == 'uniform':
            return float(self.low + uniform * (self.high - self.low))
        if self.distribution == 'dense_low':      # the inverse of F(v) = 1 - ((high - v) / w)^2
            return float(self.high - (self.high - self.low) * math.sqrt(1.0 - uniform))
        from scipy.stats import truncnorm
        middle, sigma = (self.low + self.high) / 2, (self.high - self.low) / (2 * NORMAL_SIGMAS)
        return float(truncnorm.ppf(uniform, -NORMAL_SIGMAS, NORMAL_SIGMAS, loc=middle,
                                   scale=sigma))

    def as_dict(self):
        return {'low': self.low, 'high': self.high, 'distribution': self.distribution}


@dataclasses.dataclass(frozen=True)
class LawEntry:
    """A law flown on every case: its registry name, the label its rows carry, its settings
    {section: {setting: value}} (the law's own section and NODE_SECTIONS)."""

    law: str
    label: str
    settings: dict


@dataclasses.dataclass(frozen=True)
class PlantCase:
    """A named plant case (`cases:`): its label (its rows' `case`), the plant variant it starts
    from (None: the spec's), its fixed and dispersed parameters over the spec's plant."""

    label: str
    variant: str
    fixed: dict
    dispersed: dict


@dataclasses.dataclass(frozen=True)
class Case:
    """What one run flies: its number, its noise seed, the dimensionless start, the plant
    parameters (`closed_loop(plant=...)`), the dispersed values by name and the label of its
    plant case (None in a campaign without cases)."""

    run: int
    seed: int
    x0: tuple
    plant: dict
    dispersed: dict
    plant_case: str = None


@dataclasses.dataclass(frozen=True)
class Campaign:
    """A checked spec (module docstring); `Campaign.parse(mapping)` or `load_spec(path)`."""

    runs: int
    steps: int
    seed: int
    laws: tuple
    swing_limit: float = None
    start_box: tuple = None         # (Dispersion,) * 4, or None with start_list
    start_list: tuple = ((PAPER_START),)
    variant: str = None
    plant_fixed: dict = dataclasses.field(default_factory=dict)
    plant_dispersed: dict = dataclasses.field(default_factory=dict)
    cases: tuple = ()               # (PlantCase,): none, every run flies the plant above
    figures: tuple = ()             # the EXTRA_FIGURES its rows carry

    @classmethod
    def parse(cls, spec, where='spec'):
        if not isinstance(spec, dict):
            raise ValueError(f'{where}: a spec is a mapping of {", ".join(SPEC_KEYS)}')
        _refuse_unknown(spec, SPEC_KEYS, where)
        start_box, start_list = _parse_start(spec.get('start'), f'{where}: start')
        # With cases, each case's merged plant is checked instead of the common one alone.
        variant, fixed, dispersed = _parse_plant(spec.get('plant') or {}, f'{where}: plant',
                                                 check='cases' not in spec)
        cases = _parse_cases(spec.get('cases'), (variant, fixed, dispersed), f'{where}: cases')
        default_runs = (DEFAULT_RUNS if start_box else len(start_list)) * max(1, len(cases))
        runs = _count(spec.get('runs', default_runs), f'{where}: runs', 1)
        steps = _count(spec.get('steps', DEFAULT_STEPS), f'{where}: steps', 1)
        seed = _count(spec.get('seed', 0), f'{where}: seed', 0)
        if seed > 2 ** 32 - 1:
            raise ValueError(f'{where}: seed must be < 2**32, got {seed}')
        swing_limit = spec.get('swing_limit')
        if swing_limit is not None:
            swing_limit = _number(swing_limit, f'{where}: swing_limit')
            if swing_limit <= 0:
                raise ValueError(f'{where}: swing_limit must be > 0, got {swing_limit:g}')
        laws = _parse_laws(spec.get('laws'), spec.get('set', []), where)
        figures = _parse_figures(spec.get('figures'), f'{where}: figures')
        return cls(runs, steps, seed, laws, swing_limit, start_box, start_list, variant, fixed,
                   dispersed, cases, figures)

    def as_dict(self):
        """The spec in its canonical form (every default explicit): what <out>/spec.yaml holds
        and `parse` reads back to the same campaign."""
        start = ({'low': [d.low for d in self.start_box],
                  'high': [d.high for d in self.start_box],
                  'distribution': [d.distribution for d in self.start_box]}
                 if self.start_box else [list(x) for x in self.start_list])
        plant = _plant_dict(self.variant, self.plant_fixed, self.plant_dispersed)
        spec = {'runs': self.runs, 'steps': self.steps, 'seed': self.seed,
                'swing_limit': self.swing_limit, 'start': start, 'plant': plant,
                'laws': [{'law': e.law, 'label': e.label, 'settings': _plain(e.settings)}
                         for e in self.laws]}
        # Only where given, so that a stored spec without them reads back equal.
        if self.cases:
            spec['cases'] = [{'label': c.label, **_plant_dict(c.variant, c.fixed, c.dispersed)}
                             for c in self.cases]
        if self.figures:
            spec['figures'] = list(self.figures)
        return spec

    def law(self, label):
        for entry in self.laws:
            if entry.label == label:
                return entry
        raise ValueError(f'no law {label!r} in this campaign; laws: '
                         f'{", ".join(e.label for e in self.laws)}')

    def pairs(self):
        """Every (run, law label) the campaign flies."""
        return [(run, entry.label) for run in range(self.runs) for entry in self.laws]

    def dispersed_names(self):
        """The names of the values that vary from run to run in any case (their rows'
        columns; NaN in the rows of a case that does not disperse one)."""
        return list(dict.fromkeys(name for index in range(max(1, len(self.cases)))
                                  for name in self.plant_of(index)[2]))

    def position(self, run):
        """(start index, case index) of `run`: start run mod S (a box counts as one start),
        case (run // S) mod C."""
        starts = 1 if self.start_box else len(self.start_list)
        return run % starts, (run // starts) % max(1, len(self.cases))

    def plant_of(self, index):
        """(variant, fixed, dispersed) of plant case `index`: the case's over the spec's plant
        (the spec's alone without cases)."""
        if not self.cases:
            return self.variant, self.plant_fixed, self.plant_dispersed
        return _merged(self.cases[index], self.variant, self.plant_fixed, self.plant_dispersed)

    def case(self, run):
        """Run `run`'s case, from (seed, run) alone (numpy SeedSequence): the same whatever
        the workers, their number or the order runs finish."""
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(run,)))
        noise_seed = int(rng.integers(PLANT_PARAMETERS['seed'][3] + 1))
        start, case_index = self.position(run)
        if self.start_box:
            x0 = tuple(d.draw(float(u)) for d, u in zip(self.start_box, rng.random(len(
                self.start_box))))
        else:
            x0 = tuple(self.start_list[start])
        # One number per name dispersed in any case, in one order: a case's draws do not
        # depend on what the other cases disperse.
        names = self.dispersed_names()
        uniforms = dict(zip(names, rng.random(len(names))))
        variant, fixed, dispersions = self.plant_of(case_index)
        dispersed = {name: d.draw(float(uniforms[name])) for name, d in dispersions.items()}
        plant = dict(plant_parameters(variant) if variant else {})
        plant.update(fixed)
        plant.update(dispersed)
        plant = simulator_form(plant)
        plant['seed'] = noise_seed
        label = self.cases[case_index].label if self.cases else None
        return Case(run, noise_seed, x0, plant, dispersed, label)


def simulator_form(plant):
    """Plant parameters as the simulator takes them: the scalar forms (SCALAR_FORMS) made the
    vectors they stand for."""
    plant = dict(plant)
    dim = dynamics.SPATIAL_DIM if plant.get('out_of_plane') else dynamics.PLANAR_DIM
    std = plant.get('sensor_noise_std')
    if isinstance(std, numbers.Real):
        plant['sensor_noise_std'] = [float(std)] * dim
    beta = plant.get('initial_beta')
    if isinstance(beta, numbers.Real):
        plant['initial_beta'] = [float(beta), 0.0]
    return plant


def _plant_dict(variant, fixed, dispersed):
    """A plant's spec form: its variant, fixed values and dispersions."""
    return {**({'variant': variant} if variant else {}), **_plain(fixed),
            **{name: d.as_dict() for name, d in dispersed.items()}}


def _merged(case, variant, fixed, dispersed):
    """(variant, fixed, dispersed) of `case` over a common plant: the case's values replace
    the common ones, whether fixed or dispersed."""
    fixed = {**{k: v for k, v in fixed.items() if k not in case.dispersed}, **case.fixed}
    dispersed = {**{k: d for k, d in dispersed.items() if k not in case.fixed},
                 **case.dispersed}
    return case.variant or variant, fixed, dispersed


def _plain(value):
    """Tuples as lists, for YAML."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


def _parse_start(start, where):
    if start is None:
        return None, (tuple(PAPER_START),)
    if isinstance(start, str):
        start = [start]
    if isinstance(start, list) and any(isinstance(v, str) for v in start):
        named = []
        for entry in start:
            if isinstance(entry, str) and entry not in NAMED_STARTS:
                raise ValueError(f'{where}: no start set {entry!r}; named sets: '
                                 f'{", ".join(NAMED_STARTS)}')
            named += [list(x0) for x0 in NAMED_STARTS[entry]] if isinstance(entry, str) else [
                entry]
        start = named
    if isinstance(start, dict) and 'grid' in start:
        return None, _parse_grid(start, where)
    if isinstance(start, dict):
        _refuse_unknown(start, ('low', 'high', 'distribution', 'grid'), where)
        low, high = start.get('low'), start.get('high')
        distribution = start.get('distribution', 'uniform')
        size = dynamics.PLANAR_DIM
        if isinstance(distribution, str):
            distribution = [distribution] * size
        for name, value in (('low', low), ('high', high), ('distribution', distribution)):
            if not isinstance(value, list) or len(value) != size:
                raise ValueError(f'{where}.{name} needs {size} values (theta, theta\', l - 1, '
                                 f"l'), got {value!r}")
        box = tuple(Dispersion(_number(lo, f'{where}.low'), _number(hi, f'{where}.high'),
                               kind).checked(f'{where} component {i}')
                    for i, (lo, hi, kind) in enumerate(zip(low, high, distribution)))
        return box, None
    if isinstance(start, list) and start and all(isinstance(v, numbers.Real) for v in start):
        start = [start]
    if not isinstance(start, list) or not start:
        raise ValueError(f'{where} must be a box {{low, high, distribution}}, a grid '
                         f'{{grid: [values per component]}} or a list of starts, got {start!r}')
    starts = []
    for i, x0 in enumerate(start):
        if not isinstance(x0, list) or len(x0) != dynamics.PLANAR_DIM:
            raise ValueError(f'{where} {i} needs {dynamics.PLANAR_DIM} values, got {x0!r}')
        x0 = tuple(_number(v, f'{where} {i}') for v in x0)
        if not dynamics.in_domain(np.array(x0)):
            raise ValueError(f'{where} {i} {list(x0)} is outside the model domain (l > 0)')
        starts.append(x0)
    return None, tuple(starts)


def _parse_grid(start, where):
    """The starts of `{grid: [values per component]}`: every combination, the last component
    varying fastest."""
    size = dynamics.PLANAR_DIM
    if set(start) != {'grid'}:
        raise ValueError(f'{where}: a grid takes no {", ".join(sorted(set(start) - {"grid"}))} '
                         "(it is {grid: [theta values, theta' values, l - 1 values, l' "
                         'values]})')
    grid = start['grid']
    if not isinstance(grid, list) or len(grid) != size or not all(
            isinstance(values, list) and values for values in grid):
        raise ValueError(f"{where}.grid needs {size} lists of values (theta, theta', l - 1, "
                         f"l'), got {grid!r}")
    values = [[_number(v, f'{where}.grid component {i}') for v in component]
              for i, component in enumerate(grid)]
    for i, component in enumerate(values):
        if len(set(component)) != len(component):
            raise ValueError(f'{where}.grid component {i} repeats a value: {component}')
    starts = tuple(itertools.product(*values))
    outside = [list(x0) for x0 in starts if not dynamics.in_domain(np.array(x0))]
    if outside:
        raise ValueError(f'{where}.grid: {len(outside)} starts are outside the model domain '
                         f'(l > 0), e.g. {outside[0]}')
    return starts


def _parse_cases(cases, common, where):
    """The (PlantCase,) of `cases:`, each checked merged over the `common` plant (variant,
    fixed, dispersed); () for none."""
    if cases is None:
        return ()
    if not isinstance(cases, list) or not cases:
        raise ValueError(f'{where} must be a non-empty list of {{label: ..., plant '
                         f'parameters}}, got {cases!r}')
    parsed = []
    for i, entry in enumerate(cases):
        if not isinstance(entry, dict) or 'label' not in entry:
            raise ValueError(f'{where} {i}: a case is {{label: ..., plant parameters}}, got '
                             f'{entry!r}')
        label = entry['label']
        if not isinstance(label, str) or not label.strip() or '\n' in label:
            raise ValueError(f'{where} {i}: label must be a line of text, got {label!r}')
        if label in (c.label for c in parsed):
            raise ValueError(f'{where} {i}: two cases share the label {label!r}: give each its '
                             'own')
        here = f'{where} {label!r}'
        case = PlantCase(label, *_parse_plant({k: v for k, v in entry.items() if k != 'label'},
                                              here, check=False))
        variant, fixed, dispersed = _merged(case, *common)
        _check_plant(variant, fixed, dispersed, here)
        parsed.append(case)
    return tuple(parsed)


def _parse_figures(figures, where):
    if figures is None:
        return ()
    if isinstance(figures, str):
        figures = [figures]
    if not isinstance(figures, list):
        raise ValueError(f'{where} must be a list of figure names ({", ".join(EXTRA_FIGURES)})'
                         f', got {figures!r}')
    for name in figures:
        if name not in EXTRA_FIGURES:
            hint = did_you_mean(name, EXTRA_FIGURES)
            raise ValueError(f'{where}: no figure {name!r}{hint}; figures a row may add: '
                             f'{", ".join(EXTRA_FIGURES)}')
    if len(set(figures)) != len(figures):
        raise ValueError(f'{where} names a figure twice: {figures}')
    return tuple(figures)


def _parse_laws(laws, common, where):
    if laws is None or laws == []:
        raise ValueError(f'{where}: no law to fly (laws: one or more of {sorted(CONTROLLERS)})')
    if isinstance(laws, str):
        laws = [laws]
    if not isinstance(laws, list):
        raise ValueError(f'{where}: laws must be a list, got {laws!r}')
    common = _assignments(common, f'{where}: set')
    names = {entry if isinstance(entry, str) else entry.get('law')
             for entry in laws if isinstance(entry, (str, dict))}
    for section in common:
        if section not in NODE_SECTIONS and section not in names:
            settings_class(section)        # an unknown section is one line
            raise ValueError(f'{where}: set {section}.*: {section} is not among the laws '
                             f'flown ({", ".join(sorted(n for n in names if n))})')
    entries = []
    for entry in laws:
        if isinstance(entry, str):
            entry = {'law': entry}
        if not isinstance(entry, dict) or 'law' not in entry:
            raise ValueError(f'{where}: a law is a name or {{law, label, set, settings}}, got '
                             f'{entry!r}')
        _refuse_unknown(entry, LAW_KEYS, f'{where}: law {entry["law"]!r}')
        name = entry['law']
        if not isinstance(name, str):
            raise ValueError(f'{where}: a law name is a string, got {name!r}')
        law_class(name)                    # an unknown law is one line
        label = entry.get('label', name)
        if not isinstance(label, str) or not label.isidentifier():
            raise ValueError(f'{where}: label {label!r} must be a name (letters, digits, _)')
        settings = {section: dict(values) for section, values in common.items()
                    if section in NODE_SECTIONS or section == name}
        own = entry.get('settings') or {}
        if not isinstance(own, dict):
            raise ValueError(f'{where}: law {label}: settings must be a mapping of sections')
        own = {section: dict(values or {}) for section, values in own.items()}
        for section, values in [*own.items(),
                                *_assignments(entry.get('set', []),
                                              f'{where}: law {label}: set').items()]:
            if section not in NODE_SECTIONS and section != name:
                raise ValueError(f'{where}: law {label}: {section!r} is not a section of '
                                 f'{name} ({", ".join([name, *NODE_SECTIONS])})')
            settings.setdefault(section, {}).update(values)
        for section, values in settings.items():
            try:
                checked = build(settings_class(section), None, values)
            except (ValueError, TypeError) as error:
                raise ValueError(f'{where}: law {label}: {error}') from None
            settings[section] = {key: getattr(checked, key) for key in values}
        entries.append(LawEntry(name, label, settings))
    labels = [e.label for e in entries]
    if len(set(labels)) != len(labels):
        raise ValueError(f'{where}: two laws share a label ({", ".join(labels)}): give each '
                         'its own label')
    return tuple(entries)


def _assignments(assignments, where):
    if isinstance(assignments, str):
        assignments = [assignments]
    if not isinstance(assignments, list) or not all(isinstance(a, str) for a in assignments):
        raise ValueError(f'{where} takes SECTION.SETTING=VALUE strings, got {assignments!r}')
    return parse_assignments(assignments, settings_class)


def _parse_plant(plant, where, check=True):
    """(variant, fixed, dispersed) of a plant mapping; its values checked unless not `check`
    (a case's are checked merged over the common plant)."""
    if not isinstance(plant, dict):
        raise ValueError(f'{where} must be a mapping of plant parameters, got {plant!r}')
    plant = dict(plant)
    variant = plant.pop('variant', None)
    if variant is not None:
        if not isinstance(variant, str):
            raise ValueError(f'{where}.variant must be a plant variant name, got {variant!r}')
        plant_parameters(variant)          # an unknown variant is one line
    check_plant_parameter_names(plant, where)
    for name in plant:
        if name in OWN_PARAMETERS:
            raise ValueError(f'{where}: {name} is set by the campaign (the start, steps, the '
                             "loop's period, the run's noise seed), not by the plant")
    fixed = {k: v for k, v in plant.items() if not isinstance(v, dict)}
    dispersed = {}
    for name, value in plant.items():
        if not isinstance(value, dict):
            continue
        spec = PLANT_PARAMETERS.get(name)
        numeric = name in SCALE_PARAMETERS or name in SCALAR_FORMS or (
            spec is not None and spec[2] is not None and not isinstance(spec[0], bool))
        if not numeric:
            raise ValueError(f'{where}: {name} cannot be dispersed (a number with a declared '
                             'range can)')
        dispersed[name] = Dispersion.parse(value, f'{where}.{name}')
    if check:
        _check_plant(variant, fixed, dispersed, where)
    return variant, fixed, dispersed


def _check_plant(variant, fixed, dispersed, where):
    """Both ends of every range, and the fixed values, as the simulator would check them."""
    base = plant_parameters(variant) if variant else {}
    for end in ('low', 'high'):
        values = {**base, **fixed, **{n: getattr(d, end) for n, d in dispersed.items()}}
        check_plant_parameter_values(simulator_form(values), where)
    if 'initial_beta' in {**fixed, **dispersed} and not {**base, **fixed}.get('out_of_plane'):
        raise ValueError(f'{where}: initial_beta needs out_of_plane: true')


def load_spec(path=None, **overrides):
    """The campaign of a YAML spec file (or of none: the defaults), with `overrides` (spec keys,
    as the command's flags give them: runs, steps, seed, laws, set, swing_limit, plant) on
    top; `set` adds to the file's."""
    spec = {}
    if path is not None:
        import yaml
        try:
            with open(path) as stream:
                spec = yaml.safe_load(stream) or {}
        except OSError as error:
            raise ValueError(f'{path}: {error.strerror}') from None
        except yaml.YAMLError:
            raise ValueError(f'{path}: not valid YAML') from None
        if not isinstance(spec, dict):
            raise ValueError(f'{path}: a spec is a mapping of {", ".join(SPEC_KEYS)}')
    for key, value in overrides.items():
        if value is None:
            continue
        if key == 'set':
            spec['set'] = [*(spec.get('set') or []), *value]
        elif key == 'variant':
            spec['plant'] = {**(spec.get('plant') or {}), 'variant': value}
        else:
            spec[key] = value
    return Campaign.parse(spec, where=path or 'spec')
