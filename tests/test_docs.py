"""The documentation's relative links lead to files that exist."""

import re

from conftest import ROOT
import pytest

#: Markdown links and images: [text](target) and ![alt](target), the target up to ')' or space.
LINK = re.compile(r'!?\[[^\]]*\]\(([^)\s]+)\)')
DOCUMENTS = sorted([ROOT / 'README.md', ROOT / 'CHANGELOG.md', *ROOT.glob('docs/**/*.md'),
                    *ROOT.glob('models/**/*.md'), *ROOT.glob('lab/**/*.md')])


def relative_targets(document):
    for target in LINK.findall(document.read_text()):
        if re.match(r'[a-z][a-z0-9+.-]*:', target) or target.startswith('#'):
            continue    # a URL (https:, mailto:) or an anchor in the same page
        yield target.split('#')[0]


@pytest.mark.parametrize('document', DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_leads_to_a_file_in_the_repository(document):
    missing = [t for t in relative_targets(document) if not (document.parent / t).exists()]
    assert not missing, f'{document.relative_to(ROOT)} links to missing {missing}'
    outside = [t for t in relative_targets(document)
               if ROOT not in (document.parent / t).resolve().parents
               and (document.parent / t).resolve() != ROOT]
    assert not outside, f'{document.relative_to(ROOT)} links outside the repository: {outside}'


def test_the_link_pattern_finds_links_and_images():
    text = 'see [a](docs/a.md#x) and ![b](b.png), not [c] (d) nor https://e'
    assert LINK.findall(text) == ['docs/a.md#x', 'b.png']


#: A path on a particular machine (a home, a scratch or work tree, /tmp): a reader's machine
#: has none of them. `$TMPDIR/...` and system paths such as /proc are not matched.
MACHINE_PATH = re.compile(r'(?<![\w$.~/-])/(?:work|tmp|home|Users|root|mnt|scratch)/')


@pytest.mark.parametrize('document', DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_page_names_a_path_on_a_particular_machine(document):
    found = [line.strip() for line in document.read_text().splitlines()
             if MACHINE_PATH.search(line)]
    assert not found, f'{document.relative_to(ROOT)} names machine paths: {found}'


def test_the_machine_path_pattern():
    assert MACHINE_PATH.search('cd /work/nmpc') and MACHINE_PATH.search('(/tmp/x)')
    assert MACHINE_PATH.search('PY=/home/u/.venv/bin/python')
    assert not MACHINE_PATH.search('$TMPDIR/tsr-dds-domains/1.lock, /proc/net/udp')
    assert not MACHINE_PATH.search('lab/results/work/x and docs/tmp/y')


#: A figure in prose: 1.03, 48, 2.95x (a range's two ends are two figures; not the digits of
#: a name such as seed1 or 0.8a).
FIGURE = re.compile(r'(?<![A-Za-z_\d])(?<!\d\.)\d+(?:\.\d+)?(?!\.?\d)(?![A-Za-wyz_])')


def results_rows():
    """(question, answer, linked pages) of the README's Results table."""
    text = (ROOT / 'README.md').read_text()
    table = text.split('## Results', 1)[1].split('\n\n')[2]
    for line in table.splitlines()[2:]:
        question, answer, pages = [cell.strip() for cell in line.strip('|').split(' | ')]
        yield question, answer, [ROOT / target for target in LINK.findall(pages)]


def test_the_readme_s_results_table_is_read():
    rows = list(results_rows())
    assert len(rows) >= 5 and all(pages for _, _, pages in rows)
    assert FIGURE.findall('1.03..1.08x, 48 cases, 2.95x, h = 0.01 tau, koopman_lqr 0.8a') == [
        '1.03', '1.08', '48', '2.95', '0.01']


@pytest.mark.parametrize('question, answer, pages', [
    pytest.param(*row, id=row[0]) for row in results_rows()])
def test_every_figure_the_readme_s_results_quote_is_in_a_page_they_link(
        question, answer, pages):
    shown = ' '.join(page.read_text() for page in pages)
    missing = [figure for figure in FIGURE.findall(answer) if figure not in shown]
    assert not missing, f'README, {question!r}: {missing} in none of {[p.name for p in pages]}'


def test_the_frontier_page_s_example_is_the_comparison_s_first_row():
    """frontier.md explains the ratio with the comparison's figures from the paper's start:
    each one it quotes is in comparison.md's table row for that start."""
    text = (ROOT / 'docs' / 'frontier.md').read_text()
    example = ' '.join(text.split('Example from the project', 1)[1].split('[P]', 1)[0].split())
    row = next(line for line in (ROOT / 'docs' / 'comparison.md').read_text().splitlines()
               if line.startswith('| [0.0, 0.0, -0.99, 0.5] |'))
    quoted = FIGURE.findall(example.split('u in [0, 5]):', 1)[1])
    frontier = quoted.pop(2)       # the koopman_mpc frontier: its settle time over its ratio
    assert float(frontier) == pytest.approx(float(quoted[0]) / float(quoted[2]), abs=0.05)
    cells = {value.strip('* ') for cell in row.strip('|').split('|') for value in cell.split('/')}
    assert len(quoted) == 9 and set(quoted) <= cells, (quoted, row)
