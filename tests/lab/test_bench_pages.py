"""lab/bench/: a benchmark writes what it printed to --out and into its page between the
markers named after --out, with the date, the machine and the command; a page without them is
refused before any work."""

import subprocess
import sys

from conftest import ROOT

SAMPLING = ROOT / 'lab' / 'bench' / 'bench_sampling.py'


def run(*arguments, cwd):
    return subprocess.run([sys.executable, str(SAMPLING), '--trajectories', '200',
                           '--reference-trajectories', '3', *map(str, arguments)],
                          capture_output=True, text=True, timeout=120, cwd=cwd)


def test_a_benchmark_writes_what_it_printed_into_its_page(tmp_path):
    page = tmp_path / 'bench.md'
    page.write_text('before\n<!-- bench_sampling:begin -->\nold\n<!-- bench_sampling:end -->\n'
                    'after\n')
    out = tmp_path / 'results' / 'bench_sampling.txt'
    done = run('--out', out, '--page', page, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    printed = out.read_text()
    assert printed.strip() == done.stdout.strip()
    assert 'ratio batch / solve_ivp loop' in printed and '200 x 30 steps' in printed
    text = page.read_text()
    block = text[text.index(':begin -->'):text.index('<!-- bench_sampling:end')]
    assert 'old' not in block and printed in block
    assert 'cores' in block and 'bench_sampling.py --trajectories 200' in block
    assert text.startswith('before\n') and text.endswith('after\n')


def test_a_page_without_the_markers_is_refused_before_any_work(tmp_path):
    page = tmp_path / 'bench.md'
    page.write_text('no markers\n')
    out = tmp_path / 'bench_sampling.txt'
    done = run('--out', out, '--page', page, cwd=tmp_path)
    assert done.returncode == 2 and 'no <!-- bench_sampling:begin -->' in done.stderr
    assert done.stdout == '' and not out.exists()
    done = run('--page', page, cwd=tmp_path)
    assert done.returncode == 2 and '--page needs --out' in done.stderr
