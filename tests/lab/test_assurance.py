"""The monitor part's table counts runs against the bare law's from the same start."""

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
