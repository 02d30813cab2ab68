"""Each law's settings, declared once: a frozen dataclass per law whose fields carry their
description and range (`tsr_sim.schema`, the one parameter schema of the project: the plant's
and the nodes' own parameters are declared the same way). The controller node's parameters
(``<law>.<field>``), the tools' CLI flags (``--set <law>.<field>=<value>``, read by
`registry.parse_assignments`) and the example config file are all derived from these classes.

This module imports nothing else of `control`: every law imports it.
"""

import dataclasses

from tsr_sim.schema import (build, check_value, fields, parse_assignments,  # noqa: F401
                            parse_value, setting, Settings, unknown_setting_names)


def cross_weight_setting(search_bound=10.0):
    """The state weight's cross terms, declared once for every law with a quadratic cost on
    the state (`control.lqr.state_cost_matrix`); lab/tune.py searches each in
    [-search_bound, search_bound] when asked (`--also q_cross`)."""
    return setting((0.0,) * 6, 'cross terms of the state weight Q = L L^T: the entries of L '
                   'below its diagonal sqrt(q), row by row (L10, L20, L21, L30, L31, L32); '
                   'zeros: Q = diag(q)', tune=(-search_bound, search_bound, 'linear'),
                   searched=False)


@dataclasses.dataclass(frozen=True)
class LawSettings(Settings):
    """Base of every law's settings and of the sections around a law (observer, supervisor,
    ...): checks ranges and choices when built; its section is its `law` name."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls.section = getattr(cls, 'law', cls.__name__)
