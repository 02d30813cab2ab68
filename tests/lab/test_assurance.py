"""The assurance study (`lab.assurance`): the monitor part's table counts runs against the bare
law's from the same start; its yardstick spec is its starts nudged; every part flown short."""

import pytest

from lab.assurance import monitor_table, TIE


def row(law, plant, start, settle, switches=0):
    return {'law': law, 'plant': plant, 'start': [start, 0.0, -0.9, 0.5],
            'settle_tau': settle, 'switches': switches}


def test_slower_and_faster_are_counted_per_plant_against_bare():
    rows = [row('bare', 'weak', 0.0, 4.0), row('bare', 'weak', 0.1, 5.0),
            row('bare', 'strong', 0.0, 3.0), row('bare', 'strong', 0.1, None),
            # 5% slower, and a difference within half a step (the same)
            row('A', 'weak', 0.0, 4.2, 2), row('A', 'weak', 0.1, 5.0 + 0.4 * TIE, 1),
            # 2 tau faster; settled where bare did not
            row('A', 'strong', 0.0, 1.0, 2), row('A', 'strong', 0.1, 6.0, 2),
            row('B', 'weak', 0.0, None), row('B', 'weak', 0.1, 5.0),
            row('B', 'strong', 0.0, 3.0), row('B', 'strong', 0.1, None)]
    lines = monitor_table(rows).splitlines()
    assert lines[0] == ('| monitor | weak: slower than bare (by up to) | strong: slower than '
                        'bare (by up to) | faster than bare (by up to) | settle tau, all runs '
                        '| switches |')
    a, b, bare = lines[2:]
    assert a == '| A | 1 (5.0%) | 0 | 2 (1 where bare did not settle) | 16.20 | 7 |'
    assert b == '| B | 1 (1 not settled) | 0 | 0 | inf | 0 |'
    assert bare == '| bare | - | - | - | inf | - |'


def test_the_monitor_part_s_yardstick_is_its_starts_nudged_and_its_headings_the_page_s():
    from tsr_koopman_ctrl.campaign import load_spec
    from lab import assurance
    monitor = load_spec(assurance.SPECS['monitor'])
    nudged = load_spec(assurance.SPECS['monitor_nudged'])
    assert assurance.nudge(monitor, nudged) == pytest.approx(1e-9, rel=1e-6)
    assert [assurance.heading(e) for e in monitor.laws] == [
        'bare', 'shipped', 'takeback_steps 5', 'takeback_steps 10', 'takeback_steps 40',
        'fault_count 3, fault_window 3']
    swing = load_spec(assurance.SPECS['swing'])
    assert [assurance.heading(e) for e in swing.laws] == ['bare', 'supervised',
                                                          'fallback alone']


@pytest.mark.timeout(600)
def test_the_parts_flown_short_write_their_tables(tmp_path):
    """Every part, one run of 20 steps each, on one worker: the page's sections, in order."""
    from lab import assurance
    page = tmp_path / 'page.md'
    page.write_text('<!-- assurance:begin -->\n<!-- assurance:end -->\n')
    out = tmp_path / 'assurance'
    assert assurance.main(['--parts', 'nominal', 'swing', 'robust', 'monitor', '--steps', '20',
                           '--runs', '1', '--workers', '1', '--out', str(out),
                           '--page', str(page)]) == 0
    shown = page.read_text()
    titles = ['Nominal plant, shipped settings', 'Swing bound 0.4 rad',
              'gain 0.8, lag 0.05, noise 1e-3 (', 'The robust part under other monitor']
    assert [shown.index(title) for title in titles] == sorted(shown.index(t) for t in titles)
    assert '| start | bare | supervised | fallback alone | switches |' in shown
    assert '| [0.0, 0.0, -0.99, 0.5] | not settled | not settled | 0 |' in shown
    assert '| bare, theta0 + 1e-09 rad | 0 | 0 |' in shown
    for part in ('nominal', 'swing', 'robust', 'monitor', 'monitor_nudged'):
        assert (out / part / 'runs.parquet').is_file(), part
