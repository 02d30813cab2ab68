"""The region where the supervisor's fallback holds (docs/supervisor.md, `lab.fallback_region`):
a sample of its grid flown again, held starts and starts the page lists as not held, so the
page's table cannot drift from the law."""

import pytest

from lab.fallback_region import fly

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
    row = fly((start, theta_max, 1500))
    assert row['held'] is held, row
