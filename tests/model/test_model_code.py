"""Model files that would run code when read are refused, unread, in one line: by the model
reader, by the laws that load a model, and by the controller node's configure."""

import json
import pathlib
import pickle
import shutil

import pytest

from tsr_koopman_ctrl.model import LiftedModel
from tsr_koopman_ctrl.model.model_file import ModelFileError

from conftest import SHIPPED_MODEL


class Payload:
    """Unpickling this touches `marker`: the code a pickle runs when it is read."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (pathlib.Path(self.marker),)


def poisoned(tmp_path, how):
    """A copy of the shipped model made to run code if it were read as `how` says."""
    model = tmp_path / how
    shutil.copytree(SHIPPED_MODEL, model)
    marker = tmp_path / f'{how}.ran'
    weights = model / 'weights.safetensors'
    if how == 'torch_pt_beside_no_weights':
        torch = pytest.importorskip('torch')
        weights.unlink()
        torch.save(Payload(str(marker)), model / 'model.pt')
    elif how == 'pickle_as_weights':
        weights.write_bytes(pickle.dumps(Payload(str(marker)), protocol=4))
    elif how == 'torch_save_as_weights':
        torch = pytest.importorskip('torch')
        torch.save(Payload(str(marker)), weights)
    else:                                   # model.json names other weights, or a loader
        (model / 'model.pkl').write_bytes(pickle.dumps(Payload(str(marker))))
        meta = json.loads((model / 'model.json').read_text())
        meta.update({'json_names_weights': {'weights': 'model.pkl'},
                     'json_names_loader': {'loader': 'pickle:load'}}[how])
        (model / 'model.json').write_text(json.dumps(meta))
    return model, marker


CASES = {'torch_pt_beside_no_weights': 'model.pt: a pickle runs code when read',
         'pickle_as_weights': 'a pickle (torch.save or pickle), not safetensors: refused unread',
         'torch_save_as_weights': 'a pickle (torch.save or pickle), not safetensors',
         'json_names_weights': "'weights' names 'model.pkl': a model loads its weights from "
                               'weights.safetensors only and runs no code; refused',
         'json_names_loader': "'loader' names 'pickle:load'"}


@pytest.mark.parametrize('how', sorted(CASES))
def test_a_model_that_would_run_code_is_refused_unread_in_one_line(tmp_path, how):
    model, marker = poisoned(tmp_path, how)
    with pytest.raises(ModelFileError) as refused:
        LiftedModel.load(str(model))
    message = str(refused.value)
    assert CASES[how] in message and '\n' not in message and str(model) in message
    assert not marker.exists()


def test_the_laws_with_a_model_refuse_it_too(tmp_path):
    from tsr_koopman_ctrl.control import make_controller
    model, marker = poisoned(tmp_path, 'pickle_as_weights')
    for law in ('koopman_nmpc', 'koopman_mpc', 'koopman_lqr'):
        with pytest.raises(ModelFileError, match='refused unread'):
            make_controller(law, model=str(model))
    assert not marker.exists()


@pytest.mark.ros
def test_the_controller_node_refuses_it_at_configure_in_one_line(start_node, tmp_path):
    model, marker = poisoned(tmp_path, 'torch_save_as_weights')
    process = start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
                         {'law': 'koopman_nmpc', 'koopman_nmpc': {'model': str(model)}})
    assert process.wait(timeout=60) == 2
    log = (tmp_path / 'tsr_controller.log').read_text()
    assert log.count('cannot start:') == 1 and 'refused unread' in log
    assert 'Traceback' not in log and not marker.exists()
