"""lab/manifest.yaml, the list of published results: each entry's docs page exists and shows its
command, and the command's arguments parse with the study's own parser. Nothing is run."""

import argparse
import importlib
import importlib.util
import os
import re
import shlex

import pytest
import yaml

from conftest import ROOT

MANIFEST = ROOT / 'lab' / 'manifest.yaml'
ENTRIES = yaml.safe_load(MANIFEST.read_text())['results']
RESULTS = 'lab/results/'
STUDIES = ('compare', 'tune', 'robustness', 'frontier', 'prediction', 'data_loop', 'mpc_sweep',
           'main_job')


def words(command):
    """The command's words, leading environment assignments (OMP_NUM_THREADS=1) dropped."""
    argv = shlex.split(command)
    while argv and re.match(r'[A-Za-z_][A-Za-z0-9_]*=', argv[0]):
        argv.pop(0)
    return argv


def study_arguments(entry):
    """The arguments the command gives its study: `python -m lab.<study> ...` or
    `python lab/bench/<name>.py ...`."""
    argv = words(entry['command'])
    if entry['study'].startswith('lab.'):
        assert argv[:3] == ['python', '-m', entry['study']], entry['name']
        return argv[3:]
    assert argv[:2] == ['python', entry['study']], entry['name']
    return argv[2:]


def one_line(text):
    """Markdown or a shell block as one line: continuation backslashes and runs of white space
    become one space."""
    return ' '.join(text.replace('\\\n', ' ').split())


class Parsed(Exception):
    """Raised by the patched parse_args once a benchmark's own parser has parsed its argv."""

    def __init__(self, namespace):
        super().__init__('parsed')
        self.namespace = namespace


def parsed(entry, monkeypatch):
    """The study's own parser applied to the command's arguments: the Namespace, or a test
    failure carrying argparse's message."""
    arguments = study_arguments(entry)
    try:
        if entry['study'].startswith('lab.'):
            return importlib.import_module(entry['study']).parser().parse_args(arguments)
        # A benchmark builds its parser in main() and parses sys.argv: run main() up to the
        # parse and stop there.
        path = ROOT / entry['study']
        spec = importlib.util.spec_from_file_location(f'bench_{path.stem}', path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        original = argparse.ArgumentParser.parse_args

        def parse_and_stop(self, args=None, namespace=None):
            raise Parsed(original(self, args, namespace))

        # Patched for this parse only: the next entry parses with argparse as it is.
        with monkeypatch.context() as patch:
            patch.setattr(argparse.ArgumentParser, 'parse_args', parse_and_stop)
            patch.setattr('sys.argv', [str(path), *arguments])
            with pytest.raises(Parsed) as stopped:
                module.main()
        return stopped.value.namespace
    except SystemExit as error:
        pytest.fail(f"{entry['name']}: {entry['command']!r} does not parse (exit {error.code})")


def test_the_manifest_s_entries_are_complete_and_named_once():
    names = [entry['name'] for entry in ENTRIES]
    assert len(names) == len(set(names)), 'a name is used twice'
    for entry in ENTRIES:
        missing = {'name', 'study', 'page', 'command', 'output', 'took'} - set(entry)
        assert not missing, (entry.get('name'), missing)
        assert entry['output'].startswith(RESULTS), entry['name']
        assert str(entry['took']).strip(), entry['name']


def test_every_study_and_benchmark_has_a_published_result():
    studies = {entry['study'] for entry in ENTRIES}
    assert {f'lab.{name}' for name in STUDIES} <= studies
    benchmarks = {f'lab/bench/{path.name}'
                  for path in (ROOT / 'lab' / 'bench').glob('bench_*.py')}
    assert benchmarks <= studies, benchmarks - studies


def test_the_results_folder_is_ignored_by_git():
    assert '/lab/results/' in (ROOT / '.gitignore').read_text().splitlines()


@pytest.mark.parametrize('entry', ENTRIES, ids=lambda entry: entry['name'])
def test_the_docs_page_shows_the_command(entry):
    page = ROOT / entry['page']
    assert page.is_file(), f"{entry['name']}: no page {entry['page']}"
    shown = re.compile(re.escape(one_line(entry['command'])) + r'(\s|$)')    # whole words
    assert shown.search(one_line(page.read_text())), (
        f"{entry['page']} does not show {entry['command']!r}")


@pytest.mark.parametrize('entry', ENTRIES, ids=lambda entry: entry['name'])
def test_the_command_parses_and_writes_its_output_where_the_manifest_says(entry, monkeypatch):
    monkeypatch.chdir(ROOT)      # the output checks resolve --out from the repository root
    args = parsed(entry, monkeypatch)
    output = entry['output']
    if entry['study'] == 'lab.tune':
        from lab.tuning.spec import StudySpec
        spec = StudySpec(args.law, tuple(args.fix), tuple(args.also), args.objective,
                         args.penalty, args.starts, args.swing_max, args.steps, args.study)
        assert output == f'{args.out}/{spec.study_name}.md'
    elif entry['study'] == 'lab.data_loop':
        assert output == f'{args.out}/{args.plant}/report.md'
    elif entry['study'] == 'lab.frontier':
        assert output == args.out      # the table file itself; --show prints it as markdown
    elif entry['study'].startswith('lab.'):
        assert os.path.dirname(output) == args.out, (output, args.out)
    else:
        assert output.startswith(RESULTS + 'bench/') and output == args.out, (output, args.out)


def page_option(entry, monkeypatch):
    """The page a command writes its tables into (its --page), or None for a study without
    the option or a command that does not give one."""
    return getattr(parsed(entry, monkeypatch), 'page', None) or None


def markers(entry, args):
    """The markers a command writes between: named after its --out folder (a study) or its
    --out file's name without the suffix (a benchmark)."""
    from lab.bench.printed import marker
    from lab.report import marker_name
    if not entry['study'].startswith('lab.'):
        return marker(args.out)
    study = importlib.import_module(entry['study'])
    return study.markers(args) if hasattr(study, 'markers') else marker_name(args.out)


@pytest.mark.parametrize('entry', ENTRIES, ids=lambda entry: entry['name'])
def test_a_study_that_can_write_its_page_does_and_the_page_has_its_markers(entry, monkeypatch):
    """A page generated by its study: the manifest's command gives --page (the entry's page),
    and the page has one pair of markers named after --out, which the study writes between."""
    monkeypatch.chdir(ROOT)
    if not page_option(entry, monkeypatch):
        pytest.skip('the study does not write this page')
    args = parsed(entry, monkeypatch)
    assert args.page == entry['page'], (
        f"{entry['name']}: the command writes into {args.page!r}, the manifest says "
        f"{entry['page']}")
    from lab.report import check_page
    check_page(args.page, markers(entry, args))


def test_the_pages_generated_by_their_studies(monkeypatch):
    """Which results are written into their pages by the study itself (the rest show the
    date and the law they were made with)."""
    monkeypatch.chdir(ROOT)
    generated = {entry['name'] for entry in ENTRIES if page_option(entry, monkeypatch)}
    assert generated == {'main_job', 'comparison', 'comparison_swing0.4', 'robustness',
                         'assurance', 'assurance_monitor', 'fallback_region', 'timed_rehearsal',
                         'timed_rehearsal_swing0.4',
                         'prediction', 'prediction_main_job', 'prediction_momentum',
                         'nmpc_nominal', 'nmpc_swing0.4', 'nmpc_robustness',
                         'data_loop_actuator_weak', 'data_loop_actuator_strong',
                         'data_loop_heavy_robot', 'data_loop_eccentric_orbit', 'bench_recorder',
                         'bench_lockstep', 'bench_compute', 'bench_compute_offset_free',
                         'bench_qp', 'bench_nmpc', 'bench_sampling', 'bench_training',
                         'bench_inference', 'bench_campaign', 'safety_campaign',
                         'campaign_example'}
