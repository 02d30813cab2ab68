"""The region where the supervisor's fallback holds (docs/supervisor.md, `lab.fallback_region`):
a sample of its grid flown again from its spec, held starts and starts the page lists as not
held, so the page's table cannot drift from the law."""

import pytest

from tsr_koopman_ctrl.campaign import fly
from lab import fallback_region

#: (start [theta, theta', l - 1, l'], swing bound, held as the page says): fast payout from the
#: shortest tether, reeling in at mid length (held, and swinging the wrong way: not), full
#: length reeling in, and under the 0.4 bound a swinging start at l = 0.1.
SAMPLE = [
    ((0.3, -1.0, -0.99, 1.0), 0.8, True),
    ((0.0, 0.5, -0.7, -0.5), 0.8, True),
    ((0.3, 0.0, -0.7, -0.5), 0.8, False),
    ((0.3, -1.0, 0.0, -0.5), 0.8, True),
    ((0.0, 0.0, -0.99, -0.5), 0.8, False),
    ((0.3, 0.5, -0.9, 0.5), 0.4, True),
]


@pytest.mark.parametrize('start, theta_max, held', SAMPLE)
def test_the_fallback_holds_where_the_page_says(start, theta_max, held):
    campaign = fallback_region.load()
    label = next(e.label for e in campaign.laws if fallback_region.bound(e) == theta_max)
    row = fly(campaign, campaign.start_list.index(start), label)
    assert (fallback_region.verdict(row, theta_max) == '') is held, row


def test_the_grid_and_its_bounds():
    campaign = fallback_region.load()
    lengths, rates, swings, swing_rates = fallback_region.axes(campaign)
    assert [round(v, 12) for v in lengths] == [0.01, 0.03, 0.1, 0.3, 0.6, 1.0]
    assert (rates, swings, swing_rates) == ([-0.5, 0.0, 0.5, 1.0], [-0.3, 0.0, 0.3],
                                            [-1.0, 0.0, 0.5])
    assert [fallback_region.bound(e) for e in campaign.laws] == [0.8, 0.4]
    assert [fallback_region.bound(e) for e in fallback_region.load([0.6]).laws] == [0.6]
    # The held rule reads the largest swing: a bound the grid starts past is refused.
    with pytest.raises(ValueError, match='past it'):
        fallback_region.load([0.2])
