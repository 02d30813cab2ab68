"""Bad options are one usage line and exit status 2 before any work starts, for every tool."""

import importlib

import pytest


@pytest.fixture
def text_file(tmp_path):
    path = tmp_path / 'notes.txt'
    path.write_text('my notes\n')
    return path


@pytest.fixture
def bad_yaml(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text('a: [\n')
    return path


@pytest.fixture
def bag_dir(tmp_path):
    path = tmp_path / 'bag'
    path.mkdir()
    (path / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    return path


#: The commands (the product's) and the studies (the lab's) by the names the tests use.
TOOLS = {**{name: f'tsr_koopman_ctrl.commands.{name}'
            for name in ('deploy', 'train', 'retrain', 'bag', 'config')},
         **{name: f'lab.{name}' for name in ('compare', 'robustness', 'mpc_sweep', 'tune',
                                             'frontier')},
         'loop': 'lab.data_loop', 'evaluate': 'lab.prediction'}


def run_tool(tool, argv):
    """(exit status, stderr lines) of the command or study `tool` run with `argv`."""
    module = importlib.import_module(TOOLS[tool])
    try:
        return module.main([str(a) for a in argv])
    except SystemExit as stop:
        return stop.code


@pytest.mark.parametrize('tool, argv, message', [
    ('deploy', ['--steps', '0'], 'argument --steps: 0 must be >= 1'),
    ('deploy', ['--domain', '999'], 'argument --domain: 999 must be <= 232'),
    ('deploy', ['--timeout', 'nan'], "argument --timeout: 'nan' is not a finite number"),
    ('deploy', ['--out', '{text_file}'], 'notes.txt exists and is not a directory'),
    ('deploy', ['--bags', '{text_file}/bags'], 'notes.txt is not a directory'),
    ('deploy', ['--model', 'no_such_model'], 'no_such_model: no such model directory'),
    ('deploy', ['--law', 'linear_lqr', '--model', 'koopman_default'],
     '--model: linear_lqr uses no model'),
    ('deploy', ['--namespace', 'bad!name'], "--namespace '/bad!name': Invalid namespace: "
     "namespace must not contain characters other than alphanumerics, '_', or '/': "
     "'/bad!name'"),
    ('deploy', ['--preset', '{bad_yaml}'], 'bad.yaml: not valid YAML (line 2)'),
    ('deploy', ['--plant', '{bad_yaml}'], 'bad.yaml: not valid YAML (line 2)'),
    ('compare', ['--steps', '0'], 'argument --steps: 0 must be >= 1'),
    ('compare', ['--law', 'linear_lqr', '--presets', '{bad_yaml}'], 'not valid YAML'),
    ('robustness', ['--law', 'pid'], "argument --law: invalid choice: 'pid'"),
    ('mpc_sweep', ['--horizons', '0'], 'argument --horizons: 0 must be >= 1'),
    ('tune', ['--law', 'linear_lqr', '--trials', '0'], 'argument --trials: 0 must be >= 1'),
    ('tune', ['--law', 'linear_lqr', '--swing-max', '-1'], '--swing-max: -1 must be > 0'),
    ('tune', ['--law', 'linear_lqr', '--seed', '-5'], 'argument --seed: -5 must be >= 0'),
    ('train', ['--out', '{text_file}'], 'notes.txt exists and is not a directory'),
    ('train', ['--out', 'm', '--threads', '-1'], 'argument --threads: -1 must be >= 1'),
    ('train', ['--out', 'm', '--seed', '4294967296'], 'must be <= 4.29497e+09'),
    ('train', ['--out', 'm', '--resume'], 'cannot resume: no m/checkpoint.pt'),
    ('train', ['--out', 'm', '--device', 'bogus'], "'bogus' is not a torch device"),
    ('train', ['--out', 'm', '--device', 'meta'], "'meta' is not a torch device"),
    ('train', ['--out', 'm', '--device', 'cuda:64'], 'cuda:64: torch sees'),
    ('retrain', ['--out', 'm', '--learning-rate', 'nan'], "'nan' is not a finite number"),
    ('retrain', ['--out', '{bag_dir}'], 'bag is a bag directory, not a model directory'),
    ('evaluate', ['--sweep-epochs', '0'], 'argument --sweep-epochs: 0 must be >= 1'),
    ('evaluate', ['--model', 'no_such_model', '--out', 'ev'], 'no_such_model: no such model'),
    ('loop', ['--plant', 'actuator_weak', '--rounds', '0'], 'argument --rounds: 0 must be >= 1'),
    ('loop', ['--plant', 'actuator_weak', '--steps', '20'],
     '--steps 20: retraining cuts 30-step windows from the deployments'),
    ('deploy', ['--out', 'x', '--bags', 'x'], '--out and --bags must differ'),
    ('tune', ['--law', 'koopman_mpc', '--fix', 'model=no_such_model'],
     'no_such_model: no such model directory'),
    ('mpc_sweep', ['--horizons', '3', '201'], 'argument --horizons: 201 must be <= 200'),
    ('loop', ['--plant', 'no_such_plant'], "no plant variant 'no_such_plant'"),
    ('loop', ['--plant', 'actuator_weak', '--model', 'no_such_model'], 'no such model'),
])
def test_a_bad_option_is_one_usage_line_and_status_2(tool, argv, message, text_file, bad_yaml,
                                                     bag_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = [a.format(text_file=text_file, bad_yaml=bad_yaml, bag_dir=bag_dir) for a in argv]
    assert run_tool(tool, argv) == 2
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err
    # Nothing written besides the fixtures' files.
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bad.yaml', 'bag', 'notes.txt']
    assert [p.name for p in bag_dir.iterdir()] == ['metadata.yaml']


@pytest.mark.parametrize('tool', ['train', 'retrain'])
def test_a_model_already_in_out_is_not_replaced_without_overwrite(tool, tmp_path, monkeypatch,
                                                                  capsys):
    """A mistyped --out (models/koopman_default) replaced a shipped model without a word."""
    import shutil

    from tsr_koopman_ctrl.model import shipped
    out = tmp_path / 'model'
    shutil.copytree(shipped.resolve('koopman_default'), out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.chdir(tmp_path)
    argv = ['--out', out] + (['--bags', tmp_path] if tool == 'retrain' else [])
    assert run_tool(tool, argv) == 2
    err = capsys.readouterr().err
    assert f'--out {out} already holds a model' in err and '--overwrite' in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_resume_may_continue_a_finished_run_in_out(tmp_path, capsys):
    """--resume continues in --out (a finished run too, with more epochs): not refused as a
    model in the way; here the checkpoint is missing, which is said instead."""
    import shutil

    from tsr_koopman_ctrl.model import shipped
    out = tmp_path / 'model'
    shutil.copytree(shipped.resolve('koopman_default'), out)
    assert run_tool('train', ['--out', out, '--resume']) == 2
    assert f'cannot resume: no {out}/checkpoint.pt' in capsys.readouterr().err


def test_retrain_checks_a_given_anchor_before_reading_bags(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert run_tool('retrain', ['--out', 'm', '--bags', tmp_path / 'no_bags',
                                '--anchor', '7']) == 2
    err = capsys.readouterr().err
    assert 'bad --anchor: anchor_tension must lie in tension_range' in err, err
    assert list(tmp_path.iterdir()) == []


def test_compare_reads_every_preset_before_the_first_run(tmp_path, monkeypatch, capsys):
    """A bad second preset was found after the first preset's runs (minutes at 2000 steps)."""
    monkeypatch.chdir(tmp_path)
    assert run_tool('compare', ['--law', 'linear_lqr', '--presets', 'tuned', 'no_such',
                                '--steps', '50']) == 2
    out, err = capsys.readouterr()
    assert "no settings preset 'no_such'" in err and out == ''     # no run printed


def test_loop_stops_when_a_deployment_is_interrupted(tmp_path, monkeypatch, capsys):
    """Ctrl-C cut one deployment short and the loop went on, keeping the cut-short bag."""
    from tsr_koopman_ctrl import deployment
    runs = []

    def interrupted(self):
        runs.append(self)
        raise deployment.Interrupted(deployment.RunResult(str(tmp_path / 'bag'), None, {}))
    monkeypatch.setattr(deployment.Deployment, 'run', interrupted)
    plant = params(tmp_path, 'actuator_gain: 0.9')   # a plant file: its work directory was
    assert run_tool('loop', ['--plant', plant, '--out', tmp_path / 'loop']) == 130   # the file
    assert len(runs) == 1 and (tmp_path / 'loop' / 'file').is_dir()
    assert 'holds the steps run so far; stopped, the finished rounds stay in' in \
        capsys.readouterr().err


def test_tune_leaves_a_storage_file_that_is_not_a_journal_alone(text_file, capsys):
    assert run_tool('tune', ['--law', 'linear_lqr', '--storage', text_file]) == 2
    assert 'is not an Optuna journal file; nothing was written to it' in capsys.readouterr().err
    assert text_file.read_text() == 'my notes\n'


def test_loop_refuses_to_mix_a_new_run_into_an_earlier_one(tmp_path, capsys):
    (tmp_path / 'actuator_weak').mkdir()
    (tmp_path / 'actuator_weak' / 'report.json').write_text('{}')
    assert run_tool('loop', ['--plant', 'actuator_weak', '--out', tmp_path]) == 2
    assert 'actuator_weak holds an earlier loop' in capsys.readouterr().err


def params(tmp_path, text):
    """A parameter file holding `text` under ros__parameters."""
    path = tmp_path / 'file.yaml'
    path.write_text('/**:\n  ros__parameters:\n    ' + text.replace('\n', '\n    ') + '\n')
    return path


@pytest.mark.parametrize('tool, option, text, message', [
    ('deploy', '--preset', 'koopman_mpc: {horizn: 8}', "koopman_mpc has no setting 'horizn'"),
    ('deploy', '--preset', 'koopman_mpc.horizn: 8', "koopman_mpc has no setting 'horizn'"),
    ('deploy', '--preset', 'koopman_mcp: {horizon: 8}',
     "'koopman_mcp' is not a section a preset can hold here (excitation, fractional_pd,"),
    ('deploy', '--preset', 'controller: linear_lqr', "'controller' is not a section a preset"),
    ('deploy', '--preset', 'koopman_mpc: {horizon: abc}',
     "koopman_mpc.horizon must be an integer, got 'abc'"),
    ('deploy', '--preset', 'linear_lqr: {q: [1, 2, x, 4]}', 'linear_lqr.q must be 4 numbers'),
    ('compare', '--presets', 'koopman_mpc: {horizn: 8}', "koopman_mpc has no setting 'horizn'"),
    ('compare', '--presets', 'observer: {disturbance: none}',
     "'observer' is not a section a preset can hold here (fractional_pd,"),
    ('deploy', '--plant', 'mass: -5.0', 'Scale.mass must be a finite number > 0, got -5.0'),
    ('deploy', '--plant', 'actuator_gain: 200.0', 'actuator_gain must be in [0.001, 100]'),
    ('deploy', '--plant', 'actuator_lag: fast', 'actuator_lag must be a number'),
    ('deploy', '--plant', 'substeps: 0', 'substeps must be in [1, 10000], got 0'),
    ('deploy', '--plant', 'seed: 1.5', 'seed must be an integer, got 1.5'),
    ('deploy', '--plant', 'initial_state: [0.0, 0.0, -0.5, 0.0]',
     'initial_state would be overridden by the deployment (give x0 and steps instead)'),
])
def test_a_bad_preset_or_plant_file_is_one_line_and_status_2(tool, option, text, message,
                                                             tmp_path, monkeypatch, capsys):
    """What would otherwise be ignored, a traceback, or a node failing after the others
    started."""
    path = params(tmp_path, text)
    monkeypatch.chdir(tmp_path)
    assert run_tool(tool, [option, path, '--steps', '10']) == 2
    err = capsys.readouterr().err
    assert f'{path}: {message}' in err and 'Traceback' not in err, err
    assert [p.name for p in tmp_path.iterdir()] == ['file.yaml']


def test_a_preset_may_set_the_observer_and_use_dotted_names_for_deploy(tmp_path):
    from tsr_koopman_ctrl.commands import deploy
    path = params(tmp_path, 'observer: {disturbance: none}\nkoopman_mpc.horizon: 8\n'
                  'koopman_mpc.r: 2')
    args = deploy.parse_args(['--law', 'koopman_mpc', '--preset', str(path),
                              '--set', 'koopman_mpc.r=3'])
    assert args.deployment.settings['observer'] == {'disturbance': 'none'}
    assert args.deployment.settings['koopman_mpc'] == {'horizon': 8, 'r': 3.0}  # --set on top


def test_a_mistyped_model_plant_or_bag_folder_names_what_there_is(tmp_path):
    """The one line for a model or plant that is not there lists the shipped ones; a folder of
    bags given where one bag is expected says which to give."""
    from tsr_koopman_ctrl.bag import BagReader
    from tsr_koopman_ctrl.model import ModelFileError, resolve
    from tsr_sim.plant import plant_file
    with pytest.raises(ModelFileError, match=r'the shipped models are .*koopman_retrieval'):
        resolve('koopman_defualt')
    with pytest.raises(ValueError, match=r'the variants are .*actuator_weak'):
        plant_file('actuator_wek')
    (tmp_path / 'bags' / 'run_1').mkdir(parents=True)
    (tmp_path / 'bags' / 'run_1' / 'run_1_0.mcap').write_bytes(b'')
    with pytest.raises(FileNotFoundError, match=r'a folder of bags: give one, e\.g\. .*run_1'):
        BagReader(str(tmp_path / 'bags'))
