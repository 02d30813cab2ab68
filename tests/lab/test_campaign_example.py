"""The campaign example (`lab.campaign_example`): a short campaign flown, its report's tables
and figures put into a page between its markers, the worst cases' commands left out."""

import os

import yaml

from lab import campaign_example

SPEC = {'runs': 4, 'steps': 60, 'seed': 1,
        'start': {'low': [-0.05, -0.05, -0.99, 0.3], 'high': [0.05, 0.05, -0.9, 0.6]},
        'laws': [{'law': 'linear_lqr', 'label': 'first'},
                 {'law': 'linear_lqr', 'label': 'second', 'set': ['linear_lqr.r=2.0']}]}


def test_the_page_gets_the_report_s_tables_and_figures(tmp_path, monkeypatch):
    spec = tmp_path / 'spec.yaml'
    spec.write_text(yaml.safe_dump(SPEC))
    monkeypatch.setattr(campaign_example, 'SPEC', str(spec))
    page = tmp_path / 'docs' / 'page.md'
    page.parent.mkdir()
    page.write_text('before\n<!-- example:begin -->\nstale table\n<!-- example:end -->\nafter\n')
    out = tmp_path / 'example'
    campaign_example.main(['--out', str(out), '--page', str(page), '--workers', '1'])
    text = page.read_text()
    shown = text.split('<!-- example:begin -->')[1].split('<!-- example:end -->')[0]
    assert text.startswith('before\n') and text.endswith('after\n') and 'stale' not in shown
    assert '**Success per law**' in shown and '| `first` | 4 / 4 |' in shown
    assert '**Paired: the laws on the same cases**' in shown
    assert '| `first` / `second` | 4 |' in shown
    assert 'Worst cases' not in shown and 'replay' not in shown
    for name in campaign_example.FIGURES.values():
        assert f']({name})' in shown
        assert os.path.getsize(page.parent / name) > 0
    assert (out / 'report.md').read_text().count('### `') == 2     # the worst cases stay there
