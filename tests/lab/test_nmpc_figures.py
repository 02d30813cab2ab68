"""lab/bench/nmpc_figures.py, the NMPC page's tables: each suite writes its runs' figures into
the page between the markers named after --out, and a page without them is refused before any
run."""

import importlib.util
import json

import pytest

from conftest import ROOT

PATH = ROOT / 'lab' / 'bench' / 'nmpc_figures.py'


@pytest.fixture(scope='module')
def figures():
    spec = importlib.util.spec_from_file_location('nmpc_figures', PATH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def page_with(tmp_path, *names):
    page = tmp_path / 'nmpc.md'
    page.write_text(''.join(f'<!-- {n}:begin -->\nstale\n<!-- {n}:end -->\n' for n in names))
    return page


def between(text, name):
    return text[text.index(f'<!-- {name}:begin -->'):text.index(f'<!-- {name}:end -->')]


def test_each_suite_writes_its_runs_into_the_page(figures, tmp_path):
    page = page_with(tmp_path, 'nominal', 'swing', 'robust')
    common = ['--law', 'physics_nmpc', '--starts', '5', '--page', str(page)]
    figures.main(['nominal', '--steps', '300', '--out', str(tmp_path / 'nominal.json'), *common])
    figures.main(['swing0.4', '--steps', '300', '--out', str(tmp_path / 'swing.json'), *common])
    figures.main(['robustness', '--steps', '300', '--gains', '1.1',
                  '--out', str(tmp_path / 'robust.json'), *common])
    text = page.read_text()
    assert 'stale' not in text

    run = json.loads((tmp_path / 'nominal.json').read_text())['rows'][0]
    assert run['settle_tau'] is not None   # (-0.2, 0.2, -0.6, 0.2) settles in 2.6 tau
    nominal = between(text, 'nominal')
    assert (f"| (-0.2, 0.2, -0.6, 0.2) | {run['settle_tau']:.2f} / {run['swing']:.3f} / "
            f"**{run['frontier_ratio']:.3f}** / {run['fallbacks']} |") in nominal
    assert f"| physics_nmpc | {run['median_ms']:.2f}..{run['median_ms']:.2f} |" in nominal
    assert 'the law alone (no supervisor), offset-free, 300 steps' in nominal

    swing = json.loads((tmp_path / 'swing.json').read_text())['rows'][0]
    assert swing['swing'] <= 0.405
    assert (f"{swing['settle_tau']:.2f} / {swing['swing']:.3f} / "
            f"**{swing['ratio_to_04_frontier']:.3f}**") in between(text, 'swing')
    assert 'Held: `physics_nmpc` 1 of 1.' in between(text, 'swing')

    rows = json.loads((tmp_path / 'robust.json').read_text())['rows']
    disturbed = rows[1]
    assert disturbed['plant']['actuator_gain'] == 1.1
    robust = between(text, 'robust')
    assert (f"| physics_nmpc | {rows[0]['settle_tau']:.2f} | {disturbed['settle_tau']:.2f} "
            f"({disturbed['ratio_to_nominal']:.2f}) |") in robust
    within = int(disturbed['ratio_to_nominal'] <= 1.2)
    assert f'within 1.2x nominal: `physics_nmpc` {within} of 1.' in robust


def test_a_page_without_the_markers_is_refused_before_any_run(figures, tmp_path, capsys):
    page = page_with(tmp_path, 'other')
    out = tmp_path / 'nominal.json'
    with pytest.raises(SystemExit) as stopped:
        figures.main(['nominal', '--out', str(out), '--page', str(page)])
    assert stopped.value.code == 2 and not out.exists()
    error = capsys.readouterr().err.strip()
    assert error.startswith('nmpc_figures: ') and '<!-- nominal:begin -->' in error
    with pytest.raises(SystemExit):
        figures.main(['nominal', '--page', str(page)])
    assert '--page needs --out' in capsys.readouterr().err
