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
